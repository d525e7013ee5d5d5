"""The CUDA driver started on a background thread as the process starts, before the command's
imports: the driver's start and the GPU's context (about a tenth of a second on a data-centre GPU)
then overlap the interpreter's work of importing typer, NumPy and Warp, instead of following it.

Only the driver's own calls run here (``cuInit``, ``cuDevicePrimaryCtxRetain`` through ctypes): no
Warp, no allocation. Warp later retains the same primary context, so it finds it made. On a
machine without the driver, or when the command will not use a GPU (``--device cpu``, or a
command that never starts one), nothing happens; any failure here is silent, and Warp reports
whatever it finds when it starts itself.
"""

from __future__ import annotations

import ctypes
import sys
import threading

_GPU_COMMANDS = ("simplify", "eval")  # the commands that start one device named by --device


def device_ordinal(argv: list[str]) -> int | None:
    """The CUDA ordinal the command line will use, or None when it will not use a GPU or does not say.
    ``--device`` defaults to auto (the first GPU)."""
    if len(argv) < 2 or argv[1] not in _GPU_COMMANDS:
        return None
    value = "auto"
    for i, arg in enumerate(argv[2:], start=2):
        if arg == "--device" and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith("--device="):
            value = arg.split("=", 1)[1]
    value = value.strip().lower()
    if value in ("auto", "cuda"):
        return 0
    if value.startswith("cuda:") and value[5:].isdigit():
        return int(value[5:])
    return None


def _retain_primary_context(ordinal: int) -> None:
    try:
        driver = ctypes.CDLL("nvcuda.dll" if sys.platform == "win32" else "libcuda.so.1")
        if driver.cuInit(0) != 0:
            return
        device = ctypes.c_int()
        if driver.cuDeviceGet(ctypes.byref(device), ordinal) != 0:
            return
        driver.cuDevicePrimaryCtxRetain(ctypes.byref(ctypes.c_void_p()), device)
    except (OSError, AttributeError):  # no driver, or not this driver API
        pass


def start_cuda_early(argv: list[str] | None = None) -> None:
    """Starts the driver and the primary context of the GPU that ``argv`` (default sys.argv) names,
    on a daemon thread; returns at once."""
    ordinal = device_ordinal(sys.argv if argv is None else argv)
    if ordinal is not None and sys.platform != "darwin":
        threading.Thread(target=_retain_primary_context, args=(ordinal,), name="nanogs-warp-cuda", daemon=True).start()
