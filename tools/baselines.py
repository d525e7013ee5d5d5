"""Model-only baselines at the same budget as NanoGS: keep a subset of the input's splats, unchanged.

    python tools/baselines.py IN.ply -o OUT.ply --ratio 0.1,0.01,0.001 --method topk
    python tools/baselines.py IN.ply -o OUT.ply --count 5000 --method random --seed 1

- ``topk``: the splats of largest opacity x volume, sigmoid(opacity) * prod_k exp(scale_k)
  (ties: lower row first), in their input order.
- ``random``: a uniformly random subset (seeded), in input order.

Budgets and output paths follow ``nanogs-warp simplify``: one budget writes OUT itself, several
write OUT_<budget>.ply each.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from nanogs_warp.budgets import output_paths, parse_budgets
from nanogs_warp.device import init_warp
from nanogs_warp.errors import InputError
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.splats import SplatSet

METHODS = ("topk", "random")


def importance(splats: SplatSet) -> np.ndarray:
    """sigmoid(opacity) * prod exp(log scale), in float64 (as log values, so nothing overflows)."""
    logits = splats.opacities.numpy().astype(np.float64).reshape(-1)
    log_scales = splats.log_scales.numpy().astype(np.float64).reshape(-1, 3)
    log_alpha = -np.logaddexp(0.0, -logits)
    return log_alpha + log_scales.sum(axis=1)  # log of the importance; same order


def keep_rows(splats: SplatSet, method: str, count: int, seed: int = 0) -> np.ndarray:
    """Rows (ascending) of the ``count`` splats a baseline keeps."""
    n = splats.count
    if not 1 <= count <= n:
        raise InputError(f"cannot keep {count} of {n} splats")
    if method == "topk":
        order = np.argsort(-importance(splats), kind="stable")  # descending; ties by row
        rows = order[:count]
    elif method == "random":
        rows = np.random.default_rng(seed).choice(n, size=count, replace=False)
    else:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return np.sort(rows)


def subset(splats: SplatSet, rows: np.ndarray) -> SplatSet:
    """The splat set of ``rows`` (on the same device, same layout)."""
    host = splats.to_numpy()
    return SplatSet.from_numpy(**{k: v[rows] for k, v in host.items()}, layout=splats.layout, device=splats.device)


def baseline(splats: SplatSet, method: str, count: int, seed: int = 0) -> SplatSet:
    return subset(splats, keep_rows(splats, method, count, seed))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", type=Path, help="input 3DGS .ply")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .ply (OUT_<budget>.ply with several budgets)")
    parser.add_argument("--ratio", help="fractions to keep, e.g. 0.1,0.01,0.001")
    parser.add_argument("--count", help="splat counts to keep, e.g. 5000,500")
    parser.add_argument("--method", choices=METHODS, default="topk", help="topk (opacity x volume) or random")
    parser.add_argument("--seed", type=int, default=0, help="seed of --method random")
    args = parser.parse_args(argv)
    init_warp()
    try:
        budgets = parse_budgets(args.ratio, args.count)
        paths = output_paths(args.output, budgets)
        splats = load_ply(args.input, device="cpu")
        for budget in budgets:
            result = baseline(splats, args.method, budget.target(splats.count), args.seed)
            save_ply(result, paths[budget])
            print(f"{paths[budget]}: {result.count:,} splats ({args.method}, budget {budget.label})")
    except InputError as e:
        print(f"baselines: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
