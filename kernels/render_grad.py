"""Backward pass of the 3DGS rasteriser in ``kernels/render.py``: gradients of a loss L with respect to
every splat parameter, given dL/dimage, accumulated in a fixed order (no floating-point atomics).

The forward is ``render.py``'s own (``project``, ``emit_entries``, stable radix sort, ``gather_entries``,
``composite`` / ``composite_tiles``), with its conventions; here only the bookkeeping to find a splat's
entries after the sort (``number_slots``, ``order_entries``) and the two backward stages:

1. ``composite_backward``: one thread per 16x16 tile (or ``lanes`` threads per tile, each owning every
   lanes-th pixel row, their per-entry sums then added lane by lane in ``sum_lanes``; on the CPU
   ``composite_backward_lanes_in_turn`` does both in one thread per tile, with the same sums) replays the
   tile's compositing front to back with the forward's float32 arithmetic (so every skip and early-termination decision is the forward's),
   keeping per pixel the transmittance T_k and the colour in front C_<=k. With the forward's final pixel
   colour C (background included), the colour behind entry k is B_k = C - C_<=k, and for
   C = sum_k rgb_k alpha_k T_k + T_N bg:
       dC/drgb_k = alpha_k T_k,   dC/dalpha_k = rgb_k T_k - B_k / (1 - alpha_k).
   With alpha = min(0.99, o G), G = exp(power), power = -(a dx^2 + c dy^2)/2 - b dx dy, dx = x_k - px:
       dalpha/do = G,  dalpha/dpower = alpha  (both 0 where the 0.99 clamp holds),
       dpower/da = -dx^2/2, dpower/db = -dx dy, dpower/dc = -dy^2/2,
       dpower/dx_k = -(a dx + b dy), dpower/dy_k = -(b dx + c dy).
   Each entry's gradient (position, conic, opacity, colour) is summed over the tile's pixels in row order
   and written to the entry's own slot.
   On a GPU, ``composite_backward_pixels`` replays the same walk with one thread per pixel (65,536
   threads at 256 x 256 against 16 lanes' 4,096), each writing its own term of every entry that reaches
   it into a slot of its own (``pixel_areas`` sizes them), and ``sum_pixels`` adds each entry's terms
   in the lanes' order: the same bits as the lanes, about five times faster on an H200.
2. ``splat_backward``: one thread per splat sums its entries' gradients in emit order (slot order, found
   through ``entry_of_slot``) and applies the chain rule back through the conic inverse, the EWA
   projection J W Sigma W^T J^T (with the FOV clamp of J), Sigma = R S S^T R^T, the quaternion
   normalisation, the sigmoid and the SH colour (its clamp at 0, and its view direction), adding to the
   per-splat gradient arrays: thread i writes only row i, so the order is fixed on every device.

Several views are back-propagated together as ``render.project_views`` and ``render.emit_entries``
lay them out (view v's tile t is tile v view_tiles + t, its splat i row v n + i): a tile's
kernels find their view and its own size (``view_tile_bounds``), and ``splat_backward`` adds the views
to a splat's gradients one after another, in the order of one-at-a-time back-propagation: the same bits.

A refinement of the colours alone (the colour fit: every other rate 0) asks for the colours'
gradients only (``colours`` nonzero): each (entry, pixel) term is then dL/drgb_k = alpha_k T_k dL/dC
alone, the walk keeps only T, and ``splat_backward`` runs only the SH colour's chain. The colours'
gradients are the same bits as the whole pass's, in the same order; every other gradient stays 0.
Those weights alpha_k T_k do not depend on the colours, so the forward keeps them, in the
per-pixel backward's slots (``composite_chunk_weights`` on a GPU, ``composite_tile_weights`` on the
CPU), and ``sum_weighted_colours`` adds dL/dC alpha_k T_k per entry from them in ``sum_pixels``'
order, with no second walk of the tiles. That forward composites a tile of more than a chunk of
entries (``eval/render.py``'s ``CHUNK_ENTRIES``) as ``render.render`` does, in chunks side by side,
each from the transmittance before it: there its T_k differ from one walk's by float32 rounding, and
so do the colours' gradients from the whole pass's; a tile of one chunk is one walk, to the bit.
"""

import warp as wp

from .options import PORTABLE
from .portable_math import exp32, sigmoid32
from .render import (
    ALPHA_MAX,
    ALPHA_MIN,
    LOW_PASS,
    SH_C0,
    SH_C1,
    SH_C2_0,
    SH_C2_1,
    SH_C2_2,
    SH_C2_3,
    SH_C2_4,
    SH_C3_0,
    SH_C3_1,
    SH_C3_2,
    SH_C3_3,
    SH_C3_4,
    SH_C3_5,
    SH_C3_6,
    T_MIN,
    TILE,
    TILE_PIXELS,
    CameraParams,
    _sh_coef,
    chunk_end,
    chunk_own_step,
    chunk_product,
    entry_at_pixel,
    merged_chunks,
    gram,
    matrix_product,
    outside,
    scaled_columns,
    sh_to_rgb,
)

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py


@wp.kernel
def number_slots(first: int, values: wp.array(dtype=wp.int32), slot_splat: wp.array(dtype=wp.int32)):
    """Before the sort: remembers each emitted slot's splat and replaces the sort value by the slot."""
    k = first + wp.tid()
    slot_splat[k] = values[k]
    values[k] = k


@wp.kernel
def order_entries(
    first: int,
    values: wp.array(dtype=wp.int32),
    slot_splat: wp.array(dtype=wp.int32),
    entry_splat: wp.array(dtype=wp.int32),
    entry_of_slot: wp.array(dtype=wp.int32),
):
    """After the sort (values = emitted slots): each entry's splat, and each slot's entry."""
    k = first + wp.tid()
    slot = values[k]
    entry_splat[k] = slot_splat[slot]
    entry_of_slot[slot] = k


@wp.func
def pixel_terms(
    t: float, alpha: float, gauss: float, raw: float, dx: float, dy: float, co: wp.vec4, rgb: wp.vec3,
    g: wp.vec3, final: wp.vec3, front: wp.vec3, colours: int,
):  # fmt: skip
    """One entry's terms at one pixel (module docstring), given the pixel's transmittance ``t`` and
    colour ``front`` before the entry, dL/dC ``g`` and the final colour ``final``: (colour term,
    colour in front after the entry, opacity term, conic term, 2D-mean term); the last three 0
    where the 0.99 clamp holds, and where ``colours`` is nonzero (the colour term alone; ``front``
    then unchanged)."""
    weight = alpha * t
    g_rgb = g * weight
    in_front = front
    g_op = float(0.0)
    g_co = wp.vec3(0.0, 0.0, 0.0)
    g_xy = wp.vec2(0.0, 0.0)
    if colours == 0:
        in_front = front + rgb * weight
    if colours == 0 and raw < ALPHA_MAX:
        # dL/dalpha = T rgb.g - B.g / (1 - alpha), B = C - C_<=k
        g_alpha = t * wp.dot(rgb, g) - wp.dot(final - in_front, g) / (1.0 - alpha)
        g_op = g_alpha * gauss
        g_power = g_alpha * alpha
        g_co = g_power * wp.vec3(-0.5 * dx * dx, -dx * dy, -0.5 * dy * dy)
        g_xy = -(g_power * wp.vec2(co[0] * dx + co[1] * dy, co[1] * dx + co[2] * dy))
    return g_rgb, in_front, g_op, g_co, g_xy


@wp.func
def row_gradients(
    view: int,
    py: int,
    gx0: int,
    gx1: int,
    row: int,
    p: wp.vec2,
    co: wp.vec4,
    rgb: wp.vec3,
    faint: float,
    image: wp.array4d(dtype=float),
    grad_image: wp.array4d(dtype=float),
    transmittance: wp.array(dtype=float),
    front: wp.array(dtype=wp.vec3),
    done: wp.array(dtype=int),
    gxy: wp.vec2,
    gco: wp.vec3,
    gop: float,
    grgb: wp.vec3,
    colours: int,
):
    """An entry's gradients over pixels gx0..gx1 of pixel row py of view ``view`` (their state in slots row + px),
    added to the running sums (gxy, gco, gop, grgb) pixel by pixel (the colour's alone where ``colours``
    is nonzero: ``pixel_terms``); also the number of pixels the
    entry finished (module docstring). Below the power ``faint`` alpha < ALPHA_MIN: the pixel is
    skipped without its exp, as ``composite_tiles`` skips it."""
    finished = int(0)
    fpy = float(py)
    for px in range(gx0, gx1 + 1):
        slot = row + px
        if done[slot] != 0:
            continue
        dx, dy, gauss, raw, alpha = entry_at_pixel(p, co, faint, float(px), fpy)
        if alpha == 0.0:
            continue
        t = transmittance[slot]
        test_t = t * (1.0 - alpha)
        if test_t < T_MIN:
            done[slot] = 1
            finished += 1
            continue
        g = wp.vec3(grad_image[view, py, px, 0], grad_image[view, py, px, 1], grad_image[view, py, px, 2])
        final = wp.vec3(image[view, py, px, 0], image[view, py, px, 1], image[view, py, px, 2])
        g_rgb, in_front, g_op, g_co, g_xy = pixel_terms(t, alpha, gauss, raw, dx, dy, co, rgb, g, final, front[slot], colours)
        front[slot] = in_front
        transmittance[slot] = test_t
        grgb = grgb + g_rgb
        gop += g_op  # +0 where the clamp holds: a sum from +0 is never -0, so adding 0 changes no bit
        gco = gco + g_co
        gxy = gxy + g_xy
    return gxy, gco, gop, grgb, finished


@wp.func
def entry_columns(bx: wp.vec4, x_lo: int, x_hi: int, y_lo: int, y_hi: int):
    """The pixel columns gx0..gx1 and rows gy0..gy1 of the tile [x_lo, x_hi) x [y_lo, y_hi) that an
    entry's box reaches (empty where it reaches none)."""
    gx0 = int(wp.ceil(wp.clamp(bx[0], float(x_lo), float(x_hi))))
    gx1 = int(wp.floor(wp.clamp(bx[1], float(x_lo - 1), float(x_hi - 1))))
    gy0 = int(wp.ceil(wp.clamp(bx[2], float(y_lo), float(y_hi))))
    gy1 = int(wp.floor(wp.clamp(bx[3], float(y_lo - 1), float(y_hi - 1))))
    return gx0, gx1, gy0, gy1


@wp.func
def tile_bounds(tile: int, tiles_x: int, width: int, height: int):
    """The pixels [x_lo, x_hi) x [y_lo, y_hi) of 16x16 tile ``tile`` (row-major, ``tiles_x`` a row)
    in a width x height image: (x_lo, x_hi, y_lo, y_hi)."""
    x_lo = (tile - (tile / tiles_x) * tiles_x) * TILE
    y_lo = (tile / tiles_x) * TILE
    return x_lo, wp.min(x_lo + TILE, width), y_lo, wp.min(y_lo + TILE, height)


@wp.func
def view_tile_bounds(tile: int, tiles_x: int, view_tiles: int, cams: wp.array(dtype=CameraParams)):
    """Tile ``tile`` of several views' tiles (``render.emit_entries``: view v's tile t is
    v view_tiles + t, ``tiles_x`` a row): (v, ``tile_bounds`` of t in view v's own image)."""
    view = tile / view_tiles
    own = tile - view * view_tiles
    cam = cams[view]
    x_lo, x_hi, y_lo, y_hi = tile_bounds(own, tiles_x, cam.width, cam.height)
    return view, x_lo, x_hi, y_lo, y_hi


@wp.func
def reset_rows(base: int, lane: int, lanes: int, transmittance: wp.array(dtype=float), front: wp.array(dtype=wp.vec3), done: wp.array(dtype=int)):
    """Starts the pixel state of the tile's rows lane, lane + lanes, ... (slots from ``base``)."""
    for r in range(lane, TILE, lanes):
        for c in range(TILE):
            slot = base + r * TILE + c
            transmittance[slot] = 1.0
            front[slot] = wp.vec3(0.0, 0.0, 0.0)
            done[slot] = 0


@wp.kernel
def composite_backward(
    first: int,
    lanes: int,
    colours: int,
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    image: wp.array4d(dtype=float),
    grad_image: wp.array4d(dtype=float),
    transmittance: wp.array(dtype=float),
    front: wp.array(dtype=wp.vec3),
    done: wp.array(dtype=wp.int32),
    g_xy: wp.array(dtype=wp.vec2),
    g_conic: wp.array(dtype=wp.vec3),
    g_opacity: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
):
    """``lanes`` threads per tile (1, 2, 4, 8 or 16), lane l owning the tile's pixel rows l, l + lanes, ...:
    per entry k, dL/d(mean 2D, conic, opacity, colour) summed over the lane's pixels in row order
    (see the module docstring), written to slot k * lanes + l. ``image`` is the forward's (V, H, W, 3)
    output, ``grad_image`` dL/dimage; tiles and ``cams`` of several views as in ``view_tile_bounds``. Per-pixel state lives in the tile's 256 slots of the scratch
    arrays (each lane touches only its rows')."""
    tid = first + wp.tid()
    tile = tid / lanes
    lane = tid - tile * lanes
    base = tile * TILE_PIXELS
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(tile, tiles_x, view_tiles, cams)
    reset_rows(base, lane, lanes, transmittance, front, done)
    own_rows = int(0)
    for r in range(lane, TILE, lanes):
        if y_lo + r < y_hi:
            own_rows += 1
    remaining = (x_hi - x_lo) * own_rows
    for k in range(tile_start[tile], tile_end[tile]):
        gxy = wp.vec2(0.0, 0.0)
        gco = wp.vec3(0.0, 0.0, 0.0)
        gop = float(0.0)
        grgb = wp.vec3(0.0, 0.0, 0.0)
        gx0, gx1, gy0, gy1 = entry_columns(e_box[k], x_lo, x_hi, y_lo, y_hi)
        if remaining > 0 and gx0 <= gx1:  # else the lane is finished, or no pixel of it sees this entry
            co = e_conic_opacity[k]
            faint = e_faint[k]
            first_row = gy0 + ((lane - (gy0 - y_lo)) % lanes + lanes) % lanes  # the lane's first row >= gy0
            for py in range(first_row, gy1 + 1, lanes):
                gxy, gco, gop, grgb, finished = row_gradients(
                    view, py, gx0, gx1, base + (py - y_lo) * TILE - x_lo, e_xy[k], co, e_rgb[k], faint,
                    image, grad_image, transmittance, front, done, gxy, gco, gop, grgb, colours,
                )
                remaining -= finished
        out = k * lanes + lane
        g_xy[out] = gxy
        g_conic[out] = gco
        g_opacity[out] = gop
        g_rgb[out] = grgb


@wp.kernel
def composite_backward_lanes_in_turn(
    first: int,
    lanes: int,
    colours: int,
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    image: wp.array4d(dtype=float),
    grad_image: wp.array4d(dtype=float),
    transmittance: wp.array(dtype=float),
    front: wp.array(dtype=wp.vec3),
    done: wp.array(dtype=wp.int32),
    g_xy: wp.array(dtype=wp.vec2),
    g_conic: wp.array(dtype=wp.vec3),
    g_opacity: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
):
    """``composite_backward`` followed by ``sum_lanes`` in one thread per tile, for the CPU: per entry
    each lane's sum over its rows, then the lanes' sums added lane 0 first into slot k. The same
    operations in the same order per sum, so the same bits; one walk of the tile's entries instead
    of one per lane. (Pixels are independent: the order in which the lanes visit them is free.)"""
    tile = first + wp.tid()
    base = tile * TILE_PIXELS
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(tile, tiles_x, view_tiles, cams)
    reset_rows(base, 0, 1, transmittance, front, done)
    remaining = (x_hi - x_lo) * (y_hi - y_lo)
    for k in range(tile_start[tile], tile_end[tile]):
        sum_xy = wp.vec2(0.0, 0.0)
        sum_co = wp.vec3(0.0, 0.0, 0.0)
        sum_op = float(0.0)
        sum_rgb = wp.vec3(0.0, 0.0, 0.0)
        gx0, gx1, gy0, gy1 = entry_columns(e_box[k], x_lo, x_hi, y_lo, y_hi)
        if remaining > 0 and gx0 <= gx1 and gy0 <= gy1:  # else every lane's sum is 0, and 0 + 0 = 0
            p = e_xy[k]
            co = e_conic_opacity[k]
            rgb = e_rgb[k]
            faint = e_faint[k]
            for lane in range(lanes):
                gxy = wp.vec2(0.0, 0.0)
                gco = wp.vec3(0.0, 0.0, 0.0)
                gop = float(0.0)
                grgb = wp.vec3(0.0, 0.0, 0.0)
                first_row = gy0 + ((lane - (gy0 - y_lo)) % lanes + lanes) % lanes
                for py in range(first_row, gy1 + 1, lanes):
                    gxy, gco, gop, grgb, finished = row_gradients(
                        view, py, gx0, gx1, base + (py - y_lo) * TILE - x_lo, p, co, rgb, faint,
                        image, grad_image, transmittance, front, done, gxy, gco, gop, grgb, colours,
                    )
                    remaining -= finished
                sum_xy = sum_xy + gxy
                sum_co = sum_co + gco
                sum_op = sum_op + gop
                sum_rgb = sum_rgb + grgb
        g_xy[k] = sum_xy
        g_conic[k] = sum_co
        g_opacity[k] = sum_op
        g_rgb[k] = sum_rgb


@wp.kernel
def sum_lanes(
    first: int,
    lanes: int,
    lane_xy: wp.array(dtype=wp.vec2),
    lane_conic: wp.array(dtype=wp.vec3),
    lane_opacity: wp.array(dtype=float),
    lane_rgb: wp.array(dtype=wp.vec3),
    g_xy: wp.array(dtype=wp.vec2),
    g_conic: wp.array(dtype=wp.vec3),
    g_opacity: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
):
    """Per entry k: the sum of its lanes' gradients, lane 0 first."""
    k = first + wp.tid()
    gxy = wp.vec2(0.0, 0.0)
    gco = wp.vec3(0.0, 0.0, 0.0)
    gop = float(0.0)
    grgb = wp.vec3(0.0, 0.0, 0.0)
    for lane in range(lanes):
        j = k * lanes + lane
        gxy = gxy + lane_xy[j]
        gco = gco + lane_conic[j]
        gop = gop + lane_opacity[j]
        grgb = grgb + lane_rgb[j]
    g_xy[k] = gxy
    g_conic[k] = gco
    g_opacity[k] = gop
    g_rgb[k] = grgb


@wp.func
def entry_tile_columns(key: wp.int64, bx: wp.vec4, tiles_x: int, view_tiles: int, cams: wp.array(dtype=CameraParams)):
    """``entry_columns`` of a sorted entry (key = tile << 32 | depth) in its own tile, and the
    tile's first pixel (x_lo, y_lo)."""
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(wp.int32(key >> wp.int64(32)), tiles_x, view_tiles, cams)
    gx0, gx1, gy0, gy1 = entry_columns(bx, x_lo, x_hi, y_lo, y_hi)
    return gx0, gx1, gy0, gy1, x_lo, y_lo


@wp.kernel
def pixel_areas(
    first: int,
    keys: wp.array(dtype=wp.int64),
    e_box: wp.array(dtype=wp.vec4),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    areas: wp.array(dtype=wp.int32),
):
    """Per entry: the pixels of its tile that its box reaches (its slots in the per-pixel buffers)."""
    k = first + wp.tid()
    gx0, gx1, gy0, gy1, x_lo, y_lo = entry_tile_columns(keys[k], e_box[k], tiles_x, view_tiles, cams)
    area = int(0)
    if gx0 <= gx1 and gy0 <= gy1:
        area = (gx1 - gx0 + 1) * (gy1 - gy0 + 1)
    areas[k] = area


@wp.func
def thread_pixel(tid: int, tiles_x: int, view_tiles: int, cams: wp.array(dtype=CameraParams)):
    """Thread ``tid`` of a walk with a thread per pixel (256 consecutive threads per tile, row-major):
    (tile, view, the tile's bounds x_lo, x_hi, y_lo, y_hi in its view: ``view_tile_bounds``, px, py)."""
    tile = tid / TILE_PIXELS
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(tile, tiles_x, view_tiles, cams)
    local = tid - tile * TILE_PIXELS
    return tile, view, x_lo, x_hi, y_lo, y_hi, x_lo + local - (local / TILE) * TILE, y_lo + local / TILE


@wp.func
def pixel_slot(slot_ends: wp.array(dtype=wp.int32), k: int, gx0: int, gx1: int, gy0: int, gy1: int, px: int, py: int):
    """Entry k's slot for pixel (px, py) of its box's columns gx0..gx1 and rows gy0..gy1: the pixel's
    place, row-major, among the box's slots, which end at ``slot_ends[k]``."""
    columns = gx1 - gx0 + 1
    return slot_ends[k] - columns * (gy1 - gy0 + 1) + (py - gy0) * columns + px - gx0


@wp.kernel
def composite_backward_pixels(
    first: int,
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    colours: int,
    image: wp.array4d(dtype=float),
    grad_image: wp.array4d(dtype=float),
    slot_ends: wp.array(dtype=wp.int32),
    p_xy: wp.array(dtype=wp.vec2),
    p_conic: wp.array(dtype=wp.vec3),
    p_opacity: wp.array(dtype=float),
    p_rgb: wp.array(dtype=wp.vec3),
    stops: wp.array(dtype=wp.int32),
):
    """One thread per pixel (256 per tile, as ``render.composite``): the pixel's own term of each
    entry's gradients (``row_gradients``' arithmetic, term by term), written to the entry's slot for
    this pixel (the pixel's place, row-major, in the entry's box, whose slots end at ``slot_ends[k]``:
    the inclusive running sum of ``pixel_areas``): zero where the entry's alpha is 0 there; and in
    ``stops[tid]`` (the pixel's slot of its tile) the entry the pixel finished at (its tile's end
    if none), whose slot and those of every later entry of the tile are not written. ``sum_pixels``
    then adds the slots before each pixel's stop in ``composite_backward``'s order: the same bits,
    with a thread per pixel instead of one per row. Tiles of several views as in ``view_tile_bounds``."""
    tid = first + wp.tid()
    tile, view, x_lo, x_hi, y_lo, y_hi, px, py = thread_pixel(tid, tiles_x, view_tiles, cams)
    if px >= x_hi or py >= y_hi:
        return
    g = wp.vec3(grad_image[view, py, px, 0], grad_image[view, py, px, 1], grad_image[view, py, px, 2])
    final = wp.vec3(image[view, py, px, 0], image[view, py, px, 1], image[view, py, px, 2])
    t = float(1.0)
    front = wp.vec3(0.0, 0.0, 0.0)
    fpx = float(px)
    fpy = float(py)
    stop = tile_end[tile]
    for k in range(tile_start[tile], tile_end[tile]):
        bx = e_box[k]
        if outside(bx, fpx, fpy):
            continue  # outside the entry's box: ``entry_columns`` would leave the pixel out too
        gx0, gx1, gy0, gy1 = entry_columns(bx, x_lo, x_hi, y_lo, y_hi)
        if px < gx0 or px > gx1 or py < gy0 or py > gy1:
            continue
        slot = pixel_slot(slot_ends, k, gx0, gx1, gy0, gy1, px, py)
        co = e_conic_opacity[k]
        dx, dy, gauss, raw, alpha = entry_at_pixel(e_xy[k], co, e_faint[k], fpx, fpy)
        if alpha == 0.0:
            p_rgb[slot] = wp.vec3(0.0, 0.0, 0.0)
            if colours == 0:
                p_opacity[slot] = 0.0
                p_conic[slot] = wp.vec3(0.0, 0.0, 0.0)
                p_xy[slot] = wp.vec2(0.0, 0.0)
            continue
        test_t = t * (1.0 - alpha)
        if test_t < T_MIN:
            stop = k  # the pixel is finished: no later entry reaches it
            break
        g_rgb, in_front, g_op, g_co, g_xy = pixel_terms(t, alpha, gauss, raw, dx, dy, co, e_rgb[k], g, final, front, colours)
        p_rgb[slot] = g_rgb
        if colours == 0:
            p_opacity[slot] = g_op
            p_conic[slot] = g_co
            p_xy[slot] = g_xy
        front = in_front
        t = test_t
    stops[tid] = stop


@wp.kernel
def sum_pixels(
    first: int,
    keys: wp.array(dtype=wp.int64),
    e_box: wp.array(dtype=wp.vec4),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    colours: int,
    slot_ends: wp.array(dtype=wp.int32),
    p_xy: wp.array(dtype=wp.vec2),
    p_conic: wp.array(dtype=wp.vec3),
    p_opacity: wp.array(dtype=float),
    p_rgb: wp.array(dtype=wp.vec3),
    stops: wp.array(dtype=wp.int32),
    g_xy: wp.array(dtype=wp.vec2),
    g_conic: wp.array(dtype=wp.vec3),
    g_opacity: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
):
    """Per entry k: its per-pixel terms summed row by row (each row from 0 in column order), the
    rows from 0 in row order: ``composite_backward``'s order at 16 lanes followed by ``sum_lanes``
    (a lane per row), leaving out the pixels that finished at or before k (``stops``), whose slots
    were not written. The lanes add a zero there and wherever the entry's alpha is 0 (a zero slot
    here): a sum that starts at +0 is never -0, and adding +0 or -0 to it changes no bit."""
    k = first + wp.tid()
    gx0, gx1, gy0, gy1, x_lo, y_lo = entry_tile_columns(keys[k], e_box[k], tiles_x, view_tiles, cams)
    base = wp.int32(keys[k] >> wp.int64(32)) * TILE_PIXELS - y_lo * TILE - x_lo  # + py TILE + px: the pixel's stop
    sum_xy = wp.vec2(0.0, 0.0)
    sum_co = wp.vec3(0.0, 0.0, 0.0)
    sum_op = float(0.0)
    sum_rgb = wp.vec3(0.0, 0.0, 0.0)
    if gx0 <= gx1 and gy0 <= gy1:
        slot = slot_ends[k] - (gx1 - gx0 + 1) * (gy1 - gy0 + 1)
        for py in range(gy0, gy1 + 1):
            gxy = wp.vec2(0.0, 0.0)
            gco = wp.vec3(0.0, 0.0, 0.0)
            gop = float(0.0)
            grgb = wp.vec3(0.0, 0.0, 0.0)
            for px in range(gx0, gx1 + 1):
                if k < stops[base + py * TILE + px]:
                    grgb = grgb + p_rgb[slot]
                    if colours == 0:
                        gxy = gxy + p_xy[slot]
                        gco = gco + p_conic[slot]
                        gop = gop + p_opacity[slot]
                slot += 1
            sum_xy = sum_xy + gxy
            sum_co = sum_co + gco
            sum_op = sum_op + gop
            sum_rgb = sum_rgb + grgb
    g_xy[k] = sum_xy
    g_conic[k] = sum_co
    g_opacity[k] = sum_op
    g_rgb[k] = sum_rgb


@wp.func
def _sh_term(
    features: wp.array2d(dtype=float),
    g_features: wp.array2d(dtype=float),
    i: int,
    rest: int,
    j: int,
    basis: float,
    grad_basis: wp.vec3,
    g_rgb: wp.vec3,
    g_dir: wp.vec3,
):
    """One SH term rgb += basis_j(d) f_j: dL/df_j += basis_j g_rgb; returns g_dir + grad basis_j (f_j . g_rgb)."""
    for ch in range(3):
        col = 2 + ch * rest + j
        g_features[i, col] = g_features[i, col] + basis * g_rgb[ch]
    return g_dir + grad_basis * wp.dot(_sh_coef(features, i, rest, j), g_rgb)


@wp.func
def sh_backward(
    features: wp.array2d(dtype=float),
    g_features: wp.array2d(dtype=float),
    i: int,
    degree: int,
    d: wp.vec3,
    g_rgb: wp.vec3,
):
    """Adds dL/df for rgb = sum_j basis_j(d) f_j + 0.5 (``render.sh_to_rgb``, before its clamp) to row i of
    ``g_features``; returns dL/dd, d the unit view direction."""
    rest = (degree + 1) * (degree + 1) - 1
    for ch in range(3):
        g_features[i, ch] = g_features[i, ch] + SH_C0 * g_rgb[ch]
    g_dir = wp.vec3(0.0, 0.0, 0.0)
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        g_dir = _sh_term(features, g_features, i, rest, 1, -SH_C1 * y, wp.vec3(0.0, -SH_C1, 0.0), g_rgb, g_dir)
        g_dir = _sh_term(features, g_features, i, rest, 2, SH_C1 * z, wp.vec3(0.0, 0.0, SH_C1), g_rgb, g_dir)
        g_dir = _sh_term(features, g_features, i, rest, 3, -SH_C1 * x, wp.vec3(-SH_C1, 0.0, 0.0), g_rgb, g_dir)
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            xy = x * y
            yz = y * z
            xz = x * z
            g_dir = _sh_term(features, g_features, i, rest, 4, SH_C2_0 * xy, SH_C2_0 * wp.vec3(y, x, 0.0), g_rgb, g_dir)
            g_dir = _sh_term(features, g_features, i, rest, 5, SH_C2_1 * yz, SH_C2_1 * wp.vec3(0.0, z, y), g_rgb, g_dir)
            g_dir = _sh_term(
                features, g_features, i, rest, 6, SH_C2_2 * (2.0 * zz - xx - yy),
                SH_C2_2 * wp.vec3(-2.0 * x, -2.0 * y, 4.0 * z), g_rgb, g_dir,
            )  # fmt: skip
            g_dir = _sh_term(features, g_features, i, rest, 7, SH_C2_3 * xz, SH_C2_3 * wp.vec3(z, 0.0, x), g_rgb, g_dir)
            g_dir = _sh_term(
                features, g_features, i, rest, 8, SH_C2_4 * (xx - yy), SH_C2_4 * wp.vec3(2.0 * x, -2.0 * y, 0.0), g_rgb, g_dir
            )
            if degree > 2:
                g_dir = _sh_term(
                    features, g_features, i, rest, 9, SH_C3_0 * y * (3.0 * xx - yy),
                    SH_C3_0 * wp.vec3(6.0 * xy, 3.0 * xx - 3.0 * yy, 0.0), g_rgb, g_dir,
                )  # fmt: skip
                g_dir = _sh_term(
                    features, g_features, i, rest, 10, SH_C3_1 * xy * z, SH_C3_1 * wp.vec3(yz, xz, xy), g_rgb, g_dir
                )
                g_dir = _sh_term(
                    features, g_features, i, rest, 11, SH_C3_2 * y * (4.0 * zz - xx - yy),
                    SH_C3_2 * wp.vec3(-2.0 * xy, 4.0 * zz - xx - 3.0 * yy, 8.0 * yz), g_rgb, g_dir,
                )  # fmt: skip
                g_dir = _sh_term(
                    features, g_features, i, rest, 12, SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                    SH_C3_3 * wp.vec3(-6.0 * xz, -6.0 * yz, 6.0 * zz - 3.0 * xx - 3.0 * yy), g_rgb, g_dir,
                )  # fmt: skip
                g_dir = _sh_term(
                    features, g_features, i, rest, 13, SH_C3_4 * x * (4.0 * zz - xx - yy),
                    SH_C3_4 * wp.vec3(4.0 * zz - 3.0 * xx - yy, -2.0 * xy, 8.0 * xz), g_rgb, g_dir,
                )  # fmt: skip
                g_dir = _sh_term(
                    features, g_features, i, rest, 14, SH_C3_5 * z * (xx - yy),
                    SH_C3_5 * wp.vec3(2.0 * xz, -2.0 * yz, xx - yy), g_rgb, g_dir,
                )  # fmt: skip
                g_dir = _sh_term(
                    features, g_features, i, rest, 15, SH_C3_6 * x * (xx - 3.0 * yy),
                    SH_C3_6 * wp.vec3(3.0 * xx - 3.0 * yy, -6.0 * xy, 0.0), g_rgb, g_dir,
                )  # fmt: skip
    return g_dir


@wp.func
def quat_matrix_backward(q: wp.quat, g: wp.mat33):
    """dL/dq of R(q) (Warp's quat_to_matrix, q = (x, y, z, w) unit) given G = dL/dR."""
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    gx = 2.0 * y * (g[0, 1] + g[1, 0]) + 2.0 * z * (g[0, 2] + g[2, 0]) + 2.0 * w * (g[2, 1] - g[1, 2]) - 4.0 * x * (g[1, 1] + g[2, 2])
    gy = 2.0 * x * (g[0, 1] + g[1, 0]) + 2.0 * w * (g[0, 2] - g[2, 0]) + 2.0 * z * (g[1, 2] + g[2, 1]) - 4.0 * y * (g[0, 0] + g[2, 2])
    gz = 2.0 * w * (g[1, 0] - g[0, 1]) + 2.0 * x * (g[0, 2] + g[2, 0]) + 2.0 * y * (g[1, 2] + g[2, 1]) - 4.0 * z * (g[0, 0] + g[1, 1])
    gw = 2.0 * z * (g[1, 0] - g[0, 1]) + 2.0 * y * (g[0, 2] - g[2, 0]) + 2.0 * x * (g[2, 1] - g[1, 2])
    return wp.quat(gx, gy, gz, gw)


@wp.func
def colour_backward(
    i: int,
    means: wp.array(dtype=wp.vec3),
    features: wp.array2d(dtype=float),
    g_features: wp.array2d(dtype=float),
    degree: int,
    cam: CameraParams,
    grgb: wp.vec3,
):
    """Adds dL/df of splat i's colour in the view of ``cam``, given dL/drgb ``grgb``, to row i of
    ``g_features``: rgb = max(SH(d) + 0.5, 0), d = (mean - centre) / |mean - centre|. Returns
    (dL/dd, d, |mean - centre|), whose chain to the mean is the caller's."""
    dvec = means[i] - cam.centre
    dn = wp.length(dvec)
    d = dvec
    if dn > 0.0:
        d = dvec / dn
    rgb = sh_to_rgb(features, i, degree, d)
    g_pre = wp.vec3(0.0, 0.0, 0.0)
    for ch in range(3):
        if rgb[ch] > 0.0:
            g_pre[ch] = grgb[ch]
    g_dir = sh_backward(features, g_features, i, degree, d, g_pre)
    return g_dir, d, dn


@wp.func
def splat_view_backward(
    i: int,
    row: int,
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    degree: int,
    colours: int,
    cam: CameraParams,
    touched: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    entry_of_slot: wp.array(dtype=wp.int32),
    e_g_xy: wp.array(dtype=wp.vec2),
    e_g_conic: wp.array(dtype=wp.vec3),
    e_g_opacity: wp.array(dtype=float),
    e_g_rgb: wp.array(dtype=wp.vec3),
    g_means: wp.array(dtype=wp.vec3),
    g_rotations: wp.array(dtype=wp.quat),
    g_log_scales: wp.array(dtype=wp.vec3),
    g_opacities: wp.array(dtype=float),
    g_features: wp.array2d(dtype=float),
):
    """Splat i in the view of ``cam`` (its projection in row ``row``: ``render.project_shape``): its
    entries' gradients summed in slot order, then the chain rule back to the parameters
    (``render.splat_shape`` and ``render.project_shape`` differentiated), added to row i of the g_
    arrays; where ``colours`` is nonzero, the colours' alone (``g_features``: the same bits)."""
    n = touched[row]
    if n == 0:
        return  # culled in this view: no pixel depends on it
    if colours != 0:
        grgb = wp.vec3(0.0, 0.0, 0.0)
        for slot in range(ends[row] - n, ends[row]):
            grgb = grgb + e_g_rgb[entry_of_slot[slot]]
        colour_backward(i, means, features, g_features, degree, cam, grgb)
        return
    gxy = wp.vec2(0.0, 0.0)
    gco = wp.vec3(0.0, 0.0, 0.0)
    gop = float(0.0)
    grgb = wp.vec3(0.0, 0.0, 0.0)
    for slot in range(ends[row] - n, ends[row]):
        k = entry_of_slot[slot]
        gxy = gxy + e_g_xy[k]
        gco = gco + e_g_conic[k]
        gop = gop + e_g_opacity[k]
        grgb = grgb + e_g_rgb[k]

    # Forward again (as render.project).
    t = cam.rotation * means[i] + cam.translation
    z = t[2]
    q = rotations[i]
    qn = wp.length(q)
    qu = q / qn
    r = wp.quat_to_matrix(qu)
    s = log_scales[i]
    scale = wp.vec3(exp32(s[0]), exp32(s[1]), exp32(s[2]))
    m = scaled_columns(r, scale)
    sigma = gram(m)
    rx = t[0] / z
    ry = t[1] / z
    tx = wp.clamp(rx, -cam.lim_x, cam.lim_x) * z
    ty = wp.clamp(ry, -cam.lim_y, cam.lim_y) * z
    j0 = wp.vec3(cam.fx / z, 0.0, -cam.fx * tx / (z * z))
    j1 = wp.vec3(0.0, cam.fy / z, -cam.fy * ty / (z * z))
    wt = wp.transpose(cam.rotation)
    u = wt * j0
    v = wt * j1
    su = sigma * u
    sv = sigma * v
    a = wp.dot(u, su) + LOW_PASS
    b = wp.dot(u, sv)
    c = wp.dot(v, sv) + LOW_PASS
    det = a * c - b * b
    opacity = sigmoid32(opacities[i])

    # Conic (A, B, C) = (c, -b, a) / det:
    # dA/d(a, b, c) = (-c^2, 2bc, -b^2)/det^2, dB = (bc, -det - 2b^2, ab)/det^2, dC = (-b^2, 2ab, -a^2)/det^2.
    inv2 = 1.0 / (det * det)
    ga = (-c * c * gco[0] + b * c * gco[1] - b * b * gco[2]) * inv2
    gb = (2.0 * b * c * gco[0] - (det + 2.0 * b * b) * gco[1] + 2.0 * a * b * gco[2]) * inv2
    gc = (-b * b * gco[0] + a * b * gco[1] - a * a * gco[2]) * inv2

    # a = u^T Sigma u, b = u^T Sigma v, c = v^T Sigma v: dL/dSigma = ga uu^T + gb uv^T + gc vv^T.
    g_sigma = ga * wp.outer(u, u) + gb * wp.outer(u, v) + gc * wp.outer(v, v)
    gu = 2.0 * ga * su + gb * sv
    gv = gb * su + 2.0 * gc * sv
    gj0 = cam.rotation * gu  # u = W^T j0
    gj1 = cam.rotation * gv

    # j0 = (fx/z, 0, -fx tx/z^2), j1 = (0, fy/z, -fy ty/z^2); tx = clamp(x/z) z.
    z2 = z * z
    gz = -gj0[0] * cam.fx / z2 + gj0[2] * 2.0 * cam.fx * tx / (z2 * z)
    gz = gz - gj1[1] * cam.fy / z2 + gj1[2] * 2.0 * cam.fy * ty / (z2 * z)
    gtx = -gj0[2] * cam.fx / z2
    gty = -gj1[2] * cam.fy / z2
    gt = wp.vec3(0.0, 0.0, 0.0)
    if rx > -cam.lim_x and rx < cam.lim_x:
        gt[0] = gtx
    else:
        gz += gtx * wp.clamp(rx, -cam.lim_x, cam.lim_x)
    if ry > -cam.lim_y and ry < cam.lim_y:
        gt[1] = gty
    else:
        gz += gty * wp.clamp(ry, -cam.lim_y, cam.lim_y)
    # px = fx x/z + cx - 1/2, py = fy y/z + cy - 1/2
    gt[0] = gt[0] + gxy[0] * cam.fx / z
    gt[1] = gt[1] + gxy[1] * cam.fy / z
    gz = gz - gxy[0] * cam.fx * t[0] / z2 - gxy[1] * cam.fy * t[1] / z2
    gt[2] = gz
    g_mean = wt * gt  # t = W mean + translation

    # Sigma = M M^T, M = R diag(s): dL/dM = (G + G^T) M, dL/ds_k = dM[:, k].R[:, k], dL/dR[:, k] = dM[:, k] s_k.
    gm = matrix_product(g_sigma + wp.transpose(g_sigma), m)
    g_r = scaled_columns(gm, scale)
    g_scale = wp.vec3(0.0, 0.0, 0.0)
    for col in range(3):
        g_scale[col] = (gm[0, col] * r[0, col] + gm[1, col] * r[1, col] + gm[2, col] * r[2, col]) * scale[col]
    # q_unit = q / |q|: dL/dq = (g - q_unit (q_unit . g)) / |q|
    gq_unit = quat_matrix_backward(qu, g_r)
    gq = (gq_unit - qu * wp.dot(qu, gq_unit)) / qn

    g_dir, d, dn = colour_backward(i, means, features, g_features, degree, cam, grgb)
    if dn > 0.0:
        g_mean = g_mean + (g_dir - d * wp.dot(d, g_dir)) / dn

    g_means[i] = g_means[i] + g_mean
    g_rotations[i] = g_rotations[i] + gq
    g_log_scales[i] = g_log_scales[i] + g_scale
    g_opacities[i] = g_opacities[i] + gop * opacity * (1.0 - opacity)


@wp.kernel
def splat_backward(
    first: int,
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    degree: int,
    colours: int,
    cams: wp.array(dtype=CameraParams),
    touched: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    entry_of_slot: wp.array(dtype=wp.int32),
    e_g_xy: wp.array(dtype=wp.vec2),
    e_g_conic: wp.array(dtype=wp.vec3),
    e_g_opacity: wp.array(dtype=float),
    e_g_rgb: wp.array(dtype=wp.vec3),
    g_means: wp.array(dtype=wp.vec3),
    g_rotations: wp.array(dtype=wp.quat),
    g_log_scales: wp.array(dtype=wp.vec3),
    g_opacities: wp.array(dtype=float),
    g_features: wp.array2d(dtype=float),
):
    """Per splat i: ``splat_view_backward`` for each of the views of ``cams`` in order (its rows
    v n + i of ``render.project_views``), so that its gradients add up view by view in the same
    order as when the views are back-propagated one at a time. ``colours`` nonzero: the colours'
    gradients alone (``splat_view_backward``)."""
    i = first + wp.tid()
    n = means.shape[0]
    for v in range(cams.shape[0]):
        splat_view_backward(i, v * n + i, means, rotations, log_scales, opacities, features, degree, colours, cams[v], touched, ends,
                            entry_of_slot, e_g_xy, e_g_conic, e_g_opacity, e_g_rgb, g_means, g_rotations, g_log_scales,
                            g_opacities, g_features)  # fmt: skip


@wp.kernel
def composite_tile_weights(
    first: int,
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    background: wp.vec3,
    slot_ends: wp.array(dtype=wp.int32),
    chunk: int,
    transmittance: wp.array(dtype=float),
    colour: wp.array(dtype=wp.vec3),
    done: wp.array(dtype=wp.int32),
    chunk_state: wp.array(dtype=wp.vec2),
    total: wp.array(dtype=wp.vec3),
    image: wp.array4d(dtype=float),
    weights: wp.array(dtype=float),
    stops: wp.array(dtype=wp.int32),
):
    """The forward's weights for the CPU: one thread per tile, entry by entry over the pixels of each
    entry's box (``render.composite_tiles``' walk, its per-pixel state in the tile's slots of
    ``transmittance``, ``colour`` and ``done``). A tile of more than ``chunk`` entries is walked as
    ``composite_chunk_weights`` and ``merge_chunk_weights`` walk it on a GPU, chunk by chunk from
    each chunk's transmittance before it (in ``chunk_state``: that and the chunk's own; in ``total``
    the colour of the chunks before), its stop the first chunk's where the pixel stops or where the
    transmittance before a chunk falls below T_MIN. Each pixel sees the same entries in the same
    order with the same float32 arithmetic, so the pixels, weights and stops are the GPU's."""
    tile = first + wp.tid()
    base = tile * TILE_PIXELS
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(tile, tiles_x, view_tiles, cams)
    start = tile_start[tile]
    end = tile_end[tile]
    for s in range(TILE_PIXELS):
        transmittance[base + s] = 1.0
        colour[base + s] = wp.vec3(0.0, 0.0, 0.0)
        done[base + s] = 0
        stops[base + s] = end
        chunk_state[base + s] = wp.vec2(1.0, 1.0)
        total[base + s] = wp.vec3(0.0, 0.0, 0.0)
    remaining = (x_hi - x_lo) * (y_hi - y_lo)
    chunked = end - start > chunk  # else one chunk: ``render.composite``'s one walk
    # done: 0 compositing, 1 stopped (T (1 - alpha) < T_MIN) in this chunk, 2 finished after a chunk
    chunk_first = start
    while chunk_first < end and remaining > 0:
        chunk_last = end
        if chunked:
            chunk_last = wp.min(chunk_first + chunk, end)
        last = chunk_last == end
        for k in range(chunk_first, chunk_last):
            if remaining == 0:
                break  # every pixel finished: no later entry is read back
            gx0, gx1, gy0, gy1 = entry_columns(e_box[k], x_lo, x_hi, y_lo, y_hi)
            if gx1 < gx0 or gy1 < gy0:
                continue
            p = e_xy[k]
            co = e_conic_opacity[k]
            rgb = e_rgb[k]
            faint = e_faint[k]
            slot = slot_ends[k] - (gx1 - gx0 + 1) * (gy1 - gy0 + 1)
            for py in range(gy0, gy1 + 1):
                row = base + (py - y_lo) * TILE - x_lo
                for px in range(gx0, gx1 + 1):
                    pixel = row + px
                    if done[pixel] == 0:
                        dx, dy, gauss, raw, alpha = entry_at_pixel(p, co, faint, float(px), float(py))
                        if alpha == 0.0:
                            weights[slot] = 0.0
                        else:
                            if chunked and not last:
                                chunk_own_step(chunk_state, pixel, alpha)
                            t = transmittance[pixel]
                            test_t = t * (1.0 - alpha)
                            if test_t < T_MIN:
                                done[pixel] = 1
                                stops[pixel] = k
                                remaining -= 1
                            else:
                                weight = alpha * t
                                weights[slot] = weight
                                colour[pixel] = colour[pixel] + rgb * weight
                                transmittance[pixel] = test_t
                    slot += 1
        if chunked:  # ``merge_chunk_weights``' sums and ``chunk_prefix``'s next start, as ``render.composite_tiles``
            for py in range(y_lo, y_hi):
                for px in range(x_lo, x_hi):
                    pixel = base + (py - y_lo) * TILE + px - x_lo
                    if chunk_end(pixel, last, done, colour, total, chunk_state, transmittance) == 1:
                        stops[pixel] = chunk_last  # it ran out before the next chunk: its stop is there
                        remaining -= 1
        chunk_first = chunk_last
    for py in range(y_lo, y_hi):
        for px in range(x_lo, x_hi):
            pixel = base + (py - y_lo) * TILE + px - x_lo
            c = colour[pixel]
            if chunked:
                c = total[pixel]
            c = c + background * transmittance[pixel]
            image[view, py, px, 0] = c[0]
            image[view, py, px, 1] = c[1]
            image[view, py, px, 2] = c[2]


@wp.func
def chunk_pixel(c: int, tid: int, chunk_tile: wp.array(dtype=wp.int32), tiles_x: int, view_tiles: int, cams: wp.array(dtype=CameraParams)):
    """Thread ``tid`` of chunk ``c`` in a walk with a thread per (chunk, pixel), 256 consecutive threads a
    chunk: (view, the chunk's tile's bounds x_lo, x_hi, y_lo, y_hi in its view, px, py)."""
    view, x_lo, x_hi, y_lo, y_hi = view_tile_bounds(chunk_tile[c], tiles_x, view_tiles, cams)
    local = tid - c * TILE_PIXELS
    return view, x_lo, x_hi, y_lo, y_hi, x_lo + local - (local / TILE) * TILE, y_lo + local / TILE


@wp.func
def weighted_chunk(
    e_xy: wp.array(dtype=wp.vec2),
    e_conic_opacity: wp.array(dtype=wp.vec4),
    e_rgb: wp.array(dtype=wp.vec3),
    e_box: wp.array(dtype=wp.vec4),
    e_faint: wp.array(dtype=float),
    first: int,
    last: int,
    x_lo: int,
    x_hi: int,
    y_lo: int,
    y_hi: int,
    px: int,
    py: int,
    t: float,
    slot_ends: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
):
    """``render.walked_chunk``'s walk of entries [first, last) at pixel (px, py) of a tile [x_lo, x_hi)
    x [y_lo, y_hi) from transmittance ``t``, keeping each entry's weight alpha_k T_k in the entry's
    slot for the pixel (``pixel_slot``; 0 where its alpha is 0 there): (colour and the transmittance
    after, negated where the pixel stopped in the range; the entry it stopped at, ``last`` where it
    did not)."""
    fpx = float(px)
    fpy = float(py)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    stopped = float(1.0)
    stop = last
    for k in range(first, last):
        bx = e_box[k]
        if outside(bx, fpx, fpy):
            continue  # outside the entry's box (as in ``composite_backward_pixels``)
        gx0, gx1, gy0, gy1 = entry_columns(bx, x_lo, x_hi, y_lo, y_hi)
        if px < gx0 or px > gx1 or py < gy0 or py > gy1:
            continue
        slot = pixel_slot(slot_ends, k, gx0, gx1, gy0, gy1, px, py)
        dx, dy, gauss, raw, alpha = entry_at_pixel(e_xy[k], e_conic_opacity[k], e_faint[k], fpx, fpy)
        if alpha == 0.0:
            weights[slot] = 0.0
            continue
        test_t = t * (1.0 - alpha)
        if test_t < T_MIN:
            stopped = -1.0
            stop = k
            break
        weight = alpha * t
        weights[slot] = weight
        rgb = rgb + e_rgb[k] * weight
        t = test_t
    return wp.vec4(rgb[0], rgb[1], rgb[2], stopped * t), stop


@wp.kernel
def chunk_own_transmittance(
    first: int,
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
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    tiles: int,
    slot_ends: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    transmittance: wp.array(dtype=float),
    colour: wp.array(dtype=wp.vec4),
    chunk_stop: wp.array(dtype=wp.int32),
):
    """``render.chunk_transmittance`` for several views' tiles: per (chunk, pixel) the product of
    (1 - alpha) over the chunk's entries, 0 once it falls below T_MIN. A tile's first chunk, which
    starts from T = 1, is walked as ``composite_chunk_weights`` walks it (``weighted_chunk``: its
    weights, colour and stop kept here), its product that walk's transmittance (0 where it stopped:
    the same products); a tile's last chunk but its first and the threads beyond the last chunk are
    skipped."""
    tid = first + wp.tid()
    c = tid / TILE_PIXELS
    if c >= chunk_ends[tiles - 1]:
        return
    tile = chunk_tile[c]
    opening = chunk_first[c] == tile_start[tile]
    if chunk_last[c] == tile_end[tile] and not opening:
        return
    view, x_lo, x_hi, y_lo, y_hi, px, py = chunk_pixel(c, tid, chunk_tile, tiles_x, view_tiles, cams)
    inside = px < x_hi and py < y_hi
    t = float(1.0)
    if opening:
        walked = wp.vec4(0.0, 0.0, 0.0, -1.0)
        stop = chunk_first[c]
        if inside:
            walked, stop = weighted_chunk(e_xy, e_conic_opacity, e_rgb, e_box, e_faint, chunk_first[c], chunk_last[c],
                                          x_lo, x_hi, y_lo, y_hi, px, py, 1.0, slot_ends, weights)  # fmt: skip
            t = wp.max(walked[3], 0.0)
        colour[tid] = walked
        chunk_stop[tid] = stop
    elif inside:
        t = chunk_product(e_xy, e_conic_opacity, e_box, e_faint, chunk_first[c], chunk_last[c], float(px), float(py))
    transmittance[tid] = t


@wp.kernel
def composite_chunk_weights(
    first: int,
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
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    tiles: int,
    slot_ends: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    colour: wp.array(dtype=wp.vec4),
    chunk_stop: wp.array(dtype=wp.int32),
):
    """Per (chunk, pixel) of every chunk but a tile's first (``chunk_own_transmittance`` walked it):
    ``render.composite_chunks``' walk of the chunk from the transmittance before it (its colour and
    the transmittance after, negated where the pixel stopped here) that also keeps each entry's
    weight alpha_k T_k in the entry's slot for the pixel (``weighted_chunk``), and the entry the pixel
    stopped at in ``chunk_stop`` (the chunk's end where it did not; the chunk's first entry where the
    transmittance before it is 0: it stopped before the chunk)."""
    tid = first + wp.tid()
    c = tid / TILE_PIXELS
    if c >= chunk_ends[tiles - 1]:
        return
    if chunk_first[c] == tile_start[chunk_tile[c]]:
        return
    view, x_lo, x_hi, y_lo, y_hi, px, py = chunk_pixel(c, tid, chunk_tile, tiles_x, view_tiles, cams)
    t = before[tid]
    if px >= x_hi or py >= y_hi or t == 0.0:
        colour[tid] = wp.vec4(0.0, 0.0, 0.0, -1.0)
        chunk_stop[tid] = chunk_first[c]
        return
    walked, stop = weighted_chunk(e_xy, e_conic_opacity, e_rgb, e_box, e_faint, chunk_first[c], chunk_last[c],
                                  x_lo, x_hi, y_lo, y_hi, px, py, t, slot_ends, weights)  # fmt: skip
    colour[tid] = walked
    chunk_stop[tid] = stop


@wp.kernel
def merge_chunk_weights(
    first: int,
    colour: wp.array(dtype=wp.vec4),
    before: wp.array(dtype=float),
    chunk_stop: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    chunk_ends: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    background: wp.vec3,
    image: wp.array4d(dtype=float),
    stops: wp.array(dtype=wp.int32),
):
    """Per pixel (a thread per pixel of each view's own size): ``render.composite_merge``'s sum of its
    tile's chunk colours in order up to the chunk it stopped in, plus the background times the
    transmittance left, and the entry it stopped at in ``stops`` (the first entry that no longer
    counts: the tile's end where it never stopped), as ``composite_backward_pixels`` reads them."""
    tid = first + wp.tid()
    tile, view, x_lo, x_hi, y_lo, y_hi, px, py = thread_pixel(tid, tiles_x, view_tiles, cams)
    if px >= x_hi or py >= y_hi:
        return
    c, t, stopped = merged_chunks(colour, before, counts, chunk_ends, tile, tid - tile * TILE_PIXELS)
    stop = tile_end[tile]
    if stopped >= 0:
        stop = chunk_stop[stopped]
    c = c + background * t
    image[view, py, px, 0] = c[0]
    image[view, py, px, 1] = c[1]
    image[view, py, px, 2] = c[2]
    stops[tid] = stop


@wp.kernel
def sum_weighted_colours(
    first: int,
    keys: wp.array(dtype=wp.int64),
    e_box: wp.array(dtype=wp.vec4),
    cams: wp.array(dtype=CameraParams),
    tiles_x: int,
    view_tiles: int,
    slot_ends: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=float),
    stops: wp.array(dtype=wp.int32),
    grad_image: wp.array4d(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
):
    """Per entry k: dL/drgb_k = sum over its pixels of dL/dC alpha_k T_k, from the forward's kept
    weights (``composite_chunk_weights``, ``composite_tile_weights``), in ``sum_pixels``' order (rows
    of columns, leaving out the pixels finished at or before k): where the forward walked each tile
    once, the bits of ``composite_backward_pixels`` and ``sum_pixels`` with ``colours``, whose colour
    term is the same product dL/dC * (alpha_k T_k) (where alpha is 0 that term is +0 and this one
    +-0: added to a sum, neither changes a bit)."""
    k = first + wp.tid()
    tile = wp.int32(keys[k] >> wp.int64(32))
    view = tile / view_tiles
    gx0, gx1, gy0, gy1, x_lo, y_lo = entry_tile_columns(keys[k], e_box[k], tiles_x, view_tiles, cams)
    base = tile * TILE_PIXELS - y_lo * TILE - x_lo  # + py TILE + px: the pixel's stop
    sum_rgb = wp.vec3(0.0, 0.0, 0.0)
    if gx0 <= gx1 and gy0 <= gy1:
        slot = slot_ends[k] - (gx1 - gx0 + 1) * (gy1 - gy0 + 1)
        for py in range(gy0, gy1 + 1):
            grgb = wp.vec3(0.0, 0.0, 0.0)
            for px in range(gx0, gx1 + 1):
                if k < stops[base + py * TILE + px]:
                    g = wp.vec3(grad_image[view, py, px, 0], grad_image[view, py, px, 1], grad_image[view, py, px, 2])
                    grgb = grgb + g * weights[slot]
                slot += 1
            sum_rgb = sum_rgb + grgb
    g_rgb[k] = sum_rgb
