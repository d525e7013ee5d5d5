"""``batch --mps``: the GPU workers under CUDA MPS, with the daemon's start and stop checked through a
stand-in ``nvidia-cuda-mps-control`` (no GPU and no driver needed), and the worker counts under MPS."""

import os
import socket
import stat
import sys
from pathlib import Path

import pytest
import typer
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.batch import mps
from nanogs_warp.batch.gpu_workers import GPU_BYTES_PER_SPLAT, GPU_BYTES_PER_WORKER, GPU_WORKERS_MPS, MEMORY_SHARE, workers_for
from nanogs_warp.cli.batch import batch_command
from nanogs_warp.cli.errors import user_errors
from nanogs_warp.errors import InputError

# As cli/app.py registers it: `nanogs-warp batch ...`.
app = typer.Typer(pretty_exceptions_enable=False)
app.callback()(lambda: None)
app.command("batch")(user_errors(batch_command))
runner = CliRunner()

# A stand-in for the driver's daemon: "-d" binds the control socket in $CUDA_MPS_PIPE_DIRECTORY and
# returns (the socket stays, as a daemon's would); "quit" on stdin removes it. Each call is logged.
STAND_IN = """#!{python}
import os, socket, sys
pipe = os.environ["CUDA_MPS_PIPE_DIRECTORY"]
with open({log!r}, "a") as log:
    log.write(" ".join(sys.argv[1:]) + "|" + pipe + "|" + os.environ.get("CUDA_MPS_LOG_DIRECTORY", "") + "\\n")
if sys.argv[1:] == ["-d"]:
    if {fail}:
        print("An instance of this daemon is already running", file=sys.stderr)
        sys.exit(1)
    socket.socket(socket.AF_UNIX).bind(os.path.join(pipe, "control"))
elif sys.stdin.read().strip() == "quit":
    os.remove(os.path.join(pipe, "control"))
"""


def _stand_in(tmp_path: Path, monkeypatch, fail: bool = False) -> Path:
    folder = tmp_path / "bin"
    folder.mkdir()
    log = tmp_path / "calls.log"
    script = folder / mps.CONTROL
    script.write_text(STAND_IN.format(python=sys.executable, log=str(log), fail=fail))
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ.get('PATH', '')}")
    return log


def _no_running_daemon(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv(mps.PIPE_VARIABLE, str(tmp_path / "no-daemon-here"))
    monkeypatch.delenv(mps.LOG_VARIABLE, raising=False)


def test_a_private_daemon_is_started_for_the_workers_and_quit_after(tmp_path, monkeypatch):
    log = _stand_in(tmp_path, monkeypatch)
    _no_running_daemon(tmp_path, monkeypatch)
    before = os.environ[mps.PIPE_VARIABLE]
    with mps.mps_for_batch() as pipe:
        assert os.environ[mps.PIPE_VARIABLE] == str(pipe) != before  # what spawned workers inherit
        assert Path(os.environ[mps.LOG_VARIABLE]).is_dir()
        assert stat.S_ISSOCK(os.stat(pipe / "control").st_mode)
        scratch = pipe.parent
    calls = [line.split("|") for line in log.read_text().splitlines()]
    assert [c[0] for c in calls] == ["-d", ""]  # started, then told to quit (on stdin)
    assert all(c[1] == str(pipe) for c in calls)  # both reached the batch's own daemon
    assert not scratch.exists()
    assert os.environ[mps.PIPE_VARIABLE] == before and mps.LOG_VARIABLE not in os.environ


def test_the_daemon_is_quit_when_the_batch_fails(tmp_path, monkeypatch):
    log = _stand_in(tmp_path, monkeypatch)
    _no_running_daemon(tmp_path, monkeypatch)
    with pytest.raises(RuntimeError, match="a worker failed"):
        with mps.mps_for_batch():
            raise RuntimeError("a worker failed")
    assert [line.split("|")[0] for line in log.read_text().splitlines()] == ["-d", ""]


def test_a_running_daemon_is_used_as_it_is(tmp_path, monkeypatch):
    log = _stand_in(tmp_path, monkeypatch)
    pipe = tmp_path / "system-pipe"
    pipe.mkdir()
    listening = socket.socket(socket.AF_UNIX)
    listening.bind(str(pipe / "control"))
    listening.listen()
    monkeypatch.setenv(mps.PIPE_VARIABLE, str(pipe))
    try:
        assert mps.running_mps() == pipe
        with mps.mps_for_batch() as used:
            assert used == pipe
        assert not log.exists()  # neither started nor stopped
        assert (pipe / "control").exists()
    finally:
        listening.close()


def test_neither_a_plain_file_nor_a_socket_left_by_an_ended_daemon_is_a_daemon(tmp_path, monkeypatch):
    (tmp_path / "control").write_text("")
    monkeypatch.setenv(mps.PIPE_VARIABLE, str(tmp_path))
    assert mps.running_mps() is None
    left = tmp_path / "left"
    left.mkdir()
    with socket.socket(socket.AF_UNIX) as ended:
        ended.bind(str(left / "control"))
        ended.listen()
        monkeypatch.setenv(mps.PIPE_VARIABLE, str(left))
        assert mps.running_mps() == left
    assert (left / "control").exists() and mps.running_mps() is None  # the file stays; nobody listens


def test_a_daemon_that_cannot_start_is_one_line(tmp_path, monkeypatch):
    _stand_in(tmp_path, monkeypatch, fail=True)
    _no_running_daemon(tmp_path, monkeypatch)
    with pytest.raises(InputError, match=r"^--mps: nvidia-cuda-mps-control -d failed \(exit 1\): An instance of this daemon is already running$"):
        with mps.mps_for_batch():
            pass
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    with pytest.raises(InputError, match="is not on the PATH"):
        with mps.mps_for_batch():
            pass
    assert os.environ[mps.PIPE_VARIABLE] == str(tmp_path / "no-daemon-here") and mps.LOG_VARIABLE not in os.environ


def test_up_to_six_workers_a_gpu_under_mps_as_its_memory_holds():
    largest = 6_000_000
    each = GPU_BYTES_PER_WORKER + GPU_BYTES_PER_SPLAT * largest
    assert workers_for("cuda:0", largest, int(10 * each / MEMORY_SHARE), GPU_WORKERS_MPS) == GPU_WORKERS_MPS == 6
    assert workers_for("cuda:0", largest, int(3.5 * each / MEMORY_SHARE), GPU_WORKERS_MPS) == 3
    assert workers_for("cuda:0", largest, int(0.5 * each / MEMORY_SHARE), GPU_WORKERS_MPS) == 1
    assert workers_for("cuda:0", largest, int(10 * each / MEMORY_SHARE)) == 2  # without MPS
    assert workers_for("cpu", largest, 10**15, GPU_WORKERS_MPS) == 1


@pytest.mark.parametrize("where, says", [(["--devices", "cpu"], "names none"), (["--ray", "local"], "Ray")])
def test_mps_is_refused_in_one_line_without_a_local_gpu(tmp_path, where, says):
    if "--ray" in where:
        pytest.importorskip("ray")
    scene = tmp_path / "a.ply"
    random_splats_ply(scene, 50)
    out = tmp_path / "out"
    result = runner.invoke(app, ["batch", str(scene), "-o", str(out), "--ratio", "0.5", *where, "--mps"])
    assert result.exit_code != 0
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--mps" in lines[0] and says in lines[0] and "Traceback" not in result.output
    assert not out.exists()
