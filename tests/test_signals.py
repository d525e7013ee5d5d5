"""SIGTERM and SIGHUP end a command as an interrupt does: its ``finally`` blocks run, so no
temporary file is left beside an output and a batch stops its worker processes (which the default
action, dying at once, left running)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from scene_factory import random_splats_ply

from nanogs_warp.io.ply import load_ply

# These tests send signals to runs; the fits after the merge (seconds on a CPU, tested elsewhere)
# would only make each run longer.
NO_FITS = ("--no-fit-geometry", "--no-fit-colour")

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals, pgrep and /proc")


def _wait_for(predicate, seconds: float = 60.0) -> None:
    end = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_during_simplify_leaves_no_temporary_file(tmp_path, signum):
    scene = tmp_path / "big.ply"
    random_splats_ply(scene, 200_000, sh_degree=1, seed=3)
    out = tmp_path / "out"
    out.mkdir()
    process = subprocess.Popen([sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out / "o.ply"),
                                "--ratio", "0.5", "--device", "cpu", "-q", *NO_FITS], stderr=subprocess.PIPE, text=True)  # fmt: skip
    _wait_for(lambda: any(p.name.endswith(".tmp") for p in out.iterdir()) or process.poll() is not None)
    process.send_signal(signum)
    assert process.wait(timeout=120) in (128 + signum, 0), process.stderr.read()  # 0: it had just finished
    assert [p.name for p in out.iterdir()] in ([], ["o.ply"])
    if (out / "o.ply").exists():
        assert load_ply(out / "o.ply").count == 100_000


def test_a_signal_to_batch_stops_its_workers(tmp_path):
    root = tmp_path / "in"
    root.mkdir()
    for name in ("a.ply", "b.ply"):
        random_splats_ply(root / name, 150_000, seed=len(name))
    process = subprocess.Popen([sys.executable, "-m", "nanogs_warp", "batch", str(root), "-o", str(tmp_path / "out"),
                                "--ratio", "0.1", "--devices", "cpu", "--workers", "2", "-q"])  # fmt: skip

    def workers() -> list[int]:
        found = subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True, text=True).stdout.split()
        return [int(pid) for pid in found]

    _wait_for(lambda: len(workers()) >= 2)
    children = workers()
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=120) == 128 + signal.SIGTERM
    written = sorted(p.name for p in tmp_path.rglob("*") if p.is_file())
    _wait_for(lambda: not any(_running(pid) for pid in children), 30)
    time.sleep(1.0)
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == written  # no worker wrote on alone
    assert not any(name.endswith(".tmp") for name in written)
    if not any(p.is_file() for p in (tmp_path / "out").rglob("*")):  # stopped before any scene was written:
        assert not (tmp_path / "out").exists()  # the output folder it made went too (it stayed, empty)


def _running(pid: int) -> bool:
    """Whether the process is alive (a zombie, exited but not yet reaped, is not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_what_a_killed_simplify_left_goes_with_the_next_run(tmp_path):
    """kill -9 runs no handler, so the temporary stays; the next run of the same outputs removes the
    temporaries of writers that are gone (their process id is in the name), never a live one's."""
    scene = tmp_path / "big.ply"
    random_splats_ply(scene, 200_000, sh_degree=1, seed=3)
    out = tmp_path / "out"
    out.mkdir()
    command = [sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out / "o.ply"), "--ratio", "0.5", "--device", "cpu", "-q", *NO_FITS]
    process = subprocess.Popen(command)
    _wait_for(lambda: any(p.name.endswith(".tmp") for p in out.iterdir()) or process.poll() is not None)
    process.kill()
    process.wait(timeout=60)
    left = [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    assert left == [] or left[0].startswith(f".o.ply.{process.pid}-")  # [] if it had just finished
    live = out / f".o.ply.{os.getppid()}-{'a' * 12}.tmp"  # a writer that is still there (pytest's parent)
    others = [out / ".o.ply.tmp", out / f".o.ply.{process.pid}-xyz.tmp", out / f".p.ply.{process.pid}-{'b' * 12}.tmp"]
    for path in (live, *others):
        path.write_bytes(b"partial")
    subprocess.run([*command, "-w"], check=True, timeout=300)
    assert sorted(p.name for p in out.iterdir()) == sorted(["o.ply", live.name, *(p.name for p in others)])


def test_a_batch_worker_given_two_signals_at_once_ends_quietly():
    """A process group's Ctrl-C and the batch's SIGTERM arrive together: the worker's handler had set
    SIG_IGN for the second one, which was already pending, and CPython raised "OSError: Signal 15
    ignored due to race condition" in place of the SystemExit, a traceback from the worker."""
    code = (
        "import os, signal, time\n"
        "from nanogs_warp.batch.local import _end_on_signals\n"
        "_end_on_signals()\n"
        "pair = {signal.SIGTERM, signal.SIGINT}\n"
        "try:\n"
        "    try:\n"
        "        signal.pthread_sigmask(signal.SIG_BLOCK, pair)\n"
        "        os.kill(os.getpid(), signal.SIGTERM)\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        signal.pthread_sigmask(signal.SIG_UNBLOCK, pair)  # both delivered at once\n"
        "        time.sleep(5)\n"
        "    finally:\n"
        "        time.sleep(0.2)  # the scene being written is finished here\n"
        "except SystemExit as e:\n"
        "    print('ended', e.code)\n"
    )  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.split() == ["ended", "130"] and result.stderr == "", result.stderr


def test_a_batch_workers_signal_swallowed_by_a_finaliser_still_ends_it_quietly():
    """The handler's SystemExit raised inside a finaliser (Warp's ``array.__del__``) is only printed
    ("Exception ignored in ..."), and the worker went on with its scenes, its handlers by then
    ignoring the batch's SIGTERM: a batch's Ctrl-C took 62 s to end, or never. It is now raised
    again between passes and scenes (``_end_if_signalled``), and not printed."""
    code = (
        "import os, signal, time\n"
        "from nanogs_warp.batch.local import _end_if_signalled, _end_on_signals\n"
        "_end_on_signals()\n"
        "class Slow:\n"
        "    def __del__(self):\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(0.2)  # the handler runs here, inside the finaliser\n"
        "slow = Slow()\n"
        "del slow\n"
        "print('went on')\n"
        "try:\n"
        "    _end_if_signalled()\n"
        "except SystemExit as e:\n"
        "    print('ended', e.code)\n"
    )  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.split() == ["went", "on", "ended", "130"] and result.stderr == "", result


def test_ctrl_c_between_the_package_and_the_command_ends_quietly_only_in_the_command():
    """``python -m nanogs_warp`` runs the package, then its ``__main__``, then the command's start;
    a Ctrl-C in between was a traceback. As the command (its console script's name in argv[0]) the
    package's import sets a handler that ends the process (130, nothing on stderr) until the command
    takes over; imported by another program, the program's Ctrl-C stays its own KeyboardInterrupt."""
    code = (
        "import os, signal, sys\n"
        "sys.argv[0] = {name!r}\n"
        "import nanogs_warp\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    for _ in range(10**6):\n"
        "        pass\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted')\n"
    )
    command = subprocess.run([sys.executable, "-c", code.format(name="/usr/bin/nanogs-warp")], capture_output=True, text=True, timeout=60)
    assert (command.returncode, command.stdout, command.stderr) == (130, "", ""), command
    program = subprocess.run([sys.executable, "-c", code.format(name="my_tool.py")], capture_output=True, text=True, timeout=60)
    assert (program.returncode, program.stdout, program.stderr) == (0, "interrupted\n", ""), program


def test_ctrl_c_while_the_command_is_imported_ends_it_without_a_traceback(tmp_path):
    """SIGINT in the command's first tenth of a second (the imports, the command line's parsing) gave
    a KeyboardInterrupt traceback; now exit code 130 and nothing on stderr. Later, click's own. The
    first delay is the interpreter's own start on this machine and a half (before the package is
    imported a Ctrl-C is the interpreter's, which no code of the package can catch), then later."""
    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 2000, seed=3)
    start = []
    for _ in range(3):
        begun = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], check=True)
        start.append(time.perf_counter() - begun)
    interpreter = min(start)
    for delay in (1.5 * interpreter, interpreter + 0.05, interpreter + 0.12):
        process = subprocess.Popen([sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(tmp_path / "o.ply"),
                                    "--ratio", "0.1", "--device", "cpu"], stderr=subprocess.PIPE, text=True)  # fmt: skip
        time.sleep(delay)
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=120)
        assert "Traceback" not in err, err
        assert process.returncode in (0, 1, 130), (delay, process.returncode, err)  # 0: done first; 1: click's "Aborted!"
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_command_started_with_sighup_ignored_keeps_running(tmp_path):
    """``nohup nanogs-warp ...``: SIGHUP ignored by the caller stays ignored (the command's own
    handler, which ends it as an interrupt does, replaced it and ended a farm's batch when its
    terminal closed); the run finishes and writes its output."""
    scene = tmp_path / "big.ply"
    random_splats_ply(scene, 200_000, sh_degree=1, seed=5)
    out = tmp_path / "out"
    out.mkdir()
    process = subprocess.Popen([sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out / "o.ply"),
                                "--ratio", "0.5", "--device", "cpu", "-q", *NO_FITS], stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))  # fmt: skip
    _wait_for(lambda: any(p.name.endswith(".tmp") for p in out.iterdir()) or process.poll() is not None)
    process.send_signal(signal.SIGHUP)
    assert process.wait(timeout=120) == 0, process.stderr.read()
    assert [p.name for p in out.iterdir()] == ["o.ply"] and load_ply(out / "o.ply").count == 100_000


def test_a_batch_worker_keeps_an_ignored_sighup_and_ends_on_sigterm():
    """A worker of a batch started under ``nohup`` leaves SIGHUP (and an ignored SIGINT) ignored;
    SIGTERM, the batch's own way of stopping it, still ends it as SystemExit(143)."""
    code = (
        "import os, signal, time\n"
        "signal.signal(signal.SIGHUP, signal.SIG_IGN)\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "from nanogs_warp.batch.local import _end_on_signals\n"
        "_end_on_signals()\n"
        "print(signal.getsignal(signal.SIGHUP) == signal.SIG_IGN, signal.getsignal(signal.SIGINT) == signal.SIG_IGN)\n"
        "os.kill(os.getpid(), signal.SIGHUP)\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(5)\n"
        "except SystemExit as e:\n"
        "    print('ended', e.code)\n"
    )  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.split() == ["True", "True", "ended", "143"], (result.stdout, result.stderr)


def test_a_signal_held_while_outputs_are_moved_is_not_lost_behind_an_ignored_one():
    """Under nohup a hang-up is ignored; one that arrived while the outputs were moved into place,
    before a SIGTERM, was the signal acted on at the end (ignored), and the SIGTERM was lost: the
    command kept running."""
    code = (
        "import os, signal, time\n"
        "from nanogs_warp.io.ply_write import signals_held\n"
        "signal.signal(signal.SIGHUP, signal.SIG_IGN)\n"
        "with signals_held():\n"
        "    os.kill(os.getpid(), signal.SIGHUP)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(0.1)\n"
        "print('still running')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == -signal.SIGTERM and "still running" not in done.stdout


def test_a_batch_workers_signal_while_it_waits_for_its_writer_lets_the_write_finish(tmp_path):
    """A worker whose first ending signal arrived while it waited for its writer thread (the batch
    gone, its last scene being written) ended at once, the write cut short."""
    done = tmp_path / "written"
    code = (
        "import os, queue, signal, sys, threading, time\n"
        "from nanogs_warp.batch import local\n"
        "local._end_on_signals()\n"
        "to_write = queue.Queue()\n"
        "written = threading.Event()\n"
        "def writer():\n"
        "    while to_write.get() is not None:\n"
        "        pass\n"
        "    time.sleep(1.0)\n"
        f"    open({str(done)!r}, 'w').write('whole')\n"
        "    written.set()\n"
        "threading.Thread(target=writer).start()\n"
        "threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGTERM)).start()\n"
        "try:\n"
        "    local._finish_writing(to_write, written)\n"
        "except SystemExit as e:\n"
        "    os._exit(e.code)\n"
        "os._exit(0)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 128 + signal.SIGTERM, result.stderr
    assert done.read_text() == "whole"
