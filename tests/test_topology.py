"""Candidate topology: the exact kNN graph and its undirected edges against brute-force float64 numpy.

Warp ranks neighbours by float32 squared distance, the reference by float64, so where two distances
agree to ~1e-6 the two may order them differently: distances are compared with a relative tolerance,
neighbour sets only across gaps wider than it, and whole rows exactly where every distance is exact
(integer coordinates).
"""

import types

import numpy as np
import pytest
import warp as wp
from reference_topology import edges_reference, knn_reference

from nanogs_warp.topology import KMAX, Edges, KnnTopology, candidate_edges, knn_graph

wp.config.log_level = wp.LOG_WARNING

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
# float32 squared distances of float32 points carry a relative error of a few 1e-7
RTOL = 2e-6


@pytest.fixture(params=DEVICES)
def knn_device(request):
    return request.param


def uniform_points(n, seed):
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 3)).astype(np.float32)


def clustered_points(n, seed, clusters=24, outliers=5):
    """Gaussian clusters with sigmas log-spaced from 1e-4 to 1e-1, plus a few far outliers."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1.0, 1.0, (clusters, 3))
    sigma = 10.0 ** np.linspace(-4.0, -1.0, clusters)
    label = rng.integers(0, clusters, n)
    points = centres[label] + rng.normal(size=(n, 3)) * sigma[label, None]
    points[:outliers] = rng.uniform(-100.0, 100.0, (outliers, 3))
    return points.astype(np.float32)


def lattice_points(n, seed, side=6):
    """Integer lattice points, many repeated: squared distances are exact small integers, full of ties."""
    return np.random.default_rng(seed).integers(0, side, (n, 3)).astype(np.float32)


def run_knn(points, k, device, candidates=None):
    means = wp.array(points, dtype=wp.vec3, device=device)
    neighbours = knn_graph(means, k, candidates=candidates)
    assert neighbours.device == means.device
    assert neighbours.dtype == wp.int32 and neighbours.shape == (points.shape[0], k)
    return neighbours.numpy()


def squared_distances(points, neighbours, rows=None):
    rows = np.arange(points.shape[0]) if rows is None else rows
    p = points.astype(np.float64)
    return ((p[rows, None, :] - p[neighbours[rows]]) ** 2).sum(axis=2)


def check_valid(neighbours):
    """Every row written, in range, without self and without repeats."""
    n, k = neighbours.shape
    assert neighbours.min() >= 0 and neighbours.max() < n  # the output is poisoned with -1
    assert not np.any(neighbours == np.arange(n)[:, None])
    if k > 1:
        ordered = np.sort(neighbours, axis=1)
        assert not np.any(ordered[:, 1:] == ordered[:, :-1])


def check_against_reference(points, neighbours, k, rows=None):
    """Same sorted distances as brute force; same sets wherever the k-th and (k+1)-th differ."""
    check_valid(neighbours)
    n = points.shape[0]
    rows = np.arange(n) if rows is None else rows
    ref_index, ref_d2 = knn_reference(points, min(k + 1, n - 1), rows=rows)
    got_d2 = squared_distances(points, neighbours, rows)
    np.testing.assert_allclose(got_d2, ref_d2[:, :k], rtol=RTOL, atol=0.0)
    assert np.all(got_d2[:, 1:] >= got_d2[:, :-1] * (1.0 - RTOL))  # rows come sorted by distance
    gap = np.ones(rows.size, dtype=bool)
    if k + 1 < n:
        gap = ref_d2[:, k] > ref_d2[:, k - 1] * (1.0 + 4.0 * RTOL)
        assert gap.mean() > 0.5
    got_sets = np.sort(neighbours[rows], axis=1)
    ref_sets = np.sort(ref_index[:, :k], axis=1)
    np.testing.assert_array_equal(got_sets[gap], ref_sets[gap])


@pytest.mark.parametrize("k", [1, 8, 16, KMAX])
def test_knn_uniform(knn_device, k):
    points = uniform_points(3000, seed=1)
    check_against_reference(points, run_knn(points, k, knn_device), k)


def test_knn_clustered(knn_device):
    points = clustered_points(40000, seed=2)  # on the CPU, large enough to split over threads
    neighbours = run_knn(points, 16, knn_device)
    check_valid(neighbours)
    rows = np.concatenate([np.arange(5), np.random.default_rng(3).choice(points.shape[0], 1500, replace=False)])
    check_against_reference(points, neighbours, 16, rows=rows)


def test_knn_far_outliers(knn_device):
    """A dense blob 1e7 times smaller than the reach of a few outliers: exact, and the work per point
    stays bounded (the quantisation cube ignores the outliers instead of stretching over them)."""
    rng = np.random.default_rng(13)
    points = rng.normal(size=(20000, 3)) * 1e-3
    points[:10] = rng.uniform(-1e4, 1e4, (10, 3))
    points = points.astype(np.float32)
    candidates = wp.zeros(points.shape[0], dtype=wp.int32, device=knn_device)
    neighbours = run_knn(points, 16, knn_device, candidates=candidates)
    check_valid(neighbours)
    rows = np.concatenate([np.arange(10), rng.choice(points.shape[0], 500, replace=False)])
    check_against_reference(points, neighbours, 16, rows=rows)
    assert np.median(candidates.numpy()) < 400


@pytest.mark.parametrize("k", [4, 16])
def test_knn_clustered_small(knn_device, k):
    points = clustered_points(4000, seed=4, clusters=8)
    check_against_reference(points, run_knn(points, k, knn_device), k)


@pytest.mark.parametrize("k", [1, 16])
def test_knn_ties_by_index(knn_device, k):
    """Exact distances with many ties and duplicates: rows must equal the reference exactly."""
    points = lattice_points(3000, seed=5)
    neighbours = run_knn(points, k, knn_device)
    check_valid(neighbours)
    ref_index, _ = knn_reference(points, k)
    np.testing.assert_array_equal(neighbours, ref_index)


def test_knn_duplicates(knn_device):
    """Clusters of identical points (more copies than k) among distinct ones."""
    rng = np.random.default_rng(6)
    points = uniform_points(1000, seed=6)
    points[200:260] = points[200]  # 60 copies
    points[500:510] = points[501]  # 10 copies
    points[rng.choice(1000, 50, replace=False)] = points[7]
    neighbours = run_knn(points, 16, knn_device)
    check_against_reference(points, neighbours, 16)
    copies = np.flatnonzero(np.all(points == points[200], axis=1))
    for row in copies:  # nearest are the other copies, ranked by index
        np.testing.assert_array_equal(neighbours[row], copies[copies != row][:16])


def test_knn_all_identical(knn_device):
    points = np.full((40, 3), 0.25, dtype=np.float32)
    neighbours = run_knn(points, 8, knn_device)
    for row in range(40):
        np.testing.assert_array_equal(neighbours[row], [j for j in range(40) if j != row][:8])


def test_knn_flat_and_far(knn_device):
    """Points on a plane and on a line (zero extent along some axes), far from the origin."""
    rng = np.random.default_rng(7)
    plane = np.c_[rng.uniform(0, 1, (1500, 2)), np.zeros(1500)] + [1000.0, -500.0, 30.0]
    line = np.c_[rng.uniform(0, 1, 500), np.zeros((500, 2))] - 200.0
    for points in (plane.astype(np.float32), line.astype(np.float32)):
        check_against_reference(points, run_knn(points, 16, knn_device), 16)


@pytest.mark.parametrize("n, k", [(2, 1), (3, 2), (17, 16), (33, KMAX)])
def test_knn_tiny(knn_device, n, k):
    points = uniform_points(n, seed=n)
    neighbours = run_knn(points, k, knn_device)
    check_valid(neighbours)
    ref_index, _ = knn_reference(points, k)
    np.testing.assert_array_equal(neighbours, ref_index)


def test_knn_deterministic(knn_device):
    points = clustered_points(40000, seed=8)
    first = run_knn(points, 16, knn_device)
    second = run_knn(points, 16, knn_device)
    assert first.tobytes() == second.tobytes()


def test_knn_same_on_every_device():
    points = lattice_points(2000, seed=9)
    results = [run_knn(points, 16, device) for device in DEVICES]
    for other in results[1:]:
        np.testing.assert_array_equal(other, results[0])


def test_knn_candidates(knn_device):
    points = clustered_points(5000, seed=10)
    candidates = wp.full(points.shape[0], -1, dtype=wp.int32, device=knn_device)
    run_knn(points, 16, knn_device, candidates=candidates)
    assert candidates.numpy().min() >= 16


@pytest.mark.parametrize("n, k", [(10, 0), (10, KMAX + 1), (10, 10), (1, 1)])
def test_knn_rejects_bad_k(n, k):
    with pytest.raises(ValueError):
        knn_graph(wp.array(uniform_points(n, seed=0), dtype=wp.vec3, device="cpu"), k)


def test_knn_rejects_non_finite():
    points = uniform_points(100, seed=0)
    points[17, 1] = np.nan
    with pytest.raises(ValueError):
        knn_graph(wp.array(points, dtype=wp.vec3, device="cpu"), 4)


def check_edges(edges, neighbours):
    assert isinstance(edges, Edges)
    i, j = edges.i.numpy(), edges.j.numpy()
    assert i.shape == (edges.count,) and j.shape == (edges.count,)
    ref_i, ref_j = edges_reference(neighbours)
    np.testing.assert_array_equal(i, ref_i)
    np.testing.assert_array_equal(j, ref_j)


def test_edges_hand_made(knn_device):
    # 0<->1 mutual, 2->0 one way, 3->2 one way, 1->3 one way
    neighbours = np.array([[1], [0], [0], [2]], dtype=np.int32)
    edges = candidate_edges(wp.array(neighbours, dtype=wp.int32, device=knn_device))
    assert edges.count == 3
    np.testing.assert_array_equal(edges.i.numpy(), [0, 0, 2])
    np.testing.assert_array_equal(edges.j.numpy(), [1, 2, 3])
    neighbours = np.array([[1, 3], [0, 3], [0, 3], [2, 1]], dtype=np.int32)
    check_edges(candidate_edges(wp.array(neighbours, dtype=wp.int32, device=knn_device)), neighbours)


@pytest.mark.parametrize("make", [clustered_points, lattice_points])
def test_edges_of_knn_graph(knn_device, make):
    points = make(8000, seed=11)
    neighbours = knn_graph(wp.array(points, dtype=wp.vec3, device=knn_device), 16)
    first = candidate_edges(neighbours)
    check_edges(first, neighbours.numpy())
    assert first.i.device == neighbours.device
    second = candidate_edges(neighbours)
    assert first.count == second.count
    assert first.i.numpy().tobytes() == second.i.numpy().tobytes()
    assert first.j.numpy().tobytes() == second.j.numpy().tobytes()


def test_knn_topology_stage(knn_device):
    points = uniform_points(10, seed=12)
    splats = types.SimpleNamespace(means=wp.array(points, dtype=wp.vec3, device=knn_device), count=10)
    edges = KnnTopology(16)(splats)  # k shrinks to N-1: the complete graph
    assert edges.count == 45
