"""The same scene in other units: centres times 2^K and log-scales plus K ln 2 (the centres exactly,
as float32 holds them; the log-scales to float32's rounding). Used to check that a scene simplifies,
evaluates and refines alike in any units (docs/numerics.md); K = -K scales an output back.

    python tools/rescale_scene.py statue_st_peter.ply statue_x2e72.ply 72
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.splats import SplatSet


def rescaled_arrays(arrays: dict[str, np.ndarray], exponent: int) -> dict[str, np.ndarray]:
    """``arrays`` (from ``SplatSet.to_numpy``) in units 2^exponent times smaller: centres times
    2^exponent, log-scales plus exponent ln 2."""
    out = dict(arrays)
    out["means"] = (arrays["means"].astype(np.float64) * 2.0**exponent).astype(np.float32)
    out["log_scales"] = (arrays["log_scales"].astype(np.float64) + exponent * math.log(2.0)).astype(np.float32)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input")
    parser.add_argument("output")
    parser.add_argument("exponent", type=int, help="K: centres times 2^K")
    args = parser.parse_args()
    splats = load_ply(args.input)
    save_ply(SplatSet.from_numpy(**rescaled_arrays(splats.to_numpy(), args.exponent), layout=splats.layout), args.output)


if __name__ == "__main__":
    main()
