"""Niantic SPZ, versions 2 and 3: a gzip stream of a 16-byte header and the attributes by kind.

Header (little-endian): magic 0x5053474e ("NGSP"), version (2 or 3), splat count, SH degree (0-3),
fractional bits of the positions, flags (0x1 antialiased; 0x2 extensions: not read), reserved.
Then, for all splats in turn: positions (24-bit signed fixed point, x y z), alphas (uint8
sigmoid(opacity)), colours (uint8 0.15 255 f_dc + 127.5), log scales (uint8 16 (s + 10)),
rotations (v2: x y z as uint8 127.5 (q + 1) with w >= 0; v3: 2-bit index of the largest component
and three 10-bit sign-magnitude components / sqrt(1/2), x y z w order) and SH (uint8 128 + 128 f,
coefficient-major with the colour channel inner). SPZ's axes are right-up-back (OpenGL), PLY's
right-down-forward: y and z are negated on reading and on writing (positions, the quaternion's y and
z, and the SH coefficients odd in y and z), as Niantic's library and splat-transform do.
"""

from __future__ import annotations

import gzip
import zlib
import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from .common import (
    VISIBLE_FRACTION,
    byte_to_opacity_logit,
    channel_major_to_interleaved,
    check_decoded_memory,
    clamped_scales_note,
    from_smallest_three,
    gunzip_bounded,
    host_arrays,
    interleaved_to_channel_major,
    most_inflated,
    opacity_to_byte,
    scene_extent,
    smallest_three,
    unit_quaternions,
)

MAGIC = 0x5053474E
HEADER = struct.Struct("<IIIBBBB")
MAX_SH_DEGREE = 3
COLOUR_SCALE = 0.15
LOG_SCALE_RANGE = (-10.0, 255 / 16 - 10.0)  # one byte, (log-scale + 10) x 16
MAX_FRACTIONAL_BITS = 12  # Niantic's writer uses 12 (1/4096 units); fewer when positions need it
_REST = {0: 0, 1: 3, 2: 8, 3: 15}
# RDF <-> RUB is a half turn about x: (x, y, z) -> (x, -y, -z). Signs of the real SH basis functions
# (degree 1-3, m = -l..l, as 3DGS orders them) under it: those odd in y and z change sign.
AXIS_SIGNS = np.array([1.0, -1.0, -1.0])
SH_SIGNS = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)


def looks_like_spz(head: bytes) -> bool:
    """gzip data (SPZ v2/v3) or an uncompressed NGSP header (SPZ v4, which is not read)."""
    return head[:2] == b"\x1f\x8b" or head[:4] == struct.pack("<I", MAGIC)


def read_arrays(path: Path, data: bytes) -> dict[str, np.ndarray]:
    """Decodes an SPZ file's bytes into host arrays (values not checked)."""
    name = path.name
    if data[:4] == struct.pack("<I", MAGIC):
        version = struct.unpack("<I", data[4:8])[0] if len(data) >= 8 else 0
        raise InputError(f"{name}: uncompressed SPZ (version {version}) is not supported; versions 2 and 3 are "
                         "(splat-transform writes them with --spz-version 3)")  # fmt: skip
    first = _gunzip_prefix(data, name)
    if len(first) < HEADER.size:
        raise InputError(f"{name}: truncated SPZ header ({len(first)} of {HEADER.size} bytes)")
    magic, version, n, degree, frac, flags, _ = HEADER.unpack_from(first)
    if magic != MAGIC:
        raise InputError(f"{name}: not an SPZ file (gzip data without the NGSP magic)")
    if version not in (2, 3):
        raise InputError(f"{name}: SPZ version {version} is not supported (2 and 3 are)")
    if degree > MAX_SH_DEGREE:
        raise InputError(f"{name}: SPZ SH degree {degree} is not supported (0 to 3 are)")
    if flags & 0x2:
        raise InputError(f"{name}: SPZ extensions (flag 0x2) are not supported")
    if n == 0:
        raise InputError(f"{name}: no splats (the SPZ header declares 0)")
    if frac > 24:
        raise InputError(f"{name}: {frac} fractional bits of a 24-bit position is not valid")
    rot_bytes = 4 if version == 3 else 3
    k = _REST[degree]
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k * n]
    if HEADER.size + sum(sizes) > most_inflated(len(data)):
        raise InputError(f"{name}: truncated SPZ data: {n} splats need {HEADER.size + sum(sizes)} bytes, more than "
                         f"{len(data)} bytes of gzip data can hold")  # fmt: skip
    check_decoded_memory(name, n, 3 + 3 * k)
    body = gunzip_bounded(data, HEADER.size + sum(sizes), name)  # never more than the header declares
    if len(body) < HEADER.size + sum(sizes):
        raise InputError(f"{name}: truncated SPZ data: {n} splats need {HEADER.size + sum(sizes)} bytes, "
                         f"the stream holds {len(body)}")  # fmt: skip
    parts = []
    at = HEADER.size
    for size in sizes:
        parts.append(np.frombuffer(body, np.uint8, count=size, offset=at))
        at += size
    pos, alpha, colour, scale, rot, sh = parts

    b = pos.reshape(n, 3, 3).astype(np.int32)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float64) / float(1 << frac) * AXIS_SIGNS
    features = np.zeros((n, 3 + 3 * k), np.float64)
    features[:, :3] = (colour.reshape(n, 3) / 255.0 - 0.5) / COLOUR_SCALE
    if k:
        rest = (sh.reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0 * SH_SIGNS[:k, None]
        features[:, 3:] = interleaved_to_channel_major(rest)
    log_scales = scale.reshape(n, 3) / 16.0 - 10.0
    xyzw = _unpack_v3(rot.reshape(n, 4)) if version == 3 else _unpack_v2(rot.reshape(n, 3))
    xyzw[:, :3] *= AXIS_SIGNS
    return host_arrays(means, xyzw[:, [3, 0, 1, 2]], log_scales, byte_to_opacity_logit(alpha), features)


def encode(host: dict[str, np.ndarray], version: int = 3) -> tuple[bytes, list[str]]:
    """The SPZ bytes of host arrays (gzip, deterministic) and what was clipped, if anything."""
    n = host["means"].shape[0]
    notes = []
    means = host["means"].astype(np.float64) * AXIS_SIGNS
    largest = float(np.max(np.abs(means))) if n else 0.0
    frac = MAX_FRACTIONAL_BITS
    while frac > 0 and largest * (1 << frac) > (1 << 23) - 1:
        frac -= 1
    fixed = np.rint(means * (1 << frac))
    if np.any(np.abs(fixed) > (1 << 23) - 1):
        notes.append(f"positions beyond +-{((1 << 23) - 1) / (1 << frac):.4g} units: clipped")
    extent = scene_extent(means, host["log_scales"])
    if n and 0.5 / (1 << frac) > VISIBLE_FRACTION * extent:
        notes.append(f"positions finer than 1/{1 << frac} units: rounded, by more than {VISIBLE_FRACTION:g} of the scene's extent ({extent:.3g})")
    notes += clamped_scales_note(host["log_scales"], host["means"], LOG_SCALE_RANGE[0], LOG_SCALE_RANGE[1])
    fixed = np.clip(fixed, -(1 << 23) + 1, (1 << 23) - 1).astype(np.int32)
    pos = np.stack([fixed & 255, (fixed >> 8) & 255, (fixed >> 16) & 255], axis=-1).astype(np.uint8)

    feats = host["features"].astype(np.float64)
    degree = {3: 0, 12: 1, 27: 2, 48: 3}[feats.shape[1]]
    colour = _to_u8(feats[:, :3] * (COLOUR_SCALE * 255.0) + 127.5)
    scales = _to_u8((host["log_scales"].astype(np.float64) - LOG_SCALE_RANGE[0]) * 16.0)
    xyzw = unit_quaternions(host["rotations"])[:, [1, 2, 3, 0]]
    xyzw[:, :3] *= AXIS_SIGNS
    rot = _pack_v3(xyzw) if version == 3 else _pack_v2(xyzw)
    k = feats.shape[1] // 3 - 1
    rest = channel_major_to_interleaved(feats[:, 3:]) * SH_SIGNS[:k, None]
    sh = _to_u8(rest * 128.0 + 128.0) if degree else np.zeros(0, np.uint8)
    header = HEADER.pack(MAGIC, version, n, degree, frac, 0, 0)
    raw = b"".join([header, pos.tobytes(), opacity_to_byte(host["opacities"]).tobytes(), colour.tobytes(),
                    scales.tobytes(), rot.tobytes(), sh.tobytes()])  # fmt: skip
    return gzip.compress(raw, compresslevel=6, mtime=0), notes


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _pack_v2(xyzw: np.ndarray) -> np.ndarray:
    q = xyzw * np.where(xyzw[:, 3:4] < 0, -1.0, 1.0)
    return _to_u8(q[:, :3] * 127.5 + 127.5)


def _unpack_v2(b: np.ndarray) -> np.ndarray:
    xyz = b.astype(np.float64) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - np.einsum("ij,ij->i", xyz, xyz)))
    return np.concatenate([xyz, w[:, None]], axis=1)


def _pack_v3(xyzw: np.ndarray) -> np.ndarray:
    largest, three = smallest_three(xyzw)
    word = largest.astype(np.uint32)
    mag = np.floor(511.0 * np.abs(three) / np.sqrt(0.5) + 0.5).clip(0, 511).astype(np.uint32)
    neg = (three < 0).astype(np.uint32)
    for j in range(3):
        word = (word << np.uint32(10)) | (neg[:, j] << np.uint32(9)) | mag[:, j]
    return word.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_v3(b: np.ndarray) -> np.ndarray:
    word = b.copy().view("<u4").reshape(-1).astype(np.uint32)
    largest = (word >> np.uint32(30)).astype(np.int64)
    three = np.zeros((word.shape[0], 3), np.float64)
    for j in (2, 1, 0):  # the last component packed sits in the lowest bits
        mag = (word & np.uint32(511)).astype(np.float64)
        neg = (word >> np.uint32(9)) & np.uint32(1)
        three[:, j] = np.where(neg == 1, -1.0, 1.0) * np.sqrt(0.5) * mag / 511.0
        word = word >> np.uint32(10)
    return from_smallest_three(largest, three)


def _gunzip_prefix(data: bytes, name: str) -> bytes:
    """The first bytes of the gzip stream (enough for the header), without inflating the rest."""

    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        return d.decompress(data, HEADER.size)
    except zlib.error as e:
        raise InputError(f"{name}: corrupt gzip data ({e})") from None
