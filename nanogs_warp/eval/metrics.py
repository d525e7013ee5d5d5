"""Image metrics on float images in [0, 1], shape (H, W, 3), computed in float64 with numpy.

- ``psnr``: 10 log10(1 / MSE) over all pixels and channels (data range 1).
- ``ssim``: mean SSIM with an 11-tap Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, population
  (not sample) covariances, per channel, averaged over the pixels whose whole window lies inside the
  image ('valid') and then over channels. This is scikit-image's
  ``structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1.0, channel_axis=-1)`` (which filters with reflection and then crops the 5-pixel border,
  so only in-image values matter). The INRIA training code's ``ssim`` instead zero-pads and averages
  over the border too, which gives slightly lower values near image edges.
- Foreground: the pixels where the reference differs from the background by more than half an 8-bit
  level (1/510) in some channel; ``foreground_psnr`` and ``colour_shift`` are computed over them.
"""

from __future__ import annotations

import math

import numpy as np

SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # scikit-image: int(truncate * sigma + 0.5) with truncate = 3.5 -> an 11-tap window
FOREGROUND_TOLERANCE = 1.0 / 510.0


def _pair(a, b) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    return a, b


def _psnr_of_mse(mse: float) -> float:
    if math.isnan(mse):
        return math.nan
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def psnr(a, b) -> float:
    """Peak signal-to-noise ratio in dB for data range 1 (inf for identical images)."""
    a, b = _pair(a, b)
    return _psnr_of_mse(float(np.mean((a - b) ** 2)))


def gaussian_window(sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS) -> np.ndarray:
    """The normalised 1D Gaussian taps scipy.ndimage.gaussian_filter uses."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _filter_valid(image: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable correlation of (H, W, C) with ``taps`` along H and W, 'valid' part only."""
    k = len(taps)
    h, w = image.shape[:2]
    rows = sum(taps[i] * image[i : h - k + 1 + i] for i in range(k))
    return sum(taps[i] * rows[:, i : w - k + 1 + i] for i in range(k))


def ssim_map(a, b) -> np.ndarray:
    """Per-pixel, per-channel SSIM over the valid region: (H - 10, W - 10, C)."""
    a, b = _pair(a, b)
    if a.ndim == 2:
        a, b = a[:, :, None], b[:, :, None]
    if min(a.shape[:2]) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"SSIM needs images of at least {2 * SSIM_RADIUS + 1} pixels a side, got {a.shape[:2]}")
    taps = gaussian_window()
    mu_a, mu_b = _filter_valid(a, taps), _filter_valid(b, taps)
    var_a = _filter_valid(a * a, taps) - mu_a * mu_a
    var_b = _filter_valid(b * b, taps) - mu_b * mu_b
    cov = _filter_valid(a * b, taps) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def ssim(a, b) -> float:
    """Mean structural similarity (see the module docstring for the exact definition)."""
    return float(ssim_map(a, b).mean(axis=(0, 1)).mean())


def foreground_mask(reference, background=(0.0, 0.0, 0.0), tolerance: float = FOREGROUND_TOLERANCE) -> np.ndarray:
    """(H, W) bool: pixels of ``reference`` that differ from ``background`` by more than ``tolerance``
    in at least one channel."""
    reference = np.asarray(reference, dtype=np.float64)
    return (np.abs(reference - np.asarray(background, np.float64)) > tolerance).any(axis=-1)


def foreground_psnr(reference, test, background=(0.0, 0.0, 0.0)) -> float:
    """PSNR over the reference's foreground pixels (``foreground_mask``); NaN when there are none."""
    reference, test = _pair(reference, test)
    mask = foreground_mask(reference, background)
    if not mask.any():
        return math.nan
    return _psnr_of_mse(float(np.mean((reference[mask] - test[mask]) ** 2)))


def colour_shift(reference, test, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Signed mean of (test - reference) per channel over the reference's foreground, (3,);
    NaN when there is no foreground."""
    reference, test = _pair(reference, test)
    mask = foreground_mask(reference, background)
    if not mask.any():
        return np.full(reference.shape[-1], np.nan)
    return (test[mask] - reference[mask]).mean(axis=0)
