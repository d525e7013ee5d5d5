"""PlayCanvas ``compressed.ply``: chunks of 256 splats quantised against each chunk's bounds.

Elements: ``chunk`` (float32 bounds per 256 splats: min/max x y z, min/max scale_x..z, and
optionally min/max r g b), ``vertex`` (uint32 ``packed_position`` 11-10-11 bits, ``packed_rotation``
2-bit largest-component index + 3 x 10 bits, ``packed_scale`` 11-10-11 bits of the log scales,
``packed_color`` 8-8-8-8 bits of 0.5 + SH_C0 f_dc and sigmoid(opacity)) and optionally ``sh``
(uint8 f_rest_*, (f / 8 + 0.5) 256, so [-4, 4]). Rows are written in Morton order (the format's
precision depends on chunks being compact); rotation components are in PLY order (w, x, y, z).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from .common import (
    SH_C0,
    SQRT1_2,
    byte_to_opacity_logit,
    clamped_scales_note,
    from_smallest_three,
    host_arrays,
    largest_positive,
    morton_order,
    opacity_to_byte,
)
from .ply_header import check_sizes, parse_header

_NEWLINES = re.compile(rb"\r\n|\r|\n")

CHUNK = 256
MAX_SH_DEGREE = 3
BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
          "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")  # fmt: skip
COLOUR_BOUNDS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
SCALE_LIMIT = 20.0  # chunk scale bounds are clamped to [-20, 20], as PlayCanvas does


def looks_compressed(head: bytes) -> bool:
    """Whether a PLY header (the file's first bytes) is a compressed.ply one."""
    end = head.find(b"end_header")
    lines = [line.split() for line in _NEWLINES.split(head[: end if end >= 0 else len(head)])]  # CR-only lines too
    return any(words[:2] == [b"element", b"chunk"] for words in lines) and any(
        words[:1] == [b"property"] and words[-1:] == [b"packed_position"] for words in lines
    )


def read_arrays(path: Path, data: bytes) -> dict[str, np.ndarray]:
    """Decodes a compressed.ply file's bytes into host arrays (values not checked)."""
    name = path.name
    header = parse_header(data[: 1 << 20], name)
    if header.format != "binary_little_endian":
        raise InputError(f"{name}: compressed PLY must be binary_little_endian, not {header.format}")
    names = [e.name for e in header.elements]
    if names not in (["chunk", "vertex"], ["chunk", "vertex", "sh"]):
        raise InputError(f"{name}: compressed PLY needs elements chunk, vertex [, sh]; found {', '.join(names)}")
    chunk, vertex = header.element("chunk"), header.element("vertex")
    sh = header.element("sh")
    _expect(name, chunk, {p: "f4" for p in BOUNDS}, COLOUR_BOUNDS, "f4")
    _expect(name, vertex, {p: "u4" for p in PACKED}, (), "u4")
    n_rest = 0
    if sh is not None:
        n_rest = len(sh.props)
        if n_rest not in (9, 24, 45) or [p.name for p in sh.props] != [f"f_rest_{i}" for i in range(n_rest)]:
            raise InputError(f"{name}: element sh must hold f_rest_0..f_rest_N-1 with N 9, 24 or 45")
        if any(p.is_list or p.dtype != np.dtype("u1") for p in sh.props):
            raise InputError(f"{name}: element sh must hold uchar properties")
        if sh.count != vertex.count:
            raise InputError(f"{name}: element sh has {sh.count} rows but vertex has {vertex.count}")
    n = vertex.count
    if n == 0:
        raise InputError(f"{name}: no splats (element vertex is empty)")
    if chunk.count != math.ceil(n / CHUNK):
        raise InputError(f"{name}: {chunk.count} chunks for {n} splats (expected {math.ceil(n / CHUNK)})")
    check_sizes(header, len(data), name)  # before anything is allocated

    offset = header.length
    tables = {}
    for e in header.elements:
        dtype = np.dtype([(p.name, "<" + p.dtype.str[1:]) for p in e.props])
        tables[e.name] = np.frombuffer(data, dtype, count=e.count, offset=offset)
        offset += e.count * dtype.itemsize
    c, v = tables["chunk"], tables["vertex"]
    row_chunk = np.arange(n) // CHUNK

    def lerp(lo, hi, t):
        return c[lo][row_chunk] * (1.0 - t) + c[hi][row_chunk] * t

    def unorm(word, shift, bits):
        return ((word >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)

    pos, scl, col = v["packed_position"], v["packed_scale"], v["packed_color"]
    means = np.stack([lerp("min_x", "max_x", unorm(pos, 21, 11)), lerp("min_y", "max_y", unorm(pos, 11, 10)),
                      lerp("min_z", "max_z", unorm(pos, 0, 11))], axis=1)  # fmt: skip
    log_scales = np.stack([lerp("min_scale_x", "max_scale_x", unorm(scl, 21, 11)),
                           lerp("min_scale_y", "max_scale_y", unorm(scl, 11, 10)),
                           lerp("min_scale_z", "max_scale_z", unorm(scl, 0, 11))], axis=1)  # fmt: skip
    colour = np.stack([unorm(col, 24, 8), unorm(col, 16, 8), unorm(col, 8, 8)], axis=1)
    if "min_r" in c.dtype.names:
        colour = np.stack([lerp(f"min_{k}", f"max_{k}", colour[:, i]) for i, k in enumerate("rgb")], axis=1)
    features = np.zeros((n, 3 + n_rest), np.float64)
    features[:, :3] = (colour - 0.5) / SH_C0
    if n_rest:
        codes = np.stack([tables["sh"][f"f_rest_{i}"] for i in range(n_rest)], axis=1).astype(np.float64)
        unit = np.where(codes == 0, 0.0, np.where(codes == 255, 1.0, (codes + 0.5) / 256.0))
        features[:, 3:] = (unit - 0.5) * 8.0
    opacities = byte_to_opacity_logit((col & np.uint32(255)).astype(np.uint8))
    rotations = _unpack_rotations(v["packed_rotation"])
    return host_arrays(means, rotations, log_scales, opacities, features)


def notes(host: dict[str, np.ndarray]) -> list[str]:
    """What ``encode`` cannot hold visibly: sizes beyond the format's log-scale bounds (e^+-20)."""
    return clamped_scales_note(host["log_scales"], host["means"], -SCALE_LIMIT, SCALE_LIMIT)


def encode(host: dict[str, np.ndarray], comment: str) -> bytes:
    """The compressed.ply bytes of host arrays, rows in Morton order (SH kept up to degree 3)."""
    order = morton_order(host["means"])
    n = order.shape[0]
    chunks = math.ceil(n / CHUNK)
    padded = np.concatenate([order, np.full(chunks * CHUNK - n, order[-1])])  # repeat the last row
    means = host["means"][padded].astype(np.float64).reshape(chunks, CHUNK, 3)
    log_scales = host["log_scales"][padded].astype(np.float64).reshape(chunks, CHUNK, 3)
    colour = (0.5 + SH_C0 * host["features"][padded, :3].astype(np.float64)).reshape(chunks, CHUNK, 3)

    p_lo, p_hi = means.min(axis=1), means.max(axis=1)
    s_lo = np.clip(log_scales.min(axis=1), -SCALE_LIMIT, SCALE_LIMIT)
    s_hi = np.clip(log_scales.max(axis=1), -SCALE_LIMIT, SCALE_LIMIT)
    c_lo, c_hi = colour.min(axis=1), colour.max(axis=1)

    packed = np.zeros((chunks * CHUNK, 4), np.uint32)
    packed[:, 0] = _pack_11_10_11(_normalise(means, p_lo, p_hi, smallest_span=np.finfo(np.float64).tiny))  # any units
    packed[:, 2] = _pack_11_10_11(_normalise(log_scales, s_lo, s_hi))
    c = _unorm(_normalise(colour, c_lo, c_hi), 8).reshape(-1, 3)
    alpha = opacity_to_byte(host["opacities"][padded]).astype(np.uint32)
    packed[:, 3] = (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | alpha
    packed[:, 1] = _pack_rotations(host["rotations"][padded])

    bounds = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], axis=1).astype("<f4")
    n_rest = host["features"].shape[1] - 3
    lines = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element chunk {chunks}"]
    lines += [f"property float {p}" for p in BOUNDS + COLOUR_BOUNDS]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    parts = [bounds.tobytes(), packed[:n].astype("<u4").tobytes()]
    if n_rest:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(n_rest)]
        rest = host["features"][order, 3:].astype(np.float64)
        parts.append(np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8).tobytes())
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii") + b"".join(parts)


def _expect(name, element, required: dict[str, str], optional: tuple[str, ...], dtype: str) -> None:
    props = {p.name: p for p in element.props}
    missing = [p for p in required if p not in props]
    if missing:
        raise InputError(f"{name}: compressed PLY element {element.name} lacks {', '.join(missing)}")
    allowed = set(required) | set(optional)
    odd = [p for p in props if p not in allowed]
    if odd:
        raise InputError(f"{name}: compressed PLY element {element.name} has unexpected properties {', '.join(odd)}")
    present = [p for p in optional if p in props]
    if present and len(present) != len(optional):
        raise InputError(f"{name}: compressed PLY element {element.name} has only some of {', '.join(optional)}")
    wrong = [p.name for p in element.props if p.is_list or p.dtype != np.dtype(dtype)]
    if wrong:
        raise InputError(f"{name}: compressed PLY properties {', '.join(wrong)} must be {np.dtype(dtype).name}")


def _normalise(x, lo, hi, smallest_span=1e-5):
    """(x - lo) / (hi - lo) per chunk and axis, in [0, 1]; 0 where the chunk's range is below
    ``smallest_span`` (PlayCanvas's 1e-5 for log-scales and colours; positions pass the smallest
    float64, so that a scene in tiny units keeps them)."""
    lo, hi = lo[:, None, :], hi[:, None, :]
    span = hi - lo
    flat = span < smallest_span
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(flat, 0.0, (x - lo) / np.where(flat, 1.0, span))
    return np.clip(np.nan_to_num(t), 0.0, 1.0)


def _unorm(t, bits):
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _pack_11_10_11(t):
    t = t.reshape(-1, 3)
    return (_unorm(t[:, 0], 11) << 21) | (_unorm(t[:, 1], 10) << 11) | _unorm(t[:, 2], 11)


def _pack_rotations(q_wxyz: np.ndarray) -> np.ndarray:
    largest, q = largest_positive(q_wxyz)
    word = largest.astype(np.uint32)
    for i in range(4):  # the three smaller components in order, each (q sqrt(1/2) + 0.5) in 10 bits
        code = _unorm(q[:, i] * SQRT1_2 + 0.5, 10)
        word = np.where(largest == i, word, (word << 10) | code)
    return word


def _unpack_rotations(word: np.ndarray) -> np.ndarray:
    largest = (word >> np.uint32(30)).astype(np.int64)
    three = np.stack([((word >> np.uint32(s)) & np.uint32(1023)).astype(np.float64) / 1023.0 for s in (20, 10, 0)], axis=1)
    return from_smallest_three(largest, (three - 0.5) / SQRT1_2)
