"""What ``--refine`` buys: PSNR of each simplified scene with and without refinement, on the ``eval``
orbit (16 views at 2.2x the 90th-percentile radius, 60 degrees, 256 x 256) and on a second camera set
refinement never saw (close-ups at 1.3x that radius, 45 degrees, random directions of a fixed seed).

    python tools/refine_quality.py scenes/guitar.ply scenes/statue.ply -o refine_quality/ --ratios 0.1,0.01
    python tools/refine_quality.py scenes/statue.ply -o rq_geometry/ --ratios 0.001 --learn geometry

``--learn`` refines only some of the parameters (the others' learning rates are 0): ``geometry``
(centres, rotations, scales), ``appearance`` (opacity and colour) or ``opacity``; each row also
gives the mean change of the splats' log-scales, smallest to largest axis, that refinement made.

Writes OUT/refine_quality.jsonl (one line per scene and ratio), OUT/refine_quality.md (the table) and
OUT/<scene>_closeups.json (the close-up cameras, for ``nanogs-warp eval --cameras``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from nanogs_warp.device import init_warp, resolve_device
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels
from nanogs_warp.eval.cameras import Camera, near_plane, orbit_cameras, parse_up
from nanogs_warp.eval.evaluate import evaluate
from nanogs_warp.io.ply import load_ply
from nanogs_warp.pipeline import SimplifyConfig, simplify_progressively
from nanogs_warp.refinement.cameras import scene_spread
from nanogs_warp.refinement.refine import RefineConfig, refine_with_report

CLOSEUP_DISTANCE = 1.3
CLOSEUP_FOV_DEG = 45.0
CLOSEUP_SEED = 20261123
# --learn: the learning rates set to 0, by what is left to learn
FROZEN = {
    "all": (),
    "geometry": ("lr_opacities", "lr_features_dc", "lr_features_rest"),
    "appearance": ("lr_means", "lr_rotations", "lr_log_scales"),
    "opacity": ("lr_means", "lr_rotations", "lr_log_scales", "lr_features_dc", "lr_features_rest"),
}


def closeup_cameras(means: np.ndarray, views: int, size: int, up: str = "-y") -> list[Camera]:
    """``views`` square cameras at 1.3x the 90th-percentile radius from the scene's centre, looking at
    it, 45 degree field of view, directions drawn from a fixed seed."""
    centre, p90, _ = scene_spread(means)
    rng = np.random.default_rng(CLOSEUP_SEED)
    focal = 0.5 * size / math.tan(math.radians(CLOSEUP_FOV_DEG) / 2.0)
    up_vector = parse_up(up)
    near = near_plane(CLOSEUP_DISTANCE * p90)
    cameras = []
    for k in range(views):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        cameras.append(Camera.look_at(centre + CLOSEUP_DISTANCE * p90 * d, centre, up_vector, focal, focal, size, size, f"closeup_{k:03d}", near))
    return cameras


def sorted_log_scale_change(before, after) -> list[float]:
    """The mean over splats of the change of each splat's log-scales, sorted smallest to largest
    (refinement keeps the count and the order of the splats)."""
    a = np.sort(before.log_scales.numpy().astype(np.float64), axis=1)
    b = np.sort(after.log_scales.numpy().astype(np.float64), axis=1)
    return [round(float(v), 4) for v in (b - a).mean(axis=0)]


def cameras_json(cameras: list[Camera]) -> list[dict]:
    """The INRIA trainer's cameras.json entries (rotation: camera-to-world, rows), with each camera's
    near plane (``near``, which ``eval --cameras`` reads: a scene in small units has a nearer one)."""
    return [
        {"id": k, "img_name": c.name, "width": c.width, "height": c.height, "position": c.centre.tolist(),
         "rotation": np.asarray(c.rotation, np.float64).T.tolist(), "fx": c.fx, "fy": c.fy, "near": c.near}
        for k, c in enumerate(cameras)
    ]  # fmt: skip


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", type=Path, nargs="+", help=".ply scenes")
    parser.add_argument("-o", "--out", type=Path, required=True, help="output folder")
    parser.add_argument("--ratios", default="0.1,0.01")
    parser.add_argument("--steps", type=int, default=RefineConfig.steps)
    parser.add_argument("--refine-size", type=int, default=RefineConfig.size)
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--learn", choices=list(FROZEN), default="all", help="which parameters refinement may change")
    args = parser.parse_args(argv)
    init_warp()
    device = resolve_device(args.device)
    load_kernels(device, ALL_MODULES)  # as the commands load them: no compile where they ship
    ratios = [float(r) for r in args.ratios.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(args.out / "refine_quality.jsonl", "a") as log:
        for path in args.scenes:
            splats = load_ply(path, device="cpu").to(device)
            orbit = orbit_cameras(splats, views=args.views, size=args.size)
            closeups = closeup_cameras(splats.means.numpy(), args.views, args.size)
            (args.out / f"{path.stem}_closeups.json").write_text(json.dumps(cameras_json(closeups), indent=1))
            targets = sorted({max(1, math.ceil(r * splats.count)) for r in ratios}, reverse=True)
            for target, simplified in simplify_progressively(splats, targets, SimplifyConfig()):
                config = RefineConfig(steps=args.steps, size=args.refine_size, **{name: 0.0 for name in FROZEN[args.learn]})
                started = time.perf_counter()
                refined, report = refine_with_report(simplified, splats, config)
                seconds = time.perf_counter() - started
                row = {"scene": path.stem, "count": target, "ratio": target / splats.count, "steps": args.steps,
                       "device": str(device), "learn": args.learn, "refine_seconds": round(seconds, 3), "refine": report.to_json(),
                       "log_scale_change": sorted_log_scale_change(simplified, refined)}  # fmt: skip
                for name, cams in (("orbit", orbit), ("closeup", closeups)):
                    result = evaluate(splats, [simplified, refined], cams, device)
                    row[f"{name}_before"] = result["tests"][0]["psnr"]["mean"]
                    row[f"{name}_after"] = result["tests"][1]["psnr"]["mean"]
                rows.append(row)
                log.write(json.dumps(row) + "\n")
                log.flush()
                print(f"{row['scene']} {target}: orbit {row['orbit_before']:.2f} -> {row['orbit_after']:.2f} dB, "
                      f"close-ups {row['closeup_before']:.2f} -> {row['closeup_after']:.2f} dB, {seconds:.1f} s", flush=True)  # fmt: skip
    lines = ["| scene | splats | learn | orbit PSNR | refined | gain | close-up PSNR | refined | gain | log-scale change, axes small to large | refine s |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---|---:|"]  # fmt: skip
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['count']:,} | {r['learn']} | {r['orbit_before']:.2f} | {r['orbit_after']:.2f} | "
            f"{r['orbit_after'] - r['orbit_before']:+.2f} | {r['closeup_before']:.2f} | {r['closeup_after']:.2f} | "
            f"{r['closeup_after'] - r['closeup_before']:+.2f} | {' / '.join(f'{v:+.3f}' for v in r['log_scale_change'])} | "
            f"{r['refine_seconds']:.1f} |"
        )
    (args.out / "refine_quality.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
