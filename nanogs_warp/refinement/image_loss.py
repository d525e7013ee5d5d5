"""The training loss of rendered views against their targets, L1 + ssim_weight (1 - SSIM) averaged
over each view's pixels and channels, and its gradient, on the images' device
(``kernels/image_loss.py``): one view at a time, or several rendered together in one set of launches.
A stack of targets is trained toward for many steps, so its own blurred terms are made once
(``target_views``) and every loss against it reads them; where they are not kept (memory), each
loss blurs its own views' targets, the same bits."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..eval.metrics import gaussian_window
from ..kernels import image_loss as kernels
from ..parallel import launch_rows_from

MIN_PIXELS_TO_SPLIT = 4096


def loss_view(target: int, width: int, height: int, ssim_weight: float, weight: float) -> kernels.LossView:
    """View ``target`` of a target stack, of ``width`` x ``height`` pixels, weighted so that its share
    of the loss is weight (mean |X - Y| + ssim_weight (1 - mean SSIM))."""
    per_value = weight / (3.0 * height * width)
    view = kernels.LossView()
    view.target, view.width, view.height = int(target), int(width), int(height)
    view.l1_weight, view.ssim_weight = per_value, per_value * ssim_weight
    return view


@dataclass
class Targets:
    """A stack of target views (T, H, W, 3), view k in the top-left corner of [k], and their blurred
    terms G*Y and G*Y^2 per channel ((T, H, W) of ``vec6``, each at its own view's size), or None:
    each loss then blurs its own views' targets (the same bits)."""

    images: wp.array
    moments: wp.array | None


def _blur_taps(device) -> wp.array:
    return wp.array(gaussian_window().astype(np.float32), dtype=wp.float32, device=device)


def target_views(images: wp.array, sizes: Sequence[tuple[int, int]], moments: bool = True) -> Targets:
    """``images`` (T, H, W, 3) with their blurred terms (none without ``moments``): view k of sizes[k]
    = (width, height) pixels blurred with zero padding at its own edges, one view at a time (the
    scratch is one view's)."""
    if not moments:
        return Targets(images, None)
    device = images.device
    count, height, width = images.shape[0], images.shape[1], images.shape[2]
    blurred = wp.empty((count, height, width), dtype=kernels.vec6, device=device)
    scratch = (wp.empty((1, height, width), dtype=kernels.vec6, device=device),
               wp.empty((1, height, width), dtype=kernels.vec6, device=device))  # fmt: skip
    taps = _blur_taps(device)
    specs = wp.array([loss_view(k, w, h, 0.0, 0.0) for k, (w, h) in enumerate(sizes)], dtype=kernels.LossView, device=device)
    for k in range(count):
        _blur_targets(images, specs[k : k + 1], taps, scratch, blurred[k : k + 1])
    return Targets(images, blurred)


def _blur_targets(images: wp.array, views: wp.array, taps: wp.array, scratch: tuple, blurred: wp.array) -> None:
    """blurred[v] = G*(Y, Y^2) of target ``views[v].target`` of ``images``, at view v's size."""
    device = images.device
    count, height, width = blurred.shape
    stack, half = scratch
    launch_rows_from(kernels.target_inputs, count * height * width, [images, views, stack], device, chunks_per_worker=1,
                     min_rows=MIN_PIXELS_TO_SPLIT)  # fmt: skip
    for vertical, image, target in ((0, stack, half), (1, half, blurred)):
        launch_rows_from(kernels.blur, kernels.blur_threads(count, height, width, vertical), [image, taps, vertical, views, target],
                         device, chunks_per_worker=1, min_rows=MIN_PIXELS_TO_SPLIT // kernels.RUN)  # fmt: skip


class ImageLoss:
    """Scratch buffers for ``views`` views of at most ``height`` x ``width`` pixels, reused across calls."""

    def __init__(self, height: int, width: int, device, views: int = 1):
        self.device = wp.get_device(device)
        self.height, self.width, self.views = height, width, views
        d, shape = self.device, (views, height, width)
        self.taps = _blur_taps(d)
        self.stack = wp.empty(shape, dtype=kernels.vec9, device=d)  # the view's (X, X^2, XY)
        self.half = wp.empty(shape, dtype=kernels.vec9, device=d)  # a blur's horizontal pass
        self.partials = wp.empty(shape, dtype=kernels.vec9, device=d)
        self.target_scratch: tuple | None = None  # the views' targets' blurred terms, where ``Targets`` lacks them
        self.loss = wp.empty(shape, dtype=wp.float32, device=d)
        wp.load_module(kernels, device=d)

    def _runs(self, kernel, vertical: int, inputs: list) -> None:
        # one chunk a CPU worker: every pixel costs the same, and each further chunk is a launch's
        # overhead (at 128 x 128 four a worker took 5.6 ms a loss against 1.8; docs/performance.md)
        threads = kernels.blur_threads(self.views, self.height, self.width, vertical)
        launch_rows_from(kernel, threads, inputs, self.device, chunks_per_worker=1, min_rows=MIN_PIXELS_TO_SPLIT // kernels.RUN)

    def of_views(self, images: wp.array, targets: Targets, grads: wp.array, views: wp.array) -> None:
        """For each view v of ``images`` (V, H, W, 3) and its ``views[v]`` (``loss_view``: its target
        in ``targets`` (``target_views``, (T, H', W', 3), made at the sizes the views give), its size
        and weights): writes d(its share of L)/dimage into grads[v] and each pixel's share into
        ``self.loss``. A view's pixels beyond its own size are neither read nor written (their loss is 0).
        The blur's two passes over the view's (X, X^2, XY), the second also making each pixel's terms
        and partials, then the partials' two, the second also making dL/dimage."""
        target, taps, half = targets.images, self.taps, self.half
        moments, by_view = targets.moments, 0
        if moments is None:  # each view's target blurred here, into row v
            if self.target_scratch is None:
                shape = (self.views, self.height, self.width)
                self.target_scratch = tuple(wp.empty(shape, dtype=kernels.vec6, device=self.device) for _ in range(3))
            *scratch, moments = self.target_scratch
            _blur_targets(target, views, taps, scratch, moments)
            by_view = 1
        launch_rows_from(kernels.ssim_inputs, self.views * self.height * self.width, [images, target, views, self.stack],
                         self.device, chunks_per_worker=1, min_rows=MIN_PIXELS_TO_SPLIT)  # fmt: skip
        self._runs(kernels.blur, 0, [self.stack, taps, 0, views, half])
        self._runs(kernels.ssim_terms, 1, [images, target, views, half, taps, moments, by_view, self.loss, self.partials])
        self._runs(kernels.blur, 0, [self.partials, taps, 0, views, half])
        self._runs(kernels.loss_gradient, 1, [images, target, views, half, taps, grads])

    def __call__(self, image: wp.array, target: wp.array, grad: wp.array, ssim_weight: float, weight: float = 1.0) -> None:
        """One view: writes d(weight L)/dimage into ``grad`` and each pixel's share of weight L into
        ``self.loss``; all three images (H, W, 3). L = mean |image - target| + ssim_weight (1 - mean SSIM)."""
        h, w = self.height, self.width
        views = wp.array([loss_view(0, w, h, ssim_weight, weight)], dtype=kernels.LossView, device=self.device)
        targets = target_views(target.reshape((1, h, w, 3)), [(w, h)])
        self.of_views(image.reshape((1, h, w, 3)), targets, grad.reshape((1, h, w, 3)), views)

    def value(self) -> float:
        """The loss of the last call (a host read: the sum of the per-pixel shares, in float64)."""
        return float(self.loss.numpy().astype(np.float64).sum())
