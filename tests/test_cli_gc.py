"""The console script pauses Python's garbage collector while a command's libraries are imported
(``nanogs_warp.cli.gc_pause``): it runs again, with the imported objects frozen, once the imports are
done, for ``simplify`` and every other command; called in-process, nothing changes."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
from pathlib import Path

import pytest

from nanogs_warp.cli import gc_pause
from nanogs_warp.data import sample_path

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def collector():
    """Restores the collector's state (and the module's flag) after a test."""
    was_enabled = gc.isenabled()
    yield
    gc_pause._gc_paused = False
    (gc.enable if was_enabled else gc.disable)()


def test_imports_done_changes_nothing_unless_paused(collector):
    frozen = gc.get_freeze_count()
    gc.enable()
    gc_pause.imports_done()
    assert gc.isenabled() and gc.get_freeze_count() == frozen
    gc.disable()  # off before (by the caller): stays off
    gc_pause.pause_gc()
    gc_pause.imports_done()
    assert not gc.isenabled() and gc.get_freeze_count() == frozen


def test_pause_then_imports_done_runs_it_again(collector):
    gc.enable()
    gc_pause.pause_gc()
    assert not gc.isenabled()
    kept = [[] for _ in range(100)]  # objects made during the "imports"
    gc_pause.imports_done()
    assert gc.isenabled() and gc.get_freeze_count() >= len(kept)
    gc.unfreeze()
    gc_pause.imports_done()  # once only
    assert gc.isenabled() and gc.get_freeze_count() == 0


# Runs the console script in a fresh process and reports, as the command ends (os._exit), whether
# the collector runs and whether the imported objects were frozen.
_PROBE = """
import gc, os, sys
real_exit = os._exit
def report(code):
    print("GC", gc.isenabled(), gc.get_freeze_count() > 0, flush=True)
    real_exit(code)
os._exit = report
sys.argv = ["nanogs-warp"] + sys.argv[1:]
from nanogs_warp.cli.entry import main
main()
"""


@pytest.mark.parametrize("command", ["simplify", "info"])
def test_the_console_script_runs_the_collector_again(tmp_path, command):
    if command == "simplify":
        args = ["simplify", "--sample", "-o", str(tmp_path / "o.ply"), "--count", "2000", "--device", "cpu", "--json"]
    else:
        args = ["info", str(sample_path()), "--json"]
    result = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[-1] == "GC True True"
    summary = json.loads("\n".join(lines[:-1]))
    assert summary["command"] == command


def test_a_refused_command_line_still_ends_cleanly(tmp_path):
    """An error before the imports are done (here: an unknown option) ends as before: one line, exit 2."""
    args = ["simplify", "--sample", "-o", str(tmp_path / "o.ply"), "--count", "10", "--no-such-option"]
    result = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 2 and "Traceback" not in result.stderr
