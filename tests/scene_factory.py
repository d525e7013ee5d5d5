"""Small seeded splat scenes for tests: host arrays, and INRIA-style PLY files written from them."""

from __future__ import annotations

import numpy as np
import plyfile

MEANS = ("x", "y", "z")
NORMALS = ("nx", "ny", "nz")
DC = ("f_dc_0", "f_dc_1", "f_dc_2")
SCALES = ("scale_0", "scale_1", "scale_2")
ROTS = ("rot_0", "rot_1", "rot_2", "rot_3")


def random_splat_arrays(n: int, sh_degree: int = 0, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays named as ``SplatSet.from_numpy``'s arguments (so ``SplatSet.from_numpy(**arrays)``
    works): means (N,3) ~ N(0,1); rotations (N,4) unit quaternions, w first; log_scales (N,3) in
    [-6,-1]; opacities (N,) logits ~ N(0,2); features (N, 3(d+1)^2) ~ N(0,0.5); extras (N,0).
    All float32 and writable."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "rotations": q.astype(np.float32),
        "log_scales": rng.uniform(-6.0, -1.0, size=(n, 3)).astype(np.float32),
        "opacities": rng.normal(scale=2.0, size=n).astype(np.float32),
        "features": rng.normal(scale=0.5, size=(n, 3 * (sh_degree + 1) ** 2)).astype(np.float32),
        "extras": np.zeros((n, 0), np.float32),
    }


def in_units(arrays: dict[str, np.ndarray], exponent: int) -> dict[str, np.ndarray]:
    """The same scene in units 2^exponent times smaller: centres times 2^exponent (exact in float32),
    log-scales plus exponent ln 2."""
    scaled = dict(arrays)
    scaled["means"] = (arrays["means"].astype(np.float64) * 2.0**exponent).astype(np.float32)
    scaled["log_scales"] = (arrays["log_scales"].astype(np.float64) + exponent * np.log(2.0)).astype(np.float32)
    return scaled


def random_splats_ply(
    path,
    n: int,
    sh_degree: int = 0,
    seed: int = 0,
    byte_order: str = "<",
    text: bool = False,
    dtype: str = "f4",
    extra_props=(),
    shuffle: bool = False,
) -> dict[str, np.ndarray]:
    """Writes ``random_splat_arrays(n, sh_degree, seed)`` as an INRIA 3DGS PLY file and returns the
    arrays as ``load_ply(path).to_numpy()`` should give them back (bit for bit).

    The file has ``nx ny nz`` (zeros) like INRIA's, so they lead the loaded ``extras``, followed by
    ``extra_props``: names (float32) or ``(name, dtype)`` pairs, filled with random values that
    the dtype holds exactly (those of an integer dtype are the loaded ``integer_extras``). ``dtype`` ('f4' or 'f8') is the type of the 3DGS properties and the
    normals; ``shuffle`` writes the vertex properties in a random (seeded) order.
    """
    arrays = random_splat_arrays(n, sh_degree, seed)
    return write_splats_ply(path, arrays, byte_order, text, dtype, extra_props, shuffle, seed)


def write_splats_ply(
    path,
    arrays: dict[str, np.ndarray],
    byte_order: str = "<",
    text: bool = False,
    dtype: str = "f4",
    extra_props=(),
    shuffle: bool = False,
    seed: int = 0,
    normals: bool = True,
    comments=(),
    obj_info=(),
    other_elements=(),
) -> dict[str, np.ndarray]:
    """Writes ``arrays`` (``random_splat_arrays`` names; quaternions need not be unit) as a PLY
    file; see ``random_splats_ply``. Returns the arrays, ready for ``SplatSet.from_numpy(**arrays)``,
    with ``extras`` (N, E) float32 holding the normals and the float extra properties in file order,
    ``integer_extras`` (N, I) int64 the integer ones."""
    rng = np.random.default_rng(seed + 1)
    n = arrays["means"].shape[0]
    n_rest = arrays["features"].shape[1] - 3
    columns: dict[str, tuple[np.ndarray, str]] = {}
    for names, key in ((MEANS, "means"), (SCALES, "log_scales"), (ROTS, "rotations")):
        for i, name in enumerate(names):
            columns[name] = (arrays[key][:, i], dtype)
    columns["opacity"] = (arrays["opacities"].reshape(n), dtype)
    for i in range(3 + n_rest):
        columns[DC[i] if i < 3 else f"f_rest_{i - 3}"] = (arrays["features"][:, i], dtype)
    extra_names, extra_cols = [], []
    if normals:
        for name in NORMALS:
            columns[name] = (np.zeros(n, np.float32), dtype)
            extra_names.append(name)
            extra_cols.append(np.zeros(n, np.float32))
    for prop in extra_props:
        name, pdtype = (prop, "f4") if isinstance(prop, str) else prop
        pdtype = np.dtype(pdtype)
        if pdtype.kind in "iu":
            info = np.iinfo(pdtype)
            values = rng.integers(max(info.min, -1000), min(info.max, 1000), n, endpoint=True).astype(pdtype)
        else:
            values = rng.normal(size=n).astype(np.float32).astype(pdtype)
        columns[name] = (values, pdtype.str[1:])
        extra_names.append(name)
        extra_cols.append(values)

    order = [*MEANS, *(NORMALS if normals else ()), *DC, *(f"f_rest_{i}" for i in range(n_rest)),
             "opacity", *SCALES, *ROTS, *extra_names[3 if normals else 0 :]]
    if shuffle:
        order = [order[i] for i in rng.permutation(len(order))]
        extra_names = [name for name in order if name in set(extra_names)]
        extra_cols = [columns[name][0] for name in extra_names]
    record = np.empty(n, [(name, columns[name][1]) for name in order])
    for name in order:
        record[name] = columns[name][0]
    vertex = plyfile.PlyElement.describe(record, "vertex")
    plyfile.PlyData(
        [vertex, *other_elements], text=text, byte_order=byte_order, comments=list(comments), obj_info=list(obj_info)
    ).write(str(path))

    with np.errstate(over="ignore"):  # float64 test values may overflow float32, as in load_ply
        out = {k: np.array(v, dtype=np.float32) for k, v in arrays.items() if k not in ("extras", "integer_extras")}
    floats = [c.astype(np.float32) for c in extra_cols if c.dtype.kind not in "iu"]
    integers = [c.astype(np.int64) for c in extra_cols if c.dtype.kind in "iu"]
    out["extras"] = np.stack(floats, axis=1) if floats else np.zeros((n, 0), np.float32)
    out["integer_extras"] = np.stack(integers, axis=1) if integers else np.zeros((n, 0), np.int64)
    return out


def write_2dgs_copy(src, dst, byte_order: str = "<", text: bool = False) -> None:
    """``src`` (a 3DGS PLY) written again without scale_2, as 2D Gaussian splatting stores its surfels."""
    data = plyfile.PlyData.read(str(src))["vertex"].data
    names = [n for n in data.dtype.names if n != "scale_2"]
    rows = np.empty(len(data), [(n, data.dtype[n]) for n in names])
    for n in names:
        rows[n] = data[n]
    plyfile.PlyData([plyfile.PlyElement.describe(rows, "vertex")], text=text, byte_order=byte_order).write(str(dst))
