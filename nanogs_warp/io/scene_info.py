"""What a splat file holds, including the values that would fail a load, as a JSON-ready dict
(``nanogs-warp info`` prints it: :mod:`nanogs_warp.cli.info`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import read_splat_arrays
from .ply import check_values, sh_degree_for_rest_count


def scene_info(path) -> dict:
    """Facts about a splat file (any format :func:`nanogs_warp.io.load_splats` reads) as a JSON-ready dict.

    Keys: ``file``, ``file_bytes``, ``trailing_bytes`` (of a binary PLY after the data its header
    declares, which a load ignores), ``format``, ``count``, ``sh_degree``, ``properties`` (list of
    ``{"name", "dtype"}`` in file order), ``extra_properties``, ``model`` (``3DGS``, or ``2DGS`` for
    a PLY of surfels without ``scale_2``, which a load reads as flat 3DGS splats), ``bbox``
    (``min``/``max`` xyz over rows with finite means), ``opacity`` (sigmoid of the logits: min,
    median, mean, max), ``scale`` (exp of the log scales over the file's axes, three or a 2DGS
    file's two: min, median, max), ``nonfinite``
    (property -> rows with NaN/Inf, extras included, only non-zero counts), ``nonfinite_rows``
    (rows with NaN/Inf in any property, which a load rejects), ``infinite_opacity``
    (``{"+inf": rows, "-inf": rows}``: opacity logits of alpha 1 and 0, valid), ``zero_norm_quaternions``,
    ``out_of_domain`` (log-scale property -> finite values outside the numeric domain, which a load
    rejects too; only non-zero counts), ``out_of_domain_rows``,
    ``comments``, ``obj_info`` and ``other_elements`` (``{"name", "count", "properties"}``).
    Statistics skip non-finite values and are None when no finite value is left.
    For non-PLY formats ``properties`` lists the decoded attributes in INRIA order.
    Raises InputError for files that are not readable splat files; never for bad values.
    """
    data = read_splat_arrays(path)
    a = data.arrays
    layout = data.layout
    check = check_values(a, extra_names=layout.float_extra_names)  # integer extras are always finite
    means = a["means"]
    finite_means = means[np.isfinite(means).all(axis=1)]
    with np.errstate(all="ignore"):
        logits = a["opacities"].reshape(-1).astype(np.float64)
        logits = logits[~np.isnan(logits)]  # +-Inf count: alpha 1 and 0
        opacity = np.exp(-np.logaddexp(0.0, -logits))  # sigmoid without overflow
        axes = 2 if layout.surfels else 3  # a 2DGS file's third axis is the load's, not the file's
        scales = np.exp(_finite(a["log_scales"][:, :axes]).astype(np.float64))
    return {
        "file": Path(path).name,
        "file_bytes": data.file_bytes,
        "trailing_bytes": data.trailing_bytes,
        "format": data.format,
        "count": data.count,
        "sh_degree": sh_degree_for_rest_count(a["features"].shape[1] - 3),
        "properties": [{"name": n, "dtype": t} for n, t in layout.properties],
        "extra_properties": list(layout.extra_names),
        "model": "2DGS" if layout.surfels else "3DGS",
        "bbox": {
            "min": _floats(finite_means.min(axis=0)) if len(finite_means) else None,
            "max": _floats(finite_means.max(axis=0)) if len(finite_means) else None,
        },
        "opacity": _stats(opacity, ("min", "median", "mean", "max")),
        "scale": _stats(scales, ("min", "median", "max")),
        "nonfinite": check.nonfinite_by_property,
        "nonfinite_rows": int(np.count_nonzero(check.nonfinite_rows)),
        "infinite_opacity": {"+inf": check.infinite_opacities[0], "-inf": check.infinite_opacities[1]},
        "zero_norm_quaternions": int(np.count_nonzero(check.zero_quat_rows)),
        "out_of_domain": check.out_of_domain_by_property,
        "out_of_domain_rows": int(np.count_nonzero(check.out_of_domain_rows)),
        "comments": list(layout.comments),
        "obj_info": list(layout.obj_info),
        "other_elements": [
            {"name": e.name, "count": int(e.count), "properties": [p.name for p in e.properties]}
            for e in layout.other_elements
        ],
    }


def _finite(x: np.ndarray) -> np.ndarray:
    x = x.reshape(-1)
    return x[np.isfinite(x)]


def _floats(x) -> list[float]:
    return [float(v) for v in x]


def _stats(values: np.ndarray, keys) -> dict | None:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    funcs = {"min": np.min, "median": np.median, "mean": np.mean, "max": np.max}
    return {k: float(funcs[k](values)) for k in keys}
