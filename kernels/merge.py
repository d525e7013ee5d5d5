"""Merge operators: fuse each chosen pair (i, j) of a source set into one splat of an output set,
at row destination[i] (the row where i itself went when the absorbed rows j were removed).

Every operator is a weighted moment match of the pair (``pair_moments``, ``blend_appearance``):
weights (pi, 1 - pi) give the merged mean, covariance (within-splat average + between-mean
dispersion), features and extras; integer extras are the heavier splat's (pi >= 1/2: i's, ties
included; else j's). Operators differ in their weights and in the merged opacity:

- ``mpmm``: mass w = (2 pi)^{3/2} alpha prod s; opacity by the over rule (NanoGS eq. 6-9).
- ``area``: w = alpha (s0 s1 + s0 s2 + s1 s2) (opacity x surface-area proxy, as hierarchical 3DGS);
  opacity conserves the weighted mass, alpha_m = (w_i + w_j) / area_m, clamped to (0, 1).
- ``coverage``: w = alpha s_a s_b (the two largest scales: the face-on footprint); where the pair's
  coverage alpha x footprint in the merged splat's face plane exceeds the merged footprint, the face
  plane grows by (coverage / footprint_m)^growth; the opacity is the least-squares fit of the pair's
  opacity field seen along the merged splat's three axes (``kernels/field.py``).
"""

import warp as wp

from .field import field_opacity, pair_view_overlaps
from .options import PORTABLE
from .portable_math import exp64, log64, pow64, sigmoid64
from .splat_math import Splats, covariance, first_weight, log_mass, log_sigmoid, moment_match, quaternion_from_frame, symmetric_eigen, to_vec3d

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

# Written values stay finite: |logit| <= 16.1 keeps sigmoid(logit) < 1 in float32, and scales
# below exp(-30) are not distinguishable from zero in any renderer. A merged opacity stays at or
# below 254/255 (logit log 254): 8-bit formats store alpha 255 as an infinite logit, and a trainer
# that fine-tunes the result gets no gradient at a saturated one. Renderers clamp alpha at 0.99, so
# the cap changes a render by at most 0.4 % in a splat's falloff.
LOGIT_LIMIT = wp.constant(16.1)
MERGED_LOGIT_MAX = wp.constant(5.537334267018537)  # log(254) = logit(254 / 255)
MERGED_ALPHA_MAX = wp.constant(254.0 / 255.0)
# Bounds of a merged splat's stored log-scales: the input domain's (nanogs_warp/domain.py), so every
# output is a valid input. Merged covariances are regularised relative to their trace (RIDGE in
# splat_math.py), so the floor only bites in scenes whose splats are below ~1e-40 in size (a fixed
# floor nearer to 1 would make a scene in tiny units come out in splats larger than itself), and the
# ceiling only where splats near e^100 merge into a larger one.
LOG_SCALE_MIN = wp.constant(-100.0)
LOG_SCALE_MAX = wp.constant(100.0)


@wp.func
def over_opacity_logit(logit_i: float, logit_j: float):
    """logit of alpha_m = 1 - (1 - alpha_i)(1 - alpha_j) (NanoGS eq. 9), via log transmittances."""
    log_t = log_sigmoid(-wp.float64(logit_i)) + log_sigmoid(-wp.float64(logit_j))
    alpha = wp.float64(1.0) - exp64(log_t)
    logit = log64(wp.max(alpha, wp.float64(1e-300))) - log_t
    return wp.clamp(wp.float32(logit), -LOGIT_LIMIT, MERGED_LOGIT_MAX)


@wp.func
def store_gaussian(
    row: int,
    mu: wp.vec3d,
    values: wp.vec3d,
    frame: wp.mat33d,
    out: Splats,
):
    """Stores centre ``mu`` and the covariance frame diag(values) in ``frame`` (eigenvalues
    decreasing, det frame = +1) as centre, rotation and log scales. Returns the log scales stored."""
    out.means[row] = wp.vec3(wp.float32(mu[0]), wp.float32(mu[1]), wp.float32(mu[2]))
    out.rotations[row] = quaternion_from_frame(frame)
    ls = wp.vec3()
    for k in range(3):
        ls[k] = wp.clamp(wp.float32(wp.float64(0.5) * log64(wp.max(values[k], wp.float64(1e-300)))), LOG_SCALE_MIN, LOG_SCALE_MAX)
    out.log_scales[row] = ls
    return ls


@wp.func
def write_gaussian(
    row: int,
    mu: wp.vec3d,
    cov: wp.mat33d,
    out: Splats,
):
    """Stores N(mu, cov) as centre, rotation and log scales: Sigma = R diag(s^2) R^T with R the
    eigenvector frame (eigenvalues decreasing, det R = +1). Returns the log scales stored."""
    values, frame = symmetric_eigen(cov)
    return store_gaussian(row, mu, values, frame, out)


@wp.func
def blend_rows(values: wp.array2d(dtype=float), i: int, j: int, pi: wp.float64, out: wp.array2d(dtype=float), row: int):
    """out[row] = pi values[i] + (1 - pi) values[j]."""
    for c in range(values.shape[1]):
        out[row, c] = wp.float32(pi * wp.float64(values[i, c]) + (wp.float64(1.0) - pi) * wp.float64(values[j, c]))


@wp.func
def heavier_rows(values: wp.array2d(dtype=wp.int64), i: int, j: int, pi: wp.float64, out: wp.array2d(dtype=wp.int64), row: int):
    """out[row] = values[i] when i weighs at least as much as j (pi >= 1/2, ties to i), else values[j]:
    integer properties are carried exactly, never averaged."""
    k = i
    if pi < wp.float64(0.5):
        k = j
    for c in range(values.shape[1]):
        out[row, c] = values[k, c]


@wp.func
def blend_appearance(
    i: int,
    j: int,
    pi: wp.float64,
    row: int,
    src: Splats,
    out: Splats,
):
    """Weighted features (SH) and extras of the pair, and the heavier splat's integer extras,
    written at ``row``."""
    blend_rows(src.features, i, j, pi, out.features, row)
    blend_rows(src.extras, i, j, pi, out.extras, row)
    heavier_rows(src.integer_extras, i, j, pi, out.integer_extras, row)


@wp.func
def pair_moments(
    i: int,
    j: int,
    pi: wp.float64,
    src: Splats,
):
    """Weighted mean and covariance of splats i and j (NanoGS eq. 7-8), float64."""
    return moment_match(
        pi,
        to_vec3d(src.means[i]), covariance(src.rotations[i], src.log_scales[i]),
        to_vec3d(src.means[j]), covariance(src.rotations[j], src.log_scales[j]),
    )  # fmt: skip


@wp.func
def logit_of_log_alpha(log_alpha: wp.float64):
    """logit(alpha) from log alpha, clamped to [-LOGIT_LIMIT, MERGED_LOGIT_MAX]."""
    logit = wp.float32(MERGED_LOGIT_MAX)
    if log_alpha < wp.float64(0.0):
        logit = wp.float32(log_alpha - log64(wp.max(wp.float64(1.0) - exp64(log_alpha), wp.float64(1e-300))))
    return wp.clamp(logit, -LOGIT_LIMIT, MERGED_LOGIT_MAX)


@wp.func
def log_area(log_scale: wp.vec3):
    """log(s0 s1 + s0 s2 + s1 s2): the ellipsoid's surface-area proxy, from log scales."""
    a = wp.float64(log_scale[0]) + wp.float64(log_scale[1])
    b = wp.float64(log_scale[0]) + wp.float64(log_scale[2])
    c = wp.float64(log_scale[1]) + wp.float64(log_scale[2])
    m = wp.max(a, wp.max(b, c))
    return m + log64(exp64(a - m) + exp64(b - m) + exp64(c - m))


@wp.func
def log_area_mass(opacity_logit: float, log_scale: wp.vec3):
    """log w = log alpha + log(s0 s1 + s0 s2 + s1 s2): the area operator's weight."""
    return log_sigmoid(wp.float64(opacity_logit)) + log_area(log_scale)


@wp.func
def log_footprint(log_scale: wp.vec3):
    """log(s_a s_b), the product of the two largest scales: the splat's face-on footprint."""
    a = wp.float64(log_scale[0]) + wp.float64(log_scale[1])
    b = wp.float64(log_scale[0]) + wp.float64(log_scale[2])
    c = wp.float64(log_scale[1]) + wp.float64(log_scale[2])
    return wp.max(a, wp.max(b, c))


@wp.func
def log_coverage_mass(opacity_logit: float, log_scale: wp.vec3):
    """log w = log alpha + log(s_a s_b): the coverage operator's weight."""
    return log_sigmoid(wp.float64(opacity_logit)) + log_footprint(log_scale)


@wp.func
def coverage_terms(opacity_logit: float, log_scale: wp.vec3):
    """A splat's own terms of the coverage merge: its opacity alpha and the log of its weight
    alpha s_a s_b (``log_coverage_mass``). The merge computes them here for its pair; the field cost
    once a pass for every splat (``field_cost.splat_terms``), with this same function."""
    return sigmoid64(wp.float64(opacity_logit)), log_coverage_mass(opacity_logit, log_scale)


@wp.func
def projected_footprint(cov: wp.mat33d, c0: wp.vec3d, c1: wp.vec3d):
    """sqrt(det) of the covariance's 2x2 block in the plane spanned by the unit vectors c0, c1: the
    footprint (up to 2 pi) of its splat seen along c0 x c1."""
    a00 = wp.dot(c0, cov * c0)
    a01 = wp.dot(c0, cov * c1)
    a11 = wp.dot(c1, cov * c1)
    return wp.sqrt(wp.max(a00 * a11 - a01 * a01, wp.float64(0.0)))


@wp.func
def mpmm_merged(i: int, j: int, src: Splats):
    """MPMM's merged splat of the pair (NanoGS eq. 6-9): mass weights w = (2 pi)^{3/2} alpha prod s;
    returns (pi, mu_m, Sigma_m, opacity logit by the over rule)."""
    pi = first_weight(log_mass(src.opacities[i], src.log_scales[i]), log_mass(src.opacities[j], src.log_scales[j]))
    mu_m, cov_m = pair_moments(i, j, pi, src)
    return pi, mu_m, cov_m, over_opacity_logit(src.opacities[i], src.opacities[j])


@wp.kernel
def mass_preserving_moment_matching(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    src: Splats,
    out: Splats,
):
    """MPMM (NanoGS eq. 6-9): mass weights w = (2 pi)^{3/2} alpha prod s; mass-weighted mean,
    covariance (within-splat average + between-mean dispersion), features and extras; opacity by
    the over rule."""
    p = wp.tid()
    i = int(pair_i[p])
    j = int(pair_j[p])
    row = int(destination[i])
    pi, mu_m, cov_m, logit_m = mpmm_merged(i, j, src)
    out.opacities[row] = logit_m
    blend_appearance(i, j, pi, row, src, out)
    write_gaussian(row, mu_m, cov_m, out)


@wp.kernel
def area_weighted_moment_matching(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    src: Splats,
    out: Splats,
):
    """Area-weighted moment matching (as hierarchical 3DGS weights its merges): weights
    w = alpha (s0 s1 + s0 s2 + s1 s2); w-weighted mean, covariance, features and extras; merged
    opacity alpha_m = (w_i + w_j) / area_m (the weighted mass conserved), clamped to (0, 1)."""
    p = wp.tid()
    i = int(pair_i[p])
    j = int(pair_j[p])
    row = int(destination[i])
    log_w_i = log_area_mass(src.opacities[i], src.log_scales[i])
    log_w_j = log_area_mass(src.opacities[j], src.log_scales[j])
    pi = first_weight(log_w_i, log_w_j)
    mu_m, cov_m = pair_moments(i, j, pi, src)
    blend_appearance(i, j, pi, row, src, out)
    log_scale_m = write_gaussian(row, mu_m, cov_m, out)
    log_w_m = log_w_i - log_sigmoid(log_w_i - log_w_j)  # log(w_i + w_j) = log w_i - log pi
    out.opacities[row] = logit_of_log_alpha(log_w_m - log_area(log_scale_m))


@wp.func
def coverage_moments(
    i: int, j: int, src: Splats, cov_i: wp.mat33d, cov_j: wp.mat33d, log_w_i: wp.float64, log_w_j: wp.float64
):
    """The coverage operator's weighted moment match (``coverage_merged``' first step): pi, mu_i,
    mu_j, mu_m and Sigma_m."""
    pi = first_weight(log_w_i, log_w_j)
    mu_i = to_vec3d(src.means[i])
    mu_j = to_vec3d(src.means[j])
    mu_m, cov_m = moment_match(pi, mu_i, cov_i, mu_j, cov_j)
    return pi, mu_i, mu_j, mu_m, cov_m


@wp.func
def coverage_shaped(
    values: wp.vec3d, frame: wp.mat33d, mu_i: wp.vec3d, mu_j: wp.vec3d, mu_m: wp.vec3d, cov_i: wp.mat33d, cov_j: wp.mat33d,
    a_i: wp.float64, a_j: wp.float64, growth: float,
):  # fmt: skip
    """The rest of ``coverage_merged`` given Sigma_m's eigenvalues and frame: the face plane grown,
    the opacity fitted; returns (eigenvalues, alpha_m, own, cross, comp)."""
    c0 = wp.vec3d(frame[0, 0], frame[1, 0], frame[2, 0])
    c1 = wp.vec3d(frame[0, 1], frame[1, 1], frame[2, 1])
    coverage = a_i * projected_footprint(cov_i, c0, c1) + a_j * projected_footprint(cov_j, c0, c1)
    ratio = coverage / wp.sqrt(wp.max(values[0] * values[1], wp.float64(1e-300)))
    if ratio > wp.float64(1.0):
        grow = pow64(ratio, wp.float64(growth))
        values = wp.vec3d(values[0] * grow, values[1] * grow, values[2])  # the frame and the order stay
    own, cross, comp = pair_view_overlaps(frame, values, mu_i, mu_j, mu_m, cov_i, cov_j)
    alpha = wp.min(field_opacity(a_i, a_j, own, cross), wp.float64(MERGED_ALPHA_MAX))
    return values, alpha, own, cross, comp


@wp.func
def coverage_merged(
    i: int, j: int, src: Splats, cov_i: wp.mat33d, cov_j: wp.mat33d, a_i: wp.float64, a_j: wp.float64,
    log_w_i: wp.float64, log_w_j: wp.float64, growth: float,
):
    """The coverage operator's merged splat: weights w = alpha s_a s_b (face-on footprint). With
    (c0, c1) the merged splat's two major axes (its face plane) and F_k = sqrt(det) of splat k's
    covariance projected onto that plane, the pair covers C = alpha_i F_i + alpha_j F_j there and the
    merged splat F_m = s0 s1; where C / F_m > 1, the variances along c0 and c1 grow by
    (C / F_m)^growth. The opacity is then the one that best keeps the pair's opacity field seen along
    each of the merged splat's three axes (``field_opacity``), at most MERGED_ALPHA_MAX.
    ``cov_i``, ``cov_j``: the pair's covariances; ``a_i``, ``a_j``: their opacities (``sigmoid64``);
    ``log_w_i``, ``log_w_j``: their weights' logs (``coverage_terms``). Returns (pi, mu_m, eigenvalues, frame, alpha_m,
    own, cross, comp): the overlap sums of ``view_overlaps``, which the field cost reuses.
    The frame comes from the float64 Jacobi sweep, whose arithmetic (and sqrt) rounds alike on every
    device, so CPU and CUDA merges agree bit for bit."""
    pi, mu_i, mu_j, mu_m, cov_m = coverage_moments(i, j, src, cov_i, cov_j, log_w_i, log_w_j)
    values, frame = symmetric_eigen(cov_m)
    values, alpha, own, cross, comp = coverage_shaped(values, frame, mu_i, mu_j, mu_m, cov_i, cov_j, a_i, a_j, growth)
    return pi, mu_m, values, frame, alpha, own, cross, comp


@wp.kernel
def coverage_moment_matching(
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    destination: wp.array(dtype=wp.int32),
    src: Splats,
    out: Splats,
    growth: float,
):
    """Coverage moment matching (``coverage_merged``): w-weighted mean, covariance, features and
    extras; the face plane grown where the pair covers more than the merged footprint; the opacity
    fitted to the pair's field over three views."""
    p = wp.tid()
    i = int(pair_i[p])
    j = int(pair_j[p])
    row = int(destination[i])
    cov_i = covariance(src.rotations[i], src.log_scales[i])
    cov_j = covariance(src.rotations[j], src.log_scales[j])
    a_i, log_w_i = coverage_terms(src.opacities[i], src.log_scales[i])
    a_j, log_w_j = coverage_terms(src.opacities[j], src.log_scales[j])
    pi, mu_m, values, frame, alpha, own, cross, comp = coverage_merged(i, j, src, cov_i, cov_j, a_i, a_j, log_w_i, log_w_j, growth)
    blend_appearance(i, j, pi, row, src, out)
    store_gaussian(row, mu_m, values, frame, out)
    out.opacities[row] = logit_of_log_alpha(log64(wp.max(alpha, wp.float64(1e-300))))

