"""Gathering the kept rows of a splat set into a new one."""

import warp as wp

from .options import PORTABLE
from .splat_math import Splats

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py


@wp.kernel
def drop_rows(rows: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    keep[rows[wp.tid()]] = 0


@wp.kernel
def gather_rows(
    first: int,
    keep: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    src: Splats,
    out: Splats,
):
    """Row i (thread t handles row first + t) moves to destination[i] (an exclusive scan of keep),
    order preserved."""
    i = first + wp.tid()
    if keep[i] == 0:
        return
    d = destination[i]
    out.means[d] = src.means[i]
    out.rotations[d] = src.rotations[i]
    out.log_scales[d] = src.log_scales[i]
    out.opacities[d] = src.opacities[i]
    for c in range(src.features.shape[1]):
        out.features[d, c] = src.features[i, c]
    for c in range(src.extras.shape[1]):
        out.extras[d, c] = src.extras[i, c]
    for c in range(src.integer_extras.shape[1]):
        out.integer_extras[d, c] = src.integer_extras[i, c]


@wp.kernel
def carry_merged_rows(
    keep: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    merged: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.int32),
):
    """A kept row's mark (1: a merge made it) moves with the row to destination[i]."""
    i = wp.tid()
    if keep[i] != 0:
        out[destination[i]] = merged[i]


@wp.kernel
def mark_merged_rows(rows: wp.array(dtype=wp.int32), destination: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """The row where each pair's first splat went (where the merge writes the pair's splat) is marked 1."""
    out[destination[rows[wp.tid()]]] = 1


@wp.kernel
def copy_merged_rows(merged: wp.array(dtype=wp.int32), source: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    """Row i of ``out`` becomes ``source``'s where a merge made it (merged[i] == 1)."""
    i = wp.tid()
    if merged[i] != 0:
        for c in range(source.shape[1]):
            out[i, c] = source[i, c]
