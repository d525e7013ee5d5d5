"""The emitted field of splats seen along a plane's normal: each splat's covariance projected onto the
plane (c0, c1) is a peak-one 2D Gaussian G, as a rasteriser draws it, and products of two have a
closed-form integral."""

import warp as wp

wp.set_module_options({"enable_backward": False})

TWO_PI = wp.constant(6.283185307179586)


@wp.func
def project2(cov: wp.mat33d, c0: wp.vec3d, c1: wp.vec3d):
    """The 2x2 block of cov in the plane of the unit vectors c0, c1, as (a00, a01, a11)."""
    return wp.vec3d(wp.dot(c0, cov * c0), wp.dot(c0, cov * c1), wp.dot(c1, cov * c1))


@wp.func
def overlap2(mu_a: wp.vec3d, a: wp.vec3d, mu_b: wp.vec3d, b: wp.vec3d, c0: wp.vec3d, c1: wp.vec3d):
    """int G_a G_b dA over the plane (c0, c1) of two projected peak-one 2D Gaussians
    = 2 pi sqrt(det A det B / det(A + B)) exp(-1/2 d^T (A + B)^-1 d); 0 for a degenerate one."""
    s00 = a[0] + b[0]
    s01 = a[1] + b[1]
    s11 = a[2] + b[2]
    det_s = s00 * s11 - s01 * s01
    det_a = a[0] * a[2] - a[1] * a[1]
    det_b = b[0] * b[2] - b[1] * b[1]
    if det_s <= wp.float64(0.0) or det_a <= wp.float64(0.0) or det_b <= wp.float64(0.0):
        return wp.float64(0.0)
    d = mu_a - mu_b
    x = wp.dot(d, c0)
    y = wp.dot(d, c1)
    q = (s11 * x * x - wp.float64(2.0) * s01 * x * y + s00 * y * y) / det_s
    return wp.float64(TWO_PI) * wp.sqrt(det_a * det_b / det_s) * wp.exp(wp.float64(-0.5) * q)
