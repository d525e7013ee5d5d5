"""Refinement settings (no Warp here: the command line reads the defaults before Warp starts)."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import MAX_SEED, check_types
from ..errors import InputError

MIN_SIZE = 32  # the half-size training views must fit the 11-pixel SSIM window
MAX_SIZE = 4096  # views of 4096 x 4096 (16.8 M pixels): beyond, a view's buffers outgrow a GPU or a host
MAX_STEPS = 100_000  # hours on a GPU for any scene: a larger count is a typing slip


@dataclass
class RefineConfig:
    """Refinement settings; learning rates as in 3DGS (``lr_means`` is per unit of scene extent)."""

    steps: int = 300
    coarse_steps: int = 0  # the first steps train on the views at half their size (``ReferenceViews.halved``)
    size: int = 256
    views_per_step: int = 1
    reference_views: int = 128
    seed: int = 0
    ssim_weight: float = 0.2
    lr_means: float = 1.6e-4
    lr_means_final: float = 0.1  # fraction of lr_means reached at the last step (exponential decay)
    lr_log_scales: float = 5e-3
    lr_rotations: float = 1e-3
    lr_opacities: float = 2.5e-2
    lr_features_dc: float = 2.5e-3
    lr_features_rest: float = 2.5e-3 / 20.0
    log_scale_range: tuple[float, float] = (-20.0, 5.0)  # the upper end is relative to log(extent)
    logit_range: tuple[float, float] = (-20.0, 20.0)

    def validate(self) -> None:
        check_types(self, {"steps": "int", "coarse_steps": "int", "size": "int", "views_per_step": "int", "reference_views": "int", "seed": "int"})
        if not 0 <= self.seed <= MAX_SEED:
            raise InputError(f"--seed must be between 0 and {MAX_SEED}, got {self.seed}")
        if not 0 <= self.steps <= MAX_STEPS:
            raise InputError(f"--refine-steps must be in [0, {MAX_STEPS}], got {self.steps}")
        if not 0 <= self.coarse_steps <= self.steps:
            raise InputError(f"coarse steps must be in [0, {self.steps}] (the steps), got {self.coarse_steps}")
        if not MIN_SIZE <= self.size <= MAX_SIZE:
            raise InputError(f"--refine-size must be in [{MIN_SIZE}, {MAX_SIZE}] pixels, got {self.size}")
        if self.views_per_step < 1 or self.reference_views < 1:
            raise InputError("refinement needs at least one view per step and one reference view")
