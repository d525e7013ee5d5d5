"""``nanogs-warp eval``: what simplification costs, as image metrics against the reference scene.

Registered in ``app.py`` as ``app.command("eval")(user_errors(eval_command))``.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import InputError
from . import options as opts
from .options import JSON_SCHEMA


def parse_background(text: str) -> tuple[float, float, float]:
    """``R,G,B`` with each value in [0, 1], or ``black`` / ``white``."""
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
    if text.strip().lower() in named:
        return named[text.strip().lower()]
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise InputError(f"--background {text!r}: expected R,G,B with values in [0, 1], black or white")
    return values  # type: ignore[return-value]


def eval_command(
    reference: Annotated[Path, typer.Argument(metavar="REFERENCE", help="Reference scene (usually the unsimplified one), in any format simplify reads.", show_default=False)],
    tests: Annotated[list[Path], typer.Argument(metavar="TEST", help="One or more scenes (any format simplify reads) to compare with the reference.", show_default=False)],
    views: Annotated[int, typer.Option("--views", help="Number of orbit views (ignored with --cameras).", metavar="VIEWS")] = 16,
    size: Annotated[int, typer.Option("--size", help="Image side in pixels: orbit views are square; --cameras views are scaled to this longest side (0 keeps their sizes).", metavar="SIZE")] = 256,
    device: Annotated[str, typer.Option("--device", help="auto (first GPU, else CPU), cpu, cuda or cuda:N.", metavar="DEVICE")] = "auto",
    cameras: Annotated[Optional[Path], typer.Option("--cameras", metavar="CAMERAS.JSON", help="The INRIA trainer's cameras.json to render from instead of orbit views.", show_default=False)] = None,
    up: Annotated[str, typer.Option("--up", help="World up axis of the orbit views: +x, -x, +y, -y, +z or -z (INRIA/COLMAP scenes are -y).", metavar="UP")] = "-y",
    background: Annotated[str, typer.Option("--background", metavar="R,G,B", help="Background colour R,G,B in [0, 1] (or black, white).")] = "0,0,0",
    images: Annotated[Optional[str], typer.Option("--images", metavar="FOLDER", help="Write reference | test | difference x4 PNGs per view and a contact sheet into this directory (one sub-directory per test scene).", show_default=False)] = None,
    drop_invalid: opts.DropInvalid = False,
    json_output: Annotated[bool, typer.Option("--json", help="Print machine-readable results (JSON) instead of the table.")] = False,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No progress and no table; only errors (and --json).")] = False,
) -> None:
    """Render the reference and each test scene from identical cameras and report PSNR, SSIM,
    foreground PSNR and colour shift (mean and worst view)."""
    import numpy as np

    from ..device import resolve_device
    from ..eval.cameras import load_cameras_json, orbit_cameras, parse_up
    from ..eval.evaluate import check_host_memory, evaluate, format_table, write_images
    from ..eval.units import render_offset, rescaled, rescaled_camera
    from ..folders import creatable_folder
    from ..io import input_files, load_splats
    from ..io.open_file import open_regular
    from ..io.ply_write import OutputSet
    from ..kernel_cache import EVAL_MODULES, load_kernels

    if not tests:
        raise InputError("give at least one test scene to compare with the reference")
    if size < 0:
        raise InputError(f"--size {size}: must be positive (0 keeps the sizes of --cameras)")
    if size == 0 and cameras is None:
        raise InputError("--size 0 only applies to --cameras; orbit views need a size")
    bg = parse_background(background)
    parse_up(up)
    target = resolve_device(device)
    for path in [reference, *tests]:
        if not path.exists():
            open_regular(path).close()  # its own line: no such file, a link loop, ...
            raise InputError(f"{path}: no such file")
    if images is not None:  # checked now, before any rendering (made when written): a folder that cannot be is one line
        if not images.strip():
            raise InputError("--images: give a folder")
        images = Path(images)
        if images.exists() and not images.is_dir():
            raise InputError(f"--images {images}: exists and is not a directory")
        creatable_folder(images, f"--images {images}")
    load_kernels(target, EVAL_MODULES)  # says so in one line when they must be compiled first

    def dropped(line: str) -> None:
        if not quiet:
            print(f"nanogs-warp: warning: {line}", file=sys.stderr)

    ref_splats = load_splats(reference, device=target, drop_invalid=drop_invalid, on_drop=dropped)
    test_splats = [load_splats(path, device=target, drop_invalid=drop_invalid, on_drop=dropped) for path in tests]
    offset = render_offset(ref_splats)  # a scene far from the origin for its size: seen recentred
    if offset is not None:
        ref_splats, test_splats = rescaled(ref_splats, 1.0, offset), [rescaled(t, 1.0, offset) for t in test_splats]
    if cameras is not None:
        camera_list = [rescaled_camera(c, 1.0, offset) for c in load_cameras_json(cameras, size=size or None)]
    else:
        camera_list = orbit_cameras(ref_splats, views=views, size=size, up=up)
    check_host_memory(camera_list, 1 + len(tests))
    rendered: dict = {}
    progress = _Progress(sys.stderr.isatty() and not quiet)
    result = evaluate(ref_splats, test_splats, camera_list, target, bg, names=[str(p) for p in tests], images=rendered,
                      progress=progress)  # fmt: skip
    progress.done()
    if not quiet and all(np.abs(view - np.asarray(bg, np.float32)).max() < 0.5 / 255.0 for view in rendered["reference"]):
        print("nanogs-warp: warning: the reference renders as bare background in every view: nothing lies in front of "
              f"the cameras' near plane ({camera_list[0].near:g} world units) within their view", file=sys.stderr)  # fmt: skip
    labels = scene_labels(tests)
    result["reference"]["path"] = str(reference.resolve())
    result["cameras"] = str(cameras.resolve()) if cameras is not None else {"orbit": {"views": views, "size": size, "up": up}}
    for t, path, label in zip(result["tests"], tests, labels):
        t["path"] = str(path.resolve())
        t["label"] = label
    settings = {"views": len(camera_list), "size": size, "up": up, "background": list(bg), "device": str(target),
                "cameras": result["cameras"] if cameras is not None else "orbit"}  # fmt: skip
    result = {"schema": JSON_SCHEMA, "command": "eval", "settings": settings, **result}
    for t in result["tests"]:
        t["identical"] = all(v["psnr"] == math.inf for v in t["views"])

    if images is not None:  # every image under a temporary name, all moved into place at the end
        image_files = OutputSet(keep=[f for scene in (reference, *tests) for f in input_files(scene)])  # never an input
        try:
            image_files.make_folder(images)
            counts = []
            for k, (label, name, test_images) in enumerate(zip(labels, image_folders(labels), rendered["tests"])):
                folder = images / name
                t = result["tests"][k]
                title = [f"REFERENCE {_scene_label(reference)} | {label} | DIFFERENCE ×4",
                         f"{t['count']:,} SPLATS  PSNR {_number(t['psnr']['mean'], 2)}  SSIM {_number(t['ssim']['mean'], 3)} (MEAN)"]  # fmt: skip
                try:
                    written = write_images(folder, rendered["reference"], test_images, result["view_names"], comparison=t, title=title,
                                           outputs=image_files)  # fmt: skip
                except InputError as e:
                    raise InputError(f"--images {folder}: {e}") from None
                t["images"] = str(folder.resolve())
                counts.append((len(written), folder))
            image_files.publish()
        except BaseException:
            image_files.discard()
            raise
        if not quiet:
            for count, folder in counts:
                print(f"wrote {count} images to {folder}", file=sys.stderr)

    if json_output:
        typer.echo(opts.json_text(result))
    elif not quiet:
        typer.echo(format_table(result))


def image_folders(labels: list[str]) -> list[str]:
    """A folder name inside ``--images`` for each test scene's label: at most 100 bytes in UTF-8, no
    separator, never '.', '..' or hidden (a scene file named '...ply'), and each its own (labels
    that only differ before their last 100 bytes get a number)."""
    from ..eval.evaluate import fit_bytes

    names: list[str] = []
    for k, label in enumerate(labels):
        name = fit_bytes(label.replace("/", "_").replace("\\", "_"), 100, keep_end=True).lstrip(".") or f"scene_{k + 1}"
        while name in names:
            name = f"{fit_bytes(name, 90, keep_end=True)}_{k + 1}"
        names.append(name)
    return names


def _scene_label(path: Path) -> str:
    return path.name[: -len(".ply")] if path.name.lower().endswith(".ply") else path.name


def _number(value, digits: int) -> str:
    if value is None or math.isnan(value):
        return "-"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def scene_labels(paths: list[Path]) -> list[str]:
    """Short, distinct names for the test scenes: the file name without .ply; where names repeat,
    as many parent folders in front as tell them apart (and a number where nothing does)."""
    full = [Path(p).resolve() for p in paths]
    unique = list(dict.fromkeys(full))
    names = [_scene_label(p) for p in unique]
    depth = 0
    while len(set(names)) < len(names) and depth < 64:
        depth += 1
        repeated = {name for name in names if names.count(name) > 1}
        for k, p in enumerate(unique):
            if names[k] in repeated:
                names[k] = "/".join([*p.parent.parts[1:][-depth:], _scene_label(p)])
    of_path = dict(zip(unique, names))
    labels, seen = [], {}
    for p in full:  # the same file given twice
        seen[p] = seen.get(p, 0) + 1
        labels.append(of_path[p] if seen[p] == 1 else f"{of_path[p]} ({seen[p]})")
    return labels


class _Progress:
    """One status line on stderr, rewritten; silent unless stderr is a terminal."""

    def __init__(self, enabled: bool):
        self.enabled = enabled

    def __call__(self, text: str) -> None:
        if self.enabled:
            sys.stderr.write(f"\r{text}\033[K")
            sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()
