"""Splat files in the formats people ship: reading detects the format by content (the extension
is a hint), writing picks it by ``format`` or by the output's name.

Formats: ``ply`` (INRIA 3DGS PLY, :mod:`nanogs_warp.io.ply`), ``compressed-ply`` (PlayCanvas),
``spz`` (Niantic, versions 2 and 3), ``sog`` (PlayCanvas; bundled ``.sog`` zip or unbundled
``meta.json``), ``splat`` (antimatter15) and ``lod`` (a PlayCanvas ``lod-meta.json`` set of SOG
levels). What each keeps and loses: docs/formats.md.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from . import compressed_ply, lod, sog, spz, splat
from .common import check_decoded_memory, dropped_parts, plain_layout, read_file_bytes, top_level_keys
from .open_file import open_regular
from .ply import PlyArrays, checked_rows, normalize_quaternions, read_ply_arrays, read_splats, refuse_empty, save_ply, splats_from_host
from .ply_header import MAX_HEADER_BYTES
from .ply_layout import PlyLayout
from .ply_write import OutputSet, atomic_write

if TYPE_CHECKING:
    from ..splats import SplatSet

FORMATS = ("ply", "compressed-ply", "spz", "sog", "splat", "lod")
GENERATOR = "nanogs-warp"
_MAX_SH = {"compressed-ply": 3, "spz": 3, "sog": 3, "lod": 3, "splat": 0}
_TITLE = {"ply": "PLY", "compressed-ply": "compressed PLY", "spz": "SPZ", "sog": "SOG", "splat": ".splat",
          "lod": "SOG LOD set"}  # fmt: skip
_READABLE = "INRIA or compressed PLY, SPZ v2/v3, SOG (.sog or meta.json), lod-meta.json or .splat"


def format_for_path(path, format: str | None = None) -> str:
    """The output format: ``format`` when given, else by the name (``.compressed.ply``, ``.spz``,
    ``.sog``, ``.splat``, ``lod-meta.json``, other ``.json``: unbundled SOG), else PLY."""
    if format is not None:
        if format not in FORMATS:
            raise InputError(f"--format {format!r}: expected one of {', '.join(FORMATS)}")
        return format
    name = Path(path).name.lower()
    if name == "lod-meta.json":
        return "lod"
    for suffix, fmt in ((".compressed.ply", "compressed-ply"), (".spz", "spz"), (".sog", "sog"),
                        (".splat", "splat"), (".json", "sog")):  # fmt: skip
        if name.endswith(suffix):
            return fmt
    return "ply"


# How much of a JSON file is scanned for its top-level keys (``detect_format``): a scan in Python, byte
# by byte; a lod-meta.json or meta.json names its kind in its first keys.
JSON_HEAD_BYTES = 1 << 16


def detect_format(path) -> str:
    """The format of an existing file (or SOG/LOD folder), by content; the extension decides only
    when the content has no signature (.splat has none)."""
    path = Path(path)
    name = path.name or str(path)  # "." (an empty argument reads as it) or "/" has no name of its own
    if path.is_dir():
        for inner, fmt in (("lod-meta.json", "lod"), ("meta.json", "sog")):
            if (path / inner).is_file():
                return fmt
        raise InputError(f"{name}: is a directory without meta.json or lod-meta.json")
    try:
        with open_regular(path) as f:
            head = f.read(MAX_HEADER_BYTES)  # as much as a PLY header may hold: a long one's elements are past 64 KiB
            size = f.seek(0, 2)
    except OSError as e:
        raise InputError(f"{name}: cannot read the file: {e.strerror or e}") from e
    if size == 0:
        raise InputError(f"{name}: the file is empty")
    if head.startswith(b"ply"):
        return "compressed-ply" if compressed_ply.looks_compressed(head) else "ply"
    if spz.looks_like_spz(head):
        return "spz"
    if sog.looks_bundled(head):
        return "sog"
    if head.lstrip()[:1] == b"{":
        keys = top_level_keys(head[: JSON_HEAD_BYTES])
        if "lodLevels" in keys:
            return "lod"
        if {"means", "quats"} <= keys:
            return "sog"
    hinted = format_for_path(path)
    if name.lower().endswith(".ply") or hinted in ("spz", "sog", "lod", "splat") or name.lower().endswith(".json"):
        return hinted  # that reader says what is wrong with the file
    raise InputError(f"{name}: not a splat file this tool reads ({_READABLE}; .splat files are known by their extension)")


def check_output_name(path: Path, fmt: str) -> None:
    """Refuses to write a file that no reader would recognise again: a .splat file has no signature,
    so only a name ending in .splat tells what it is."""
    if fmt == "splat" and not path.name.lower().endswith(".splat"):
        raise InputError(f"{path.name}: a .splat file needs a name ending in .splat (it has no signature: readers "
                         "know it by its extension)")  # fmt: skip


def read_splat_arrays(path) -> PlyArrays:
    """A splat file's host arrays (before value checks), its layout, format and size in bytes."""
    with np.errstate(all="ignore"):  # malformed values are found by the checks, not as warnings
        return _read_splat_arrays(Path(path))


def _read_splat_arrays(path: Path) -> PlyArrays:
    fmt = detect_format(path)
    if fmt == "ply":
        return read_ply_arrays(path)
    if fmt == "lod":
        meta_path = path / "lod-meta.json" if path.is_dir() else path
        inner = lod.finest_level_meta(meta_path, read_file_bytes(meta_path, lod.META_LIMIT))
        try:
            arrays = sog.read_unbundled(inner)
        except InputError as e:  # named from the set: "meta.json: no such file" said not which
            raise InputError(f"{meta_path.name}: its finest level {inner.relative_to(meta_path.parent)}: {e}") from None
        label, size = "SOG LOD set, level 0", meta_path.stat().st_size
    elif fmt == "sog" and (path.is_dir() or not sog.looks_bundled(_head(path))):
        arrays = sog.read_unbundled(path)
        label, size = "SOG (meta.json)", (path / "meta.json" if path.is_dir() else path).stat().st_size
    elif fmt == "sog":
        arrays, label, size = sog.read_bundled(path), "SOG (.sog)", path.stat().st_size
    else:
        if fmt == "splat":  # 32 bytes a splat, decoded to 17 values
            check_decoded_memory(path.name, path.stat().st_size // 32, 3)
        data = read_file_bytes(path)
        module = {"spz": spz, "compressed-ply": compressed_ply, "splat": splat}[fmt]
        arrays, label, size = module.read_arrays(path, data), _TITLE[fmt], len(data)
    return PlyArrays(arrays, plain_layout(arrays["features"].shape[1] - 3), label, size)


def load_splats(path, device="cpu", drop_invalid: bool = False, on_drop=None) -> SplatSet:
    """Reads a splat file of any supported format into a :class:`SplatSet` on ``device``.

    Values are checked as :func:`nanogs_warp.io.ply.load_ply` checks them (``drop_invalid`` and
    ``on_drop`` likewise). Scenes from non-PLY files get the plain INRIA layout.
    """
    from ..splats import warp_device

    device = warp_device(device)  # a device this machine lacks: said before the file is read
    arrays, layout = read_any_splats(path, drop_invalid, on_drop)
    return splats_from_host(arrays, layout, device)


def read_any_splats(path, drop_invalid: bool = False, on_drop=None, upload=None) -> tuple[dict[str, np.ndarray], PlyLayout]:
    """load_splats' part on the host, without Warp: the checked host arrays (quaternions
    normalised) and the layout; :func:`nanogs_warp.io.ply.splats_from_host` makes them a SplatSet.
    ``upload`` (a :class:`~nanogs_warp.io.row_upload.RowUpload`) is handed a binary PLY's rows as
    they are read."""
    path = Path(path)
    if detect_format(path) == "ply":
        return read_splats(path, drop_invalid=drop_invalid, on_drop=on_drop, upload=upload)
    data = read_splat_arrays(path)
    a = checked_rows(data.arrays, path.name, drop_invalid, on_drop)
    a["rotations"] = normalize_quaternions(a["rotations"])
    return a, data.layout


def save_splats(
    splats: SplatSet, path, format: str | None = None, on_loss=None, overwrite: bool = True, outputs: OutputSet | None = None
) -> None:
    """Writes ``splats`` in ``format`` (by default: by the name, :func:`format_for_path`), each
    file atomically. ``on_loss``, if given, is called with one line naming what the format could
    not hold (SH bands, extra properties, PLY elements), when anything. Without ``overwrite`` a
    file already there is an InputError and stays as it is. With ``outputs`` (an ``OutputSet``) the
    files are staged there, to appear together with the set's others when it is published."""
    save_levels([splats], path, format, on_loss, overwrite, outputs)


def save_levels(
    levels: list[SplatSet], path, format: str | None = None, on_loss=None, overwrite: bool = True, outputs: OutputSet | None = None
) -> None:
    """Writes one scene (``levels`` of one) or, for the ``lod`` format, a level-of-detail set of
    several, finest first. Files of one call (an unbundled SOG's images, a set's levels) appear
    together or not at all; with ``outputs`` they are staged there instead (``save_splats``)."""
    path = Path(path)
    fmt = format_for_path(path, format)
    check_output_name(path, fmt)
    from ..splats import SplatSet  # a SplatSet exists: Warp is loaded already

    levels = list(levels)
    if not levels:
        raise InputError(f"{path.name}: no levels to write")
    for level in levels:
        if not isinstance(level, SplatSet):
            raise TypeError(f"each level must be a SplatSet, got {type(level).__name__}")
        refuse_empty(level, path)
    if fmt != "lod" and len(levels) != 1:
        raise ValueError("several levels need the lod format")
    counts = [level.count for level in levels]
    if any(a < b for a, b in zip(counts, counts[1:])):
        raise InputError(f"{path.name}: levels go finest first (counts that never grow), got counts {counts}")
    staged = OutputSet(overwrite) if outputs is None else outputs
    try:
        if fmt == "ply":
            save_ply(levels[0], path, overwrite=overwrite, outputs=staged)
        else:
            with np.errstate(all="ignore"):  # out-of-range values clip, by design
                _write_levels([s.to_numpy() for s in levels], levels, path, fmt, on_loss, overwrite, staged)
        if outputs is None:
            staged.publish()
    except BaseException:
        if outputs is None:
            staged.discard()
        raise


def _write_levels(hosts, levels, path: Path, fmt: str, on_loss, overwrite: bool, outputs: OutputSet) -> None:
    def _write(path: Path, data: bytes) -> None:
        atomic_write(path, lambda stream: stream.write(data), overwrite, outputs)

    lost, changed = [], []  # parts the format drops; values it holds only clamped or rounded
    for s, host in zip(levels, hosts):
        lost += [p for p in dropped_parts(host, s.layout, _MAX_SH[fmt]) if p not in lost]
    if fmt == "splat":
        _write(path, splat.encode(hosts[0]))
        changed += splat.notes(hosts[0])
    elif fmt == "compressed-ply":
        _write(path, compressed_ply.encode(hosts[0], f"Generated by {GENERATOR}"))
        changed += compressed_ply.notes(hosts[0])
    elif fmt == "spz":
        data, notes = spz.encode(hosts[0])
        changed += notes
        _write(path, data)
    elif fmt == "sog" and path.suffix.lower() == ".json":
        files = sog.encode(hosts[0], GENERATOR)
        if overwrite:  # images of the SOG already there that this one does not write (its SH palette)
            written = {os.path.realpath(path.with_name(name)) for name in files}
            outputs.retire([m for m in sog.member_files(path)[1:]
                            if m.suffix == ".webp" and m.is_file() and os.path.realpath(m) not in written])  # fmt: skip
        for name, data in files.items():  # meta.json last: the images are in place when it appears
            _write(path if name == "meta.json" else path.with_name(name), data)
    elif fmt == "sog":
        _write(path, sog.bundle(sog.encode(hosts[0], GENERATOR)))
    else:
        folder = path.parent if path.name.lower() == "lod-meta.json" else path
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{folder.name}: exists and is not a directory")
        files = {folder / relative: data for relative, data in lod.encode(hosts, GENERATOR).items()}
        if overwrite:
            outputs.retire(_stale_level_files(folder, files))
        for target, data in files.items():
            outputs.make_folder(target.parent)
            _write(target, data)
    if lost and on_loss is not None:
        on_loss(f"{path.name}: {_TITLE[fmt]} cannot hold {'; '.join(lost)}: dropped")
    if changed and on_loss is not None:
        on_loss(f"{path.name}: {_TITLE[fmt]} cannot hold all values exactly: {'; '.join(changed)}")


def _stale_level_files(folder: Path, files) -> list[Path]:
    """The files of the level-of-detail set already in ``folder`` (its ``lod-meta.json``'s levels:
    each SOG's meta.json and the .webp images it names) that a new set of ``files`` does not write:
    the levels an older set had beyond the new one's. Paths are compared as they resolve (a level
    folder may be a link to another); only files inside ``folder`` are named, each once; none where
    there is no readable set."""
    meta_path = folder / "lod-meta.json"
    try:
        metas = lod.level_metas(meta_path, read_file_bytes(meta_path, lod.META_LIMIT))
    except InputError:  # no set there (or not one that can be read): nothing to retire
        return []
    root = os.path.realpath(folder) + os.sep
    written = {os.path.realpath(p) for p in files}
    stale: dict[str, None] = {}  # real paths, in order, each once
    for meta in dict.fromkeys(os.path.realpath(m) for m in metas):
        if not (meta.startswith(root) and os.path.isfile(meta)):
            continue
        for member in dict.fromkeys(sog.member_files(Path(meta))):
            real = os.path.realpath(member)
            if (member.name == "meta.json" or member.suffix == ".webp") and real.startswith(root) and real not in written \
                    and real not in stale and os.path.isfile(real):  # fmt: skip
                stale[real] = None
    return [Path(real) for real in stale]


def output_files(path, format: str | None = None, levels: int = 1) -> list[Path]:
    """Every file that saving ``levels`` levels to ``path`` in ``format`` (by default: by the name)
    may write: the file itself, or an unbundled SOG's meta.json and images, or a level-of-detail
    set's lod-meta.json and each level's SOG."""
    path = Path(path)
    fmt = format_for_path(path, format)
    if fmt == "sog" and path.suffix.lower() == ".json":
        return [path, *(path.with_name(name) for name in sog.IMAGE_FILES)]
    if fmt == "lod":
        folder = path.parent if path.name.lower() == "lod-meta.json" else path
        members = ("meta.json", *sog.IMAGE_FILES)
        return [folder / "lod-meta.json", *(folder / f"{i}_0" / name for i in range(levels) for name in members)]
    return [path]


def input_files(path) -> list[Path]:
    """The files a scene at ``path`` is read from, as far as they can be told before reading it: the
    file itself, or an unbundled SOG's meta.json and images, or a level-of-detail set's lod-meta.json
    and its finest level's SOG."""
    path = Path(path)
    try:
        fmt = detect_format(path)
    except InputError:
        return [path]
    if fmt == "sog" and (path.is_dir() or not sog.looks_bundled(_head(path))):
        return sog.member_files(path)
    if fmt == "lod":
        meta_path = path / "lod-meta.json" if path.is_dir() else path
        try:
            return [meta_path, *sog.member_files(lod.finest_level_meta(meta_path, read_file_bytes(meta_path, lod.META_LIMIT)))]
        except InputError:
            return [meta_path]
    return [path]


def _head(path: Path) -> bytes:
    with open_regular(path) as f:
        return f.read(4)


__all__ = ["FORMATS", "detect_format", "format_for_path", "input_files", "load_splats", "output_files",
           "read_splat_arrays", "save_levels", "save_splats"]  # fmt: skip
