"""Merge operator against a float64 numpy MPMM, plus the invariants of a merge."""

import numpy as np
import pytest
import reference
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp.operators import MassPreservingMomentMatching
from nanogs_warp.pairing import Pairs
from nanogs_warp.splats import SplatSet


def merged(arrays, device, pairs_ij, operator=None):
    """Runs ``operator`` (default MPMM) with every row kept in place (identity destination); the
    rows it must write are poisoned with NaN first."""
    n = len(arrays["means"])
    arrays = dict(arrays, extras=np.random.default_rng(3).normal(size=(n, 2)).astype(np.float32))
    source = SplatSet.from_numpy(**arrays, device=device)
    poisoned = {key: value.copy() for key, value in arrays.items()}
    for value in poisoned.values():
        value[pairs_ij[:, 0]] = np.nan
    out = SplatSet.from_numpy(**poisoned, device=device, validate=False)
    pi = wp.array(pairs_ij[:, 0].astype(np.int32), device=device)
    pj = wp.array(pairs_ij[:, 1].astype(np.int32), device=device)
    identity = wp.array(np.arange(n, dtype=np.int32), device=device)
    (operator or MassPreservingMomentMatching())(source, Pairs(pi, pj, len(pairs_ij)), out, identity)
    np.testing.assert_array_equal(source.means.numpy(), arrays["means"])  # the source is never changed
    return arrays, out.to_numpy()


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_mpmm_matches_reference(device, rng, sh_degree):
    n = 256
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    perm = rng.permutation(n)
    pairs_ij = np.stack([perm[: n // 2], perm[n // 2 :]], 1)
    before, after = merged(arrays, device, pairs_ij)
    for i, j in pairs_ij:
        ref = reference.mpmm(before, i, j)
        cov = reference.covariances(after["rotations"][[i]], after["log_scales"][[i]])[0]
        scale = np.abs(ref["cov"]).max()
        np.testing.assert_allclose(after["means"][i], ref["mean"], rtol=1e-5, atol=1e-6 * np.abs(ref["mean"]).max())
        np.testing.assert_allclose(cov, ref["cov"], atol=2e-5 * scale)
        np.testing.assert_allclose(reference.sigmoid(after["opacities"][i]), ref["alpha"], rtol=1e-5)
        np.testing.assert_allclose(after["features"][i], ref["features"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(after["extras"][i], ref["extras"], rtol=1e-5, atol=1e-6)
        # invariants: unit quaternion, decreasing scales, mean inside the pair's bounding box
        assert abs(np.linalg.norm(after["rotations"][i]) - 1) < 1e-6
        assert after["log_scales"][i][0] >= after["log_scales"][i][1] >= after["log_scales"][i][2]
        lo = np.minimum(before["means"][i], before["means"][j]) - 1e-6
        hi = np.maximum(before["means"][i], before["means"][j]) + 1e-6
        assert np.all((after["means"][i] >= lo) & (after["means"][i] <= hi))
    untouched = np.setdiff1d(np.arange(n), pairs_ij[:, 0])
    np.testing.assert_array_equal(after["means"][untouched], before["means"][untouched])


def test_identical_splats_keep_shape(device, rng):
    """Merging a splat with its copy keeps mean and covariance; opacity follows the over rule."""
    arrays = random_splat_arrays(2, sh_degree=1, seed=7)
    for key in arrays:
        arrays[key][1] = arrays[key][0]
    before, after = merged(arrays, device, np.array([[0, 1]]))
    cov_before = reference.covariances(before["rotations"][:1], before["log_scales"][:1])[0]
    cov_after = reference.covariances(after["rotations"][:1], after["log_scales"][:1])[0]
    np.testing.assert_allclose(cov_after, cov_before, atol=1e-5 * np.abs(cov_before).max())
    np.testing.assert_allclose(after["means"][0], before["means"][0], rtol=1e-6)
    alpha = reference.sigmoid(before["opacities"][0])
    np.testing.assert_allclose(reference.sigmoid(after["opacities"][0]), 1 - (1 - alpha) ** 2, rtol=1e-5)


def test_extreme_values_stay_finite(device):
    """Tiny scales, near-opaque and near-transparent splats, isotropic splats: finite output."""
    arrays = random_splat_arrays(8, sh_degree=0, seed=11)
    arrays["log_scales"][0:2] = -19.0
    arrays["log_scales"][2:4] = np.log(0.01)  # isotropic
    arrays["opacities"][4:6] = 30.0
    arrays["opacities"][6:8] = -30.0
    _, after = merged(arrays, device, np.array([[0, 1], [2, 3], [4, 5], [6, 7]]))
    merged_rows = [0, 2, 4, 6]
    for key in ("means", "rotations", "log_scales", "opacities", "features"):
        assert np.all(np.isfinite(after[key][merged_rows])), key
    assert np.all(np.abs(after["opacities"][merged_rows]) <= 16.1 + 1e-5)
