"""Probe: would fitting each simplified splat again, to the ORIGINAL splats it stands for, help?

The merge operators fit a merged splat to its pair, pass after pass, so a splat of the final output
is a fit of fits. This probe fits each output splat once more, directly to the input's splats, and
writes the result next to the output for `nanogs-warp eval`. It is a float64 NumPy experiment (the splats' covariances from the kernels' references in tests/reference.py), not
part of the product (docs/quality.md has what it measured). Needs scipy (the `test` extra).

The pipeline does not record which originals became which output splat, so each original is given
to the output splat whose field a_m G_m(mu_o) is largest at its centre, among its 16 nearest
outputs. The fits (three views along the output splat's axes, as `field_opacity` in
kernels/field.py):

- ``colour``: the colour (every SH coefficient) that changes the colour field least for the output
  splat's shape and opacity: the originals' colours weighted by a_o S_om, S_om the overlap of the
  original with the output splat summed over the three views.
- ``shape-sum``: a scale factor k for all three axes of the output splat, from a grid of 0.5-2, and
  its opacity a(k) = min(sum_o a_o S_om(k) / S_mm(k), 254/255), that minimise the squared change of
  the originals' summed opacity field, sum_o a_o G_o.
- ``shape-composited``: the same against the originals' field as a renderer composites it,
  1 - prod_o (1 - a_o G_o), evaluated on a 16 x 16 grid per view (only for small outputs: it loops
  over the output splats in Python).

    python tools/final_fit_probe.py scene.ply small.ply small_fit.ply --fit shape-sum
    nanogs-warp eval scene.ply small.ply small_fit.ply
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.splats import SplatSet

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from reference import axis_variances, rotation_matrices, sigmoid  # noqa: E402 - the kernels' float64 references

VIEWS = ((0, 1), (0, 2), (1, 2))  # the plane of each view, in the output splat's axes
SCALES = np.array([0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.12, 1.25, 1.4, 1.6, 1.8, 2.0])
ALPHA_MAX = 254.0 / 255.0
NEAREST = 16


def float64_arrays(splats: SplatSet) -> dict[str, np.ndarray]:
    d = splats.to_numpy()
    rotation = rotation_matrices(d["rotations"])
    variances = axis_variances(d["log_scales"])
    return d | {
        "mu": d["means"].astype(np.float64),
        "frame": rotation,
        "variances": variances,
        "cov": np.einsum("nij,nj,nkj->nik", rotation, variances, rotation),
        "alpha": sigmoid(d["opacities"]),
    }


def owners(orig: dict, out: dict) -> np.ndarray:
    """For each original, the output splat of largest a_m G_m(mu_o) among its nearest outputs."""
    k = min(NEAREST, len(out["mu"]))
    _, near = cKDTree(out["mu"]).query(orig["mu"], k=k)
    near = near.reshape(len(orig["mu"]), k)
    best = np.full(len(orig["mu"]), -np.inf)
    owner = np.zeros(len(orig["mu"]), dtype=np.int64)
    for c in range(k):
        m = near[:, c]
        d = orig["mu"] - out["mu"][m]
        log_field = np.log(out["alpha"][m]) - 0.5 * np.einsum("ni,nij,nj->n", d, np.linalg.inv(out["cov"][m]), d)
        better = log_field > best
        best[better] = log_field[better]
        owner[better] = m[better]
    return owner


def overlaps_with_owner(orig: dict, out: dict, owner: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """S_om: each original's overlap with its owner (axes scaled by ``scale``), summed over the three
    views: 2 pi sqrt(det A det B / det(A + B)) exp(-d^T (A + B)^-1 d / 2) per view."""
    frame = out["frame"][owner]
    d = np.einsum("nji,nj->ni", frame, orig["mu"] - out["mu"][owner])
    a = np.einsum("nji,njk,nkl->nil", frame, orig["cov"], frame)
    total = np.zeros(len(owner))
    for u, w in VIEWS:
        a00, a01, a11 = a[:, u, u], a[:, u, w], a[:, w, w]
        b00 = out["variances"][owner, u] * scale**2
        b11 = out["variances"][owner, w] * scale**2
        s00, s11 = a00 + b00, a11 + b11
        det_s = s00 * s11 - a01 * a01
        det_a = np.maximum(a00 * a11 - a01 * a01, 0.0)
        x, y = d[:, u], d[:, w]
        q = (s11 * x * x - 2 * a01 * x * y + s00 * y * y) / det_s
        total += 2 * np.pi * np.sqrt(det_a * b00 * b11 / det_s) * np.exp(-0.5 * q)
    return total


def self_overlaps(out: dict, scale: float = 1.0) -> np.ndarray:
    """S_mm summed over the three views: pi sqrt(det B) per view."""
    v = out["variances"] * scale**2
    return sum(np.pi * np.sqrt(v[:, u] * v[:, w]) for u, w in VIEWS)


def fit_colour(orig: dict, out: dict, owner: np.ndarray) -> dict:
    weight = orig["alpha"] * overlaps_with_owner(orig, out, owner)
    n = len(out["mu"])
    total = np.bincount(owner, weight, minlength=n)
    features = orig["features"].astype(np.float64)
    summed = np.stack([np.bincount(owner, weight * features[:, c], minlength=n) for c in range(features.shape[1])], 1)
    fitted = out["features"].astype(np.float64)
    has = total > 0
    fitted[has] = summed[has] / total[has, None]
    return {"features": fitted}


def best_scale(out: dict, owned: np.ndarray, field_dot: np.ndarray, self_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per output splat, the scale (row of SCALES) and opacity that minimise -2 a <T, G> + a^2 <G, G>
    (the squared change up to the target's own energy), a clamped to (0, ALPHA_MAX]; a splat that
    no original was given to (``owned`` false) keeps its scale and opacity."""
    alpha = np.clip(field_dot / self_dot, 1e-6, ALPHA_MAX)
    change = -2 * alpha * field_dot + alpha**2 * self_dot
    best = np.argmin(change, axis=0)
    rows = np.arange(change.shape[1])
    return np.where(owned, SCALES[best], 1.0), np.where(owned, alpha[best, rows], out["alpha"])


def fit_shape_sum(orig: dict, out: dict, owner: np.ndarray) -> dict:
    n = len(out["mu"])
    field_dot = np.stack([np.bincount(owner, orig["alpha"] * overlaps_with_owner(orig, out, owner, s), minlength=n) for s in SCALES])
    self_dot = np.stack([self_overlaps(out, s) for s in SCALES])
    scale, alpha = best_scale(out, np.bincount(owner, minlength=n) > 0, field_dot, self_dot)
    return {"scale": scale, "alpha": alpha}


def fit_shape_composited(orig: dict, out: dict, owner: np.ndarray, grid: int = 16) -> dict:
    n = len(out["mu"])
    t = np.linspace(-1.0, 1.0, grid) * 3 * SCALES.max()
    order = np.argsort(owner, kind="stable")
    starts = np.searchsorted(owner[order], np.arange(n + 1))
    field_dot = np.zeros((len(SCALES), n))
    self_dot = np.ones((len(SCALES), n))
    for m in range(n):
        mine = order[starts[m] : starts[m + 1]]
        if len(mine) == 0:
            continue
        frame = out["frame"][m]
        d = (orig["mu"][mine] - out["mu"][m]) @ frame
        a = np.einsum("ji,njk,kl->nil", frame, orig["cov"][mine], frame)
        self_dot[:, m] = 0.0
        for u, w in VIEWS:
            su, sw = np.sqrt(out["variances"][m, u]), np.sqrt(out["variances"][m, w])
            x, y = (g.ravel() for g in np.meshgrid(t * su, t * sw, indexing="ij"))
            area = (t[1] - t[0]) ** 2 * su * sw
            a00, a01, a11 = a[:, u, u, None], a[:, u, w, None], a[:, w, w, None]
            det = np.maximum(a00 * a11 - a01 * a01, 1e-300)
            dx, dy = x - d[:, u, None], y - d[:, w, None]
            g = np.exp(-0.5 * (a11 * dx * dx - 2 * a01 * dx * dy + a00 * dy * dy) / det)
            composited = 1 - np.prod(1 - orig["alpha"][mine, None] * g, axis=0)
            for i, s in enumerate(SCALES):
                gm = np.exp(-0.5 * (x * x / out["variances"][m, u] + y * y / out["variances"][m, w]) / s**2)
                field_dot[i, m] += (composited * gm).sum() * area
                self_dot[i, m] += (gm * gm).sum() * area
    scale, alpha = best_scale(out, starts[1:] > starts[:-1], field_dot, self_dot)
    return {"scale": scale, "alpha": alpha}


FITS = {"colour": fit_colour, "shape-sum": fit_shape_sum, "shape-composited": fit_shape_composited}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("original", help="the unsimplified scene (.ply)")
    parser.add_argument("simplified", help="its simplified output (.ply)")
    parser.add_argument("output", help="where to write the re-fitted splats (.ply)")
    parser.add_argument("--fit", choices=sorted(FITS), required=True)
    args = parser.parse_args()
    small = load_ply(args.simplified)
    orig, out = float64_arrays(load_ply(args.original)), float64_arrays(small)
    owner = owners(orig, out)
    fitted = FITS[args.fit](orig, out, owner)
    d = dict(out)
    if "features" in fitted:
        d["features"] = fitted["features"].astype(np.float32)
    if "scale" in fitted:
        d["log_scales"] = (out["log_scales"].astype(np.float64) + np.log(fitted["scale"])[:, None]).astype(np.float32)
        d["opacities"] = np.log(fitted["alpha"] / (1 - fitted["alpha"])).astype(np.float32)
        counts = {float(s): int((fitted["scale"] == s).sum()) for s in SCALES}
        print("scale factors chosen:", {s: c for s, c in counts.items() if c})
    result = SplatSet.from_numpy(
        d["means"], d["rotations"], d["log_scales"], d["opacities"], d["features"], d.get("extras"),
        layout=small.layout, device="cpu", integer_extras=d.get("integer_extras"),
    )  # fmt: skip
    save_ply(result, args.output)


if __name__ == "__main__":
    main()
