"""Crops the shipped sample scene, ``nanogs_warp/data/plant_crop.ply``, from a real 3DGS capture.

Source: ``plant.ply``, a potted plant captured by Marcel Padilla, CC-BY-4.0
(github.com/marcelpadilla/splats, ``data/plant/plant.splat``), converted to an INRIA PLY as
docs/scenes.md describes. Coordinates are y-down (COLMAP/INRIA), as in the source.

How the box is chosen (deterministic, no randomness):
1. Take the robust extent of the splat centres, the 0.5th..99.5th percentile per axis, and count
   centres in a 16 x 16 x 16 grid over it.
2. Sum each cell's 3 x 3 x 3 neighbourhood; the cell with the largest sum is the densest part
   (ties: the first in C order). Its centre is the box centre.
3. The box is the cube around that centre whose half-width is the Chebyshev (L-inf) distance of the
   ``count``-th nearest centre, so it holds ``count`` splats (more only on exact distance ties).
For plant.ply this is the top of the pot: soil, the stem's base and the lower leaves.

The crop keeps every splat in the box, in the source's order, written in the INRIA property order
(``x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*``) as float32 with the source's values
unchanged (quaternions included; they are already unit length in this source).

Usage: python tools/make_sample.py INPUT.ply OUTPUT.ply [--count 20000]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import plyfile

GRID = 16
PERCENTILES = (0.5, 99.5)
INRIA_PREFIX = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
INRIA_SUFFIX = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
COMMENT = "crop of plant.ply (Marcel Padilla, CC-BY-4.0) made by tools/make_sample.py"


def choose_box(means: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners of the crop cube; see the module docstring."""
    m = means.astype(np.float64)
    lo, hi = np.percentile(m, PERCENTILES[0], axis=0), np.percentile(m, PERCENTILES[1], axis=0)
    hist, edges = np.histogramdd(m, bins=GRID, range=list(zip(lo, hi)))
    padded = np.pad(hist, 1)
    density = sum(
        padded[i : i + GRID, j : j + GRID, k : k + GRID] for i in range(3) for j in range(3) for k in range(3)
    )
    cell = np.unravel_index(np.argmax(density), density.shape)
    centre = np.array([(e[i] + e[i + 1]) / 2 for e, i in zip(edges, cell)])
    chebyshev = np.abs(m - centre).max(axis=1)
    half = np.partition(chebyshev, min(count, len(m)) - 1)[min(count, len(m)) - 1]
    return centre - half, centre + half


def crop(input_path: Path, output_path: Path, count: int) -> tuple[int, np.ndarray, np.ndarray]:
    vertex = plyfile.PlyData.read(str(input_path))["vertex"].data
    names = vertex.dtype.names
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    order = [*INRIA_PREFIX, *rest, *INRIA_SUFFIX]
    means = np.stack([vertex[c] for c in ("x", "y", "z")], axis=1)
    lo, hi = choose_box(means, count)
    inside = np.all((means >= lo) & (means <= hi), axis=1)
    out = np.empty(int(inside.sum()), [(n, "<f4") for n in order])
    for n in order:
        out[n] = vertex[n][inside] if n in names else 0.0
    element = plyfile.PlyElement.describe(out, "vertex")
    plyfile.PlyData([element], byte_order="<", comments=[COMMENT]).write(str(output_path))
    return len(out), lo, hi


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("input", type=Path, help="source scene: plant.ply (docs/scenes.md)")
    parser.add_argument("output", type=Path, help="where to write the crop")
    parser.add_argument("--count", type=int, default=20000, help="splats to keep (default 20000)")
    args = parser.parse_args(argv)
    n, lo, hi = crop(args.input, args.output, args.count)
    size = args.output.stat().st_size
    print(f"{args.output}: {n} splats, {size:,} bytes, box lo {np.round(lo, 4).tolist()} hi {np.round(hi, 4).tolist()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
