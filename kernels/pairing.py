"""Disjoint low-cost pairs: the greedy matching over edges in rank order.

An edge's rank orders it by cost, then by edge index (edges come in (i, j) order). Two ways to the
same matching:

- Sequentially: scan the edges by rank, take an edge when both ends are free. The edges are sorted
  in one or two runs (a stable radix sort of (cost, ends) each; one per CPU core), which the
  matching thread merges as it scans.
- In parallel: an edge whose priority (cost, edge index), packed in one uint64, is the smallest
  among the free edges at both of its ends (locally dominant) is in the greedy matching; accept all
  of them, drop the edges with a matched end, repeat until no free edge is left. No sort of the
  edges: only the matched edges are sorted, to list the pairs in rank order.

The greedy result capped at P pairs is the first P matched edges by rank.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

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
def priority(cost: float, e: int) -> wp.uint64:
    """(cost, edge index) as one unsigned key: smaller is earlier in rank order."""
    return (wp.uint64(cost_order(cost)) << wp.uint64(32)) | wp.uint64(e)


# -- sequential: sorted runs, merged by the matching thread -------------------------------------


@wp.kernel
def runs_to_sort(
    first: int,
    split: int,
    costs: wp.array(dtype=float),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.uint32),
    ends: wp.array(dtype=wp.vec2i),
):
    """Sort input, (cost order, ends): edges before ``split`` go to run 0 at [0, 2 split), the
    others to run 1 right after it (each run has room for the radix sort's second buffer)."""
    e = first + wp.tid()
    slot = e + wp.where(e < split, 0, split)
    keys[slot] = cost_order(costs[e])
    ends[slot] = wp.vec2i(edge_i[e], edge_j[e])


@wp.kernel
def greedy_pairs_in_rank_order(
    keys: wp.array(dtype=wp.uint32),
    ends: wp.array(dtype=wp.vec2i),
    a_begin: int,
    a_end: int,
    b_begin: int,
    b_end: int,
    cap: int,
    partner: wp.array(dtype=wp.int32),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
):
    """Sequential greedy matching, one thread: merges the sorted runs [a_begin, a_end) and
    [b_begin, b_end) by (cost, run), run a holding the lower edge indices, and takes every edge
    whose ends are both free. The merge step is branch-free (selects, not jumps)."""
    taken = int(0)
    a = a_begin
    b = b_begin
    steps = (a_end - a_begin) + (b_end - b_begin)
    for _ in range(steps):
        key_a = wp.where(a < a_end, keys[wp.min(a, a_end - 1)], wp.uint32(0xFFFFFFFF))
        key_b = wp.where(b < b_end, keys[wp.max(wp.min(b, b_end - 1), b_begin)], wp.uint32(0xFFFFFFFF))
        from_b = wp.where(a >= a_end, 1, wp.where(key_b < key_a, 1, 0))
        r = wp.where(from_b == 1, b, a)
        a += 1 - from_b
        b += from_b
        ij = ends[r]
        i = ij[0]
        j = ij[1]
        if partner[i] < 0 and partner[j] < 0:
            partner[i] = j
            partner[j] = i
            pair_i[taken] = i
            pair_j[taken] = j
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
    if partner[i] < 0 and partner[j] < 0:
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
    if partner[edge_i[e]] < 0 and partner[edge_j[e]] < 0:
        next_active[wp.atomic_add(slots, 0, 1)] = e


@wp.kernel
def first_pairs_by_rank(
    matched_edges: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
):
    """Pair p is the p-th matched edge by rank (``matched_edges`` sorted by priority)."""
    p = wp.tid()
    e = matched_edges[p]
    pair_i[p] = edge_i[e]
    pair_j[p] = edge_j[e]
