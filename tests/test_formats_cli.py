"""The commands with every format: outputs in the format their name (or --format) asks for, LOD
sets, infinite opacity logits (accepted, counted, never dropped silently) and eval/batch inputs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scene_factory import random_splat_arrays, write_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.io import detect_format, load_splats
from nanogs_warp.io.ply import load_ply

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.ply"
    write_splats_ply(path, random_splat_arrays(400, 3, seed=5))
    return path


def test_output_names_pick_the_format(scene, tmp_path):
    result = run("simplify", scene, "-o", tmp_path / "small.splat", "--ratio", "0.1", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert detect_format(tmp_path / "small.splat") == "splat" and load_splats(tmp_path / "small.splat").count == 40
    assert "warning: small.splat: .splat cannot hold SH degree 3 -> 0" in result.stderr
    result = run("simplify", scene, "-o", tmp_path / "c.compressed.ply", "--ratio", "0.1,0.05", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    assert detect_format(tmp_path / "c_0.1.compressed.ply") == "compressed-ply"
    assert load_splats(tmp_path / "c_0.05.compressed.ply").count == 20
    (tmp_path / "c_0.1.compressed.ply").rename(tmp_path / "my.scene.compressed.ply")  # into a folder: its name less the two-part suffix
    result = run("simplify", tmp_path / "my.scene.compressed.ply", "-o", f"{tmp_path / 'dir'}/", "--ratio", "0.5", "--device", "cpu", "-q")
    assert result.exit_code == 0 and (tmp_path / "dir" / "my.scene_0.5.ply").is_file(), result.output
    result = run("simplify", scene, "-o", tmp_path / "forced.ply", "--ratio", "0.1", "--format", "spz", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert detect_format(tmp_path / "forced.ply") == "spz"


def test_chain_in_sog_and_as_a_lod_set(scene, tmp_path):
    result = run("simplify", scene, "-o", tmp_path / "lod.sog", "--ratio", "0.1,0.01", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    assert [load_splats(tmp_path / f"lod_{r}.sog").count for r in ("0.1", "0.01")] == [40, 4]
    (tmp_path / "set").mkdir()
    result = run("simplify", scene, "-o", tmp_path / "set" / "lod-meta.json", "--ratio", "0.01,0.1", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert [(o["budget"], o["level"], o["count"]) for o in summary["outputs"]] == [("0.1", 0, 40), ("0.01", 1, 4)]
    meta = json.loads((tmp_path / "set" / "lod-meta.json").read_text())
    assert meta["counts"] == [40, 4]
    # the same merges as the PLY chain: the finest level holds the PLY output's centres (quantised)
    assert run("simplify", scene, "-o", tmp_path / "p.ply", "--ratio", "0.1", "--device", "cpu", "-q").exit_code == 0
    ply = load_ply(tmp_path / "p.ply").to_numpy()["means"]
    sog = load_splats(tmp_path / "set" / "lod-meta.json").to_numpy()["means"]
    assert np.abs(np.sort(sog, axis=0) - np.sort(ply, axis=0)).max() < 1e-3 * np.ptp(ply)


def test_several_budgets_cannot_share_an_unbundled_sog(scene, tmp_path):
    result = run("simplify", scene, "-o", tmp_path / "meta.json", "--ratio", "0.1,0.01", "--device", "cpu")
    assert result.exit_code == 2 and "lod-meta.json" in result.stderr


def test_infinite_opacity_logits_are_valid(tmp_path):
    a = random_splat_arrays(300, 1, seed=7)
    a["opacities"][:20] = np.inf
    a["opacities"][20:30] = -np.inf
    path = tmp_path / "inf.ply"
    write_splats_ply(path, a)
    result = run("info", path, "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["infinite_opacity"] == {"+inf": 20, "-inf": 10} and info["nonfinite_rows"] == 0
    splats = load_ply(path)
    logits = splats.opacities.numpy()
    assert splats.count == 300 and np.all(np.isfinite(logits))
    assert np.all(logits[:20] == np.finfo(np.float32).max) and np.all(logits[20:30] == -np.finfo(np.float32).max)
    np.testing.assert_array_equal(logits[30:], a["opacities"][30:])  # finite logits untouched
    out = tmp_path / "out.ply"
    result = run("simplify", path, "-o", out, "--ratio", "0.1", "--device", "cpu", "--drop-invalid")
    assert result.exit_code == 0, result.output
    assert "dropped" not in result.stderr
    small = load_ply(out).to_numpy()
    assert small["means"].shape[0] == 30
    assert all(np.isfinite(small[k]).all() for k in ("means", "log_scales", "rotations", "features"))


def test_drop_invalid_says_how_many_and_why(tmp_path):
    a = random_splat_arrays(100, 0, seed=8)
    a["means"][3, 1] = np.nan
    a["opacities"][5] = np.nan
    path = tmp_path / "nan.ply"
    write_splats_ply(path, a)
    result = run("simplify", path, "-o", tmp_path / "o.ply", "--count", "10", "--device", "cpu", "--drop-invalid")
    assert result.exit_code == 0, result.output
    assert "warning: nan.ply: dropped 2 of 100 splats (2 with NaN/Inf values in y, opacity)" in result.stderr


def test_eval_and_info_read_every_format(scene, tmp_path):
    assert run("simplify", scene, "-o", tmp_path / "s.sog", "--ratio", "0.1", "--device", "cpu", "-q").exit_code == 0
    result = run("eval", scene, tmp_path / "s.sog", "--views", "2", "--size", "32", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["tests"][0]["count"] == 40
    result = run("info", tmp_path / "s.sog")
    assert result.exit_code == 0 and "SOG (.sog)" in result.stdout and "SH degree   3" in result.stdout


def test_batch_writes_the_format_asked_for(tmp_path):
    (tmp_path / "in").mkdir()
    write_splats_ply(tmp_path / "in" / "a.ply", random_splat_arrays(200, 0, seed=9))
    result = run("batch", tmp_path / "in", "-o", tmp_path / "out", "--ratio", "0.1", "--format", "spz",
                 "--devices", "cpu", "-q")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert detect_format(tmp_path / "out" / "a_0.1.spz") == "spz"
    # and reads it back as a scene of a second batch
    result = run("batch", tmp_path / "out", "-o", tmp_path / "again", "--ratio", "0.5", "--devices", "cpu", "-q")
    assert result.exit_code == 0, result.output
    assert load_ply(tmp_path / "again" / "a_0.1_0.5.ply").count == 10


def test_batch_reports_dropped_rows_and_losses(tmp_path):
    (tmp_path / "in").mkdir()
    a = random_splat_arrays(100, 1, seed=12)
    a["means"][7, 0] = np.nan
    write_splats_ply(tmp_path / "in" / "b.ply", a)
    result = run("batch", tmp_path / "in", "-o", tmp_path / "out", "--ratio", "0.5,0.2", "--format", "splat",
                 "--drop-invalid", "--devices", "cpu", "--json")  # fmt: skip
    assert result.exit_code == 0, result.output
    notes = json.loads(result.stdout)["scenes"][0]["notes"]
    assert notes[0] == "b.ply: dropped 1 of 100 splats (1 with NaN/Inf values in x)"
    assert len(notes) == 2 and "SH degree 1 -> 0" in notes[1]


def _contents(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_unbundled_sog_never_replaces_the_inputs_images_or_existing_files(scene, tmp_path):
    """An unbundled SOG writes images beside its meta.json, and a LOD set a folder per level: the
    overwrite check covers every one of them, and none may be one of the input's own files."""
    sog = tmp_path / "sog"
    sog.mkdir()
    assert run("simplify", scene, "-o", sog / "meta.json", "--ratio", "0.5", "--device", "cpu", "-q").exit_code == 0
    before = _contents(sog)
    for extra in ((), ("-w",)):  # the input's images, with or without --overwrite
        result = run("simplify", sog / "meta.json", "-o", sog / "small.json", "--count", "10", "--device", "cpu", *extra)
        assert result.exit_code == 2 and "means_l.webp is one of the input's files" in result.output
    assert _contents(sog) == before

    other = tmp_path / "other"
    other.mkdir()
    (other / "sh0.webp").write_bytes(b"not ours")
    result = run("simplify", scene, "-o", other / "meta.json", "--count", "10", "--device", "cpu")
    assert result.exit_code == 2 and "sh0.webp already exists; pass --overwrite" in result.output
    assert _contents(other) == {"sh0.webp": b"not ours"}
    assert run("simplify", scene, "-o", other / "meta.json", "--count", "10", "--device", "cpu", "-w", "-q").exit_code == 0
    assert load_splats(other / "meta.json").count == 10


def test_overwriting_a_lod_set_with_fewer_levels_removes_the_older_levels(scene, tmp_path, monkeypatch):
    lods = tmp_path / "set"
    lods.mkdir()
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.2,0.1", "--device", "cpu", "-q").exit_code == 0
    (lods / "2_0" / "notes.txt").write_text("mine")  # not a file of the set: stays, and its folder with it
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5", "--device", "cpu", "-q", "-w").exit_code == 0
    meta = json.loads((lods / "lod-meta.json").read_text())
    assert meta["filenames"] == ["0_0/meta.json"]
    assert not (lods / "1_0").exists() and sorted(p.name for p in (lods / "2_0").iterdir()) == ["notes.txt"]
    assert load_splats(lods / "lod-meta.json").count == 200
    # a level that is the input is never removed, though the new set leaves it out
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.2,0.1", "--device", "cpu", "-q", "-w").exit_code == 0
    level = _contents(lods / "2_0")
    result = run("simplify", lods / "2_0" / "meta.json", "-o", lods / "lod-meta.json", "--ratio", "0.5", "--device", "cpu", "-q", "-w")
    assert result.exit_code == 0, result.output
    assert _contents(lods / "2_0") == level and not (lods / "1_0").exists()
    # a set whose writing fails part way (a full disk at its third file) retires nothing
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.2,0.1", "--device", "cpu", "-q", "-w").exit_code == 0
    before = _contents(lods)
    from nanogs_warp.errors import InputError
    from nanogs_warp.io import ply_write

    calls = []

    def full_disk(path, write, overwrite=True, outputs=None):
        calls.append(path)
        if len(calls) == 3:
            raise InputError(f"{path.name}: cannot write the file: No space left on device")
        return ply_write.atomic_write(path, write, overwrite, outputs)

    monkeypatch.setattr("nanogs_warp.io.atomic_write", full_disk)
    result = run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5", "--device", "cpu", "-w")
    assert result.exit_code == 2 and "No space left on device" in result.stderr and _contents(lods) == before


def test_retiring_an_older_lod_set_never_removes_the_new_one_nor_other_files(scene, tmp_path):
    """A level folder that links to another level, the same level named in many spellings, and a
    lod-meta.json that names itself with a 'files' list of other files: the new set stays whole,
    files that are not SOG files stay, and the old level's files go once."""
    lods = tmp_path / "set"
    lods.mkdir()
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.2", "--device", "cpu", "-q").exit_code == 0
    shutil.rmtree(lods / "1_0")
    (lods / "1_0").symlink_to("0_0", target_is_directory=True)
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.3", "--device", "cpu", "-q", "-w").exit_code == 0
    assert load_splats(lods / "lod-meta.json").count == 120 and (lods / "0_0" / "meta.json").is_file()
    (lods / "1_0").unlink()
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.2", "--device", "cpu", "-q", "-w").exit_code == 0
    (lods / "notes.txt").write_text("mine")
    meta = json.loads((lods / "lod-meta.json").read_text())
    meta["filenames"] += ["./1_0/meta.json", "1_0//meta.json", "lod-meta.json"]
    meta["junk"] = {"files": ["notes.txt"]}
    (lods / "lod-meta.json").write_text(json.dumps(meta))
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5", "--device", "cpu", "-q", "-w").exit_code == 0
    assert sorted(p.name for p in lods.iterdir()) == ["0_0", "lod-meta.json", "notes.txt"]
    assert load_splats(lods / "lod-meta.json").count == 200


def test_a_lod_set_never_replaces_the_inputs_level_or_existing_levels(scene, tmp_path):
    lods = tmp_path / "set"
    lods.mkdir()
    assert run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.1", "--device", "cpu", "-q").exit_code == 0
    (lods / "lod-meta.json").unlink()
    before = _contents(lods)
    for extra in ((), ("-w",)):  # reading level 0 and writing a set over it
        result = run("simplify", lods / "0_0" / "meta.json", "-o", lods / "lod-meta.json", "--ratio", "0.5,0.1", "--device", "cpu", *extra)
        assert result.exit_code == 2 and "0_0/meta.json is one of the input's files" in result.output.replace("\\", "/")
    result = run("simplify", scene, "-o", lods / "lod-meta.json", "--ratio", "0.5,0.1", "--device", "cpu")
    assert result.exit_code == 2 and "meta.json already exists; pass --overwrite" in result.output
    assert _contents(lods) == before
