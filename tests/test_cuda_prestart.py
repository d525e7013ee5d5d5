"""The CUDA driver started early by the console script: which command lines start it, the driver
calls it makes, and that it is harmless where there is no driver or it fails."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import pytest

from nanogs_warp.cli import cuda_prestart
from nanogs_warp.cli.cuda_prestart import device_ordinal, start_cuda_early

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    "args, ordinal",
    [
        (["simplify", "in.ply", "-o", "o.ply"], 0),  # --device defaults to auto
        (["simplify", "in.ply", "--device", "auto"], 0),
        (["simplify", "in.ply", "--device", "CUDA"], 0),
        (["simplify", "in.ply", "--device", "cuda:3"], 3),
        (["simplify", "in.ply", "--device=cuda:1", "-o", "o.ply"], 1),
        (["eval", "a.ply", "b.ply", "--device", "cuda:2"], 2),
        (["simplify", "in.ply", "--device", "cpu"], None),
        (["simplify", "in.ply", "--device", "cuda:x"], None),  # refused later by the command itself
        (["simplify", "in.ply", "--device", "cuda:1", "--device", "cpu"], None),  # the last one counts, as for typer
        (["simplify", "in.ply", "--device"], 0),  # no value: the command reports it
        (["info", "in.ply"], None),
        (["batch", "scenes/", "-o", "out/"], None),
        (["warmup"], None),
        ([], None),
    ],
)
def test_the_gpu_named_on_the_command_line(args, ordinal):
    assert device_ordinal(["nanogs-warp", *args]) == ordinal


class FakeDriver:
    def __init__(self, init_result: int = 0):
        self.calls = []
        self.init_result = init_result

    def cuInit(self, flags):
        self.calls.append(("cuInit", flags))
        return self.init_result

    def cuDeviceGet(self, device, ordinal):
        self.calls.append(("cuDeviceGet", ordinal))
        return 0

    def cuDevicePrimaryCtxRetain(self, context, device):
        self.calls.append(("cuDevicePrimaryCtxRetain",))
        return 0


def _join_started_threads(before: set) -> None:
    for thread in set(threading.enumerate()) - before:
        thread.join(timeout=10)
        assert not thread.is_alive()


def test_it_starts_the_driver_and_retains_the_named_gpus_context(monkeypatch):
    driver = FakeDriver()
    monkeypatch.setattr(cuda_prestart.ctypes, "CDLL", lambda name: driver)
    monkeypatch.setattr(cuda_prestart.sys, "platform", "linux")
    before = set(threading.enumerate())
    start_cuda_early(["nanogs-warp", "simplify", "in.ply", "--device", "cuda:2"])
    _join_started_threads(before)
    assert driver.calls == [("cuInit", 0), ("cuDeviceGet", 2), ("cuDevicePrimaryCtxRetain",)]


def test_nothing_starts_for_the_cpu_or_a_failing_driver(monkeypatch):
    driver = FakeDriver(init_result=100)  # CUDA_ERROR_NO_DEVICE
    monkeypatch.setattr(cuda_prestart.ctypes, "CDLL", lambda name: driver)
    monkeypatch.setattr(cuda_prestart.sys, "platform", "linux")
    before = set(threading.enumerate())
    start_cuda_early(["nanogs-warp", "simplify", "in.ply", "--device", "cpu"])
    _join_started_threads(before)
    assert driver.calls == []
    start_cuda_early(["nanogs-warp", "simplify", "in.ply"])
    _join_started_threads(before)
    assert driver.calls == [("cuInit", 0)]  # stops at the first failure, silently


def test_no_driver_library_is_silent(monkeypatch):
    def missing(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(cuda_prestart.ctypes, "CDLL", missing)
    monkeypatch.setattr(cuda_prestart.sys, "platform", "linux")
    before = set(threading.enumerate())
    start_cuda_early(["nanogs-warp", "simplify", "in.ply"])
    _join_started_threads(before)


def test_the_console_script_starts_it_before_the_commands_imports():
    """pyproject's ``nanogs-warp`` is the entry that starts the driver first, and it imports neither
    typer, NumPy nor Warp before doing so."""
    import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["scripts"]
    assert scripts["nanogs-warp"] == "nanogs_warp.cli.entry:main"
    probe = (
        "import sys, nanogs_warp.cli.entry\n"
        "print(sorted(m for m in ('typer', 'numpy', 'warp') if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
