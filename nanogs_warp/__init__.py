"""nanogs-warp: training-free simplification of 3D Gaussian Splatting scenes (NanoGS) with Warp."""

__version__ = "0.1.0"

from .errors import InputError  # noqa: E402
from .pipeline import SimplifyConfig, simplify, simplify_progressively  # noqa: E402
from .ply import load_ply, save_ply  # noqa: E402
from .refine import RefineConfig, refine  # noqa: E402
from .splats import SplatSet  # noqa: E402

__all__ = [
    "InputError",
    "RefineConfig",
    "SimplifyConfig",
    "SplatSet",
    "load_ply",
    "refine",
    "save_ply",
    "simplify",
    "simplify_progressively",
]
