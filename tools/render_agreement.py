"""Render a scene from the default orbit cameras on one device, or compare two such renders
(e.g. CPU here and CUDA on a GPU machine):

    python tools/render_agreement.py render scene.ply cpu.npy --device cpu
    python tools/render_agreement.py compare cpu.npy cuda.npy
"""

from __future__ import annotations

import argparse

import numpy as np

from nanogs_warp.device import resolve_device
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels
from nanogs_warp.eval.cameras import orbit_cameras
from nanogs_warp.eval.render import render_views
from nanogs_warp.io.ply import load_ply


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render")
    r.add_argument("scene")
    r.add_argument("out")
    r.add_argument("--device", default="auto")
    r.add_argument("--views", type=int, default=16)
    r.add_argument("--size", type=int, default=256)
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    args = parser.parse_args()
    if args.command == "render":
        device = resolve_device(args.device)
        load_kernels(device, ALL_MODULES)  # as the commands load them: no compile where they ship
        splats = load_ply(args.scene, device=device)
        np.save(args.out, render_views(splats, orbit_cameras(splats, args.views, args.size)))
    else:
        a, b = np.load(args.a), np.load(args.b)
        diff = np.abs(a - b)
        print(f"{a.shape[0]} views {a.shape[2]}x{a.shape[1]}: max |diff| {diff.max():.2e}, mean {diff.mean():.2e}, "
              f"pixels > 1e-4: {(diff.max(-1) > 1e-4).mean():.4%}, > 1/255: {(diff.max(-1) > 1 / 255).mean():.4%}")


if __name__ == "__main__":
    main()
