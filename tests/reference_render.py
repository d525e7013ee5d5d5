"""Float64 numpy twin of the Warp rasteriser (kernels/render.py): the same maths, written for reading.

``render_reference`` loops over the splats in (depth, row) order and composites all pixels at once.
A splat reaches a pixel only when the pixel's 16x16 tile lies in the splat's tile rectangle (INRIA's
3-sigma ``getRect``), as in the tiled renderer.

The rasteriser computes in float32, so a handful of discrete decisions can go the other way there:
an alpha within rounding of 1/255, a transmittance within rounding of 1e-4, a tile rectangle edge or
near-plane test within rounding, two splats of (almost) equal depth. Each flips a pixel by up to a whole
splat contribution, not by rounding. The reference flags the pixels where such a threshold decision
is within ``eps`` (relative) of its threshold as ``ambiguous``. Depth ties (depths within 1e-6
relative, the order float32 cannot be trusted to keep) are reported in ``stats["ties"]`` instead;
``render_reference(..., swap=pair)`` renders with that pair's order reversed, so that a test can
accept either order.
"""

from __future__ import annotations

import numpy as np

TILE = 16
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
]


def quat_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions, w first, normalised here -> (N, 3, 3) rotation matrices."""
    q = q_wxyz / np.linalg.norm(q_wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def sh_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """(N, 3) unit directions -> (N, (degree + 1)^2) real SH basis values, INRIA's signs and order."""
    x, y, z = d.T
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    b = [np.full_like(x, C0)]
    if degree > 0:
        b += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        b += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree > 2:
        b += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(b, 1)


def sh_colour(features: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, F) file-order features -> (N, 3) RGB = SH + 0.5, clamped at 0."""
    n, f = features.shape
    k = f // 3
    degree = int(round(np.sqrt(k))) - 1
    coeffs = np.empty((n, k, 3))
    coeffs[:, 0, :] = features[:, :3]
    coeffs[:, 1:, :] = features[:, 3:].reshape(n, 3, k - 1).transpose(0, 2, 1)  # channel-major f_rest
    rgb = np.einsum("nk,nkc->nc", sh_basis(directions, degree), coeffs) + 0.5
    return np.maximum(rgb, 0.0)


def tile_rect(px, py, radius, tiles_x, tiles_y):
    """INRIA's getRect: [x0, x1) x [y0, y1) of tiles covered by the square of half-side radius."""
    x0 = np.clip((px - radius) / TILE, 0, tiles_x).astype(np.int64)
    x1 = np.clip((px + radius + TILE - 1) / TILE, 0, tiles_x).astype(np.int64)
    y0 = np.clip((py - radius) / TILE, 0, tiles_y).astype(np.int64)
    y1 = np.clip((py + radius + TILE - 1) / TILE, 0, tiles_y).astype(np.int64)
    return x0, x1, y0, y1


def project(splats: dict, camera, eps: float = 1e-5) -> dict:
    """Per-splat screen-space quantities (float64), INRIA's preprocessCUDA. ``splats`` is
    ``SplatSet.to_numpy()``. Also returns, per splat, the tile rectangles that float32 rounding could
    give (``inner`` and ``outer``) and whether the near-plane test is within rounding."""
    means = splats["means"].astype(np.float64)
    R = np.asarray(camera.rotation, np.float64)
    t = np.asarray(camera.translation, np.float64)
    W, H = int(camera.width), int(camera.height)
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    tiles_x, tiles_y = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE

    view = means @ R.T + t
    z = view[:, 2]
    # float32 rounds z = R p + t to about 6e-8 (|p| + |t|); allow 16x that
    z_tolerance = 1e-6 * (1.0 + np.abs(means).sum(1) + np.abs(t).sum())
    near = float(camera.near)
    near_ambiguous = np.abs(z - near) <= z_tolerance
    zs = np.where(z > near - z_tolerance, z, 1.0)  # keep the maths finite for culled splats

    rot = quat_to_matrix(splats["rotations"].astype(np.float64))
    m = rot * np.exp(splats["log_scales"].astype(np.float64))[:, None, :]
    sigma = m @ m.transpose(0, 2, 1)
    lim_x, lim_y = 1.3 * 0.5 * W / fx, 1.3 * 0.5 * H / fy
    tx = np.clip(view[:, 0] / zs, -lim_x, lim_x) * zs
    ty = np.clip(view[:, 1] / zs, -lim_y, lim_y) * zs
    J = np.zeros((len(z), 2, 3))
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * tx / zs**2
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * ty / zs**2
    T = J @ R
    cov = T @ sigma @ T.transpose(0, 2, 1)
    a, b, c = cov[:, 0, 0] + 0.3, cov[:, 0, 1], cov[:, 1, 1] + 0.3
    det = a * c - b * b
    mid = 0.5 * (a + c)
    lambda1 = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
    extent = 3.0 * np.sqrt(lambda1)
    radius = np.ceil(extent)
    px = fx * view[:, 0] / zs + cx - 0.5
    py = fy * view[:, 1] / zs + cy - 0.5
    rect = tile_rect(px, py, radius, tiles_x, tiles_y)

    # The rectangles float32 rounding of the position and the extent could produce.
    r_lo, r_hi = np.ceil(extent * (1 - eps)), np.ceil(extent * (1 + eps))
    dx, dy = eps * (1 + np.abs(px)), eps * (1 + np.abs(py))
    lo = tile_rect(px - dx, py - dy, r_lo, tiles_x, tiles_y)
    hi = tile_rect(px + dx, py + dy, r_hi, tiles_x, tiles_y)
    lo2 = tile_rect(px + dx, py + dy, r_lo, tiles_x, tiles_y)
    hi2 = tile_rect(px - dx, py - dy, r_hi, tiles_x, tiles_y)
    cands = [rect, lo, hi, lo2, hi2]
    outer = tuple(f([r[k] for r in cands], axis=0) for k, f in zip(range(4), (np.min, np.max, np.min, np.max)))
    inner = tuple(f([r[k] for r in cands], axis=0) for k, f in zip(range(4), (np.max, np.min, np.max, np.min)))

    quat_ok = np.linalg.norm(splats["rotations"], axis=1) > 0
    visible = (z > near) & (det > 0) & quat_ok & ((rect[1] - rect[0]) * (rect[3] - rect[2]) > 0)
    maybe_visible = (visible | near_ambiguous) & (det > 0) & quat_ok

    centre = -R.T @ t
    d = means - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    rgb = sh_colour(splats["features"].astype(np.float64), d)
    opacity = 1.0 / (1.0 + np.exp(-splats["opacities"].astype(np.float64)))
    conic = np.stack([c / det, -b / det, a / det], 1)
    return dict(
        xy=np.stack([px, py], 1), depth=z, conic=conic, opacity=opacity, rgb=rgb, rect=rect,
        visible=visible, maybe_visible=maybe_visible, near_ambiguous=near_ambiguous, inner=inner, outer=outer,
        tiles_x=tiles_x, tiles_y=tiles_y,
    )  # fmt: skip


def render_reference(splats: dict, camera, background=(0.0, 0.0, 0.0), eps: float = 1e-4, swap=None):
    """Returns (image (H, W, 3) float64, ambiguous (H, W) bool, stats dict). ``stats["ties"]`` lists
    the pairs of rows adjacent in depth order whose depths are within 1e-6 relative; ``swap``, one
    such pair, composites that pair in the other order."""
    W, H = int(camera.width), int(camera.height)
    s = project(splats, camera)
    bg = np.asarray(background, np.float64)
    pyy, pxx = np.mgrid[0:H, 0:W].astype(np.float64)
    tile_x, tile_y = (pxx // TILE).astype(np.int64), (pyy // TILE).astype(np.int64)
    colour = np.zeros((H, W, 3))
    trans = np.ones((H, W))
    done = np.zeros((H, W), bool)
    ambiguous = np.zeros((H, W), bool)
    stats = dict(contributions=0, terminated=0, visible=int(s["visible"].sum()), ties=[])

    def in_rect(rect, i):
        x0, x1, y0, y1 = (r[i] for r in rect)
        return (tile_x >= x0) & (tile_x < x1) & (tile_y >= y0) & (tile_y < y1)

    def alpha_of(i):
        dx, dy = s["xy"][i, 0] - pxx, s["xy"][i, 1] - pyy
        a, b, c = s["conic"][i]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        return power, np.minimum(0.99, s["opacity"][i] * np.exp(power))

    rows = np.flatnonzero(s["maybe_visible"])
    order = rows[np.lexsort((rows, s["depth"][rows]))]
    depths = s["depth"][order]
    close = np.flatnonzero(np.abs(np.diff(depths)) <= 1e-6 * depths[1:])
    stats["ties"] = [(int(order[k]), int(order[k + 1])) for k in close]
    if swap is not None:
        k = int(np.flatnonzero(order == swap[0])[0])
        if order[k + 1] != swap[1]:
            raise ValueError(f"{swap} is not a pair of rows adjacent in depth order")
        order[k], order[k + 1] = order[k + 1], order[k]
    for i in order:
        power, alpha = alpha_of(i)
        reaches = alpha >= ALPHA_MIN * (1 - eps)
        # Decisions within rounding: the splat's visibility, its rectangle's edge.
        unsure = in_rect(s["outer"], i) & ~in_rect(s["inner"], i)
        if s["near_ambiguous"][i]:
            unsure |= in_rect(s["outer"], i)
        ambiguous |= unsure & reaches & ~done
        if not s["visible"][i]:
            continue
        inside = in_rect(s["rect"], i) & ~done & (power <= 0)
        ambiguous |= inside & (np.abs(alpha - ALPHA_MIN) <= eps * ALPHA_MIN)
        active = inside & (alpha >= ALPHA_MIN)
        test_t = trans * (1.0 - alpha)
        ambiguous |= active & (np.abs(test_t - T_MIN) <= eps * T_MIN)
        stop = active & (test_t < T_MIN)
        done |= stop
        accumulate = active & ~stop
        colour[accumulate] += (s["rgb"][i] * (alpha * trans)[:, :, None])[accumulate]
        trans = np.where(accumulate, test_t, trans)
        stats["contributions"] += int(accumulate.sum())
        stats["terminated"] += int(stop.sum())
    return colour + trans[:, :, None] * bg, ambiguous, stats
