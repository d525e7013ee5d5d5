"""Time one cost objective on a scene's first-pass edges: nanoseconds an edge, and a checksum.

    python tools/cost_bench.py playbot.ply --device cpu
    python tools/cost_bench.py playbot.ply --cost runnalls --k 16 --repeat 5 --save costs.npy

The kNN graph and its edges are built once (as the pipeline's first pass does, without pruning);
the cost is then run ``--repeat`` times after one warm-up run, and the fastest is reported. On the
CPU the cost uses every core (``nanogs_warp.parallel``). ``--save`` writes the costs (float32), to
compare two versions of a kernel bit for bit. tools/bench.py times whole runs stage by stage.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from nanogs_warp.cost import COSTS
from nanogs_warp.io import load_splats
from nanogs_warp.topology import KnnTopology


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", help="a 3DGS .ply file")
    parser.add_argument("--cost", default="field", choices=sorted(COSTS))
    parser.add_argument("--k", type=int, default=16, help="neighbours per splat (default 16, the default's k above 65,536 splats)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--save", help="write the costs to this .npy file")
    args = parser.parse_args()

    wp.config.quiet = True
    splats = load_splats(args.scene, device=args.device)
    edges = KnnTopology(args.k)(splats)
    cost = COSTS[args.cost]()
    costs = cost(splats, edges, 0)  # warm-up: loads the kernels
    seconds = []
    for _ in range(max(1, args.repeat)):
        wp.synchronize_device(splats.device)
        start = time.perf_counter()
        costs = cost(splats, edges, 0)
        wp.synchronize_device(splats.device)
        seconds.append(time.perf_counter() - start)
    values = costs.numpy()
    finite = values[np.isfinite(values)]
    best = min(seconds)
    print(
        f"{args.scene}: {splats.count:,} splats, {edges.count:,} edges, cost {args.cost} on {splats.device}: "
        f"{best * 1e3:.0f} ms, {best * 1e9 / max(edges.count, 1):.0f} ns an edge (fastest of {len(seconds)}); "
        f"checksum {finite.astype(np.float64).sum():.9e}"
    )
    if args.save:
        np.save(args.save, values)


if __name__ == "__main__":
    main()
