"""Keep a subset of rows of a splat set, in order, on its device."""

from __future__ import annotations

import warp as wp

from .kernels import compact as kernels
from .parallel import launch_rows_from
from .splats import SplatSet


def select_rows(splats: SplatSet, keep: wp.array, kept_count: int) -> tuple[SplatSet, wp.array]:
    """A new splat set of the rows whose ``keep`` flag (int32 0/1) is 1 (``kept_count`` of them), and
    the map from old to new rows (valid where ``keep`` is 1)."""
    device = splats.device
    destination = wp.empty(splats.count, dtype=wp.int32, device=device)
    wp.utils.array_scan(keep, destination, inclusive=False)
    out = SplatSet.empty(kept_count, splats.features.shape[1], splats.extras.shape[1], device, splats.layout,
                         splats.integer_extras.shape[1])  # fmt: skip
    launch_rows_from(kernels.gather_rows, splats.count, [keep, destination, splats.kernel_view(), out.kernel_view()], device)
    return out, destination


def remove_rows(splats: SplatSet, rows: wp.array, count: int) -> tuple[SplatSet, wp.array]:
    """The splat set without the ``count`` distinct rows listed in ``rows``, and the old -> new row map."""
    keep = wp.ones(splats.count, dtype=wp.int32, device=splats.device)
    wp.launch(kernels.drop_rows, count, inputs=[rows], outputs=[keep], device=splats.device)
    return select_rows(splats, keep, splats.count - count)
