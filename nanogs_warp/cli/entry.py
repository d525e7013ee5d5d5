"""The console script (``nanogs-warp``, and ``python -m nanogs_warp``): starts the CUDA driver on
a background thread first (:mod:`.cuda_prestart`), has SIGTERM and SIGHUP end the command as an
interrupt does, then imports and runs the command.

Python's garbage collector is paused first, for the command's imports (:mod:`.gc_pause`)."""

import os
import signal
import sys

from .cuda_prestart import start_cuda_early
from .gc_pause import pause_gc


def _end_command(signum, frame) -> None:
    """SIGTERM / SIGHUP: unwind as SystemExit(128 + signal), so that the command's ``finally``
    blocks run: temporary files are removed, a write in progress ends renamed into place or not at
    all, and a batch stops its worker processes (by default the process just died, leaving them)."""
    raise SystemExit(128 + signum)


def main() -> None:
    pause_gc()
    for name in ("stdout", "stderr"):  # started with one closed (>&-): what goes there is discarded
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))
    start_cuda_early()
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _end_command)
    from .app import main as run_command

    run_command()
