"""A 2D Gaussian splatting (2DGS) copy of a 3DGS scene, to try 2DGS input with: each splat keeps its
two largest axes as scale_0 and scale_1 (its rotation turned so that they come first) and loses the
smallest; every other property stays as it was.

    python tools/surfel_scene.py IN.ply OUT.ply
"""

from __future__ import annotations

import argparse

import numpy as np
import plyfile

# The quaternions (w, x, y, z) of the two cyclic turns of the axes: the axes (1, 2, 0) and (2, 0, 1)
# of the old frame become the new frame's (0, 1, 2).
_TURNS = {0: np.array([0.5, 0.5, 0.5, 0.5]), 1: np.array([0.5, -0.5, -0.5, -0.5])}


def hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The quaternion products a b of (N, 4) w-first quaternions: the rotation of b, then a's."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], 1)  # fmt: skip


def surfel_rows(vertex: np.ndarray) -> np.ndarray:
    """The vertex rows of a 3DGS PLY as a 2DGS file's: without scale_2, the smallest axis's."""
    scales = np.stack([vertex[f"scale_{a}"] for a in range(3)], 1).astype(np.float64)
    rotations = np.stack([vertex[f"rot_{a}"] for a in range(4)], 1).astype(np.float64)
    smallest = np.argmin(scales, axis=1)
    for axis, turn in _TURNS.items():
        rows = smallest == axis
        order = [(axis + 1) % 3, (axis + 2) % 3]  # the new scale_0, scale_1
        rotations[rows] = hamilton(rotations[rows], np.broadcast_to(turn, (int(rows.sum()), 4)))
        scales[rows, :2] = scales[rows][:, order]
    names = [n for n in vertex.dtype.names if n != "scale_2"]
    out = np.empty(len(vertex), [(n, vertex.dtype[n]) for n in names])
    for n in names:
        out[n] = vertex[n]
    for a in range(2):
        out[f"scale_{a}"] = scales[:, a]
    for a in range(4):
        out[f"rot_{a}"] = rotations[:, a]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input")
    parser.add_argument("output")
    args = parser.parse_args()
    ply = plyfile.PlyData.read(args.input)
    if "scale_2" not in ply["vertex"].data.dtype.names:
        raise SystemExit(f"{args.input}: no scale_2 (a 2DGS file already?)")
    vertex = plyfile.PlyElement.describe(surfel_rows(ply["vertex"].data), "vertex")
    others = [e for e in ply.elements if e.name != "vertex"]
    plyfile.PlyData([vertex, *others], comments=list(ply.comments)).write(args.output)


if __name__ == "__main__":
    main()
