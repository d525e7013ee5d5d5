"""Disjoint pairs: both methods equal the sequential greedy matching on (cost, i, j)."""

import numpy as np
import pytest
import reference
import warp as wp

from nanogs_warp.pairing import select_pairs
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


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_large_graph_equals_sequential_greedy(device, rng, method):
    """Enough edges for the CPU to sort them in two runs, merged by the matching; ties across the runs."""
    n = 30_000
    ei, ej, costs = random_graph(rng, n, 80_000, tie_levels=4)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    pairs = select_pairs(edges, wp.array(costs, device=device), n, 12_000, method=method)
    got = list(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist()))
    assert got == reference.greedy_pairs(ei, ej, costs, n, 12_000)


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


def test_no_edges_no_pairs(device):
    empty = wp.zeros(0, dtype=wp.int32, device=device)
    pairs = select_pairs(Edges(empty, empty, 0), wp.zeros(0, dtype=float, device=device), 5, 2)
    assert pairs.count == 0
