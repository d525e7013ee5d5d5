"""Opacity pruning: activated opacities and keep flags."""

import warp as wp

from .options import PORTABLE
from .portable_math import sigmoid64

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py


@wp.kernel
def activated_opacity(
    logits: wp.array(dtype=float),
    alpha: wp.array(dtype=float),
    sort_keys: wp.array(dtype=float),
    sort_ids: wp.array(dtype=wp.int32),
):
    """alpha = sigmoid(logit) (float64, portable, then rounded), plus a copy with row ids to sort."""
    i = wp.tid()
    a = wp.float32(sigmoid64(wp.float64(logits[i])))
    alpha[i] = a
    sort_keys[i] = a
    sort_ids[i] = i


@wp.kernel
def keep_at_least(values: wp.array(dtype=float), threshold: wp.float64, keep: wp.array(dtype=wp.int32)):
    """keep[i] = values[i] >= threshold."""
    i = wp.tid()
    keep[i] = wp.where(wp.float64(values[i]) >= threshold, 1, 0)


@wp.kernel
def keep_rows(rows: wp.array(dtype=wp.int32), first: int, keep: wp.array(dtype=wp.int32)):
    """keep[rows[first + t]] = 1."""
    keep[rows[first + wp.tid()]] = 1
