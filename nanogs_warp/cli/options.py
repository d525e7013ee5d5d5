"""Command-line options shared by ``simplify`` and ``batch``. Method options left unset take the
preset's value (``--preset default``: SimplifyConfig's defaults; ``--preset paper``: the NanoGS
paper's configuration, --operator mpmm --cost idiv --prune-opacity 0.1 --k 16 --pass-fraction 0.5 --median-cost-factor 0)."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from ..refinement.config import MAX_SIZE as MAX_REFINE_SIZE
from ..refinement.config import MIN_SIZE as MIN_REFINE_SIZE
from ..refinement.config import RefineConfig

# The version of every --json output's layout (docs/json.md): raised when a field changes meaning or goes.
JSON_SCHEMA = 1


def json_text(value) -> str:
    """``value`` as every --json output prints it: indented, and JSON itself (which has no NaN or
    infinity: a number that is not finite, such as an infinite PSNR of identical images or the loss
    of a refinement that took no step, is written as null). A file name's bytes that are not UTF-8
    (held by Python as lone surrogates, which strict JSON readers refuse) are written as ``\\xff``."""
    import json
    import math

    def text(v: str) -> str:
        try:
            v.encode("utf-8")
            return v
        except UnicodeEncodeError:
            try:
                return v.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
            except UnicodeEncodeError:  # a surrogate that stands for no byte
                return v.encode("utf-8", "backslashreplace").decode("utf-8")

    def finite(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, str):
            return text(v)
        if isinstance(v, dict):
            return {text(k) if isinstance(k, str) else k: finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        return v

    return json.dumps(finite(value), indent=2, allow_nan=False)


Ratio = Annotated[Optional[str], typer.Option("--ratio", metavar="RATIOS", help="Fraction of the input's splats to keep, in (0, 1]; several as 0.1,0.01,0.001. The output has exactly ceil(ratio x N) splats.")]
Count = Annotated[Optional[str], typer.Option("--count", metavar="COUNTS", help="Number of splats to keep; several as 100000,10000.")]
K = Annotated[
    Optional[int],
    typer.Option("--k", metavar="NEIGHBOURS", show_default=False, help="Neighbours per splat in the candidate graph, 1 to 32 [default: 24 below 65,536 splats, 16 from there on]."),
]
Preset = Annotated[str, typer.Option("--preset", metavar="PRESET", help="Method configuration: default (the measured best), fast (the Runnalls cost, whole matchings and no fits: many times faster on a CPU) or paper (the NanoGS paper's: mpmm, idiv, prune 0.1, k 16); the options below override it.")]
PruneOpacity = Annotated[Optional[float], typer.Option("--prune-opacity", metavar="OPACITY", show_default=False, help="Prune splats with opacity below min(this, median opacity) first; 0 disables [default: 0].")]
Samples = Annotated[Optional[int], typer.Option("--samples", metavar="SAMPLES", show_default=False, help="Monte Carlo samples per edge; used only by --cost idiv (the default cost draws none) [default: 1].")]
Seed = Annotated[Optional[int], typer.Option("--seed", metavar="SEED", show_default=False, help="Seed of the common random numbers of --cost idiv and of the cameras of the size, geometry and colour fits and of --refine (the merging's costs are otherwise deterministic) [default: 0].")]
LambdaGeo = Annotated[Optional[float], typer.Option("--lambda-geo", metavar="WEIGHT", show_default=False, help="Weight of the geometric term of the cost: for the default field cost, the change of the opacity field a merge makes; for runnalls the merged Gaussian's extra volume (Runnalls' bound), for idiv the I-divergence, for mse the mean and covariance distance [default: 1].")]
LambdaApp = Annotated[Optional[float], typer.Option("--lambda-app", metavar="WEIGHT", show_default=False, help="Weight of the appearance term: for the default field cost, the change of the colour field (SH, averaged over view directions); for the other costs the SH difference ||f_i - f_j||^2 (runnalls scales it by 4 pi (1 - pi), so absorbing a light splat into a heavy one is cheap) [default: 1].")]
Cost = Annotated[Optional[str], typer.Option("--cost", metavar="COST", show_default=False, help="Cost objective: field (change of the projected emitted field under the operator's own merge, for mpmm and coverage; default), runnalls (closed-form mixture-reduction bound), idiv (the paper's Monte Carlo I-divergence) or mse (the paper's ablation surrogate).")]
Operator = Annotated[Optional[str], typer.Option("--operator", metavar="OPERATOR", show_default=False, help="Merge operator: coverage (keeps the pair's coverage; default), area (opacity x surface-area weights) or mpmm (the paper's mass-preserving moment matching).")]
PassFraction = Annotated[Optional[float], typer.Option("--pass-fraction", metavar="FRACTION", show_default=False, help="At most this fraction of the splats merges in one pass, the cheapest pairs first, from 0.05 to 0.5; 0.5 takes every pair of the matching, as the paper does (fewer passes, faster) [default: 0.45].")]
MedianCostFactor = Annotated[Optional[float], typer.Option("--median-cost-factor", metavar="FACTOR", show_default=False, help="A pass merges no pair that costs more than FACTOR times the median pair's cost (at least half of its pairs always merge); 0: no limit, as the paper; else at least 1 [default: 3].")]
FitSize = Annotated[Optional[bool], typer.Option("--fit-size/--no-fit-size", show_default=False, help="Scale each output's splats by the one factor whose renders match the input's best at a coarse and a fine pixel size (default; off in the fast and paper presets).")]
FitGeometry = Annotated[Optional[bool], typer.Option("--fit-geometry/--no-fit-geometry", show_default=False, help="Fit the centres, rotations and scales of each output of at most 1 % of the input's splats to renders of the input (40 steps of two views, 125 of eight for outputs of at most 0.1 %; kept only where held-out views render better), after the size fit (default; off in the fast and paper presets).")]
FitColour = Annotated[Optional[bool], typer.Option("--fit-colour/--no-fit-colour", show_default=False, help="Fit the colours of the merged splats of each output above 0.1 % of the input's splats to renders of the input (40 steps; in the 1 % outputs their opacities too; every splat that no merge made keeps its own colour and opacity; kept only where the output then renders the size fit's coarse and fine views better), after the size and geometry fits (default; off in the fast and paper presets).")]
DropInvalid = Annotated[bool, typer.Option(help="Drop rows with NaN/Inf values, zero quaternions or log-scales beyond +-100 instead of failing (says how many and why). Opacity logits of +-Inf (alpha 1 or 0) are valid.")]
Format = Annotated[Optional[str], typer.Option("--format", metavar="FORMAT", show_default=False, help="Output format, whatever the output's name: ply, compressed-ply, spz, sog, splat or lod [default: by the output's name, else ply].")]
ShDegree = Annotated[Optional[int], typer.Option("--sh-degree", metavar="DEGREE", show_default=False, help="Spherical-harmonics degree of the outputs, 0 to 3 (0: the base colour only, the smallest files): each output's higher bands are dropped after the merge, before refinement [default: the input's].")]
Json = Annotated[bool, typer.Option("--json", help="Print a machine-readable summary on stdout.")]
Quiet = Annotated[bool, typer.Option("-q", "--quiet", help="Print nothing but errors (and --json).")]


def check_sh_degree(degree: int | None) -> None:
    if degree is not None and not 0 <= degree <= 3:
        from ..errors import InputError

        raise InputError(f"--sh-degree must be 0, 1, 2 or 3, got {degree}")


def method_config(preset: str, **options):
    """The SimplifyConfig of ``preset`` with every option that was given (not None)."""
    from ..config import SimplifyConfig

    return SimplifyConfig.preset(preset, **{name: value for name, value in options.items() if value is not None})
Refine = Annotated[bool, typer.Option("--refine", help=f"Refine each output toward the input's appearance ({RefineConfig.steps} steps of Adam on renders from training cameras; the count is kept).")]
RefineSteps = Annotated[Optional[int], typer.Option("--refine-steps", help=f"Refinement steps (implies --refine) [default: {RefineConfig.steps}].", show_default=False, metavar="STEPS")]
RefineSizeImplied = Annotated[Optional[int], typer.Option("--refine-size", help=f"Longest side in pixels of the training views of refinement, {MIN_REFINE_SIZE} to {MAX_REFINE_SIZE} (implies --refine) [default: {RefineConfig.size}].", show_default=False, metavar="PIXELS")]
