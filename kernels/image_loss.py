"""The training loss of a rendered view X against a target Y (both (H, W, 3)) and its gradient dL/dX:

    L = l1_weight sum |X - Y| + ssim_weight sum (1 - S),

summed over pixels and channels, S the per-pixel, per-channel SSIM with an 11-tap Gaussian window
(sigma 1.5) and zero padding (the INRIA trainer's ``ssim``), C1 = 0.01^2, C2 = 0.03^2:

    S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sxx + syy + C2)),
    mx = G*X, my = G*Y, sxx = G*X^2 - mx^2, syy = G*Y^2 - my^2, sxy = G*XY - mx my.

With A1 = 2 mx my + C1, A2 = 2 sxy + C2, B1 = mx^2 + my^2 + C1, B2 = sxx + syy + C2:

    dS/dmx = 2 my (A2 - A1) / (B1 B2) - 2 mx S (1/B1 - 1/B2),  dS/d(G*X^2) = -S / B2,
    dS/d(G*XY) = 2 A1 / (B1 B2),

and as the zero-padded Gaussian correlation is its own transpose,

    dL/dX = G*(dL/dmx) + 2 X G*(dL/dG*X^2) + Y G*(dL/dG*XY) + l1_weight sign(X - Y).

The target's terms, my and G*Y^2, do not change while it is trained toward: they are blurred once
per target view (``target_inputs``, then ``blur``), and each loss reads them; where they are not
kept (memory), each loss blurs its own views' targets the same way.

Several views at once: X is (V, H, W, 3), Y a stack of targets, and view v compares X[v] with
target ``views[v].target``, both of its own size ``views[v].width`` x ``views[v].height`` in the
top-left corner (H, W at least every view's). A loss is four passes of the separable blur, each
thread RUN pixels side by side along the pass's axis (``blur_threads``; view-major, then row-major),
over the view's (X, X^2, XY) (``ssim_inputs``) and then the partials, the second and fourth also
making what the pixel's blurred values give (its SSIM terms, dL/dX), each writing only its own
pixels; a pixel outside its view's size is left alone, and the blur reads none
(its zero padding is at the view's own edges), so each view's loss and gradient are the bits of
that view computed alone.
"""

from typing import Any

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

SSIM_C1 = wp.constant(0.0001)
SSIM_C2 = wp.constant(0.0009)
RADIUS = wp.constant(5)
TAPS = wp.constant(11)  # 2 RADIUS + 1: a loop over a constant range is unrolled

vec6 = wp.types.vector(length=6, dtype=wp.float32)  # a target's Y, Y^2 for 3 channels
vec9 = wp.types.vector(length=9, dtype=wp.float32)  # X, X^2, XY; or dL/d(mx, G*X^2, G*XY); for 3 channels


@wp.struct
class LossView:
    """One view of a loss over several: its target in the stack, its size and its two weights."""

    target: int
    width: int
    height: int
    l1_weight: float
    ssim_weight: float


@wp.func
def view_pixel(tid: int, height: int, width: int):
    """(view, row, column) of pixel ``tid`` of a (V, height, width) stack, view-major then row-major."""
    view = tid / (height * width)
    rest = tid - view * (height * width)
    py = rest / width
    return view, py, rest - py * width


@wp.kernel
def target_inputs(
    first: int,
    y: wp.array4d(dtype=float),
    views: wp.array(dtype=LossView),
    stack: wp.array3d(dtype=vec6),
):
    """stack[v, py, px] = (Y, Y^2) of target ``views[v].target``, each for channels 0..2 (6 values)."""
    view, py, px = view_pixel(first + wp.tid(), stack.shape[1], stack.shape[2])
    lv = views[view]
    if px >= lv.width or py >= lv.height:
        return
    v = vec6()
    for ch in range(3):
        b = y[lv.target, py, px, ch]
        v[ch] = b
        v[3 + ch] = b * b
    stack[view, py, px] = v


RUN = wp.constant(4)  # pixels a blur thread computes side by side along its axis (``row_sums`` and ``column_sums`` write out four)


def blur_threads(views: int, height: int, width: int, vertical: int) -> int:
    """The threads a blur pass runs over a (views, height, width) stack: one a RUN of pixels along its
    axis (``blur``, ``ssim_terms``, ``loss_gradient``)."""
    if vertical:
        return views * ((height + RUN - 1) // RUN) * width
    return views * height * ((width + RUN - 1) // RUN)


@wp.func
def run_at(tid: int, height: int, width: int, vertical: int):
    """(view, row, column) of the first pixel of thread ``tid``'s run (``blur_threads``: view-major,
    then row-major over the runs)."""
    rows = height
    columns = (width + RUN - 1) / RUN
    if vertical != 0:
        rows = (height + RUN - 1) / RUN
        columns = width
    view = tid / (rows * columns)
    rest = tid - view * (rows * columns)
    row = rest / columns
    column = rest - row * columns
    if vertical != 0:
        return view, row * RUN, column
    return view, row, column * RUN


@wp.func
def inside_run(start: int, length: int) -> bool:
    """Whether every tap of the RUN pixels from ``start`` on lands inside an axis of ``length`` pixels."""
    return start >= RADIUS and start + RUN - 1 + RADIUS < length


@wp.func
def tap_sum(
    source: wp.array3d(dtype=Any),
    taps: wp.array(dtype=float),
    view: int,
    py: int,
    px: int,
    vertical: int,
    position: int,
    length: int,
):
    """The blur at one pixel, ``position`` along an axis of ``length`` pixels: the centre tap, then the
    other taps that land inside, in order."""
    acc = taps[RADIUS] * source[view, py, px]
    lo = wp.max(0, RADIUS - position)
    hi = wp.min(2 * RADIUS, length - 1 - position + RADIUS)
    for j in range(lo, hi + 1):
        if j != RADIUS:
            if vertical != 0:
                acc += taps[j] * source[view, py + j - RADIUS, px]
            else:
                acc += taps[j] * source[view, py, px + j - RADIUS]
    return acc


@wp.func
def column_sums(source: wp.array3d(dtype=Any), taps: wp.array(dtype=float), view: int, py: int, px: int):
    """``tap_sum`` down the column at rows py .. py + 3 (``inside_run``), their loads shared."""
    centre = taps[RADIUS]
    a0 = centre * source[view, py, px]
    a1 = centre * source[view, py + 1, px]
    a2 = centre * source[view, py + 2, px]
    a3 = centre * source[view, py + 3, px]
    for j in range(TAPS):
        if j != RADIUS:
            tap = taps[j]
            a0 += tap * source[view, py + j - RADIUS, px]
            a1 += tap * source[view, py + 1 + j - RADIUS, px]
            a2 += tap * source[view, py + 2 + j - RADIUS, px]
            a3 += tap * source[view, py + 3 + j - RADIUS, px]
    return a0, a1, a2, a3


@wp.func
def row_sums(source: wp.array3d(dtype=Any), taps: wp.array(dtype=float), view: int, py: int, px: int):
    """``tap_sum`` along the row at columns px .. px + 3 (``inside_run``), their loads shared."""
    centre = taps[RADIUS]
    a0 = centre * source[view, py, px]
    a1 = centre * source[view, py, px + 1]
    a2 = centre * source[view, py, px + 2]
    a3 = centre * source[view, py, px + 3]
    for j in range(TAPS):
        if j != RADIUS:
            tap = taps[j]
            a0 += tap * source[view, py, px + j - RADIUS]
            a1 += tap * source[view, py, px + 1 + j - RADIUS]
            a2 += tap * source[view, py, px + 2 + j - RADIUS]
            a3 += tap * source[view, py, px + 3 + j - RADIUS]
    return a0, a1, a2, a3


@wp.kernel
def blur(
    first: int,
    source: wp.array3d(dtype=Any),
    taps: wp.array(dtype=float),
    vertical: int,
    views: wp.array(dtype=LossView),
    target: wp.array3d(dtype=Any),
):
    """target[v, py, px] = sum_j taps[j] source[v, py, px + j - 5] (vertically: py + j - 5); zero
    outside view v's own size. The centre tap first, then the others in order (``tap_sum``). A thread
    computes RUN pixels side by side along the axis (``blur_threads``); a run whose every tap lands
    inside the view shares its loads (``row_sums``, ``column_sums``: the same sums in the same order),
    at twice the speed of a thread a pixel on the CPU."""
    view, py, px = run_at(first + wp.tid(), source.shape[1], source.shape[2], vertical)
    lv = views[view]
    if py >= lv.height or px >= lv.width:
        return
    if vertical != 0:
        if inside_run(py, lv.height):
            a0, a1, a2, a3 = column_sums(source, taps, view, py, px)
            target[view, py, px] = a0
            target[view, py + 1, px] = a1
            target[view, py + 2, px] = a2
            target[view, py + 3, px] = a3
        else:
            for i in range(RUN):
                if py + i < lv.height:
                    target[view, py + i, px] = tap_sum(source, taps, view, py + i, px, 1, py + i, lv.height)
    else:
        if inside_run(px, lv.width):
            a0, a1, a2, a3 = row_sums(source, taps, view, py, px)
            target[view, py, px] = a0
            target[view, py, px + 1] = a1
            target[view, py, px + 2] = a2
            target[view, py, px + 3] = a3
        else:
            for i in range(RUN):
                if px + i < lv.width:
                    target[view, py, px + i] = tap_sum(source, taps, view, py, px + i, 0, px + i, lv.width)


wp.overload(blur, {"source": wp.array3d(dtype=vec6), "target": wp.array3d(dtype=vec6)})
wp.overload(blur, {"source": wp.array3d(dtype=vec9), "target": wp.array3d(dtype=vec9)})


@wp.kernel
def ssim_inputs(
    first: int,
    x: wp.array4d(dtype=float),
    y: wp.array4d(dtype=float),
    views: wp.array(dtype=LossView),
    stack: wp.array3d(dtype=vec9),
):
    """stack[v, py, px] = (X, X^2, XY), each for channels 0..2 (9 values)."""
    view, py, px = view_pixel(first + wp.tid(), x.shape[1], x.shape[2])
    lv = views[view]
    if px >= lv.width or py >= lv.height:
        return
    v = vec9()
    for ch in range(3):
        a = x[view, py, px, ch]
        v[ch] = a
        v[3 + ch] = a * a
        v[6 + ch] = a * y[lv.target, py, px, ch]
    stack[view, py, px] = v


@wp.func
def ssim_at(
    x: wp.array4d(dtype=float),
    y: wp.array4d(dtype=float),
    lv: LossView,
    view: int,
    py: int,
    px: int,
    mo: vec9,
    tm: vec6,
    loss: wp.array3d(dtype=float),
    partials: wp.array3d(dtype=vec9),
):
    """A pixel's loss terms (summed over channels) and dL/d(mx, G*X^2, G*XY) per channel, with its
    view's weights, from ``mo``, its G*(X, X^2, XY), and ``tm``, its target's G*(Y, Y^2)."""
    l1_weight = lv.l1_weight
    ssim_weight = lv.ssim_weight
    total = float(0.0)
    out = vec9()
    for ch in range(3):
        mx = mo[ch]
        my = tm[ch]
        sxx = mo[3 + ch] - mx * mx
        syy = tm[3 + ch] - my * my
        sxy = mo[6 + ch] - mx * my
        a1 = 2.0 * mx * my + SSIM_C1
        a2 = 2.0 * sxy + SSIM_C2
        b1 = mx * mx + my * my + SSIM_C1
        b2 = sxx + syy + SSIM_C2
        s = (a1 * a2) / (b1 * b2)
        total += l1_weight * wp.abs(x[view, py, px, ch] - y[lv.target, py, px, ch]) + ssim_weight * (1.0 - s)
        g_s = -ssim_weight
        out[ch] = g_s * (2.0 * my * (a2 - a1) / (b1 * b2) - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2))
        out[3 + ch] = g_s * (-s / b2)
        out[6 + ch] = g_s * (2.0 * a1 / (b1 * b2))
    partials[view, py, px] = out
    loss[view, py, px] = total


@wp.kernel
def ssim_terms(
    first: int,
    x: wp.array4d(dtype=float),
    y: wp.array4d(dtype=float),
    views: wp.array(dtype=LossView),
    half: wp.array3d(dtype=vec9),
    taps: wp.array(dtype=float),
    target_moments: wp.array3d(dtype=vec6),
    by_view: int,
    loss: wp.array3d(dtype=float),
    partials: wp.array3d(dtype=vec9),
):
    """The vertical pass of ``blur`` over ``half`` (the horizontal pass of ``ssim_inputs``' stack), giving
    the view's G*(X, X^2, XY),
    and at each pixel its loss terms and partials (``ssim_at``; ``target_moments``: each target's
    G*(Y, Y^2), read at ``views[v].target``, or with ``by_view`` view v's target's at v). The loss
    is 0 outside the view."""
    view, py, px = run_at(first + wp.tid(), x.shape[1], x.shape[2], 1)
    lv = views[view]
    if px >= lv.width or py >= lv.height:
        for i in range(RUN):
            if py + i < x.shape[1]:
                loss[view, py + i, px] = 0.0
        return
    t = lv.target
    if by_view != 0:
        t = view
    if inside_run(py, lv.height):
        a0, a1, a2, a3 = column_sums(half, taps, view, py, px)
        ssim_at(x, y, lv, view, py, px, a0, target_moments[t, py, px], loss, partials)
        ssim_at(x, y, lv, view, py + 1, px, a1, target_moments[t, py + 1, px], loss, partials)
        ssim_at(x, y, lv, view, py + 2, px, a2, target_moments[t, py + 2, px], loss, partials)
        ssim_at(x, y, lv, view, py + 3, px, a3, target_moments[t, py + 3, px], loss, partials)
        return
    for i in range(RUN):
        if py + i < lv.height:
            mo = tap_sum(half, taps, view, py + i, px, 1, py + i, lv.height)
            ssim_at(x, y, lv, view, py + i, px, mo, target_moments[t, py + i, px], loss, partials)
        elif py + i < x.shape[1]:
            loss[view, py + i, px] = 0.0


@wp.func
def gradient_at(x: wp.array4d(dtype=float), y: wp.array4d(dtype=float), lv: LossView, view: int, py: int, px: int, bl: vec9,
                grad: wp.array4d(dtype=float)):  # fmt: skip
    """dL/dX = G*(dL/dmx) + 2 X G*(dL/dG*X^2) + Y G*(dL/dG*XY) + l1_weight sign(X - Y) at a pixel,
    ``bl`` its G*(dL/dmx, dL/dG*X^2, dL/dG*XY)."""
    for ch in range(3):
        a = x[view, py, px, ch]
        b = y[lv.target, py, px, ch]
        g = bl[ch] + 2.0 * a * bl[3 + ch] + b * bl[6 + ch]
        if a > b:
            g += lv.l1_weight
        elif a < b:
            g -= lv.l1_weight
        grad[view, py, px, ch] = g


@wp.kernel
def loss_gradient(
    first: int,
    x: wp.array4d(dtype=float),
    y: wp.array4d(dtype=float),
    views: wp.array(dtype=LossView),
    half: wp.array3d(dtype=vec9),
    taps: wp.array(dtype=float),
    grad: wp.array4d(dtype=float),
):
    """The vertical pass of ``blur`` over ``half`` (the partials' horizontal pass), and at each pixel
    dL/dX (``gradient_at``)."""
    view, py, px = run_at(first + wp.tid(), x.shape[1], x.shape[2], 1)
    lv = views[view]
    if px >= lv.width or py >= lv.height:
        return
    if inside_run(py, lv.height):
        a0, a1, a2, a3 = column_sums(half, taps, view, py, px)
        gradient_at(x, y, lv, view, py, px, a0, grad)
        gradient_at(x, y, lv, view, py + 1, px, a1, grad)
        gradient_at(x, y, lv, view, py + 2, px, a2, grad)
        gradient_at(x, y, lv, view, py + 3, px, a3, grad)
        return
    for i in range(RUN):
        if py + i < lv.height:
            gradient_at(x, y, lv, view, py + i, px, tap_sum(half, taps, view, py + i, px, 1, py + i, lv.height), grad)


@wp.kernel
def halved(first: int, image: wp.array3d(dtype=float), half: wp.array3d(dtype=float)):
    """half[py, px] = the mean of image's 2x2 block at (2 py, 2 px), per channel: 0.25 ((a + b) + (c + d)),
    a b the block's top row, c d its bottom row (a training view at half its size)."""
    tid = first + wp.tid()
    width = half.shape[1]
    py = tid / width
    px = tid - py * width
    for ch in range(3):
        top = image[2 * py, 2 * px, ch] + image[2 * py, 2 * px + 1, ch]
        bottom = image[2 * py + 1, 2 * px, ch] + image[2 * py + 1, 2 * px + 1, ch]
        half[py, px, ch] = 0.25 * (top + bottom)
