"""Keep a subset of rows of a splat set, in order, on its device."""

from __future__ import annotations

from dataclasses import replace

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


def remove_rows(splats: SplatSet, rows: wp.array, count: int) -> tuple[SplatSet, wp.array, wp.array]:
    """The splat set without the ``count`` distinct rows listed in ``rows``, the old -> new row map,
    and the rows' keep flags (int32, 0 for the removed rows)."""
    keep = wp.ones(splats.count, dtype=wp.int32, device=splats.device)
    wp.launch(kernels.drop_rows, count, inputs=[rows], outputs=[keep], device=splats.device)
    out, destination = select_rows(splats, keep, splats.count - count)
    return out, destination, keep


def merged_rows_after(merged: wp.array | None, keep: wp.array, destination: wp.array, first: wp.array, pair_count: int,
                      count: int) -> wp.array:  # fmt: skip
    """The marks (int32, 1: a merge made the row) of the ``count`` rows after a pass that kept the rows
    flagged in ``keep`` (moved to ``destination``) and merged each pair into the row of its first
    splat (``first``, ``pair_count`` of them). ``merged``: the marks before the pass (None: no row
    merged yet)."""
    device = keep.device
    out = wp.zeros(count, dtype=wp.int32, device=device)
    if merged is not None:
        wp.launch(kernels.carry_merged_rows, keep.shape[0], inputs=[keep, destination, merged], outputs=[out], device=device)
    wp.launch(kernels.mark_merged_rows, pair_count, inputs=[first, destination], outputs=[out], device=device)
    return out


def with_merged_appearance(splats: SplatSet, fitted: SplatSet, merged: wp.array, opacities: bool = False) -> SplatSet:
    """``splats`` with the features (colours) of ``fitted`` (the same rows after a fit changed them)
    and, with ``opacities``, its opacities (the opacity array seen as one column, so the same copy
    serves), in every row that a merge made (``merged``:
    ``merged_rows_after``'s marks); every other value is ``splats``' own."""
    n, device = splats.count, splats.device
    features = wp.clone(splats.features)
    wp.launch(kernels.copy_merged_rows, n, inputs=[merged, fitted.features], outputs=[features], device=device)
    if not opacities:
        return replace(splats, features=features)
    values = wp.clone(splats.opacities)
    wp.launch(kernels.copy_merged_rows, n, inputs=[merged, fitted.opacities.reshape((n, 1))], outputs=[values.reshape((n, 1))],
              device=device)  # fmt: skip
    return replace(splats, features=features, opacities=values)
