"""The same scene in other units: centres times 2^K and log-scales plus K ln 2 (the centres exactly,
as float32 holds them; the log-scales to float32's rounding). Used to check that a scene simplifies,
evaluates and refines alike in any units (docs/numerics.md); K = -K scales an output back.

    python tools/rescale_scene.py statue_st_peter.ply statue_x2e72.ply 72
"""

from __future__ import annotations

import argparse

from nanogs_warp.eval.units import rescaled
from nanogs_warp.io.ply import load_ply, save_ply


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input")
    parser.add_argument("output")
    parser.add_argument("exponent", type=int, help="K: centres times 2^K")
    args = parser.parse_args()
    save_ply(rescaled(load_ply(args.input), 2.0**args.exponent), args.output)


if __name__ == "__main__":
    main()
