"""``nanogs-warp batch``: simplify many scenes to several budgets each, on every local GPU, a
Slurm array (``--shard``) or a Ray cluster (``--ray``), resumably.

Registered in ``app.py`` as ``app.command("batch")(user_errors(batch_command))``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import InputError
from ..folders import writable_folder
from ..refinement.config import RefineConfig
from . import options as opts


# The longest --scene-timeout: 11.6 days (the workers' waits take milliseconds in a 32-bit integer, 24.8 days).
MAX_SCENE_TIMEOUT = 1e6


def parse_workers(text: str) -> int | None:
    """``--workers``: ``auto`` -> None (``gpu_workers.auto_workers`` decides), else a whole count >= 1."""
    value = text.strip().lower()
    if value == "auto":
        return None
    if not (value.isascii() and value.isdigit()) or int(value) < 1:
        raise InputError(f"--workers must be auto or a whole number of at least 1, got {text!r}")
    return int(value)


def batch_command(
    input: Annotated[str, typer.Argument(metavar="INPUT", help="A directory (every .ply, .spz, .sog and .splat below it), a glob pattern such as 'scenes/**/point_cloud.ply' (quote it), or a manifest: one path per line, or a JSON list of paths or {\"path\": ..., \"ratio\"/\"count\"/<option>: ...} objects.", show_default=False)],
    output: Annotated[str, typer.Option("-o", "--output", metavar="DIRECTORY", help="Output directory: OUTPUT/<path below the input root>/<stem>_<budget>.<ext of --format>, and <stem>.nanogs.json records for resuming.", show_default=False)],
    ratio: opts.Ratio = None,
    count: opts.Count = None,
    devices: Annotated[str, typer.Option("--devices", help="auto (every GPU, else the CPU), all (every GPU), cpu, all,cpu (every GPU and the CPU), or a list such as cuda:0,cuda:1; --workers sets the worker processes on each. With --ray: cpu asks for CPU tasks, cuda/all for GPU tasks, auto for GPU tasks when the cluster has GPUs.", metavar="DEVICES")] = "auto",
    workers: Annotated[str, typer.Option("--workers", help="Worker processes per device: auto (two on a GPU whose memory holds two of the batch's largest scene, when every input is a plain PLY, six under MPS; one otherwise, and on the CPU) or a count (e.g. several on the CPU).", metavar="WORKERS")] = "auto",
    mps: Annotated[bool, typer.Option("--mps", help="Run the GPU workers under CUDA MPS, so that their kernels share each GPU at once instead of in turns (about twice the scenes a second on a GPU): an MPS control daemon already running is used, else one is started for this batch and stopped at its end.")] = False,
    readers: Annotated[Optional[int], typer.Option("--readers", metavar="N", help="Threads per worker that read, check and hash each input file while the device works on the previous scene. [default: the CPU cores shared out among the workers, 1 to 8]", show_default=False)] = None,
    shard: Annotated[Optional[str], typer.Option("--shard", help="Only scenes i, i+n, i+2n, ... of the sorted list, as i/n (0-based), e.g. $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT.", show_default=False, metavar="SHARD")] = None,
    ray: Annotated[Optional[str], typer.Option("--ray", help="Run each scene as a Ray task: auto (the cluster this machine belongs to), local (a Ray instance started here) or the head's ADDRESS. Needs Ray (pip install 'ray>=2.9').", show_default=False, metavar="RAY")] = None,
    scene_timeout: Annotated[Optional[float], typer.Option("--scene-timeout", metavar="SECONDS", help="Time limit per scene; a scene past it fails and its worker process is replaced. 0: no limit. [default: 300 s plus 0.1 s per MB of input on a GPU, 0.5 s per MB on the CPU]", show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Redo every scene, even those whose outputs and record are up to date.")] = False,
    preset: opts.Preset = "default",
    k: opts.K = None,
    prune_opacity: opts.PruneOpacity = None,
    samples: opts.Samples = None,
    seed: opts.Seed = None,
    lambda_geo: opts.LambdaGeo = None,
    lambda_app: opts.LambdaApp = None,
    cost: opts.Cost = None,
    operator: opts.Operator = None,
    pass_fraction: opts.PassFraction = None,
    median_cost_factor: opts.MedianCostFactor = None,
    fit_size: opts.FitSize = None,
    fit_geometry: opts.FitGeometry = None,
    fit_colour: opts.FitColour = None,
    drop_invalid: Annotated[bool, typer.Option(help="Drop rows with NaN/Inf values, zero quaternions or log-scales beyond +-100 instead of failing the scene.")] = False,
    refine: opts.Refine = False,
    refine_steps: opts.RefineSteps = None,
    refine_size: opts.RefineSizeImplied = None,
    output_format: Annotated[Optional[str], typer.Option("--format", show_default=False, metavar="OUTPUT_FORMAT", help="Output format: ply (default), compressed-ply, spz, sog or splat.")] = None,
    sh_degree: opts.ShDegree = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="List the scenes (of this shard) and what a run would do with each: simplify it (and why), skip it as up to date, or fail; records are read and inputs hashed as a run does, the devices are not checked, nothing is written.")] = False,
    json_output: Annotated[bool, typer.Option("--json", help="Print a machine-readable summary (one entry per scene) on stdout instead of the table.")] = False,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No progress and no table; only errors (and --json).")] = False,
) -> None:
    """Simplify many scenes to every budget (one progressive run each) on all local GPUs, a shard
    of a Slurm array, or a Ray cluster. Finished scenes are skipped when run again; one failing
    scene is reported and the others go on (exit code 1 if any failed)."""
    from ..batch.run import BatchProgress, find_scenes, format_summary, parse_shard, plan_batch, run_batch, select_shard, summary_json
    from ..batch.scenes import OUTPUT_SUFFIXES, SceneDefaults, scenes_left_out
    from ..budgets import parse_budgets

    started = time.perf_counter()
    method_options = dict(
        k=k, prune_opacity=prune_opacity, samples=samples, seed=seed, lambda_geo=lambda_geo, lambda_app=lambda_app,
        cost=cost, operator=operator, pass_fraction=pass_fraction, median_cost_factor=median_cost_factor, fit_size=fit_size,
        fit_geometry=fit_geometry, fit_colour=fit_colour,
    )  # fmt: skip
    config = opts.method_config(preset, **method_options)
    config.validate()
    opts.check_sh_degree(sh_degree)
    budgets = parse_budgets(ratio, count) if ratio is not None or count is not None else None
    shard_index, shard_count = parse_shard(shard)
    if scene_timeout is not None and not (0 <= scene_timeout <= MAX_SCENE_TIMEOUT):  # NaN too
        raise InputError(f"--scene-timeout must be 0 (no limit) to {MAX_SCENE_TIMEOUT:g} seconds, got {scene_timeout}")
    workers_per_device = parse_workers(workers)
    if readers is not None and readers < 1:
        raise InputError(f"--readers must be at least 1, got {readers}")
    if not output.strip():
        raise InputError("give an output directory with -o/--output")
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise InputError(f"--output {output} is not a directory")

    fmt = output_format or "ply"
    if fmt not in OUTPUT_SUFFIXES:
        raise InputError(f"--format {fmt!r}: batch writes one of {', '.join(OUTPUT_SUFFIXES)}")
    size = RefineConfig.size if refine_size is None else refine_size
    refine_config = RefineConfig(steps=0, size=size)  # a scene of a manifest may still ask for steps
    if refine or refine_steps is not None or refine_size is not None:
        refine_config = RefineConfig(steps=RefineConfig.steps if refine_steps is None else refine_steps, size=size)
        refine_config.validate()
    defaults = SceneDefaults(
        tuple((name, value) for name, value in method_options.items() if value is not None),
        sh_degree, refine_config.steps, refine_config.size,
    )  # fmt: skip
    jobs = find_scenes(input, output, budgets, config, drop_invalid, fmt, defaults)
    left_out = scenes_left_out(input, output, jobs)
    if left_out and not quiet:
        typer.echo(f"nanogs-warp: warning: {len(left_out)} scene file(s) inside the output folder {output} left out "
                   f"(it lies inside {input}; e.g. {left_out[0]}): give an output folder outside the scenes to simplify them", err=True)  # fmt: skip
    selected = select_shard(jobs, shard_index, shard_count)
    if dry_run:
        _print_plan(plan_batch(selected, force), output, (shard_index, shard_count), json_output)
        return
    device_list, ray_gpu = None, None
    if ray is not None:
        from ..batch.ray_cluster import import_ray

        import_ray()  # fails here, with one line, when Ray is missing
        ray_gpu = None if devices.strip().lower() == "auto" else devices.strip().lower() != "cpu"
    else:
        from ..batch.local import parse_devices

        device_list = parse_devices(devices)
        if mps and device_list == ["cpu"]:
            raise InputError("--mps shares a GPU among its workers; --devices names none")
    if mps and ray is not None:
        raise InputError("--mps is for this machine's workers; a Ray cluster's GPUs run one task each")
    made_here = _missing_folders(output, [job.out_dir for job in selected])
    writable_folder(output, f"--output {output}")

    progress = BatchProgress(len(selected), quiet=quiet)
    if shard_count > 1 and not quiet:
        typer.echo(f"nanogs-warp batch: shard {shard_index}/{shard_count}: {len(selected)} of {len(jobs)} scenes", err=True)
    try:
        results = run_batch(selected, device_list, workers_per_device, ray, ray_gpu, force, progress, scene_timeout, readers, mps)
    finally:  # a signal or Ctrl-C too: the empty folders this run made went with it
        if shard_count == 1:  # every worker was this run's and has ended: nothing else writes there now
            _remove_empty(made_here)
    seconds = time.perf_counter() - started
    if json_output:
        summary = summary_json(results, seconds, (shard_index, shard_count))
        for scene in summary["scenes"]:  # full paths, as every --json output
            scene["input"] = os.path.abspath(scene["input"])
            for out in scene["outputs"]:
                out["path"] = os.path.abspath(out["path"])
        settings = {**vars(config), "devices": devices, "workers": "auto" if workers_per_device is None else workers_per_device, "readers": readers, "ray": ray, "mps": mps, "drop_invalid": drop_invalid}
        if sh_degree is not None:
            settings["sh_degree"] = sh_degree
        summary = {"schema": opts.JSON_SCHEMA, "command": "batch", "output": os.path.abspath(output), "settings": settings, **summary}
        typer.echo(opts.json_text(summary))
    elif not quiet:
        typer.echo(format_summary(results, seconds))
    sys.stdout.flush()
    if any(r.status == "failed" for r in results):
        raise typer.Exit(1)


def _print_plan(plan: list[dict], output: Path, shard: tuple[int, int], json_output: bool) -> None:
    from ..batch.run import format_plan

    if json_output:
        for scene in plan:  # full paths, as every --json output
            scene["input"] = os.path.abspath(scene["input"])
            scene["outputs"] = [os.path.abspath(path) for path in scene["outputs"]]
        totals = {action: sum(p["action"] == action for p in plan) for action in ("run", "skip", "fail")}
        typer.echo(opts.json_text({"schema": opts.JSON_SCHEMA, "command": "batch", "dry_run": True, "output": os.path.abspath(output),
                                   "shard": f"{shard[0]}/{shard[1]}", "scenes": plan, **totals}))  # fmt: skip
    else:
        typer.echo(format_plan(plan))


def _missing_folders(root: Path, folders: list[Path]) -> list[Path]:
    """The folders that do not exist yet among ``folders`` (below ``root``), ``root`` and all the
    folders above each of them, up to the first that exists."""
    missing = set()
    for folder in {root, *folders}:
        while not folder.exists() and folder not in missing:
            missing.add(folder)
            folder = folder.parent
    return sorted(missing)


def _remove_empty(folders: list[Path]) -> None:
    """Removes those of ``folders`` (made by this run) that its failed scenes left empty, deepest first."""
    for folder in sorted(folders, key=lambda f: len(f.parts), reverse=True):
        try:
            folder.rmdir()  # only an empty one
        except OSError:
            pass


def main() -> None:
    """``python -m nanogs_warp.cli.batch``: the batch command on its own (as ``nanogs-warp batch``)."""
    from .errors import one_line_usage_errors, user_errors

    one_line_usage_errors()
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, rich_markup_mode=None,
                      context_settings={"help_option_names": ["-h", "--help"]})  # fmt: skip
    app.command("batch")(user_errors(batch_command))
    app(prog_name="nanogs-warp batch")


if __name__ == "__main__":
    main()
