"""tools/surfel_scene.py: a 2DGS copy of a 3DGS scene keeps each splat's two largest axes where they
were, so that the copy, read as flat splats, has the covariances of the original without their
smallest axis."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from reference import covariances
from scene_factory import random_splat_arrays, write_splats_ply

sys.path.insert(0, str(Path(__file__).parents[1] / "tools"))

from surfel_scene import main as surfel_scene  # noqa: E402

from nanogs_warp.io.ply import load_ply  # noqa: E402


def test_the_copy_is_the_scene_without_its_smallest_axes(tmp_path, monkeypatch):
    arrays = random_splat_arrays(300, sh_degree=1, seed=12)
    write_splats_ply(tmp_path / "in.ply", arrays)
    monkeypatch.setattr(sys, "argv", ["surfel_scene.py", str(tmp_path / "in.ply"), str(tmp_path / "out.ply")])
    surfel_scene()
    copy = load_ply(tmp_path / "out.ply")
    assert copy.layout.surfels and copy.count == 300
    got = copy.to_numpy()
    flat = arrays["log_scales"].copy()
    flat[np.arange(300), np.argmin(flat, axis=1)] = -30.0
    np.testing.assert_allclose(covariances(got["rotations"], got["log_scales"]), covariances(arrays["rotations"], flat),
                               rtol=0, atol=2e-6 * np.exp(2 * arrays["log_scales"].max()))  # fmt: skip
    two_largest = np.sort(arrays["log_scales"], axis=1)[:, 1:]
    np.testing.assert_array_equal(np.sort(got["log_scales"][:, :2], axis=1), two_largest)
    for key in ("means", "opacities", "features"):
        np.testing.assert_array_equal(got[key], arrays[key])
