"""Make a large scene by tiling a real one: copies offset by its bounding box on a 3D grid, so local
structure stays real. The last copy is cut so the result has exactly the requested count.

    python tools/tile_scene.py IN.ply OUT.ply --count 6000000
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.splats import SplatSet


def tile_arrays(arrays: dict[str, np.ndarray], count: int, gap: float = 0.05) -> dict[str, np.ndarray]:
    """``count`` rows: whole copies of ``arrays`` (from ``SplatSet.to_numpy``) placed on a grid of
    cells of the scene's bounding-box size plus ``gap`` of it, then a part of one more copy."""
    n = len(arrays["means"])
    copies = math.ceil(count / n)
    side = math.ceil(copies ** (1 / 3))
    lo, hi = arrays["means"].min(0), arrays["means"].max(0)
    step = (hi - lo) * (1 + gap)
    cell = np.stack(np.unravel_index(np.arange(copies), (side, side, side)), 1).astype(np.float32)
    out = {key: np.concatenate([value] * copies)[:count] for key, value in arrays.items()}
    out["means"] = out["means"] + np.repeat(cell * step, n, axis=0)[:count]
    return out


def tile_splats(splats: SplatSet, count: int, device=None) -> SplatSet:
    arrays = tile_arrays(splats.to_numpy(), count)
    return SplatSet.from_numpy(**arrays, layout=splats.layout, device=device or splats.device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input")
    parser.add_argument("output")
    parser.add_argument("--count", type=int, required=True)
    args = parser.parse_args()
    save_ply(tile_splats(load_ply(args.input), args.count), args.output)


if __name__ == "__main__":
    main()
