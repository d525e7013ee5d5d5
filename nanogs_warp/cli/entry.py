"""The console script (``nanogs-warp``, and ``python -m nanogs_warp``): starts the CUDA driver on
a background thread first (:mod:`.cuda_prestart`), has SIGTERM and SIGHUP end the command as an
interrupt does (unless the command was started with them ignored, as ``nohup`` does for SIGHUP),
then imports and runs the command.

Python's garbage collector is paused first, for the command's imports (:mod:`.gc_pause`). Only the
interpreter's built-in modules are imported here, so that a Ctrl-C during the imports ends the
command quietly (exit code 130) instead of with a traceback."""

import errno
import io
import os
import signal
import sys


def _end_command(signum, frame) -> None:
    """SIGTERM / SIGHUP: unwind as SystemExit(128 + signal), so that the command's ``finally``
    blocks run: temporary files are removed, a write in progress ends renamed into place or not at
    all, and a batch stops its worker processes (by default the process just died, leaving them)."""
    raise SystemExit(128 + signum)


def _open_standard_descriptors() -> None:
    """Standard streams the command was started without (``<&- >&- 2>&-``) opened on the null
    device. A closed descriptor 0, 1 or 2 would be the next file's: Warp's start, which briefly
    points descriptor 2 at a file of its own, then swapped the input file out from under the read."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            os.open(os.devnull, os.O_RDWR)  # the lowest free descriptor: this one
    if sys.stdout is None:  # the command's output cannot be written: printing it fails (exit code 2)
        sys.stdout = _ClosedOutput()
    if sys.stderr is None:  # nowhere to say anything: what goes there is discarded, the exit code says it
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - the process's own stream


class _ClosedOutput(io.TextIOBase):
    """Standard output for a command started without one (``>&-``): what is printed is discarded, and
    flushing after anything was printed fails as a closed descriptor does (EBADF), so that a command
    with something to print (``info``, a ``--json`` summary) ends, its outputs in place, with exit
    code 2 and one line on stderr instead of losing it silently; one that prints nothing (``-q``)
    ends as usual."""

    lost = False

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self.lost = self.lost or bool(text)
        return len(text)

    def flush(self) -> None:
        if self.lost:
            raise OSError(errno.EBADF, "standard output is closed")


def main() -> None:
    try:
        _open_standard_descriptors()
        from .gc_pause import pause_gc

        pause_gc()
        from .cuda_prestart import start_cuda_early

        start_cuda_early()
        for name in ("SIGTERM", "SIGHUP"):
            # one the command was started with ignored stays ignored: ``nohup`` (SIGHUP) keeps a long
            # batch running after its terminal closes, as the caller asked
            if hasattr(signal, name) and signal.getsignal(getattr(signal, name)) != signal.SIG_IGN:
                signal.signal(getattr(signal, name), _end_command)
        from .app import main as run_command
    except KeyboardInterrupt:  # Ctrl-C while the command is still being imported: nothing was started
        os._exit(130)
    from .. import _quiet_interrupt

    if signal.getsignal(signal.SIGINT) is _quiet_interrupt:  # the package's start-up handler: the command's own from here
        signal.signal(signal.SIGINT, signal.default_int_handler)
    run_command()
