"""Edge costs C(i, j) = lambda_geo D_geo(i, j) + lambda_app ||f_i - f_j||^2 (NanoGS eq. 1)."""

import warp as wp

from .merge import log_area_mass
from .splat_math import LOG_2PI, covariance, first_weight, log_mass, moment_match, rotation_matrix, to_vec3d

wp.set_module_options({"enable_backward": False})

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
def log_normal_axes(x: wp.vec3d, mu: wp.vec3d, rot: wp.mat33d, log_scale: wp.vec3):
    """log N(x; mu, R diag(s)^2 R^T), evaluated in the splat's own axes."""
    local = wp.transpose(rot) * (x - mu)
    m = wp.float64(0.0)
    log_det_half = wp.float64(0.0)
    for k in range(3):
        ls = wp.float64(log_scale[k])
        u = local[k] * wp.exp(-ls)
        m += u * u
        log_det_half += ls
    return wp.float64(-0.5) * m - log_det_half - wp.float64(1.5) * wp.float64(LOG_2PI)


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
def log_normal_cholesky(x: wp.vec3d, mu: wp.vec3d, l: wp.mat33d):
    """log N(x; mu, L L^T) with L lower triangular."""
    d = x - mu
    y0 = d[0] / l[0, 0]
    y1 = (d[1] - l[1, 0] * y0) / l[1, 1]
    y2 = (d[2] - l[2, 0] * y0 - l[2, 1] * y1) / l[2, 2]
    log_det_half = wp.log(l[0, 0]) + wp.log(l[1, 1]) + wp.log(l[2, 2])
    return (
        wp.float64(-0.5) * (y0 * y0 + y1 * y1 + y2 * y2) - log_det_half - wp.float64(1.5) * wp.float64(LOG_2PI)
    )


@wp.func
def scales(log_scale: wp.vec3):
    return wp.vec3d(
        wp.exp(wp.float64(log_scale[0])), wp.exp(wp.float64(log_scale[1])), wp.exp(wp.float64(log_scale[2]))
    )


@wp.func
def log_add(a: wp.float64, b: wp.float64):
    """log(exp(a) + exp(b))."""
    m = wp.max(a, b)
    return m + wp.log(wp.exp(a - m) + wp.exp(b - m))


@wp.func
def finite_cost(c: wp.float64):
    out = wp.float32(c) + wp.float32(0.0)  # + 0 turns -0 into +0, so ties sort by edge
    if not wp.isfinite(out):
        out = wp.float32(UNMERGEABLE)
    return out


@wp.func
def mixture_divergence(
    pi: wp.float64,
    i: int,
    j: int,
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    samples: wp.array(dtype=wp.vec4),
):
    """Monte Carlo KL(p~ || q_m) of the normalised mixture p~ = pi N_i + (1 - pi) N_j against its
    moment-matched Gaussian q_m (NanoGS eq. 5 and Appendix A, eq. 12), and whether q_m is valid.
    Each sample (z, u) is shared by every edge (common random numbers): x = mu_i + R_i (s_i * z)
    if u < pi, else from splat j."""
    log_pi = wp.log(pi)
    log_pj = wp.log(wp.float64(1.0) - pi)
    mu_i = to_vec3d(means[i])
    mu_j = to_vec3d(means[j])
    rot_i = rotation_matrix(rotations[i])
    rot_j = rotation_matrix(rotations[j])
    mu_m, cov_m = moment_match(
        pi, mu_i, covariance(rotations[i], log_scales[i]), mu_j, covariance(rotations[j], log_scales[j])
    )
    l_m, ok = cholesky(cov_m)
    divergence = wp.float64(0.0)
    if not ok:
        return divergence, ok
    for s in range(samples.shape[0]):
        zu = samples[s]
        z = wp.vec3d(wp.float64(zu[0]), wp.float64(zu[1]), wp.float64(zu[2]))
        x = wp.vec3d()
        if wp.float64(zu[3]) < pi:
            x = mu_i + rot_i * wp.cw_mul(z, scales(log_scales[i]))
        else:
            x = mu_j + rot_j * wp.cw_mul(z, scales(log_scales[j]))
        log_mixture = log_add(
            log_pi + log_normal_axes(x, mu_i, rot_i, log_scales[i]),
            log_pj + log_normal_axes(x, mu_j, rot_j, log_scales[j]),
        )
        divergence += log_mixture - log_normal_cholesky(x, mu_m, l_m)
    return divergence / wp.float64(samples.shape[0]), ok


@wp.kernel
def idivergence_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    samples: wp.array(dtype=wp.vec4),
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
):
    """Per splat, once per pass (every edge reads two): Sigma and w = alpha (s0 s1 + s0 s2 + s1 s2)."""
    i = wp.tid()
    covariances[i] = covariance(rotations[i], log_scales[i])
    weights[i] = wp.exp(log_area_mass(opacities[i], log_scales[i]))


@wp.func
def mass_power(w: wp.float64, exponent: float):
    """w^exponent; the default exponent 1/4 as two square roots."""
    if exponent == 0.25:
        return wp.sqrt(wp.sqrt(w))
    if exponent == 0.0:
        return wp.float64(1.0)
    return wp.exp(wp.float64(exponent) * wp.log(w))


@wp.func
def log_det_positive(a: wp.mat33d):
    """log det of a symmetric matrix and whether it is positive definite (Sylvester: every leading
    minor positive)."""
    m1 = a[0, 0]
    m2 = m1 * a[1, 1] - a[0, 1] * a[1, 0]
    det = wp.determinant(a)
    ok = m1 > wp.float64(0.0) and m2 > wp.float64(0.0) and det > wp.float64(0.0)
    return wp.log(wp.max(det, wp.float64(1e-300))), ok


@wp.func
def log_det_scales(log_scale: wp.vec3):
    """log det Sigma = 2 sum_k log s_k."""
    return wp.float64(2.0) * (wp.float64(log_scale[0]) + wp.float64(log_scale[1]) + wp.float64(log_scale[2]))


@wp.kernel
def runnalls_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    means: wp.array(dtype=wp.vec3),
    log_scales: wp.array(dtype=wp.vec3),
    covariances: wp.array(dtype=wp.mat33d),
    weights: wp.array(dtype=wp.float64),
    features: wp.array2d(dtype=float),
    lambda_geo: float,
    lambda_app: float,
    mass_exponent: float,
    costs: wp.array(dtype=float),
):
    """W^gamma [lambda_geo B(i, j) + lambda_app 4 pi (1 - pi) ||f_i - f_j||^2], deterministic and >= 0:
    weights w = alpha (s0 s1 + s0 s2 + s1 s2) (the area operator's), W = w_i + w_j,
    pi = w_i / W, and B = 1/2 [log det Sigma_m - pi log det Sigma_i - (1 - pi) log det Sigma_j],
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
    bound = wp.float64(0.5) * (log_det_m - pi * log_det_scales(log_scales[i]) - (one - pi) * log_det_scales(log_scales[j]))
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
def draw_common_samples(seed: int, pass_index: int, samples: wp.array(dtype=wp.vec4)):
    """Common random numbers of one pass: z ~ N(0, I_3) and u ~ U[0, 1) per sample."""
    s = wp.tid()
    state = wp.rand_init(seed, pass_index * samples.shape[0] + s)
    samples[s] = wp.vec4(wp.randn(state), wp.randn(state), wp.randn(state), wp.randf(state))
