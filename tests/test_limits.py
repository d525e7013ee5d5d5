"""32-bit index limits: a scene too large for the kNN table or the CPU pairing is refused with a
clear input error that says what fits. The limits are lowered here so that small scenes reach them."""

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splat_arrays, random_splats_ply
from typer.testing import CliRunner

from nanogs_warp import pairing, pipeline
from nanogs_warp.cli.app import app
from nanogs_warp.errors import InputError
from nanogs_warp.pairing import select_pairs
from nanogs_warp.pipeline import SimplifyConfig, check_index_limits, simplify
from nanogs_warp.splats import SplatSet
from nanogs_warp.topology import Edges


def test_check_index_limits_edges():
    check_index_limits(2**27 - 1, 16)  # 2^31 - 16 slots: fits
    with pytest.raises(InputError, match=r"at most 134,217,727 splats fit"):
        check_index_limits(2**27, 16)  # 2^31 slots exactly: does not
    check_index_limits(62, 16, limit=1000)
    with pytest.raises(InputError, match=r"at k = 16 at most 62 splats fit"):
        check_index_limits(63, 16, limit=1000)


def test_pipeline_refuses_before_any_pass(monkeypatch):
    monkeypatch.setattr(pipeline, "INDEX_LIMIT", 1000)
    splats = SplatSet.from_numpy(**random_splat_arrays(100, seed=1), device="cpu")
    passes = []
    with pytest.raises(InputError, match=r"100 splats x 16 neighbours .* at most 62 splats fit"):
        next(pipeline.simplify_progressively(splats, [10], SimplifyConfig(k=16), on_pass=passes.append))
    assert passes == []
    # a scene that fits runs to the end under the same limit
    assert simplify(SplatSet.from_numpy(**random_splat_arrays(60, seed=1), device="cpu"), count=6, config=SimplifyConfig(k=16)).count == 6


def test_limit_counts_the_k_used_after_pruning(monkeypatch):
    """k shrinks to N - 1 on tiny scenes; the check uses the k that runs."""
    monkeypatch.setattr(pipeline, "INDEX_LIMIT", 100)
    splats = SplatSet.from_numpy(**random_splat_arrays(10, seed=2), device="cpu")
    assert simplify(splats, count=2, config=SimplifyConfig(k=32)).count == 2  # 10 x 9 = 90 slots


def test_cpu_pairing_refuses_too_many_edges(monkeypatch):
    rng = np.random.default_rng(0)
    n, e = 50, 120
    i = rng.integers(0, n - 1, e).astype(np.int32)
    j = (i + 1 + rng.integers(0, 3, e)).clip(max=n - 1).astype(np.int32)
    edges = Edges(wp.array(i, device="cpu"), wp.array(j, device="cpu"), e)
    costs = wp.array(rng.random(e).astype(np.float32), device="cpu")
    monkeypatch.setattr(pairing, "INDEX_LIMIT", 2 * e + 1)
    assert select_pairs(edges, costs, n, 10, method="sequential").count > 0  # 2 E = limit - 1: fits
    monkeypatch.setattr(pairing, "INDEX_LIMIT", 2 * e)
    with pytest.raises(InputError, match=r"120 candidate edges.* about 49 splats of this scene fit"):
        select_pairs(edges, costs, n, 10, method="sequential")
    assert select_pairs(edges, costs, n, 10, method="parallel").count > 0  # the GPU method has no such buffer


def test_cli_reports_what_fits(monkeypatch, tmp_path):
    monkeypatch.setattr(pipeline, "INDEX_LIMIT", 1000)
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 300, seed=3)
    result = CliRunner().invoke(app, ["simplify", str(scene), "-o", str(tmp_path / "out.ply"), "--ratio", "0.1", "--device", "cpu"])
    assert result.exit_code == 2
    assert result.stderr.startswith("nanogs-warp: error: 300 splats x 24 neighbours")
    assert "at most 41 splats fit" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out.ply").exists()


def test_failed_run_leaves_no_output_folder(monkeypatch, tmp_path):
    monkeypatch.setattr(pipeline, "INDEX_LIMIT", 1000)
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 300, seed=3)
    result = CliRunner().invoke(app, ["simplify", str(scene), "-o", f"{tmp_path}/lods/", "--ratio", "0.1", "--device", "cpu"])
    assert result.exit_code == 2 and not (tmp_path / "lods").exists()
