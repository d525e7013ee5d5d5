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
def jacobi_sweeps(a: wp.mat33d):
    """Cyclic Jacobi sweeps of a symmetric 3x3 matrix in float64, until the off-diagonal's square is
    at most 1e-36 times the diagonal's (at most 12 sweeps): (the diagonal, the accumulated rotation)."""
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
    return wp.vec3d(a[0, 0], a[1, 1], a[2, 2]), v


@wp.func
def sorted_frame(diagonal: wp.vec3d, v: wp.mat33d):
    """The eigenvalues ``diagonal`` sorted decreasing with their eigenvectors (the columns of v), the
    frame made right-handed (det = +1)."""
    e0 = diagonal[0]
    e1 = diagonal[1]
    e2 = diagonal[2]
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
def symmetric_eigen(a: wp.mat33d):
    """Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi in float64 (``jacobi_sweeps``).

    Returns (eigenvalues, eigenvectors as columns) sorted by decreasing eigenvalue, the frame
    right-handed (det = +1)."""
    diagonal, v = jacobi_sweeps(a)
    return sorted_frame(diagonal, v)


# Four symmetric matrices at once (``jacobi_sweeps_in_lanes``): on a CPU a thread runs one chain of
# dependent divisions and square roots at a time, and four independent ones fill its pipelines.
@wp.func
def lane_select(rotate: wp.vec4i, a: wp.vec4d, b: wp.vec4d):
    """Per lane: a where ``rotate`` is set, else b."""
    return wp.vec4d(
        wp.where(rotate[0] != 0, a[0], b[0]), wp.where(rotate[1] != 0, a[1], b[1]),
        wp.where(rotate[2] != 0, a[2], b[2]), wp.where(rotate[3] != 0, a[3], b[3]),
    )  # fmt: skip


@wp.func
def lane_sqrt(a: wp.vec4d):
    return wp.vec4d(wp.sqrt(a[0]), wp.sqrt(a[1]), wp.sqrt(a[2]), wp.sqrt(a[3]))


@wp.func
def lane_rotation(active: wp.vec4i, app: wp.vec4d, aqq: wp.vec4d, apq: wp.vec4d):
    """``jacobi_sweeps``' rotation per lane: whether the lane rotates (active, |a_pq| > 1e-300) and
    its (t, c, s), with the same operations (a lane that does not rotate computes and drops them)."""
    one = wp.vec4d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    rotate = wp.vec4i()
    t = wp.vec4d()
    tau = wp.cw_div(aqq - app, wp.float64(2.0) * apq)
    root = lane_sqrt(one + wp.cw_mul(tau, tau))
    for lane in range(4):
        rotate[lane] = wp.where(active[lane] != 0 and wp.abs(apq[lane]) > wp.float64(1e-300), 1, 0)
        t[lane] = one[lane] / (wp.abs(tau[lane]) + root[lane])
        if tau[lane] < wp.float64(0.0):
            t[lane] = -t[lane]
    c = wp.cw_div(one, lane_sqrt(one + wp.cw_mul(t, t)))
    return rotate, t, c, wp.cw_mul(t, c)


@wp.func
def lane_rotated(rotate: wp.vec4i, c: wp.vec4d, s: wp.vec4d, x_p: wp.vec4d, x_q: wp.vec4d):
    """(c x_p - s x_q, s x_p + c x_q) in the lanes that rotate; (x_p, x_q) in the others."""
    return (
        lane_select(rotate, wp.cw_mul(c, x_p) - wp.cw_mul(s, x_q), x_p),
        lane_select(rotate, wp.cw_mul(s, x_p) + wp.cw_mul(c, x_q), x_q),
    )


@wp.func
def lane_entries(m0: wp.mat33d, m1: wp.mat33d, m2: wp.mat33d, m3: wp.mat33d, r: int, c: int):
    return wp.vec4d(m0[r, c], m1[r, c], m2[r, c], m3[r, c])


@wp.func
def lane_matrix(lane: int, v00: wp.vec4d, v01: wp.vec4d, v02: wp.vec4d, v10: wp.vec4d, v11: wp.vec4d, v12: wp.vec4d,
                v20: wp.vec4d, v21: wp.vec4d, v22: wp.vec4d):  # fmt: skip
    return wp.mat33d(
        v00[lane], v01[lane], v02[lane],
        v10[lane], v11[lane], v12[lane],
        v20[lane], v21[lane], v22[lane],
    )  # fmt: skip


@wp.func
def jacobi_sweeps_in_lanes(m0: wp.mat33d, m1: wp.mat33d, m2: wp.mat33d, m3: wp.mat33d):
    """``jacobi_sweeps`` of four symmetric matrices, lane by lane the same operations in the same
    order (so the same bits): each entry of the upper triangle and of the rotation is a vec4d of
    the four matrices' entries. A lane stops where its own matrix would; the sweeps go on while any
    lane is active. Returns (diagonal, rotation) of m0, then of m1, m2, m3."""
    a00 = lane_entries(m0, m1, m2, m3, 0, 0)
    a01 = lane_entries(m0, m1, m2, m3, 0, 1)
    a02 = lane_entries(m0, m1, m2, m3, 0, 2)
    a11 = lane_entries(m0, m1, m2, m3, 1, 1)
    a12 = lane_entries(m0, m1, m2, m3, 1, 2)
    a22 = lane_entries(m0, m1, m2, m3, 2, 2)
    zero = wp.vec4d()
    one = wp.vec4d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    v00 = one
    v01 = zero
    v02 = zero
    v10 = zero
    v11 = one
    v12 = zero
    v20 = zero
    v21 = zero
    v22 = one
    active = wp.vec4i(1, 1, 1, 1)
    for _sweep in range(12):
        off = wp.cw_mul(a01, a01) + wp.cw_mul(a02, a02) + wp.cw_mul(a12, a12)
        diag = wp.cw_mul(a00, a00) + wp.cw_mul(a11, a11) + wp.cw_mul(a22, a22)
        for lane in range(4):
            if off[lane] <= wp.float64(1e-36) * diag[lane]:
                active[lane] = 0
        if active[0] + active[1] + active[2] + active[3] == 0:
            break
        # plane (0, 1), third axis 2 (each result named first: Warp carries a loop's variables
        # through plain assignments)
        rotate, t, c, s = lane_rotation(active, a00, a11, a01)
        n00 = lane_select(rotate, a00 - wp.cw_mul(t, a01), a00)
        n11 = lane_select(rotate, a11 + wp.cw_mul(t, a01), a11)
        n02, n12 = lane_rotated(rotate, c, s, a02, a12)
        w00, w01 = lane_rotated(rotate, c, s, v00, v01)
        w10, w11 = lane_rotated(rotate, c, s, v10, v11)
        w20, w21 = lane_rotated(rotate, c, s, v20, v21)
        a00 = n00
        a11 = n11
        a01 = lane_select(rotate, zero, a01)
        a02 = n02
        a12 = n12
        v00 = w00
        v01 = w01
        v10 = w10
        v11 = w11
        v20 = w20
        v21 = w21
        # plane (0, 2), third axis 1
        rotate, t, c, s = lane_rotation(active, a00, a22, a02)
        n00 = lane_select(rotate, a00 - wp.cw_mul(t, a02), a00)
        n22 = lane_select(rotate, a22 + wp.cw_mul(t, a02), a22)
        n01, n12 = lane_rotated(rotate, c, s, a01, a12)
        w00, w02 = lane_rotated(rotate, c, s, v00, v02)
        w10, w12 = lane_rotated(rotate, c, s, v10, v12)
        w20, w22 = lane_rotated(rotate, c, s, v20, v22)
        a00 = n00
        a22 = n22
        a02 = lane_select(rotate, zero, a02)
        a01 = n01
        a12 = n12
        v00 = w00
        v02 = w02
        v10 = w10
        v12 = w12
        v20 = w20
        v22 = w22
        # plane (1, 2), third axis 0
        rotate, t, c, s = lane_rotation(active, a11, a22, a12)
        n11 = lane_select(rotate, a11 - wp.cw_mul(t, a12), a11)
        n22 = lane_select(rotate, a22 + wp.cw_mul(t, a12), a22)
        n01, n02 = lane_rotated(rotate, c, s, a01, a02)
        w01, w02 = lane_rotated(rotate, c, s, v01, v02)
        w11, w12 = lane_rotated(rotate, c, s, v11, v12)
        w21, w22 = lane_rotated(rotate, c, s, v21, v22)
        a11 = n11
        a22 = n22
        a12 = lane_select(rotate, zero, a12)
        a01 = n01
        a02 = n02
        v01 = w01
        v02 = w02
        v11 = w11
        v12 = w12
        v21 = w21
        v22 = w22
    return (
        wp.vec3d(a00[0], a11[0], a22[0]), lane_matrix(0, v00, v01, v02, v10, v11, v12, v20, v21, v22),
        wp.vec3d(a00[1], a11[1], a22[1]), lane_matrix(1, v00, v01, v02, v10, v11, v12, v20, v21, v22),
        wp.vec3d(a00[2], a11[2], a22[2]), lane_matrix(2, v00, v01, v02, v10, v11, v12, v20, v21, v22),
        wp.vec3d(a00[3], a11[3], a22[3]), lane_matrix(3, v00, v01, v02, v10, v11, v12, v20, v21, v22),
    )


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

