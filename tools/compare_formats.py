"""Counts and attribute errors between a reference scene and the same scene in another file
(any format nanogs-warp reads), rows in the same order when the centres agree row by row, else matched by nearest centre (compressed
PLY and SOG reorder rows).

    python tools/compare_formats.py REFERENCE OTHER [OTHER ...]

Per file: splat counts, and over matched rows the largest and RMS difference of the centres
(relative to the scene's extent), log scales, opacity (alpha = sigmoid(logit)), DC colour
(0.5 + SH_C0 f_dc), higher SH coefficients (when both have them) and the rotation angle between
the quaternions, in degrees. Needs scipy.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nanogs_warp.io import load_splats
from nanogs_warp.io.common import SH_C0, sigmoid


def compare(ref: dict, other: dict) -> dict:
    extent = float(np.ptp(ref["means"], axis=0).max()) or 1.0
    if len(ref["means"]) == len(other["means"]) and np.abs(other["means"] - ref["means"]).max() < 1e-2 * extent:
        return _errors(ref, other, extent)  # the same row order (.splat, SPZ and PLY keep it)
    k = min(8, len(ref["means"]))
    _, near = cKDTree(ref["means"]).query(other["means"], k=k)  # quantised centres may coincide:
    near = near.reshape(len(other["means"]), k)  # among the nearest, the most similar splat
    cost = ((ref["log_scales"][near] - other["log_scales"][:, None, :]) ** 2).sum(axis=2)
    cost += (10.0 * (sigmoid(ref["opacities"])[near] - sigmoid(other["opacities"])[:, None])) ** 2
    cost += (((ref["means"][near] - other["means"][:, None, :]) / extent) ** 2).sum(axis=2) * 1e6
    match = near[np.arange(len(near)), np.argmin(np.nan_to_num(cost, nan=np.inf, posinf=np.inf), axis=1)]
    return _errors({key: v[match] for key, v in ref.items()}, other, extent)


def _errors(r: dict, other: dict, extent: float) -> dict:
    def stats(diff):
        d = np.abs(np.asarray(diff, dtype=np.float64)).reshape(-1)
        return {"max": float(d.max()), "rms": float(np.sqrt(np.mean(d * d)))}

    dot = np.abs(np.einsum("ij,ij->i", r["rotations"].astype(np.float64), other["rotations"].astype(np.float64)))
    out = {
        "count": [len(r["means"]), len(other["means"])],
        "means/extent": stats((other["means"] - r["means"]) / extent),
        "log_scales": stats(other["log_scales"] - r["log_scales"]),
        "alpha": stats(sigmoid(other["opacities"]) - sigmoid(r["opacities"])),
        "dc_colour": stats(SH_C0 * (other["features"][:, :3].astype(np.float64) - r["features"][:, :3])),
        "rotation_deg": stats(np.degrees(2 * np.arccos(np.clip(dot, 0, 1)))),
    }
    f = min(r["features"].shape[1], other["features"].shape[1])
    if f > 3:
        out["sh_rest"] = stats(other["features"][:, 3:f] - r["features"][:, 3:f])
    return out


def main(argv: list[str]) -> int:
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    ref = load_splats(argv[0]).to_numpy()
    for path in argv[1:]:
        result = compare(ref, load_splats(path).to_numpy())
        parts = [f"count {result.pop('count')[1]:,}/{len(ref['means']):,}"]
        parts += [f"{k} max {v['max']:.3g} rms {v['rms']:.3g}" for k, v in result.items()]
        print(f"{Path(path).name}: " + "; ".join(parts))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
