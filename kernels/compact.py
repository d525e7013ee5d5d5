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
