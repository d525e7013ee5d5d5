"""Command-line options shared by ``simplify`` and ``batch``; defaults come from SimplifyConfig.
The paper's configuration: --operator mpmm --cost idiv --prune-opacity 0.1 --k 16."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from .refine import RefineConfig

Ratio = Annotated[Optional[str], typer.Option(help="Fraction of the input's splats to keep, in (0, 1]; several as 0.1,0.01,0.001.")]
Count = Annotated[Optional[str], typer.Option(help="Number of splats to keep; several as 100000,10000.")]
K = Annotated[
    Optional[int],
    typer.Option("--k", show_default=False, help="Neighbours per splat in the candidate graph [default: 24 below 65,536 splats, 16 from there on]."),
]
PruneOpacity = Annotated[float, typer.Option(help="Prune splats with opacity below min(this, median opacity) first; 0 disables.")]
Samples = Annotated[int, typer.Option(help="Monte Carlo samples per edge for the I-divergence.")]
Seed = Annotated[int, typer.Option(help="Seed of the common random numbers.")]
LambdaGeo = Annotated[float, typer.Option(help="Weight of the geometric (I-divergence) cost.")]
LambdaApp = Annotated[float, typer.Option(help="Weight of the appearance cost ||f_i - f_j||^2.")]
Cost = Annotated[str, typer.Option(help="Cost objective: runnalls (closed-form mixture-reduction bound), idiv (the paper's Monte Carlo I-divergence) or mse (the paper's ablation surrogate).")]
Operator = Annotated[str, typer.Option(help="Merge operator: coverage (keeps the pair's coverage), area (opacity x surface-area weights) or mpmm (the paper's mass-preserving moment matching).")]
DropInvalid = Annotated[bool, typer.Option(help="Drop rows with NaN/Inf values or zero quaternions instead of failing.")]
Json = Annotated[bool, typer.Option("--json", help="Print a machine-readable summary on stdout.")]
Quiet = Annotated[bool, typer.Option("-q", "--quiet", help="Print nothing but errors (and --json).")]
Refine = Annotated[bool, typer.Option("--refine", help=f"Refine each output toward the input's appearance ({RefineConfig.steps} steps of Adam on renders from training cameras; the count is kept).")]
RefineSteps = Annotated[Optional[int], typer.Option(help=f"Refinement steps (implies --refine) [default: {RefineConfig.steps}].", show_default=False)]
RefineSize = Annotated[int, typer.Option(help="Longest side in pixels of the training views of refinement.")]
