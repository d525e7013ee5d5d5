"""Command-line options shared by ``simplify`` and ``batch``; defaults come from SimplifyConfig.
The paper's configuration: --operator mpmm --cost idiv --prune-opacity 0.1 --k 16."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

# The version of every --json output's layout (docs/json.md): raised when a field changes meaning or goes.
JSON_SCHEMA = 1

Ratio = Annotated[Optional[str], typer.Option(metavar="RATIOS", help="Fraction of the input's splats to keep, in (0, 1]; several as 0.1,0.01,0.001. The output has exactly ceil(ratio x N) splats.")]
Count = Annotated[Optional[str], typer.Option(metavar="COUNTS", help="Number of splats to keep; several as 100000,10000.")]
K = Annotated[
    Optional[int],
    typer.Option("--k", metavar="NEIGHBOURS", show_default=False, help="Neighbours per splat in the candidate graph [default: 24 below 65,536 splats, 16 from there on]."),
]
PruneOpacity = Annotated[float, typer.Option(metavar="OPACITY", help="Prune splats with opacity below min(this, median opacity) first; 0 disables.")]
Samples = Annotated[int, typer.Option(metavar="SAMPLES", help="Monte Carlo samples per edge; used only by --cost idiv (the default cost draws none).")]
Seed = Annotated[int, typer.Option(metavar="SEED", help="Seed of the common random numbers; used only by --cost idiv (the default cost is deterministic).")]
LambdaGeo = Annotated[float, typer.Option(metavar="WEIGHT", help="Weight of the geometric term of the cost: for the default runnalls cost, how much the merged Gaussian's extra volume (Runnalls' bound) counts against a merge; for idiv the I-divergence, for mse the mean and covariance distance.")]
LambdaApp = Annotated[float, typer.Option(metavar="WEIGHT", help="Weight of the appearance term: the colour (SH) difference ||f_i - f_j||^2 of the pair; the default runnalls cost scales it by 4 pi (1 - pi), so absorbing a light splat into a heavy one is cheap.")]
Cost = Annotated[str, typer.Option(metavar="COST", help="Cost objective: runnalls (closed-form mixture-reduction bound), idiv (the paper's Monte Carlo I-divergence) or mse (the paper's ablation surrogate).")]
Operator = Annotated[str, typer.Option(metavar="OPERATOR", help="Merge operator: coverage (keeps the pair's coverage), area (opacity x surface-area weights) or mpmm (the paper's mass-preserving moment matching).")]
DropInvalid = Annotated[bool, typer.Option(help="Drop rows with NaN/Inf values or zero quaternions instead of failing.")]
Json = Annotated[bool, typer.Option("--json", help="Print a machine-readable summary on stdout.")]
Quiet = Annotated[bool, typer.Option("-q", "--quiet", help="Print nothing but errors (and --json).")]
