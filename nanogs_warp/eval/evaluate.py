"""What simplification costs: render a reference and simplified scenes from the same cameras, compare.

Images are rendered on one device (``render_views``), clamped to [0, 1] as saved images would be, and
compared per view with ``metrics``. Per test scene the result holds each metric's mean over views
and its worst view. ``write_images`` saves what was compared as PNGs (written with zlib and struct).
"""

from __future__ import annotations

import math
import struct
import time
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np
import warp as wp

from ..errors import InputError, elided
from ..splats import SplatSet
from . import metrics
from .cameras import Camera
from .glyphs import GLYPH_HEIGHT, draw_text, text_width
from .render import render_views
from .units import render_units, rescaled, rescaled_camera

DIFF_GAIN = 4.0


def render_all(splats: SplatSet, cameras: Sequence[Camera], background=(0.0, 0.0, 0.0)) -> list[np.ndarray]:
    """One float32 (H, W, 3) image per camera, clamped to [0, 1]; cameras of one size render together."""
    groups: dict[tuple[int, int], list[int]] = {}
    for k, camera in enumerate(cameras):
        groups.setdefault((int(camera.width), int(camera.height)), []).append(k)
    images: list[np.ndarray | None] = [None] * len(cameras)
    for indices in groups.values():
        rendered = render_views(splats, [cameras[k] for k in indices], background)
        for k, image in zip(indices, np.clip(rendered, 0.0, 1.0)):
            images[k] = image
    return images  # type: ignore[return-value]


# In a mean over views, a view that both scenes render identically (PSNR inf) counts as this many dB
# (a mean squared error of 1e-10) where another view differs: one such view (a far view that sees
# nothing of either scene, say) would otherwise make the mean infinite and hide every other view.
# Only when every view is identical is the mean inf.
IDENTICAL_VIEW_DB = 100.0


def _summary(values: list[float], names: list[str], worst=min, identical_as: float | None = None) -> dict:
    finite = [(v, n) for v, n in zip(values, names) if not math.isnan(v)]
    if not finite:
        return {"mean": math.nan, "worst": math.nan, "worst_view": None}
    worst_value, worst_name = worst(finite, key=lambda vn: vn[0])
    counted = [v for v, _ in finite]
    if identical_as is not None and not all(math.isinf(v) for v in counted):
        counted = [identical_as if v == math.inf else v for v in counted]
    return {"mean": float(np.mean(counted)), "worst": float(worst_value), "worst_view": worst_name}


def compare_images(
    reference_images: Sequence[np.ndarray],
    test_images: Sequence[np.ndarray],
    view_names: Sequence[str],
    background=(0.0, 0.0, 0.0),
) -> dict:
    """Metrics of one test scene's views against the reference's: per view, and per metric the mean
    over views and the worst view (lowest PSNR / SSIM / foreground PSNR; largest absolute colour
    shift in any channel). Views without foreground are left out of the foreground means."""
    names = list(view_names)
    per_view = []
    for name, ref, test in zip(names, reference_images, test_images):
        per_view.append(
            {
                "name": name,
                "psnr": metrics.psnr(ref, test),
                "ssim": metrics.ssim(ref, test),
                "fg_psnr": metrics.foreground_psnr(ref, test, background),
                "colour_shift": [float(v) for v in metrics.colour_shift(ref, test, background)],
            }
        )
    shifts = [np.asarray(v["colour_shift"]) for v in per_view]
    valid = [(s, n) for s, n in zip(shifts, names) if not np.isnan(s).any()]
    if valid:
        worst_shift, worst_name = max(valid, key=lambda sn: float(np.abs(sn[0]).max()))
        shift = {
            "mean": [float(v) for v in np.mean([s for s, _ in valid], axis=0)],
            "worst": [float(v) for v in worst_shift],
            "worst_view": worst_name,
        }
    else:
        shift = {"mean": [math.nan] * 3, "worst": [math.nan] * 3, "worst_view": None}
    return {
        "psnr": _summary([v["psnr"] for v in per_view], names, identical_as=IDENTICAL_VIEW_DB),
        "ssim": _summary([v["ssim"] for v in per_view], names),
        "fg_psnr": _summary([v["fg_psnr"] for v in per_view], names, identical_as=IDENTICAL_VIEW_DB),
        "colour_shift": shift,
        "views": per_view,
    }


def evaluate(
    reference: SplatSet,
    tests: Sequence[SplatSet],
    cameras: Sequence[Camera],
    device=None,
    background=(0.0, 0.0, 0.0),
    names: Sequence[str] | None = None,
    images: dict | None = None,
    progress=None,
) -> dict:
    """Renders ``reference`` and each of ``tests`` from ``cameras`` on ``device`` (default: the
    reference's) and compares them. Returns a dict: ``reference`` {count, sh_degree}, ``views``,
    ``view_names``, ``background``, ``device``, ``seconds`` and ``tests``, a list with per test scene
    {name, count, sh_degree, ratio, psnr, ssim, fg_psnr, colour_shift, views} (see ``compare_images``).
    Pass a dict as ``images`` to receive the rendered images: ``reference`` (list of (H, W, 3)) and
    ``tests`` (one such list per test scene). ``progress`` (optional) is called with a short line
    before each scene is rendered."""
    cameras = list(cameras)
    if not cameras:
        raise InputError("no cameras to evaluate with")
    background = tuple(float(v) for v in background)
    device = wp.get_device(device) if device is not None else reference.device
    view_names = [c.name or f"view_{k:03d}" for k, c in enumerate(cameras)]
    if names is None:
        names = [f"test_{k}" for k in range(len(tests))]
    started = time.perf_counter()
    scale = render_units(reference)
    if scale != 1.0:
        reference, tests = rescaled(reference, scale), [rescaled(t, scale) for t in tests]
        cameras = [rescaled_camera(c, scale) for c in cameras]
    if progress is not None:
        progress(f"rendering the reference, {len(cameras)} views")
    reference_images = render_all(reference.to(device), cameras, background)
    results = []
    all_test_images = []
    for k, (name, test) in enumerate(zip(names, tests)):
        if progress is not None:
            progress(f"rendering test scene {k + 1}/{len(tests)}: {name}")
        test_images = render_all(test.to(device), cameras, background)
        all_test_images.append(test_images)
        results.append(
            {
                "name": str(name),
                "count": test.count,
                "sh_degree": test.sh_degree,
                "ratio": test.count / reference.count if reference.count else math.nan,
                **compare_images(reference_images, test_images, view_names, background),
            }
        )
    if images is not None:
        images["reference"] = reference_images
        images["tests"] = all_test_images
    sizes = sorted({(int(c.width), int(c.height)) for c in cameras})
    return {
        "reference": {"count": reference.count, "sh_degree": reference.sh_degree},
        "views": len(cameras),
        "view_names": view_names,
        "sizes": [list(s) for s in sizes],
        "background": list(background),
        "device": str(device),
        "seconds": {"render_and_compare": round(time.perf_counter() - started, 4)},
        "tests": results,
    }


def _fmt(value: float, digits: int) -> str:
    if value is None or math.isnan(value):
        return "-"
    if math.isinf(value):
        return "inf"
    return f"{value:.{digits}f}"


TABLE_NAME = 48  # characters of a view's name in the table, ``elided`` (--json has it whole)


def format_table(result: dict) -> str:
    """The evaluation as a text table: one row per test scene."""
    sizes = ", ".join(f"{w}x{h}" for w, h in result["sizes"])
    bg = ",".join(f"{v:g}" for v in result["background"])
    lines = [
        f"reference: {result['reference']['count']:,} splats (SH {result['reference']['sh_degree']}); "
        f"{result['views']} views {sizes} on {result['device']}, background {bg}",
        "PSNR, SSIM, FG-PSNR: mean / worst view; colour shift: mean (test - reference) over the foreground, R G B",
    ]
    header = ["scene", "splats", "ratio", "PSNR dB", "SSIM", "FG-PSNR dB", "colour shift", "worst view"]
    rows = [header]
    for t in result["tests"]:
        shift = " ".join(("-" if math.isnan(v) else f"{v:+.4f}") for v in t["colour_shift"]["mean"])
        rows.append(
            [
                t["name"],
                f"{t['count']:,}",
                _fmt(t["ratio"], 4),
                f"{_fmt(t['psnr']['mean'], 2)} / {_fmt(t['psnr']['worst'], 2)}",
                f"{_fmt(t['ssim']['mean'], 4)} / {_fmt(t['ssim']['worst'], 4)}",
                f"{_fmt(t['fg_psnr']['mean'], 2)} / {_fmt(t['fg_psnr']['worst'], 2)}",
                shift,
                elided(str(t["psnr"]["worst_view"]), TABLE_NAME),  # no column padded to a hostile name
            ]
        )
    widths = [max(len(r[c]) for r in rows) for c in range(len(header))]
    for k, r in enumerate(rows):
        cells = [r[0].ljust(widths[0])] + [cell.rjust(w) for cell, w in zip(r[1:], widths[1:])]
        lines.append("  ".join(cells).rstrip())
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# PNG output


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] floats -> uint8, rounded; values outside are clamped."""
    return np.round(np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: Path | str, image: np.ndarray, outputs=None) -> None:
    """Writes an (H, W, 3) uint8 image as an 8-bit RGB PNG (no filtering, zlib level 6), staged in
    ``outputs`` (an ``OutputSet``) when given."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got {image.shape}")
    height, width = image.shape[:2]
    raw = np.zeros((height, 1 + 3 * width), np.uint8)  # filter type 0 per row
    raw[:, 1:] = image.reshape(height, 3 * width)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b"")
    if outputs is None:
        Path(path).write_bytes(png)
    else:
        from ..io.ply_write import atomic_write

        atomic_write(Path(path), lambda stream: stream.write(png), True, outputs)


def comparison_strip(reference: np.ndarray, test: np.ndarray, gap: int = 2) -> np.ndarray:
    """reference | test | |test - reference| x 4, side by side with white gaps, as uint8."""
    reference = np.clip(np.asarray(reference, np.float64), 0.0, 1.0)
    test = np.clip(np.asarray(test, np.float64), 0.0, 1.0)
    diff = np.abs(test - reference) * DIFF_GAIN
    h, w = reference.shape[:2]
    strip = np.full((h, 3 * w + 2 * gap, 3), 255, np.uint8)
    for k, panel in enumerate((reference, test, diff)):
        strip[:, k * (w + gap) : k * (w + gap) + w] = to_uint8(panel)
    return strip


LABEL_COLOUR = (0, 0, 0)
WORST_COLOUR = (220, 0, 0)


def contact_sheet(
    strips: Sequence[np.ndarray],
    gap: int = 4,
    labels: Sequence[str] | None = None,
    worst: int | None = None,
    title: Sequence[str] = (),
) -> np.ndarray:
    """Strips on a grid of ceil(sqrt(V)) columns, each cell the size of the largest strip. With
    ``labels``, a line of text under each strip; strip ``worst`` is framed and labelled in red; the
    ``title`` lines head the sheet."""
    count = len(strips)
    columns = max(1, math.ceil(math.sqrt(count)))
    rows = math.ceil(count / columns)
    cell_w = max(s.shape[1] for s in strips)
    scale = 2 if cell_w >= 2 * text_width("VIEW_000  PSNR 00.00  SSIM 0.000  WORST") + 8 else 1
    line = (GLYPH_HEIGHT + 4) * scale
    label_h = line if labels is not None else 0
    cell_h = max(s.shape[0] for s in strips) + label_h
    title_h = len(title) * line + (gap if title else 0)
    width = columns * cell_w + (columns - 1) * gap
    sheet = np.full((title_h + rows * cell_h + (rows - 1) * gap, width, 3), 255, np.uint8)
    for t, text in enumerate(title):
        draw_text(sheet, text, 2, 2 * scale + t * line, LABEL_COLOUR, scale)
    for k, strip in enumerate(strips):
        y, x = title_h + (k // columns) * (cell_h + gap), (k % columns) * (cell_w + gap)
        sheet[y : y + strip.shape[0], x : x + strip.shape[1]] = strip
        colour = WORST_COLOUR if k == worst else LABEL_COLOUR
        if labels is not None:
            text = labels[k] + ("  WORST" if k == worst else "")
            draw_text(sheet, text, x + 1, y + strip.shape[0] + 2 * scale, colour, scale)
        if k == worst:  # a frame in the gap around the cell
            y0, y1, x0, x1 = max(y - 2, 0), min(y + cell_h + 1, sheet.shape[0]), max(x - 2, 0), min(x + cell_w + 1, width)
            sheet[y0:y1, x0 : x0 + 2] = colour
            sheet[y0:y1, x1 - 2 : x1] = colour
            sheet[y0 : y0 + 2, x0:x1] = colour
            sheet[y1 - 2 : y1, x0:x1] = colour
    return sheet


def view_label(name: str, psnr: float, ssim: float) -> str:
    """``VIEW_003  PSNR 23.41  SSIM 0.812`` (inf for identical views)."""
    return f"{name}  PSNR {_fmt(psnr, 2)}  SSIM {_fmt(ssim, 3)}"


def write_images(
    directory: Path | str,
    reference_images: Sequence[np.ndarray],
    test_images: Sequence[np.ndarray],
    names: Sequence[str],
    comparison: dict | None = None,
    title: Sequence[str] = (),
    outputs=None,
) -> list[Path]:
    """Writes ``<name>.png`` per view (reference | test | difference x 4) and ``contact_sheet.png``
    (every view's strip on a grid) into ``directory`` (created if missing). With ``comparison``
    (``compare_images``' result for these images), each cell of the sheet is labelled with its view,
    PSNR and SSIM and the worst view by PSNR is marked; ``title`` lines head the sheet (the scene
    names). With ``outputs`` (an ``OutputSet``) the files and the folder are staged there, to
    appear when it is published. Returns the paths."""
    directory = Path(directory)
    if outputs is None:
        directory.mkdir(parents=True, exist_ok=True)
    else:
        outputs.make_folder(directory)
    written, strips, used = [], [], {"contact_sheet"}
    for k, (name, ref, test) in enumerate(zip(names, reference_images, test_images)):
        strip = comparison_strip(ref, test)
        strips.append(strip)
        stem = _safe_name(name)
        if stem in used:
            stem = f"{stem}_{k:03d}"
        used.add(stem)
        path = directory / f"{stem}.png"
        write_png(path, strip, outputs)
        written.append(path)
    if strips:
        labels, worst = None, None
        if comparison is not None:
            views = comparison["views"]
            labels = [view_label(v["name"], v["psnr"], v["ssim"]) for v in views]
            worst_name = comparison["psnr"]["worst_view"]
            identical = all(v["psnr"] == math.inf for v in views)
            worst = None if identical else next((k for k, v in enumerate(views) if v["name"] == worst_name), None)
        path = directory / "contact_sheet.png"
        write_png(path, contact_sheet(strips, labels=labels, worst=worst, title=title), outputs)
        written.append(path)
    return written


# Host memory that eval takes, measured on the CPU with one test scene: about 270 bytes a pixel of
# the view in hand (its renders and the SSIM's float64 maps: 4.5 GB for one 4096 x 4096 view, 17.5 GB
# for 8192 x 8192), and 14 bytes a pixel of every view, for each scene, kept until the end (4 views
# against 1 at 1024 x 1024: 86 MB more).
VIEW_BYTES_PER_PIXEL = 270
KEPT_BYTES_PER_PIXEL = 14


def check_host_memory(cameras: Sequence, scenes: int) -> None:
    """Refuses, before any rendering, views whose comparison would need more host memory than is
    available (``scenes``: the reference and the test scenes): 8192 x 8192 views took 17 GB."""
    from ..device import memory_short

    largest = max(c.width * c.height for c in cameras)
    need = largest * VIEW_BYTES_PER_PIXEL + sum(c.width * c.height for c in cameras) * KEPT_BYTES_PER_PIXEL * scenes
    available = memory_short(need)
    if available is not None:
        raise InputError(f"{len(cameras)} view(s) of up to {largest:,} pixels for {scenes} scenes need about {need:,} bytes "
                         f"of memory, more than the {available:,} available: give a smaller --size or fewer views")  # fmt: skip


def _safe_name(name: str) -> str:
    """A view's name as a file name: letters, digits, '-', '_' and '.', at most 100 bytes in UTF-8
    (a file name holds 255 bytes, and a letter may take four)."""
    stem = Path(str(name)).stem or "view"
    return fit_bytes("".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem), 100)


def fit_bytes(name: str, most: int, keep_end: bool = False) -> str:
    """``name`` cut to at most ``most`` bytes in UTF-8 (never inside a character): its start, or
    with ``keep_end`` its end. A character takes at least one byte, so at most ``most`` of them are
    measured (a 2 MB name was cut one character a time, each time measured whole: minutes)."""
    name = name[max(0, len(name) - most) :] if keep_end else name[:most]
    while len(name.encode("utf-8", "surrogateescape")) > most:
        name = name[1:] if keep_end else name[:-1]
    return name
