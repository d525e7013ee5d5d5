"""3DGS forward rasterisation (the INRIA / gsplat forward pass): projection, tile binning, compositing.

Conventions (shared with ``tests/reference_render.py``):

- Cameras are pinhole, OpenCV/COLMAP axes (x right, y down, z forward), ``x_cam = R x_world + t``.
- Pixel (px, py) samples the image-plane point (px + 0.5, py + 0.5), so a mean projects to the pixel
  index coordinate ``u = fx x/z + cx - 0.5``. With ``cx = W/2`` this is INRIA's ``ndc2Pix``
  (``((ndc + 1) W - 1) / 2`` compared with the integer pixel index).
- Activations: opacity = sigmoid(logit), scale = exp(log-scale), quaternion normalised; 3D covariance
  R S S^T R^T; EWA 2D covariance J W Sigma W^T J^T with the view-space x/z and y/z clamped to 1.3x the
  half-FOV tangents (W/(2 fx), H/(2 fy)) inside J, plus 0.3 px^2 on the diagonal.
- Colour: INRIA's real SH basis (C0 = 0.28209479177387814 ...) of degree 0-3 at the unit direction
  mean - camera centre, + 0.5, clamped at 0 (not at 1).
- Culling: view-space ``z <= near`` (the camera's near plane: INRIA's 0.2, less for cameras around
  a scene stored in small units, ``eval.cameras.near_plane``), a non-positive 2D covariance determinant,
  a zero quaternion, an empty tile rectangle, or opacity < 1/255 (which can reach no pixel).
- Tile binning: 16x16 tiles; a splat covers the tiles of the square of half-side
  ``ceil(3 sqrt(lambda_max))`` px around its projected mean (INRIA's ``getRect``), less the tiles
  where its alpha is below 1/255 for certain: outside the box of its ellipse of alpha >= 1/255 (see
  ``project``), and, row by row, outside that ellipse itself (``reached_columns``): the same image,
  fewer entries.
- Entries are keyed ``tile << 32 | float bits of depth`` (depth > near > 0, so the bits sort as the
  floats do) and radix-sorted stably; splats of equal depth keep their row order.
- Several views at once (refinement's steps): ``project_views`` writes splat i seen by camera v to
  row v n + i, and ``emit_entries`` numbers view v's tiles after the earlier views' (tile v view_tiles
  + t), so each tile's list, and each pixel, is that of its view rendered alone.
- Compositing, per pixel in depth order: alpha = min(0.99, opacity exp(-d^T conic d / 2)); skip
  alpha < 1/255; stop before accumulating when T (1 - alpha) < 1e-4; C += rgb alpha T, T *= 1 - alpha;
  finally C + T background.
- The same bits on every device: float32 arithmetic that no compiler fuses (``PORTABLE``) and the
  portable ``exp32``, ``log32`` and ``sigmoid32`` (``portable_math.py``). A tile whose list is
  longer than the renderer's chunk is composited in chunks (the GPU's ``composite_chunks``) with
  the chunks' own arithmetic on every device (``composite_tiles`` replays it on the CPU), so the
  CPU's images are the GPU's to the bit.
"""

import warp as wp

from .options import PORTABLE
from .portable_math import exp32, log32, sigmoid32

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

TILE = wp.constant(16)
TILE_PIXELS = wp.constant(256)
LOW_PASS = wp.constant(0.3)
ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)
# Every walk skips the exp where power < log(ALPHA_MIN / opacity) - FAINT_MARGIN (``project``'s faint
# power, -log(255 opacity) - FAINT_MARGIN): there the float32 alpha is below ALPHA_MIN by ~1e-3
# relative, far beyond the exp's and log's rounding, so the skipped pixels are exactly those the
# alpha test would skip, and the images those of the test alone.
FAINT_MARGIN = wp.constant(1.0e-3)

SH_C0 = wp.constant(0.28209479177387814)
SH_C1 = wp.constant(0.4886025119029199)
SH_C2_0 = wp.constant(1.0925484305920792)
SH_C2_1 = wp.constant(-1.0925484305920792)
SH_C2_2 = wp.constant(0.31539156525252005)
SH_C2_3 = wp.constant(-1.0925484305920792)
SH_C2_4 = wp.constant(0.5462742152960396)
SH_C3_0 = wp.constant(-0.5900435899266435)
SH_C3_1 = wp.constant(2.890611442640554)
SH_C3_2 = wp.constant(-0.4570457994644658)
SH_C3_3 = wp.constant(0.3731763325901154)
SH_C3_4 = wp.constant(-0.4570457994644658)
SH_C3_5 = wp.constant(1.445305721320277)
SH_C3_6 = wp.constant(-0.5900435899266435)


@wp.struct
class CameraParams:
    """A pinhole camera as the kernels see it (built by ``nanogs_warp.eval.render``)."""

    rotation: wp.mat33  # world-to-camera
    translation: wp.vec3
    centre: wp.vec3  # camera centre in world space, -R^T t
    fx: float
    fy: float
    cx: float
    cy: float
    lim_x: float  # 1.3 * tan(half horizontal FOV) = 1.3 * W / (2 fx)
    lim_y: float
    width: int
    height: int
    tiles_x: int
    tiles_y: int
    near: float  # view-space depth at or below which a splat is culled


@wp.func
def _sh_coef(features: wp.array2d(dtype=float), i: int, rest: int, j: int):
    """Coefficient j >= 1 of splat i for R, G, B (f_rest is channel-major: rest per channel)."""
    return wp.vec3(features[i, 2 + j], features[i, 2 + rest + j], features[i, 2 + 2 * rest + j])


@wp.func
def sh_to_rgb(features: wp.array2d(dtype=float), i: int, degree: int, d: wp.vec3):
    """INRIA's computeColorFromSH: real SH up to ``degree`` at unit direction d, + 0.5, clamped at 0."""
    rest = (degree + 1) * (degree + 1) - 1
    c = SH_C0 * wp.vec3(features[i, 0], features[i, 1], features[i, 2])
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        c = c - SH_C1 * y * _sh_coef(features, i, rest, 1)
        c = c + SH_C1 * z * _sh_coef(features, i, rest, 2)
        c = c - SH_C1 * x * _sh_coef(features, i, rest, 3)
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            xy = x * y
            yz = y * z
            xz = x * z
            c = c + SH_C2_0 * xy * _sh_coef(features, i, rest, 4)
            c = c + SH_C2_1 * yz * _sh_coef(features, i, rest, 5)
            c = c + SH_C2_2 * (2.0 * zz - xx - yy) * _sh_coef(features, i, rest, 6)
            c = c + SH_C2_3 * xz * _sh_coef(features, i, rest, 7)
            c = c + SH_C2_4 * (xx - yy) * _sh_coef(features, i, rest, 8)
            if degree > 2:
                c = c + SH_C3_0 * y * (3.0 * xx - yy) * _sh_coef(features, i, rest, 9)
                c = c + SH_C3_1 * xy * z * _sh_coef(features, i, rest, 10)
                c = c + SH_C3_2 * y * (4.0 * zz - xx - yy) * _sh_coef(features, i, rest, 11)
                c = c + SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * _sh_coef(features, i, rest, 12)
                c = c + SH_C3_4 * x * (4.0 * zz - xx - yy) * _sh_coef(features, i, rest, 13)
                c = c + SH_C3_5 * z * (xx - yy) * _sh_coef(features, i, rest, 14)
                c = c + SH_C3_6 * x * (xx - 3.0 * yy) * _sh_coef(features, i, rest, 15)
    c = c + wp.vec3(0.5, 0.5, 0.5)
    return wp.vec3(wp.max(c[0], 0.0), wp.max(c[1], 0.0), wp.max(c[2], 0.0))


@wp.func
def scaled_columns(r: wp.mat33, scale: wp.vec3):
    """R diag(scale): column k of R times scale k, one product an entry."""
    m = wp.mat33()
    for a in range(3):
        for k in range(3):
            m[a, k] = r[a, k] * scale[k]
    return m


@wp.func
def matrix_product(a: wp.mat33, b: wp.mat33):
    """A B with entry (i, j) = (a_i0 b_0j + a_i1 b_1j) + a_i2 b_2j. Written out because Warp's matrix
    product calls fma(): correctly rounded everywhere, but a library call per term on a CPU without
    FMA in its baseline, and an instruction that the PTX check of the portable modules refuses."""
    m = wp.mat33()
    for i in range(3):
        for j in range(3):
            m[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return m


@wp.func
def gram(m: wp.mat33):
    """M M^T, exactly symmetric: entry (a, b) = (m_a0 m_b0 + m_a1 m_b1) + m_a2 m_b2 (see ``matrix_product``)."""
    g = wp.mat33()
    for a in range(3):
        for b in range(a, 3):
            v = m[a, 0] * m[b, 0] + m[a, 1] * m[b, 1] + m[a, 2] * m[b, 2]
            g[a, b] = v
            g[b, a] = v
    return g


# A splat's view-independent terms, once per splat set for a renderer that draws many views of it
# (``splat_shapes``): its 3D covariance's six distinct entries (00, 01, 02, 11, 12, 22), its opacity
# and log(255 opacity), the reach that culls it below 1/255 (``project_shape``).
vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def world_covariance(q: wp.quat, log_scale: wp.vec3):
    """Sigma = R S S^T R^T for the normalised quaternion q (non-zero) and scales exp(log_scale)."""
    r = wp.quat_to_matrix(q / wp.length(q))
    m = scaled_columns(r, wp.vec3(exp32(log_scale[0]), exp32(log_scale[1]), exp32(log_scale[2])))
    return gram(m)


@wp.func
def splat_shape(q: wp.quat, log_scale: wp.vec3, logit: float):
    """The view-independent terms of a splat (``vec8`` above); a zero quaternion gets reach -1 (culled)."""
    opacity = sigmoid32(logit)
    if wp.length(q) == 0.0:
        return vec8(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, opacity, -1.0)
    sigma = world_covariance(q, log_scale)
    reach = log32(255.0 * opacity)
    return vec8(sigma[0, 0], sigma[0, 1], sigma[0, 2], sigma[1, 1], sigma[1, 2], sigma[2, 2], opacity, reach)


@wp.kernel
def splat_shapes(
    first: int,
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    shapes: wp.array(dtype=vec8),
):
    """shapes[i] = ``splat_shape`` of splat ``first + tid``."""
    i = first + wp.tid()
    shapes[i] = splat_shape(rotations[i], log_scales[i], opacities[i])


# The walks' float32 power -(a dx^2 + c dy^2)/2 - b dx dy (dx = x_k - px) lies within ROUNDING
# ((a dx^2 + c dy^2)/2 + |b dx dy|) of the exact value from the same float32 inputs (about seven
# roundings of 2^-24: 4.2e-7), so where the exact q/2 = (a dx^2 + 2 b dx dy + c dy^2)/2 exceeds
# -faint by more than that everywhere in a tile, no walk composites the splat there (``reached_columns``).
ROUNDING = wp.constant(1.0e-6)


@wp.func
def ellipse_span(a: wp.float64, b: wp.float64, c: wp.float64, det: wp.float64, limit: wp.float64, lo: wp.float64, hi: wp.float64):
    """(least, greatest) d over the ellipse a d^2 + 2 b d e + c e^2 <= limit (det = a c - b^2 > 0) with e
    in [lo, hi] (already within the ellipse's own range of e); each end where the ellipse's extreme
    d lies inside the band, else at the band's edge nearer to it (d is concave in e along the ellipse's
    right half and convex along its left half)."""
    reach = wp.sqrt(limit * c / det)  # the ellipse's greatest d, at e = -b reach / c
    e_right = -b * reach / c
    right = reach
    if e_right < lo or e_right > hi:
        e = wp.clamp(e_right, lo, hi)
        right = (-b * e + wp.sqrt(wp.max(a * limit - det * e * e, wp.float64(0.0)))) / a
    left = -reach  # at e = b reach / c
    if -e_right < lo or -e_right > hi:
        e = wp.clamp(-e_right, lo, hi)
        left = (-b * e - wp.sqrt(wp.max(a * limit - det * e * e, wp.float64(0.0)))) / a
    return left, right


@wp.func
def reached_columns(p: wp.vec2, co: wp.vec4, faint: float, r: wp.vec4i, ty: int):
    """The tiles [first, last] of row ``ty`` of tile rectangle ``r`` ([x0, x1) x [y0, y1)) where the
    splat seen at ``p`` with conic ``co`` may reach alpha >= 1/255 (first > last: none): those whose
    pixel centres meet its ellipse q/2 <= -faint + ROUNDING S, S the rounding bound's largest value over
    the rectangle. A walk skips a pixel whose float32 power is below ``faint`` (``composite``), so the
    tiles left out are tiles where every walk skips the splat at every pixel: the same images, fewer
    entries. float64 throughout (the same bits on every device); the whole row where the conic is not
    positive definite or anything is not finite."""
    everything = wp.vec2i(r[0], r[2] - 1)
    a = wp.float64(co[0])
    b = wp.float64(co[1])
    c = wp.float64(co[2])
    det = a * c - b * b
    x = wp.float64(p[0])
    y = wp.float64(p[1])
    if not (a > wp.float64(0.0) and c > wp.float64(0.0) and det > wp.float64(0.0) and det < wp.float64(wp.inf)
            and wp.abs(x) < wp.float64(1.0e30) and wp.abs(y) < wp.float64(1.0e30)):  # fmt: skip
        return everything
    # d = p - pixel over the rectangle's pixel centres, and the rounding bound's largest value there
    tile = wp.float64(TILE)
    dx_far = wp.max(wp.abs(x - tile * wp.float64(r[0])), wp.abs(x - tile * wp.float64(r[2]) + wp.float64(1.0)))
    dy_far = wp.max(wp.abs(y - tile * wp.float64(r[1])), wp.abs(y - tile * wp.float64(r[3]) + wp.float64(1.0)))
    bound = wp.float64(0.5) * ((a + wp.abs(b)) * dx_far * dx_far + (c + wp.abs(b)) * dy_far * dy_far)
    limit = wp.float64(2.0) * (-wp.float64(faint) + wp.float64(ROUNDING) * bound)  # q <= limit
    if not (limit > wp.float64(0.0) and limit < wp.float64(wp.inf)):
        return everything
    # the row's band of dy, within the ellipse's own range of dy
    reach_y = wp.sqrt(limit * a / det)
    lo = wp.max(y - tile * wp.float64(ty) - tile + wp.float64(1.0), -reach_y)
    hi = wp.min(y - tile * wp.float64(ty), reach_y)
    if lo > hi:
        return wp.vec2i(r[0], r[0] - 1)
    left, right = ellipse_span(a, b, c, det, limit, lo, hi)
    # pixel x = p_x - dx, widened by far more than the float64 rounding of the above
    slack = wp.float64(1.0e-9) * (wp.float64(1.0) + wp.abs(x) + wp.abs(left) + wp.abs(right))
    first = wp.ceil((x - right - slack - tile + wp.float64(1.0)) / tile)  # its last column, 16 tx + 15, reaches x - right
    last = wp.floor((x - left + slack) / tile)  # its first column, 16 tx, reaches x - left
    first = wp.max(first, wp.float64(r[0]))
    last = wp.min(last, wp.float64(r[2] - 1))
    if first > last:
        return wp.vec2i(r[0], r[0] - 1)
    return wp.vec2i(int(first), int(last))


@wp.func
def one_tile(r: wp.vec4i):
    """Whether tile rectangle ``r`` is a single tile, which a splat keeps without ``reached_columns``."""
    return (r[2] - r[0]) * (r[3] - r[1]) == 1


@wp.func
def reached_tiles(p: wp.vec2, co: wp.vec4, faint: float, r: wp.vec4i):
    """How many tiles of rectangle ``r`` the splat may reach: ``reached_columns`` summed over its rows
    (every tile of a ``one_tile`` rectangle)."""
    if one_tile(r):
        return 1
    n = int(0)
    for ty in range(r[1], r[3]):
        span = reached_columns(p, co, faint, r, ty)
        n += wp.max(span[1] - span[0] + 1, 0)
    return n


@wp.func
def project_shape(
    i: int,
    out: int,
    means: wp.array(dtype=wp.vec3),
    shape: vec8,
    features: wp.array2d(dtype=float),
    degree: int,
    cam: CameraParams,
    xy: wp.array(dtype=wp.vec2),
    depth: wp.array(dtype=float),
    conic_opacity: wp.array(dtype=wp.vec4),
    rgb: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec4),
    faint: wp.array(dtype=float),
    rect: wp.array(dtype=wp.vec4i),
    touched: wp.array(dtype=wp.int32),
):
    """Splat i of view-independent terms ``shape`` (``splat_shape``) seen by ``cam``, written to row
    ``out``: projected mean, depth, conic and opacity, colour, reach box, faint power, tile rectangle
    [x0, x1) x [y0, y1) and the count of its tiles the splat reaches (``reached_tiles``; 0 and an empty
    rectangle when culled)."""
    touched[out] = 0
    rect[out] = wp.vec4i(0, 0, 0, 0)
    # Where alpha >= 1/255 can hold: opacity * exp(power) >= 1/255, i.e. d^T conic d <= 2 ln(255 opacity)
    # (see below); none where opacity < 1/255 (or the quaternion is zero: ``splat_shape``)
    reach = shape[7]
    if reach <= 0.0:
        return
    t = cam.rotation * means[i] + cam.translation
    z = t[2]
    if z <= cam.near:
        return
    sigma = wp.mat33(shape[0], shape[1], shape[2], shape[1], shape[3], shape[4], shape[2], shape[4], shape[5])

    # EWA: Jacobian of the perspective projection at the (FOV-clamped) view-space mean.
    tx = wp.clamp(t[0] / z, -cam.lim_x, cam.lim_x) * z
    ty = wp.clamp(t[1] / z, -cam.lim_y, cam.lim_y) * z
    j0 = wp.vec3(cam.fx / z, 0.0, -cam.fx * tx / (z * z))
    j1 = wp.vec3(0.0, cam.fy / z, -cam.fy * ty / (z * z))
    wt = wp.transpose(cam.rotation)
    u = wt * j0  # row 0 of J W, as a column
    v = wt * j1
    a = wp.dot(u, sigma * u) + LOW_PASS
    b = wp.dot(u, sigma * v)
    c = wp.dot(v, sigma * v) + LOW_PASS
    det = a * c - b * b
    if det <= 0.0:
        return
    mid = 0.5 * (a + c)
    lambda1 = mid + wp.sqrt(wp.max(0.1, mid * mid - det))
    radius = wp.ceil(3.0 * wp.sqrt(lambda1))

    px = cam.fx * t[0] / z + cam.cx - 0.5
    py = cam.fy * t[1] / z + cam.cy - 0.5
    conic = wp.vec3(c / det, -b / det, a / det)
    opacity = shape[6]

    # The ellipse of alpha >= 1/255 has half-widths sqrt(2 ln(255 opacity) conic_yy / det(conic)) in x,
    # likewise in y. Widened by 1% + 1 px, so float32 rounding of the per-pixel test cannot matter, this
    # box only lets pixels and tiles skip splats that cannot reach them: the image is that of INRIA's rule.
    ca = wp.float64(conic[0])
    cb = wp.float64(conic[1])
    cc = wp.float64(conic[2])
    conic_det = ca * cc - cb * cb
    half_x = float(1.0e30)
    half_y = float(1.0e30)
    if conic_det > wp.float64(0.0):
        two_reach = wp.float64(2.0) * wp.float64(reach)
        half_x = float(wp.sqrt(two_reach * cc / conic_det)) * 1.01 + 1.0
        half_y = float(wp.sqrt(two_reach * ca / conic_det)) * 1.01 + 1.0

    # INRIA's getRect (tiles of the 3-sigma square), intersected with the tiles of the reach box.
    tile = float(TILE)
    fx_tiles = float(cam.tiles_x)
    fy_tiles = float(cam.tiles_y)
    x0 = int(wp.clamp(wp.max((px - radius) / tile, wp.floor((px - half_x) / tile)), 0.0, fx_tiles))
    x1 = int(wp.clamp(wp.min((px + radius + tile - 1.0) / tile, wp.floor((px + half_x) / tile) + 1.0), 0.0, fx_tiles))
    y0 = int(wp.clamp(wp.max((py - radius) / tile, wp.floor((py - half_y) / tile)), 0.0, fy_tiles))
    y1 = int(wp.clamp(wp.min((py + radius + tile - 1.0) / tile, wp.floor((py + half_y) / tile) + 1.0), 0.0, fy_tiles))
    if x1 <= x0 or y1 <= y0:
        return

    d = means[i] - cam.centre
    dn = wp.length(d)
    if dn > 0.0:
        d = d / dn
    rgb[out] = sh_to_rgb(features, i, degree, d)
    xy[out] = wp.vec2(px, py)
    box[out] = wp.vec4(px - half_x, px + half_x, py - half_y, py + half_y)
    faint_power = -reach - FAINT_MARGIN  # log(ALPHA_MIN / opacity) - FAINT_MARGIN: below it no exp is needed
    faint[out] = faint_power
    depth[out] = z
    co = wp.vec4(conic[0], conic[1], conic[2], opacity)
    conic_opacity[out] = co
    r = wp.vec4i(x0, y0, x1, y1)
    rect[out] = r
    touched[out] = reached_tiles(wp.vec2(px, py), co, faint_power, r)


@wp.kernel
def project(
    means: wp.array(dtype=wp.vec3),
    shapes: wp.array(dtype=vec8),
    features: wp.array2d(dtype=float),
    degree: int,
    cam: CameraParams,
    first: int,
    xy: wp.array(dtype=wp.vec2),
    depth: wp.array(dtype=float),
    conic_opacity: wp.array(dtype=wp.vec4),
    rgb: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec4),
    faint: wp.array(dtype=float),
    rect: wp.array(dtype=wp.vec4i),
    touched: wp.array(dtype=wp.int32),
):
    """``project_shape`` of splat ``first + tid`` (its terms from ``splat_shapes``) into its own row."""
    i = first + wp.tid()
    project_shape(i, i, means, shapes[i], features, degree, cam, xy, depth, conic_opacity, rgb, box, faint, rect, touched)


@wp.kernel
def project_views(
    means: wp.array(dtype=wp.vec3),
    shapes: wp.array(dtype=vec8),
    features: wp.array2d(dtype=float),
    degree: int,
    cams: wp.array(dtype=CameraParams),
    first: int,
    xy: wp.array(dtype=wp.vec2),
    depth: wp.array(dtype=float),
    conic_opacity: wp.array(dtype=wp.vec4),
    rgb: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec4),
    faint: wp.array(dtype=float),
    rect: wp.array(dtype=wp.vec4i),
    touched: wp.array(dtype=wp.int32),
):
    """Several views at once: row v n + i (n splats) is ``project_shape`` of splat i by camera v."""
    row = first + wp.tid()
    n = means.shape[0]
    v = row / n
    i = row - v * n
    project_shape(i, row, means, shapes[i], features, degree, cams[v], xy, depth, conic_opacity, rgb, box, faint, rect,
                  touched)  # fmt: skip


@wp.kernel
def rect_areas(first: int, rect: wp.array(dtype=wp.vec4i), areas: wp.array(dtype=wp.int32)):
    """areas[i] = the number of tiles of row i's tile rectangle (``project_shape``'s, empty for a row
    culled before it), i = ``first`` + tid."""
    i = first + wp.tid()
    r = rect[i]
    areas[i] = wp.max(r[2] - r[0], 0) * wp.max(r[3] - r[1], 0)


@wp.kernel
def emit_entries(
    depth: wp.array(dtype=float),
    xy: wp.array(dtype=wp.vec2),
    conic_opacity: wp.array(dtype=wp.vec4),
    faint: wp.array(dtype=float),
    rect: wp.array(dtype=wp.vec4i),
    touched: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    tiles_x: int,
    splats: int,
    view_tiles: int,
    first: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    """Writes one (tile << 32 | depth bits, row) entry per tile the splat reaches (``reached_tiles``:
    row by row, its ``reached_columns``), at the row's slots [ends[i] - touched[i], ends[i]) of the
    inclusive prefix sum. Rows of several views (``project_views``: ``splats`` rows a view) number
    their tiles after the earlier views' ``view_tiles`` each (``tiles_x`` a row): view v's tile t is
    v view_tiles + t."""
    i = first + wp.tid()
    n = touched[i]
    if n == 0:
        return
    slot = ends[i] - n
    bits = wp.int64(wp.cast(depth[i], wp.int32))
    r = rect[i]
    offset = (i / splats) * view_tiles
    if one_tile(r):
        keys[slot] = (wp.int64(offset + r[1] * tiles_x + r[0]) << wp.int64(32)) | bits
        values[slot] = i
        return
    p = xy[i]
    co = conic_opacity[i]
    f = faint[i]
    for ty in range(r[1], r[3]):
        span = reached_columns(p, co, f, r, ty)
        for tx in range(span[0], span[1] + 1):
            keys[slot] = (wp.int64(offset + ty * tiles_x + tx) << wp.int64(32)) | bits
            values[slot] = i
            slot += 1


@wp.kernel
def gather_entries(
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    count: int,
    xy: wp.array(dtype=wp.vec2),
    conic_opacity: wp.array(dtype=wp.vec4),
    rgb: wp.array(dtype=wp.vec3),
    box: wp.array(dtype=wp.vec4),
    faint: wp.array(dtype=float),
    first: int,
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
):
    """Copies each sorted entry's splat data into entry order and records each tile's entry range
    (tiles without entries keep the empty range their arrays were zeroed to)."""
    k = first + wp.tid()
    i = values[k]
    e_xy[k] = xy[i]
    e_conic_opacity[k] = conic_opacity[i]
    e_rgb[k] = rgb[i]
    e_box[k] = box[i]
    e_faint[k] = faint[i]
    tile = wp.int32(keys[k] >> wp.int64(32))
    if k == 0:
        tile_start[tile] = k
    elif wp.int32(keys[k - 1] >> wp.int64(32)) != tile:
        tile_start[tile] = k
    if k == count - 1:
        tile_end[tile] = k + 1
    elif wp.int32(keys[k + 1] >> wp.int64(32)) != tile:
        tile_end[tile] = k + 1


@wp.kernel
def composite(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tiles_x: int,
    background: wp.vec3,
    view: int,
    view_tiles: int,
    first: int,
    image: wp.array4d(dtype=float),
):
    """One thread per pixel, 256 consecutive threads per 16x16 tile (one CUDA block per tile):
    front-to-back alpha compositing of the tile's depth-sorted entries, INRIA's renderCUDA. Tiles
    of several views (``emit_entries``): tile v view_tiles + t is tile t of view ``view`` + v.
    The walk is ``walked_chunk``'s from T = 1, the background behind what transmittance is left."""
    tid = first + wp.tid()
    tile = tid / TILE_PIXELS
    local = tid - (tid / TILE_PIXELS) * TILE_PIXELS
    shown = tile / view_tiles
    tile_of_view = tile - shown * view_tiles
    px = (tile_of_view - (tile_of_view / tiles_x) * tiles_x) * TILE + local - (local / TILE) * TILE
    py = (tile_of_view / tiles_x) * TILE + local / TILE
    if px >= width or py >= height:
        return
    walked = walked_chunk(e_xy, e_conic_opacity, e_rgb, e_box, e_faint, tile_start[tile], tile_end[tile], float(px), float(py), 1.0)
    c = wp.vec3(walked[0], walked[1], walked[2]) + background * wp.abs(walked[3])
    image[view + shown, py, px, 0] = c[0]
    image[view + shown, py, px, 1] = c[1]
    image[view + shown, py, px, 2] = c[2]


@wp.func
def pixel_of(tile: int, local: int, tiles_x: int):
    """Pixel (x, y) of slot ``local`` (row-major) of 16x16 tile ``tile``."""
    return wp.vec2i((tile - (tile / tiles_x) * tiles_x) * TILE + local - (local / TILE) * TILE, (tile / tiles_x) * TILE + local / TILE)


@wp.func
def entry_at_pixel(p: wp.vec2, co: wp.vec4, faint: float, fpx: float, fpy: float):
    """(dx, dy, G, o G, alpha) of an entry (centre ``p``, conic and opacity ``co``) at pixel (fpx, fpy),
    alpha = min(0.99, o G) as INRIA's renderCUDA computes it; alpha 0 where a walk skips the entry:
    power > 0, power below ``faint`` (alpha < ALPHA_MIN there: no exp, as ``composite_tiles`` skips
    it) or alpha < ALPHA_MIN. The entry's values are passed in and there is one return: a GPU's walk
    through a function that took the entry arrays and returned early ran ``composite`` about 8 %
    slower (docs/performance.md)."""
    dx = p[0] - fpx
    dy = p[1] - fpy
    power = -0.5 * (co[0] * dx * dx + co[2] * dy * dy) - co[1] * dx * dy
    gauss = float(0.0)
    raw = float(0.0)
    alpha = float(0.0)
    if power > 0.0 or power < faint:
        alpha = 0.0
    else:
        gauss = exp32(power)
        raw = co[3] * gauss
        alpha = wp.min(ALPHA_MAX, raw)
        if alpha < ALPHA_MIN:
            alpha = 0.0
    return dx, dy, gauss, raw, alpha


@wp.func
def alpha_at(p: wp.vec2, co: wp.vec4, faint: float, fpx: float, fpy: float):
    """An entry's alpha at pixel (fpx, fpy) (``entry_at_pixel``'s; the walks' ``walked_chunk`` and
    ``chunk_product``, where refinement's backward takes its other terms too)."""
    dx, dy, gauss, raw, alpha = entry_at_pixel(p, co, faint, fpx, fpy)
    return alpha


@wp.func
def outside(box: wp.vec4, fpx: float, fpy: float):
    """Whether pixel (fpx, fpy) is outside an entry's reach box (x0, x1, y0, y1)."""
    return fpx < box[0] or fpx > box[1] or fpy < box[2] or fpy > box[3]


# Compositing a tile's entries in chunks of at most ``chunk`` entries, one CUDA block per (chunk, tile),
# so that a tile holding far more entries than the others (a dense cluster seen end-on) is composited
# by many blocks instead of one. Front-to-back compositing splits at any entry: with the chunk's own
# transmittance T_j and colour C_j (each from T = 1), the pixel's colour is sum_j T_<j C_j, and the
# stop rule (T (1 - alpha) < 1e-4) is kept by starting each chunk at the transmittance before it:
#   chunk_counts, chunk_ranges   the chunks of each tile (and whether any tile needs more than one:
#                                else ``composite`` does) (an inclusive scan of the counts between)
#   chunk_transmittance          T_j of every chunk but a tile's last (0 where it falls below 1e-4);
#                                a tile's first chunk, which starts from T = 1, composited on the way
#   chunk_prefix                 per pixel, the transmittance before each chunk (0 once stopped)
#   composite_chunks             each later chunk composited from that transmittance, as ``composite`` does
#   composite_merge              the chunks' colours summed in order, then the background
# A tile of one chunk takes exactly ``composite``'s arithmetic, so its pixels are ``composite``'s bits.


@wp.kernel
def chunk_counts(
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    chunk: int,
    first: int,
    counts: wp.array(dtype=wp.int32),
    longest: wp.array(dtype=wp.int32),
):
    """Chunks of at most ``chunk`` entries in each tile's range, and the most entries any tile
    holds (``longest`` zeroed before)."""
    t = first + wp.tid()
    n = tile_end[t] - tile_start[t]
    counts[t] = (n + chunk - 1) / chunk
    wp.atomic_max(longest, 0, n)


@wp.kernel
def chunk_ranges(
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    chunk: int,
    first: int,
    chunk_tile: wp.array(dtype=wp.int32),
    chunk_first: wp.array(dtype=wp.int32),
    chunk_last: wp.array(dtype=wp.int32),
):
    """Each tile's chunks, in entry order, at its slots [chunk_ends[t] - counts[t], chunk_ends[t])."""
    t = first + wp.tid()
    c = chunk_ends[t] - counts[t]
    k = tile_start[t]
    end = tile_end[t]
    while k < end:
        chunk_tile[c] = t
        chunk_first[c] = k
        chunk_last[c] = wp.min(k + chunk, end)
        c += 1
        k += chunk


@wp.func
def chunk_product(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    first: int,
    last: int,
    fpx: float,
    fpy: float,
):
    """The product of (1 - alpha) over entries [first, last) at pixel (fpx, fpy), 0 once it falls
    below T_MIN: a chunk's own transmittance (``chunk_transmittance``)."""
    t = float(1.0)
    for k in range(first, last):
        if outside(e_box[k], fpx, fpy):
            continue
        alpha = alpha_at(e_xy[k], e_conic_opacity[k], e_faint[k], fpx, fpy)
        if alpha > 0.0:
            t = t * (1.0 - alpha)
            if t < T_MIN:
                t = 0.0
                break
    return t


@wp.func
def merged_chunks(
    colour: wp.array(dtype=wp.vec4),
    before: wp.array(dtype=float),
    counts: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    tile: int,
    local: int,
):
    """A pixel's walk over its tile's chunks (``composite_merge``): (their colours summed in order up to
    the chunk it stopped in, the transmittance left, that chunk's (chunk, pixel) slot, or -1 where it
    never stopped). It stops in the chunk before which its transmittance is 0, or in the one whose
    own walk stopped (a negative transmittance after it)."""
    c = wp.vec3(0.0, 0.0, 0.0)
    transmittance = float(1.0)
    stopped = int(-1)
    for k in range(chunk_ends[tile] - counts[tile], chunk_ends[tile]):
        slot = k * TILE_PIXELS + local
        if before[slot] == 0.0:
            stopped = slot
            break
        v = colour[slot]
        c = c + wp.vec3(v[0], v[1], v[2])
        transmittance = wp.abs(v[3])
        if v[3] < 0.0:
            stopped = slot
            break
    return c, transmittance, stopped


@wp.func
def walked_chunk(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    first: int,
    last: int,
    fpx: float,
    fpy: float,
    transmittance: float,
):
    """Front-to-back compositing of entries [first, last) at pixel (fpx, fpy) from ``transmittance``
    (``alpha_at``; a pixel stops where T (1 - alpha) would fall below 1e-4): (colour, transmittance
    after), the transmittance negated where the pixel stopped in the range."""
    rgb = wp.vec3(0.0, 0.0, 0.0)
    stopped = float(1.0)
    for k in range(first, last):
        if outside(e_box[k], fpx, fpy):
            continue
        alpha = alpha_at(e_xy[k], e_conic_opacity[k], e_faint[k], fpx, fpy)
        if alpha == 0.0:
            continue
        test_t = transmittance * (1.0 - alpha)
        if test_t < T_MIN:
            stopped = -1.0
            break
        rgb = rgb + e_rgb[k] * (alpha * transmittance)
        transmittance = test_t
    return wp.vec4(rgb[0], rgb[1], rgb[2], stopped * transmittance)


@wp.kernel
def chunk_transmittance(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    chunk_tile: wp.array(dtype=wp.int32),
    chunk_first: wp.array(dtype=wp.int32),
    chunk_last: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tiles_x: int,
    tiles: int,
    first: int,
    transmittance: wp.array(dtype=float),
    colour: wp.array(dtype=wp.vec4),
):
    """Per (chunk, pixel): the product of (1 - alpha) over the chunk's entries, 0 once it falls below
    1e-4 (the pixel stops in this chunk, whatever came before). A tile's first chunk starts from
    T = 1, so its walk is ``composite_chunks``' own: it is composited here (``walked_chunk``, its
    colour to ``colour``), its product the walk's transmittance (0 where it stopped: the same
    products), and ``composite_chunks`` leaves it alone. A tile's last chunk but its first is
    skipped: nothing follows it; so are the threads beyond the last chunk (launched for a bound on
    the count)."""
    tid = first + wp.tid()
    c = tid / TILE_PIXELS
    if c >= chunk_ends[tiles - 1]:
        return
    tile = chunk_tile[c]
    opening = chunk_first[c] == tile_start[tile]
    if chunk_last[c] == tile_end[tile] and not opening:
        return
    pixel = pixel_of(tile, tid - c * TILE_PIXELS, tiles_x)
    inside = pixel[0] < width and pixel[1] < height
    t = float(1.0)
    if opening:
        walked = wp.vec4(0.0, 0.0, 0.0, -1.0)
        if inside:
            walked = walked_chunk(e_xy, e_conic_opacity, e_rgb, e_box, e_faint, chunk_first[c], chunk_last[c],
                                  float(pixel[0]), float(pixel[1]), 1.0)  # fmt: skip
            t = wp.max(walked[3], 0.0)
        colour[tid] = walked
    elif inside:
        t = chunk_product(e_xy, e_conic_opacity, e_box, e_faint, chunk_first[c], chunk_last[c], float(pixel[0]), float(pixel[1]))
    transmittance[tid] = t


@wp.kernel
def chunk_prefix(
    counts: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    first: int,
    transmittance: wp.array(dtype=float),
):
    """Per pixel of each tile, in place over its chunks in order: each chunk's own transmittance
    becomes the pixel's transmittance before the chunk, 0 for the chunks after the one it stops in."""
    tid = first + wp.tid()
    tile = tid / TILE_PIXELS
    local = tid - tile * TILE_PIXELS
    before = float(1.0)
    last = chunk_ends[tile] - 1
    for c in range(chunk_ends[tile] - counts[tile], chunk_ends[tile]):
        slot = c * TILE_PIXELS + local
        own = float(0.0)
        if c < last:  # the last chunk's own transmittance is not computed, nor needed
            own = transmittance[slot]
        transmittance[slot] = before
        before = before * own
        if before < T_MIN:
            before = 0.0


@wp.kernel
def composite_chunks(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    chunk_tile: wp.array(dtype=wp.int32),
    chunk_first: wp.array(dtype=wp.int32),
    chunk_last: wp.array(dtype=wp.int32),
    before: wp.array(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    tiles: int,
    first: int,
    colour: wp.array(dtype=wp.vec4),
):
    """Per (chunk, pixel) of every chunk but a tile's first (``chunk_transmittance`` composited it):
    ``composite``'s loop over the chunk's entries from the transmittance before it (``walked_chunk``);
    (colour, transmittance after), the transmittance negated where the pixel stopped here."""
    tid = first + wp.tid()
    c = tid / TILE_PIXELS
    if c >= chunk_ends[tiles - 1]:
        return
    if chunk_first[c] == tile_start[chunk_tile[c]]:
        return
    pixel = pixel_of(chunk_tile[c], tid - c * TILE_PIXELS, tiles_x)
    transmittance = before[tid]
    if pixel[0] >= width or pixel[1] >= height or transmittance == 0.0:
        colour[tid] = wp.vec4(0.0, 0.0, 0.0, -1.0)
        return
    colour[tid] = walked_chunk(e_xy, e_conic_opacity, e_rgb, e_box, e_faint, chunk_first[c], chunk_last[c],
                               float(pixel[0]), float(pixel[1]), transmittance)  # fmt: skip


@wp.kernel
def composite_merge(
    colour: wp.array(dtype=wp.vec4),
    before: wp.array(dtype=float),
    counts: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tiles_x: int,
    background: wp.vec3,
    view: int,
    first: int,
    image: wp.array4d(dtype=float),
):
    """Per pixel: its tile's chunk colours summed in order up to the chunk it stopped in, plus the
    background times the transmittance left."""
    tid = first + wp.tid()
    tile = tid / TILE_PIXELS
    local = tid - tile * TILE_PIXELS
    pixel = pixel_of(tile, local, tiles_x)
    if pixel[0] >= width or pixel[1] >= height:
        return
    c, transmittance, _stopped = merged_chunks(colour, before, counts, chunk_ends, tile, local)
    c = c + background * transmittance
    image[view, pixel[1], pixel[0], 0] = c[0]
    image[view, pixel[1], pixel[0], 1] = c[1]
    image[view, pixel[1], pixel[0], 2] = c[2]


@wp.func
def chunk_own_step(chunk_state: wp.array(dtype=wp.vec2), slot: int, alpha: float):
    """``chunk_transmittance``'s step in a tile walk (``composite_tiles``): the pixel's own product over
    the chunk, from 1, times (1 - alpha), and 0 once it falls below T_MIN (``chunk_state[slot]``: the
    transmittance before the chunk, the chunk's own)."""
    state = chunk_state[slot]
    if state[1] > 0.0:
        own = state[1] * (1.0 - alpha)
        if own < T_MIN:
            own = 0.0
        chunk_state[slot] = wp.vec2(state[0], own)


@wp.func
def chunk_end(
    slot: int,
    last: bool,
    done: wp.array(dtype=wp.int32),
    colour: wp.array(dtype=wp.vec3),
    total: wp.array(dtype=wp.vec3),
    chunk_state: wp.array(dtype=wp.vec2),
    transmittance: wp.array(dtype=float),
):
    """A tile walk's end of a chunk for the pixel in ``slot``: ``composite_merge`` adds the chunk's
    colour to ``total``; a pixel that stopped in the chunk (done 1) is finished (done 2); any other,
    unless the chunk was the tile's last, goes on from ``chunk_prefix``'s transmittance before the
    next chunk or, where that is 0, is finished too. Returns 1 for that last case (the pixel ran out
    between chunks), else 0."""
    if done[slot] == 2:
        return 0
    total[slot] = total[slot] + colour[slot]
    if done[slot] == 1:
        done[slot] = 2
        return 0
    if not last:
        state = chunk_state[slot]
        before = state[0] * state[1]
        if before < T_MIN:
            before = 0.0
        if before == 0.0:  # the merge stops before the next chunk
            done[slot] = 2
            return 1
        chunk_state[slot] = wp.vec2(before, 1.0)
        transmittance[slot] = before
        colour[slot] = wp.vec3(0.0, 0.0, 0.0)
    return 0


@wp.kernel
def composite_tiles(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tiles_x: int,
    background: wp.vec3,
    view: int,
    view_tiles: int,
    chunk: int,
    first: int,
    transmittance: wp.array(dtype=float),
    colour: wp.array(dtype=wp.vec3),
    done: wp.array(dtype=wp.int32),
    chunk_state: wp.array(dtype=wp.vec2),
    total: wp.array(dtype=wp.vec3),
    image: wp.array4d(dtype=float),
):
    """``composite`` for the CPU: one thread per tile, splat-major, visiting only the pixels inside each
    entry's reach box; per-pixel state in the tile's 256 slots of ``transmittance``, ``colour`` and
    ``done``. Each pixel sees the same entries in the same order with the same float32 arithmetic as
    in ``composite``, so the images are identical. A tile of more than ``chunk`` entries is composited
    as ``chunk_transmittance`` to ``composite_merge`` do it on the GPU, chunk by chunk, with their
    arithmetic (per pixel in ``chunk_state``: the transmittance before the chunk and the chunk's own,
    and in ``total`` the colour of the chunks before): the same bits as the GPU's chunked image.
    Tiles of several views as in ``composite``."""
    tile = first + wp.tid()
    base = tile * TILE_PIXELS
    shown = tile / view_tiles
    tile_of_view = tile - shown * view_tiles
    x_lo = (tile_of_view - (tile_of_view / tiles_x) * tiles_x) * TILE
    y_lo = (tile_of_view / tiles_x) * TILE
    x_hi = wp.min(x_lo + TILE, width)  # exclusive
    y_hi = wp.min(y_lo + TILE, height)
    for s in range(TILE_PIXELS):
        transmittance[base + s] = 1.0
        colour[base + s] = wp.vec3(0.0, 0.0, 0.0)
        done[base + s] = 0
        chunk_state[base + s] = wp.vec2(1.0, 1.0)
        total[base + s] = wp.vec3(0.0, 0.0, 0.0)
    remaining = (x_hi - x_lo) * (y_hi - y_lo)
    fx_lo = float(x_lo)
    fx_hi = float(x_hi - 1)
    fy_lo = float(y_lo)
    fy_hi = float(y_hi - 1)
    start = tile_start[tile]
    end = tile_end[tile]
    chunked = end - start > chunk  # else one chunk: ``composite``'s one walk
    # done: 0 compositing, 1 stopped (T (1 - alpha) < T_MIN) in this chunk, 2 finished after a chunk
    chunk_first = start
    while chunk_first < end and remaining > 0:
        chunk_last = end
        if chunked:
            chunk_last = wp.min(chunk_first + chunk, end)
        last = chunk_last == end
        for k in range(chunk_first, chunk_last):
            if remaining == 0:
                break
            bx = e_box[k]
            # pixels px with bx[0] <= px <= bx[1] (and likewise y) inside this tile
            gx0 = int(wp.ceil(wp.clamp(bx[0], fx_lo, fx_hi + 1.0)))
            gx1 = int(wp.floor(wp.clamp(bx[1], fx_lo - 1.0, fx_hi)))
            gy0 = int(wp.ceil(wp.clamp(bx[2], fy_lo, fy_hi + 1.0)))
            gy1 = int(wp.floor(wp.clamp(bx[3], fy_lo - 1.0, fy_hi)))
            if gx1 < gx0 or gy1 < gy0:
                continue
            p = e_xy[k]
            co = e_conic_opacity[k]
            rgb = e_rgb[k]
            faint = e_faint[k]
            for py in range(gy0, gy1 + 1):
                row = base + (py - y_lo) * TILE - x_lo
                dy = p[1] - float(py)
                for px in range(gx0, gx1 + 1):
                    slot = row + px
                    if done[slot] != 0:
                        continue
                    dx = p[0] - float(px)
                    power = -0.5 * (co[0] * dx * dx + co[2] * dy * dy) - co[1] * dx * dy
                    if power > 0.0 or power < faint:
                        continue
                    alpha = wp.min(ALPHA_MAX, co[3] * exp32(power))
                    if alpha < ALPHA_MIN:
                        continue
                    if chunked and not last:
                        chunk_own_step(chunk_state, slot, alpha)
                    t = transmittance[slot]
                    test_t = t * (1.0 - alpha)
                    if test_t < T_MIN:
                        done[slot] = 1  # stopped: in a chunked tile the merge stops at this chunk
                        remaining -= 1
                        continue
                    colour[slot] = colour[slot] + rgb * (alpha * t)
                    transmittance[slot] = test_t
        if chunked:
            for py in range(y_lo, y_hi):
                for px in range(x_lo, x_hi):
                    remaining -= chunk_end(base + (py - y_lo) * TILE + px - x_lo, last, done, colour, total, chunk_state, transmittance)
        chunk_first = chunk_last
    for py in range(y_lo, y_hi):
        for px in range(x_lo, x_hi):
            slot = base + (py - y_lo) * TILE + px - x_lo
            c = colour[slot]
            if chunked:
                c = total[slot]
            c = c + background * transmittance[slot]
            image[view + shown, py, px, 0] = c[0]
            image[view + shown, py, px, 1] = c[1]
            image[view + shown, py, px, 2] = c[2]
