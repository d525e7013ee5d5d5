"""Candidate topology: the exact kNN graph and its undirected edges against brute-force float64 numpy.

Warp ranks neighbours by float32 squared distance, the reference by float64, so where two distances
agree to ~1e-6 the two may order them differently: distances are compared with a relative tolerance,
neighbour sets only across gaps wider than it, and whole rows exactly where every distance is exact
(integer coordinates).
"""

import sys
import types
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from reference_topology import edges_reference, knn_reference

from nanogs_warp.kernels import edges as edge_kernels
from nanogs_warp.kernels import knn as knn_kernels
from nanogs_warp import parallel
from nanogs_warp.parallel import launch_rows_from
from nanogs_warp.topology import (
    KMAX, MEASURED_SIDE, Edges, KnnTopology, bounding_box, candidate_edges, knn_graph, measured_points,
)

sys.path.insert(0, str(Path(__file__).parents[1] / "tools"))
from adversarial_scenes import bit_centres  # noqa: E402 - the same scenes as the tool's

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
    for row in copies:  # nearest are the other copies, ranked by index counted on from the row's own
        others = copies[copies != row]
        np.testing.assert_array_equal(neighbours[row], others[np.argsort((others - row) % 1000, kind="stable")][:16])


def test_knn_all_identical(knn_device):
    points = np.full((40, 3), 0.25, dtype=np.float32)
    neighbours = run_knn(points, 8, knn_device)
    for row in range(40):  # the copies that follow the row, wrapping round
        np.testing.assert_array_equal(neighbours[row], [(row + t) % 40 for t in range(1, 9)])


def test_knn_large_duplicate_cluster(knn_device):
    """Thousands of copies of one position: each copy lists the copies that follow it (so a greedy
    matching can pair them all off), and the work per query stays bounded, not the cluster's size."""
    rng = np.random.default_rng(21)
    points = uniform_points(12000, seed=21)
    copies = np.sort(rng.choice(12000, 8000, replace=False))
    points[copies] = points[copies[0]]
    candidates = wp.zeros(points.shape[0], dtype=wp.int32, device=knn_device)
    neighbours = run_knn(points, 16, knn_device, candidates=candidates)
    others = np.setdiff1d(np.arange(12000), copies)
    check_against_reference(points, neighbours, 16, rows=rng.choice(others, 300, replace=False))
    for r in (0, 1, 4000, 7990, 7999):  # the next 16 copies by index, wrapping round
        row = copies[r]
        np.testing.assert_array_equal(neighbours[row], copies[(r + 1 + np.arange(16)) % copies.size])
    assert np.percentile(candidates.numpy()[copies], 99) < 400


def test_knn_extreme_coordinates(knn_device):
    """Finite coordinates up to float32's largest: squared distances overflow to inf, which then
    rank by index; every query ends, and the ordinary points keep their exact neighbours."""
    points = uniform_points(3000, seed=22)
    points[5] = [0.0, 0.0, 1e20]
    points[6] = [3.4e38, -3.4e38, 3.4e38]
    points[7] = [-3.4e38, 3.4e38, -1e-38]
    points[8] = [3.7e37, 0.5, 0.5]
    neighbours = run_knn(points, 16, knn_device)
    check_valid(neighbours)
    far = np.arange(5, 9)
    check_against_reference(points, neighbours, 16, rows=np.setdiff1d(np.arange(3000), far))
    # a far point's neighbours: the ordinary points nearest it where float32 distances are finite,
    # else (all at inf) the lowest indices
    np.testing.assert_array_equal(neighbours[6], [t for t in range(17) if t != 6])


@pytest.mark.parametrize("exponent", [-120, -64, 64, 100])
def test_knn_of_scenes_far_from_unit_size(knn_device, exponent):
    """A scene scaled by 2^exponent has the neighbours of the unscaled scene, and each query examines
    about as few points: at 2^64 and beyond squared distances overflow float32 (every query used to
    scan every point), at 2^-64 and below they fall to subnormals and zero."""
    points = off_lattice_points(20000, seed=23)
    scaled = (points.astype(np.float64) * 2.0**exponent).astype(np.float32)
    assert np.array_equal(scaled.astype(np.float64) * 2.0**-exponent, points)  # the scaling itself is exact
    work = wp.zeros(len(points), dtype=wp.int32, device=knn_device)
    np.testing.assert_array_equal(run_knn(scaled, 16, knn_device, candidates=work), run_knn(points, 16, knn_device))
    assert np.median(work.numpy()) < 400


def test_knn_of_a_scene_in_huge_units_matches_float64_reference(knn_device):
    """Coordinates near 1e20 (not a power of two apart from the unscaled scene): exact neighbours."""
    points = (clustered_points(6000, seed=24, outliers=0).astype(np.float64) * 3.3e20).astype(np.float32)
    check_against_reference(points, run_knn(points, 16, knn_device), 16)


def test_knn_of_coordinates_over_every_magnitude(knn_device, monkeypatch):
    """Coordinates of every magnitude float32 holds (+-10^U(-37, 38)): most points lie outside the
    quantisation cube, crowd its cells, and their squared distances overflow. The points within a
    crowded cell are then sorted by their float bits, which leaves the neighbours as they are and
    takes a fraction of the work; nodes whose every distance is infinite are skipped by index."""
    import nanogs_warp.topology as topology

    rng = np.random.default_rng(28)
    points = (np.sign(rng.normal(size=(4000, 3))) * 10.0 ** rng.uniform(-37, 38, (4000, 3))).astype(np.float32)
    runs = []
    for crowded_order in (True, False):
        if not crowded_order:  # crowded cells keep index order
            index_order = lambda means: wp.array(np.arange(means.shape[0], dtype=np.int32), device=means.device)  # noqa: E731
            monkeypatch.setattr(topology, "_float_bit_order", index_order)
        work = wp.zeros(len(points), dtype=wp.int32, device=knn_device)
        runs.append((run_knn(points, 16, knn_device, candidates=work), int(work.numpy().sum())))
    (table, work), (plain_table, plain_work) = runs
    check_valid(table)
    np.testing.assert_array_equal(table, plain_table)
    assert work <= plain_work and work < 0.25 * len(points) ** 2  # every query scanned everything before


def random_bit_points(n, seed):
    """Coordinates from random float32 bit patterns (a damaged file's), infinities and NaNs set to 0
    (tools/adversarial_scenes.py): every magnitude from 1e-45 to 3e38 about equally often, so most
    squared distances are 0 or +inf in float32 and tie."""
    return bit_centres(n, np.random.default_rng(seed))


def work_limit(k):
    return knn_kernels.WORK_BASE + knn_kernels.WORK_PER_NEIGHBOUR * k


def test_knn_work_is_bounded_where_distances_tie(knn_device):
    """Where float32 cannot tell most distances apart, queries stop at their work limit and keep the
    best k they met: the work grows as N, not N^2. Such rows are marked in ``reach``, and the
    edges read them by a scan of the row, giving exactly the edges of the table itself."""
    points = random_bit_points(20000, seed=31)
    means = wp.array(points, dtype=wp.vec3, device=knn_device)
    candidates = wp.zeros(len(points), dtype=wp.int32, device=knn_device)
    reach = wp.zeros(len(points), dtype=wp.int64, device=knn_device)
    table = knn_graph(means, 16, candidates=candidates, reach=reach)
    neighbours = table.numpy()
    check_valid(neighbours)
    inexact = reach.numpy() == knn_kernels.INEXACT
    assert inexact.sum() > work_limit(16)  # too many to search again
    assert candidates.numpy().max() < work_limit(16) + knn_kernels.BLOCK
    with_reach = candidate_edges(table, means, reach)
    scanned = candidate_edges(table)
    assert with_reach.count == scanned.count
    np.testing.assert_array_equal(with_reach.i.numpy(), scanned.i.numpy())
    np.testing.assert_array_equal(with_reach.j.numpy(), scanned.j.numpy())
    again = wp.zeros(len(points), dtype=wp.int64, device=knn_device)
    np.testing.assert_array_equal(knn_graph(means, 16, reach=again).numpy(), neighbours)  # deterministic
    np.testing.assert_array_equal(again.numpy(), reach.numpy())


def test_knn_few_queries_past_the_limit_are_searched_again(knn_device):
    """Where only a few queries reach the work limit (here 378 of 10,000), they are searched again
    without it: every row exact, none marked."""
    points = random_bit_points(10000, seed=2)
    means = wp.array(points, dtype=wp.vec3, device=knn_device)
    reach = wp.zeros(len(points), dtype=wp.int64, device=knn_device)
    candidates = wp.zeros(len(points), dtype=wp.int32, device=knn_device)
    check_valid(knn_graph(means, 16, candidates=candidates, reach=reach).numpy())
    assert not np.any(reach.numpy() == knn_kernels.INEXACT)
    assert candidates.numpy().max() > work_limit(16)  # some did search past it


def test_measured_points(knn_device):
    """Scenes inside MEASURED_SIDE are measured as they are; others in a copy scaled by a power of
    two to a side in [1/2, 1), clamped to float32's range and without subnormals; a far outlier
    does not set the scale (the quantisation cube leaves it out)."""
    ordinary = wp.array(uniform_points(1000, seed=25) * np.float32(100.0), dtype=wp.vec3, device=knn_device)
    points, (_, quantum, _) = measured_points(ordinary)
    assert points.ptr == ordinary.ptr and MEASURED_SIDE[0] <= quantum * 2**21 <= MEASURED_SIDE[1]
    f32 = np.finfo(np.float32)
    far = uniform_points(5000, seed=26).astype(np.float64) * 2.0**80
    far[0] = [3.4e38, -3.4e38, 1e-30]  # an outlier, and a coordinate the scaling takes below float32's normals
    tiny = uniform_points(5000, seed=27).astype(np.float64) * 2.0**-80
    tiny[0] = [3.0e38, 1.0, -2.0]  # the scaling takes the outlier past float32's largest
    for scene in (far, tiny):
        scene = scene.astype(np.float32).astype(np.float64)
        points, (_, quantum, margin) = measured_points(wp.array(scene.astype(np.float32), dtype=wp.vec3, device=knn_device))
        assert 0.5 <= quantum * 2**21 < 1.0 and margin == 2 * quantum
        got = points.numpy().astype(np.float64)
        scale = got[1, 0] / scene[1, 0]
        assert np.frexp(scale)[0] == 0.5  # a power of two
        expected = np.clip(scene * scale, -f32.max, f32.max)
        expected[np.abs(expected) < f32.tiny] = 0.0
        np.testing.assert_array_equal(got, expected)
        assert expected[0, 2] == 0.0 or expected[0, 0] == f32.max  # the flush and the clamp were exercised


@pytest.mark.parametrize("offset", [1e30, 3.4e38])
def test_knn_of_fine_clusters_far_apart(knn_device, offset):
    """Two clusters of ordinary spacing, 2e30 and 6.8e38 apart: scaled to the cube's usual side, their
    neighbours' squared distances would be zero in float32 (every candidate tied, the graph a list
    of indices, each query's search far longer); measured_points takes a larger scale."""
    rng = np.random.default_rng(29)
    points = rng.normal(size=(4000, 3))
    points[:2000, 0] += offset
    points[2000:, 0] -= offset
    points = points.astype(np.float32)  # x rounds to +-offset: each cluster is flat
    _, (_, quantum, _) = measured_points(wp.array(points, dtype=wp.vec3, device=knn_device))
    assert quantum * 2**21 >= 2.0**40  # the larger scale was taken
    check_against_reference(points, run_knn(points, 16, knn_device), 16)


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


def off_lattice_points(n, seed):
    """Clustered points scaled and shifted off any grid: float32 squared distances round, so a
    back-end that computes them differently (fused multiply-adds, another order) can rank them
    differently."""
    return (clustered_points(n, seed) * np.float32(0.7310585) + np.float32(0.1234567)).astype(np.float32)


HAS_CUDA = wp.get_cuda_device_count() > 0 and wp.is_cpu_available()  # both back-ends: a Warp build without its CPU compiler cannot compare


@pytest.mark.skipif(not HAS_CUDA, reason="compares the CPU with a CUDA GPU (needs Warp's CPU compiler too)")
def test_knn_same_on_cpu_and_cuda():
    """The CPU and CUDA kNN graphs are identical on inputs where distances round."""
    for points in (
        off_lattice_points(6000, seed=9),
        uniform_points(4000, seed=19) * np.float32(1e3) + np.float32(7.3),
        random_bit_points(20000, seed=31),  # queries stopped at their work limit
    ):
        np.testing.assert_array_equal(run_knn(points, 16, "cuda:0"), run_knn(points, 16, "cpu"))


def test_knn_off_lattice_matches_float64_reference(knn_device):
    """Without a second device to compare with, each one is held to the float64 brute force on the
    same off-lattice inputs."""
    points = off_lattice_points(3000, seed=9)
    check_against_reference(points, run_knn(points, 16, knn_device), 16)


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
    means = wp.array(points, dtype=wp.vec3, device=knn_device)
    reach = wp.full(len(points), -1, dtype=wp.int64, device=knn_device)
    neighbours = knn_graph(means, 16, reach=reach)
    table = neighbours.numpy()
    # reach: the k-th neighbour's (float32 squared distance bits, tie rank: its index, or at distance
    # 0 its index counted from the row's); a GPU may fuse the distance's multiply-adds, so its bits
    # are compared with numpy's to a float32 tolerance
    got = reach.numpy()
    last = table[:, -1]
    rows = np.arange(len(points))
    tie = np.where(got >> 32 == 0, (last - rows) % len(points), last)
    np.testing.assert_array_equal(got & 0xFFFFFFFF, tie)
    d = ((points[last].astype(np.float64) - points) ** 2).sum(axis=1)
    np.testing.assert_allclose((got >> 32).astype(np.int32).view(np.float32), d, rtol=1e-6, atol=1e-30)
    # the one-comparison test of "row j lists i" gives the edges of the scan
    check_edges(candidate_edges(neighbours, means, reach), table)
    first = candidate_edges(neighbours)
    check_edges(first, table)
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


# Candidate edges on hand-built neighbour tables: the sort-free construction against numpy.


def random_neighbours(n, k, rng):
    """Row i: k distinct random points other than i."""
    if n <= 2000:
        offsets = np.argpartition(rng.random((n, n - 1)), k - 1, axis=1)[:, :k] + 1
    else:
        offsets = rng.integers(1, n, (n, k))
        while True:
            ordered = np.sort(offsets, axis=1)
            bad = np.flatnonzero(np.any(ordered[:, 1:] == ordered[:, :-1], axis=1))
            if bad.size == 0:
                break
            offsets[bad] = rng.integers(1, n, (bad.size, k))
    return ((np.arange(n)[:, None] + offsets) % n).astype(np.int32)


def local_neighbours(n, k, rng):
    """Row i: k distinct random points within k of i (in index): most pairs are mutual, as in kNN."""
    steps = np.r_[-k:0, 1 : k + 1]
    targets = np.arange(n)[:, None] + steps
    keys = np.where((targets >= 0) & (targets < n), rng.random(targets.shape), np.inf)
    chosen = np.argsort(keys, axis=1)[:, :k]
    return np.take_along_axis(targets, chosen, axis=1).astype(np.int32)


def edges_of(neighbours, device):
    edges = candidate_edges(wp.array(neighbours, dtype=wp.int32, device=device))
    assert edges.i.device == wp.get_device(device) and edges.j.device == wp.get_device(device)
    return edges


@pytest.mark.parametrize(
    "n, k", [(2, 1), (3, 2), (60, 1), (40, 32), (1000, 3), (1000, 4), (3000, 16), (3000, 24), (40000, 16)]
)
def test_edges_random_graphs(device, n, k, rng):
    """Random tables (few mutual pairs) and local ones (mostly mutual), k = 1 to 32; 40,000 rows
    split the CPU launches over threads; k = 32 fills segments past the in-register sort."""
    for neighbours in (random_neighbours(n, k, rng), local_neighbours(n, k, rng)):
        check_edges(edges_of(neighbours, device), neighbours)


def test_edges_k1(device):
    # mutual pairs, a chain pointing down, a chain pointing up, and a star
    pairs = np.array([[1], [0], [3], [2]], dtype=np.int32)
    down = np.r_[1, np.arange(0, 99)].astype(np.int32)[:, None]
    up = np.r_[np.arange(1, 100), 98].astype(np.int32)[:, None]
    star = np.r_[1, np.zeros(99)].astype(np.int32)[:, None]
    for neighbours in (pairs, down, up, star):
        check_edges(edges_of(neighbours, device), neighbours)
    edges = edges_of(pairs, device)
    assert edges.count == 2
    np.testing.assert_array_equal(edges.i.numpy(), [0, 2])
    np.testing.assert_array_equal(edges.j.numpy(), [1, 3])


@pytest.mark.parametrize("k", [1, 4, 7, 16])
def test_edges_all_mutual(device, k, rng):
    """Cliques of k+1 points, their labels shuffled: every entry is listed by both rows."""
    groups = 50
    labels = rng.permutation(groups * (k + 1)).reshape(groups, k + 1)
    neighbours = np.empty((groups * (k + 1), k), dtype=np.int32)
    for members in labels:
        for m, point in enumerate(members):
            neighbours[point] = rng.permutation(np.delete(members, m))
    edges = edges_of(neighbours, device)
    assert edges.count == groups * (k + 1) * k // 2
    check_edges(edges, neighbours)


@pytest.mark.parametrize("k", [1, 4, 7, 16])
def test_edges_none_mutual(device, k, rng):
    """Row i lists i+1..i+k (or i-1..i-k), modulo n > 2k: no pair is listed by both rows."""
    n = 1000
    for sign in (1, -1):
        neighbours = ((np.arange(n)[:, None] + sign * np.arange(1, k + 1)) % n).astype(np.int32)
        neighbours = rng.permuted(neighbours, axis=1)
        edges = edges_of(neighbours, device)
        assert edges.count == n * k
        check_edges(edges, neighbours)


def with_hub(neighbours, hub, rng):
    """Every row but the hub's own lists the hub (one random entry replaced where it did not)."""
    n, k = neighbours.shape
    lacking = np.flatnonzero(~np.any(neighbours == hub, axis=1) & (np.arange(n) != hub))
    neighbours[lacking, rng.integers(0, k, lacking.size)] = hub
    check_valid(neighbours)
    return neighbours


@pytest.mark.parametrize("hub", ["first", "middle", "last"])
@pytest.mark.parametrize("k", [4, 16])
def test_edges_hub(device, hub, k, rng):
    """One point listed by every other row (thousands): its segment is far longer than a row."""
    n = 6000
    h = {"first": 0, "middle": n // 2, "last": n - 1}[hub]
    neighbours = with_hub(random_neighbours(n, k, rng), h, rng)
    check_edges(edges_of(neighbours, device), neighbours)


def staged_edges(neighbours, device, rng):
    """candidate_edges stage by stage, with every segment's part (b) shuffled before the final sort,
    as a GPU may leave it: the result must not depend on that order (the CPU always places it
    ascending, so this is the only way the heap sort of a long part (b) runs there)."""
    n, k = neighbours.shape
    table = wp.array(neighbours, dtype=wp.int32, device=device)
    rows = table.reshape((n, k // 4, 4)).view(wp.vec4i) if k % 4 == 0 else table
    foreign = wp.empty(n, dtype=wp.uint32, device=device)
    count = wp.empty(n, dtype=wp.int32, device=device)
    no_reach = [wp.empty(0, dtype=wp.vec3, device=device), wp.empty(0, dtype=wp.int64, device=device)]
    wp.launch(edge_kernels._classify_rows, n, inputs=[0, rows, k, *no_reach, foreign, count], device=device)
    wp.launch(edge_kernels._count_foreign, n, inputs=[table, foreign, count], device=device)
    offsets = np.r_[0, np.cumsum(count.numpy())].astype(np.int32)
    offsets_wp = wp.array(offsets, dtype=wp.int32, device=device)
    j = wp.full(int(offsets[-1]), -1, dtype=wp.int32, device=device)
    wp.launch(edge_kernels._place_foreign, n, inputs=[table, foreign, offsets_wp, count, j], device=device)
    above, placed = count.numpy(), j.numpy()
    for s in range(n):
        part_b = placed[offsets[s] + above[s] : offsets[s + 1]]
        part_b[:] = rng.permutation(part_b)
    j = wp.array(placed, dtype=wp.int32, device=device)
    i = wp.full(int(offsets[-1]), -1, dtype=wp.int32, device=device)
    wp.launch(edge_kernels._finish_segments, n, inputs=[0, rows, k, offsets_wp, i, j], device=device)
    return Edges(i=i, j=j, count=int(offsets[-1]))


@pytest.mark.parametrize("k", [3, 16, 32])
def test_edges_independent_of_part_b_order(device, k, rng):
    n = 3000
    neighbours = with_hub(random_neighbours(n, k, rng), 0, rng)
    check_edges(staged_edges(neighbours, device, rng), neighbours)


def test_edges_of_views(device, rng):
    """A strided view and a view not aligned to 16 bytes read through the plain int32 path."""
    n, k = 5000, 16
    neighbours = local_neighbours(n, k, rng)
    wide = wp.array(np.c_[neighbours, np.full((n, 3), -1, dtype=np.int32)], dtype=wp.int32, device=device)
    strided = wide[:, :k]
    assert not strided.is_contiguous
    flat = wp.array(np.r_[np.int32(-1), neighbours.ravel()], dtype=wp.int32, device=device)
    shifted = flat[1:].reshape((n, k))
    assert shifted.ptr % 16 != 0
    for view in (strided, shifted):
        check_edges(candidate_edges(view), neighbours)


def test_edges_deterministic(device, rng):
    neighbours = with_hub(random_neighbours(40000, 16, rng), 7, rng)
    table = wp.array(neighbours, dtype=wp.int32, device=device)
    first, second = candidate_edges(table), candidate_edges(table)
    assert first.count == second.count
    assert first.i.numpy().tobytes() == second.i.numpy().tobytes()
    assert first.j.numpy().tobytes() == second.j.numpy().tobytes()


def knn_edges_of(points, device):
    means = wp.array(points, dtype=wp.vec3, device=device)
    reach = wp.full(len(points), -1, dtype=wp.int64, device=device)
    neighbours = knn_graph(means, 16, reach=reach)
    return neighbours.numpy(), candidate_edges(neighbours, means, reach)


@pytest.mark.skipif(not HAS_CUDA, reason="compares the CPU with a CUDA GPU (needs Warp's CPU compiler too)")
def test_edges_same_on_cpu_and_cuda(rng):
    """Edges of a hand-made table and of an off-lattice kNN graph (the reach comparison, which
    recomputes distances): identical on the CPU and CUDA."""
    neighbours = random_neighbours(20000, 24, rng)
    cpu, gpu = edges_of(neighbours, "cpu"), edges_of(neighbours, "cuda:0")
    np.testing.assert_array_equal(gpu.i.numpy(), cpu.i.numpy())
    np.testing.assert_array_equal(gpu.j.numpy(), cpu.j.numpy())
    points = off_lattice_points(6000, seed=21)
    (_, cpu), (_, gpu) = knn_edges_of(points, "cpu"), knn_edges_of(points, "cuda:0")
    np.testing.assert_array_equal(gpu.i.numpy(), cpu.i.numpy())
    np.testing.assert_array_equal(gpu.j.numpy(), cpu.j.numpy())


def test_edges_off_lattice_match_reference(knn_device):
    """Without a second device: the edges of an off-lattice kNN graph, through the reach comparison,
    against the reference built from the table."""
    table, edges = knn_edges_of(off_lattice_points(6000, seed=21), knn_device)
    check_edges(edges, table)


def test_edges_empty_and_too_wide(device):
    for shape in ((0, 4), (5, 0)):
        edges = candidate_edges(wp.empty(shape, dtype=wp.int32, device=device))
        assert edges.count == 0 and edges.i.shape == (0,) and edges.j.shape == (0,)
    with pytest.raises(ValueError):
        candidate_edges(wp.zeros((40, 33), dtype=wp.int32, device=device))


@wp.kernel
def _sort_parts(values: wp.array(dtype=wp.int32), bounds: wp.array(dtype=wp.int32)):
    s = wp.tid()
    edge_kernels._sort_part(values, bounds[s], bounds[s + 1])


def test_sort_part(device, rng):
    """The segment sort: insertion up to SMALL_PART values, a heap sort beyond, any input order."""
    sizes = [0, 1, 2, 31, 32, 33, 100, 5000, 5000, 5000]
    parts = [rng.permutation(10**6)[:m] for m in sizes[:-2]]
    parts += [np.arange(5000) * 3, np.arange(5000)[::-1] * 3]  # already sorted, reversed
    values = np.concatenate(parts).astype(np.int32)
    bounds = np.r_[0, np.cumsum(sizes)].astype(np.int32)
    out = wp.array(values, dtype=wp.int32, device=device)
    wp.launch(_sort_parts, len(sizes), inputs=[out, wp.array(bounds, dtype=wp.int32, device=device)], device=device)
    expected = np.concatenate([np.sort(p) for p in parts])
    np.testing.assert_array_equal(out.numpy(), expected)


@wp.kernel
def _mark_rows(first: int, marks: wp.array(dtype=wp.int32)):
    r = first + wp.tid()
    marks[r] = marks[r] + 1 + r


def test_launch_rows_from_covers_every_row_once(device):
    for rows in (0, 1, 1000, 100003):
        marks = wp.zeros(rows, dtype=wp.int32, device=device)
        launch_rows_from(_mark_rows, rows, [marks], device)
        np.testing.assert_array_equal(marks.numpy(), np.arange(rows) + 1)


@pytest.mark.parametrize("n", [1, 5, 4096, 10_007])
@pytest.mark.parametrize("cores", [1, 3])
def test_bounding_box_matches_numpy(device, rng, monkeypatch, n, cores):
    """The finite points' box and the count of the others, with the parts on one or several CPU
    threads (``cores``); no finite point: an empty (inf, -inf) box."""
    monkeypatch.setattr(parallel, "cpu_workers", lambda: cores)
    points = (rng.normal(size=(n, 3)) * 10.0**rng.integers(-3, 4, size=(n, 1))).astype(np.float32)
    bad = rng.random(n) < 0.1
    points[bad, rng.integers(0, 3, size=int(bad.sum()))] = rng.choice([np.nan, np.inf, -np.inf], size=int(bad.sum()))
    lo, hi, count = bounding_box(wp.array(points, dtype=wp.vec3, device=device))
    finite = points[np.isfinite(points).all(axis=1)].astype(np.float64)
    assert count == n - len(finite)
    if len(finite):
        np.testing.assert_array_equal(lo, finite.min(axis=0))
        np.testing.assert_array_equal(hi, finite.max(axis=0))
    else:
        assert np.all(lo == np.inf) and np.all(hi == -np.inf)
