"""The training loss of a rendered view against a target, L1 + ssim_weight (1 - SSIM) averaged over
pixels and channels, and its gradient, on the images' device (``kernels/image_loss.py``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..eval.metrics import gaussian_window
from ..kernels import image_loss as kernels
from ..parallel import launch_rows_from

MIN_PIXELS_TO_SPLIT = 4096


class ImageLoss:
    """Scratch buffers for images of one size, reused across views."""

    def __init__(self, height: int, width: int, device):
        self.device = wp.get_device(device)
        self.height, self.width = height, width
        d, shape = self.device, (height, width)
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
        launch_rows_from(kernel, self.height * self.width, inputs, self.device, chunks_per_worker=1, min_rows=MIN_PIXELS_TO_SPLIT)

    def _blur(self, source, half, target) -> None:
        self._pixels(kernels.blur, [source, self.taps, 0, half])
        self._pixels(kernels.blur, [half, self.taps, 1, target])

    def __call__(self, image: wp.array, target: wp.array, grad: wp.array, ssim_weight: float, weight: float = 1.0) -> None:
        """Writes d(weight L)/dimage into ``grad`` and each pixel's share of weight L into ``self.loss``;
        all three images (H, W, 3). L = mean |image - target| + ssim_weight (1 - mean SSIM)."""
        per_value = weight / (3.0 * self.height * self.width)
        l1, s = per_value, per_value * ssim_weight
        self._pixels(kernels.ssim_inputs, [image, target, self.stack])
        self._blur(self.stack, self.half, self.moments)
        self._pixels(kernels.ssim_terms, [image, target, self.moments, l1, s, self.loss, self.partials])
        self._blur(self.partials, self.half9, self.blurred)
        self._pixels(kernels.loss_gradient, [image, target, self.blurred, l1, grad])

    def value(self) -> float:
        """weight L of the last call (a host read: the sum of the per-pixel shares, in float64)."""
        return float(self.loss.numpy().astype(np.float64).sum())
