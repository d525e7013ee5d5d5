"""Merge operators: fuse each chosen pair (i, j) of a source set into one splat of an output set,
at row destination[i] (the row where i itself went when the absorbed rows j were removed)."""

import warp as wp

from .splat_math import covariance, first_weight, log_mass, log_sigmoid, moment_match, quaternion_from_frame, symmetric_eigen, to_vec3d

wp.set_module_options({"enable_backward": False})

# Written values stay finite: |logit| <= 16.1 keeps sigmoid(logit) < 1 in float32, and scales
# below exp(-30) are not distinguishable from zero in any renderer.
LOGIT_LIMIT = wp.constant(16.1)
LOG_SCALE_MIN = wp.constant(-30.0)


@wp.func
def over_opacity_logit(logit_i: float, logit_j: float):
    """logit of alpha_m = 1 - (1 - alpha_i)(1 - alpha_j) (NanoGS eq. 9), via log transmittances."""
    log_t = log_sigmoid(-wp.float64(logit_i)) + log_sigmoid(-wp.float64(logit_j))
    alpha = wp.float64(1.0) - wp.exp(log_t)
    logit = wp.log(wp.max(alpha, wp.float64(1e-300))) - log_t
    return wp.clamp(wp.float32(logit), -LOGIT_LIMIT, LOGIT_LIMIT)


@wp.func
def write_gaussian(
    row: int,
    mu: wp.vec3d,
    cov: wp.mat33d,
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
):
    """Stores N(mu, cov) as centre, rotation and log scales: Sigma = R diag(s^2) R^T with R the
    eigenvector frame (eigenvalues decreasing, det R = +1)."""
    values, frame = symmetric_eigen(cov)
    means[row] = wp.vec3(wp.float32(mu[0]), wp.float32(mu[1]), wp.float32(mu[2]))
    rotations[row] = quaternion_from_frame(frame)
    ls = wp.vec3()
    for k in range(3):
        ls[k] = wp.max(wp.float32(wp.float64(0.5) * wp.log(wp.max(values[k], wp.float64(1e-300)))), LOG_SCALE_MIN)
    log_scales[row] = ls


@wp.func
def blend_rows(values: wp.array2d(dtype=float), i: int, j: int, pi: wp.float64, out: wp.array2d(dtype=float), row: int):
    """out[row] = pi values[i] + (1 - pi) values[j]."""
    for c in range(values.shape[1]):
        out[row, c] = wp.float32(pi * wp.float64(values[i, c]) + (wp.float64(1.0) - pi) * wp.float64(values[j, c]))


@wp.kernel
def mass_preserving_moment_matching(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
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
    """MPMM (NanoGS eq. 6-9): mass weights w = (2 pi)^{3/2} alpha prod s; mass-weighted mean,
    covariance (within-splat average + between-mean dispersion), features and extras; opacity by
    the over rule."""
    p = wp.tid()
    i = int(pair_i[p])
    j = int(pair_j[p])
    row = int(destination[i])
    pi = first_weight(log_mass(opacities[i], log_scales[i]), log_mass(opacities[j], log_scales[j]))
    mu_m, cov_m = moment_match(
        pi,
        to_vec3d(means[i]), covariance(rotations[i], log_scales[i]),
        to_vec3d(means[j]), covariance(rotations[j], log_scales[j]),
    )  # fmt: skip
    out_opacities[row] = over_opacity_logit(opacities[i], opacities[j])
    blend_rows(features, i, j, pi, out_features, row)
    blend_rows(extras, i, j, pi, out_extras, row)
    write_gaussian(row, mu_m, cov_m, out_means, out_rotations, out_log_scales)
