"""The emitted field of splats seen along the three axes of a merged splat's frame.

Seen along an axis, each splat's covariance projected onto the plane of the other two axes is a
peak-one 2D Gaussian G, as a rasteriser draws it, and the product of two has a closed-form
integral. Working in the merged splat's frame F, splat k's projection onto the plane of axes
(u, v) is the (u, v) block of F^T Sigma_k F and its centre the (u, v) part of F^T (mu_k - mu_m):
one 3 x 3 change of basis per splat serves all three views.
"""

import warp as wp

from .options import PORTABLE
from .portable_math import exp64

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

PI = wp.constant(3.141592653589793)
TWO_PI = wp.constant(6.283185307179586)


@wp.func
def in_frame(frame: wp.mat33d, cov: wp.mat33d):
    """F^T Sigma F: the covariance in the frame's axes, exactly symmetric; written out (entry (a, b)
    = sum_r F_ra (sum_k Sigma_rk F_kb), in that order) because Warp's matrix product calls fma()."""
    t = wp.mat33d()
    for r in range(3):
        for b in range(3):
            t[r, b] = cov[r, 0] * frame[0, b] + cov[r, 1] * frame[1, b] + cov[r, 2] * frame[2, b]
    m = wp.mat33d()
    for a in range(3):
        for b in range(a, 3):
            v = frame[0, a] * t[0, b] + frame[1, a] * t[1, b] + frame[2, a] * t[2, b]
            m[a, b] = v
            m[b, a] = v
    return m


@wp.func
def self_overlap(det_a: wp.float64):
    """int G_a^2 dA = pi sqrt(det A) for a peak-one 2D Gaussian of covariance determinant det_a; 0
    if degenerate (selected, not branched: ``view_overlaps`` runs as a GPU loop)."""
    zero = wp.float64(0.0)
    return wp.where(det_a > zero, wp.float64(PI) * wp.sqrt(wp.max(det_a, zero)), zero)


@wp.func
def plane_overlap(
    a00: wp.float64, a01: wp.float64, a11: wp.float64, det_a: wp.float64,
    b00: wp.float64, b01: wp.float64, b11: wp.float64, det_b: wp.float64, x: wp.float64, y: wp.float64,
):  # fmt: skip
    """int G_a G_b dA over a plane for two peak-one 2D Gaussians (covariances A, B given by their
    entries and determinants) whose centres are d = (x, y) apart:
    2 pi sqrt(det A det B / det(A + B)) exp(-1/2 d^T (A + B)^-1 d); 0 for a degenerate one."""
    s00 = a00 + b00
    s01 = a01 + b01
    s11 = a11 + b11
    det_s = s00 * s11 - s01 * s01
    if det_s <= wp.float64(0.0) or det_a <= wp.float64(0.0) or det_b <= wp.float64(0.0):
        return wp.float64(0.0)
    inv_s = wp.float64(1.0) / det_s
    q = (s11 * x * x - wp.float64(2.0) * s01 * x * y + s00 * y * y) * inv_s
    return wp.float64(TWO_PI) * wp.sqrt(det_a * det_b * inv_s) * exp64(wp.float64(-0.5) * q)


@wp.func
def plane_entries(m: wp.mat33d, view: int):
    """The 2 x 2 block of m in the plane of ``view`` (0: axes (0, 1), 1: (0, 2), 2: (1, 2)) as
    (m_uu, m_uv, m_vv), selected without indexing by a run-time index."""
    uu = wp.where(view == 2, m[1, 1], m[0, 0])
    uv = wp.where(view == 0, m[0, 1], wp.where(view == 1, m[0, 2], m[1, 2]))
    vv = wp.where(view == 0, m[1, 1], m[2, 2])
    return uu, uv, vv


@wp.func
def plane_point(d: wp.vec3d, view: int):
    """(d_u, d_v) of d in the plane of ``view`` (``plane_entries``)."""
    return wp.where(view == 2, d[1], d[0]), wp.where(view == 0, d[1], d[2])


@wp.func
def view_overlaps(d_i: wp.vec3d, d_j: wp.vec3d, m_i: wp.mat33d, m_j: wp.mat33d, values: wp.vec3d):
    """The overlaps of splats i, j and the merged m = diag(values) (centred at 0), each summed over the
    three views along the merged frame's axes: own = (S_ii, S_jj, S_mm), cross = (S_ij, S_im, S_jm);
    and, face-on only (the view along the merged splat's minor axis, view 0), the integrals of the
    composited pair's term in G_i G_j, comp = (int G_i^2 G_j, int G_i G_j^2, int G_i^2 G_j^2,
    int G_i G_j G_m); d_k = F^T (mu_k - mu_m), m_k = F^T Sigma_k F.

    In each view G_i G_j = kappa G_p, kappa = exp(-e^T S^-1 e / 2) (S = A + B, e = c_i - c_j) and G_p
    the peak-one Gaussian of covariance P = A S^-1 B centred at p, p - c_i = -A S^-1 e and
    p - c_j = B S^-1 e. So S_ij = 2 pi sqrt(det P) kappa, int G_i^2 G_j^2 = kappa S_ij / 2, and the
    other three are kappa times the overlap of G_p with G_i, G_j or G_m."""
    own = wp.vec3d()
    cross = wp.vec3d()
    comp = wp.vec4d()
    zero = wp.float64(0.0)
    views = int(3)
    for view in range(views):  # a loop at run time, not unrolled: on a GPU three copies of the body spill registers
        a00, a01, a11 = plane_entries(m_i, view)
        b00, b01, b11 = plane_entries(m_j, view)
        m0 = wp.where(view == 2, values[1], values[0])
        m1 = wp.where(view == 0, values[1], values[2])
        xi, yi = plane_point(d_i, view)
        xj, yj = plane_point(d_j, view)
        det_a = a00 * a11 - a01 * a01
        det_b = b00 * b11 - b01 * b01
        det_m = m0 * m1
        own += wp.vec3d(self_overlap(det_a), self_overlap(det_b), self_overlap(det_m))
        s_im = plane_overlap(a00, a01, a11, det_a, m0, zero, m1, det_m, xi, yi)
        s_jm = plane_overlap(b00, b01, b11, det_b, m0, zero, m1, det_m, xj, yj)
        s00 = a00 + b00
        s01 = a01 + b01
        s11 = a11 + b11
        det_s = s00 * s11 - s01 * s01
        s_ij = zero
        if det_s > zero and det_a > zero and det_b > zero:
            inv_s = wp.float64(1.0) / det_s
            e0 = xi - xj
            e1 = yi - yj
            w0 = (s11 * e0 - s01 * e1) * inv_s  # w = S^-1 e
            w1 = (s00 * e1 - s01 * e0) * inv_s
            det_p = det_a * det_b * inv_s
            kappa = exp64(wp.float64(-0.5) * (e0 * w0 + e1 * w1))
            s_ij = wp.float64(TWO_PI) * wp.sqrt(det_p) * kappa
            if view == 0 and kappa > zero:  # the composited terms, face-on only (docs/quality.md); each is kappa times a finite overlap
                # P = A S^-1 B
                c00 = (s11 * b00 - s01 * b01) * inv_s
                c01 = (s11 * b01 - s01 * b11) * inv_s
                c10 = (s00 * b01 - s01 * b00) * inv_s
                c11 = (s00 * b11 - s01 * b01) * inv_s
                p00 = a00 * c00 + a01 * c10
                p01 = a00 * c01 + a01 * c11
                p11 = a01 * c01 + a11 * c11
                bw0 = b00 * w0 + b01 * w1
                bw1 = b01 * w0 + b11 * w1
                comp += kappa * wp.vec4d(
                    plane_overlap(p00, p01, p11, det_p, a00, a01, a11, det_a, a00 * w0 + a01 * w1, a01 * w0 + a11 * w1),
                    plane_overlap(p00, p01, p11, det_p, b00, b01, b11, det_b, bw0, bw1),
                    wp.float64(0.5) * s_ij,
                    plane_overlap(p00, p01, p11, det_p, m0, zero, m1, det_m, xj + bw0, yj + bw1),
                )
        cross += wp.vec3d(s_ij, s_im, s_jm)
    return own, cross, comp


@wp.func
def pair_view_overlaps(frame: wp.mat33d, values: wp.vec3d, mu_i: wp.vec3d, mu_j: wp.vec3d, mu_m: wp.vec3d, cov_i: wp.mat33d, cov_j: wp.mat33d):
    """``view_overlaps`` of a pair and its merged splat diag(values) in ``frame`` centred at mu_m."""
    ft = wp.transpose(frame)
    return view_overlaps(ft * (mu_i - mu_m), ft * (mu_j - mu_m), in_frame(frame, cov_i), in_frame(frame, cov_j), values)


@wp.func
def field_opacity(a_i: wp.float64, a_j: wp.float64, own: wp.vec3d, cross: wp.vec3d):
    """The merged opacity that minimises the squared L2 change of the opacity field summed over the
    three views, sum_v int (a_i G_i + a_j G_j - a G_m)^2 dA: quadratic in a, least at
    a = (a_i S_im + a_j S_jm) / S_mm (``view_overlaps``' sums)."""
    if own[2] <= wp.float64(0.0):
        return wp.float64(0.0)
    return (a_i * cross[1] + a_j * cross[2]) / own[2]
