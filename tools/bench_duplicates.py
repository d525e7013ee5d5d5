"""Splats at the same position: passes and time against the same scene without the copies.

    python tools/bench_duplicates.py scene.ply --device cpu --ratio 0.1 --repeat 3
    python tools/bench_duplicates.py scene.ply --device cuda:0 --ratio 0.01 --config paper

From the scene (its first N splats, N = --splats, default all) three variants of equal size are
made in memory: the scene itself; ``dup25``: a quarter of its rows (chosen at random) overwritten
with copies of 200 other rows, so those positions are shared by clusters of varied size; and
``cluster``: --cluster rows (default 32,768; at most N - 1) overwritten with copies of one row.
Each is simplified to the same target count; the passes, the output count and the median wall
time of --repeat runs (state on the device, kernels loaded) are printed, with the time and pass
count relative to the scene itself, and optionally appended to --log as JSON lines.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from nanogs_warp.device import init_warp, resolve_device
from nanogs_warp.kernel_cache import SIMPLIFY_MODULES, load_kernels
from nanogs_warp.io.ply import load_ply
from nanogs_warp.pipeline import SimplifyConfig, simplify_progressively, target_count
from nanogs_warp.splats import SplatSet


def with_rows_copied(splats: SplatSet, rows: np.ndarray, sources: np.ndarray) -> SplatSet:
    """The splat set with every property of ``rows`` replaced by that of ``sources``."""
    host = splats.to_numpy()
    for key, value in host.items():
        if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == splats.count:
            value[rows] = value[sources]
    return SplatSet.from_numpy(host["means"], host["rotations"], host["log_scales"], host["opacities"],
                               host["features"], host["extras"], layout=splats.layout, device="cpu",
                               integer_extras=host["integer_extras"])  # fmt: skip


def variants(splats: SplatSet, cluster: int, seed: int) -> dict[str, SplatSet]:
    n = splats.count
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    sources = order[:200]
    rows = order[200 : 200 + n // 4]
    dup25 = with_rows_copied(splats, rows, rng.choice(sources, rows.size))
    size = min(cluster, n - 1)
    rows = order[1 : 1 + size]
    clustered = with_rows_copied(splats, rows, np.full(size, order[0]))
    return {"scene": splats, "dup25": dup25, f"cluster{size}": clustered}


def run(splats: SplatSet, target: int, config: SimplifyConfig) -> tuple[float, int, int]:
    passes = []
    wp.synchronize_device(splats.device)
    start = time.perf_counter()
    (_, result), = simplify_progressively(splats, [target], config, on_pass=passes.append)
    wp.synchronize_device(splats.device)
    return time.perf_counter() - start, len(passes), result.count


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--splats", type=int, default=None, help="use the first N splats (default all)")
    parser.add_argument("--cluster", type=int, default=32768, help="copies in the one-position cluster")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", choices=["default", "paper"], default="default",
                        help="the default configuration or the NanoGS paper's")
    parser.add_argument("--log", type=Path, default=None, help="append JSON lines here")
    args = parser.parse_args(argv)

    init_warp()
    device = resolve_device(args.device)
    load_kernels(device, SIMPLIFY_MODULES)  # as the commands load them (shipped, or compiled once), outside every timing
    splats = load_ply(args.scene)
    if args.splats is not None and args.splats < splats.count:
        host = splats.to_numpy()
        m = args.splats
        splats = SplatSet.from_numpy(host["means"][:m], host["rotations"][:m], host["log_scales"][:m],
                                     host["opacities"][:m], host["features"][:m], host["extras"][:m],
                                     layout=splats.layout, device="cpu", integer_extras=host["integer_extras"][:m])  # fmt: skip
    target = target_count(splats.count, args.ratio)
    config = SimplifyConfig.paper() if args.config == "paper" else SimplifyConfig()
    reference = None
    for name, variant in variants(splats, args.cluster, args.seed).items():
        on_device = variant.to(device)
        run(on_device, target, config)  # kernels loaded, caches warm
        times, passes, count = [], 0, 0
        for _ in range(args.repeat):
            seconds, passes, count = run(on_device, target, config)
            times.append(seconds)
        median = statistics.median(times)
        if reference is None:
            reference = (median, passes)
        row = {"scene": args.scene.stem, "variant": name, "config": args.config, "splats": variant.count, "target": target,
               "count": count, "passes": passes, "seconds": round(median, 4), "device": str(device),
               "time_ratio": round(median / reference[0], 3), "pass_difference": passes - reference[1]}  # fmt: skip
        print(f"{args.scene.stem:>20} {name:>13}: {variant.count:,} -> {count:,} (target {target:,}), "
              f"{passes} passes ({passes - reference[1]:+d}), {median:.3f} s ({median / reference[0]:.2f}x)")  # fmt: skip
        if args.log is not None:
            with args.log.open("a") as log:
                log.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
