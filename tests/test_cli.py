"""The command line: budgets and outputs, summaries, and one clear line for every bad input."""

import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.io.ply import load_ply

SAMPLE = Path(str(resources.files("nanogs_warp.data") / "plant_crop.ply"))
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.ply"
    random_splats_ply(path, 600, sh_degree=1, seed=1)
    return path


def test_several_budgets_in_one_run(scene, tmp_path):
    result = run("simplify", scene, "-o", tmp_path / "out.ply", "--ratio", "0.1,0.01", "--device", "cpu", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert [(o["budget"], o["count"]) for o in summary["outputs"]] == [("0.1", 60), ("0.01", 6)]
    assert load_ply(tmp_path / "out_0.1.ply").count == 60
    assert load_ply(tmp_path / "out_0.01.ply").count == 6
    assert not (tmp_path / "out.ply").exists()


def test_count_budget_and_text_summary(scene, tmp_path):
    out = tmp_path / "small.ply"
    result = run("simplify", scene, "-o", out, "--count", "50", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "50 splats" in result.stdout
    assert load_ply(out).count == 50


def test_same_input_same_bytes(scene, tmp_path):
    for name in ("a.ply", "b.ply"):
        assert run("simplify", scene, "-o", tmp_path / name, "--ratio", "0.05", "--device", "cpu", "-q").exit_code == 0
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_info(scene):
    result = run("info", scene, "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["count"] == 600
    text = run("info", scene)
    assert text.exit_code == 0 and "600" in text.stdout


def digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def nan_scene(tmp_path):
    path = tmp_path / "nan.ply"
    random_splats_ply(path, 100, seed=2)
    from plyfile import PlyData

    ply = PlyData.read(str(path), mmap=False)
    ply["vertex"].data["opacity"][3] = np.nan
    ply.write(str(path))
    return path


BAD = {
    "missing file": lambda t, s: ["simplify", t / "nope.ply", "-o", t / "o.ply", "--ratio", "0.1"],
    "not a ply": lambda t, s: ["simplify", (t / "x.ply").write_text("hello") and t / "x.ply", "-o", t / "o.ply", "--ratio", "0.1"],
    "ratio zero": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0"],
    "ratio above one": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "1.5"],
    "ratio not a number": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "abc"],
    "count too large": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--count", "601"],
    "count zero": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--count", "0"],
    "both budgets": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--count", "5", "--ratio", "0.1"],
    "no budget": lambda t, s: ["simplify", s, "-o", t / "o.ply"],
    "output is input": lambda t, s: ["simplify", s, "-o", s, "--ratio", "0.1"],
    "missing output dir": lambda t, s: ["simplify", s, "-o", t / "no" / "o.ply", "--ratio", "0.1"],
    "bad k": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0.1", "--k", "0"],
    "bad cost": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0.1", "--cost", "nope"],
    "bad device": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0.1", "--device", "tpu"],
    "nan values": lambda t, s: ["simplify", nan_scene(t), "-o", t / "o.ply", "--ratio", "0.1"],
    "pass fraction that would take hours": lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0.1", "--pass-fraction", "1e-9"],
    "symbolic link loop": lambda t, s: ["simplify", link_loop(t), "-o", t / "o.ply", "--ratio", "0.1"],
}


def link_loop(folder: Path) -> Path:
    """a.ply -> b.ply -> a.ply"""
    (folder / "a.ply").symlink_to(folder / "b.ply")
    (folder / "b.ply").symlink_to(folder / "a.ply")
    return folder / "a.ply"

if wp.get_cuda_device_count() == 0:
    BAD["cuda without gpu"] = lambda t, s: ["simplify", s, "-o", t / "o.ply", "--ratio", "0.1", "--device", "cuda"]


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_one_line_exit_2(case, scene, tmp_path):
    before = digest(scene)
    result = run(*BAD[case](tmp_path, scene))
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nanogs-warp: error: "), result.stderr
    assert "Traceback" not in result.output
    assert not list(tmp_path.glob("o*.ply")) and not (tmp_path / "no").exists()
    assert digest(scene) == before


def test_numpy_warnings_stay_off_stderr(scene, tmp_path):
    """A little-endian body under a big-endian header (garbage values, some NaN of every kind):
    in a real process, where Python shows warnings, stderr holds the one error line and nothing
    else; NANOGS_DEBUG=1 lets the warnings through."""
    import sys

    bad = tmp_path / "mislabelled.ply"
    bad.write_bytes(scene.read_bytes().replace(b"binary_little_endian", b"binary_big_endian", 1))
    command = [sys.executable, "-m", "nanogs_warp", "simplify", bad, "-o", tmp_path / "o.ply", "--ratio", "0.1",
               "--device", "cpu"]  # fmt: skip
    environment = {k: v for k, v in os.environ.items() if k != "NANOGS_DEBUG"}
    done = subprocess.run(command, capture_output=True, text=True, env=environment)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("nanogs-warp: error: "), done.stderr
    assert not list(tmp_path.glob("o*.ply"))


def test_commands_silence_warnings_unless_debugging(scene):
    """Whatever warns inside a command (here a patched step: a Python warning and a numpy overflow)
    stays off stderr; NANOGS_DEBUG=1 lets it through."""
    import sys

    code = (
        "import sys, warnings, numpy as np, nanogs_warp.io.scene_info as info\n"
        "from nanogs_warp.cli.app import app\n"
        "real = info.scene_info\n"
        "def noisy(path):\n"
        "    warnings.warn('a library warning')\n"
        "    np.float32(3e38) * np.float32(10)\n"
        "    return real(path)\n"
        "info.scene_info = noisy\n"
        "app(['info', sys.argv[1]])\n"
    )
    environment = {k: v for k, v in os.environ.items() if k != "NANOGS_DEBUG"}
    quiet = subprocess.run([sys.executable, "-c", code, scene], capture_output=True, text=True, env=environment)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    debug = subprocess.run([sys.executable, "-c", code, scene], capture_output=True, text=True,
                           env={**environment, "NANOGS_DEBUG": "1"})  # fmt: skip
    assert debug.returncode == 0
    assert "a library warning" in debug.stderr and "overflow" in debug.stderr


def test_unwritable_output_directory(scene, tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root can write into read-only directories")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    result = run("simplify", scene, "-o", locked / "o.ply", "--ratio", "0.1")
    assert result.exit_code == 2 and "not writable" in result.stderr


def test_drop_invalid(tmp_path):
    out = tmp_path / "o.ply"
    result = run("simplify", nan_scene(tmp_path), "-o", out, "--count", "10", "--drop-invalid", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output
    assert load_ply(out).count == 10


def test_installed_command_on_the_shipped_sample(tmp_path):
    """The README's first command, through the installed entry point."""
    exe = shutil.which("nanogs-warp") or pytest.skip("nanogs-warp is not on PATH")
    version = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True)
    assert version.stdout.startswith("nanogs-warp ")
    out = tmp_path / "plant.ply"
    done = subprocess.run(
        [exe, "simplify", SAMPLE, "-o", out, "--ratio", "0.1,0.01,0.001", "--device", "cpu", "--json"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    n = load_ply(SAMPLE).count
    for ratio in (0.1, 0.01, 0.001):
        assert load_ply(tmp_path / f"plant_{ratio:g}.ply").count == max(1, math.ceil(ratio * n))
    assert json.loads(done.stdout)["input_count"] == n


def test_preset_paper_is_the_papers_flags_and_flags_override_it(scene, tmp_path):
    flags = ["--operator", "mpmm", "--cost", "idiv", "--prune-opacity", "0.1", "--pass-fraction", "0.5", "--median-cost-factor", "0",
             "--no-fit-size", "--no-fit-geometry", "--no-fit-colour", "--k", "16"]  # fmt: skip
    common = ["--ratio", "0.1", "--device", "cpu", "-q"]
    assert run("simplify", scene, "-o", tmp_path / "flags.ply", *common, *flags).exit_code == 0
    assert run("simplify", scene, "-o", tmp_path / "preset.ply", *common, "--preset", "paper").exit_code == 0
    assert run("simplify", scene, "-o", tmp_path / "k8.ply", *common, "--preset", "paper", "--k", "8").exit_code == 0
    assert run("simplify", scene, "-o", tmp_path / "k8flags.ply", *common, *flags[:-1], "8").exit_code == 0
    assert (tmp_path / "flags.ply").read_bytes() == (tmp_path / "preset.ply").read_bytes()
    assert (tmp_path / "k8.ply").read_bytes() == (tmp_path / "k8flags.ply").read_bytes()
    assert (tmp_path / "k8.ply").read_bytes() != (tmp_path / "preset.ply").read_bytes()


def test_unknown_preset_and_field_cost_with_area_are_input_errors(scene, tmp_path):
    for extra in (["--preset", "nope"], ["--cost", "field", "--operator", "area"]):
        result = run("simplify", scene, "-o", tmp_path / "x.ply", "--ratio", "0.1", "--device", "cpu", *extra)
        assert result.exit_code == 2, result.output
        assert not (tmp_path / "x.ply").exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_a_pipe_named_like_a_scene_is_refused_at_once(scene, tmp_path):
    """A FIFO (or a device) would block the open or the read for ever: every command refuses it."""
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    cameras = tmp_path / "cameras.json"
    os.mkfifo(cameras)
    for args in (("info", fifo), ("simplify", fifo, "-o", tmp_path / "o.ply", "--ratio", "0.5", "--device", "cpu"),
                 ("eval", fifo, scene, "--device", "cpu"), ("eval", scene, scene, "--cameras", cameras, "--device", "cpu")):  # fmt: skip
        result = run(*args)
        assert result.exit_code == 2, (args, result.output)
        assert "not a regular file" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "o.ply").exists()
    if os.path.exists("/dev/zero"):
        result = run("info", "/dev/zero")
        assert result.exit_code == 2 and "zero: not a regular file" in result.output


def test_an_empty_output_is_refused(scene, tmp_path, monkeypatch):
    """-o "" used to write <input stem>_<budget>.ply into the current directory."""
    monkeypatch.chdir(tmp_path)
    result = run("simplify", scene, "-o", "", "--ratio", "0.5,0.1", "--device", "cpu")
    assert result.exit_code == 2 and "give an output path with -o/--output" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_overwrite_never_replaces_what_is_not_a_regular_file(scene, tmp_path):
    """-o /dev/null -w, run as root, would have replaced the device node with a regular file."""
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    link = tmp_path / "link.ply"
    link.symlink_to(fifo)
    for target in (fifo, link):
        result = run("simplify", scene, "-o", target, "--ratio", "0.5", "--device", "cpu", "-w")
        assert result.exit_code == 2 and "exists and is not a regular file" in result.output
    assert fifo.is_fifo() and link.is_symlink()


def test_output_names_too_long_to_write_are_refused_first(scene, tmp_path):
    """A name is written beside a temporary with 26 more bytes: 229 bytes at most (longer names
    failed late, and names beyond 255 bytes were an internal error)."""
    from nanogs_warp.io.ply_write import TEMPORARY_EXTRA_BYTES

    assert TEMPORARY_EXTRA_BYTES == 26
    for length in (230, 300):
        result = run("simplify", scene, "-o", tmp_path / ("x" * (length - 4) + ".ply"), "--ratio", "0.5", "--device", "cpu")
        assert result.exit_code == 2 and f"is {length} bytes long; at most 229 can be written" in result.output
    assert run("simplify", scene, "-o", tmp_path / ("y" * 225 + ".ply"), "--ratio", "0.5", "--device", "cpu", "-q").exit_code == 0


def _failing_write(monkeypatch, module: str, fail_on: int):
    """Makes ``module``'s ``atomic_write`` fail as a full disk does, at its ``fail_on``-th call."""
    from nanogs_warp.errors import InputError
    from nanogs_warp.io import ply_write

    calls = []

    def write(path, write, overwrite=True, outputs=None):
        calls.append(path)
        if len(calls) == fail_on:
            raise InputError(f"{path.name}: cannot write the file: No space left on device")
        return ply_write.atomic_write(path, write, overwrite, outputs)

    monkeypatch.setattr(f"{module}.atomic_write", write)
    return calls


@pytest.mark.parametrize("output", ["out.ply", "out.sog", "lods/", "lod-meta.json"])
def test_a_run_that_fails_part_way_leaves_no_output(scene, tmp_path, monkeypatch, output):
    """Each file is written under a temporary name; the run's files appear together once the last
    is written. A write that fails at the second file (a full disk) leaves none of them, no
    temporary file and no folder the run made: one line, exit 2."""
    module = "nanogs_warp.io.ply" if output.endswith(("ply", "/")) else "nanogs_warp.io"
    calls = _failing_write(monkeypatch, module, fail_on=2)
    result = run("simplify", scene, "-o", tmp_path / output, "--ratio", "0.1,0.01", "--device", "cpu")
    assert result.exit_code == 2 and "No space left on device" in result.stderr
    assert len(calls) == 2 and sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]
    monkeypatch.undo()
    result = run("simplify", scene, "-o", tmp_path / output, "--ratio", "0.1,0.01", "--device", "cpu", "-q")
    assert result.exit_code == 0, result.output


def test_memory_that_runs_out_is_one_line_and_no_output(scene, tmp_path, monkeypatch):
    """Warp's failed allocation (a scene too large for the device) names the device and the size,
    not an internal error; the run leaves nothing behind."""
    allocator = wp.get_device("cpu").get_allocator()
    allocate, calls = allocator.allocate, []

    def failing(size_in_bytes):  # the 30th allocation asks for 4 EiB: Warp's own error, as a full host gives it
        calls.append(size_in_bytes)
        return allocate(1 << 62 if len(calls) == 30 else size_in_bytes)

    monkeypatch.setattr(allocator, "allocate", failing)
    result = run("simplify", scene, "-o", tmp_path / "out.ply", "--ratio", "0.1,0.01", "--device", "cpu")
    assert len(calls) >= 30 and result.exit_code == 1, result.output
    assert result.stderr == f"nanogs-warp: error: out of memory on cpu: could not allocate {1 << 62:,} bytes\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_out_of_memory_lines():
    from nanogs_warp.errors import out_of_memory

    assert out_of_memory(MemoryError()) == "out of memory"
    assert out_of_memory(RuntimeError("Failed to allocate 2048 bytes on device 'cuda:1'")) == (
        "out of memory on cuda:1: could not allocate 2,048 bytes")  # fmt: skip
    assert out_of_memory(RuntimeError("Failed to allocate 5 bytes with CudaManagedAllocator on device 'cuda:0'; x")) == (
        "out of memory on cuda:0: could not allocate 5 bytes")  # fmt: skip
    assert out_of_memory(RuntimeError("Failed to load the shared library")) is None
    assert out_of_memory(ValueError("Failed to allocate 5 bytes on device 'cpu'")) is None


def test_what_the_machine_lacks_is_said_in_words(scene, tmp_path):
    """Limits of the shell and the machine were 'internal error: ...' lines (the eighth hostile round)."""
    import errno

    from nanogs_warp.cli.errors import _environment_error

    assert _environment_error(OSError(errno.EMFILE, "Too many open files")).startswith("too many open files")
    assert _environment_error(FileNotFoundError(errno.ENOENT, "No usable temporary directory found in ['/tmp']")) == (
        "no temporary folder can be written: set TMPDIR to a writable folder")  # fmt: skip
    try:
        raise RuntimeError("Failed to load the shared library 'warp.so'") from OSError("failed to map segment")
    except RuntimeError as e:
        assert _environment_error(e).startswith("cannot start Warp: Failed to load the shared library 'warp.so': failed to map segment")
    assert _environment_error(RuntimeError("can't start new thread")).startswith("cannot start a thread: too little memory")
    assert _environment_error(ValueError("x")) is None
    gone = tmp_path / "gone"
    gone.mkdir()
    code = f"import os; os.chdir({str(gone)!r}); os.rmdir({str(gone)!r}); from nanogs_warp.cli.entry import main; main()"
    done = subprocess.run([sys.executable, "-c", code, "simplify", str(scene), "-o", "b.ply", "--ratio", "0.1", "--device", "cpu"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1
    assert done.stderr == "nanogs-warp: error: the working folder no longer exists: run the command from one that does\n"


def test_only_the_notices_that_no_gpu_is_there_are_dropped_from_warps_start():
    from nanogs_warp.device import start_up_messages

    output = (
        "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be available.\n\n"
        "Warp CUDA error 100: no CUDA-capable device is detected (in function init_cuda_driver, cuda_util.cpp:333)\n"
        "Warp CUDA error 2: out of memory (in function alloc_device, warp.cu:1)\n  \n"
        "Warp: something else\n"
    )
    assert start_up_messages(output) == ["Warp CUDA error 2: out of memory (in function alloc_device, warp.cu:1)", "Warp: something else"]


def test_warp_starts_where_no_temporary_file_can_be_made():
    """In a fresh process (Warp starts once a process): its output is then not captured."""
    code = (
        "import tempfile\n"
        "def no_temporary_folder(*args, **kwargs):\n"
        "    raise FileNotFoundError(2, \"No usable temporary directory found in ['/tmp']\")\n"
        "tempfile.TemporaryFile = no_temporary_folder\n"
        "from nanogs_warp.device import init_warp\n"
        "init_warp()\n"
        "from warp._src.context import runtime\n"
        "print(runtime is not None)\n"
    )  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout == "True\n", result.stderr


def test_without_overwrite_a_file_that_appears_meanwhile_is_kept(scene, tmp_path, monkeypatch):
    """The check that an output does not exist comes before the work; a file put there meanwhile
    (another run writing the same name) used to be replaced by the final rename. Now the write fails
    in one line and the other file stays, with no temporary file left."""
    from nanogs_warp.io import ply_write
    from nanogs_warp.io.ply import save_ply

    out = tmp_path / "o.ply"
    original = ply_write.atomic_write

    def first_another_run(path, write, overwrite=True, outputs=None):
        path.write_bytes(b"the other run's output")
        return original(path, write, overwrite, outputs)

    monkeypatch.setattr("nanogs_warp.io.ply.atomic_write", first_another_run)
    result = run("simplify", scene, "-o", out, "--ratio", "0.5", "--device", "cpu")
    assert result.exit_code == 2 and "already exists; pass --overwrite (-w)" in result.output
    assert out.read_bytes() == b"the other run's output" and sorted(p.name for p in tmp_path.iterdir()) == ["o.ply", "scene.ply"]
    assert run("simplify", scene, "-o", out, "--ratio", "0.5", "--device", "cpu", "-w").exit_code == 0
    assert load_ply(out).count == 300
    save_ply(load_ply(scene), out, overwrite=True)  # the library's default replaces, as before


@pytest.mark.parametrize(
    "args, message",
    [
        (["eval", "a.ply"], "Missing argument 'TEST'"),
        (["simplify", "a.ply", "--bogus"], "No such option: --bogus"),
        (["eval", "a.ply", "b.ply", "--views", "many"], "'many' is not a valid int"),
        (["frobnicate"], "No such command 'frobnicate'"),
        (["simplify", "a.ply", "-o"], "Option '-o' requires an argument"),
    ],
)
def test_a_command_line_the_parser_refuses_is_one_line(args, message):
    result = run(*args)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nanogs-warp: error: ") and message in lines[0], result.stderr
    command = args[0] if args[0] != "frobnicate" else None
    assert lines[0].endswith(f"(see '{' '.join(filter(None, ['nanogs-warp', command]))} -h')"), lines[0]


def test_errors_about_names_and_json_stay_one_line(scene, tmp_path):
    """A name longer than the file system takes, a newline in a name, a NUL in a SOG's image name
    and a JSON integer too long to read: one line each, exit 2 (they were internal errors, exit 1,
    or two lines); a value of thousands of characters is shown by its ends."""
    import json as json_module

    long_name = tmp_path / ("a" * 300 + ".ply")
    result = run("info", long_name)
    assert result.exit_code == 2 and "File name too long" in result.stderr and result.stderr.count("\n") == 1
    newline = tmp_path / "bad\nname.ply"
    newline.write_bytes(b"garbage")
    result = run("info", newline)
    assert result.exit_code == 2 and "bad\\nname.ply: not a PLY file" in result.stderr and result.stderr.count("\n") == 1
    (tmp_path / "huge.json").write_text('[{"path": "x.ply", "ratio": ' + "9" * 5000 + "}]")
    result = run("batch", tmp_path / "huge.json", "-o", tmp_path / "out", "--ratio", "0.1", "--devices", "cpu")
    assert result.exit_code == 2 and "huge.json: not valid JSON" in result.stderr
    result = run("simplify", scene, "-o", tmp_path / "o.ply", "--ratio", "x" * 5000, "--device", "cpu")
    line = result.stderr.strip()  # a value of thousands of characters is shown by its ends
    assert result.exit_code == 2 and result.stderr.count("\n") == 1 and len(line) < 1100
    assert line.startswith("nanogs-warp: error: --ratio 'xxx") and "characters ...]" in line
    result = run("simplify", scene, "-o", tmp_path / "o.ply", "--k", "x" * 5000 + "\n", "--device", "cpu")
    assert result.exit_code == 2 and result.stderr.count("\n") == 1 and len(result.stderr) < 1200  # the parser's own errors too
    (tmp_path / "cams.json").write_text('[{"width": ' + "9" * 5000 + "}]")
    result = run("eval", scene, scene, "--cameras", tmp_path / "cams.json", "--device", "cpu")
    assert result.exit_code == 2 and "is not JSON" in result.stderr
    assert run("simplify", scene, "-o", tmp_path / "s" / "meta.json", "--ratio", "0.5", "--device", "cpu", "-q").exit_code == 0
    meta = json_module.loads((tmp_path / "s" / "meta.json").read_text())
    meta["means"]["files"][0] = "a\u0000b"
    (tmp_path / "s" / "meta.json").write_text(json_module.dumps(meta))
    result = run("simplify", tmp_path / "s" / "meta.json", "-o", tmp_path / "o.ply", "--ratio", "0.5", "--device", "cpu")
    assert result.exit_code == 2 and "is not a plain file name" in result.stderr and result.stderr.count("\n") == 1


def test_output_that_cannot_be_written_is_one_line_and_exit_code_2(scene, tmp_path):
    """Started with stdout closed (>&-), a command with something to print says that it cannot and
    exits 2, its outputs in place (it exited 0, the printout lost, and a traceback before that); one
    that prints nothing (-q) exits 0. With stdout on a full disk, one line and exit 2."""
    command = [sys.executable, "-m", "nanogs_warp", "info", str(scene)]
    closed = subprocess.run(["bash", "-c", '"$@" >&-', "_", *command], capture_output=True, text=True, timeout=120)
    assert closed.returncode == 2 and closed.stderr == "nanogs-warp: error: cannot write the command's output: standard output is closed\n"
    out = tmp_path / "o.ply"
    simplify = [sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out), "--ratio", "0.5", "--device", "cpu"]
    summary = subprocess.run(["bash", "-c", '"$@" >&-', "_", *simplify, "--json"], capture_output=True, text=True, timeout=300)
    assert summary.returncode == 2 and summary.stderr.count("\n") == 1 and out.exists()
    quiet = subprocess.run(["bash", "-c", '"$@" >&-', "_", *simplify, "-w", "-q"], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0 and quiet.stderr == ""
    if os.path.exists("/dev/full"):
        with open("/dev/full", "w") as full:
            result = subprocess.run(command, stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
        assert result.returncode == 2 and result.stderr.strip() == "nanogs-warp: error: cannot write the command's output: No space left on device"



@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("args", [["--help"], ["--version"], ["simplify", "--help"], ["info", "-h"]])
def test_help_to_a_full_disk_is_one_line(args):
    """Help and the version are printed before any command runs: a full disk was a traceback, exit 1."""
    with open("/dev/full", "w") as full:
        result = subprocess.run([sys.executable, "-m", "nanogs_warp", *args], stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert result.returncode == 2 and result.stderr == "nanogs-warp: error: cannot write the command's output: No space left on device\n"


def test_a_command_started_with_every_standard_stream_closed_reads_its_input(scene, tmp_path):
    """<&- >&- 2>&-: the input file was opened as descriptor 2, which Warp's start then pointed at a
    file of its own and back, so the read found "the file is empty" (exit 2, no output)."""
    out = tmp_path / "o.ply"
    command = [sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out), "--ratio", "0.5", "--device", "cpu", "-q"]
    closed = subprocess.run(["bash", "-c", '"$@" <&- >&- 2>&-', "_", *command], capture_output=True, text=True, timeout=300)
    assert closed.returncode == 0 and out.exists()
    # the race, made certain: the first file opened after the console script's start is not on 0-2
    probe = ("import sys\nfrom nanogs_warp.cli.entry import _open_standard_descriptors\n_open_standard_descriptors()\n"
             "f = open(sys.argv[1], 'rb')\nopen(sys.argv[2], 'w').write(str(f.fileno()))")  # fmt: skip
    fd_file = tmp_path / "fd.txt"
    subprocess.run(["bash", "-c", '"$@" <&- >&- 2>&-', "_", sys.executable, "-c", probe, str(scene), str(fd_file)], timeout=120)
    assert int(fd_file.read_text()) >= 3

@pytest.mark.parametrize("value, on", [("", False), ("0", False), ("1", True), ("yes", True)])
def test_debugging_is_off_for_zero(monkeypatch, value, on):
    from nanogs_warp.errors import debugging

    monkeypatch.setenv("NANOGS_DEBUG", value)
    assert debugging() is on


def test_an_output_that_is_a_loop_of_symbolic_links_is_one_line(scene, tmp_path):
    """-o naming a loop of links was an internal error (pathlib's RuntimeError, exit 1)."""
    (tmp_path / "l1.ply").symlink_to("l2.ply")
    (tmp_path / "l2.ply").symlink_to("l1.ply")
    for output in ("l1.ply", "l1.ply/", "l1.ply/lod-meta.json"):
        result = run("simplify", scene, "-o", f"{tmp_path}/{output}", "--ratio", "0.5", "--device", "cpu")
        assert result.exit_code == 2 and "too many levels of symbolic links" in result.stderr, result.stderr
        assert result.stderr.count("\n") == 1
