"""Choose disjoint low-cost pairs: exactly the sequential greedy matching over the edges in rank
order (by cost, then by edge index: the canonical order of ``Edges``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from .errors import InputError
from .kernels import pairing as kernels
from .parallel import MIN_ROWS_TO_SPLIT, cpu_workers, in_turn, launch_rows_from

if TYPE_CHECKING:
    from .topology import Edges


# The sequential pairing sorts the edges in buckets of twice their length (the radix sort's second
# buffer), indexed with int32 as Warp's array lengths are: 2 E must stay below this. A module
# constant so that tests can lower it.
INDEX_LIMIT = 2**31
# Rounds of the parallel pairing before the edges left are matched sequentially (same result): twice
# the most any pass of the twelve scenes of docs/quality.md takes (32). A module constant so that
# tests can lower it.
MAX_ROUNDS = 64
# The sequential pairing's buckets (``_bucket_count``): about this many edges each (12 bytes an edge
# and as much again for the sort's second buffer: a few MB, a core's share of cache), at most
# MAX_BUCKETS, with BUCKET_SAMPLES sampled costs a bucket for the splitters.
BUCKET_EDGES = 1 << 18
MAX_BUCKETS = 64
BUCKET_SAMPLES = 64


def check_sequential_fits(edge_count: int, vertex_count: int, limit: int | None = None) -> None:
    """Refuses ``edge_count`` edges whose sort buffers (2 E slots) would not fit int32 indices; the
    message says about how many splats of this scene (edges per splat as here) fit."""
    limit = INDEX_LIMIT if limit is None else limit
    if 2 * edge_count >= limit:
        fits = (limit - 1) // 2 * vertex_count // max(edge_count, 1)
        raise InputError(
            f"{vertex_count:,} splats give {edge_count:,} candidate edges; the CPU pairing sorts 2 x that many, "
            f"more than the {limit - 1:,} that 32-bit indices address: about {fits:,} splats of this scene fit "
            f"on the CPU (a smaller --k or a GPU fits more)"
        )


@dataclass
class Pairs:
    """``count`` disjoint pairs (i[p], j[p]) in rank order, with their edges' costs (not decreasing)."""

    i: wp.array
    j: wp.array
    count: int
    costs: wp.array | None = None

    def first(self, count: int) -> Pairs:
        """The first ``count`` pairs."""
        return Pairs(self.i[:count], self.j[:count], count, None if self.costs is None else self.costs[:count])


def select_pairs(edges: Edges, costs: wp.array, vertex_count: int, cap: int, method: str = "auto") -> Pairs:
    """Up to ``cap`` disjoint edges, greedily in rank order.

    ``method`` is "sequential" (sorted buckets scanned by one thread; fastest on the CPU), "parallel"
    (locally dominant rounds, no sort of the edges; for GPUs) or "auto" (sequential on the CPU,
    parallel elsewhere). Both give the same pairs.
    """
    device = costs.device
    if method == "auto":
        method = "sequential" if device.is_cpu else "parallel"
    if method not in ("sequential", "parallel"):
        raise ValueError(f"unknown pairing method {method!r}")
    cap = max(0, min(cap, vertex_count // 2))
    if edges.count == 0 or cap == 0:
        none = wp.zeros(0, dtype=wp.int32, device=device)
        return Pairs(none, none, 0)
    pair_i = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_j = wp.full(cap, -1, dtype=wp.int32, device=device)
    pair_cost = wp.full(cap, float("nan"), dtype=wp.float32, device=device)
    if method == "sequential":
        check_sequential_fits(edges.count, vertex_count)
        count = _greedy_in_rank_order(edges, costs, vertex_count, cap, pair_i, pair_j, pair_cost)
    else:
        count = _locally_dominant_pairs(edges, costs, vertex_count, cap, pair_i, pair_j, pair_cost)
    return Pairs(pair_i, pair_j, cap, pair_cost).first(count)


def cheap_pairs(pairs: Pairs, factor: float) -> Pairs:
    """The first pairs whose cost is at most ``factor`` (>= 1) times the median pair's: at least half
    of ``pairs`` (rounded up), all of them when the median cost is 0. One integer comes to the host."""
    if pairs.count == 0:
        return pairs
    kept = wp.empty(1, dtype=wp.int32, device=pairs.costs.device)
    wp.launch(kernels.cheap_pair_count, 1, inputs=[pairs.costs, pairs.count, float(factor)], outputs=[kept], device=kept.device)
    return pairs.first(int(kept.numpy()[0]))


def _greedy_in_rank_order(edges: Edges, costs, vertex_count, cap, pair_i, pair_j, pair_cost) -> int:
    """Splits the edges stably into buckets of consecutive cost ranges, sorts each (stable radix
    sorts of (cost, ends), on every CPU core at once), then one thread scans the buckets in turn and
    takes every edge whose ends are both free. Edges of equal cost share a bucket and keep their
    order: this is rank order."""
    device = costs.device
    e = edges.count
    workers = cpu_workers() if device.is_cpu else 1
    splitters = _cost_splitters(costs, _bucket_count(e, workers))
    keys = wp.empty(e, dtype=wp.uint32, device=device)
    bucket = wp.empty(e, dtype=wp.int32, device=device)
    splitters_on_device = wp.array(splitters, dtype=wp.uint32, device=device)
    launch_rows_from(kernels.bucket_of_edges, e, [costs, splitters_on_device, keys, bucket], device)
    # the stable split: how many edges of each chunk go to each bucket, then each chunk's slots
    chunks = min(e, 4 * workers)
    rows_per_chunk = -(-e // chunks)
    counts = wp.empty((chunks, len(splitters) + 1), dtype=wp.int32, device=device)
    launch_rows_from(kernels.bucket_counts, chunks, [bucket, rows_per_chunk, counts], device, chunks_per_worker=1, min_rows=1)
    per_chunk = counts.numpy().astype(np.int64)
    sizes = per_chunk.sum(axis=0)
    starts = 2 * (np.cumsum(sizes) - sizes)  # each bucket with room for the sort's second buffer
    slots = wp.array(starts[None, :] + np.cumsum(per_chunk, axis=0) - per_chunk, dtype=wp.int32, device=device)
    bucket_keys = wp.empty(2 * e, dtype=wp.uint32, device=device)
    bucket_ends = wp.empty(2 * e, dtype=wp.vec2i, device=device)
    launch_rows_from(
        kernels.buckets_to_sort, chunks,
        [keys, bucket, rows_per_chunk, slots, edges.i, edges.j, bucket_keys, bucket_ends],
        device, chunks_per_worker=1, min_rows=1,
    )  # fmt: skip
    del keys, bucket

    def sort(b: int) -> None:
        room = slice(int(starts[b]), int(starts[b] + 2 * sizes[b]))
        wp.utils.radix_sort_pairs(bucket_keys[room], bucket_ends[room], int(sizes[b]))

    largest_first = sorted(np.flatnonzero(sizes > 1).tolist(), key=lambda b: -sizes[b])
    in_turn(workers, largest_first, sort)  # the host sort releases the GIL
    partner = wp.full(vertex_count, -1, dtype=wp.int32, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(
        kernels.greedy_pairs_in_rank_order, 1,
        inputs=[bucket_ends, bucket_keys, wp.array(starts, dtype=wp.int32, device=device),
                wp.array(sizes, dtype=wp.int32, device=device), cap],
        outputs=[partner, pair_i, pair_j, pair_cost, pair_count], device=device,
    )  # fmt: skip
    return int(pair_count.numpy()[0])


def _bucket_count(edge_count: int, workers: int) -> int:
    """Buckets for ``edge_count`` edges: one below 2 x MIN_ROWS_TO_SPLIT edges; otherwise at least
    one a worker, and enough that each holds about BUCKET_EDGES (a bucket that stays in a core's
    cache sorts faster: one core sorted 4.6M edges in 120 ms as one bucket, in 66-73 ms as 8 to 64),
    at most MAX_BUCKETS."""
    if edge_count < 2 * MIN_ROWS_TO_SPLIT:
        return 1
    return min(MAX_BUCKETS, max(workers, -(-edge_count // BUCKET_EDGES)))


def _cost_splitters(costs: wp.array, buckets: int) -> np.ndarray:
    """``buckets - 1`` ascending cost orders (as ``kernels.pairing.cost_order`` maps costs) at even
    quantiles of a sample of the costs (the CPU's own memory: no copy). They only balance the
    buckets: any splitters give the same matching."""
    if buckets <= 1:
        return np.zeros(0, dtype=np.uint32)
    sample = costs.numpy()[:: max(1, costs.shape[0] // (BUCKET_SAMPLES * buckets))]
    bits = sample.view(np.uint32)
    order = np.sort(np.where(bits >> 31 == 0, bits | np.uint32(0x80000000), ~bits))
    return order[[len(order) * b // buckets for b in range(1, buckets)]].astype(np.uint32)


def _locally_dominant_pairs(edges: Edges, costs, vertex_count, cap, pair_i, pair_j, pair_cost) -> int:
    """Rounds of: free edges claim both ends by priority, mutual winners match, edges with a
    matched end leave the active list. Every round matches at least the smallest-priority active
    edge, and on scenes the active list shrinks fast (at most 32 rounds in the twelve scenes of
    docs/quality.md). Where costs grow along chains of splats a round can match as little as one
    edge, N/2 rounds over all the edges; so after MAX_ROUNDS the edges left are sorted and matched
    by one thread in rank order, the same matching. The matched edges are then sorted by priority:
    the first ``cap`` are the pairs."""
    device = costs.device
    edge_i, edge_j = edges.i, edges.j
    best = wp.full(vertex_count, kernels.NO_CLAIM, dtype=wp.uint64, device=device)
    partner = wp.full(vertex_count, -1, dtype=wp.int32, device=device)
    most = vertex_count // 2  # a matching has at most this many edges; the sort needs twice the room
    matched_keys = wp.empty(2 * most, dtype=wp.uint64, device=device)
    matched_edges = wp.empty(2 * most, dtype=wp.int32, device=device)
    matched_count = wp.zeros(1, dtype=wp.int32, device=device)
    counter = wp.zeros(1, dtype=wp.int32, device=device)
    active = wp.empty(0, dtype=wp.int32, device=device)  # empty: every edge
    count = edges.count
    # Ends: the active edge of smallest priority (a total order on distinct keys) wins both its ends
    # and is matched each round; after MAX_ROUNDS the rest are matched in one sequential scan.
    rounds = 0
    while count > 0 and rounds < MAX_ROUNDS:
        rounds += 1
        wp.launch(kernels.claim_endpoints, count, inputs=[active, edge_i, edge_j, costs], outputs=[best], device=device)
        wp.launch(
            kernels.accept_mutual_claims, count,
            inputs=[active, edge_i, edge_j, costs, best],
            outputs=[partner, matched_keys, matched_edges, matched_count], device=device,
        )  # fmt: skip
        counter.zero_()
        wp.launch(
            kernels.count_still_free, count, inputs=[active, edge_i, edge_j, partner], outputs=[best, counter], device=device
        )
        remaining = int(counter.numpy()[0])
        next_active = wp.empty(remaining, dtype=wp.int32, device=device)
        if remaining > 0:
            counter.zero_()
            wp.launch(
                kernels.gather_still_free, count,
                inputs=[active, edge_i, edge_j, partner], outputs=[counter, next_active], device=device,
            )  # fmt: skip
        active, count = next_active, remaining
    if count > 0:
        keys = wp.empty(2 * count, dtype=wp.uint64, device=device)  # the sort's second buffer too
        rest = wp.empty(2 * count, dtype=wp.int32, device=device)
        wp.launch(kernels.active_priorities, count, inputs=[active, costs], outputs=[keys, rest], device=device)
        wp.utils.radix_sort_pairs(keys, rest, count)
        wp.launch(
            kernels.greedy_rest_in_rank_order, 1,
            inputs=[keys, rest, count, edge_i, edge_j], outputs=[partner, matched_keys, matched_edges, matched_count],
            device=device,
        )  # fmt: skip
    matched = int(matched_count.numpy()[0])
    wp.utils.radix_sort_pairs(matched_keys, matched_edges, matched)
    taken = min(matched, cap)
    wp.launch(
        kernels.first_pairs_by_rank, taken, inputs=[matched_edges, edge_i, edge_j, costs], outputs=[pair_i, pair_j, pair_cost], device=device
    )
    return taken
