"""Float64 splat geometry shared by the cost and merge kernels.

A splat is N(mu, Sigma) with Sigma = R diag(s)^2 R^T, R from its unit quaternion (Warp's x, y, z, w
order) and s = exp(log_scale); its opacity alpha = sigmoid(logit) and its mass (NanoGS eq. 4)
w = (2 pi)^{3/2} alpha prod_k s_k, used here as log w.

Degenerate covariances. Every covariance the costs and the merge operators work with has each
eigenvalue at least RIDGE = 1e-10 times its trace (a thickness at least 1e-5 of the largest
scale): a splat's own variances along its axes are floored at RIDGE times their sum
(``axis_variances``), and a moment match, whose between-mean dispersion can make a pair of thin
splats' match thinner relative to its size than either of them, adds RIDGE times that dispersion
to every variance (``moment_match``). float64 resolves a variance to about 1e-16 of the largest,
so without a floor a very flat or thin splat (log-scales 17 apart; inputs may hold them 200 apart)
has a determinant, a Cholesky factor and a smallest eigenvalue made of rounding noise: a cost that
is noise, or none at all (such edges used to be marked unmergeable and merged last). With it,
every factorisation resolves the smallest eigenvalue to about 1e-6, and no float32 renderer can
tell the difference: its covariances resolve no better than about 1e-7 of their largest variance
(a thickness of 2e-4). The floor is idempotent in effect: a merged splat stores the eigenvalues of
its floored covariance, which the next pass's floor leaves as they are (to 1e-10), and two
identical splats merge into themselves. Splats that are never merged keep their log-scales.
"""

import warp as wp

from .options import PORTABLE
from .portable_math import exp64, log64

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

LOG_2PI = wp.constant(1.8378770664093453)
RIDGE = wp.constant(wp.float64(1.0e-10))  # variance floor, relative to the trace (module docstring)


@wp.struct
class Splats:
    """A splat set's arrays as kernels see them (``SplatSet.kernel_view()``)."""

    means: wp.array(dtype=wp.vec3)
    rotations: wp.array(dtype=wp.quat)
    log_scales: wp.array(dtype=wp.vec3)
    opacities: wp.array(dtype=float)
    features: wp.array2d(dtype=float)
    extras: wp.array2d(dtype=float)
    integer_extras: wp.array2d(dtype=wp.int64)


@wp.func
def to_vec3d(v: wp.vec3):
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def rotation_matrix(q: wp.quat):
    """Rotation matrix of the quaternion (x, y, z, w), normalised in float64: orthogonal to float64
    rounding, where the float32 quaternion is unit only to about 1e-7 (which would blur a thin axis
    with 1e-7 of the largest variance; the variance floor is 1e-10)."""
    x = wp.float64(q[0])
    y = wp.float64(q[1])
    z = wp.float64(q[2])
    w = wp.float64(q[3])
    one = wp.float64(1.0)
    two = wp.float64(2.0) / (((x * x + y * y) + z * z) + w * w)
    return wp.mat33d(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
    )  # fmt: skip


@wp.func
def frame_covariance(r: wp.mat33d, d: wp.vec3d):
    """R diag(d) R^T, exactly symmetric: entry (a, b) = (R_a0 d_0) R_b0 + (R_a1 d_1) R_b1 + (R_a2 d_2) R_b2
    in that order. Written out because Warp's matrix product calls fma(), which is correctly rounded
    everywhere but a library call per term on a CPU without FMA in its baseline."""
    m = wp.mat33d()
    for a in range(3):
        u0 = r[a, 0] * d[0]
        u1 = r[a, 1] * d[1]
        u2 = r[a, 2] * d[2]
        for b in range(a, 3):
            v = u0 * r[b, 0] + u1 * r[b, 1] + u2 * r[b, 2]
            m[a, b] = v
            m[b, a] = v
    return m


@wp.func
def axis_variances(log_scale: wp.vec3):
    """The splat's variances along its own axes, floored: max(s_k^2, RIDGE (s_0^2 + s_1^2 + s_2^2))."""
    v0 = exp64(wp.float64(2.0) * wp.float64(log_scale[0]))
    v1 = exp64(wp.float64(2.0) * wp.float64(log_scale[1]))
    v2 = exp64(wp.float64(2.0) * wp.float64(log_scale[2]))
    floor = RIDGE * ((v0 + v1) + v2)
    return wp.vec3d(wp.max(v0, floor), wp.max(v1, floor), wp.max(v2, floor))


@wp.func
def log_det_axes(variances: wp.vec3d):
    """log det of the covariance with these axis variances: one log of their product (each at most
    3 e^200 and at least e^-200: the product stays finite and normal)."""
    return log64((variances[0] * variances[1]) * variances[2])


@wp.func
def covariance(q: wp.quat, log_scale: wp.vec3):
    """Sigma = R diag(s^2) R^T, floored: R diag(axis_variances) R^T."""
    return frame_covariance(rotation_matrix(q), axis_variances(log_scale))


@wp.func
def log_sigmoid(x: wp.float64):
    """log(sigmoid(x)), stable for large |x|."""
    return -(wp.max(-x, wp.float64(0.0)) + log64(wp.float64(1.0) + exp64(-wp.abs(x))))


@wp.func
def log_mass(opacity_logit: float, log_scale: wp.vec3):
    """log w = 3/2 log(2 pi) + log alpha + sum_k log s_k (NanoGS eq. 4)."""
    return (
        wp.float64(1.5) * wp.float64(LOG_2PI)
        + log_sigmoid(wp.float64(opacity_logit))
        + wp.float64(log_scale[0])
        + wp.float64(log_scale[1])
        + wp.float64(log_scale[2])
    )


@wp.func
def first_weight(log_w_i: wp.float64, log_w_j: wp.float64):
    """pi = w_i / (w_i + w_j), computed from log masses."""
    return wp.float64(1.0) / (wp.float64(1.0) + exp64(log_w_j - log_w_i))


@wp.func
def moment_match(pi: wp.float64, mu_i: wp.vec3d, cov_i: wp.mat33d, mu_j: wp.vec3d, cov_j: wp.mat33d):
    """Weighted moment matching of a two-component mixture (NanoGS eq. 7-8):
    mu_m = pi mu_i + (1 - pi) mu_j,
    Sigma_m = pi (Sigma_i + d_i d_i^T) + (1 - pi) (Sigma_j + d_j d_j^T) + RIDGE D I,  d = mu - mu_m,
    with D = pi |d_i|^2 + (1 - pi) |d_j|^2 the dispersion's trace: the floor of the module docstring
    (the pair's own covariances carry theirs)."""
    pj = wp.float64(1.0) - pi
    mu_m = pi * mu_i + pj * mu_j
    d_i = mu_i - mu_m
    d_j = mu_j - mu_m
    cov_m = pi * (cov_i + wp.outer(d_i, d_i)) + pj * (cov_j + wp.outer(d_j, d_j))
    t = RIDGE * (pi * wp.dot(d_i, d_i) + pj * wp.dot(d_j, d_j))
    cov_m[0, 0] = cov_m[0, 0] + t
    cov_m[1, 1] = cov_m[1, 1] + t
    cov_m[2, 2] = cov_m[2, 2] + t
    return mu_m, cov_m


@wp.func
def symmetric_eigen(a: wp.mat33d):
    """Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi in float64.

    Returns (eigenvalues, eigenvectors as columns) sorted by decreasing eigenvalue, the frame
    right-handed (det = +1)."""
    v = wp.identity(n=3, dtype=wp.float64)
    one = wp.float64(1.0)
    for _sweep in range(12):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= wp.float64(1e-36) * diag:
            break
        for plane in range(3):
            # the rotation in plane (p, q) that zeroes a[p, q]; r is the third axis
            p = wp.where(plane == 2, 1, 0)
            q = wp.where(plane == 0, 1, 2)
            r = 2 - plane
            apq = a[p, q]
            if wp.abs(apq) > wp.float64(1e-300):
                tau = (a[q, q] - a[p, p]) / (wp.float64(2.0) * apq)
                t = one / (wp.abs(tau) + wp.sqrt(one + tau * tau))
                if tau < wp.float64(0.0):
                    t = -t
                c = one / wp.sqrt(one + t * t)
                s = t * c
                # a <- J^T a J with J = I + (c - 1)(e_p e_p^T + e_q e_q^T) + s (e_p e_q^T - e_q e_p^T)
                arp = a[r, p]
                arq = a[r, q]
                a[p, p] = a[p, p] - t * apq
                a[q, q] = a[q, q] + t * apq
                a[p, q] = wp.float64(0.0)
                a[q, p] = wp.float64(0.0)
                a[r, p] = c * arp - s * arq
                a[p, r] = a[r, p]
                a[r, q] = s * arp + c * arq
                a[q, r] = a[r, q]
                # v <- v J
                for row in range(3):
                    vp = v[row, p]
                    vq = v[row, q]
                    v[row, p] = c * vp - s * vq
                    v[row, q] = s * vp + c * vq
    e0 = a[0, 0]
    e1 = a[1, 1]
    e2 = a[2, 2]
    c0 = wp.vec3d(v[0, 0], v[1, 0], v[2, 0])
    c1 = wp.vec3d(v[0, 1], v[1, 1], v[2, 1])
    c2 = wp.vec3d(v[0, 2], v[1, 2], v[2, 2])
    # sort descending with a three-element network
    if e0 < e1:
        e0, e1 = e1, e0
        c0, c1 = c1, c0
    if e1 < e2:
        e1, e2 = e2, e1
        c1, c2 = c2, c1
    if e0 < e1:
        e0, e1 = e1, e0
        c0, c1 = c1, c0
    if wp.dot(wp.cross(c0, c1), c2) < wp.float64(0.0):
        c2 = -c2
    frame = wp.mat33d(
        c0[0], c1[0], c2[0],
        c0[1], c1[1], c2[1],
        c0[2], c1[2], c2[2],
    )  # fmt: skip
    return wp.vec3d(e0, e1, e2), frame


@wp.func
def quaternion_from_frame(r: wp.mat33d):
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method, float64)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    one = wp.float64(1.0)
    x = wp.float64(0.0)
    y = wp.float64(0.0)
    z = wp.float64(0.0)
    w = wp.float64(1.0)
    if tr > r[0, 0] and tr > r[1, 1] and tr > r[2, 2]:
        s = wp.sqrt(one + tr) * wp.float64(2.0)
        w = wp.float64(0.25) * s
        x = (r[2, 1] - r[1, 2]) / s
        y = (r[0, 2] - r[2, 0]) / s
        z = (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = wp.sqrt(one + r[0, 0] - r[1, 1] - r[2, 2]) * wp.float64(2.0)
        w = (r[2, 1] - r[1, 2]) / s
        x = wp.float64(0.25) * s
        y = (r[0, 1] + r[1, 0]) / s
        z = (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = wp.sqrt(one + r[1, 1] - r[0, 0] - r[2, 2]) * wp.float64(2.0)
        w = (r[0, 2] - r[2, 0]) / s
        x = (r[0, 1] + r[1, 0]) / s
        y = wp.float64(0.25) * s
        z = (r[1, 2] + r[2, 1]) / s
    else:
        s = wp.sqrt(one + r[2, 2] - r[0, 0] - r[1, 1]) * wp.float64(2.0)
        w = (r[1, 0] - r[0, 1]) / s
        x = (r[0, 2] + r[2, 0]) / s
        y = (r[1, 2] + r[2, 1]) / s
        z = wp.float64(0.25) * s
    n = wp.sqrt(x * x + y * y + z * z + w * w)
    if w < wp.float64(0.0):
        n = -n  # canonical sign: w >= 0
    return wp.quat(wp.float32(x / n), wp.float32(y / n), wp.float32(z / n), wp.float32(w / n))

