"""CUDA MPS for the batch's GPU workers (``batch --mps``).

Without MPS, the processes that share a GPU take turns on it: while one worker runs the geometry
fit's small kernels (a few dozen 16x16 tiles each), the rest of the GPU waits, though it is free.
Under MPS the workers' kernels run side by side. ``batch --mps`` uses an MPS control daemon that is
already running (the one ``CUDA_MPS_PIPE_DIRECTORY`` names, else the system's ``/tmp/nvidia-mps``)
or starts one of its own for the batch: its pipe and log directories in a new temporary
directory, named to the workers through the environment they inherit, so that no other program
on the machine joins it; the daemon is told to quit when the batch ends, whatever ends it.
"""

from __future__ import annotations

import os
import shutil
import socket
import stat
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import InputError

CONTROL = "nvidia-cuda-mps-control"  # the daemon's command, installed with the NVIDIA driver
SYSTEM_PIPE = Path("/tmp/nvidia-mps")  # where a daemon started without CUDA_MPS_PIPE_DIRECTORY listens
PIPE_VARIABLE = "CUDA_MPS_PIPE_DIRECTORY"
LOG_VARIABLE = "CUDA_MPS_LOG_DIRECTORY"
START_S = 10.0  # for the started daemon's control socket to appear
STOP_S = 10.0  # for the told daemon to end (no longer listening): it ends after its server
COMMAND_S = 30.0  # for the daemon's command to start it or to quit it


def _is_socket(path: Path) -> bool:
    try:
        return stat.S_ISSOCK(os.stat(path).st_mode)
    except OSError:
        return False


def _listening(path: Path) -> bool:
    """Whether a daemon accepts connections on the socket ``path`` (a socket file left by a daemon
    that has ended refuses them: the daemon does not remove it)."""
    if not _is_socket(path):
        return False
    with socket.socket(socket.AF_UNIX) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(str(path))
        except OSError:
            return False
    return True


def running_mps() -> Path | None:
    """The pipe directory of the MPS control daemon that this process's CUDA clients would join
    (``CUDA_MPS_PIPE_DIRECTORY``, else the system's), when it is listening there; else None."""
    pipe = Path(os.environ.get(PIPE_VARIABLE) or SYSTEM_PIPE)
    return pipe if _listening(pipe / "control") else None


def _control(arguments: list[str], env: dict[str, str], stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([CONTROL, *arguments], env=env, input=stdin, capture_output=True, text=True, timeout=COMMAND_S)


def _last_line(text: str) -> str:
    lines = [line.strip() for line in (text or "").splitlines() if line.strip()]
    return lines[-1] if lines else "no message"


@contextmanager
def mps_for_batch() -> Iterator[Path]:
    """Yields the pipe directory of an MPS control daemon that worker processes started inside the
    ``with`` reach: a running one (``running_mps``), used as it is, or a private one started here
    and quit on leaving (the environment variables it sets are restored too). InputError, in one
    line, where none can be started: no ``nvidia-cuda-mps-control`` on the PATH, or it fails."""
    running = running_mps()
    if running is not None:
        yield running
        return
    if shutil.which(CONTROL) is None:
        raise InputError(f"--mps: {CONTROL} is not on the PATH (it comes with the NVIDIA driver); run without --mps")
    scratch = Path(tempfile.mkdtemp(prefix="nanogs-mps-"))
    pipe, log = scratch / "pipe", scratch / "log"
    pipe.mkdir()
    log.mkdir()
    saved = {name: os.environ.get(name) for name in (PIPE_VARIABLE, LOG_VARIABLE)}
    env = {**os.environ, PIPE_VARIABLE: str(pipe), LOG_VARIABLE: str(log)}
    started = False
    try:
        try:
            result = _control(["-d"], env)
        except (OSError, subprocess.SubprocessError) as error:
            raise InputError(f"--mps: {CONTROL} -d could not run: {error}") from None
        if result.returncode != 0:
            raise InputError(f"--mps: {CONTROL} -d failed (exit {result.returncode}): {_last_line(result.stderr or result.stdout)}")
        started = True
        deadline = time.monotonic() + START_S
        while not _is_socket(pipe / "control"):
            if time.monotonic() > deadline:
                raise InputError(f"--mps: the MPS control daemon did not start within {START_S:g} s (its log: {log})")
            time.sleep(0.02)
        os.environ[PIPE_VARIABLE], os.environ[LOG_VARIABLE] = str(pipe), str(log)
        yield pipe
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        if started:
            try:
                _control([], env, stdin="quit\n")
            except (OSError, subprocess.SubprocessError):
                pass  # the daemon was gone already
            deadline = time.monotonic() + STOP_S
            while _listening(pipe / "control") and time.monotonic() < deadline:
                time.sleep(0.05)
        shutil.rmtree(scratch, ignore_errors=True)
