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


def test_coverage_grows_the_face_plane_and_fits_the_opacity(device, rng):
    """Where the pair covers more than the merged footprint (ratio r > 1) the face plane grows to
    coverage / r^(1 - growth); the opacity is the one whose three-view field error is least: below
    the cap, nudging it either way increases that error (float64 quadrature-free closed forms)."""
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
        if ref["ratio"] > 1.001:
            np.testing.assert_allclose(face, ref["coverage"] / ref["ratio"] ** (1 - growth), rtol=2e-5)
            counts[1] += 1
        if ref["alpha_fit"] < reference.MERGED_ALPHA_MAX - 1e-3:
            rows = [i, j]
            mus = before["means"][rows].astype(np.float64)
            covs = reference.covariances(before["rotations"][rows], before["log_scales"][rows])
            pair_alpha = reference.sigmoid(before["opacities"][rows])

            def error(a):
                total = 0.0
                for plane in reference.view_planes(ref["cov"]):
                    pm, cm = plane @ ref["mean"], plane @ ref["cov"] @ plane.T
                    terms = [(pa, plane @ mu, plane @ c @ plane.T) for pa, mu, c in zip(pair_alpha, mus, covs)] + [(-a, pm, cm)]
                    total += sum(x[0] * y[0] * reference.gaussian_overlap_2d(x[1], x[2], y[1], y[2]) for x in terms for y in terms)
                return total

            assert error(alpha_m) <= min(error(alpha_m * 1.01), error(alpha_m * 0.99)) * (1 + 1e-9)
            counts[0] += 1
        else:
            assert alpha_m > reference.MERGED_ALPHA_MAX - 1e-6
    assert min(counts) > 0



def test_area_and_coverage_deterministic(device, rng):
    arrays = random_splat_arrays(128, sh_degree=2, seed=3)
    pairs_ij = random_pairs(rng, 128)
    for operator in (AreaWeightedMomentMatching(), CoverageMomentMatching()):
        _, a = merged(arrays, device, pairs_ij, operator)
        _, b = merged(arrays, device, pairs_ij, operator)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
