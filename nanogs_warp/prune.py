"""Opacity pruning (NanoGS Algorithm 1, lines 3-4): drop splats below tau' = min(tau, median alpha)."""

from __future__ import annotations

import warp as wp

from .compact import select_rows
from .kernels import prune as kernels
from .splats import SplatSet


def prune_low_opacity(splats: SplatSet, threshold: float, keep_at_least: int) -> SplatSet:
    """Keeps splats with sigmoid opacity >= min(threshold, median opacity), in row order.

    When that would leave fewer than ``keep_at_least`` splats, keeps the ``keep_at_least`` most
    opaque ones instead (among equal opacities, later rows first).
    """
    n = splats.count
    device = splats.device
    if threshold <= 0.0:
        return splats  # every opacity is >= 0: nothing to prune (splat sets are never changed in place)
    alpha = wp.empty(n, dtype=wp.float32, device=device)
    sorted_alpha = wp.empty(2 * n, dtype=wp.float32, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.launch(kernels.activated_opacity, n, inputs=[splats.opacities], outputs=[alpha, sorted_alpha, order], device=device)
    wp.utils.radix_sort_pairs(sorted_alpha, order, n)
    median = float(sorted_alpha[(n - 1) // 2 : n // 2 + 1].numpy().astype("float64").mean())
    keep = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(kernels.keep_at_least, n, inputs=[alpha, min(float(threshold), median)], outputs=[keep], device=device)
    kept_before = wp.empty(n, dtype=wp.int32, device=device)
    wp.utils.array_scan(keep, kept_before, inclusive=True)
    kept = int(kept_before[n - 1 : n].numpy()[0])
    if kept < keep_at_least:
        keep.zero_()
        wp.launch(kernels.keep_rows, keep_at_least, inputs=[order, n - keep_at_least], outputs=[keep], device=device)
        kept = keep_at_least
    if kept == n:
        return splats
    pruned, _ = select_rows(splats, keep, kept)
    return pruned
