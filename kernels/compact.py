"""Gathering the kept rows of a splat set into a new one."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def drop_rows(rows: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    keep[rows[wp.tid()]] = 0


@wp.kernel
def gather_rows(
    keep: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    extras: wp.array2d(dtype=float),
    out_means: wp.array(dtype=wp.vec3),
    out_rotations: wp.array(dtype=wp.quat),
    out_log_scales: wp.array(dtype=wp.vec3),
    out_opacities: wp.array(dtype=float),
    out_features: wp.array2d(dtype=float),
    out_extras: wp.array2d(dtype=float),
):
    """Row i moves to destination[i] (an exclusive scan of keep), order preserved."""
    i = wp.tid()
    if keep[i] == 0:
        return
    d = destination[i]
    out_means[d] = means[i]
    out_rotations[d] = rotations[i]
    out_log_scales[d] = log_scales[i]
    out_opacities[d] = opacities[i]
    for c in range(features.shape[1]):
        out_features[d, c] = features[i, c]
    for c in range(extras.shape[1]):
        out_extras[d, c] = extras[i, c]
