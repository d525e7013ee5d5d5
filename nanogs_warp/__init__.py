"""nanogs-warp: training-free simplification of 3D Gaussian Splatting scenes (NanoGS) with Warp.

Importing the package is quick and quiet: the names below load their modules (and Warp) on first
use, with Warp's start-up and module-load messages off, and its notice that a machine has no CUDA
driver dropped (NANOGS_DEBUG=1 turns them on).
"""

__version__ = "0.1.0"

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
