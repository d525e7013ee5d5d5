"""The training loss of rendered views against their targets, L1 + ssim_weight (1 - SSIM) averaged
over each view's pixels and channels, and its gradient, on the images' device
(``kernels/image_loss.py``): one view at a time, or several rendered together in one set of launches."""

from __future__ import annotations

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


class ImageLoss:
    """Scratch buffers for ``views`` views of at most ``height`` x ``width`` pixels, reused across calls."""

    def __init__(self, height: int, width: int, device, views: int = 1):
        self.device = wp.get_device(device)
        self.height, self.width, self.views = height, width, views
        d, shape = self.device, (views, height, width)
        self.taps = wp.array(gaussian_window().astype(np.float32), dtype=wp.float32, device=d)
        self.stack = wp.empty(shape, dtype=kernels.vec15, device=d)
        self.half = wp.empty(shape, dtype=kernels.vec15, device=d)
        self.moments = wp.empty(shape, dtype=kernels.vec15, device=d)
        self.partials = wp.empty(shape, dtype=kernels.vec9, device=d)
        self.half9 = wp.empty(shape, dtype=kernels.vec9, device=d)
        self.blurred = wp.empty(shape, dtype=kernels.vec9, device=d)
        self.loss = wp.empty(shape, dtype=wp.float32, device=d)
        wp.load_module(kernels, device=d)

    def _pixels(self, kernel, inputs: list) -> None:
        # one chunk a CPU worker: every pixel costs the same, and each further chunk is a launch's
        # overhead (at 128 x 128 four a worker took 5.6 ms a loss against 1.8; docs/performance.md)
        launch_rows_from(kernel, self.views * self.height * self.width, inputs, self.device, chunks_per_worker=1,
                         min_rows=MIN_PIXELS_TO_SPLIT)  # fmt: skip

    def _blur(self, source, half, target, views) -> None:
        self._pixels(kernels.blur, [source, self.taps, 0, views, half])
        self._pixels(kernels.blur, [half, self.taps, 1, views, target])

    def of_views(self, images: wp.array, targets: wp.array, grads: wp.array, views: wp.array) -> None:
        """For each view v of ``images`` (V, H, W, 3) and its ``views[v]`` (``loss_view``: its target
        in ``targets`` (T, H', W', 3), its size and weights): writes d(its share of L)/dimage into
        grads[v] and each pixel's share into ``self.loss``. A view's pixels beyond its own size are
        neither read nor written (their loss is 0)."""
        self._pixels(kernels.ssim_inputs, [images, targets, views, self.stack])
        self._blur(self.stack, self.half, self.moments, views)
        self._pixels(kernels.ssim_terms, [images, targets, views, self.moments, self.loss, self.partials])
        self._blur(self.partials, self.half9, self.blurred, views)
        self._pixels(kernels.loss_gradient, [images, targets, views, self.blurred, grads])

    def __call__(self, image: wp.array, target: wp.array, grad: wp.array, ssim_weight: float, weight: float = 1.0) -> None:
        """One view: writes d(weight L)/dimage into ``grad`` and each pixel's share of weight L into
        ``self.loss``; all three images (H, W, 3). L = mean |image - target| + ssim_weight (1 - mean SSIM)."""
        h, w = self.height, self.width
        views = wp.array([loss_view(0, w, h, ssim_weight, weight)], dtype=kernels.LossView, device=self.device)
        self.of_views(image.reshape((1, h, w, 3)), target.reshape((1, h, w, 3)), grad.reshape((1, h, w, 3)), views)

    def value(self) -> float:
        """The loss of the last call (a host read: the sum of the per-pixel shares, in float64)."""
        return float(self.loss.numpy().astype(np.float64).sum())
