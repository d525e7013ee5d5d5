"""Cost objectives: score every candidate edge; lower is a better merge.

A cost objective is a callable ``cost(splats, edges, pass_index) -> wp.array(float32)`` of one cost
per edge. Add a new objective by writing its kernel in ``nanogs_warp.kernels.cost`` and a class here,
then naming it in ``COSTS``.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from .kernels import cost as kernels
from .operators import COVERAGE_GROWTH
from .parallel import launch_rows, launch_rows_from
from .splats import SplatSet
from .topology import Edges

# Fewest groups of four edges per CPU worker for the field cost (about 2 microseconds a group).
LANE_GROUPS_TO_SPLIT = 1024


@dataclass(frozen=True)
class IDivergenceCost:
    """lambda_geo * I(p~_ij || q_m) (Monte Carlo, S common samples per pass) + lambda_app * ||f_i - f_j||^2."""

    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        device = splats.device
        common = wp.empty(self.samples, dtype=wp.vec3, device=device)
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
class RunnallsCost:
    """Deterministic, non-negative and mass-aware: W^gamma [lambda_geo B + lambda_app 4 pi (1 - pi)
    ||f_i - f_j||^2] with weights w = alpha x surface-area proxy, W = w_i + w_j, pi = w_i / W and
    B Runnalls' bound on KL(p~_ij || q_m). ``samples`` and ``seed`` are unused (no sampling).

    ``mass_exponent`` (gamma) is fixed at 0.25 and not a command-line option: it is a tuned
    constant of the default configuration, not a knob. W^gamma orders merges of light pairs before
    heavy ones; over the five measured scenes gamma = 0.125 / 0.25 / 0.375 gave 26.39 / 26.63 /
    26.24 dB mean PSNR and gamma = 0 / 0.25 / 0.5 gave 26.49 / 26.76 / 26.56 (docs/quality.md), so
    0.25 is the measured best and both neighbours are worse. A change of the scene's units scales
    every cost by one factor, so the merge order does not depend on them. Python callers may still
    build ``RunnallsCost(mass_exponent=...)`` to experiment (0 is the paper's scale-free form)."""

    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0
    mass_exponent: float = 0.25

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        device = splats.device
        covariances = wp.empty(splats.count, dtype=wp.mat33d, device=device)
        weights = wp.empty(splats.count, dtype=wp.float64, device=device)
        log_dets = wp.empty(splats.count, dtype=wp.float64, device=device)
        launch_rows(
            kernels.runnalls_splat_terms, splats.count,
            lambda rows: [
                splats.rotations[rows], splats.log_scales[rows], splats.opacities[rows], covariances[rows],
                weights[rows], log_dets[rows],
            ],
            device,
        )  # fmt: skip
        costs = wp.empty(edges.count, dtype=wp.float32, device=device)
        launch_rows(
            kernels.runnalls_costs, edges.count,
            lambda rows: [
                edges.i[rows], edges.j[rows], splats.means, covariances, weights, log_dets,
                splats.features, self.lambda_geo, self.lambda_app, self.mass_exponent, costs[rows],
            ],
            device,
        )  # fmt: skip
        return costs


# The field cost's colour contrast weight lambda_c (kernels/field_cost.py): one constant for every
# scene, as the term is in units of the scene's typical splat energy; chosen by leave-one-scene-out
# over the shared and stress scenes (docs/quality.md).
CONTRAST_WEIGHT = 30.0


@dataclass(frozen=True)
class FieldCost:
    """The squared L2 change of the projected emitted field (the pair's opacity field, face-on as a
    renderer composites it, and its colour over view directions) when a pair becomes the merge
    operator's own merged splat, plus a colour contrast term in units of the scene's typical splat
    energy (``kernels/field_cost.py``), reported in a power of two near that energy (so a scene's
    units change no merge). ``operator`` is the pipeline's merge operator (mpmm or coverage);
    ``growth`` the coverage operator's; ``lambda_contrast`` the contrast term's weight (0: the field
    terms alone)."""

    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    samples: int = 1
    seed: int = 0
    operator: str = "coverage"
    growth: float = COVERAGE_GROWTH
    lambda_contrast: float = CONTRAST_WEIGHT

    OPERATOR_IDS = {"mpmm": 0, "coverage": 1}
    ENERGY_CHUNK = 256  # splats summed in order by one thread of log_energy_partials

    def __call__(self, splats: SplatSet, edges: Edges, pass_index: int) -> wp.array:
        from .kernels import field_cost

        device = splats.device
        covariances = wp.empty(splats.count, dtype=wp.mat33d, device=device)
        colour_norms = wp.empty(splats.count, dtype=wp.float64, device=device)
        alphas = wp.empty(splats.count, dtype=wp.float64, device=device)
        log_weights = wp.empty(splats.count, dtype=wp.float64, device=device)
        launch_rows(
            field_cost.splat_terms, splats.count,
            lambda rows: [splats.rotations[rows], splats.log_scales[rows], splats.opacities[rows], splats.features[rows],
                          covariances[rows], colour_norms[rows], alphas[rows], log_weights[rows]],
            device,
        )  # fmt: skip
        energy = reference_energy(splats, self.ENERGY_CHUNK)
        costs = wp.empty(edges.count, dtype=wp.float32, device=device)
        terms = [splats.kernel_view(), covariances, colour_norms, alphas, log_weights, self.OPERATOR_IDS[self.operator],
                 self.growth, self.lambda_geo, self.lambda_app, self.lambda_contrast, energy]  # fmt: skip
        if device.is_cpu:  # four edges a thread, their Jacobi sweeps side by side: the same bits
            launch_rows_from(
                field_cost.field_costs_in_lanes, -(-edges.count // 4), [edges.count, edges.i, edges.j, *terms, costs], device,
                min_rows=LANE_GROUPS_TO_SPLIT,
            )  # fmt: skip
        elif edges.count > 0:
            wp.launch(field_cost.field_costs, edges.count, inputs=[edges.i, edges.j, *terms, costs], device=device)
        return costs


def reference_energy(splats: SplatSet, chunk: int = FieldCost.ENERGY_CHUNK) -> wp.array:
    """E_ref of the field cost's colour contrast term and the unit of its costs, as a two-element
    float64 array on the splats' device (no host round trip): E_ref, the geometric mean of
    a^2 s_a s_b over the splats, summed in a fixed order (``chunk`` splats a thread, then the partial
    sums in order) so every device agrees; then the power of two 2^-e with E_ref in [2^e, 2^(e+1))."""
    from .kernels import field_cost

    device = splats.device
    chunks = max(1, -(-splats.count // chunk))
    partials = wp.empty(chunks, dtype=wp.float64, device=device)
    launch_rows_from(field_cost.log_energy_partials, chunks, [splats.opacities, splats.log_scales, chunk, partials], device, min_rows=64)
    energy = wp.empty(2, dtype=wp.float64, device=device)
    wp.launch(field_cost.reference_energy, 1, inputs=[partials, max(splats.count, 1)], outputs=[energy], device=device)
    return energy


COSTS = {"field": FieldCost, "idiv": IDivergenceCost, "mse": MeanSquaredCost, "runnalls": RunnallsCost}
