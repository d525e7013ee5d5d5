"""Compaction: removing rows keeps every other row's every attribute, in order (against numpy)."""

import numpy as np
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp.compact import merged_rows_after, remove_rows, select_rows, with_merged_appearance
from nanogs_warp.splats import SplatSet


def test_remove_rows_keeps_every_attribute(device, rng):
    n = 500
    arrays = random_splat_arrays(n, sh_degree=2, seed=8)
    arrays["extras"] = rng.normal(size=(n, 3)).astype(np.float32)
    splats = SplatSet.from_numpy(**arrays, device=device)
    removed = np.sort(rng.choice(n, 180, replace=False)).astype(np.int32)
    out, destination, keep = remove_rows(splats, wp.array(rng.permutation(removed), dtype=wp.int32, device=device), len(removed))
    kept = np.setdiff1d(np.arange(n), removed)
    assert out.count == len(kept)
    got, source = out.to_numpy(), splats.to_numpy()
    for key in source:
        np.testing.assert_array_equal(got[key], source[key][kept], err_msg=key)
    np.testing.assert_array_equal(destination.numpy()[kept], np.arange(len(kept)))
    np.testing.assert_array_equal(keep.numpy(), np.isin(np.arange(n), kept).astype(np.int32))


def test_select_rows_by_flag(device, rng):
    n = 64
    splats = SplatSet.from_numpy(**random_splat_arrays(n, seed=3), device=device)
    keep = (rng.random(n) < 0.5).astype(np.int32)
    out, _ = select_rows(splats, wp.array(keep, dtype=wp.int32, device=device), int(keep.sum()))
    for key, value in splats.to_numpy().items():
        np.testing.assert_array_equal(out.to_numpy()[key], value[keep == 1], err_msg=key)


def merged_rows_reference(merged, removed, first, n):
    """numpy: the marks after a pass that removed the rows ``removed`` and merged each pair into the
    row of its ``first`` splat."""
    kept = np.setdiff1d(np.arange(n), removed)
    new_row = np.full(n, -1)
    new_row[kept] = np.arange(len(kept))
    out = np.zeros(len(kept), np.int32) if merged is None else merged[kept].astype(np.int32)
    out[new_row[first]] = 1
    return out


def test_merged_rows_follow_their_rows(device, rng):
    n = 400
    for before in (None, (rng.random(n) < 0.3).astype(np.int32)):
        rows = rng.permutation(n).astype(np.int32)
        first, removed = rows[:90], rows[90:180]  # 90 disjoint pairs (first, removed)
        splats = SplatSet.from_numpy(**random_splat_arrays(n, seed=5), device=device)
        _, destination, keep = remove_rows(splats, wp.array(removed, dtype=wp.int32, device=device), len(removed))
        marks_before = None if before is None else wp.array(before, dtype=wp.int32, device=device)
        marks = merged_rows_after(marks_before, keep, destination, wp.array(first, dtype=wp.int32, device=device), len(first), n - len(removed))
        np.testing.assert_array_equal(marks.numpy(), merged_rows_reference(before, removed, first, n))


def test_merged_features_are_taken_in_merged_rows_only(device, rng):
    n = 300
    splats = SplatSet.from_numpy(**random_splat_arrays(n, sh_degree=3, seed=11), device=device)
    fitted = SplatSet.from_numpy(**random_splat_arrays(n, sh_degree=3, seed=12), device=device)
    merged = (rng.random(n) < 0.6).astype(np.int32)
    before = splats.features.numpy().copy()
    out = with_merged_appearance(splats, fitted, wp.array(merged, dtype=wp.int32, device=device))
    expected = np.where(merged[:, None] == 1, fitted.features.numpy(), before)
    np.testing.assert_array_equal(out.features.numpy(), expected)
    np.testing.assert_array_equal(splats.features.numpy(), before)  # a new array: the input unchanged
    for key in ("means", "rotations", "log_scales", "opacities"):  # the same arrays: nothing else is copied
        assert getattr(out, key) is getattr(splats, key)


def test_with_opacities_the_merged_rows_opacities_are_taken_too(device, rng):
    """``opacities=True``: the merged rows' opacities are ``fitted``'s as well, every other row's the
    input's, into a new array (the input unchanged)."""
    n = 300
    splats = SplatSet.from_numpy(**random_splat_arrays(n, sh_degree=1, seed=13), device=device)
    fitted = SplatSet.from_numpy(**random_splat_arrays(n, sh_degree=1, seed=14), device=device)
    merged = (rng.random(n) < 0.6).astype(np.int32)
    before = splats.opacities.numpy().copy()
    out = with_merged_appearance(splats, fitted, wp.array(merged, dtype=wp.int32, device=device), opacities=True)
    np.testing.assert_array_equal(out.opacities.numpy(), np.where(merged == 1, fitted.opacities.numpy(), before))
    np.testing.assert_array_equal(out.features.numpy(), np.where(merged[:, None] == 1, fitted.features.numpy(), splats.features.numpy()))
    np.testing.assert_array_equal(splats.opacities.numpy(), before)
    for key in ("means", "rotations", "log_scales"):
        assert getattr(out, key) is getattr(splats, key)
