"""``nanogs-warp batch``: every budget of every scene, resume after a kill, one bad scene failing
alone, shards, manifests, Ray giving the same bytes as local workers."""

import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.batch.run import BatchProgress, SceneJob, SceneResult, find_scenes, select_shard
from nanogs_warp.batch.scenes import timed_out_error
from nanogs_warp.cli.batch import batch_command
from nanogs_warp.cli.errors import user_errors
from nanogs_warp.io.ply import load_ply
from nanogs_warp.pipeline import SimplifyConfig

# As cli/app.py registers it: `nanogs-warp batch ...`.
app = typer.Typer(pretty_exceptions_enable=False)
app.callback()(lambda: None)
app.command("batch")(user_errors(batch_command))
runner = CliRunner()

SCENES = {"room/a.ply": 2000, "room/sub/b.ply": 1200, "c.ply": 500, "d/d.ply": 200}
RATIOS = (0.1, 0.01, 0.001)
# What these tests check is the batch around the simplification (records, resume, workers, shards,
# manifests, Ray). The geometry and colour fits, which take most of a small scene's time on a CPU
# (seconds, whatever its size: their views' pixels), have tests of their own (test_geometry_fit.py,
# test_colour_fit.py; through batch: test_farm.py), so the runs here leave them out.
NO_FITS = ("--no-fit-geometry", "--no-fit-colour")


def run(*args):
    return runner.invoke(app, ["batch", *(str(a) for a in args), *NO_FITS])


def run_json(*args, code=0):
    result = run(*args, "--json", "--devices", "cpu")
    assert result.exit_code == code, result.output
    return {s["relative"]: s for s in json.loads(result.stdout)["scenes"]}


@pytest.fixture
def scenes(tmp_path):
    root = tmp_path / "in"
    for i, (rel, n) in enumerate(SCENES.items()):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        random_splats_ply(root / rel, n, sh_degree=i % 2, seed=i)
    return root


def outputs(out: Path) -> dict[str, int]:
    return {p.relative_to(out).as_posix(): p.stat().st_mtime_ns for p in sorted(out.rglob("*.ply"))}


def test_every_budget_of_every_scene_with_exact_counts(scenes, tmp_path):
    out = tmp_path / "out"
    summary = run_json(scenes, "-o", out, "--ratio", ",".join(map(str, RATIOS)))
    assert set(summary) == set(SCENES)
    for rel, n in SCENES.items():
        assert summary[rel]["status"] == "done" and summary[rel]["input_count"] == n
        stem = out / Path(rel).with_suffix("")
        for ratio, entry in zip(RATIOS, summary[rel]["outputs"]):
            expected = max(1, math.ceil(ratio * n))
            assert entry["budget"] == f"{ratio:g}" and entry["count"] == expected
            assert load_ply(f"{stem}_{ratio:g}.ply").count == expected
        record = json.loads(Path(f"{stem}.nanogs.json").read_text())
        assert record["input_count"] == n and len(record["input"]["sha256_pieces"]) == 64
    assert len(outputs(out)) == len(SCENES) * len(RATIOS)
    assert not list(out.rglob(".*"))  # no temporary files left


def test_table_and_progress_lines(scenes, tmp_path):
    result = run(scenes, "-o", tmp_path / "out", "--count", "50", "--devices", "cpu")
    assert result.exit_code == 0, result.output
    table = result.stdout.splitlines()
    assert table[0].split() == ["scene", "in", "out", "seconds", "device", "status"]
    assert any(line.split()[:3] == ["room/a.ply", "2,000", "50"] and line.endswith("done") for line in table)
    assert table[-1].startswith("4 scenes: 4 done, 0 skipped, 0 failed")
    assert result.stderr.count("started on cpu") == 4  # plain log lines when stderr is no terminal


def test_rerun_skips_finished_scenes_and_redoes_what_changed(scenes, tmp_path):
    out = tmp_path / "out"
    args = (scenes, "-o", out, "--ratio", "0.1,0.01")
    run_json(*args)
    first = outputs(out)
    assert {s["status"] for s in run_json(*args).values()} == {"skipped"}
    assert outputs(out) == first  # nothing rewritten

    (out / "room/sub/b.nanogs.json").unlink()  # as if killed before its record was written
    random_splats_ply(scenes / "c.ply", 500, seed=99)  # a changed input
    summary = run_json(*args)
    assert {rel: s["status"] for rel, s in summary.items()} == {
        "room/a.ply": "skipped", "room/sub/b.ply": "done", "c.ply": "done", "d/d.ply": "skipped"}  # fmt: skip
    again = outputs(out)
    assert again["room/a_0.1.ply"] == first["room/a_0.1.ply"] and again["c_0.1.ply"] != first["c_0.1.ply"]

    assert {s["status"] for s in run_json(*args, "--seed", "1").values()} == {"done"}  # other options
    assert {s["status"] for s in run_json(*args, "--seed", "1", "--force").values()} == {"done"}


def test_killed_run_resumes_without_redoing_finished_scenes(tmp_path):
    """A real subprocess, killed (with its worker) as soon as its first scene's record appears."""
    root, out = tmp_path / "in", tmp_path / "out"
    root.mkdir()
    for i in range(4):
        random_splats_ply(root / f"s{i}.ply", 40000, seed=i)
    command = [sys.executable, "-m", "nanogs_warp.cli.batch", str(root), "-o", str(out), "--ratio", "0.1,0.01",
               "--devices", "cpu", "--json", *NO_FITS]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 60
    while not list(out.glob("*.nanogs.json")) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    os.killpg(process.pid, signal.SIGKILL)
    process.communicate()
    finished = {p.name.removesuffix(".nanogs.json") for p in out.glob("*.nanogs.json")}
    assert 1 <= len(finished) < 4, "the run should have been killed midway"
    for path in out.glob("[!.]*.ply"):  # whatever is there under an output's name is whole
        load_ply(path)
    before = outputs(out)

    resumed = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0, resumed.stderr
    summary = {s["relative"]: s["status"] for s in json.loads(resumed.stdout)["scenes"]}
    assert summary == {f"s{i}.ply": "skipped" if f"s{i}" in finished else "done" for i in range(4)}
    after = outputs(out)
    assert all(after[name] == before[name] for name in before if name.split("_")[0] in finished)
    assert len(after) == 8 and not list(out.glob(".*"))  # the killed scene's temporary files are gone


def test_corrupt_scene_fails_alone(scenes, tmp_path):
    data = (scenes / "c.ply").read_bytes()
    (scenes / "bad.ply").write_bytes(data[: len(data) // 2])  # truncated, sorted between others
    (scenes / "room" / "zero.ply").write_bytes(b"")
    out = tmp_path / "out"
    summary = run_json(scenes, "-o", out, "--ratio", "0.1", code=1)
    failed = {rel: s["error"] for rel, s in summary.items() if s["status"] == "failed"}
    assert set(failed) == {"bad.ply", "room/zero.ply"}
    assert "bad.ply" in failed["bad.ply"] and "\n" not in failed["bad.ply"]
    assert all(summary[rel]["status"] == "done" for rel in SCENES)
    assert not (out / "bad.nanogs.json").exists() and not (out / "bad_0.1.ply").exists()

    result = run(scenes, "-o", out, "--ratio", "0.1", "--devices", "cpu")  # again: still fails, others skipped
    assert result.exit_code == 1
    assert "failed: bad.ply: " in result.stdout and "6 scenes: 0 done, 4 skipped, 2 failed" in result.stdout


def test_quiet_still_names_the_failures(scenes, tmp_path):
    """-q drops the progress and the table, not the errors: a failed scene is one line on stderr."""
    (scenes / "bad.ply").write_bytes(b"ply\nnot really")
    result = run(scenes, "-o", tmp_path / "out", "--ratio", "0.1", "--devices", "cpu", "-q")
    assert result.exit_code == 1 and result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.ply: FAILED" in lines[0], result.stderr


def test_two_shards_cover_the_batch_exactly_once(scenes, tmp_path):
    out = tmp_path / "out"
    parts = [run_json(scenes, "-o", out, "--count", "20", "--shard", f"{i}/2") for i in range(2)]
    assert not set(parts[0]) & set(parts[1]) and set(parts[0]) | set(parts[1]) == set(SCENES)
    assert sorted(parts[0]) == ["c.ply", "room/a.ply"]  # every other one of the sorted names
    assert all(s["status"] == "done" for part in parts for s in part.values())
    assert len(outputs(out)) == len(SCENES)

    jobs = list(range(11))
    for n in (1, 3, 4, 12):
        shards = [select_shard(jobs, i, n) for i in range(n)]
        assert sorted(sum(shards, [])) == jobs


def test_same_bytes_from_any_worker(scenes, tmp_path):
    run_json(scenes, "-o", tmp_path / "one", "--ratio", "0.05")
    run_json(scenes, "-o", tmp_path / "two", "--ratio", "0.05", "--workers", "2")
    for name in outputs(tmp_path / "one"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name


def test_manifests(scenes, tmp_path):
    (scenes / "list.txt").write_text("# scenes\nroom/a.ply\n\n  c.ply  \n")
    summary = run_json(scenes / "list.txt", "-o", tmp_path / "text", "--count", "10")
    assert sorted(summary) == ["c.ply", "room/a.ply"]  # relative to the deepest common directory

    manifest = tmp_path / "scenes.json"
    manifest.write_text(json.dumps([
        {"path": "in/room/a.ply", "ratio": [0.5, 0.25]},
        {"path": "in/c.ply", "count": 7, "k": 8, "prune-opacity": 0},
        "in/d/d.ply",
    ]))  # fmt: skip
    out = tmp_path / "json"
    summary = run_json(manifest, "-o", out, "--ratio", "0.1")
    assert [o["count"] for o in summary["room/a.ply"]["outputs"]] == [1000, 500]
    assert [o["count"] for o in summary["c.ply"]["outputs"]] == [7]
    assert [o["count"] for o in summary["d/d.ply"]["outputs"]] == [20]
    assert json.loads((out / "c.nanogs.json").read_text())["options"]["k"] == 8
    assert (out / "room" / "a_0.25.ply").exists()

    manifest.write_text(json.dumps([{"path": "in/c.ply", "ratios": 0.1}]))
    result = run(manifest, "-o", out, "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2 and "unknown key(s) ratios" in result.stderr


def test_a_manifest_scene_with_its_own_preset_sh_degree_and_refinement(scenes, tmp_path):
    manifest = tmp_path / "scenes.json"
    manifest.write_text(json.dumps([
        {"path": "in/room/a.ply", "preset": "fast", "sh-degree": 0},
        {"path": "in/c.ply", "pass_fraction": 0.3, "fit_size": False, "refine_steps": 2, "refine_size": 32},
        {"path": "in/d/d.ply", "sh_degree": None},
    ]))  # fmt: skip
    out = tmp_path / "json"
    run_json(manifest, "-o", out, "--ratio", "0.1", "--k", "8", "--sh-degree", "1")
    options = {name: json.loads((out / f"{name}.nanogs.json").read_text())["options"] for name in ("room/a", "c", "d/d")}
    assert options["room/a"]["cost"] == "runnalls" and options["room/a"]["k"] == 8  # the preset, the command line's --k over it
    assert options["room/a"]["sh_degree"] == 0 and "refine_steps" not in options["room/a"]
    assert options["c"]["cost"] == "field" and options["c"]["pass_fraction"] == 0.3 and options["c"]["fit_size"] is False
    assert options["c"]["sh_degree"] == 1 and (options["c"]["refine_steps"], options["c"]["refine_size"]) == (2, 32)
    assert "sh_degree" not in options["d/d"]  # null: the input's degree, as without --sh-degree

    # each scene's outputs are the bytes a batch of that scene alone with the same options writes
    alone = [
        ("room/a.ply", "a_0.1.ply", ["--preset", "fast", "--k", "8", "--sh-degree", "0"]),
        ("c.ply", "c_0.1.ply", ["--k", "8", "--pass-fraction", "0.3", "--no-fit-size", "--sh-degree", "1",
                                "--refine-steps", "2", "--refine-size", "32"]),
        ("d/d.ply", "d_0.1.ply", ["--k", "8"]),
    ]  # fmt: skip
    for i, (scene, name, args) in enumerate(alone):
        run_json(scenes / scene, "-o", tmp_path / f"alone{i}", "--ratio", "0.1", *args)
        assert (out / Path(scene).parent / name).read_bytes() == (tmp_path / f"alone{i}" / name).read_bytes(), scene
    assert load_ply(out / "room" / "a_0.1.ply").sh_degree == 0 and load_ply(out / "d" / "d_0.1.ply").sh_degree == 1


def test_an_output_name_too_long_to_write_fails_its_scene_in_the_dry_run_too(tmp_path):
    """A 236-letter stem gives a legal 244-byte output name whose temporary file's name is too long:
    the dry run said 'run', and the run failed with 'File name too long' after the work."""
    root = tmp_path / "in"
    root.mkdir()
    long = "s" * 236 + ".ply"
    random_splats_ply(root / long, 30, seed=1)
    random_splats_ply(root / "short.ply", 30, seed=2)
    plan = run(root, "-o", tmp_path / "out", "--ratio", "0.1", "--dry-run", "--json", "--devices", "cpu")
    actions = {s["relative"]: (s["action"], s["reason"]) for s in json.loads(plan.stdout)["scenes"]}
    message = f"output name {'s' * 40}... is 244 bytes long; at most 229 can be written"
    assert actions == {long: ("fail", message), "short.ply": ("run", "no record")}
    summary = run_json(root, "-o", tmp_path / "out", "--ratio", "0.1", code=1)
    assert summary[long]["status"] == "failed" and summary[long]["error"] == message
    assert summary["short.ply"]["status"] == "done"


def test_outputs_no_run_could_write_fail_their_scene_in_the_dry_run_too(tmp_path):
    """An output path that is a folder or a FIFO, or a record path that is a folder: the dry run
    said 'run', and the run refused the path only after the scene's work."""
    root, out = tmp_path / "in", tmp_path / "out"
    root.mkdir()
    for k, name in enumerate(("folder", "fifo", "record", "fine")):
        random_splats_ply(root / f"{name}.ply", 30, seed=k)
    out.mkdir()
    (out / "folder_0.1.ply").mkdir()
    os.mkfifo(out / "fifo_0.1.ply")
    (out / "record.nanogs.json").mkdir()
    expected = {"folder.ply": "folder_0.1.ply: is a directory", "fifo.ply": "fifo_0.1.ply: exists and is not a regular file",
                "record.ply": f"its record {out / 'record.nanogs.json'} is a folder; move it away"}  # fmt: skip
    plan = run(root, "-o", out, "--ratio", "0.1", "--dry-run", "--json", "--devices", "cpu")
    actions = {s["relative"]: (s["action"], s["reason"]) for s in json.loads(plan.stdout)["scenes"]}
    assert actions == {**{k: ("fail", v) for k, v in expected.items()}, "fine.ply": ("run", "no record")}
    summary = run_json(root, "-o", out, "--ratio", "0.1", code=1)
    assert {k: summary[k]["error"] for k in expected} == expected and summary["fine.ply"]["status"] == "done"
    assert all(summary[k]["input_count"] in (None, 0) for k in expected)  # refused before the scene was read


def test_an_output_folder_it_may_not_search_fails_that_scene_alone_in_the_dry_run_too(tmp_path, monkeypatch):
    """A folder on an output's path that the user may not search (EACCES, which ``Path.is_dir``
    raises): the dry run stopped at that scene with the error, listing no other, and the run named
    a raw PermissionError."""
    from nanogs_warp.batch.work import planned
    from nanogs_warp.budgets import parse_budgets

    random_splats_ply(tmp_path / "a.ply", 30, seed=1)
    (job,) = find_scenes(str(tmp_path / "a.ply"), tmp_path / "out", parse_budgets("0.1", None), SimplifyConfig(), False)
    is_dir = Path.is_dir

    def unsearchable(path):
        if path.parent == tmp_path / "out":
            raise PermissionError(13, "Permission denied", str(path))
        return is_dir(path)

    monkeypatch.setattr(Path, "is_dir", unsearchable)
    assert planned(job, False) == ("fail", "cannot check its outputs: Permission denied")


def test_a_dry_run_says_what_a_run_would_do_and_writes_nothing(scenes, tmp_path):
    out = tmp_path / "out"

    def plan(*args):
        result = run(scenes, "-o", out, "--ratio", "0.1", "--dry-run", "--json", *args)
        assert result.exit_code == 0, result.output
        return {s["relative"]: (s["action"], s["reason"]) for s in json.loads(result.stdout)["scenes"]}

    assert plan() == {name: ("run", "no record") for name in SCENES}
    assert not out.exists()  # no folder made
    run_json(scenes, "-o", out, "--ratio", "0.1")
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    assert plan() == {name: ("skip", None) for name in SCENES}
    (out / "c_0.1.ply").unlink()
    random_splats_ply(scenes / "d" / "d.ply", 201, seed=9)  # another input under the same name
    assert plan()["c.ply"] == ("run", "an output is missing") and plan()["d/d.ply"] == ("run", "the input changed")
    assert plan("--seed", "1")["room/a.ply"] == ("run", "other budgets or options")
    assert plan("--force")["room/a.ply"] == ("run", "--force")
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == {p: t for p, t in before.items() if p.name != "c_0.1.ply"}

    (scenes / "room" / "sub" / "b.ply").unlink()
    os.mkfifo(scenes / "room" / "pipe.ply")  # a dry run neither reads nor waits on it
    manifest = tmp_path / "list.txt"
    manifest.write_text("".join(f"{scenes / 'room' / name}\n" for name in ("a.ply", "sub/b.ply", "pipe.ply")))
    result = run(manifest, "-o", out / "room", "--ratio", "0.1", "--dry-run")
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [
        "skip  a.ply      up to date",
        "fail  pipe.ply   not a regular file",
        "fail  sub/b.ply  no such file",
        "3 scenes: 0 to run, 1 up to date, 2 would fail (dry run: nothing written)",
    ]
    result = run(manifest, "-o", out / "room", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 1 and "failed: sub/b.ply: no such file\n" in result.stdout  # the scene named once


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"sh_degree": 4}, "sh_degree must be 0, 1, 2, 3 or null, got 4"),
        ({"sh_degree": "3"}, "sh_degree: expected int"),
        ({"refine_steps": -1}, "refine_steps must be in"),
        ({"refine_steps": 5, "refine_size": 8}, "refine_size must be in"),
        ({"preset": "quick"}, "unknown preset 'quick'"),
        ({"fit_size": 1}, "fit_size: expected bool"),
        ({"pass_fraction": 0.9}, "pass"),
    ],
)
def test_bad_per_scene_settings_are_one_line(scenes, tmp_path, entry, message):
    manifest = tmp_path / "scenes.json"
    manifest.write_text(json.dumps([{"path": "in/c.ply", **entry}]))
    result = run(manifest, "-o", tmp_path / "out", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith("nanogs-warp: error: c.ply: ") and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--shard", "2/2"], "--shard '2/2'"),
        (["--shard", "x"], "--shard 'x'"),
        (["--workers", "0"], "--workers"),
        (["--workers", "two"], "--workers must be auto or a whole number"),
        (["--workers", "1.5"], "--workers must be auto or a whole number"),
        (["--workers", "\uff12"], "--workers must be auto or a whole number"),
        (["--devices", "tpu"], "--devices 'tpu'"),
        (["--k", "0"], "--k"),
        (["--count", "0"], "--count 0"),
        (["--scene-timeout", "2200000"], "--scene-timeout must be 0 (no limit) to 1e+06 seconds"),
        (["--scene-timeout", "nan"], "--scene-timeout"),
    ],
)
def test_bad_arguments_exit_2(scenes, tmp_path, args, message):
    base = ["--ratio", "0.1"] if "--count" not in args else []
    result = run(scenes, "-o", tmp_path / "out", *base, *args)
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith("nanogs-warp: error: ") and message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_an_empty_output_is_refused(scenes, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = run(scenes, "-o", "", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2 and "give an output directory with -o/--output" in result.stderr
    assert list(tmp_path.iterdir()) == [scenes]


def test_bad_inputs_exit_2(scenes, tmp_path):
    cases = [
        ((tmp_path / "missing", "-o", tmp_path / "o", "--ratio", "0.1"), "no such file, directory or glob"),
        ((f"{scenes}/*.nope", "-o", tmp_path / "o", "--ratio", "0.1"), "no .ply files match"),
        ((scenes, "-o", scenes / "c.ply", "--ratio", "0.1"), "is not a directory"),
        ((scenes, "-o", scenes, "--ratio", "0.1"), "is the input directory"),
        ((scenes, "-o", tmp_path / "o"), "no budget"),
    ]
    for args, message in cases:
        result = run(*args, "--devices", "cpu")
        assert result.exit_code == 2 and message in result.stderr, (args, result.output)
    (scenes / "room" / "A.PLY").write_bytes((scenes / "c.ply").read_bytes())
    (scenes / "room" / "a.PLY").write_bytes((scenes / "c.ply").read_bytes())
    result = run(scenes, "-o", tmp_path / "o", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2 and "would write the same outputs" in result.stderr


def test_output_inside_input_is_not_rescanned(scenes):
    jobs = find_scenes(str(scenes), scenes / "simplified", [], SimplifyConfig(), False)
    (scenes / "simplified").mkdir()
    random_splats_ply(scenes / "simplified" / "x.ply", 10)
    assert [j.relative for j in find_scenes(str(scenes), scenes / "simplified", [], SimplifyConfig(), False)] == [
        j.relative for j in jobs]  # fmt: skip
    globbed = find_scenes(f"{scenes}/**/*.ply", scenes / "simplified", [], SimplifyConfig(), False)
    assert sorted(j.relative for j in globbed) == sorted(SCENES)


def test_hidden_folders_and_a_manifests_byte_order_mark_are_no_scenes(scenes, tmp_path):
    """A folder's scan took .ipynb_checkpoints/*.ply as scenes (a glob already left them out), and a
    text manifest saved with a byte-order mark named its first scene '\ufeffc.ply'."""
    before = sorted(j.relative for j in find_scenes(str(scenes), tmp_path / "out", [], SimplifyConfig(), False))
    (scenes / ".ipynb_checkpoints").mkdir()
    random_splats_ply(scenes / ".ipynb_checkpoints" / "c-checkpoint.ply", 10)
    assert sorted(j.relative for j in find_scenes(str(scenes), tmp_path / "out", [], SimplifyConfig(), False)) == before
    (scenes / "list.txt").write_bytes("\ufeffc.ply\nroom/a.ply\n".encode("utf-8"))
    summary = run_json(scenes / "list.txt", "-o", tmp_path / "text", "--count", "10")
    assert sorted(summary) == ["c.ply", "room/a.ply"] and {s["status"] for s in summary.values()} == {"done"}


def test_live_progress_redraws_in_place():
    stream = io.StringIO()
    progress = BatchProgress(2, stream=stream, live=True)
    job = SceneJob(Path("a.ply"), "a.ply", Path("o"), (), SimplifyConfig(), False, 1)
    progress.started("w0", "cuda:1", job)
    progress.advanced("w0", (0, 1000, 500))
    progress.finished("w0", SceneResult("a.ply", "a.ply", "failed", "cuda:1", error="boom"))
    progress.close()
    text = stream.getvalue()
    assert "w0 cuda:1: a.ply: loading" in text and "\033[" in text
    assert "a.ply: FAILED on cuda:1: boom\n" in text and "1/2 scenes (0 done, 0 skipped, 1 failed)" in text


def test_a_failed_scene_is_named_once_in_its_line():
    from nanogs_warp.batch.run import format_summary

    result = SceneResult("/in/room/bad.ply", "room/bad.ply", "failed", "cpu", error="bad.ply: not a PLY file")
    dropped = SceneResult("/in/a.ply", "a.ply", "done", "cpu", notes=["a.ply: dropped 5 of 100 splats"])
    lines = format_summary([result, dropped], 1.0).splitlines()
    assert "failed: room/bad.ply: not a PLY file" in lines and "note: a.ply: dropped 5 of 100 splats" in lines


def test_missing_ray_is_one_line(scenes, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    result = run(scenes, "-o", tmp_path / "out", "--ratio", "0.1", "--ray", "auto")
    assert result.exit_code == 2
    assert result.stderr.strip() == "nanogs-warp: error: --ray needs Ray, which is not installed: pip install 'ray>=2.9' (or, from the source tree, pip install '.[ray]')"


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING", log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_tasks_write_the_same_bytes(local_ray, scenes, tmp_path):
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    run_json(scenes, "-o", local, "--ratio", "0.1,0.01")
    summary = run_json(scenes, "-o", on_ray, "--ratio", "0.1,0.01", "--ray", "auto")
    assert {s["status"] for s in summary.values()} == {"done"}
    assert all(s["device"].endswith("/cpu") for s in summary.values())
    assert outputs(local).keys() == outputs(on_ray).keys()
    for name in outputs(local):
        assert (local / name).read_bytes() == (on_ray / name).read_bytes(), name
    assert {s["status"] for s in run_json(scenes, "-o", on_ray, "--ratio", "0.1,0.01", "--ray", "auto").values()} == {"skipped"}


def test_a_dead_worker_fails_its_scene_and_is_replaced(tmp_path):
    """The worker is busy with a large scene (seconds on a CPU); killing it fails that scene alone,
    and a new worker takes the scenes still waiting."""
    root = tmp_path / "in"
    root.mkdir()
    random_splats_ply(root / "big.ply", 300)
    random_splats_ply(root / "a_slow.ply", 120_000)  # the largest: started first
    (root / "z_empty.ply").write_bytes(b"")
    command = [sys.executable, "-m", "nanogs_warp.cli.batch", str(root), "-o", str(tmp_path / "out"),
               "--count", "10", "--devices", "cpu", "--json"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if "a_slow.ply: started" in line:
            break
    workers = subprocess.run(["pgrep", "-P", str(process.pid), "-f", "spawn_main"], capture_output=True, text=True)
    worker = [int(pid) for pid in workers.stdout.split()]
    assert len(worker) == 1, workers.stdout
    os.kill(worker[0], signal.SIGKILL)
    out, _ = process.communicate(timeout=60)
    assert process.returncode == 1
    summary = {s["relative"]: s for s in json.loads(out)["scenes"]}
    assert summary["big.ply"]["status"] == "done"
    assert summary["a_slow.ply"]["error"] == "the worker process died (killed by SIGKILL); out of memory?"
    assert summary["z_empty.ply"]["status"] == "failed" and "died" not in summary["z_empty.ply"]["error"]


def test_default_time_limit_scales_with_the_scene():
    from nanogs_warp.batch.scenes import scene_timeout

    job = SceneJob(Path("a.ply"), "a.ply", Path("o"), (), SimplifyConfig(), False, 1_500_000_000)
    assert scene_timeout(job, on_gpu=True) == pytest.approx(450.0)  # docs/batch.md's example
    assert scene_timeout(job, on_gpu=False) == pytest.approx(1050.0)
    assert scene_timeout(job, on_gpu=True, seconds=12.5) == 12.5 and scene_timeout(job, True, seconds=0) is None


def test_devices_every_gpu_and_the_cpu():
    import warp as wp

    from nanogs_warp.batch.local import parse_devices
    from nanogs_warp.errors import InputError

    gpus = [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
    assert parse_devices("auto,cpu") == gpus + ["cpu"]
    if gpus:
        assert parse_devices("all,cpu") == gpus + ["cpu"]
    else:
        with pytest.raises(InputError, match="no CUDA GPU"):
            parse_devices("all,cpu")


SPIN = "NANOGS_WARP_TEST_SPIN_SCENE"  # batch_work.SPIN_SCENE_VARIABLE: a worker spins on this scene


@pytest.fixture(scope="module")
def scenes_and_a_spinner(tmp_path_factory):
    """Three scenes (the largest, taken first, is the one a worker will spin on) and their outputs
    from a batch without the spinner."""
    root, clean = tmp_path_factory.mktemp("in"), tmp_path_factory.mktemp("clean")
    for i, (name, n) in enumerate({"spin.ply": 900, "a.ply": 400, "b.ply": 300}.items()):
        random_splats_ply(root / name, n, sh_degree=i % 2, seed=i)
    run_json(root, "-o", clean, "--ratio", "0.1,0.01")
    return root, clean


def check_spinner_timed_out(summary, clean: Path, out: Path, timeout: float, what: str):
    spin = summary["spin.ply"]
    assert spin["status"] == "failed" and f"timed out after {timeout:.0f} s (--scene-timeout)" in spin["error"]
    assert what in spin["error"] and timeout <= spin["seconds"] < timeout + 10
    assert {summary[name]["status"] for name in ("a.ply", "b.ply")} == {"done"}
    assert not list(out.glob("spin*")) and not list(out.rglob(".*"))
    done = sorted(p.name for p in out.glob("[ab]_*.ply"))
    assert len(done) == 4
    for name in done:
        assert (out / name).read_bytes() == (clean / name).read_bytes(), name


def test_a_scene_past_its_time_limit_fails_alone(scenes_and_a_spinner, tmp_path, monkeypatch):
    """The worker spinning on one scene is killed at the time limit and replaced; the scene it had
    read next is handed back, and every other output is the same bytes as without the spinner."""
    (root, clean), out = scenes_and_a_spinner, tmp_path / "out"
    monkeypatch.setenv(SPIN, "spin.ply")
    started = time.monotonic()
    summary = run_json(root, "-o", out, "--ratio", "0.1,0.01", "--scene-timeout", "6", code=1)
    assert time.monotonic() - started < 60
    check_spinner_timed_out(summary, clean, out, 6, "its worker process was replaced")


@pytest.mark.parametrize("stderr", ["2>/dev/full", "2>&-"])
def test_a_batch_whose_stderr_cannot_be_written_finishes(scenes, tmp_path, stderr):
    """A full or closed stderr: the progress falls silent and every scene is done. The first hung:
    the progress's write error was taken for the worker's pipe closing. With the second, every
    worker failed to start Warp (its sys.stderr was None)."""
    out = tmp_path / "out"
    command = f"{sys.executable} -m nanogs_warp batch {scenes} -o {out} --ratio 0.1 --devices cpu --json {' '.join(NO_FITS)} {stderr}"
    done = subprocess.run(["bash", "-c", command], capture_output=False, stdout=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 0
    assert {s["status"] for s in json.loads(done.stdout)["scenes"]} == {"done"}
    assert len(list(out.rglob("*.ply"))) == len(SCENES)


def _children(pid: int) -> set[int]:
    found = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        found |= {int(c) for c in (task / "children").read_text().split()}
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir() or not sys.platform.startswith("linux"), reason="Linux's /proc")
def test_workers_end_with_their_batch(scenes_and_a_spinner, tmp_path):
    """A batch killed with SIGKILL (no handler runs) left its workers simplifying the scenes they
    held; now the kernel sends them SIGTERM, and a worker stuck in a scene ends too."""
    root, _ = scenes_and_a_spinner
    command = [sys.executable, "-m", "nanogs_warp", "batch", str(root), "-o", str(tmp_path / "out"), "--ratio", "0.1",
               "--devices", "cpu", "--workers", "1", "--scene-timeout", "0"]  # fmt: skip
    batch = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, env={**os.environ, SPIN: "spin.ply"})
    children: set[int] = set()
    try:
        for line in batch.stderr:
            if "spin.ply: started" in line:
                break
        children = _children(batch.pid)
        assert children
        batch.kill()
        batch.wait(10)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(Path(f"/proc/{c}").exists() for c in children):
            time.sleep(0.2)
        alive = [c for c in children if Path(f"/proc/{c}").exists() and "Z" not in Path(f"/proc/{c}/stat").read_text().split()[2]]
        assert not alive, alive
    finally:
        batch.kill()
        for child in children:  # a regression must not leave a worker spinning
            try:
                os.kill(child, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _deaf_to_sigterm(ready) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as a worker inside a native call that never returns
    ready.set()
    while True:
        time.sleep(1)


def test_a_worker_deaf_to_sigterm_is_killed_when_the_batch_ends(tmp_path):
    """The batch's last step sent a worker that would not end SIGTERM once, then left it: the
    parent waited on it at exit, and it ran on after the batch."""
    import multiprocessing

    from nanogs_warp.batch.local import _stop, _Worker

    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    process = context.Process(target=_deaf_to_sigterm, args=(ready,), daemon=True)
    process.start()
    parent, child = context.Pipe()
    try:
        assert ready.wait(60)
        child.close()
        _stop([_Worker("w0", "cpu", process, parent)])
        assert not process.is_alive() and process.exitcode == -signal.SIGKILL
    finally:
        if process.is_alive():
            process.kill()


def test_a_batch_whose_last_scene_times_out_ends(scenes_and_a_spinner, tmp_path):
    """The only worker is stopped at the time limit with nothing left to do: the batch ends (it used
    to wait for ever on no worker at all). In a child process, so that a regression fails, not hangs."""
    root, _ = scenes_and_a_spinner
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "spin.ply").write_bytes((root / "spin.ply").read_bytes())
    command = [sys.executable, "-m", "nanogs_warp.cli.batch", str(alone), "-o", str(tmp_path / "out"), "--ratio", "0.1",
               "--devices", "cpu", "--scene-timeout", "3", "--json"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env={**os.environ, SPIN: "spin.ply"})
    assert done.returncode == 1, done.stderr
    (scene,) = json.loads(done.stdout)["scenes"]
    assert scene["status"] == "failed" and "timed out after 3 s" in scene["error"]


def test_a_time_limit_below_ten_seconds_keeps_its_digits():
    assert timed_out_error(0.5, "x") == "timed out after 0.5 s (--scene-timeout); x"
    assert timed_out_error(3.0, "x").startswith("timed out after 3 s ")
    assert timed_out_error(2.125, "x").startswith("timed out after 2.12 s ")
    assert timed_out_error(300.4, "x").startswith("timed out after 300 s ")


def test_more_workers_than_scenes_start_one_per_scene(scenes, tmp_path):
    summary = run_json(scenes, "-o", tmp_path / "out", "--ratio", "0.1", "--workers", str(10**20))
    assert {s["status"] for s in summary.values()} == {"done"}


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_a_pipe_among_the_scenes_fails_alone_at_once(scenes, tmp_path):
    """A FIFO named like a scene would block its worker until the scene's time limit: it fails at once."""
    os.mkfifo(scenes / "pipe.ply")
    summary = run_json(scenes, "-o", tmp_path / "out", "--ratio", "0.1", code=1)
    assert summary["pipe.ply"]["status"] == "failed" and "not a regular file" in summary["pipe.ply"]["error"]
    assert all(summary[rel]["status"] == "done" for rel in SCENES)


def test_a_folder_whose_scenes_all_fail_gets_no_output_folder(scenes, tmp_path):
    (scenes / "broken").mkdir()
    (scenes / "broken" / "x.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    summary = run_json(scenes, "-o", tmp_path / "out", "--ratio", "0.1", code=1)
    assert summary["broken/x.ply"]["status"] == "failed"
    assert not (tmp_path / "out" / "broken").exists() and (tmp_path / "out" / "room" / "sub").is_dir()


@pytest.mark.parametrize("content", ['["in/c\\u0000.ply"]', '[{"path": "in/c\\u0000.ply"}]', "in/c\0.ply\n",
                                     "[" * 100_000 + "]" * 100_000])  # fmt: skip
def test_hostile_manifests_are_one_line(scenes, tmp_path, content):
    manifest = tmp_path / ("m.json" if content.startswith("[") else "m.txt")
    manifest.write_text(content)
    result = run(manifest, "-o", tmp_path / "out", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2 and ("NUL character" in result.stderr or "nested too deeply" in result.stderr), result.output


@pytest.mark.parametrize(
    "edit",
    [
        lambda r: r.update(input_count="lots"),
        lambda r: r["outputs"][0].update(count="ten"),
        lambda r: r["outputs"][0].update(count=10**400),
        lambda r: r["outputs"][0].update(path="c_0.1\0.ply"),
        lambda r: r["outputs"][0].update(path="../c.ply"),
    ],
)
def test_a_record_edited_by_hand_is_redone(scenes, tmp_path, edit):
    """Records with wrong types or names crashed the summary after all the work, or failed the scene."""
    out = tmp_path / "out"
    run_json(scenes, "-o", out, "--ratio", "0.1")
    record_path = out / "c.nanogs.json"
    record = json.loads(record_path.read_text())
    edit(record)
    record_path.write_text(json.dumps(record))
    summary = run_json(scenes, "-o", out, "--ratio", "0.1")
    assert summary["c.ply"]["status"] == "done" and summary["c.ply"]["input_count"] == 500
    assert {summary[rel]["status"] for rel in SCENES if rel != "c.ply"} == {"skipped"}
    record_path.write_text("[" * 100_000 + "]" * 100_000)
    assert run_json(scenes, "-o", out, "--ratio", "0.1")["c.ply"]["status"] == "done"


def test_the_same_budgets_in_another_order_are_up_to_date(scenes, tmp_path):
    """They make the same outputs (one progressive run); every scene was redone, and alternating the
    two orders redid every scene each time."""
    out = tmp_path / "out"
    run_json(scenes, "-o", out, "--ratio", "0.1,0.01")
    before = outputs(out)
    summary = run_json(scenes, "-o", out, "--ratio", "0.01,0.1")
    assert {s["status"] for s in summary.values()} == {"skipped"} and outputs(out) == before
    assert [o["budget"] for o in summary["c.ply"]["outputs"]] == ["0.01", "0.1"]  # listed in the order given
    assert {s["status"] for s in run_json(scenes, "-o", out, "--ratio", "0.01,0.2").values()} == {"done"}


def test_a_record_naming_other_files_is_redone(scenes, tmp_path):
    """A record whose output entry named another file of the right size (its own output deleted)
    was taken as up to date: the scene was skipped and the summary listed the other file."""
    out = tmp_path / "out"
    run_json(scenes, "-o", out, "--ratio", "0.1")
    own = out / "c_0.1.ply"
    (out / "zz.ply").write_bytes(own.read_bytes())
    own.unlink()
    record_path = out / "c.nanogs.json"
    record = json.loads(record_path.read_text())
    record["outputs"][0]["path"] = "zz.ply"
    record_path.write_text(json.dumps(record))
    summary = run_json(scenes, "-o", out, "--ratio", "0.1")
    assert summary["c.ply"]["status"] == "done" and own.exists()


def test_a_ratio_written_apart_from_its_float_is_its_own_budget(tmp_path):
    """0.10000000000000001 keeps 3 of 20 splats and 0.1 keeps 2, but both were labelled and recorded
    as 0.1: a resumed batch skipped the scene with the other count."""
    root = tmp_path / "in"
    root.mkdir()
    random_splats_ply(root / "t.ply", 20, seed=5)
    first = run_json(root, "-o", tmp_path / "out", "--ratio", "0.1")["t.ply"]
    second = run_json(root, "-o", tmp_path / "out", "--ratio", "0.10000000000000001")["t.ply"]
    assert first["status"] == second["status"] == "done"
    assert [(Path(o["path"]).name, o["count"]) for o in second["outputs"]] == [("t_0.10000000000000001.ply", 3)]
    assert run_json(root, "-o", tmp_path / "out", "--ratio", "0.10000000000000001")["t.ply"]["status"] == "skipped"


def test_ray_task_past_its_time_limit_is_cancelled(scenes_and_a_spinner, tmp_path, monkeypatch):
    """As above with Ray tasks (a private local Ray started with the spinning scene named in its
    environment; kept last in this file, since it shuts down the shared Ray first)."""
    ray = pytest.importorskip("ray")
    (root, clean), out = scenes_and_a_spinner, tmp_path / "out"
    monkeypatch.setenv(SPIN, "spin.ply")
    if ray.is_initialized():
        ray.shutdown()
    summary = run_json(root, "-o", out, "--ratio", "0.1,0.01", "--scene-timeout", "20", "--ray", "local", code=1)
    check_spinner_timed_out(summary, clean, out, 20, "its Ray task was cancelled")


def test_failed_scenes_leave_no_folders_the_run_made(scenes, tmp_path):
    """A batch whose scenes all fail leaves no output folder it made; one whose scene fails while
    writing (a full disk, simulated) leaves no empty scene folder, while a folder that was there
    before stays."""
    manifest = tmp_path / "list.txt"
    manifest.write_text("in/missing.ply\n")
    result = run(manifest, "-o", tmp_path / "new" / "out", "--ratio", "0.1", "--devices", "cpu", "-q")
    assert result.exit_code == 1 and not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()
    result = run(manifest, "-o", tmp_path / "kept", "--ratio", "0.1", "--devices", "cpu", "-q")
    assert result.exit_code == 1 and (tmp_path / "kept").is_dir()


def test_an_output_that_is_a_scene_of_the_batch_is_refused(tmp_path):
    """An output tree that overlaps the input tree: a scene's output (or record) that is another
    scene of the batch is refused before anything runs, and that input is left as it was."""
    root = tmp_path / "b"
    root.mkdir()
    random_splats_ply(root / "a.ply", 300, seed=1)
    random_splats_ply(root / "a_0.5.ply", 100, seed=2)
    (root / "list.txt").write_text("a.ply\na_0.5.ply\n")
    before = (root / "a_0.5.ply").read_bytes()
    result = run(root / "list.txt", "-o", root, "--ratio", "0.5", "--devices", "cpu")
    assert result.exit_code == 2 and "a.ply's output" in result.stderr and "is the scene a_0.5.ply of this batch" in result.stderr
    assert (root / "a_0.5.ply").read_bytes() == before and sorted(p.name for p in root.iterdir()) == ["a.ply", "a_0.5.ply", "list.txt"]


def test_a_recursive_pattern_does_not_follow_links_to_folders(tmp_path):
    """'**' is matched by walking the tree without following links to folders: three links to '.'
    made Python's glob run for ever (and one made it list the same scene 41 times)."""
    root = tmp_path / "gl"
    (root / "sub").mkdir(parents=True)
    random_splats_ply(root / "a.ply", 50, seed=1)
    random_splats_ply(root / "sub" / "b.ply", 50, seed=2)
    for name in ("l1", "l2", "l3"):
        (root / name).symlink_to(".", target_is_directory=True)
    jobs = find_scenes(str(root / "**" / "*.ply"), tmp_path / "out", parse_budgets_for_test(), SimplifyConfig(), False)
    assert [job.relative for job in jobs] == ["a.ply", "sub/b.ply"]
    jobs = find_scenes(str(root / "sub" / "**"), tmp_path / "out", parse_budgets_for_test(), SimplifyConfig(), False)
    assert [job.relative for job in jobs] == ["b.ply"]


def parse_budgets_for_test():
    from nanogs_warp.budgets import parse_budgets

    return parse_budgets("0.5", None)
