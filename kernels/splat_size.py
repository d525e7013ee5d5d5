"""The size fit's kernels (``size_fit``): a splat set's overall size (every splat's axes times one
factor), and how far a render is from the input's."""

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py


@wp.kernel
def resized_log_scales(log_scales: wp.array(dtype=wp.vec3), log_factor: float, out: wp.array(dtype=wp.vec3)):
    """out = log_scales + log(factor) on every axis: each splat's standard deviations times the
    factor, its centre, rotation, opacity and colour unchanged (one float32 addition an axis)."""
    i = wp.tid()
    s = log_scales[i]
    out[i] = wp.vec3(s[0] + log_factor, s[1] + log_factor, s[2] + log_factor)


@wp.kernel
def squared_error_rows(
    reference: wp.array4d(dtype=float),
    test: wp.array4d(dtype=float),
    rows: wp.array2d(dtype=wp.float64),
):
    """Per view v and image row y: the sum over the row's pixels and channels of the squared
    difference of the two images, each clamped to [0, 1] as ``eval`` compares them, in float64 and
    in pixel order (so every device sums alike)."""
    v, y = wp.tid()
    total = wp.float64(0.0)
    for x in range(test.shape[2]):
        for c in range(3):
            d = wp.float64(wp.clamp(test[v, y, x, c], 0.0, 1.0)) - wp.float64(wp.clamp(reference[v, y, x, c], 0.0, 1.0))
            total = total + d * d
    rows[v, y] = total
