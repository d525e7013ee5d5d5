"""Disjoint low-cost pairs: the greedy matching over edges in rank order.

An edge's rank orders it by cost, then by edge index (the canonical order of ``Edges``). Two ways to the
same matching:

- Sequentially: scan the edges by rank, take an edge when both ends are free. The edges are split
  stably into buckets of consecutive cost ranges (splitters from a sample of the costs), each bucket
  sorted on its own (a stable radix sort of (cost, ends); the buckets on every CPU core at once, each
  small enough to stay in a core's cache); the matching thread scans them in turn.
- In parallel: an edge whose priority (cost, edge index), packed in one uint64, is the smallest
  among the free edges at both of its ends (locally dominant) is in the greedy matching; accept all
  of them, drop the edges with a matched end, repeat until no free edge is left. No sort of the
  edges: only the matched edges are sorted, to list the pairs in rank order. A round may match only
  one edge (costs that grow along a chain of splats), so after a bounded number of rounds the edges
  left are sorted and matched sequentially, which gives the same matching.

The greedy result capped at P pairs is the first P matched edges by rank. Each pair comes with its
edge's cost; in rank order the costs do not decrease, so ``cheap_pair_count`` finds by bisection how
many pairs cost at most a factor times the median pair's cost.
"""

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

NO_CLAIM = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))
SIGN_BIT = wp.constant(wp.uint32(0x80000000))


@wp.func
def cost_order(cost: float) -> wp.uint32:
    """The float's bits mapped so that unsigned order is float order (-0 just below +0), as the
    radix sort orders float keys."""
    bits = wp.cast(cost, wp.uint32)
    if (bits & SIGN_BIT) == wp.uint32(0):
        return bits | SIGN_BIT
    return ~bits


@wp.func
def cost_of_order(order: wp.uint32) -> float:
    """The inverse of ``cost_order``: the float whose bits ``order`` stands for."""
    bits = ~order
    if (order & SIGN_BIT) != wp.uint32(0):
        bits = order & ~SIGN_BIT
    return wp.cast(bits, float)


@wp.func
def priority(cost: float, e: int) -> wp.uint64:
    """(cost, edge index) as one unsigned key: smaller is earlier in rank order."""
    return (wp.uint64(cost_order(cost)) << wp.uint64(32)) | wp.uint64(e)


@wp.func
def both_free(partner: wp.array(dtype=wp.int32), i: int, j: int) -> bool:
    return partner[i] < 0 and partner[j] < 0


# -- sequential: buckets split by cost, each sorted, scanned one after the other ----------------


@wp.kernel
def bucket_of_edges(
    first: int,
    costs: wp.array(dtype=float),
    splitters: wp.array(dtype=wp.uint32),
    keys: wp.array(dtype=wp.uint32),
    bucket: wp.array(dtype=wp.int32),
):
    """Each edge's cost order and its bucket: how many of the ascending ``splitters`` are at or below
    it (edges of equal cost share a bucket)."""
    e = first + wp.tid()
    key = cost_order(costs[e])
    keys[e] = key
    lo = int(0)
    hi = splitters.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if splitters[mid] <= key:
            lo = mid + 1
        else:
            hi = mid
    bucket[e] = lo


@wp.func
def chunk_rows(c: int, rows_per_chunk: int, rows: int):
    start = c * rows_per_chunk
    return start, wp.min(start + rows_per_chunk, rows)


@wp.kernel
def bucket_counts(
    first: int, bucket: wp.array(dtype=wp.int32), rows_per_chunk: int, counts: wp.array2d(dtype=wp.int32)
):
    """counts[c, b]: how many edges of chunk c (edges [c R, (c + 1) R)) fall in bucket b."""
    c = first + wp.tid()
    for b in range(counts.shape[1]):
        counts[c, b] = 0
    start, stop = chunk_rows(c, rows_per_chunk, bucket.shape[0])
    for e in range(start, stop):
        counts[c, bucket[e]] += 1


@wp.kernel
def buckets_to_sort(
    first: int,
    keys: wp.array(dtype=wp.uint32),
    bucket: wp.array(dtype=wp.int32),
    rows_per_chunk: int,
    slots: wp.array2d(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    bucket_keys: wp.array(dtype=wp.uint32),
    bucket_ends: wp.array(dtype=wp.vec2i),
):
    """Sort input, (cost order, ends), split stably into the buckets: chunk c's edges in order, each
    to slots[c, b], the next free slot of its bucket b for chunk c (advanced as it is used). Bucket
    b's room starts at twice the edges of the buckets before it (the radix sort's second buffer)."""
    c = first + wp.tid()
    start, stop = chunk_rows(c, rows_per_chunk, bucket.shape[0])
    for e in range(start, stop):
        b = bucket[e]
        slot = slots[c, b]
        slots[c, b] = slot + 1
        bucket_keys[slot] = keys[e]
        bucket_ends[slot] = wp.vec2i(edge_i[e], edge_j[e])


@wp.kernel
def greedy_pairs_in_rank_order(
    ends: wp.array(dtype=wp.vec2i),
    keys: wp.array(dtype=wp.uint32),
    bucket_start: wp.array(dtype=wp.int32),
    bucket_count: wp.array(dtype=wp.int32),
    cap: int,
    partner: wp.array(dtype=wp.int32),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_cost: wp.array(dtype=float),
    pair_count: wp.array(dtype=wp.int32),
):
    """Sequential greedy matching, one thread: the sorted buckets in turn, bucket b at
    [start_b, start_b + count_b) (``keys``: their cost orders); takes every edge whose ends are both
    free, until ``cap`` pairs."""
    taken = int(0)
    for b in range(bucket_start.shape[0]):
        if taken >= cap:
            break
        for r in range(bucket_start[b], bucket_start[b] + bucket_count[b]):
            ij = ends[r]
            i = ij[0]
            j = ij[1]
            if both_free(partner, i, j):
                partner[i] = j
                partner[j] = i
                pair_i[taken] = i
                pair_j[taken] = j
                pair_cost[taken] = cost_of_order(keys[r])
                taken += 1
                if taken >= cap:
                    break
    pair_count[0] = taken


# -- parallel: locally dominant rounds ----------------------------------------------------------


@wp.func
def active_edge(active: wp.array(dtype=wp.int32), t: int) -> int:
    """Edge of active slot t; an empty list means every edge (the first round)."""
    if active.shape[0] == 0:
        return t
    return active[t]


@wp.kernel
def claim_endpoints(
    active: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    costs: wp.array(dtype=float),
    best: wp.array(dtype=wp.uint64),
):
    """Every active edge (all have both ends free) offers its priority to both ends; each end keeps the smallest."""
    e = active_edge(active, wp.tid())
    key = priority(costs[e], e)
    wp.atomic_min(best, edge_i[e], key)
    wp.atomic_min(best, edge_j[e], key)


@wp.kernel
def accept_mutual_claims(
    active: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    costs: wp.array(dtype=float),
    best: wp.array(dtype=wp.uint64),
    partner: wp.array(dtype=wp.int32),
    matched_keys: wp.array(dtype=wp.uint64),
    matched_edges: wp.array(dtype=wp.int32),
    matched_count: wp.array(dtype=wp.int32),
):
    """Edges that won at both ends are matched (only the winner of an end writes its partner) and
    listed, in any order, with their priority."""
    e = active_edge(active, wp.tid())
    i = edge_i[e]
    j = edge_j[e]
    key = priority(costs[e], e)
    if best[i] == key and best[j] == key:
        partner[i] = j
        partner[j] = i
        slot = wp.atomic_add(matched_count, 0, 1)
        matched_keys[slot] = key
        matched_edges[slot] = e


@wp.kernel
def count_still_free(
    active: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.uint64),
    remaining: wp.array(dtype=wp.int32),
):
    """Counts the active edges with both ends still free; clears the claims of every active edge's ends."""
    e = active_edge(active, wp.tid())
    i = edge_i[e]
    j = edge_j[e]
    if both_free(partner, i, j):
        wp.atomic_add(remaining, 0, 1)
    best[i] = NO_CLAIM
    best[j] = NO_CLAIM


@wp.kernel
def gather_still_free(
    active: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    next_active: wp.array(dtype=wp.int32),
):
    """The next round's active list: the edges with both ends free, in any order (claims are order-free)."""
    e = active_edge(active, wp.tid())
    if both_free(partner, edge_i[e], edge_j[e]):
        next_active[wp.atomic_add(slots, 0, 1)] = e


@wp.kernel
def active_priorities(
    active: wp.array(dtype=wp.int32),
    costs: wp.array(dtype=float),
    keys: wp.array(dtype=wp.uint64),
    edges: wp.array(dtype=wp.int32),
):
    """The active edges' priorities and indices, for the sort before ``greedy_rest_in_rank_order``."""
    t = wp.tid()
    e = active_edge(active, t)
    keys[t] = priority(costs[e], e)
    edges[t] = e


@wp.kernel
def greedy_rest_in_rank_order(
    keys: wp.array(dtype=wp.uint64),
    edges: wp.array(dtype=wp.int32),
    count: int,
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    matched_keys: wp.array(dtype=wp.uint64),
    matched_edges: wp.array(dtype=wp.int32),
    matched_count: wp.array(dtype=wp.int32),
):
    """One thread: the edges the rounds left (both ends free), sorted by priority, scanned in order;
    an edge whose ends are both still free is matched and listed. On what the rounds left, the
    greedy matching is what the remaining rounds would have matched."""
    taken = matched_count[0]
    for t in range(count):
        e = edges[t]
        i = edge_i[e]
        j = edge_j[e]
        if both_free(partner, i, j):
            partner[i] = j
            partner[j] = i
            matched_keys[taken] = keys[t]
            matched_edges[taken] = e
            taken += 1
    matched_count[0] = taken


@wp.kernel
def first_pairs_by_rank(
    matched_edges: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    costs: wp.array(dtype=float),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_cost: wp.array(dtype=float),
):
    """Pair p is the p-th matched edge by rank (``matched_edges`` sorted by priority)."""
    p = wp.tid()
    e = matched_edges[p]
    pair_i[p] = edge_i[e]
    pair_j[p] = edge_j[e]
    pair_cost[p] = costs[e]


@wp.kernel
def cheap_pair_count(pair_cost: wp.array(dtype=float), count: int, factor: float, kept: wp.array(dtype=wp.int32)):
    """kept[0] = how many of the ``count`` pairs (costs not decreasing) cost at most ``factor`` times
    the median pair's cost, pair count // 2 (one thread, bisection); every pair when that cost is
    not positive or the limit not finite. At least the pairs up to the median are kept (factor >= 1)."""
    median = wp.float64(pair_cost[count // 2])
    limit = wp.float64(factor) * median
    if not (median > wp.float64(0.0) and wp.isfinite(limit)):
        kept[0] = count
        return
    low = count // 2 + 1  # pairs [0, low) are within the limit
    high = count  # pairs [high, count) are beyond it
    while low < high:
        mid = (low + high) // 2
        if wp.float64(pair_cost[mid]) <= limit:
            low = mid + 1
        else:
            high = mid
    kept[0] = low
