"""The method's settings (:class:`SimplifyConfig`) and the target count of a ratio, without Warp:
the command line reads them before it decides whether it needs Warp at all."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import InputError

# Neighbours per splat when k is not set: more for small scenes, where they are cheap (docs/quality.md:
# the one shared scene below the threshold, 4,721 splats, needs 24 at rho = 0.1 to beat the top-k
# baseline; the four above it, 91k to 500k splats, measure the same mean PSNR at 16 and 24, and 16 is
# about 1.3x faster). The measurements put the threshold anywhere from 4,722 to 90,854 splats.
SMALL_SCENE_SPLATS = 65_536
K_SMALL_SCENE = 24
K_LARGE_SCENE = 16


@dataclass(frozen=True)
class SimplifyConfig:
    """Every constant of the method.

    The defaults are the configuration with the best measured mean PSNR over the shared scenes and
    budgets (docs/quality.md): the coverage merge operator, the Runnalls cost, no opacity pruning
    and k = None: 24 neighbours below 65,536 splats, 16 from there on. ``SimplifyConfig.paper()`` is
    the NanoGS paper's configuration.
    """

    k: int | None = None
    prune_opacity: float = 0.0
    samples: int = 1
    seed: int = 0
    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    cost: str = "runnalls"
    operator: str = "coverage"

    @staticmethod
    def paper(**overrides) -> SimplifyConfig:
        """The paper's configuration: MPMM, Monte Carlo I-divergence, pruning at 0.1, k = 16."""
        return SimplifyConfig(**{"k": 16, "prune_opacity": 0.1, "cost": "idiv", "operator": "mpmm", **overrides})

    def neighbours(self, splat_count: int) -> int:
        """k for a scene of ``splat_count`` splats (after pruning): k itself, or when unset 24 below
        SMALL_SCENE_SPLATS splats and 16 from there on."""
        if self.k is not None:
            return self.k
        return K_SMALL_SCENE if splat_count < SMALL_SCENE_SPLATS else K_LARGE_SCENE

    def validate(self) -> None:
        from .cost import COSTS  # the registries hold Warp kernels: imported when needed
        from .operators import OPERATORS
        from .topology import KnnTopology

        if self.k is not None and not 1 <= self.k <= KnnTopology.MAX_K:
            raise InputError(f"--k must be between 1 and {KnnTopology.MAX_K}, got {self.k}")
        if not 0.0 <= self.prune_opacity <= 1.0:
            raise InputError(f"--prune-opacity must be in [0, 1], got {self.prune_opacity}")
        if not 1 <= self.samples <= 1024:
            raise InputError(f"--samples must be between 1 and 1024, got {self.samples}")
        if self.cost not in COSTS:
            raise InputError(f"unknown cost {self.cost!r}; choose one of {', '.join(COSTS)}")
        if self.operator not in OPERATORS:
            raise InputError(f"unknown operator {self.operator!r}; choose one of {', '.join(OPERATORS)}")
        for name in ("lambda_geo", "lambda_app"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number >= 0, got {value}")


def target_count(input_count: int, ratio: float) -> int:
    """N_tgt = max(1, ceil(ratio * N_0))."""
    if not (0.0 < ratio <= 1.0):
        raise InputError(f"ratio must be in (0, 1], got {ratio}")
    return max(1, math.ceil(ratio * input_count))
