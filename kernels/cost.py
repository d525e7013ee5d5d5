"""Edge costs C(i, j) = lambda_geo D_geo(i, j) + lambda_app ||f_i - f_j||^2 (NanoGS eq. 1)."""

import warp as wp

from .merge import log_area_mass
from .options import PORTABLE
from .portable_math import exp64, log64, normal_from_uniforms
from .splat_math import (
    LOG_2PI,
    axis_variances,
    covariance,
    first_weight,
    frame_covariance,
    log_det_axes,
    log_mass,
    moment_match,
    rotation_matrix,
    to_vec3d,
)

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

# Finite stand-in for costs that cannot be evaluated (a degenerate merged covariance): such an edge
# sorts after every real one.
UNMERGEABLE = wp.constant(3.0e38)


@wp.func
def appearance_distance(features: wp.array2d(dtype=float), i: int, j: int):
    """D_app = ||f_i - f_j||^2 over every SH coefficient (NanoGS eq. 6)."""
    # four running sums: a single one would chain every addition on the one before
    d0 = wp.float64(0.0)
    d1 = wp.float64(0.0)
    d2 = wp.float64(0.0)
    d3 = wp.float64(0.0)
    count = features.shape[1]
    c = int(0)
    while c + 4 <= count:
        x0 = wp.float64(features[i, c] - features[j, c])
        x1 = wp.float64(features[i, c + 1] - features[j, c + 1])
        x2 = wp.float64(features[i, c + 2] - features[j, c + 2])
        x3 = wp.float64(features[i, c + 3] - features[j, c + 3])
        d0 += x0 * x0
        d1 += x1 * x1
        d2 += x2 * x2
        d3 += x3 * x3
        c += 4
    while c < count:
        x = wp.float64(features[i, c] - features[j, c])
        d0 += x * x
        c += 1
    return (d0 + d1) + (d2 + d3)


@wp.func
def log_normal_axes(x: wp.vec3d, mu: wp.vec3d, rot: wp.mat33d, inv_sd: wp.vec3d, log_det: wp.float64):
    """log N(x; mu, R diag(v) R^T), evaluated in the splat's own axes: ``inv_sd`` = 1 / sqrt(v),
    ``log_det`` = log det."""
    local = wp.transpose(rot) * (x - mu)
    m = wp.float64(0.0)
    for k in range(3):
        u = local[k] * inv_sd[k]
        m += u * u
    return wp.float64(-0.5) * m - wp.float64(0.5) * log_det - wp.float64(1.5) * wp.float64(LOG_2PI)


@wp.func
def cholesky(a: wp.mat33d):
    """Lower Cholesky factor of a symmetric matrix and whether it is positive definite."""
    l = wp.mat33d()
    ok = True
    l00 = a[0, 0]
    if l00 <= wp.float64(0.0):
        ok = False
        return l, ok
    l00 = wp.sqrt(l00)
    l10 = a[1, 0] / l00
    l20 = a[2, 0] / l00
    d1 = a[1, 1] - l10 * l10
    if d1 <= wp.float64(0.0):
        ok = False
        return l, ok
    l11 = wp.sqrt(d1)
    l21 = (a[2, 1] - l20 * l10) / l11
    d2 = a[2, 2] - l20 * l20 - l21 * l21
    if d2 <= wp.float64(0.0):
        ok = False
        return l, ok
    l22 = wp.sqrt(d2)
    l = wp.mat33d(
        l00, wp.float64(0.0), wp.float64(0.0),
        l10, l11, wp.float64(0.0),
        l20, l21, l22,
    )  # fmt: skip
    return l, ok


@wp.func
def log_add(a: wp.float64, b: wp.float64):
    """log(exp(a) + exp(b))."""
    m = wp.max(a, b)
    return m + log64(exp64(a - m) + exp64(b - m))


@wp.func
def finite_cost(c: wp.float64):
    out = wp.float32(c) + wp.float32(0.0)  # + 0 turns -0 into +0, so ties sort by edge
    if not wp.isfinite(out):
        out = wp.float32(UNMERGEABLE)
    return out


@wp.func
def entropy_cholesky(l: wp.mat33d):
    """-E_q[log q] = (3 log 2 pi + log det(L L^T) + 3) / 2, the entropy of N(mu, L L^T)."""
    log_det_half = log64(l[0, 0]) + log64(l[1, 1]) + log64(l[2, 2])
    return wp.float64(1.5) * (wp.float64(LOG_2PI) + wp.float64(1.0)) + log_det_half


@wp.func
def mixture_divergence(
    pi: wp.float64,
    i: int,
    j: int,
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    samples: wp.array(dtype=wp.vec3),
):
    """Monte Carlo KL(p~ || q_m) of the normalised mixture p~ = pi N_i + (1 - pi) N_j against its
    moment-matched Gaussian q_m (NanoGS eq. 5 and Appendix A, eq. 12), and whether q_m is valid.

    KL = E_p~[log p~] - E_p~[log q_m]. q_m has p~'s mean and covariance, so E_p~[-log q_m] is q_m's
    entropy, in closed form. E_p~[log p~] is sampled from both components with the same common
    normals z (shared by every edge): x_i = mu_i + R_i (sd_i * z) weighted pi and x_j likewise
    weighted 1 - pi, the draw of the component averaged out exactly; in each component's own
    density at its own point, -|z|^2 / 2, |z|^2 is replaced by its mean 3 (a control variate that
    is the same for every edge, so the ranking does not change, and a pair of identical splats costs
    exactly 0). Every Gaussian is the regularised one (``axis_variances``, ``moment_match``), as the
    merge operators see it."""
    log_pi = log64(pi)
    log_pj = log64(wp.float64(1.0) - pi)
    mu_i = to_vec3d(means[i])
    mu_j = to_vec3d(means[j])
    rot_i = rotation_matrix(rotations[i])
    rot_j = rotation_matrix(rotations[j])
    var_i = axis_variances(log_scales[i])
    var_j = axis_variances(log_scales[j])
    sd_i = wp.vec3d(wp.sqrt(var_i[0]), wp.sqrt(var_i[1]), wp.sqrt(var_i[2]))
    sd_j = wp.vec3d(wp.sqrt(var_j[0]), wp.sqrt(var_j[1]), wp.sqrt(var_j[2]))
    one = wp.float64(1.0)
    inv_sd_i = wp.vec3d(one / sd_i[0], one / sd_i[1], one / sd_i[2])
    inv_sd_j = wp.vec3d(one / sd_j[0], one / sd_j[1], one / sd_j[2])
    log_det_i = log_det_axes(var_i)
    log_det_j = log_det_axes(var_j)
    mu_m, cov_m = moment_match(pi, mu_i, frame_covariance(rot_i, var_i), mu_j, frame_covariance(rot_j, var_j))
    l_m, ok = cholesky(cov_m)
    if not ok:
        return wp.float64(0.0), ok
    log_mixture = wp.float64(0.0)
    for s in range(samples.shape[0]):
        z = to_vec3d(samples[s])
        x_i = mu_i + rot_i * wp.cw_mul(z, sd_i)
        x_j = mu_j + rot_j * wp.cw_mul(z, sd_j)
        at_i = log_add(
            log_pi + log_normal_axes(x_i, mu_i, rot_i, inv_sd_i, log_det_i),
            log_pj + log_normal_axes(x_i, mu_j, rot_j, inv_sd_j, log_det_j),
        )
        at_j = log_add(
            log_pi + log_normal_axes(x_j, mu_i, rot_i, inv_sd_i, log_det_i),
            log_pj + log_normal_axes(x_j, mu_j, rot_j, inv_sd_j, log_det_j),
        )
        log_mixture += pi * at_i + (one - pi) * at_j + wp.float64(0.5) * (wp.dot(z, z) - wp.float64(3.0))
    return log_mixture / wp.float64(samples.shape[0]) + entropy_cholesky(l_m), ok


@wp.kernel
def idivergence_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    samples: wp.array(dtype=wp.vec3),
    lambda_geo: float,
    lambda_app: float,
    costs: wp.array(dtype=float),
):
    """The paper's cost: Monte Carlo I-divergence I(p~_ij || q_m) between the normalised two-splat
    mixture (mass weights, NanoGS eq. 4) and its moment-matched Gaussian, + lambda_app D_app."""
    e = wp.tid()
    i = int(edge_i[e])
    j = int(edge_j[e])
    pi = first_weight(log_mass(opacities[i], log_scales[i]), log_mass(opacities[j], log_scales[j]))
    divergence, ok = mixture_divergence(pi, i, j, means, rotations, log_scales, samples)
    if not ok:
        costs[e] = wp.float32(UNMERGEABLE)
        return
    costs[e] = finite_cost(
        wp.float64(lambda_geo) * divergence + wp.float64(lambda_app) * appearance_distance(features, i, j)
    )


@wp.kernel
def runnalls_splat_terms(
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    covariances: wp.array(dtype=wp.mat33d),
    weights: wp.array(dtype=wp.float64),
    log_dets: wp.array(dtype=wp.float64),
):
    """Per splat, once per pass (every edge reads two): the regularised Sigma, its log det and
    w = alpha (s0 s1 + s0 s2 + s1 s2)."""
    i = wp.tid()
    variances = axis_variances(log_scales[i])
    covariances[i] = frame_covariance(rotation_matrix(rotations[i]), variances)
    log_dets[i] = log_det_axes(variances)
    weights[i] = exp64(log_area_mass(opacities[i], log_scales[i]))


@wp.func
def mass_power(w: wp.float64, exponent: float):
    """w^exponent; the default exponent 1/4 as two square roots."""
    if exponent == 0.25:
        return wp.sqrt(wp.sqrt(w))
    if exponent == 0.0:
        return wp.float64(1.0)
    return exp64(wp.float64(exponent) * log64(w))


@wp.func
def log_det_positive(a: wp.mat33d):
    """log det of a symmetric matrix from its LDL^T pivots (Gaussian elimination without pivoting,
    backward stable for a positive definite matrix: each pivot within a few ulp of tr(a) of its exact
    value, so a regularised covariance's are all positive), and whether every pivot is positive.
    The cofactor determinant would be noise for a needle: its two small eigenvalues multiply."""
    d0 = a[0, 0]
    ok = d0 > wp.float64(0.0)
    if not ok:
        return wp.float64(0.0), ok
    l10 = a[1, 0] / d0
    l20 = a[2, 0] / d0
    d1 = a[1, 1] - l10 * a[1, 0]
    ok = d1 > wp.float64(0.0)
    if not ok:
        return wp.float64(0.0), ok
    e21 = a[2, 1] - l20 * a[1, 0]
    d2 = (a[2, 2] - l20 * a[2, 0]) - (e21 / d1) * e21
    ok = d2 > wp.float64(0.0)
    return log64((d0 * d1) * d2), ok


@wp.kernel
def runnalls_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    covariances: wp.array(dtype=wp.mat33d),
    weights: wp.array(dtype=wp.float64),
    log_dets: wp.array(dtype=wp.float64),
    features: wp.array2d(dtype=float),
    lambda_geo: float,
    lambda_app: float,
    mass_exponent: float,
    costs: wp.array(dtype=float),
):
    """W^gamma [lambda_geo B(i, j) + lambda_app 4 pi (1 - pi) ||f_i - f_j||^2], deterministic and >= 0:
    weights w = alpha (s0 s1 + s0 s2 + s1 s2) (the area operator's), W = w_i + w_j,
    pi = w_i / W, and B = 1/2 [log det Sigma_m - pi log det Sigma_i - (1 - pi) log det Sigma_j]
    (every Sigma regularised, ``splat_math``),
    Runnalls' upper bound on KL(p~ || q_m) for the normalised pair and its moment match q_m
    (Runnalls 2007, Kullback-Leibler approach to Gaussian mixture reduction). 4 pi (1 - pi) makes
    absorbing a light splat into a heavy one cheap (the weighted colour variance of the pair,
    scaled to D_app for equal weights); gamma = ``mass_exponent`` (0: scale-free as the paper's)."""
    e = wp.tid()
    i = int(edge_i[e])
    j = int(edge_j[e])
    w_i = weights[i]
    w_j = weights[j]
    big_w = w_i + w_j
    pi = w_i / big_w
    mu_m, cov_m = moment_match(pi, to_vec3d(means[i]), covariances[i], to_vec3d(means[j]), covariances[j])
    log_det_m, ok = log_det_positive(cov_m)
    if not ok:
        costs[e] = wp.float32(UNMERGEABLE)
        return
    one = wp.float64(1.0)
    bound = wp.float64(0.5) * (log_det_m - pi * log_dets[i] - (one - pi) * log_dets[j])
    bound = wp.max(bound, wp.float64(0.0))
    app = wp.float64(4.0) * pi * (one - pi) * appearance_distance(features, i, j)
    costs[e] = finite_cost(mass_power(big_w, mass_exponent) * (wp.float64(lambda_geo) * bound + wp.float64(lambda_app) * app))


@wp.kernel
def mse_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    features: wp.array2d(dtype=float),
    lambda_geo: float,
    lambda_app: float,
    costs: wp.array(dtype=float),
):
    """The fast geometric surrogate of the NanoGS ablation: ||mu_i - mu_j||^2 + ||Sigma_i - Sigma_j||_F^2."""
    e = wp.tid()
    i = int(edge_i[e])
    j = int(edge_j[e])
    d = to_vec3d(means[i]) - to_vec3d(means[j])
    dc = covariance(rotations[i], log_scales[i]) - covariance(rotations[j], log_scales[j])
    frob = wp.float64(0.0)
    for r in range(3):
        for c in range(3):
            frob += dc[r, c] * dc[r, c]
    costs[e] = finite_cost(
        wp.float64(lambda_geo) * (wp.dot(d, d) + frob)
        + wp.float64(lambda_app) * appearance_distance(features, i, j)
    )


@wp.kernel
def draw_common_samples(seed: int, pass_index: int, samples: wp.array(dtype=wp.vec3)):
    """Common random numbers of one pass: z ~ N(0, I_3) per sample. Warp's randn uses float32 log
    and cos, which differ between the CPU and CUDA math libraries (and draws its two uniforms within
    one expression, in an order C++ leaves open): the normals here come from
    ``normal_from_uniforms`` (portable float64 Box-Muller), their uniforms drawn one statement at a
    time."""
    s = wp.tid()
    state = wp.rand_init(seed, pass_index * samples.shape[0] + s)
    z = wp.vec3()
    for c in range(3):
        u1 = wp.randf(state)
        u2 = wp.randf(state)
        z[c] = wp.float32(normal_from_uniforms(u1, u2))
    samples[s] = z
