"""Float64 numpy twins of the refinement kernels: the training loss (kernels/image_loss.py) and Adam
(kernels/adam.py)."""

from __future__ import annotations

import numpy as np

from nanogs_warp.eval.metrics import gaussian_window

C1, C2 = 0.01**2, 0.03**2


def blur_same(image: np.ndarray) -> np.ndarray:
    """Separable 11-tap Gaussian correlation of (H, W, C), zero outside the image, same size."""
    taps = gaussian_window()
    r = len(taps) // 2
    h, w = image.shape[:2]
    padded = np.zeros((h + 2 * r, w + 2 * r) + image.shape[2:])
    padded[r : r + h, r : r + w] = image
    rows = sum(taps[j] * padded[:, j : j + w] for j in range(len(taps)))
    return sum(taps[j] * rows[j : j + h] for j in range(len(taps)))


def training_loss(x: np.ndarray, y: np.ndarray, ssim_weight: float) -> float:
    """mean |x - y| + ssim_weight (1 - mean SSIM), SSIM zero-padded (the INRIA trainer's)."""
    x, y = x.astype(np.float64), y.astype(np.float64)
    mx, my = blur_same(x), blur_same(y)
    sxx, syy, sxy = blur_same(x * x) - mx * mx, blur_same(y * y) - my * my, blur_same(x * y) - mx * my
    s = (2 * mx * my + C1) * (2 * sxy + C2) / ((mx * mx + my * my + C1) * (sxx + syy + C2))
    return float(np.abs(x - y).mean() + ssim_weight * (1.0 - s.mean()))


def adam(param, grads, rates, columns, beta1=0.9, beta2=0.999, eps=1e-15, scales=None):
    """Adam over the steps' gradients ``grads`` (list of arrays like ``param``), learning rate
    scales[t] * rates[i mod columns]."""
    p = param.astype(np.float64).copy()
    m, v = np.zeros_like(p), np.zeros_like(p)
    lr = np.asarray(rates, np.float64)[np.arange(p.size) % columns]
    for t, g in enumerate(grads):
        g = g.astype(np.float64)
        m = beta1 * m + (1 - beta1) * g
        v = beta2 * v + (1 - beta2) * g * g
        scale = 1.0 if scales is None else scales[t]
        p -= scale * lr * (m / (1 - beta1 ** (t + 1))) / (np.sqrt(v / (1 - beta2 ** (t + 1))) + eps)
    return p
