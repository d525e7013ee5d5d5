"""What a seventh round of hostile use found: an output that is the input by another path (a bind
mount, a volume mounted twice, a hard link) replaced it; a batch whose output folder inside its
scenes held scenes left them out without a word; batch's --refine-size was neither checked nor
used; --format lod wrote lod-meta.json whatever the output's name; Python's 1_000 read as a budget;
a missing input was reported as "the input file" when the output was named like it; and a full
kernel cache was said to be the command's output."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys

import pytest
from scene_factory import random_splats_ply

from nanogs_warp import InputError
from nanogs_warp.batch.scenes import find_scenes, scenes_left_out
from nanogs_warp.budgets import parse_budgets
from nanogs_warp.file_identity import file_identity
from nanogs_warp.pipeline import SimplifyConfig

FAST = ("--device", "cpu", "--no-fit-geometry", "--no-fit-colour")


def cli(*args):
    return subprocess.run([sys.executable, "-m", "nanogs_warp", *map(str, args)], capture_output=True, text=True, timeout=300)


def test_file_identity_sees_one_file_by_every_path(tmp_path):
    a = tmp_path / "a.ply"
    a.write_bytes(b"x")
    os.link(a, tmp_path / "hard.ply")
    (tmp_path / "soft.ply").symlink_to(a)
    (tmp_path / "copy.ply").write_bytes(b"x")
    assert file_identity(a) == file_identity(tmp_path / "hard.ply") == file_identity(tmp_path / "soft.ply") is not None
    assert file_identity(tmp_path / "copy.ply") != file_identity(a)
    assert file_identity(tmp_path / "missing.ply") is None and file_identity("a\0b") is None


def test_an_output_that_is_the_input_by_another_path_is_refused(tmp_path):
    """A second name of the input's own file (a hard link here; a bind mount or a volume mounted
    twice alike): the path check let it through and the output replaced the input."""
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 200, seed=1)
    before = scene.read_bytes()
    os.link(scene, tmp_path / "alias.ply")
    result = cli("simplify", scene, "-o", tmp_path / "alias.ply", "--ratio", "0.5", "-w", *FAST)
    assert result.returncode == 2 and result.stderr == f"nanogs-warp: error: output {tmp_path / 'alias.ply'} is the input file; choose another output path\n"
    assert scene.read_bytes() == before and (tmp_path / "alias.ply").read_bytes() == before


@pytest.fixture
def bound_folder(tmp_path):
    """``tmp_path / "alias"``: ``tmp_path`` itself bind-mounted there (root only; skipped elsewhere)."""
    alias = tmp_path / "alias"
    alias.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "--bind", str(tmp_path), str(alias)], capture_output=True).returncode != 0:
        pytest.skip("needs root and mount --bind")
    yield alias
    subprocess.run(["umount", str(alias)], capture_output=True)


def test_an_output_into_a_bind_mount_of_the_inputs_folder_is_refused(tmp_path, bound_folder):
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 200, seed=1)
    before = scene.read_bytes()
    result = cli("simplify", scene, "-o", bound_folder / "scene.ply", "--ratio", "0.5", "-w", *FAST)
    assert result.returncode == 2 and "is the input file" in result.stderr and scene.read_bytes() == before
    result = cli("batch", tmp_path, "-o", bound_folder, "--ratio", "0.5", "--devices", "cpu")
    assert result.returncode == 2 and "is the input directory" in result.stderr


def test_a_batch_output_that_is_another_scene_by_another_path_is_refused(tmp_path):
    scenes, out = tmp_path / "in", tmp_path / "out"
    scenes.mkdir()
    out.mkdir()
    random_splats_ply(scenes / "a.ply", 200, seed=1)
    random_splats_ply(scenes / "b.ply", 200, seed=2)
    os.link(scenes / "b.ply", out / "a_0.5.ply")  # a's output would be b
    with pytest.raises(InputError, match="is the scene b.ply of this batch"):
        find_scenes(str(scenes), out, parse_budgets("0.5", None), SimplifyConfig.preset("fast"), False)


def test_scenes_inside_a_batchs_output_folder_are_named_as_left_out(tmp_path):
    scenes = tmp_path / "in"
    (scenes / "sub").mkdir(parents=True)
    random_splats_ply(scenes / "a.ply", 200, seed=1)
    random_splats_ply(scenes / "sub" / "b.ply", 200, seed=2)
    result = cli("batch", scenes, "-o", scenes / "sub", "--ratio", "0.5", "--devices", "cpu", "--no-fit-geometry", "--no-fit-colour")
    assert result.returncode == 0 and (scenes / "sub" / "a_0.5.ply").exists()
    (warning,) = [line for line in result.stderr.splitlines() if line.startswith("nanogs-warp: warning")]
    assert warning.startswith("nanogs-warp: warning: 1 scene file(s) inside the output folder") and "b.ply" in warning
    jobs = find_scenes(str(scenes), scenes / "sub", parse_budgets("0.5", None), SimplifyConfig(), False)
    assert scenes_left_out(str(scenes), scenes / "sub", jobs) == [scenes / "sub" / "b.ply"]  # its own output is not
    assert scenes_left_out(str(scenes), tmp_path / "elsewhere", jobs) == []


def test_batch_refine_size_is_checked_and_implies_refine(tmp_path):
    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 200, seed=3)
    common = ("--ratio", "0.5", "--devices", "cpu", "--no-fit-geometry", "--no-fit-colour", "--json")
    bad = cli("batch", scene, "-o", tmp_path / "bad", "--refine-size", "31", *common[:-1])
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--refine-size" in bad.stderr
    plain = cli("batch", scene, "-o", tmp_path / "plain", *common)
    sized = cli("batch", scene, "-o", tmp_path / "sized", "--refine-size", "32", *common)  # 300 steps at 32 pixels
    assert plain.returncode == 0 and sized.returncode == 0, sized.stderr
    assert (tmp_path / "plain" / "s_0.5.ply").read_bytes() != (tmp_path / "sized" / "s_0.5.ply").read_bytes()
    assert json.loads(sized.stdout)["scenes"][0]["status"] == "done"


def test_format_lod_writes_only_a_set_named_lod_meta_json(tmp_path):
    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 200, seed=4)
    (tmp_path / "lod-meta.json").write_text("{}")  # somebody else's set: never replaced unasked
    result = cli("simplify", scene, "-o", tmp_path / "o.ply", "--format", "lod", "--ratio", "0.5,0.1", "-w", *FAST)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "name the output lod-meta.json" in result.stderr
    assert (tmp_path / "lod-meta.json").read_text() == "{}" and not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("ratio, count", [("0.1_0", None), (None, "1_000")])
def test_budgets_with_underscores_are_refused(ratio, count):
    with pytest.raises(InputError, match="expected comma-separated numbers"):
        parse_budgets(ratio, count)


def test_a_missing_input_is_reported_as_missing_whatever_the_output(tmp_path):
    result = cli("simplify", tmp_path / "nothere.ply", "-o", tmp_path / "nothere.ply", "--ratio", "0.5", *FAST)
    assert result.returncode == 2 and result.stderr == "nanogs-warp: error: nothere.ply: no such file\n"


def test_a_full_kernel_cache_is_named(monkeypatch):
    import warp as wp

    from nanogs_warp import kernel_cache

    def full(**kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(wp, "force_load", full)
    with pytest.raises(InputError, match=r"^kernel cache .*: cannot write the compiled kernels: No space left on device$"):
        kernel_cache._force_load([], [wp.get_device("cpu")], 1)
