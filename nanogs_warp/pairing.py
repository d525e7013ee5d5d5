"""Choose disjoint low-cost pairs: exactly the sequential greedy matching on (cost, i, j) order."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import warp as wp

from .kernels import pairing as kernels

if TYPE_CHECKING:
    from .topology import Edges

# Rounds of the parallel matching between two checks of its progress on the host.
ROUNDS_PER_CHECK = 4


@dataclass
class Pairs:
    """``count`` disjoint pairs (i[p], j[p]) in the order they were chosen."""

    i: wp.array
    j: wp.array
    count: int


def rank_edges(costs: wp.array) -> wp.array:
    """Edge ids sorted by cost; equal costs keep edge order, which is (i, j) order."""
    n = costs.shape[0]
    device = costs.device
    keys = wp.empty(2 * n, dtype=wp.float32, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.launch(kernels.edge_ids, n, inputs=[keys, costs, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n)
    return order[:n]


def select_pairs(edges: Edges, costs: wp.array, vertex_count: int, cap: int, method: str = "auto") -> Pairs:
    """Up to ``cap`` disjoint edges, greedily by increasing cost (ties by (i, j)).

    ``method`` is "sequential" (one thread; fastest on the CPU), "parallel" (locally dominant
    rounds; for GPUs) or "auto" (sequential on the CPU, parallel elsewhere). Both give the same pairs.
    """
    device = costs.device
    if method == "auto":
        method = "sequential" if device.is_cpu else "parallel"
    cap = max(0, min(cap, vertex_count // 2))
    e = edges.count
    if e == 0 or cap == 0:
        none = wp.zeros(0, dtype=wp.int32, device=device)
        return Pairs(none, none, 0)
    order = rank_edges(costs)
    partner = wp.full(vertex_count, -1, dtype=wp.int32, device=device)
    pair_i = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_j = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    if method == "sequential":
        wp.launch(
            kernels.greedy_pairs_in_order, 1,
            inputs=[order, edges.i, edges.j, cap],
            outputs=[partner, pair_i, pair_j, pair_count], device=device,
        )  # fmt: skip
    elif method == "parallel":
        matched = wp.zeros(e, dtype=wp.int32, device=device)
        best = wp.empty(vertex_count, dtype=wp.int32, device=device)
        accepted = wp.zeros(ROUNDS_PER_CHECK, dtype=wp.int32, device=device)
        while True:
            accepted.zero_()
            for round_index in range(ROUNDS_PER_CHECK):
                best.fill_(kernels.NO_CLAIM)
                wp.launch(kernels.claim_endpoints, e, inputs=[order, edges.i, edges.j, partner], outputs=[best], device=device)
                wp.launch(
                    kernels.accept_mutual_claims, e,
                    inputs=[order, edges.i, edges.j, best], outputs=[partner, matched, accepted, round_index],
                    device=device,
                )  # fmt: skip
            if accepted.numpy()[-1] == 0:  # a round with no free edge left: the matching is maximal
                break
        matched_before = wp.empty(e, dtype=wp.int32, device=device)
        wp.utils.array_scan(matched, matched_before, inclusive=False)
        wp.launch(
            kernels.first_matched_pairs, e,
            inputs=[order, edges.i, edges.j, matched, matched_before, cap],
            outputs=[pair_i, pair_j, pair_count], device=device,
        )  # fmt: skip
    else:
        raise ValueError(f"unknown pairing method {method!r}")
    count = int(pair_count.numpy()[0])
    return Pairs(pair_i[:count], pair_j[:count], count)
