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
    order: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    cap: int,
    partner: wp.array(dtype=wp.int32),
    pair_i: wp.array(dtype=wp.int32),
    pair_j: wp.array(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
):
    """Sequential greedy matching, launched as one thread (for the CPU, where a launch is one core)."""
    taken = int(0)
    for r in range(order.shape[0]):
        if taken >= cap:
            break
        e = order[r]
        i = edge_i[e]
        j = edge_j[e]
        if partner[i] < 0 and partner[j] < 0:
            partner[i] = j
            partner[j] = i
            pair_i[taken] = i
            pair_j[taken] = j
            taken += 1
    pair_count[0] = taken


@wp.kernel
def claim_endpoints(
    order: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int32),
):
    """Every free edge offers its rank to both ends; each end keeps the smallest."""
    r = wp.tid()
    e = order[r]
    i = edge_i[e]
    j = edge_j[e]
    if partner[i] < 0 and partner[j] < 0:
        wp.atomic_min(best, i, r)
        wp.atomic_min(best, j, r)


@wp.kernel
def accept_mutual_claims(
    order: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int32),
    partner: wp.array(dtype=wp.int32),
    matched: wp.array(dtype=wp.int32),
    accepted: wp.array(dtype=wp.int32),
    round_index: int,
):
    """Edges that won at both ends are matched. Only the winner of an end writes its partner, so
    the reads of partner by other edges in this launch cannot change their outcome."""
    r = wp.tid()
    e = order[r]
    i = edge_i[e]
    j = edge_j[e]
    if best[i] == r and best[j] == r:
        partner[i] = j
        partner[j] = i
        matched[r] = 1
        wp.atomic_add(accepted, round_index, 1)


@wp.kernel
def first_matched_pairs(
    order: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
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
        e = order[r]
        pair_i[slot] = edge_i[e]
        pair_j[slot] = edge_j[e]
    if r == order.shape[0] - 1:
        pair_count[0] = wp.min(slot + matched[r], cap)
