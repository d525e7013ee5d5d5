"""Disjoint low-cost pairs: the greedy matching over edges taken in rank order (cost, then (i, j)).

Two ways to the same matching. Sequentially: scan edges by rank, take an edge when both ends are
free. In parallel: an edge whose rank is the smallest among the free edges at both of its ends
(locally dominant) is in the greedy matching; accept all of them, repeat until no free edge is left.
The greedy result capped at P pairs is the first P matched edges by rank.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

NO_CLAIM = wp.constant(2147483647)


@wp.kernel
def edge_ids(keys: wp.array(dtype=float), costs: wp.array(dtype=float), ids: wp.array(dtype=wp.int32)):
    """Sort input: keys = costs, values = edge ids 0..E-1."""
    e = wp.tid()
    keys[e] = costs[e]
    ids[e] = e


@wp.kernel
def greedy_pairs_in_order(
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    cap: int,
    partner: wp.array(dtype=wp.int32),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
):
    """Sequential greedy matching, launched as one thread (for the CPU, where a launch is one core)."""
    taken = int(0)
    for r in range(rank_i.shape[0]):
        if taken >= cap:
            break
        i = rank_i[r]
        j = rank_j[r]
        if partner[i] < 0 and partner[j] < 0:
            partner[i] = j
            partner[j] = i
            pair_i[taken] = i
            pair_j[taken] = j
            taken += 1
    pair_count[0] = taken


@wp.kernel
def ranked_endpoints(
    order: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
):
    """Endpoints of the edge of each rank."""
    r = wp.tid()
    e = order[r]
    rank_i[r] = edge_i[e]
    rank_j[r] = edge_j[e]


@wp.kernel
def all_ranks(active: wp.array(dtype=wp.int32)):
    """The active list at the start: every rank."""
    r = wp.tid()
    active[r] = r


@wp.kernel
def claim_endpoints(
    active: wp.array(dtype=wp.int32),
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int32),
):
    """Every free edge (all active edges are free) offers its rank to both ends; each end keeps the smallest."""
    r = active[wp.tid()]
    wp.atomic_min(best, rank_i[r], r)
    wp.atomic_min(best, rank_j[r], r)


@wp.kernel
def accept_mutual_claims(
    active: wp.array(dtype=wp.int32),
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
):
    """Edges that won at both ends are matched. Only the winner of an end writes its partner."""
    r = active[wp.tid()]
    i = rank_i[r]
    j = rank_j[r]
    if best[i] == r and best[j] == r:
        partner[i] = j
        partner[j] = i


@wp.kernel
def matched_ranks(
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    matched: wp.array(dtype=wp.int32),
):
    """matched[r] = 1 where the edge of rank r joined its ends."""
    r = wp.tid()
    matched[r] = wp.where(partner[rank_i[r]] == rank_j[r], 1, 0)


@wp.kernel
def still_free(
    active: wp.array(dtype=wp.int32),
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int32),
    keep: wp.array(dtype=wp.int32),
):
    """An active edge stays active while both its ends are free; clears the claims of its ends."""
    t = wp.tid()
    r = active[t]
    i = rank_i[r]
    j = rank_j[r]
    keep[t] = wp.where(partner[i] < 0 and partner[j] < 0, 1, 0)
    best[i] = NO_CLAIM
    best[j] = NO_CLAIM


@wp.kernel
def gather_active(
    active: wp.array(dtype=wp.int32),
    keep: wp.array(dtype=wp.int32),
    position: wp.array(dtype=wp.int32),
    next_active: wp.array(dtype=wp.int32),
):
    """Active edges that stay, in order (``position`` is the inclusive scan of ``keep``)."""
    t = wp.tid()
    if keep[t] == 1:
        next_active[position[t] - 1] = active[t]


@wp.kernel
def first_matched_pairs(
    rank_i: wp.array(dtype=wp.int32),
    rank_j: wp.array(dtype=wp.int32),
    matched: wp.array(dtype=wp.int32),
    matched_before: wp.array(dtype=wp.int32),
    cap: int,
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
):
    """Keeps the first ``cap`` matched edges by rank, in rank order."""
    r = wp.tid()
    slot = matched_before[r]
    if matched[r] == 1 and slot < cap:
        pair_i[slot] = rank_i[r]
        pair_j[slot] = rank_j[r]
    if r == matched.shape[0] - 1:
        pair_count[0] = wp.min(slot + matched[r], cap)
