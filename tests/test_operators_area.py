"""The area and coverage merge operators and the Runnalls cost against float64 numpy references,
plus their invariants (conserved quantities, finite values, unit quaternions)."""

import numpy as np
import pytest
import reference
import warp as wp
from scene_factory import random_splat_arrays
from test_merge import merged

from nanogs_warp.operators import OPERATORS, AreaWeightedMomentMatching, CoverageMomentMatching
from nanogs_warp.splats import SplatSet

LOGIT_LIMIT = 16.1


def random_pairs(rng, n):
    perm = rng.permutation(n)
    return np.stack([perm[: n // 2], perm[n // 2 :]], 1)


def near_random_pairs(rng, arrays, spread=0.05):
    """Disjoint random pairs, each j moved near its i (so that merges overlap and some saturate)."""
    pairs_ij = random_pairs(rng, len(arrays["means"]))
    i, j = pairs_ij.T
    arrays["means"][j] = arrays["means"][i] + rng.normal(scale=spread, size=(len(i), 3)).astype(np.float32)
    return pairs_ij


def check_splat(before, after, i, j):
    """Unit quaternion, decreasing scales, finite values, mean inside the pair's bounding box."""
    for key in ("means", "rotations", "log_scales", "opacities", "features", "extras"):
        assert np.all(np.isfinite(after[key][i])), key
    assert abs(np.linalg.norm(after["rotations"][i]) - 1) < 1e-6
    assert after["log_scales"][i][0] >= after["log_scales"][i][1] >= after["log_scales"][i][2]
    assert abs(after["opacities"][i]) <= LOGIT_LIMIT + 1e-5
    lo = np.minimum(before["means"][i], before["means"][j]) - 1e-6
    hi = np.maximum(before["means"][i], before["means"][j]) + 1e-6
    assert np.all((after["means"][i] >= lo) & (after["means"][i] <= hi))


def check_against(ref, before, after, i):
    cov = reference.covariances(after["rotations"][[i]], after["log_scales"][[i]])[0]
    np.testing.assert_allclose(after["means"][i], ref["mean"], rtol=1e-5, atol=1e-6 * np.abs(ref["mean"]).max())
    np.testing.assert_allclose(cov, ref["cov"], atol=2e-5 * np.abs(ref["cov"]).max())
    np.testing.assert_allclose(reference.sigmoid(after["opacities"][i]), ref["alpha"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(after["features"][i], ref["features"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(after["extras"][i], ref["extras"], rtol=1e-5, atol=1e-6)


def test_registered():
    assert OPERATORS["area"] is AreaWeightedMomentMatching
    assert OPERATORS["coverage"] is CoverageMomentMatching


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_area_matches_reference(device, rng, sh_degree):
    n = 256
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    pairs_ij = near_random_pairs(rng, arrays)
    before, after = merged(arrays, device, pairs_ij, AreaWeightedMomentMatching())
    clamped = 0
    for i, j in pairs_ij:
        ref = reference.area_merge(before, i, j)
        check_against(ref, before, after, i)
        check_splat(before, after, i, j)
        clamped += ref["alpha_unclamped"] >= 1
    assert 0 < clamped < len(pairs_ij)  # both branches of the clamp are exercised
    untouched = np.setdiff1d(np.arange(n), pairs_ij[:, 0])
    np.testing.assert_array_equal(after["means"][untouched], before["means"][untouched])


def test_area_conserves_weighted_mass(device, rng):
    """alpha_m * area(Sigma_m) = w_i + w_j wherever alpha_m is not clamped."""
    n = 512
    arrays = random_splat_arrays(n, sh_degree=0, seed=int(rng.integers(1 << 30)))
    arrays["opacities"] -= 3.0  # mostly faint, so that few merges clamp
    pairs_ij = near_random_pairs(rng, arrays)
    before, after = merged(arrays, device, pairs_ij, AreaWeightedMomentMatching())
    checked = 0
    for i, j in pairs_ij:
        alpha_m = reference.sigmoid(after["opacities"][i])
        if alpha_m > 0.999:
            continue
        mass = alpha_m * reference.area_proxy(after["log_scales"][[i]])[0]
        w = reference.sigmoid(before["opacities"][[i, j]]) * reference.area_proxy(before["log_scales"][[i, j]])
        np.testing.assert_allclose(mass, w.sum(), rtol=2e-5)
        checked += 1
    assert checked > len(pairs_ij) // 2


@pytest.mark.parametrize("sh_degree", [0, 3])
@pytest.mark.parametrize("growth", [0.0, 0.25, 1.0, 2.0])  # 2: alpha_m = r^-1 < 1 checks alpha_m = r / grow
def test_coverage_matches_reference(device, rng, sh_degree, growth):
    n = 256
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    pairs_ij = near_random_pairs(rng, arrays)
    before, after = merged(arrays, device, pairs_ij, CoverageMomentMatching(growth))
    saturated = 0
    for i, j in pairs_ij:
        ref = reference.coverage_merge(before, i, j, growth)
        check_against(ref, before, after, i)
        check_splat(before, after, i, j)
        saturated += ref["ratio"] > 1
    assert 0 < saturated < len(pairs_ij)


def test_coverage_conserves_coverage(device, rng):
    """alpha_m * (s0 s1)_m = the pair's coverage in the merged face plane wherever alpha_m < 1, and
    growth happens only where alpha_m would exceed 1 (then alpha_m = 1)."""
    n = 512
    growth = 0.25
    arrays = random_splat_arrays(n, sh_degree=0, seed=int(rng.integers(1 << 30)))
    pairs_ij = near_random_pairs(rng, arrays)
    before, after = merged(arrays, device, pairs_ij, CoverageMomentMatching(growth))
    counts = [0, 0]
    for i, j in pairs_ij:
        ref = reference.coverage_merge(before, i, j, growth)
        alpha_m = reference.sigmoid(after["opacities"][i])
        face = np.exp(after["log_scales"][i][0] + after["log_scales"][i][1], dtype=np.float64)
        if ref["ratio"] < reference.MERGED_ALPHA_MAX - 1e-3:  # below the cap: the coverage is kept
            np.testing.assert_allclose(alpha_m * face, ref["coverage"], rtol=2e-5)
            counts[0] += 1
        elif ref["ratio"] > 1.001:
            assert alpha_m > reference.MERGED_ALPHA_MAX - 1e-6
            np.testing.assert_allclose(face, ref["coverage"] / ref["ratio"] ** (1 - growth), rtol=2e-5)
            counts[1] += 1
    assert min(counts) > 0


@pytest.mark.parametrize("operator", ["area", "coverage"])
def test_identical_faint_splats_keep_shape(device, operator):
    """A faint splat merged with its copy keeps its mean and covariance; its opacity doubles (both
    the area-weighted mass and the coverage are additive when nothing clamps)."""
    arrays = random_splat_arrays(2, sh_degree=1, seed=7)
    arrays["opacities"][0] = -3.0
    for key in arrays:
        arrays[key][1] = arrays[key][0]
    before, after = merged(arrays, device, np.array([[0, 1]]), OPERATORS[operator]())
    cov_before = reference.covariances(before["rotations"][:1], before["log_scales"][:1])[0]
    cov_after = reference.covariances(after["rotations"][:1], after["log_scales"][:1])[0]
    np.testing.assert_allclose(cov_after, cov_before, atol=1e-5 * np.abs(cov_before).max())
    np.testing.assert_allclose(after["means"][0], before["means"][0], rtol=1e-6)
    np.testing.assert_allclose(after["features"][0], before["features"][0], rtol=1e-6)
    alpha = reference.sigmoid(before["opacities"][0])
    np.testing.assert_allclose(reference.sigmoid(after["opacities"][0]), 2 * alpha, rtol=1e-5)


@pytest.mark.parametrize("operator", ["area", "coverage"])
def test_extreme_values_stay_finite(device, operator):
    """Tiny scales, near-opaque and near-transparent splats, isotropic splats: finite output."""
    arrays = random_splat_arrays(10, sh_degree=0, seed=11)
    arrays["log_scales"][0:2] = -19.0
    arrays["log_scales"][2:4] = np.log(0.01)  # isotropic
    arrays["opacities"][4:6] = 30.0
    arrays["opacities"][6:8] = -30.0
    arrays["log_scales"][8] = [-1.0, -1.0, -19.0]  # flat
    arrays["log_scales"][9] = [-1.0, -19.0, -19.0]  # needle
    before, after = merged(arrays, device, np.array([[0, 1], [2, 3], [4, 5], [6, 7], [8, 9]]), OPERATORS[operator]())
    for i, j in [(0, 1), (2, 3), (4, 5), (6, 7), (8, 9)]:
        check_splat(before, after, i, j)


def test_area_and_coverage_deterministic(device, rng):
    arrays = random_splat_arrays(128, sh_degree=2, seed=3)
    pairs_ij = random_pairs(rng, 128)
    for operator in (AreaWeightedMomentMatching(), CoverageMomentMatching()):
        _, a = merged(arrays, device, pairs_ij, operator)
        _, b = merged(arrays, device, pairs_ij, operator)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
