"""Agreement of two sets of outputs (e.g. CPU and CUDA runs of the same scenes and budgets).

    python tools/compare_outputs.py CPU_DIR CUDA_DIR

For every .ply present in both: counts, the fraction of rows identical to the bit, the largest
relative difference of each attribute row by row, and, since one different neighbour choice makes
later passes diverge, the distance from each splat centre to the nearest centre of the other set
(relative to the scene's extent).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nanogs_warp.io.ply import load_ply


def compare(a_path: Path, b_path: Path) -> str:
    a, b = load_ply(a_path).to_numpy(), load_ply(b_path).to_numpy()
    if len(a["means"]) != len(b["means"]):
        return f"{a_path.name}: counts differ {len(a['means'])} vs {len(b['means'])}"
    same = np.ones(len(a["means"]), bool)
    worst = {}
    for key in ("means", "log_scales", "opacities", "features"):
        x, y = a[key].reshape(len(same), -1), b[key].reshape(len(same), -1)
        same &= np.all(x == y, axis=1)
        scale = np.abs(x).max() or 1.0
        worst[key] = float(np.abs(x - y).max() / scale)
    extent = float(np.ptp(a["means"], axis=0).max()) or 1.0
    nearest, _ = cKDTree(a["means"]).query(b["means"])
    return (
        f"{a_path.name}: {len(same):,} splats, identical rows {same.mean():.1%}, max rel diff "
        + " ".join(f"{k}={v:.1e}" for k, v in worst.items())
        + f", nearest-centre distance / extent: median {np.median(nearest) / extent:.1e} max {nearest.max() / extent:.1e}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a_dir", type=Path, help="a folder of outputs (e.g. the CPU's)")
    parser.add_argument("b_dir", type=Path, help="a folder of the same outputs made otherwise (e.g. the GPU's)")
    args = parser.parse_args()
    for a_path in sorted(args.a_dir.glob("*.ply")):
        b_path = args.b_dir / a_path.name
        if b_path.exists():
            print(compare(a_path, b_path), flush=True)


if __name__ == "__main__":
    main()
