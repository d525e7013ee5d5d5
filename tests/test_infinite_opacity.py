"""Opacity logits of +-Inf (alpha 1 and 0) through every operator and cost and the renderer: the
load saturates them to +-float32 max, and every output stays finite."""

from __future__ import annotations

import numpy as np
import pytest
from scene_factory import random_splat_arrays, write_splats_ply

from nanogs_warp import SimplifyConfig, SplatSet, simplify
from nanogs_warp.io.ply import load_ply


def _scene(logit_inf: float) -> dict[str, np.ndarray]:
    a = random_splat_arrays(240, 1, seed=11)
    rows = np.random.default_rng(3).permutation(240)
    a["opacities"][rows[:60]] = logit_inf
    a["opacities"][rows[60:120]] = -logit_inf  # pairs of two alpha-0 splats are likely neighbours
    return a


@pytest.fixture(scope="module")
def infinite_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("inf") / "inf.ply"
    write_splats_ply(path, _scene(np.inf))
    return path


@pytest.mark.parametrize("operator", ["coverage", "area", "mpmm"])
@pytest.mark.parametrize("cost", ["runnalls", "idiv", "mse"])
def test_every_operator_and_cost_stays_finite(infinite_scene, device, operator, cost):
    splats = load_ply(infinite_scene, device=device)
    out = simplify(splats, ratio=0.1, config=SimplifyConfig(operator=operator, cost=cost), device=device).to_numpy()
    assert out["means"].shape[0] == 24
    for key in ("means", "rotations", "log_scales", "opacities", "features"):
        assert np.isfinite(out[key]).all(), key


def test_render_of_infinite_opacities(infinite_scene, device, tmp_path):
    """Alpha exactly 1 and 0 render as logits of +-30 do (sigmoid 1 in float32, and below 1/255)."""
    from nanogs_warp.eval.cameras import orbit_cameras
    from nanogs_warp.eval.evaluate import evaluate

    finite = tmp_path / "finite.ply"
    write_splats_ply(finite, _scene(30.0))
    splats = load_ply(infinite_scene, device=device)
    cameras = orbit_cameras(splats, views=2, size=32, up="-y")
    result = evaluate(load_ply(finite, device=device), [splats], cameras, device, (0.0, 0.0, 0.0), names=["inf"])
    assert all(v["psnr"] == np.inf for v in result["tests"][0]["views"])


def test_infinite_logits_from_host_arrays_are_saturated_as_on_reading(infinite_scene, device):
    """``SplatSet.from_numpy`` took +-Inf logits as they were: two alpha-0 splats merged into NaN
    centres and colours (written silently) or stopped the next pass with an internal error. Now it
    saturates them as the readers do, so the scene simplifies to the bytes its file gives."""
    arrays = _scene(np.inf)
    before = {key: value.copy() for key, value in arrays.items()}
    built = SplatSet.from_numpy(**arrays, device=device)
    assert all(np.array_equal(arrays[key], before[key]) for key in arrays)  # the caller's arrays unchanged
    logits = built.opacities.numpy()
    assert np.isfinite(logits).all() and logits.max() == np.finfo(np.float32).max and logits.min() == -np.finfo(np.float32).max
    from_file = load_ply(infinite_scene, device=device)
    for ratio in (0.6, 0.1):  # one pass (every pair of two alpha-0 splats merges), then several
        got = simplify(built, ratio=ratio, device=device).to_numpy()
        expected = simplify(from_file, ratio=ratio, device=device).to_numpy()
        for key in ("means", "rotations", "log_scales", "opacities", "features"):
            assert np.isfinite(got[key]).all() and np.array_equal(got[key], expected[key]), key
