"""The ``nanogs-warp`` command: simplify and inspect 3DGS scenes. Only this module knows about paths."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer

from . import cli_options as opts
from . import __version__
from .budgets import Budget, output_paths, parse_budgets
from .cli_batch import batch_command
from .cli_eval import eval_command
from .errors import InputError
from .pipeline import SimplifyConfig

app = typer.Typer(
    name="nanogs-warp",
    help="Make trained 3D Gaussian Splatting scenes 10x-1000x smaller without training images (NanoGS).",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _fail(message: str, code: int) -> None:
    typer.echo(f"nanogs-warp: error: {message}", err=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def quiet_warnings():
    """Python warnings (numpy's floating-point RuntimeWarnings, Warp's) and numpy's floating-point
    error reports silenced for a command, so that stderr holds at most its one error line;
    NANOGS_DEBUG=1 lets them through."""
    if os.environ.get("NANOGS_DEBUG"):
        yield
        return
    import numpy as np

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        yield


def user_errors(command):
    """Turns known errors into one line on stderr and exit code 2; anything else into one line and
    exit code 1 (NANOGS_DEBUG=1 shows the traceback and lets warnings through)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            with quiet_warnings():
                return command(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except InputError as e:
            _fail(str(e), 2)
        except MemoryError:
            _fail("out of memory", 1)
        except Exception as e:  # noqa: BLE001 - the last line of defence for a command-line tool
            if os.environ.get("NANOGS_DEBUG"):
                traceback.print_exc()
            _fail(f"internal error: {type(e).__name__}: {e} (set NANOGS_DEBUG=1 for details)", 1)

    return wrapper


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


@app.command()
@user_errors
def simplify(
    input: Annotated[Path, typer.Argument(help="Input 3DGS .ply file.", show_default=False)],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output .ply path. With several budgets, OUT_<budget>.ply is written for each.", show_default=False)],
    ratio: opts.Ratio = None,
    count: opts.Count = None,
    device: Annotated[str, typer.Option(help="auto (first GPU, else CPU), cpu, cuda or cuda:N.")] = "auto",
    k: opts.K = SimplifyConfig.k,
    prune_opacity: opts.PruneOpacity = SimplifyConfig.prune_opacity,
    samples: opts.Samples = SimplifyConfig.samples,
    seed: opts.Seed = SimplifyConfig.seed,
    lambda_geo: opts.LambdaGeo = SimplifyConfig.lambda_geo,
    lambda_app: opts.LambdaApp = SimplifyConfig.lambda_app,
    cost: opts.Cost = SimplifyConfig.cost,
    operator: opts.Operator = SimplifyConfig.operator,
    drop_invalid: opts.DropInvalid = False,
    json_output: opts.Json = False,
    quiet: opts.Quiet = False,
) -> None:
    """Simplify a 3DGS scene to one or several budgets in one progressive run."""
    from .device import keep_freed_host_memory, resolve_device
    from .pipeline import simplify_progressively
    from .ply import load_ply, save_ply

    config = SimplifyConfig(k, prune_opacity, samples, seed, lambda_geo, lambda_app, cost, operator)
    config.validate()
    budgets = parse_budgets(ratio, count)
    paths = output_paths(output, budgets)
    _check_outputs(input, list(paths.values()))
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
    for target, result in simplify_progressively(on_device, list(budgets_for_target), config, on_pass=lambda r: (passes.append(r), progress(r))):
        reached = time.perf_counter()
        for budget in budgets_for_target[target]:
            save_ply(result, paths[budget])
            written.append({"path": str(paths[budget]), "budget": budget.label, "count": result.count,
                            "passes": len(passes), "seconds": round(reached - loaded, 4)})  # fmt: skip
        smaller = [t for t in budgets_for_target if t < target]
        progress.target = max(smaller) if smaller else target
    progress.done()
    finished = time.perf_counter()
    summary = {
        "input": str(input),
        "input_count": splats.count,
        "after_prune_count": passes[0].count_before if passes else (written[0]["count"] if written else splats.count),
        "device": str(target_device),
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


def _check_outputs(input: Path, outputs: list[Path]) -> None:
    """Refuses outputs that would overwrite the input or cannot be written, before any work."""
    input_resolved = input.resolve()
    for path in outputs:
        if path.resolve() == input_resolved:
            raise InputError(f"output {path} is the input file; choose another output path")
        parent = path.resolve().parent
        if not parent.is_dir():
            raise InputError(f"output directory {parent} does not exist")
        if not os.access(parent, os.W_OK):
            raise InputError(f"output directory {parent} is not writable")
        if path.is_dir():
            raise InputError(f"output {path} is a directory")


@app.command()
@user_errors
def info(
    input: Annotated[Path, typer.Argument(help="A 3DGS .ply file.", show_default=False)],
    json_output: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Describe a 3DGS scene: count, SH degree, properties, bounds, opacity and scale statistics."""
    from .info import format_info, scene_info

    details = scene_info(input)
    typer.echo(json.dumps(details, indent=2) if json_output else format_info(details))


app.command("eval")(user_errors(eval_command))
app.command("batch")(user_errors(batch_command))


def main() -> None:
    app()
