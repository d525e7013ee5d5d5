"""The ``nanogs-warp`` command (``main``) and its ``simplify``; the other commands have a module each
in this package, the only one that knows about paths, terminals and exit codes."""

from __future__ import annotations

import contextlib
import errno
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from .. import __version__
from ..budgets import Budget, output_paths, parse_budgets
from ..errors import InputError, package_warnings
from ..refinement.config import RefineConfig
from . import options as opts
from .batch import batch_command
from .errors import examples, one_line_usage_errors, readable_placeholders, user_errors
from .eval import eval_command
from .info import info_command
from .warmup import warmup_command

readable_placeholders()
one_line_usage_errors()
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
    ctx: typer.Context,
    version: Annotated[
        Optional[bool], typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = None,
) -> None:
    """nanogs-warp"""
    if ctx.invoked_subcommand != "simplify":  # simplify does this after its own imports
        from .gc_pause import imports_done

        imports_done()


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
    input: Annotated[Optional[Path], typer.Argument(help="Input scene (or --sample): INRIA or compressed .ply, .spz, .sog, meta.json, lod-meta.json or .splat.", show_default=False, metavar="SCENE")] = None,
    output: Annotated[Optional[str], typer.Option("-o", "--output", help="Output path; its name picks the format (.ply, .compressed.ply, .spz, .sog, meta.json, .splat, lod-meta.json). With several budgets OUT_<budget>.<ext> is written for each (a name without an extension takes --format's; an unbundled SOG, meta.json, holds one budget); lod-meta.json writes them as one level-of-detail set. A folder (ending in /, or an existing one) receives <input name>_<budget>.ply (or --format's extension).", show_default=False, metavar="PATH")] = None,
    ratio: opts.Ratio = None,
    count: opts.Count = None,
    device: Annotated[str, typer.Option("--device", help="auto (first GPU, else CPU), cpu, cuda or cuda:N.", metavar="DEVICE")] = "auto",
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
    drop_invalid: opts.DropInvalid = False,
    refine: opts.Refine = False,
    refine_steps: opts.RefineSteps = None,
    refine_size: opts.RefineSizeImplied = None,
    output_format: opts.Format = None,
    sh_degree: opts.ShDegree = None,
    sample: Annotated[bool, typer.Option("--sample", help="Use the shipped 20,000-splat sample scene as the input.")] = False,
    overwrite: Annotated[bool, typer.Option("-w", "--overwrite", help="Replace output files that already exist (by default they are an error).")] = False,
    json_output: opts.Json = False,
    quiet: opts.Quiet = False,
) -> None:
    """Simplify a 3DGS scene to one or several budgets in one progressive run."""
    from ..device import WarpStart, keep_freed_host_memory, process_age
    from ..io import check_output_name, format_for_path, input_files, output_files, read_any_splats, save_levels
    from ..io.ply_write import OutputSet
    from ..io.ply import splats_from_host
    from ..io.row_upload import RowUpload

    config = opts.method_config(
        preset, k=k, prune_opacity=prune_opacity, samples=samples, seed=seed, lambda_geo=lambda_geo,
        lambda_app=lambda_app, cost=cost, operator=operator, pass_fraction=pass_fraction,
        median_cost_factor=median_cost_factor, fit_size=fit_size, fit_geometry=fit_geometry,
        fit_colour=fit_colour,
    )
    config.validate()  # before anything is started or read
    opts.check_sh_degree(sh_degree)
    refine_config = None
    if refine or refine_steps is not None or refine_size is not None:
        refine_config = RefineConfig(steps=RefineConfig.steps if refine_steps is None else refine_steps,
                                     size=RefineConfig.size if refine_size is None else refine_size, seed=config.seed)  # fmt: skip
        refine_config.validate()
    budgets = parse_budgets(ratio, count)
    input = _input_path(input, sample)
    if output is None or not output.strip():
        raise InputError("give an output path with -o/--output (a file, or a folder ending in /)")
    fmt = format_for_path(output, output_format)
    lod_set = fmt == "lod"
    if lod_set and (output.endswith(("/", os.sep)) or _is_folder(output)):  # a folder, made if new (as -o DIR/ is)
        output = str(Path(output) / "lod-meta.json")
    elif lod_set:  # the set's file is lod-meta.json, whatever case the name was given in
        if Path(output).name.lower() != "lod-meta.json":  # never a file of another name, nor one nobody named
            raise InputError(f"{Path(output).name}: --format lod writes a level-of-detail set as lod-meta.json beside "
                             "its levels; name the output lod-meta.json or give a folder")  # fmt: skip
        output = str(Path(output).with_name("lod-meta.json"))
    if fmt == "sog" and Path(output).suffix.lower() == ".json" and len(budgets) > 1:
        raise InputError(f"{Path(output).name}: several budgets cannot share one unbundled SOG folder; "
                         "write .sog files or a lod-meta.json set")  # fmt: skip
    if lod_set:
        paths, folder = {b: Path(output) for b in budgets}, None
    else:
        paths, folder = _output_paths(output, input, budgets, output_format)
    if folder is None and (lod_set or fmt == "sog" and Path(output).suffix.lower() == ".json"):
        folder = Path(output).parent  # a set of files in a folder of its own: made as -o DIR/ makes one
    for path in paths.values():
        check_output_name(path, fmt)
    written = [f for p in dict.fromkeys(paths.values()) for f in output_files(p, fmt, len(budgets) if lod_set else 1)]
    _check_outputs(input, list(paths.values()), written, overwrite, folder)
    from ..io.ply_write import remove_stale_temporaries

    remove_stale_temporaries(written)  # what runs of these outputs killed on this machine left
    keep_freed_host_memory()
    notes = _Notes(quiet or json_output)

    started = time.perf_counter()
    stages: dict[str, float] = {}
    age = process_age()
    if age is not None:
        stages["start"] = age  # process start to here: the interpreter and the imports
    from ..kernel_cache import REFINE_MODULES, simplify_modules

    # Warp and the kernel definitions are imported first, on this thread: that is Python work, and
    # beside the read (which needs the interpreter between its copies) each slowed the other. What
    # runs outside the interpreter, the device's start and the kernel binaries' load, then goes on
    # on another thread while the file is read.
    modules = simplify_modules(config) + (REFINE_MODULES if refine_config else ())
    from .. import pipeline  # noqa: F401 - Warp and the kernel definitions
    from .gc_pause import imports_done

    imports_done()  # the garbage collector, paused by the console script for the imports, runs again
    stages["warp_import"] = time.perf_counter() - started
    warp_start = WarpStart(device, modules=modules, announce=not quiet)
    upload = RowUpload(warp_start.resolved_device)  # a binary PLY's rows go to the GPU as they are read
    try:
        read_begun = time.perf_counter()
        arrays, layout = read_any_splats(input, drop_invalid=drop_invalid, on_drop=notes, upload=upload)
        read_done = time.perf_counter()
        stages["read"] = read_done - read_begun
        target_device = warp_start.device()
    except BaseException:
        upload.cancel()
        warp_start.wait()
        raise
    loaded = time.perf_counter()
    stages["warp_wait"] = loaded - read_done  # what the read did not hide of Warp's start
    stages.update(warp_start.stages)
    uploaded = upload.splats(arrays, layout)
    splats = uploaded if uploaded is not None else splats_from_host(arrays, layout)
    # On a GPU the read's host arrays are freed here (the upload let go of them): malloc keeps
    # that memory (keep_freed_host_memory), and each result's copy back to the host reuses its
    # pages, already mapped, instead of faulting in new ones.
    del arrays
    targets = {budget: budget.target(splats.count) for budget in budgets}
    progress = _PassProgress(sys.stderr.isatty() and not quiet and not json_output, max(targets.values()))
    passes = []
    written = []
    levels = [] if lod_set else None
    budgets_for_target: dict[int, list[Budget]] = {}
    for budget, target in targets.items():
        budgets_for_target.setdefault(target, []).append(budget)
    on_device = splats.to(target_device)
    if not target_device.is_cpu:
        import warp as wp

        wp.synchronize_device(target_device)
    stages["upload"] = time.perf_counter() - loaded
    # The outputs are written on another thread while the next budget is simplified, under
    # temporary names: they appear together once the last is written, or not at all.
    outputs = OutputSet(overwrite, keep=input_files(input))  # an older LOD set's levels go, never the input's files
    writer = _Writer()
    try:
        try:
            with package_warnings(notes):  # on stderr unless silenced, and in the --json summary's notes
                _simplify_and_save(on_device, budgets_for_target, config, paths, passes, progress, loaded, written, fmt, notes,
                                   levels, refine_config, writer, stages, overwrite, outputs, sh_degree)  # fmt: skip
            writer.finish(stages)
        finally:
            writer.close()  # every write started has ended: none stages a file after a discard
        progress.done()
        if lod_set:  # level 0 is the finest: the largest budget, reached first
            for level, out in enumerate(written):
                out["level"] = level
            save_levels(levels, Path(output), fmt, on_loss=notes, overwrite=overwrite, outputs=outputs)
        outputs.publish()
    except BaseException:
        outputs.discard()
        raise
    finished = time.perf_counter()
    if not lod_set:  # reached largest first; listed as given (a set's by level, finest first)
        labels = [budget.label for budget in budgets]
        written.sort(key=lambda out: labels.index(out["budget"]))
    after_prune = passes[0].count_before if passes else (written[0]["count"] if written else splats.count)
    summary = {
        "schema": opts.JSON_SCHEMA,
        "command": "simplify",
        "input": str(input.resolve()),
        "input_count": splats.count,
        "after_prune_count": after_prune,
        "device": str(target_device),
        "settings": _settings(config, after_prune, target_device, None if sh_degree is None else min(sh_degree, splats.sh_degree)),
        "passes": len(passes),
        "outputs": written,
        "notes": notes.lines,
        "seconds": {"read": round(loaded - started, 4), "total": round(finished - started, 4),
                    "stages": {name: round(seconds, 4) for name, seconds in stages.items()}},
    }
    if json_output:
        typer.echo(opts.json_text(summary))
    elif not quiet:
        for out in written:
            level = f", level {out['level']}" if "level" in out else ""
            typer.echo(f"{out['path']}: {out['count']:,} splats (budget {out['budget']}{level}, {out['passes']} passes)")
            if "refine" in out:
                r = out["refine"]
                typer.echo(
                    f"  refined: {r['steps']} steps, training loss {r['loss_before']:.5f} -> {r['loss_after']:.5f}, "
                    f"held-out {r['validation_before']:.5f} -> {r['validation_after']:.5f} (step {r['kept_step']} kept), {r['seconds']:.2f} s"
                )
        typer.echo(f"{splats.count:,} splats in, {len(passes)} passes on {target_device}, {finished - started:.2f} s")


class _Notes:
    """Warnings that are not errors (rows dropped on load, what an output format cannot hold):
    each distinct one once on stderr (unless silenced), all kept for the --json summary."""

    def __init__(self, silent: bool):
        self.silent = silent
        self.lines: list[str] = []
        self._seen: set[str] = set()

    def __call__(self, line: str) -> None:
        self.lines.append(line)
        what = line.split(": ", 1)[-1]  # the same loss for every budget's file: said once
        if what not in self._seen and not self.silent:
            typer.echo(f"nanogs-warp: warning: {line}", err=True)
        self._seen.add(what)


class _Writer:
    """Writes outputs in turn on one background thread; its clock: ``write`` (seconds spent
    writing) and ``write_wait`` (the caller waiting for the writes at the end)."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(1, thread_name_prefix="nanogs-write")
        self.pending: list = []
        self.seconds = 0.0

    def submit(self, write) -> None:
        for future in [f for f in self.pending if f.done()]:  # an error shows as soon as it is seen
            self.pending.remove(future)
            future.result()
        self.pending.append(self.pool.submit(self._timed, write))

    def _timed(self, write) -> None:
        begun = time.perf_counter()
        write()
        self.seconds += time.perf_counter() - begun

    def finish(self, stages: dict) -> None:
        begun = time.perf_counter()
        for future in self.pending:
            future.result()
        self.pending = []
        stages["write"] = self.seconds
        stages["write_wait"] = time.perf_counter() - begun

    def close(self) -> None:
        self.pool.shutdown(wait=True)


def _simplify_and_save(on_device, budgets_for_target, config, paths, passes, progress, loaded, written, fmt, notes, levels,
                       refine_config, writer, stages, overwrite, outputs, sh_degree=None):  # fmt: skip
    """Runs the progressive merge and writes each budget as it is reached (appending to ``written``);
    for a level-of-detail set (``levels`` a list) keeps each level on the host instead. With
    ``refine_config``, each budget's result is refined toward the input first. Each result comes
    to the host here (``stages["download"]``) and is handed to ``writer``, which stages its files
    in ``outputs`` (an ``OutputSet``: the caller publishes them). Without ``overwrite`` a file
    that appeared at an output's path since it was checked stays, and the publishing fails.
    ``sh_degree``: each output's bands above it are dropped after the merge and the size fit,
    before refinement (which then compares the output as it will be written with the input)."""
    from ..io import save_splats
    from ..pipeline import simplify_progressively
    from ..refinement.size_fit import size_fit_for

    stages.setdefault("download", 0.0)
    on_pass = lambda r: (passes.append(r), progress(r))  # noqa: E731
    size_fit = size_fit_for(on_device, config)
    views = None  # the input's renders that refinement trains on: made once, shared by every budget
    if refine_config is not None:
        from ..refinement.refine import ReferenceViews

        views = ReferenceViews(on_device, refine_config)  # refuses an impossible refinement before the merge
    for target, result in simplify_progressively(on_device, list(budgets_for_target), config, on_pass=on_pass, finish=size_fit):
        reached = time.perf_counter()
        report = None
        if sh_degree is not None:
            result = result.with_sh_degree(sh_degree)
        if refine_config is not None:
            progress.done()
            result, report = _refine(result, on_device, refine_config, progress.enabled, views)
        begun = time.perf_counter()
        host = result.to("cpu")
        stages["download"] += time.perf_counter() - begun
        for budget in budgets_for_target[target]:
            outputs.make_folder(paths[budget].parent)  # -o DIR/: made with the first output, not before
            if levels is not None:
                levels.append(host)
            else:
                writer.submit(lambda host=host, path=paths[budget]: save_splats(host, path, fmt, on_loss=notes, overwrite=overwrite,
                                                                                outputs=outputs))  # fmt: skip
            written.append({"path": str(paths[budget].resolve()), "budget": budget.label, "count": result.count,
                            "passes": len(passes), "seconds": round(reached - loaded, 4)})  # fmt: skip
            if size_fit is not None and size_fit.applies(result.count):
                if size_fit.size:
                    written[-1]["size_factor"] = round(size_fit.factors[result.count], 6)
                if size_fit.applies_geometry(result.count):
                    written[-1]["geometry_fit"] = size_fit.geometry_kept.get(result.count, False)
                if size_fit.applies_colour(result.count):
                    written[-1]["colour_fit"] = size_fit.colour_kept.get(result.count, False)
            if report is not None:
                written[-1]["refine"] = report.to_json()
        smaller = [t for t in budgets_for_target if t < target]
        progress.target = max(smaller) if smaller else target
    stages["simplify"] = time.perf_counter() - loaded - stages.get("upload", 0.0) - stages["download"]


def _refine(result, reference, config: RefineConfig, show_progress: bool, views=None):
    """``result`` refined toward ``reference`` (with the shared ``views`` of it), with a progress line
    on stderr when asked."""
    from ..refinement.refine import refine_with_report

    def on_step(step: int, steps: int) -> None:
        if step == steps or step % max(1, steps // 100) == 0:
            sys.stderr.write(f"\rrefine {result.count:,} splats: step {step}/{steps}\033[K")
            sys.stderr.flush()

    refined, report = refine_with_report(result, reference, config, on_step=on_step if show_progress else None, views=views)
    if show_progress:
        sys.stderr.write("\r\033[K")
        sys.stderr.flush()
    return refined, report


def _settings(config, splat_count: int, device, sh_degree: int | None = None) -> dict:
    """The settings a run used, as --json echoes them: k resolved for the scene's size."""
    settings = dict(vars(config))
    settings["k"] = config.neighbours(splat_count)
    settings["device"] = str(device)
    if sh_degree is not None:
        settings["sh_degree"] = sh_degree
    return settings


def _input_path(input: Path | None, sample: bool) -> Path:
    if sample and input is not None:
        raise InputError("give an input file or --sample, not both")
    if sample:
        from ..data import sample_path

        return sample_path()
    if input is None:
        raise InputError("give an input .ply file (or --sample for the shipped sample scene)")
    return input


# The file extension of each output format, for -o DIR/.
_EXTENSIONS = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog", "splat": ".splat"}


def _output_paths(output: str, input: Path, budgets: list[Budget], output_format: str | None) -> tuple[dict[Budget, Path], Path | None]:
    """The file of each budget, and the folder to write into when -o names one (ends in a separator
    or is an existing directory): FOLDER/<input stem>_<budget><ext> for each budget, the extension
    of --format (.ply without it)."""
    if output.endswith(("/", os.sep)) or _is_folder(output):
        folder = Path(output)
        ext = _EXTENSIONS.get(output_format or "ply", ".ply")
        compressed = input.name.lower().endswith(".compressed.ply")  # one suffix in two parts: a.b.compressed.ply is a.b's
        stem = input.name[: -len(".compressed.ply")] if compressed else input.stem
        return {b: folder / f"{stem}_{b.label}{ext}" for b in budgets}, folder
    return output_paths(Path(output), budgets, _EXTENSIONS.get(output_format or "ply", ".ply")), None


def _is_folder(path: str) -> bool:
    """Whether ``path`` names an existing folder (False for a name too long to be one)."""
    try:
        return Path(path).is_dir()
    except OSError:
        return False


def _not_a_folder(path: Path) -> str:
    """Why ``path``, no folder, cannot hold outputs: it is a file, or nothing."""
    return f"{path} is not a folder" if path.exists() else f"{path} does not exist"


def _check_outputs(input: Path, outputs: list[Path], written: list[Path], overwrite: bool = False,
                   folder: Path | None = None) -> None:  # fmt: skip
    """Refuses outputs that would overwrite the input, replace an existing file without
    ``overwrite``, or cannot be written, before any work. ``outputs``: the paths named; ``written``:
    every file they consist of (themselves, or an unbundled SOG's images, a level-of-detail set's
    levels besides), none of which may be one of the input's files, exist without ``overwrite``,
    or exist as anything but a regular file. ``folder`` (from -o DIR/) may be created: its parent
    must exist."""
    from ..file_identity import file_identity
    from ..io import input_files
    from ..io.open_file import open_regular

    from ..io.ply_write import check_name_length

    for path in written:  # written beside a temporary ".<name>.<pid>-<12 hex>.tmp"
        check_name_length(path)
    if not input.exists():  # a missing input is the error to report, not an output named like it
        open_regular(input).close()  # says why in one line
    try:
        input_paths = input_files(input)
    except OSError:
        open_regular(input).close()  # says why in one line
        raise
    inputs = {Path(os.path.realpath(p)) for p in input_paths}  # never raises: a member's link loop is the read's to report
    # by identity, the input is the same file whatever path reaches it (a folder mounted twice, a link)
    input_id = file_identity(input)
    input_ids = {file_identity(p) for p in input_paths} - {None}

    def resolved(path: Path) -> Path:
        try:
            return path.resolve()
        except RuntimeError:  # a loop of symbolic links (an OSError from Python 3.13, which names the path)
            raise InputError(f"output {path}: too many levels of symbolic links") from None

    if folder is not None and not folder.is_dir():
        if folder.exists():
            raise InputError(f"output {folder} is not a folder")
        if not resolved(folder).parent.is_dir():
            raise InputError(f"output folder {folder} cannot be created: {_not_a_folder(resolved(folder).parent)}")
    for path in outputs:
        if input_id is not None and file_identity(path) == input_id:
            raise InputError(f"output {path} is the input file; choose another output path")
        parent = resolved(path).parent
        if folder is not None and not folder.is_dir():
            parent = parent.parent  # the folder itself is created
        if not parent.is_dir():
            raise InputError(f"output directory {_not_a_folder(parent)}")
        if not os.access(parent, os.W_OK):
            raise InputError(f"output directory {parent} is not writable")
        if path.is_dir():
            raise InputError(f"output {path} is a directory")
    for path in written:
        if resolved(path) in inputs or file_identity(path) in input_ids:
            raise InputError(f"output {path} is one of the input's files; choose another output path")
        if path.exists() and not path.is_file():  # -w never replaces a device, a FIFO or a socket
            raise InputError(f"output {path} exists and is not a regular file; choose another output path")
        if path.exists() and not overwrite:
            raise InputError(f"output {path} already exists; pass --overwrite (-w) to replace it")


app.command("info", epilog=examples(
    "nanogs-warp info scene.ply",
    "nanogs-warp info scene.ply --json   # for scripts: see docs/json.md",
))(user_errors(info_command))  # fmt: skip
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
app.command("warmup", epilog=examples(
    "nanogs-warp warmup                      # every kernel for this machine's devices",
    "nanogs-warp warmup --device cpu --arch 75,80,86,89,90,100,120 --cache-dir /opt/nanogs-kernels",
))(user_errors(warmup_command))  # fmt: skip


def main() -> None:
    """The console script. When a command has finished, the process ends at once, with its exit
    code, without the interpreter's teardown: every output is written and closed by then, and
    tearing down Warp's modules and device memory (a tenth of a second on the CPU, more with a
    GPU) would only add to the command's wall time."""
    try:
        try:
            app()
        except KeyboardInterrupt:  # Ctrl-C while the command line is being read (a command's own is click's)
            raise SystemExit(130) from None
        except OSError as e:  # --help or --version to a closed pipe or a full disk, before any command runs
            if e.errno not in (errno.EPIPE, errno.ENOSPC, errno.EIO, errno.EBADF):
                raise
            with contextlib.suppress(OSError):
                sys.stderr.write(f"nanogs-warp: error: cannot write the command's output: {e.strerror}\n")
            raise SystemExit(2) from None
    except SystemExit as e:
        code = e.code
        if code is not None and not isinstance(code, int):
            print(code, file=sys.stderr)
            code = 1
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except OSError as e:  # a closed pipe or a full disk: what was not written is lost
                if not code and stream is sys.stdout:  # said once, as a command's own error would be
                    with contextlib.suppress(OSError):
                        sys.stderr.write(f"nanogs-warp: error: cannot write the command's output: {e.strerror}\n")
                        sys.stderr.flush()
                code = code or 2
        os._exit(code or 0)
