"""A level-of-detail set for streaming viewers, in PlayCanvas's layout: ``lod-meta.json`` beside
one unbundled SOG per level (``<level>_0/meta.json``), level 0 the finest.

``lod-meta.json`` (version 1): ``count`` (splats over all levels), ``counts`` (per level),
``lodLevels``, ``lodErrors`` (false: no per-node error tables), ``filenames`` (the levels' SOG
``meta.json`` paths) and ``tree``: one root node with the scene's ``bound`` (min/max corners of the
splats' centres +- their largest scale) and ``lods``: level -> ``{file, offset: 0, count}``. A
viewer streams the set by picking a level per node; here the whole scene is one node, so it picks
one level for the whole scene.
"""

from __future__ import annotations

import json

import numpy as np

from ..errors import InputError
from . import sog

META_LIMIT = 16 << 20


def encode(levels: list[dict[str, np.ndarray]], generator: str) -> dict[str, bytes]:
    """Relative path -> bytes of every file of the set (``lod-meta.json`` last); ``levels`` are
    host arrays, finest first."""
    files: dict[str, bytes] = {}
    filenames = []
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i, host in enumerate(levels):
        folder = f"{i}_0"
        for name, data in sog.encode(host, generator).items():
            files[f"{folder}/{name}"] = data
        filenames.append(f"{folder}/meta.json")
        reach = np.exp(host["log_scales"].astype(np.float64).max(axis=1))[:, None]
        lo = np.minimum(lo, (host["means"] - reach).min(axis=0))
        hi = np.maximum(hi, (host["means"] + reach).max(axis=0))
    counts = [int(h["means"].shape[0]) for h in levels]
    meta = {
        "version": 1,
        "asset": {"generator": generator},
        "count": sum(counts),
        "counts": counts,
        "lodLevels": len(levels),
        "lodErrors": False,
        "filenames": filenames,
        "tree": {
            "bound": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
            "lods": {str(i): {"file": i, "offset": 0, "count": c} for i, c in enumerate(counts)},
        },
    }
    files["lod-meta.json"] = json.dumps(meta, separators=(",", ":")).encode("ascii")
    return files


def level_metas(path, data: bytes) -> list:
    """The paths of every level's SOG ``meta.json`` that a ``lod-meta.json`` names inside its folder
    (the others are left out), each once; an empty list where it is not a readable version-1 set."""
    try:
        meta = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError):  # not UTF-8, not JSON, an integer too long to read
        return []
    files = meta.get("filenames") if isinstance(meta, dict) and meta.get("version", 1) == 1 else None
    if not isinstance(files, list):
        return []
    return [path.parent / f for f in dict.fromkeys(f for f in files if isinstance(f, str) and f and _inside(f))]


def _inside(relative: str) -> bool:
    return not relative.startswith(("/", "\\")) and "\0" not in relative and ".." not in relative.replace("\\", "/").split("/")


def finest_level_meta(path, data: bytes):
    """The path of the finest level's SOG ``meta.json`` named by a ``lod-meta.json``."""
    name = path.name
    try:
        meta = json.loads(data.decode("utf-8"))
    except RecursionError:
        raise InputError(f"{name}: nested too deeply to read") from None
    except ValueError:  # not UTF-8, not JSON, an integer too long to read
        raise InputError(f"{name}: not valid JSON") from None
    if not isinstance(meta, dict) or meta.get("version", 1) != 1:
        raise InputError(f"{name}: not a version-1 lod-meta.json")
    files = meta.get("filenames")
    tree = meta.get("tree")
    if not (isinstance(files, list) and files and all(isinstance(f, str) for f in files) and isinstance(tree, dict)):
        raise InputError(f"{name}: lod-meta.json needs 'filenames' and 'tree'")
    node = tree
    while isinstance(node, dict) and "lods" not in node and isinstance(node.get("children"), list) and node["children"]:
        node = node["children"][0]
    lods = node.get("lods") if isinstance(node, dict) else None
    ref = lods.get("0") if isinstance(lods, dict) else None
    index = ref.get("file") if isinstance(ref, dict) else None
    if not (isinstance(index, int) and not isinstance(index, bool) and 0 <= index < len(files)):
        raise InputError(f"{name}: lod-meta.json has no level-0 file reference")
    relative = files[index]
    if not _inside(relative):
        raise InputError(f"{name}: lod-meta.json names {relative!r} outside its folder")
    return path.parent / relative
