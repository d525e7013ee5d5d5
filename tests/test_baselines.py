"""tools/baselines.py: top-k by opacity x volume and seeded random subsets, and its command line."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scene_factory import random_splats_ply

from nanogs_warp.io.ply import load_ply

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import baselines  # noqa: E402


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.ply"
    arrays = random_splats_ply(path, 200, sh_degree=1, seed=4)
    return path, arrays


def test_topk_keeps_the_largest_opacity_times_volume(scene):
    path, arrays = scene
    splats = load_ply(path)
    rows = baselines.keep_rows(splats, "topk", 20)
    importance = 1 / (1 + np.exp(-arrays["opacities"].astype(np.float64))) * np.exp(arrays["log_scales"].astype(np.float64)).prod(1)
    want = np.sort(np.argsort(-importance, kind="stable")[:20])
    np.testing.assert_array_equal(rows, want)
    kept = baselines.baseline(splats, "topk", 20).to_numpy()
    for key in ("means", "rotations", "log_scales", "opacities", "features", "extras"):
        np.testing.assert_array_equal(kept[key], splats.to_numpy()[key][want])


def test_random_is_seeded_and_distinct(scene):
    path, _ = scene
    splats = load_ply(path)
    a = baselines.keep_rows(splats, "random", 50, seed=1)
    b = baselines.keep_rows(splats, "random", 50, seed=1)
    c = baselines.keep_rows(splats, "random", 50, seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert len(np.unique(a)) == 50 and np.all(np.diff(a) > 0)


def test_command_line_writes_one_file_per_budget(scene, tmp_path):
    path, _ = scene
    out = tmp_path / "out.ply"
    assert baselines.main([str(path), "-o", str(out), "--ratio", "0.1,0.01", "--method", "topk"]) == 0
    assert load_ply(tmp_path / "out_0.1.ply").count == 20
    assert load_ply(tmp_path / "out_0.01.ply").count == 2
    assert baselines.main([str(path), "-o", str(out), "--count", "500", "--method", "random"]) == 2  # more than the input
