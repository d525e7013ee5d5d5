"""simplify's outputs: no silent overwrite, -o DIR/ writes inside the folder, --sample; help text
with examples and word placeholders."""

import json
import os
import re
from pathlib import Path

import pytest
from scene_factory import (
    random_splat_arrays,
    random_splats_ply,
    write_2dgs_copy,
    write_splats_ply,
)
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.data import sample_path
from nanogs_warp.io.ply import load_ply, save_ply


def run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.ply"
    random_splats_ply(path, 400, seed=6)
    return path


def test_existing_output_needs_overwrite(scene, tmp_path):
    out = tmp_path / "out.ply"
    assert run("simplify", scene, "-o", out, "--count", "40", "--device", "cpu", "-q").exit_code == 0
    first = out.read_bytes()
    again = run("simplify", scene, "-o", out, "--count", "20", "--device", "cpu", "-q")
    assert again.exit_code == 2
    assert again.stderr.strip() == f"nanogs-warp: error: output {out} already exists; pass --overwrite (-w) to replace it"
    assert out.read_bytes() == first
    for flag in ("--overwrite", "-w"):
        replaced = run("simplify", scene, "-o", out, "--count", "20", "--device", "cpu", "-q", flag)
        assert replaced.exit_code == 0, replaced.output
        assert load_ply(out).count == 20


def test_one_existing_output_of_several_stops_before_any_work(scene, tmp_path):
    (tmp_path / "out_0.01.ply").write_bytes(b"keep me")
    result = run("simplify", scene, "-o", tmp_path / "out.ply", "--ratio", "0.1,0.01", "--device", "cpu")
    assert result.exit_code == 2 and "out_0.01.ply already exists" in result.stderr
    assert not (tmp_path / "out_0.1.ply").exists() and (tmp_path / "out_0.01.ply").read_bytes() == b"keep me"


@pytest.mark.parametrize("existing", [True, False])
def test_output_folder_receives_every_budget(scene, tmp_path, existing):
    folder = tmp_path / "lods"
    if existing:
        folder.mkdir()
    target = folder if existing else f"{folder}/"
    result = run("simplify", scene, "-o", target, "--ratio", "0.1,0.01", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in folder.iterdir()) == ["scene_0.01.ply", "scene_0.1.ply"]
    assert not list(tmp_path.glob("lods_*"))  # inside the folder, not beside it
    assert [o["path"] for o in json.loads(result.stdout)["outputs"]] == [str(folder / "scene_0.1.ply"), str(folder / "scene_0.01.ply")]
    single = run("simplify", scene, "-o", f"{folder}/", "--count", "7", "--device", "cpu", "-q")
    assert single.exit_code == 0 and load_ply(folder / "scene_7.ply").count == 7


def test_output_folder_whose_parent_is_missing(scene, tmp_path):
    result = run("simplify", scene, "-o", f"{tmp_path}/no/lods/", "--ratio", "0.1", "--device", "cpu")
    assert result.exit_code == 2 and "cannot be created" in result.stderr
    assert not (tmp_path / "no").exists()


def test_sample_input(tmp_path):
    assert sample_path().is_file() and load_ply(sample_path()).count == 20_000
    result = run("simplify", "--sample", "-o", tmp_path / "plant.ply", "--count", "2000,200", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["input"] == str(sample_path().resolve()) and summary["input_count"] == 20_000
    assert load_ply(tmp_path / "plant_200.ply").count == 200


@pytest.mark.parametrize(
    "args, message",
    [(["--sample", "SCENE"], "not both"), ([], "give an input .ply file"), (["--sample", "--no-output"], None)],
)
def test_input_or_sample(tmp_path, scene, args, message):
    args = [scene if a == "SCENE" else a for a in args]
    if "--no-output" in args:
        result = run("simplify", "--sample", "--ratio", "0.1")
        assert result.exit_code == 2 and "give an output path" in result.stderr
        return
    result = run("simplify", *args, "-o", tmp_path / "o.ply", "--ratio", "0.1")
    assert result.exit_code == 2 and message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("command", ["simplify", "eval", "batch", "info"])
def test_help_has_examples_and_word_placeholders(command):
    result = run(command, "--help")
    assert result.exit_code == 0
    text = result.stdout
    assert "Examples:" in text and len(re.findall(r"^\s+nanogs-warp " + command, text, flags=re.MULTILINE)) >= 2
    assert not re.search(r"<(str|int|float|path)>|\{input\}|TEXT|INTEGER|FLOAT", text), text


def test_help_describes_the_default_cost():
    text = run("simplify", "--help").stdout
    lambda_geo = text[text.index("--lambda-geo") : text.index("--lambda-app")]
    assert "runnalls" in lambda_geo and "default" in lambda_geo


def test_sh_degree_of_the_outputs(tmp_path):
    """--sh-degree drops each output's higher bands after the merge and the size fit: the outputs
    are the plain run's with the PLY's f_rest block cut to that degree, --json echoes it, the
    input's own degree changes nothing, and batch writes the same bytes as simplify."""
    import typer
    from plyfile import PlyData

    from nanogs_warp.cli.batch import batch_command
    from nanogs_warp.cli.errors import user_errors

    scenes = tmp_path / "in"
    scenes.mkdir()
    scene = scenes / "s.ply"
    random_splats_ply(scene, 2000, sh_degree=3, seed=8)
    budgets = ("--ratio", "0.1,0.005")
    result = run("simplify", scene, "-o", tmp_path / "one.ply", *budgets, "--sh-degree", "1", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["settings"]["sh_degree"] == 1
    assert run("simplify", scene, "-o", tmp_path / "all.ply", *budgets, "--sh-degree", "3", "--device", "cpu", "-q").exit_code == 0
    assert run("simplify", scene, "-o", tmp_path / "plain.ply", *budgets, "--device", "cpu", "-q").exit_code == 0
    for budget, count in (("0.1", 200), ("0.005", 10)):
        names = [p.name for p in PlyData.read(str(tmp_path / f"one_{budget}.ply"))["vertex"].properties]
        assert [n for n in names if n.startswith("f_rest_")] == [f"f_rest_{i}" for i in range(9)]
        assert load_ply(tmp_path / f"one_{budget}.ply").count == count
        assert (tmp_path / f"all_{budget}.ply").read_bytes() == (tmp_path / f"plain_{budget}.ply").read_bytes()
        save_ply(load_ply(tmp_path / f"plain_{budget}.ply").with_sh_degree(1), tmp_path / "cut.ply")
        assert (tmp_path / "cut.ply").read_bytes() == (tmp_path / f"one_{budget}.ply").read_bytes()
    assert run("simplify", scene, "-o", tmp_path / "zero.ply", *budgets, "--sh-degree", "0", "--device", "cpu", "-q").exit_code == 0
    batch = typer.Typer(pretty_exceptions_enable=False)
    batch.callback()(lambda: None)
    batch.command("batch")(user_errors(batch_command))
    result = CliRunner().invoke(batch, ["batch", str(scenes), "-o", str(tmp_path / "out"), *budgets, "--sh-degree", "0", "--devices", "cpu", "-q"])
    assert result.exit_code == 0, result.output
    for budget in ("0.1", "0.005"):
        assert (tmp_path / "out" / f"s_{budget}.ply").read_bytes() == (tmp_path / f"zero_{budget}.ply").read_bytes()
    assert json.loads((tmp_path / "out" / "s.nanogs.json").read_text())["options"]["sh_degree"] == 0
    for command in (["simplify", scene, "-o", tmp_path / "bad.ply"], ["batch", scenes, "-o", tmp_path / "bad"]):
        result = run(*command, "--ratio", "0.1", "--sh-degree", "4", "--device" if command[0] == "simplify" else "--devices", "cpu")
        assert result.exit_code == 2 and result.stderr.strip() == "nanogs-warp: error: --sh-degree must be 0, 1, 2 or 3, got 4"
    assert not (tmp_path / "bad.ply").exists() and not (tmp_path / "bad").exists()


def test_outputs_are_listed_in_the_order_the_budgets_were_given(scene, tmp_path):
    """The JSON and the lines list the budgets as given, as batch and the Python API do (they were
    listed as reached, largest first)."""
    result = run("simplify", scene, "-o", tmp_path / "o.ply", "--ratio", "0.01,0.5,0.1", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert [o["budget"] for o in summary["outputs"]] == ["0.01", "0.5", "0.1"]
    assert [o["count"] for o in summary["outputs"]] == [4, 200, 40]
    lines = run("simplify", scene, "-o", tmp_path / "o.ply", "--ratio", "0.01,0.5", "--device", "cpu", "-w").stdout.splitlines()
    assert "(budget 0.01" in lines[0] and "(budget 0.5" in lines[1]


def test_a_set_of_files_gets_its_own_folder(scene, tmp_path):
    """A lod-meta.json set and an unbundled SOG are folders of files: theirs is made as -o DIR/'s
    is (the README's `-o web/lod-meta.json` failed in a fresh folder); a plain file's is not."""
    assert run("simplify", scene, "-o", tmp_path / "web" / "lod-meta.json", "--ratio", "0.5,0.1", "--device", "cpu", "-q").exit_code == 0
    assert (tmp_path / "web" / "lod-meta.json").is_file() and (tmp_path / "web" / "1_0" / "meta.json").is_file()
    assert run("simplify", scene, "-o", tmp_path / "ub" / "meta.json", "--ratio", "0.5", "--device", "cpu", "-q").exit_code == 0
    assert (tmp_path / "ub" / "quats.webp").is_file()
    missing = run("simplify", scene, "-o", tmp_path / "x" / "y" / "lod-meta.json", "--ratio", "0.5", "--device", "cpu")
    assert missing.exit_code == 2 and "cannot be created" in missing.stderr and not (tmp_path / "x").exists()
    plain = run("simplify", scene, "-o", tmp_path / "nd" / "s.ply", "--ratio", "0.5", "--device", "cpu")
    assert plain.exit_code == 2 and "does not exist" in plain.stderr and not (tmp_path / "nd").exists()


def test_an_output_where_no_file_can_go_says_why(scene, tmp_path):
    """A file where the output's folder should be was said not to exist; a FIFO at the output
    asked for -w, which then refused it as no regular file."""
    (tmp_path / "file").write_text("x")
    os.mkfifo(tmp_path / "fifo.ply")
    for output, why in ((tmp_path / "file" / "o.ply", f"output directory {tmp_path / 'file'} is not a folder"),
                        (f"{tmp_path / 'file' / 'new'}/", f"cannot be created: {tmp_path / 'file'} is not a folder"),
                        (tmp_path / "fifo.ply", "exists and is not a regular file")):  # fmt: skip
        result = run("simplify", scene, "-o", output, "--ratio", "0.5", "--device", "cpu")
        assert result.exit_code == 2 and why in result.stderr, result.stderr


def test_a_lod_set_into_a_new_folder(scene, tmp_path):
    """--format lod -o NEW/ was refused as a file not named lod-meta.json: only a folder that
    already existed was taken for one, where every other output takes -o NEW/ as a folder to make."""
    result = run("simplify", scene, "-o", f"{tmp_path / 'new'}/", "--format", "lod", "--ratio", "0.5,0.1", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    assert {Path(o["path"]) for o in json.loads(result.stdout)["outputs"]} == {tmp_path / "new" / "lod-meta.json"}
    assert (tmp_path / "new" / "0_0" / "meta.json").is_file() and (tmp_path / "new" / "1_0" / "meta.json").is_file()
    named = run("simplify", scene, "-o", tmp_path / "other", "--format", "lod", "--ratio", "0.5", "--device", "cpu")
    assert named.exit_code == 2 and "name the output lod-meta.json or give a folder" in named.stderr


def test_a_lod_set_named_in_capitals_and_refine_size_alone(scene, tmp_path):
    """-o LOD-META.JSON wrote lod-meta.json but reported LOD-META.JSON, which no reader found; and
    --refine-size without --refine was silently ignored (it implies --refine, as --refine-steps does)."""
    result = run("simplify", scene, "-o", tmp_path / "LOD-META.JSON", "--ratio", "0.5,0.1", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    assert {Path(o["path"]).name for o in json.loads(result.stdout)["outputs"]} == {"lod-meta.json"}
    assert (tmp_path / "lod-meta.json").is_file()
    result = run("simplify", scene, "-o", tmp_path / "r.ply", "--ratio", "0.1", "--refine-size", "64", "--refine-steps", "2",
                 "--device", "cpu", "--json")  # fmt: skip
    assert json.loads(result.stdout)["outputs"][0]["refine"]["steps"] == 2
    result = run("simplify", scene, "-o", tmp_path / "r2.ply", "--ratio", "0.1", "--refine-size", "64", "--device", "cpu", "--json")
    assert "refine" in json.loads(result.stdout)["outputs"][0]


def test_several_budgets_to_a_name_without_an_extension_take_the_formats(tmp_path):
    """-o x --format sog with two budgets wrote SOG archives named x_0.5.ply and x_0.1.ply."""
    scene = tmp_path / "scene.ply"
    random_splats_ply(scene, 200, seed=3)
    result = run("simplify", scene, "-o", tmp_path / "x", "--format", "sog", "--ratio", "0.5,0.1", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply", "x_0.1.sog", "x_0.5.sog"]


def test_a_2dgs_input_simplifies_as_its_flat_3dgs_twin(tmp_path):
    """A PLY of 2DGS surfels (no scale_2) gives the outputs, byte for byte, of the same splats with
    scale_2 at the flat log-scale: 3DGS files; the command says once how it read them."""
    arrays = random_splat_arrays(600, sh_degree=1, seed=11)
    arrays["log_scales"][:, 2] = -30.0  # ply_header.FLAT_LOG_SCALE
    write_splats_ply(tmp_path / "flat.ply", arrays)
    write_2dgs_copy(tmp_path / "flat.ply", tmp_path / "surfels.ply")
    budgets = ("--ratio", "0.1,0.01", "--device", "cpu")
    flat = run("simplify", tmp_path / "flat.ply", "-o", f"{tmp_path}/a/", *budgets)
    surfels = run("simplify", tmp_path / "surfels.ply", "-o", f"{tmp_path}/b/", *budgets)
    assert flat.exit_code == 0 and surfels.exit_code == 0, surfels.output
    note = ("surfels.ply: 2DGS surfels (scale_0 and scale_1, no scale_2) read as flat 3DGS splats (log-scale -30 on "
            "the third axis), and written as 3DGS")  # fmt: skip
    assert surfels.stderr.count(note) == 1 and "2DGS" not in flat.stderr
    for budget in ("0.1", "0.01"):
        assert (tmp_path / "b" / f"surfels_{budget}.ply").read_bytes() == (tmp_path / "a" / f"flat_{budget}.ply").read_bytes()
