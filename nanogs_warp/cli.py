"""The ``nanogs-warp`` command: simplify and inspect 3DGS scenes. Only this module knows about paths."""

from __future__ import annotations

import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer

from . import cli_options as opts
from . import __version__
from .budgets import Budget, output_paths, parse_budgets
from .cli_batch import batch_command
from .cli_eval import eval_command
from .cli_errors import examples, readable_placeholders, user_errors
from .errors import InputError, NanogsWarning
from .pipeline import SimplifyConfig

readable_placeholders()
app = typer.Typer(
    name="nanogs-warp",
    help="Make trained 3D Gaussian Splatting scenes 10x-1000x smaller without training images (NanoGS).",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"nanogs-warp {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        Optional[bool], typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = None,
) -> None:
    """nanogs-warp"""


class _PassProgress:
    """One status line on stderr, rewritten each pass; silent unless stderr is a terminal."""

    def __init__(self, enabled: bool, first_target: int):
        self.enabled = enabled
        self.target = first_target

    def __call__(self, report) -> None:
        if self.enabled:
            sys.stderr.write(
                f"\rpass {report.index + 1}: {report.count_before:,} -> {report.count_after:,} splats "
                f"(target {self.target:,})\033[K"
            )
            sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()


@app.command(
    epilog=examples(
        "nanogs-warp simplify scene.ply -o small.ply --ratio 0.01",
        "nanogs-warp simplify scene.ply -o lods/ --ratio 0.1,0.01,0.001   # lods/scene_0.1.ply, ...",
        "nanogs-warp simplify --sample -o plant.ply --count 2000 --device cpu",
    ),
)
@user_errors
def simplify(
    input: Annotated[Optional[Path], typer.Argument(help="Input 3DGS .ply file (or --sample).", show_default=False, metavar="SCENE.PLY")] = None,
    output: Annotated[Optional[str], typer.Option("-o", "--output", help="Output .ply path; with several budgets OUT_<budget>.ply is written for each. A folder (ending in /, or an existing one) receives <input name>_<budget>.ply.", show_default=False, metavar="PATH")] = None,
    ratio: opts.Ratio = None,
    count: opts.Count = None,
    device: Annotated[str, typer.Option(help="auto (first GPU, else CPU), cpu, cuda or cuda:N.", metavar="DEVICE")] = "auto",
    k: opts.K = SimplifyConfig.k,
    prune_opacity: opts.PruneOpacity = SimplifyConfig.prune_opacity,
    samples: opts.Samples = SimplifyConfig.samples,
    seed: opts.Seed = SimplifyConfig.seed,
    lambda_geo: opts.LambdaGeo = SimplifyConfig.lambda_geo,
    lambda_app: opts.LambdaApp = SimplifyConfig.lambda_app,
    cost: opts.Cost = SimplifyConfig.cost,
    operator: opts.Operator = SimplifyConfig.operator,
    drop_invalid: opts.DropInvalid = False,
    sample: Annotated[bool, typer.Option("--sample", help="Use the shipped 20,000-splat sample scene as the input.")] = False,
    overwrite: Annotated[bool, typer.Option("-w", "--overwrite", help="Replace output files that already exist (by default they are an error).")] = False,
    json_output: opts.Json = False,
    quiet: opts.Quiet = False,
) -> None:
    """Simplify a 3DGS scene to one or several budgets in one progressive run."""
    from .device import keep_freed_host_memory, resolve_device
    from .ply import load_ply, save_ply

    config = SimplifyConfig(k, prune_opacity, samples, seed, lambda_geo, lambda_app, cost, operator)
    budgets = parse_budgets(ratio, count)
    input = _input_path(input, sample)
    if output is None:
        raise InputError("give an output path with -o/--output (a .ply file, or a folder ending in /)")
    paths, folder = _output_paths(output, input, budgets)
    _check_outputs(input, list(paths.values()), overwrite, folder)
    target_device = resolve_device(device)
    keep_freed_host_memory()

    started = time.perf_counter()
    splats = load_ply(input, device="cpu", drop_invalid=drop_invalid)
    loaded = time.perf_counter()
    targets = {budget: budget.target(splats.count) for budget in budgets}
    progress = _PassProgress(sys.stderr.isatty() and not quiet and not json_output, max(targets.values()))
    passes = []
    written = []
    budgets_for_target: dict[int, list[Budget]] = {}
    for budget, target in targets.items():
        budgets_for_target.setdefault(target, []).append(budget)
    on_device = splats.to(target_device)
    with warnings.catch_warnings(record=True) as caught:  # the package's own: one line each, below
        warnings.simplefilter("always", NanogsWarning)
        _simplify_and_save(on_device, budgets_for_target, config, paths, passes, progress, loaded, written, save_ply)
    progress.done()
    for warning in caught:
        if not issubclass(warning.category, NanogsWarning):
            warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
        elif not quiet:
            typer.echo(f"nanogs-warp: warning: {warning.message}", err=True)
    finished = time.perf_counter()
    after_prune = passes[0].count_before if passes else (written[0]["count"] if written else splats.count)
    summary = {
        "schema": opts.JSON_SCHEMA,
        "command": "simplify",
        "input": str(input.resolve()),
        "input_count": splats.count,
        "after_prune_count": after_prune,
        "device": str(target_device),
        "settings": _settings(config, after_prune, target_device),
        "passes": len(passes),
        "outputs": written,
        "seconds": {"read": round(loaded - started, 4), "total": round(finished - started, 4)},
    }
    if json_output:
        typer.echo(json.dumps(summary, indent=2))
    elif not quiet:
        for out in written:
            typer.echo(f"{out['path']}: {out['count']:,} splats (budget {out['budget']}, {out['passes']} passes)")
        typer.echo(f"{splats.count:,} splats in, {len(passes)} passes on {target_device}, {finished - started:.2f} s")


def _simplify_and_save(on_device, budgets_for_target, config, paths, passes, progress, loaded, written, save_ply):
    """Runs the progressive merge and writes each budget as it is reached (appending to ``written``)."""
    from .pipeline import simplify_progressively

    on_pass = lambda r: (passes.append(r), progress(r))  # noqa: E731
    for target, result in simplify_progressively(on_device, list(budgets_for_target), config, on_pass=on_pass):
        reached = time.perf_counter()
        for budget in budgets_for_target[target]:
            paths[budget].parent.mkdir(exist_ok=True)  # -o DIR/: created with the first output, not before
            save_ply(result, paths[budget])
            written.append({"path": str(paths[budget].resolve()), "budget": budget.label, "count": result.count,
                            "passes": len(passes), "seconds": round(reached - loaded, 4)})  # fmt: skip
        smaller = [t for t in budgets_for_target if t < target]
        progress.target = max(smaller) if smaller else target


def _settings(config: SimplifyConfig, splat_count: int, device) -> dict:
    """The settings a run used, as --json echoes them: k resolved for the scene's size."""
    settings = dict(vars(config))
    settings["k"] = config.neighbours(splat_count)
    settings["device"] = str(device)
    return settings


def _input_path(input: Path | None, sample: bool) -> Path:
    if sample and input is not None:
        raise InputError("give an input file or --sample, not both")
    if sample:
        from .data import sample_path

        return sample_path()
    if input is None:
        raise InputError("give an input .ply file (or --sample for the shipped sample scene)")
    return input


def _output_paths(output: str, input: Path, budgets: list[Budget]) -> tuple[dict[Budget, Path], Path | None]:
    """The file of each budget, and the folder to write into when -o names one (ends in a separator
    or is an existing directory): FOLDER/<input stem>_<budget>.ply for each budget."""
    if output.endswith(("/", os.sep)) or Path(output).is_dir():
        folder = Path(output)
        return {b: folder / f"{input.stem}_{b.label}.ply" for b in budgets}, folder
    return output_paths(Path(output), budgets), None


def _check_outputs(input: Path, outputs: list[Path], overwrite: bool = False, folder: Path | None = None) -> None:
    """Refuses outputs that would overwrite the input, replace an existing file without
    ``overwrite``, or cannot be written, before any work. ``folder`` (from -o DIR/) may be created:
    its parent must exist."""
    input_resolved = input.resolve()
    if folder is not None and not folder.is_dir():
        if folder.exists():
            raise InputError(f"output {folder} is not a folder")
        if not folder.resolve().parent.is_dir():
            raise InputError(f"output folder {folder} cannot be created: {folder.resolve().parent} does not exist")
    for path in outputs:
        if path.resolve() == input_resolved:
            raise InputError(f"output {path} is the input file; choose another output path")
        parent = path.resolve().parent
        if folder is not None and not folder.is_dir():
            parent = parent.parent  # the folder itself is created
        if not parent.is_dir():
            raise InputError(f"output directory {parent} does not exist")
        if not os.access(parent, os.W_OK):
            raise InputError(f"output directory {parent} is not writable")
        if path.is_dir():
            raise InputError(f"output {path} is a directory")
        if path.exists() and not overwrite:
            raise InputError(f"output {path} already exists; pass --overwrite (-w) to replace it")


@app.command(epilog=examples(
    "nanogs-warp info scene.ply",
    "nanogs-warp info scene.ply --json   # for scripts: see docs/json.md",
))  # fmt: skip
@user_errors
def info(
    input: Annotated[Path, typer.Argument(help="A 3DGS .ply file.", show_default=False, metavar="SCENE.PLY")],
    json_output: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Describe a 3DGS scene: count, SH degree, properties, bounds, opacity and scale statistics."""
    from .info import format_info, scene_info

    details = scene_info(input)
    if json_output:
        details = {"schema": opts.JSON_SCHEMA, "command": "info", "path": str(input.resolve()), **details}
    typer.echo(json.dumps(details, indent=2) if json_output else format_info(details))


app.command("eval", epilog=examples(
    "nanogs-warp eval scene.ply lod_0.1.ply lod_0.01.ply                 # table of PSNR, SSIM, ...",
    "nanogs-warp eval scene.ply lod_0.01.ply --images eval/              # + contact sheets",
    "nanogs-warp eval scene.ply small.ply --cameras cameras.json --json  # the trainer's cameras",
))(user_errors(eval_command))  # fmt: skip
app.command("batch", epilog=examples(
    "nanogs-warp batch scenes/ -o simplified/ --ratio 0.1,0.01,0.001 --devices all",
    "nanogs-warp batch 'captures/**/point_cloud.ply' -o out/ --count 100000 --shard 0/4",
    "nanogs-warp batch manifest.json -o out/ --ray auto --json",
))(user_errors(batch_command))  # fmt: skip


def main() -> None:
    app()
