"""Two configurations compared on cameras the defaults were never chosen on.

The defaults are chosen on ``eval``'s orbit (16 views at 2.2x the 90th-percentile radius, 60
degrees, 256 x 256); users look from elsewhere. This scores the outputs of a quality sweep, kept as
PLY files, on three other camera sets, against the unsimplified scene:

- ``closeup``: 16 views at 1.3x that radius, 45 degrees, 256 x 256, random directions of a fixed
  seed (``tools/refine_quality.py``'s close-ups);
- ``orbit512``: the orbit itself at 512 x 512 (pixels half as wide);
- ``tight``: 16 views at 1.5x the radius, 40 degrees, 256 x 256, on Fibonacci directions other than
  the orbit's.

    python tools/quality_sweep.py SCENES/ -o sweep/ --device cpu --configs default,paper --keep-ply
    python tools/unseen_cameras.py SCENES/ sweep/ -o unseen.jsonl [--configs default,paper]

Prints, per camera set, each scene's PSNR gap (first configuration minus second) at every ratio, with
the SSIM and foreground-PSNR gaps beside it, and the mean and the worst cell; writes one JSON line per
(scene, ratio, camera set) to ``-o``, with each configuration's per-view PSNRs (``view_psnr``, in the
set's camera order): a cell's mean is the mean of its views' PSNRs in dB, so one view that is nearly
perfect in both can move it by a decibel or more (docs/quality.md).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from refine_quality import closeup_cameras  # noqa: E402  (this folder's)

from nanogs_warp.device import init_warp, resolve_device  # noqa: E402
from nanogs_warp.eval.cameras import Camera, fibonacci_directions, near_plane, orbit_cameras, parse_up  # noqa: E402
from nanogs_warp.eval.evaluate import evaluate  # noqa: E402
from nanogs_warp.io.ply import load_ply  # noqa: E402
from nanogs_warp.refinement.cameras import scene_spread  # noqa: E402

TIGHT_DISTANCE = 1.5  # in 90th-percentile radii (eval's orbit: 2.2)
TIGHT_FOV_DEG = 40.0
TIGHT_SKIP = 3  # the tight views take Fibonacci directions 3.. of 19, not the orbit's 16


def tight_cameras(means: np.ndarray, views: int = 16, size: int = 256, up: str = "-y") -> list[Camera]:
    centre, p90, _ = scene_spread(means)
    radius = TIGHT_DISTANCE * p90
    up_vector = parse_up(up)
    focal = 0.5 * size / math.tan(math.radians(TIGHT_FOV_DEG) / 2.0)
    directions = fibonacci_directions(views + TIGHT_SKIP, up_vector)[TIGHT_SKIP:]
    near = near_plane(radius)
    return [
        Camera.look_at(centre + radius * d, centre, up_vector, focal, focal, size, size, f"tight_{k:03d}", near)
        for k, d in enumerate(directions)
    ]


def camera_sets(reference) -> dict[str, list[Camera]]:
    means = reference.means.numpy()
    return {"closeup": closeup_cameras(means, 16, 256), "orbit512": orbit_cameras(reference, 16, 512), "tight": tight_cameras(means)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes_dir", type=Path, help="the folder of unsimplified scenes the sweep ran on")
    parser.add_argument("sweep_dir", type=Path, help="a quality_sweep.py output folder made with --keep-ply")
    parser.add_argument("-o", "--out", type=Path, required=True, help="JSON lines, one per scene, ratio and camera set")
    parser.add_argument("--configs", default="default,paper", help="two sweep configurations: the first is compared with the second")
    parser.add_argument("--ratios", default="0.1,0.01,0.001")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)

    configs = args.configs.split(",")
    if len(configs) != 2:
        parser.error("--configs takes two configurations")
    ratios = args.ratios.split(",")
    init_warp()
    device = resolve_device(args.device)
    kept = args.sweep_dir / "ply"
    scenes = sorted({p.name.split(f"_{configs[0]}_")[0] for p in kept.glob(f"*_{configs[0]}_*.ply")})
    if not scenes:
        parser.error(f"no {kept}/<scene>_{configs[0]}_<ratio>.ply files: run quality_sweep.py with --keep-ply")
    gaps: dict[str, dict[str, list[tuple[float, float, float]]]] = {}
    with open(args.out, "w") as out:
        for scene in scenes:
            reference = load_ply(args.scenes_dir / f"{scene}.ply", device=device)
            sets = camera_sets(reference)
            for ratio in ratios:
                tests = [load_ply(kept / f"{scene}_{c}_{ratio}.ply", device=device) for c in configs]
                for name, cameras in sets.items():
                    report = evaluate(reference, tests, cameras, device)
                    row = {"scene": scene, "ratio": ratio, "cameras": name}
                    for config, test in zip(configs, report["tests"]):
                        row[config] = {"psnr": test["psnr"]["mean"], "ssim": test["ssim"]["mean"], "fg_psnr": test["fg_psnr"]["mean"],
                                       "view_psnr": [v["psnr"] for v in test["views"]]}  # fmt: skip
                    out.write(json.dumps(row) + "\n")
                    a, b = row[configs[0]], row[configs[1]]
                    gap = (a["psnr"] - b["psnr"], a["ssim"] - b["ssim"], a["fg_psnr"] - b["fg_psnr"])
                    gaps.setdefault(name, {}).setdefault(scene, []).append(gap)
    print(f"{configs[0]} minus {configs[1]}: PSNR dB (SSIM x 100, foreground PSNR dB), ratios {', '.join(ratios)}")
    for name, per_scene in gaps.items():
        print(f"\n{name}")
        cells = [g[0] for row in per_scene.values() for g in row]
        for scene, row in per_scene.items():
            print(f"  {scene:20s} " + "  ".join(f"{p:+6.2f} ({100 * s:+5.1f}, {f:+6.2f})" for p, s, f in row))
        print(f"  mean {statistics.mean(cells):+.2f}, worst cell {min(cells):+.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
