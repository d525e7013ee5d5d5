"""Disjoint pairs: both methods equal the sequential greedy matching on (cost, i, j)."""

import numpy as np
import pytest
import reference
import warp as wp

from nanogs_warp import pairing
from nanogs_warp.pairing import cheap_pairs, select_pairs
from nanogs_warp.topology import Edges


def random_graph(rng, n_vertices, n_edges, tie_levels=None):
    pairs = set()
    while len(pairs) < n_edges:
        a, b = rng.integers(0, n_vertices, 2)
        if a != b:
            pairs.add((min(a, b), max(a, b)))
    edges = np.array(sorted(pairs), dtype=np.int32)
    costs = rng.normal(size=len(edges)).astype(np.float32)
    if tie_levels:
        costs = np.round(costs * tie_levels) / tie_levels + 0.0  # many exact ties, negative costs too; no -0
    return edges[:, 0], edges[:, 1], costs.astype(np.float32)


@pytest.mark.parametrize("method", ["sequential", "parallel"])
@pytest.mark.parametrize("tie_levels", [None, 2])
@pytest.mark.parametrize("cap", [3, 40, 10_000])
def test_pairs_equal_sequential_greedy(device, rng, method, tie_levels, cap):
    n = 400
    ei, ej, costs = random_graph(rng, n, 1500, tie_levels)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    pairs = select_pairs(edges, wp.array(costs, device=device), n, cap, method=method)
    got = list(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist()))
    assert got == reference.greedy_pairs(ei, ej, costs, n, min(cap, n // 2))
    cost_of = {(a, b): c for a, b, c in zip(ei.tolist(), ej.tolist(), costs.tolist())}
    pair_costs = pairs.costs.numpy()  # each pair's own edge cost, bit for bit, in rank order
    assert pair_costs.tolist() == [cost_of[(min(a, b), max(a, b))] for a, b in got]
    assert np.all(np.diff(pair_costs) >= 0)


@pytest.mark.parametrize("method", ["sequential", "parallel"])
@pytest.mark.parametrize("tie_levels", [None, 4])
@pytest.mark.parametrize("bucket_edges", [None, 1000])
def test_large_graph_equals_sequential_greedy(device, rng, monkeypatch, method, tie_levels, bucket_edges):
    """Enough edges for the CPU to sort them in buckets, scanned in turn by the matching: as many
    buckets as the cores (and the size) give, or the most (``bucket_edges`` 1000); ties across the
    buckets' bounds."""
    if bucket_edges is not None:
        monkeypatch.setattr(pairing, "BUCKET_EDGES", bucket_edges)
        assert pairing._bucket_count(80_000, 1) == pairing.MAX_BUCKETS
    n = 30_000
    ei, ej, costs = random_graph(rng, n, 80_000, tie_levels)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    pairs = select_pairs(edges, wp.array(costs, device=device), n, 12_000, method=method)
    got = list(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist()))
    assert got == reference.greedy_pairs(ei, ej, costs, n, 12_000)


def test_cost_splitters_cut_even_quantiles(rng):
    """Splitters ascend in cost order and cut a sample into buckets of about equal size."""
    costs = rng.normal(size=100_000).astype(np.float32)
    splitters = pairing._cost_splitters(wp.array(costs, device="cpu"), 8)
    assert len(splitters) == 7 and np.all(np.diff(splitters.astype(np.int64)) > 0)
    bits = costs.view(np.uint32)
    order = np.where(bits >> 31 == 0, bits | np.uint32(0x80000000), ~bits)
    sizes = np.bincount(np.searchsorted(splitters, order, side="right"), minlength=8)
    assert sizes.min() > 0.8 * len(costs) / 8 and sizes.max() < 1.2 * len(costs) / 8


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_sorted_path_needs_many_rounds(device, method):
    """Costs increasing along a path: the parallel rounds resolve one pair at a time."""
    n = 41
    ei = np.arange(n - 1, dtype=np.int32)
    ej = ei + 1
    costs = np.arange(n - 1, dtype=np.float32)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), n - 1)
    pairs = select_pairs(edges, wp.array(costs, device=device), n, 100, method=method)
    assert list(zip(pairs.i.numpy(), pairs.j.numpy())) == [(k, k + 1) for k in range(0, n - 1, 2)]


def test_random_costs_need_few_rounds(device, rng, monkeypatch):
    """Random costs: each round matches every locally smallest edge, so a few rounds match them all,
    without the sequential rest (a round that claims the wrong ends would match almost nothing
    and leave the rest to it)."""
    rounds = []
    launch = pairing.wp.launch

    def counting_launch(kernel, *args, **kwargs):
        rounds.append(kernel is pairing.kernels.claim_endpoints)
        assert kernel is not pairing.kernels.greedy_rest_in_rank_order
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(pairing.wp, "launch", counting_launch)
    n = 2000
    ei, ej, costs = random_graph(rng, n, 8000)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    pairs = select_pairs(edges, wp.array(costs, device=device), n, n, method="parallel")
    assert list(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist())) == reference.greedy_pairs(ei, ej, costs, n, n // 2)
    assert 0 < sum(rounds) <= 16, sum(rounds)


def test_rounds_are_bounded_and_the_rest_matched_in_rank_order(device, monkeypatch):
    """A path of 20,000 edges with costs growing along it (splats spaced ever wider, all alike)
    would take one round per pair: after MAX_ROUNDS the rest is matched by one sequential scan,
    and the pairs are still the greedy ones."""
    import nanogs_warp.pairing as pairing

    rounds = []
    launch = pairing.wp.launch

    def counting_launch(kernel, *args, **kwargs):
        rounds.append(kernel is pairing.kernels.claim_endpoints)
        return launch(kernel, *args, **kwargs)

    monkeypatch.setattr(pairing.wp, "launch", counting_launch)
    n = 20_001
    ei = np.arange(n - 1, dtype=np.int32)
    ej = ei + 1
    costs = np.linspace(1.0, 2.0, n - 1).astype(np.float32)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), n - 1)
    pairs = select_pairs(edges, wp.array(costs, device=device), n, n, method="parallel")
    assert list(zip(pairs.i.numpy(), pairs.j.numpy())) == [(k, k + 1) for k in range(0, n - 1, 2)]
    assert sum(rounds) == pairing.MAX_ROUNDS


@pytest.mark.parametrize("max_rounds", [0, 1, 3])
@pytest.mark.parametrize("tie_levels", [None, 2])
def test_rest_after_a_few_rounds_equals_sequential_greedy(device, rng, monkeypatch, max_rounds, tie_levels):
    """Whatever the rounds have matched, the sequential scan of the edges left completes the greedy
    matching: the same pairs, costs and rank order as the reference."""
    import nanogs_warp.pairing as pairing

    monkeypatch.setattr(pairing, "MAX_ROUNDS", max_rounds)
    n = 3000
    ei, ej, costs = random_graph(rng, n, 12_000, tie_levels)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    pairs = select_pairs(edges, wp.array(costs, device=device), n, 1000, method="parallel")
    got = list(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist()))
    assert got == reference.greedy_pairs(ei, ej, costs, n, 1000)
    cost_of = {(a, b): c for a, b, c in zip(ei.tolist(), ej.tolist(), costs.tolist())}
    assert pairs.costs.numpy().tolist() == [cost_of[(min(a, b), max(a, b))] for a, b in got]


def test_no_edges_no_pairs(device):
    empty = wp.zeros(0, dtype=wp.int32, device=device)
    pairs = select_pairs(Edges(empty, empty, 0), wp.zeros(0, dtype=float, device=device), 5, 2)
    assert pairs.count == 0


def cheap_count_reference(costs: np.ndarray, factor: float) -> int:
    """How many of the sorted ``costs`` are at most factor x the median pair's (index count // 2) cost,
    float64; all of them when that cost is not positive."""
    median = float(costs[len(costs) // 2])
    if not median > 0:
        return len(costs)
    return int(np.searchsorted(costs.astype(np.float64), factor * median, side="right"))


@pytest.mark.parametrize("method", ["sequential", "parallel"])
@pytest.mark.parametrize("factor", [1.0, 3.0, 1e30])
def test_cheap_pairs_keep_those_within_the_factor_of_the_median(device, rng, method, factor):
    """cheap_pairs against the float64 reference, on matchings with a heavy tail of costs, with ties
    and with zero costs; every pair up to the median is kept."""
    n = 600
    for trial in range(6):
        ei, ej, _ = random_graph(rng, n, 2000)
        costs = np.exp(rng.normal(scale=3.0, size=len(ei))).astype(np.float32)  # a heavy tail
        if trial == 1:
            costs = np.round(costs, 1).astype(np.float32)  # ties at the limit and zero costs
        if trial == 2:
            costs[:] = 0.0  # median 0: every pair
        edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
        pairs = select_pairs(edges, wp.array(costs, device=device), n, [7, 1, 2, 40, 300, 300][trial], method=method)
        kept = cheap_pairs(pairs, factor)
        want = cheap_count_reference(pairs.costs.numpy(), factor)
        assert kept.count == want >= (pairs.count + 1) // 2
        assert kept.i.numpy().tolist() == pairs.i.numpy()[:want].tolist()
        assert kept.j.numpy().tolist() == pairs.j.numpy()[:want].tolist()
        if trial == 4 and factor == 3.0:
            assert want < pairs.count  # the tail is cut somewhere in these trials
