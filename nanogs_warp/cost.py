"""Cost objectives: score every candidate edge; lower is a better merge.

A cost objective is a callable ``cost(splats, edges, pass_index) -> wp.array(float32)`` of one cost
per edge. Add a new objective by writing its kernel in ``nanogs_warp.kernels.cost`` and a class here,
then naming it in ``COSTS``.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from .kernels import cost as kernels
from .parallel import launch_rows
from .splats import SplatSet
from .topology import Edges


@dataclass(frozen=True)
class IDivergenceCost:
    """lambda_geo * I(p~_ij || q_m) (Monte Carlo, S common samples per pass) + lambda_app * ||f_i - f_j||^2."""

    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        device = splats.device
        common = wp.empty(self.samples, dtype=wp.vec4, device=device)
        wp.launch(kernels.draw_common_samples, self.samples, inputs=[self.seed, pass_index], outputs=[common], device=device)
        costs = wp.empty(edges.count, dtype=wp.float32, device=device)
        launch_rows(
            kernels.idivergence_costs, edges.count,
            lambda rows: [
                edges.i[rows], edges.j[rows], splats.means, splats.rotations, splats.log_scales,
                splats.opacities, splats.features, common, self.lambda_geo, self.lambda_app, costs[rows],
            ],
            device,
        )  # fmt: skip
        return costs


@dataclass(frozen=True)
class MeanSquaredCost:
    """The ablation's fast surrogate: lambda_geo * (||mu_i - mu_j||^2 + ||Sigma_i - Sigma_j||_F^2) + appearance."""

    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        costs = wp.empty(edges.count, dtype=wp.float32, device=splats.device)
        launch_rows(
            kernels.mse_costs, edges.count,
            lambda rows: [
                edges.i[rows], edges.j[rows], splats.means, splats.rotations, splats.log_scales,
                splats.features, self.lambda_geo, self.lambda_app, costs[rows],
            ],
            splats.device,
        )  # fmt: skip
        return costs


@dataclass(frozen=True)
class WeightedIDivergenceCost:
    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0
    area_weights: int = 1
    mass_scaled: int = 1
    app_mode: int = 0

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        device = splats.device
        common = wp.empty(self.samples, dtype=wp.vec4, device=device)
        wp.launch(kernels.draw_common_samples, self.samples, inputs=[self.seed, pass_index], outputs=[common], device=device)
        costs = wp.empty(edges.count, dtype=wp.float32, device=device)
        launch_rows(
            kernels.weighted_idivergence_costs, edges.count,
            lambda rows: [
                edges.i[rows], edges.j[rows], splats.means, splats.rotations, splats.log_scales,
                splats.opacities, splats.features, common, self.lambda_geo, self.lambda_app,
                self.area_weights, self.mass_scaled, self.app_mode, costs[rows],
            ],
            device,
        )  # fmt: skip
        return costs


def _variant(name, **fixed):
    def make(lambda_geo=1.0, lambda_app=1.0, samples=1, seed=0):
        return WeightedIDivergenceCost(lambda_geo, lambda_app, samples, seed, **fixed)
    make.__name__ = name
    return make


COSTS = {
    "idiv": IDivergenceCost,
    "mse": MeanSquaredCost,
    "x-area": _variant("x-area", area_weights=1, mass_scaled=0, app_mode=0),
    "x-areamass": _variant("x-areamass", area_weights=1, mass_scaled=1, app_mode=0),
    "x-volmass": _variant("x-volmass", area_weights=0, mass_scaled=1, app_mode=0),
    "x-rgb": _variant("x-rgb", area_weights=0, mass_scaled=0, app_mode=1),
    "x-area-rgb": _variant("x-area-rgb", area_weights=1, mass_scaled=0, app_mode=1),
    "x-areamass-rgb": _variant("x-areamass-rgb", area_weights=1, mass_scaled=1, app_mode=1),
}
