"""Refinement speed on one device: end to end (read, simplify, refine, write) and per step, split
into forward (render and loss), backward and optimiser.

    python tools/refine_bench.py scene.ply --ratio 0.1 --steps 200 --device cuda:0 [--jsonl bench.jsonl]

Kernels are compiled by a warm-up refine of a small subset first. The end-to-end run does not
synchronise between phases; a second refine with ``timing`` does, for the per-phase split (the
reference renders are timed apart, and excluded from the per-step times). Prints one JSON line
(device, commit, counts, seconds), also appended to ``--jsonl`` when given.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import warp as wp

from nanogs_warp.device import init_warp, resolve_device
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.pipeline import simplify
from nanogs_warp.refinement.refine import RefineConfig, refine_with_report


def commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).parent).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--steps", type=int, default=RefineConfig.steps)
    parser.add_argument("--refine-size", type=int, default=RefineConfig.size)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--jsonl", type=Path, help="append the result to this JSON-lines file")
    args = parser.parse_args(argv)
    init_warp()
    device = resolve_device(args.device)
    load_kernels(device, ALL_MODULES)  # as the commands load them (shipped, or compiled once), outside every timing
    config = RefineConfig(steps=args.steps, size=args.refine_size)

    warm = load_ply(args.scene, device=device)
    small = simplify(warm, ratio=args.ratio)
    refine_with_report(small, small, RefineConfig(steps=2, size=args.refine_size, reference_views=2))

    with tempfile.TemporaryDirectory() as tmp:
        wp.synchronize_device(device)
        started = time.perf_counter()
        splats = load_ply(args.scene, device=device)
        read = time.perf_counter()
        simplified = simplify(splats, ratio=args.ratio)
        wp.synchronize_device(device)
        simplified_at = time.perf_counter()
        refined, report = refine_with_report(simplified, splats, config)
        refined_at = time.perf_counter()
        save_ply(refined, Path(tmp) / "refined.ply")
        finished = time.perf_counter()

    _, timed = refine_with_report(simplified, splats, config, timing=True)
    per_step = {k: round(1000.0 * getattr(timed, f"seconds_{k}") / max(1, args.steps), 3)
                for k in ("forward", "backward", "optimiser")}  # fmt: skip
    result = {
        "tool": "refine_bench",
        "device": str(device),
        "device_name": device.name,
        "commit": commit(),
        "scene": args.scene.name,
        "input_count": splats.count,
        "count": simplified.count,
        "steps": args.steps,
        "refine_size": args.refine_size,
        "seconds": {
            "end_to_end": round(finished - started, 3),
            "read": round(read - started, 3),
            "simplify": round(simplified_at - read, 3),
            "refine": round(refined_at - simplified_at, 3),
            "write": round(finished - refined_at, 3),
            "reference_renders": round(timed.seconds_reference, 3),
        },
        "ms_per_step": per_step,
        "loss": [report.loss_before, report.loss_after],
    }
    line = json.dumps(result)
    print(line)
    if args.jsonl is not None:
        with open(args.jsonl, "a") as f:
            f.write(line + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
