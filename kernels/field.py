"""The emitted field of splats seen along the three axes of a merged splat's frame.

Seen along an axis, each splat's covariance projected onto the plane of the other two axes is a
peak-one 2D Gaussian G, as a rasteriser draws it, and the product of two has a closed-form
integral. Working in the merged splat's frame F, splat k's projection onto the plane of axes
(u, v) is the (u, v) block of F^T Sigma_k F and its centre the (u, v) part of F^T (mu_k - mu_m):
one 3 x 3 change of basis per splat serves all three views.
"""

import warp as wp

from .portable_math import exp64

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # the same bits on every device: portable_math.py

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
def self_overlap(a: wp.mat33d, u: int, v: int):
    """int G_a^2 dA over the plane (u, v) = pi sqrt(det A) for the 2D block A; 0 if degenerate."""
    det_a = a[u, u] * a[v, v] - a[u, v] * a[u, v]
    if det_a <= wp.float64(0.0):
        return wp.float64(0.0)
    return wp.float64(PI) * wp.sqrt(det_a)


@wp.func
def overlap(d: wp.vec3d, a: wp.mat33d, b: wp.mat33d, u: int, v: int):
    """int G_a G_b dA over the plane (u, v) of two peak-one 2D Gaussians whose centres differ by d
    (frame coordinates) = 2 pi sqrt(det A det B / det(A + B)) exp(-1/2 d^T (A + B)^-1 d); 0 for a
    degenerate one."""
    s00 = a[u, u] + b[u, u]
    s01 = a[u, v] + b[u, v]
    s11 = a[v, v] + b[v, v]
    det_s = s00 * s11 - s01 * s01
    det_a = a[u, u] * a[v, v] - a[u, v] * a[u, v]
    det_b = b[u, u] * b[v, v] - b[u, v] * b[u, v]
    if det_s <= wp.float64(0.0) or det_a <= wp.float64(0.0) or det_b <= wp.float64(0.0):
        return wp.float64(0.0)
    x = d[u]
    y = d[v]
    q = (s11 * x * x - wp.float64(2.0) * s01 * x * y + s00 * y * y) / det_s
    return wp.float64(TWO_PI) * wp.sqrt(det_a * det_b / det_s) * exp64(wp.float64(-0.5) * q)


@wp.func
def view_overlaps(d_i: wp.vec3d, d_j: wp.vec3d, m_i: wp.mat33d, m_j: wp.mat33d, m_m: wp.mat33d):
    """The six overlaps of splats i, j and the merged m, each summed over the three views along the
    merged frame's axes, as ((S_ii, S_jj, S_mm), (S_ij, S_im, S_jm)); d_k = F^T (mu_k - mu_m),
    m_k = F^T Sigma_k F."""
    own = wp.vec3d()
    cross = wp.vec3d()
    for view in range(3):
        u = wp.where(view == 2, 1, 0)
        v = wp.where(view == 0, 1, 2)
        own += wp.vec3d(self_overlap(m_i, u, v), self_overlap(m_j, u, v), self_overlap(m_m, u, v))
        cross += wp.vec3d(overlap(d_i - d_j, m_i, m_j, u, v), overlap(d_i, m_i, m_m, u, v), overlap(d_j, m_j, m_m, u, v))
    return own, cross


@wp.func
def pair_view_overlaps(frame: wp.mat33d, values: wp.vec3d, mu_i: wp.vec3d, mu_j: wp.vec3d, mu_m: wp.vec3d, cov_i: wp.mat33d, cov_j: wp.mat33d):
    """``view_overlaps`` of a pair and its merged splat diag(values) in ``frame`` centred at mu_m."""
    ft = wp.transpose(frame)
    return view_overlaps(ft * (mu_i - mu_m), ft * (mu_j - mu_m), in_frame(frame, cov_i), in_frame(frame, cov_j), wp.diag(values))


@wp.func
def field_opacity(a_i: wp.float64, a_j: wp.float64, own: wp.vec3d, cross: wp.vec3d):
    """The merged opacity that minimises the squared L2 change of the opacity field summed over the
    three views, sum_v int (a_i G_i + a_j G_j - a G_m)^2 dA: quadratic in a, least at
    a = (a_i S_im + a_j S_jm) / S_mm (``view_overlaps``' sums)."""
    if own[2] <= wp.float64(0.0):
        return wp.float64(0.0)
    return (a_i * cross[1] + a_j * cross[2]) / own[2]
