"""Renderer speed on one device, and a fingerprint of its images to compare devices by.

    python tools/render_bench.py scene.ply [more.ply ...] --device cuda:0 [--repeat 7] [--jsonl bench.jsonl]

For each scene: the size fit's eight views of the input (four 256² training cameras and the same
zoomed four times, ``refinement/size_fit.py``) and ``eval``'s 16-view orbit, each set rendered
``--repeat`` times into one device array (the first run loads the kernels and is not counted).
Prints one JSON line per scene with the median and fastest seconds of each set and the SHA-256 of
each set's images: the renderer gives the same bits on every device (``kernels/render.py``), so
the fingerprints of a CPU run and a GPU run of the same scene match.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import time
from pathlib import Path

import warp as wp

from nanogs_warp.device import init_warp, resolve_device
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels
from nanogs_warp.eval.cameras import orbit_cameras
from nanogs_warp.eval.render import render_views_on_device
from nanogs_warp.io.ply import load_ply
from nanogs_warp.refinement import size_fit


def timed(splats, cameras, repeat: int) -> tuple[list[float], str]:
    """Seconds of each of ``repeat`` renders of ``cameras`` (after one untimed) and the images' SHA-256."""
    times = []
    for run in range(repeat + 1):
        wp.synchronize_device(splats.device)
        started = time.perf_counter()
        images = render_views_on_device(splats, cameras)
        wp.synchronize_device(splats.device)
        if run:
            times.append(time.perf_counter() - started)
    return times, hashlib.sha256(images.numpy().tobytes()).hexdigest()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", type=Path, nargs="+")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--jsonl", type=Path)
    args = parser.parse_args(argv)
    init_warp()
    device = resolve_device(args.device)
    load_kernels(device, ALL_MODULES)  # as the commands load them (shipped, or compiled once), outside every timing
    for path in args.scenes:
        splats = load_ply(path).to(device)
        coarse, fine = size_fit.fit_cameras(size_fit.sampled_means(splats))  # the default seed's
        row = {"scene": path.name, "splats": splats.count, "device": str(device), "device_name": device.name}
        for name, cameras in (("fit_views", coarse + fine), ("orbit", orbit_cameras(splats))):
            times, digest = timed(splats, cameras, args.repeat)
            row[name] = {"views": len(cameras), "median_s": round(statistics.median(times), 4),
                         "fastest_s": round(min(times), 4), "sha256": digest}  # fmt: skip
        line = json.dumps(row)
        print(line, flush=True)
        if args.jsonl:
            with args.jsonl.open("a") as out:
                out.write(line + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
