"""Compaction: removing rows keeps every other row's every attribute, in order (against numpy)."""

import numpy as np
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp.compact import remove_rows, select_rows
from nanogs_warp.splats import SplatSet


def test_remove_rows_keeps_every_attribute(device, rng):
    n = 500
    arrays = random_splat_arrays(n, sh_degree=2, seed=8)
    arrays["extras"] = rng.normal(size=(n, 3)).astype(np.float32)
    splats = SplatSet.from_numpy(**arrays, device=device)
    removed = np.sort(rng.choice(n, 180, replace=False)).astype(np.int32)
    out, destination = remove_rows(splats, wp.array(rng.permutation(removed), dtype=wp.int32, device=device), len(removed))
    kept = np.setdiff1d(np.arange(n), removed)
    assert out.count == len(kept)
    got, source = out.to_numpy(), splats.to_numpy()
    for key in source:
        np.testing.assert_array_equal(got[key], source[key][kept], err_msg=key)
    np.testing.assert_array_equal(destination.numpy()[kept], np.arange(len(kept)))


def test_select_rows_by_flag(device, rng):
    n = 64
    splats = SplatSet.from_numpy(**random_splat_arrays(n, seed=3), device=device)
    keep = (rng.random(n) < 0.5).astype(np.int32)
    out, _ = select_rows(splats, wp.array(keep, dtype=wp.int32, device=device), int(keep.sum()))
    for key, value in splats.to_numpy().items():
        np.testing.assert_array_equal(out.to_numpy()[key], value[keep == 1], err_msg=key)
