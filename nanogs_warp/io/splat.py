"""antimatter15 ``.splat``: 32-byte rows with no header, SH degree 0 only.

Each row: position float32 x3, linear scale float32 x3, colour RGBA uint8 (RGB = 255 (0.5 +
SH_C0 f_dc), A = 255 sigmoid(opacity)), rotation uint8 x4 (w, x, y, z as 128 + 128 q). Positions
and scales are exact (scales as exp of the log scales, float32); colour, opacity and rotation are
8-bit. The file has no signature: it is recognised by its name's .splat extension alone.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from .common import SH_C0, byte_to_opacity_logit, clamped_scales_note, host_arrays, opacity_to_byte, unit_quaternions

ROW = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
MAX_SH_DEGREE = 0


def read_arrays(path: Path, data: bytes) -> dict[str, np.ndarray]:
    """Decodes a .splat file's bytes into host arrays (values not checked)."""
    name = path.name
    if len(data) == 0:
        raise InputError(f"{name}: the file is empty")
    if len(data) % ROW.itemsize:
        raise InputError(f"{name}: not a .splat file ({len(data)} bytes is not a multiple of 32)")
    rows = np.frombuffer(data, ROW)
    scale = rows["scale"].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        # a scale of 0 (or subnormal) is a splat too small for float32's exp: the smallest normal float32
        tiny = np.finfo(np.float32).tiny
        log_scales = np.log(np.where((scale >= 0.0) & (scale < tiny), tiny, scale))
    rgba = rows["rgba"]
    features = (rgba[:, :3].astype(np.float64) / 255.0 - 0.5) / SH_C0
    rotations = (rows["rotation"].astype(np.float64) - 128.0) / 128.0
    return host_arrays(rows["position"], rotations, log_scales, byte_to_opacity_logit(rgba[:, 3]), features)


_LARGEST_SCALE = float(np.finfo(np.float32).max)  # .splat stores sizes, not their logs, in float32
_SMALLEST_SCALE = float(np.finfo(np.float32).tiny)  # and reads one below float32's smallest normal as it


def notes(host: dict[str, np.ndarray]) -> list[str]:
    """What ``encode`` cannot hold visibly: sizes beyond float32 (log-scales above 88.7); those
    below its smallest normal (log-scales below -87.3) are stored as it, as reading gives them."""
    return clamped_scales_note(host["log_scales"], host["means"], math.log(_SMALLEST_SCALE), math.log(_LARGEST_SCALE))


def encode(host: dict[str, np.ndarray]) -> bytes:
    """The .splat bytes of host arrays (rows in their order; SH bands above 0 are not written)."""
    n = host["means"].shape[0]
    rows = np.zeros(n, ROW)
    rows["position"] = host["means"]
    with np.errstate(over="ignore"):  # sizes clamped to float32's normal range (notes())
        rows["scale"] = np.clip(np.exp(host["log_scales"].astype(np.float64)), _SMALLEST_SCALE, _LARGEST_SCALE).astype(np.float32)
    colour = 255.0 * (0.5 + SH_C0 * host["features"][:, :3].astype(np.float64))
    rows["rgba"][:, :3] = np.clip(np.rint(colour), 0, 255)
    rows["rgba"][:, 3] = opacity_to_byte(host["opacities"])
    rows["rotation"] = np.clip(np.rint(128.0 + 128.0 * unit_quaternions(host["rotations"])), 0, 255)
    return rows.tobytes()
