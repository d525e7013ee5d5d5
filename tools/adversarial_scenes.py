"""Scenes made to defeat the search structures, for their work bounds (docs/numerics.md, "Scenes in
any units", and docs/performance.md, "Pairing"), and the rasteriser's tile binning: made
deterministically (seeded), nothing is committed as data.

    python tools/adversarial_scenes.py OUT_DIR --count 400000 [--seed 0]

Writes five INRIA 3DGS PLY files (SH degree 0; where not said otherwise, rotations, log-scales in
[-6, -1], opacity logits N(0, 2) and colours N(0, 0.5) as ordinary random splats):

- ``ray.ply``: every centre on the x axis at 10^U(-30, 30): sixty decades, so most squared
  distances between centres are 0 or +inf in float32 (the kNN's work limit).
- ``bits.ply``: every coordinate a random float32 bit pattern (infinities and NaNs set to 0), as
  random bytes give: every magnitude from 1e-45 to 3e38 about equally often, either sign.
- ``clusters.ply``: two clusters of ordinary spacing (normal-distributed centres, sigma 1), one at
  x = +1e30 and one at -1e30 (x rounds to exactly that in float32: each cluster is flat). The
  scene's extent is 2e30, its neighbours a hundredth apart: measured at the extent's scale, their
  squared distances would be zero in float32 (the kNN's spacing rule).
- ``chain.ply``: chains of up to 100,000 alike splats (one colour, one opacity, axis-aligned),
  side by side along y, each along x and spaced ever wider (x_i = 10^(6 i / 100,000)), each splat
  as long as its spacing: merge costs grow along every chain, which would take the GPU's parallel
  pairing one round per pair (its bounded rounds).
- ``needles.ply``: faint needles of random direction (opacity 0.05, as long as the scene is wide,
  a thousandth of that thick) around the origin: each one's tile rectangle is most of a view, and
  it reaches the tiles along a line across it (the rasteriser's ``reached_columns``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def random_splats(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    q = rng.normal(size=(n, 4))
    return {
        "rotations": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        "log_scales": rng.uniform(-6.0, -1.0, (n, 3)).astype(np.float32),
        "opacities": rng.normal(scale=2.0, size=n).astype(np.float32),
        "features": rng.normal(scale=0.5, size=(n, 3)).astype(np.float32),
    }


def ray_centres(n: int, rng: np.random.Generator) -> np.ndarray:
    centres = np.zeros((n, 3), np.float32)
    centres[:, 0] = 10.0 ** rng.uniform(-30.0, 30.0, n)
    return centres


def bit_centres(n: int, rng: np.random.Generator) -> np.ndarray:
    centres = rng.integers(0, 2**32, size=(n, 3), dtype=np.uint64).astype(np.uint32).view(np.float32).copy()
    centres[~np.isfinite(centres)] = 0.0
    return centres


CHAIN = 100_000  # splats a chain: float32 still orders the costs of neighbouring pairs


def chain_splats(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    step = np.arange(n) % CHAIN
    x = 10.0 ** (6.0 * step / CHAIN)
    spacing = x * (10.0 ** (6.0 / CHAIN) - 1.0)
    a = random_splats(n, rng)
    a["means"] = np.c_[x, 3e6 * (np.arange(n) // CHAIN), np.zeros(n)].astype(np.float32)
    a["log_scales"] = np.log(np.c_[spacing, spacing / 2, spacing / 2]).astype(np.float32)
    a["rotations"][:] = (1.0, 0.0, 0.0, 0.0)
    a["opacities"][:] = 2.0
    a["features"][:] = 0.0
    return a


def with_centres(centres):
    def make(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        a = random_splats(n, rng)
        a["means"] = centres(n, rng)
        return a

    return make


def cluster_centres(n: int, rng: np.random.Generator) -> np.ndarray:
    centres = rng.normal(size=(n, 3)).astype(np.float32)
    centres[: n // 2, 0] = np.float32(1e30)
    centres[n // 2 :, 0] = np.float32(-1e30)
    return centres


def needle_splats(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    a = random_splats(n, rng)
    a["means"] = rng.normal(size=(n, 3)).astype(np.float32)
    a["log_scales"] = np.log(np.c_[np.full(n, 2.0), np.full(n, 2e-3), np.full(n, 2e-3)]).astype(np.float32)
    a["opacities"][:] = np.float32(np.log(0.05 / 0.95))
    return a


SCENES = {
    "ray": with_centres(ray_centres),
    "bits": with_centres(bit_centres),
    "chain": chain_splats,
    "clusters": with_centres(cluster_centres),
    "needles": needle_splats,
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--count", type=int, default=100_000, help="splats a scene")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from stress_scenes import write_scene  # this folder's: a script's own folder is on the path

    args.out_dir.mkdir(parents=True, exist_ok=True)
    for k, (name, make) in enumerate(SCENES.items()):
        write_scene(make(args.count, np.random.default_rng(args.seed * 100 + k)), args.out_dir / f"{name}.ply")
    return 0


if __name__ == "__main__":
    sys.exit(main())
