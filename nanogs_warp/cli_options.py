"""Command-line options shared by ``simplify`` and ``batch``. Method options left unset take the
preset's value (``--preset default``: SimplifyConfig's defaults; ``--preset paper``: the NanoGS
paper's configuration, --operator mpmm --cost idiv --prune-opacity 0.1 --k 16)."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

Ratio = Annotated[Optional[str], typer.Option(help="Fraction of the input's splats to keep, in (0, 1]; several as 0.1,0.01,0.001.")]
Count = Annotated[Optional[str], typer.Option(help="Number of splats to keep; several as 100000,10000.")]
K = Annotated[
    Optional[int],
    typer.Option("--k", show_default=False, help="Neighbours per splat in the candidate graph [default: 24 below 65,536 splats, 16 from there on]."),
]
Preset = Annotated[str, typer.Option(help="Method configuration: default (the measured best) or paper (the NanoGS paper's: mpmm, idiv, prune 0.1, k 16); options below override it.")]
PruneOpacity = Annotated[Optional[float], typer.Option(show_default=False, help="Prune splats with opacity below min(this, median opacity) first; 0 disables [default: 0].")]
Samples = Annotated[Optional[int], typer.Option(show_default=False, help="Monte Carlo samples per edge for the I-divergence [default: 1].")]
Seed = Annotated[Optional[int], typer.Option(show_default=False, help="Seed of the common random numbers [default: 0].")]
LambdaGeo = Annotated[Optional[float], typer.Option(show_default=False, help="Weight of the cost's geometric term (the mixture-reduction bound, I-divergence or field change, by --cost) [default: 1].")]
LambdaApp = Annotated[Optional[float], typer.Option(show_default=False, help="Weight of the cost's appearance term (SH difference; the colour field for --cost field) [default: 1].")]
Cost = Annotated[Optional[str], typer.Option(show_default=False, help="Cost objective: field (change of the projected emitted field under the operator's own merge, for mpmm and coverage; default), runnalls (closed-form mixture-reduction bound), idiv (the paper's Monte Carlo I-divergence) or mse (the paper's ablation surrogate).")]
Operator = Annotated[Optional[str], typer.Option(show_default=False, help="Merge operator: coverage (keeps the pair's coverage; default), area (opacity x surface-area weights) or mpmm (the paper's mass-preserving moment matching).")]
DropInvalid = Annotated[bool, typer.Option(help="Drop rows with NaN/Inf values or zero quaternions instead of failing (says how many and why). Opacity logits of +-Inf (alpha 1 or 0) are valid.")]
Format = Annotated[Optional[str], typer.Option("--format", show_default=False, help="Output format, whatever the output's name: ply, compressed-ply, spz, sog, splat or lod [default: by the output's name, else ply].")]
Json = Annotated[bool, typer.Option("--json", help="Print a machine-readable summary on stdout.")]
Quiet = Annotated[bool, typer.Option("-q", "--quiet", help="Print nothing but errors (and --json).")]


def method_config(preset: str, **options):
    """The SimplifyConfig of ``preset`` with every option that was given (not None)."""
    from .pipeline import SimplifyConfig

    return SimplifyConfig.preset(preset, **{name: value for name, value in options.items() if value is not None})
