"""Choose disjoint low-cost pairs: exactly the sequential greedy matching on (cost, i, j) order."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import warp as wp

from .kernels import pairing as kernels

if TYPE_CHECKING:
    from .topology import Edges


@dataclass
class Pairs:
    """``count`` disjoint pairs (i[p], j[p]) in the order they were chosen."""

    i: wp.array
    j: wp.array
    count: int


@dataclass
class RankedEdges:
    """Candidate edges in rank order, by cost and then (i, j): the r-th cheapest joins i[r] and j[r]."""

    i: wp.array
    j: wp.array
    count: int


def rank_edges(edges: Edges, costs: wp.array) -> RankedEdges:
    """Sorts the edges by cost; equal costs keep edge order, which is (i, j) order. The sort's
    double buffers are freed on return, so the caller may drop ``edges`` and ``costs`` next."""
    n = edges.count
    device = costs.device
    keys = wp.empty(2 * n, dtype=wp.float32, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.launch(kernels.edge_ids, n, inputs=[keys, costs, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n)
    del keys  # before the ranked endpoints are allocated: the peak of a pass is here
    rank_i = wp.empty(n, dtype=wp.int32, device=device)
    rank_j = wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(kernels.ranked_endpoints, n, inputs=[order, edges.i, edges.j], outputs=[rank_i, rank_j], device=device)
    return RankedEdges(rank_i, rank_j, n)


def select_pairs(ranked: RankedEdges, vertex_count: int, cap: int, method: str = "auto") -> Pairs:
    """Up to ``cap`` disjoint edges, greedily in rank order.

    ``method`` is "sequential" (one thread; fastest on the CPU), "parallel" (locally dominant
    rounds; for GPUs) or "auto" (sequential on the CPU, parallel elsewhere). Both give the same pairs.
    """
    device = ranked.i.device
    if method == "auto":
        method = "sequential" if device.is_cpu else "parallel"
    cap = max(0, min(cap, vertex_count // 2))
    if ranked.count == 0 or cap == 0:
        none = wp.zeros(0, dtype=wp.int32, device=device)
        return Pairs(none, none, 0)
    partner = wp.full(vertex_count, -1, dtype=wp.int32, device=device)
    pair_i = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_j = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    if method == "sequential":
        wp.launch(
            kernels.greedy_pairs_in_order, 1,
            inputs=[ranked.i, ranked.j, cap], outputs=[partner, pair_i, pair_j, pair_count], device=device,
        )  # fmt: skip
    elif method == "parallel":
        _locally_dominant_pairs(ranked, partner, cap, pair_i, pair_j, pair_count)
    else:
        raise ValueError(f"unknown pairing method {method!r}")
    count = int(pair_count.numpy()[0])
    return Pairs(pair_i[:count], pair_j[:count], count)


def _locally_dominant_pairs(ranked: RankedEdges, partner, cap, pair_i, pair_j, pair_count) -> None:
    """Rounds of: free edges claim both ends by rank, mutual winners match, edges with a matched
    end leave the active list. Every round matches at least the lowest-ranked active edge, and the
    active list shrinks fast, so the total work stays a small multiple of the edge count."""
    device = ranked.i.device
    e = ranked.count
    rank_i, rank_j = ranked.i, ranked.j
    active = wp.empty(e, dtype=wp.int32, device=device)
    wp.launch(kernels.all_ranks, e, outputs=[active], device=device)
    spare = wp.empty(e, dtype=wp.int32, device=device)
    keep = wp.empty(e, dtype=wp.int32, device=device)
    position = wp.empty(e, dtype=wp.int32, device=device)
    best = wp.full(partner.shape[0], kernels.NO_CLAIM, dtype=wp.int32, device=device)
    count = e
    while count > 0:
        now = active[:count]
        wp.launch(kernels.claim_endpoints, count, inputs=[now, rank_i, rank_j], outputs=[best], device=device)
        wp.launch(kernels.accept_mutual_claims, count, inputs=[now, rank_i, rank_j, best], outputs=[partner], device=device)
        wp.launch(kernels.still_free, count, inputs=[now, rank_i, rank_j, partner], outputs=[best, keep], device=device)
        wp.utils.array_scan(keep[:count], position[:count], inclusive=True)
        remaining = int(position[count - 1 : count].numpy()[0])
        wp.launch(kernels.gather_active, count, inputs=[now, keep, position], outputs=[spare], device=device)
        active, spare, count = spare, active, remaining
    del active, spare
    matched = keep
    wp.launch(kernels.matched_ranks, e, inputs=[rank_i, rank_j, partner], outputs=[matched], device=device)
    wp.utils.array_scan(matched, position, inclusive=False)
    wp.launch(
        kernels.first_matched_pairs, e,
        inputs=[rank_i, rank_j, matched, position, cap], outputs=[pair_i, pair_j, pair_count], device=device,
    )  # fmt: skip
