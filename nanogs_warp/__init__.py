"""nanogs-warp: training-free simplification of 3D Gaussian Splatting scenes (NanoGS) with Warp.

Importing the package is quick and quiet: the names below load their modules (and Warp) on first
use, with Warp's start-up and module-load messages off, and its notice that a machine has no CUDA
driver dropped (NANOGS_DEBUG=1 turns them on).
"""

import os as _os
import signal as _signal
import sys as _sys

__version__ = "0.1.0"


def _quiet_interrupt(signum, frame) -> None:
    """Ctrl-C before the command has started: nothing was started, so it ends at once (exit code 130)."""
    _os._exit(130)


def _started_as_the_command() -> bool:
    """Whether this process is the ``nanogs-warp`` console script or ``python -m nanogs_warp``, not a
    program that imports the package."""
    argv = getattr(_sys, "orig_argv", None) or []
    module = next((argv[k + 1] for k in range(len(argv) - 1) if argv[k] == "-m"), None)
    script = (getattr(_sys, "argv", None) or [""])[0]  # (an embedded interpreter may have no argv)
    return module == "nanogs_warp" or _os.path.basename(str(script)) in ("nanogs-warp", "nanogs-warp.exe")


# The command's own start (``cli/entry.py``) ends a Ctrl-C during its imports quietly; before it runs,
# ``python -m`` executes this package and its ``__main__`` and the console script imports its entry
# point: a Ctrl-C there ends quietly too (a SIGINT the command was started with ignored stays so).
if _started_as_the_command() and _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:
    _signal.signal(_signal.SIGINT, _quiet_interrupt)

# name -> module that defines it
_EXPORTS = {
    "InputError": "errors",
    "SimplifyConfig": "config",
    "simplify": "refinement.simplify",
    "simplify_progressively": "refinement.simplify",
    "load_ply": "io.ply",
    "save_ply": "io.ply",
    "SplatSet": "splats",
    "RefineConfig": "refinement.config",
    "refine": "refinement.refine",
    "load_splats": "io",
    "save_splats": "io",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'nanogs_warp' has no attribute {name!r}")
    import importlib

    if module in ("refinement.simplify", "io.ply", "splats", "io", "refinement.refine"):
        importlib.import_module(".device", __name__).init_warp()  # quiet: no "no CUDA driver" notice on a CPU machine
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
