"""PlayCanvas SOG (version 2): ``meta.json`` and lossless WebP images, one pixel per splat.

Images (row-major, width a multiple of 4, rows in Morton order): ``means_l``/``means_u`` (low and
high bytes of 16-bit x y z, each sign(v) ln(|v| + 1) quantised between ``means.mins``/``maxs``),
``quats`` (three smaller components (q sqrt2 / 2 + 0.5) 255 and 252 + the largest component's
index, components in PLY order w x y z), ``scales`` (indices into a 256-entry codebook of log
scales), ``sh0`` (indices into a 256-entry codebook of f_dc, alpha = 255 sigmoid(opacity)) and,
for SH degree 1-3, ``shN_centroids`` (a palette: 64 entries per row, each entry's coefficients as
codebook indices) and ``shN_labels`` (16-bit palette index per splat). Scenes of up to 65,536
splats get one palette entry per splat; larger ones a k-means palette of 65,536 entries.
Bundled ``.sog``: the same files in a zip archive; unbundled: ``meta.json`` with the images beside.
"""

from __future__ import annotations

import io
import json
import math
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from .codebook import kmeans_1d, kmeans_rows
from .common import (
    SQRT1_2,
    byte_to_opacity_logit,
    check_decoded_memory,
    from_smallest_three,
    host_arrays,
    morton_order,
    opacity_to_byte,
    smallest_three,
)
from .open_file import open_regular

MAX_SH_DEGREE = 3
PALETTE_LIMIT = 65536
META_LIMIT = 64 << 20  # bytes of meta.json read at most
IMAGE_BYTES_PER_PIXEL = 8  # an image read at most: twice a lossless WebP of incompressible RGBA, plus 1 MiB
_REST = {0: 0, 1: 3, 2: 8, 3: 15}
# The images ``encode`` writes beside meta.json (the last two only for SH bands beyond the DC term).
IMAGE_FILES = ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_centroids.webp", "shN_labels.webp")


def looks_bundled(head: bytes) -> bool:
    return head[:4] == b"PK\x03\x04"


# ----------------------------------------------------------------------------------------------
# Writing


def encode(host: dict[str, np.ndarray], generator: str, kmeans_iterations: int = 2) -> dict[str, bytes]:
    """The SOG files (name -> bytes, meta.json last) of host arrays, rows in Morton order."""
    from PIL import Image  # noqa: F401 - fail early when Pillow is missing

    order = morton_order(host["means"])
    n = order.shape[0]
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    height = max(4, math.ceil(n / width / 4) * 4)

    def image(channels: list[np.ndarray], alpha=None) -> bytes:
        pixels = np.zeros((width * height, 4), np.uint8)
        for c, values in enumerate(channels):
            pixels[:n, c] = values
        pixels[:n, 3] = 255 if alpha is None else alpha
        return _webp(pixels.reshape(height, width, 4))

    files = {}
    means = host["means"][order].astype(np.float64)
    logm = np.sign(means) * np.log1p(np.abs(means))
    lo, hi = logm.min(axis=0), logm.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    q16 = np.clip(np.rint((logm - lo) / span * 65535.0), 0, 65535).astype(np.uint32)
    files["means_l.webp"] = image([q16[:, i] & 255 for i in range(3)])
    files["means_u.webp"] = image([q16[:, i] >> 8 for i in range(3)])

    largest, three = smallest_three(host["rotations"][order])
    codes = np.clip(np.rint(255.0 * (three * (2.0 * SQRT1_2) * 0.5 + 0.5)), 0, 255).astype(np.uint8)
    files["quats.webp"] = image([codes[:, 0], codes[:, 1], codes[:, 2]], alpha=(252 + largest).astype(np.uint8))

    scale_book, scale_idx = kmeans_1d(host["log_scales"][order].astype(np.float64))
    files["scales.webp"] = image([scale_idx[:, i] for i in range(3)])

    feats = host["features"][order].astype(np.float64)
    dc_book, dc_idx = kmeans_1d(feats[:, :3])
    files["sh0.webp"] = image([dc_idx[:, i] for i in range(3)], alpha=opacity_to_byte(host["opacities"][order]))

    meta = {
        "version": 2,
        "asset": {"generator": generator},
        "count": int(n),
        "means": {"mins": _floats(lo), "maxs": _floats(hi), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": _floats(scale_book), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": _floats(dc_book), "files": ["sh0.webp"]},
    }
    k = feats.shape[1] // 3 - 1
    if k:
        rest = feats[:, 3:]
        if n <= PALETTE_LIMIT:
            palette, labels = rest, np.arange(n)
        else:
            palette, labels = kmeans_rows(rest, PALETTE_LIMIT, kmeans_iterations)
        entries = palette.shape[0]
        sh_book, sh_idx = kmeans_1d(palette)
        rows = math.ceil(entries / 64)
        centroids = np.zeros((rows * 64, k, 4), np.uint8)
        centroids[:entries, :, :3] = sh_idx.reshape(entries, 3, k).transpose(0, 2, 1)
        centroids[:, :, 3] = 255
        files["shN_centroids.webp"] = _webp(centroids.reshape(rows, 64 * k, 4))
        labels = labels.astype(np.uint32)
        files["shN_labels.webp"] = image([labels & 255, labels >> 8, np.zeros(n, np.uint32)])
        meta["shN"] = {"count": int(entries), "bands": {3: 1, 8: 2, 15: 3}[k], "codebook": _floats(sh_book),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}  # fmt: skip
    files["meta.json"] = json.dumps(meta, separators=(",", ":")).encode("ascii")
    return files


def bundle(files: dict[str, bytes]) -> bytes:
    """A .sog archive (zip, stored, fixed timestamps) of the files, meta.json first."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as z:
        for name in ["meta.json", *(f for f in files if f != "meta.json")]:
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            z.writestr(info, files[name])
    return out.getvalue()


def _webp(pixels: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels), "RGBA").save(out, format="WEBP", lossless=True, exact=True)
    return out.getvalue()


def _floats(values) -> list[float]:
    return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]


# ----------------------------------------------------------------------------------------------
# Reading


def read_bundled(path: Path) -> dict[str, np.ndarray]:
    """Decodes a bundled .sog (zip) file."""
    name = path.name
    try:
        archive = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise InputError(f"{name}: no such file") from None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as e:  # a directory entry of a zip version zipfile refuses
        raise InputError(f"{name}: not a readable .sog archive ({e})") from None
    with archive:
        members = {i.filename: i for i in archive.infolist()}

        def load(member: str, limit: int) -> bytes:
            info = members.get(member)
            if info is None:
                raise InputError(f"{name}: the archive has no {member}")
            if info.file_size > limit:
                raise InputError(f"{name}: {member} declares {info.file_size} bytes, more than {limit}")
            try:
                with archive.open(info) as f:
                    data = f.read(limit + 1)
            except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError, RuntimeError) as e:
                raise InputError(f"{name}: cannot read {member} from the archive ({_short(e)})") from None
            if len(data) > limit:
                raise InputError(f"{name}: {member} holds more than {limit} bytes")
            return data

        def image(member: str, limit: int) -> tuple[bytes, int]:
            data = load(member, min(limit, 64 * archive_bytes + (1 << 20)))
            return data, min(len(data), members[member].compress_size)  # the bytes it takes in the archive

        archive_bytes = path.stat().st_size
        return _decode(name, load("meta.json", META_LIMIT), image)


def read_unbundled(meta_path: Path) -> dict[str, np.ndarray]:
    """Decodes an unbundled SOG: ``meta.json`` (or a directory holding it) and its images."""
    from .common import read_file_bytes

    if meta_path.is_dir():
        meta_path = meta_path / "meta.json"
    folder = meta_path.parent

    def load(member: str, limit: int) -> tuple[bytes, int]:
        data = read_file_bytes(folder / member, limit)
        return data, len(data)

    return _decode(meta_path.name, read_file_bytes(meta_path, META_LIMIT), load)


def plain_name(name: str) -> bool:
    """Whether a file name from a meta.json names a file beside it: not empty, not '.' or '..', no
    separator and no NUL."""
    return bool(name) and name not in (".", "..") and not {"/", "\\", "\0"} & set(name)


def member_files(meta_path: Path) -> list[Path]:
    """The files an unbundled SOG is made of: ``meta.json`` and the images it names (as far as it can
    be read; the decoder says what is wrong with it)."""
    if meta_path.is_dir():
        meta_path = meta_path / "meta.json"
    names = []
    try:
        with open_regular(meta_path) as f:
            meta = json.loads(f.read(META_LIMIT).decode("utf-8"))
        for sec in meta.values() if isinstance(meta, dict) else ():
            listed = sec.get("files") if isinstance(sec, dict) else None
            if isinstance(listed, list):
                names += [n for n in listed if isinstance(n, str) and plain_name(n)]
    except (InputError, OSError, ValueError, RecursionError):
        pass
    return [meta_path, *(meta_path.parent / n for n in names)]


def _decode(name: str, meta_bytes: bytes, load) -> dict[str, np.ndarray]:
    try:
        meta = json.loads(meta_bytes.decode("utf-8"))
    except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, an integer too long to read
        raise InputError(f"{name}: meta.json is not valid JSON ({_short(e)})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{name}: meta.json is not a JSON object")
    if "version" not in meta:
        raise InputError(f"{name}: SOG version 1 (no 'version' in meta.json) is not supported; version 2 is")
    if meta.get("version") != 2:
        raise InputError(f"{name}: SOG version {json.dumps(meta.get('version'))[:40]} is not supported (the number 2 is)")
    n = _int(meta, "count", name, 1, 1 << 31)
    bands = meta["shN"].get("bands") if isinstance(meta.get("shN"), dict) else 0
    check_decoded_memory(name, n, 3 + 3 * (_REST[bands] if bands in (0, 1, 2, 3) else 0))

    def section(key: str) -> dict:
        value = meta.get(key)
        if not isinstance(value, dict):
            raise InputError(f"{name}: meta.json lacks the {key!r} section")
        return value

    def files(sec: dict, key: str, count: int) -> list[str]:
        names = sec.get("files")
        if not (isinstance(names, list) and len(names) == count and all(isinstance(f, str) for f in names)):
            raise InputError(f"{name}: meta.json {key}.files must list {count} file name(s)")
        for f in names:
            if not plain_name(f):
                raise InputError(f"{name}: meta.json {key}.files: {f!r} is not a plain file name")
        return names

    def codebook(sec: dict, key: str) -> np.ndarray:
        book = sec.get("codebook")
        if not (isinstance(book, list) and 0 < len(book) <= 256 and all(_is_number(v) for v in book)):
            raise InputError(f"{name}: meta.json {key}.codebook must be 1 to 256 numbers")
        return np.asarray(book, dtype=np.float64)

    def pixels(member: str, min_pixels: int, width: int | None = None) -> np.ndarray:
        data, stored = load(member, IMAGE_BYTES_PER_PIXEL * min_pixels + (1 << 20))
        return _decode_webp(name, member, data, stored, min_pixels, width)

    means_sec = section("means")
    lo, hi = _vector(means_sec, "mins", name), _vector(means_sec, "maxs", name)
    m_files = files(means_sec, "means", 2)
    low, high = pixels(m_files[0], n), pixels(m_files[1], n)
    q16 = low[:n, :3].astype(np.float64) + 256.0 * high[:n, :3]
    logm = lo + np.where(hi > lo, hi - lo, 1.0) * q16 / 65535.0
    means = np.sign(logm) * np.expm1(np.abs(logm))

    quats = pixels(files(section("quats"), "quats", 1)[0], n)[:n]
    tag = quats[:, 3].astype(np.int64)
    if np.any((tag < 252) | (tag > 255)):
        raise InputError(f"{name}: quats image has alpha values other than 252-255 (the largest component)")
    three = (quats[:, :3].astype(np.float64) / 255.0 - 0.5) * 2.0 / (2.0 * SQRT1_2)
    rotations = from_smallest_three(tag - 252, three)

    scale_sec = section("scales")
    scale_book = codebook(scale_sec, "scales")
    scale_idx = pixels(files(scale_sec, "scales", 1)[0], n)[:n, :3]
    log_scales = _lookup(scale_book, scale_idx, name, "scales")

    sh0_sec = section("sh0")
    dc_book = codebook(sh0_sec, "sh0")
    sh0 = pixels(files(sh0_sec, "sh0", 1)[0], n)[:n]
    dc = _lookup(dc_book, sh0[:, :3], name, "sh0")
    opacities = byte_to_opacity_logit(sh0[:, 3])

    features = dc
    if "shN" in meta:
        sec = section("shN")
        bands = _int(sec, "bands", name, 0, 3)
        k = _REST[bands]
        if k:
            entries = _int(sec, "count", name, 1, PALETTE_LIMIT)
            sh_book = codebook(sec, "shN")
            c_file, l_file = files(sec, "shN", 2)
            rows = math.ceil(entries / 64)
            centroids = pixels(c_file, rows * 64 * k, width=64 * k)
            labels_px = pixels(l_file, n)[:n]
            labels = labels_px[:, 0].astype(np.int64) | (labels_px[:, 1].astype(np.int64) << 8)
            if np.any(labels >= entries):
                raise InputError(f"{name}: shN labels point past the {entries}-entry palette")
            table = centroids.reshape(-1, k, 4)[:entries, :, :3]  # (entries, k, rgb)
            coeffs = _lookup(sh_book, table.transpose(0, 2, 1).reshape(entries, 3 * k), name, "shN")
            features = np.concatenate([dc, coeffs[labels]], axis=1)
    return host_arrays(means, rotations, log_scales, opacities, features)


def _decode_webp(name: str, member: str, data: bytes, stored: int, min_pixels: int, width: int | None) -> np.ndarray:
    """RGBA pixels (H * W, 4) of a WebP image, after checking its declared size against what the
    scene needs and against ``stored``, the bytes it takes on disk (in a .sog, compressed): a small
    file never makes a large allocation."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            img = Image.open(io.BytesIO(data), formats=["WEBP"])
            w, h = img.size
            limit = max(4 * min_pixels, 1 << 16) + (1 << 16)
            if w * h < min_pixels:
                raise InputError(f"{name}: {member} is {w}x{h}, too small for {min_pixels} pixels")
            if w * h > limit:
                raise InputError(f"{name}: {member} declares {w}x{h} pixels, far more than the scene needs")
            if w * h > 1024 * stored + (1 << 22):
                raise InputError(f"{name}: {member} declares {w}x{h} pixels, far more than its {stored:,} bytes can hold")
            if width is not None and w != width:
                raise InputError(f"{name}: {member} is {w} pixels wide, expected {width}")
            rgba = np.asarray(img.convert("RGBA"))
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - any decoder failure on malformed bytes
        raise InputError(f"{name}: {member} is not a readable WebP image ({_short(e)})") from None
    return rgba.reshape(-1, 4)


def _lookup(book: np.ndarray, idx: np.ndarray, name: str, key: str) -> np.ndarray:
    if int(idx.max(initial=0)) >= book.shape[0]:
        raise InputError(f"{name}: {key} indices point past its {book.shape[0]}-entry codebook")
    return book[idx.astype(np.int64)]


def _vector(sec: dict, key: str, name: str) -> np.ndarray:
    v = sec.get(key)
    if not (isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v)):
        raise InputError(f"{name}: meta.json means.{key} must be 3 numbers")
    return np.asarray(v, dtype=np.float64)


def _int(sec: dict, key: str, name: str, lo: int, hi: int) -> int:
    v = sec.get(key)
    if not (isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi):
        raise InputError(f"{name}: meta.json {key!r} must be an integer in [{lo}, {hi}]")
    return v


def _is_number(v) -> bool:
    """A finite number that a float holds (an integer of 400 digits is not one)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _short(e: BaseException) -> str:
    text = re.sub(r" ?<[^<>]* object at 0x[0-9a-fA-F]+>", "", " ".join(str(e).split()))  # no object reprs
    text = re.sub(r"<ZipInfo filename='([^']*)'[^<>]*>", r"\1", text)  # zipfile's own: its member's name
    return (text[:120] + "...") if len(text) > 120 else (text or type(e).__name__)
