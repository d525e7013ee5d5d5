"""A splat set's overall size: every splat's axes times one factor (``size_fit``)."""

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # the same bits on every device: portable_math.py


@wp.kernel
def resized_log_scales(log_scales: wp.array(dtype=wp.vec3), log_factor: float, out: wp.array(dtype=wp.vec3)):
    """out = log_scales + log(factor) on every axis: each splat's standard deviations times the
    factor, its centre, rotation, opacity and colour unchanged (one float32 addition an axis)."""
    i = wp.tid()
    s = log_scales[i]
    out[i] = wp.vec3(s[0] + log_factor, s[1] + log_factor, s[2] + log_factor)
