"""``simplify --refine`` and ``batch --refine``: refined outputs of the budgets' counts, the JSON report, unchanged outputs
without the flag, and one line with exit code 2 for bad refinement settings."""

import json

import numpy as np
import pytest
import typer
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.cli.batch import batch_command
from nanogs_warp.cli.errors import user_errors
from nanogs_warp.io.ply import load_ply

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_refine_each_budget(tmp_path):
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 400, sh_degree=1, seed=4)
    plain = run("simplify", scene, "-o", tmp_path / "plain.ply", "--ratio", "0.1,0.05", "--device", "cpu", "-q")
    assert plain.exit_code == 0, plain.output
    result = run("simplify", scene, "-o", tmp_path / "refined.ply", "--ratio", "0.1,0.05", "--device", "cpu",
                 "--refine-steps", "4", "--refine-size", "40", "--json")  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    for out, budget, count in zip(summary["outputs"], ("0.1", "0.05"), (40, 20)):
        assert out["budget"] == budget and out["count"] == count
        report = out["refine"]
        assert report["steps"] == 4 and report["count"] == count and report["seconds"] > 0
        assert report["loss_before"] > 0 and report["loss_after"] > 0
        refined = load_ply(out["path"]).to_numpy()
        unrefined = load_ply(tmp_path / f"plain_{budget}.ply").to_numpy()
        assert refined["means"].shape == unrefined["means"].shape
        assert not np.array_equal(refined["features"], unrefined["features"])
    again = run("simplify", scene, "-o", tmp_path / "plain2.ply", "--ratio", "0.1,0.05", "--device", "cpu", "-q")
    assert again.exit_code == 0
    for budget in ("0.1", "0.05"):
        assert (tmp_path / f"plain_{budget}.ply").read_bytes() == (tmp_path / f"plain2_{budget}.ply").read_bytes()


def test_no_loss_measured_is_null_in_the_json(tmp_path):
    """JSON has no NaN: a refinement of no step measures no loss, and says so with null."""
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 100, seed=6)
    result = run("simplify", scene, "-o", tmp_path / "out.ply", "--ratio", "0.5", "--device", "cpu", "--refine-steps", "0", "--json")
    assert result.exit_code == 0, result.output

    def no_constant(name):
        raise ValueError(f"{name} is not JSON")

    report = json.loads(result.stdout, parse_constant=no_constant)["outputs"][0]["refine"]
    assert report["steps"] == 0 and report["loss_before"] is None and report["validation_after"] is None


def test_bad_refine_settings(tmp_path):
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 50, seed=5)
    for option, value in (("--refine-size", "8"), ("--refine-steps", "-2"), ("--seed", "-1")):
        result = run("simplify", scene, "-o", tmp_path / "out.ply", "--ratio", "0.5", "--device", "cpu", "--refine", option, value)
        assert result.exit_code == 2
        assert result.stderr.count("\n") == 1 and result.stderr.startswith("nanogs-warp: error: ")
        assert not (tmp_path / "out.ply").exists()


def test_refinement_views_beyond_the_memory_are_refused_first(tmp_path, monkeypatch):
    """--refine-size 4096 at the default 300 steps would render 136 reference views of 16.8 M pixels
    (about 44 GB with a step's buffers): refused in one line before any rendering, no output written."""
    import nanogs_warp.refinement.refine as refine

    scene, out = tmp_path / "scene.ply", tmp_path / "out.ply"
    random_splats_ply(scene, 50, seed=5)
    monkeypatch.setattr(refine, "memory_short", lambda need, device: 10**9 if need > 10**9 else None)
    monkeypatch.setattr(refine, "_render_views", lambda *a: pytest.fail("rendered before the memory check"))
    result = run("simplify", scene, "-o", out, "--ratio", "0.5", "--device", "cpu", "--refine-size", "4096")
    assert result.exit_code == 2 and result.stderr.count("\n") == 1
    assert result.stderr.startswith("nanogs-warp: error: refining with 136 reference views of 4096x4096 pixels needs about 44,")
    assert "more than the 1,000,000,000 available: give a smaller --refine-size" in result.stderr
    assert not out.exists()
    monkeypatch.undo()
    result = run("simplify", scene, "-o", out, "--ratio", "0.5", "--device", "cpu", "--refine-size", "64", "--refine-steps", "2")
    assert result.exit_code == 0, result.stderr  # 64 x 64 views fit


def test_batch_refine(tmp_path):
    batch = typer.Typer(pretty_exceptions_enable=False)
    batch.callback()(lambda: None)
    batch.command("batch")(user_errors(batch_command))
    scenes = tmp_path / "in"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 300, sh_degree=1, seed=6)
    out = tmp_path / "out"
    args = ["batch", str(scenes), "-o", str(out), "--ratio", "0.1", "--devices", "cpu", "--json"]
    plain = runner.invoke(batch, args)
    assert plain.exit_code == 0, plain.output
    unrefined = load_ply(out / "a_0.1.ply").to_numpy()
    result = runner.invoke(batch, [*args, "--refine-steps", "3", "--refine-size", "40"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["scenes"][0]["status"] == "done"  # the record's options differ: redone
    refined = load_ply(out / "a_0.1.ply").to_numpy()
    assert refined["means"].shape == unrefined["means"].shape
    assert not np.array_equal(refined["features"], unrefined["features"])
    record = json.loads((out / "a.nanogs.json").read_text())
    assert record["options"]["refine_steps"] == 3 and record["options"]["refine_size"] == 40
