"""The splat set: one struct of arrays on one device, passed explicitly to every stage."""

from __future__ import annotations

import numbers
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from .domain import saturate_opacity_logits

if TYPE_CHECKING:
    from .io.ply_layout import PlyLayout


@dataclass
class SplatSet:
    """N Gaussian splats in the INRIA 3DGS parameterisation, all arrays on ``device``.

    - ``means``: centres, vec3.
    - ``rotations``: unit quaternions in Warp's (x, y, z, w) order (PLY stores w first).
    - ``log_scales``: natural-log standard deviations along the rotated axes, vec3.
    - ``opacities``: opacity logits (the activated opacity is sigmoid(logit)).
    - ``features``: (N, F) spherical-harmonics coefficients in file order, f_dc_0..2 then f_rest_*
      (channel-major: all R coefficients, then G, then B).
    - ``extras``: (N, E) the other per-vertex properties of a floating-point type, carried through a
      simplification (merged: weighted as the features; E may be 0).
    - ``integer_extras``: (N, I) int64, the other per-vertex properties of an integer type, carried
      exactly (merged: the value of the pair's heavier splat; I may be 0, and is by default).

    Every array's layout here, in ``to_numpy()`` and in ``to_torch()`` (gsplat's: w-first
    quaternions, SH as (N, K, 3)) is described in one place, docs/api.md.
    """

    means: wp.array
    rotations: wp.array
    log_scales: wp.array
    opacities: wp.array
    features: wp.array
    extras: wp.array
    layout: PlyLayout | None = None
    integer_extras: wp.array | None = None  # None: (N, 0)

    def __post_init__(self):
        if not isinstance(self.means, wp.array):
            raise TypeError(f"SplatSet.means must be a Warp array, got {type(self.means).__name__}")
        if self.integer_extras is None:
            self.integer_extras = wp.empty((self.means.shape[0], 0), dtype=wp.int64, device=self.means.device)
        self._check_arrays()

    def _check_arrays(self) -> None:
        """Every array a Warp array of its dtype and dimensions, with one row per splat, on the means'
        device, and 3 (d + 1)^2 features for an SH degree d of 0 to 3: a kernel given a shorter array
        would read and write memory it does not own."""
        n, device = self.means.shape[0], self.means.device
        for name, (dtype, ndim) in _ARRAY_LAYOUT.items():
            a = getattr(self, name)
            if not isinstance(a, wp.array):
                raise TypeError(f"SplatSet.{name} must be a Warp array, got {type(a).__name__}")
            if a.dtype is not dtype or a.ndim != ndim:
                raise ValueError(f"SplatSet.{name} must be a {ndim}-D Warp array of {dtype.__name__}, "
                                 f"got a {a.ndim}-D array of {getattr(a.dtype, '__name__', a.dtype)}")  # fmt: skip
            if a.shape[0] != n:
                raise ValueError(f"SplatSet.{name} has {a.shape[0]} rows, not one per splat ({n}, as means)")
            if a.device != device:
                raise ValueError(f"SplatSet.{name} is on {a.device}, the means on {device}: one splat set lives on one device")
        sh_degree_for_features(self.features.shape[1])

    @property
    def count(self) -> int:
        return self.means.shape[0]

    def __len__(self) -> int:
        return self.count

    @property
    def device(self) -> wp.Device:
        return self.means.device

    @property
    def sh_degree(self) -> int:
        return sh_degree_for_features(self.features.shape[1])

    @staticmethod
    def from_numpy(
        means: np.ndarray,
        rotations: np.ndarray,
        log_scales: np.ndarray,
        opacities: np.ndarray,
        features: np.ndarray,
        extras: np.ndarray | None = None,
        layout: PlyLayout | None = None,
        device=None,
        integer_extras: np.ndarray | None = None,
        validate: bool = True,
    ) -> SplatSet:
        """Builds a splat set from host arrays; quaternions are given w-first, as PLY stores them.

        ``extras`` may also hold every extra property of ``layout`` (integer ones included, as
        floats) when ``integer_extras`` is not given: the integer columns are then rounded (half to
        even) and clipped to their type. Arrays of the wrong shape raise ValueError naming them;
        with ``validate`` (the default), values a scene file may not hold either raise InputError,
        as on reading a file: NaN or infinite values (opacity logits of +-Inf are valid: alpha 1
        or 0, kept as +-the largest float32 as on reading), quaternions of norm 0, log-scales
        beyond the numeric domain."""
        device = warp_device(device)
        means = _host_rows("means", means, 3)
        n = means.shape[0]
        rotations = _host_rows("rotations", rotations, 4, n)
        log_scales = _host_rows("log_scales", log_scales, 3, n)
        opacities = _host_rows("opacities", opacities, None, n)
        features = _host_rows("features", features, 0, n)
        sh_degree_for_features(features.shape[1])
        extras = np.zeros((n, 0), np.float32) if extras is None else _host_rows("extras", extras, 0, n)
        if integer_extras is not None:
            integer_extras = _whole_numbers("integer_extras", _host_rows("integer_extras", integer_extras, 0, n))
            _check_integer_types(integer_extras, layout)
        else:  # integer columns given as floats are rounded and clipped (NaN as 0)
            extras, integer_extras = split_integer_extras(np.asarray(extras), layout)
        if validate:
            _check_values(means, rotations, log_scales, opacities, features, extras)
            # logits of +-Inf (alpha 1 and 0) become +-the largest float32, as a file's do on reading
            with np.errstate(over="ignore"):
                opacities = saturate_opacity_logits(np.asarray(opacities, dtype=np.float32))
        quat_xyzw = np.ascontiguousarray(np.asarray(rotations, dtype=np.float32)[:, [1, 2, 3, 0]])

        def f32(a, shape):
            with np.errstate(over="ignore", invalid="ignore"):  # unchecked (validate=False): taken as float32 holds it
                return np.ascontiguousarray(np.asarray(a, dtype=np.float32).reshape(shape))

        def i64(a, shape):
            return np.ascontiguousarray(np.asarray(a, dtype=np.int64).reshape(shape))

        return SplatSet(
            means=wp.array(f32(means, (n, 3)), dtype=wp.vec3, device=device),
            rotations=wp.array(quat_xyzw, dtype=wp.quat, device=device),
            log_scales=wp.array(f32(log_scales, (n, 3)), dtype=wp.vec3, device=device),
            opacities=wp.array(f32(opacities, (n,)), dtype=wp.float32, device=device),
            features=wp.array(f32(features, (n, features.shape[1])), dtype=wp.float32, device=device),
            extras=wp.array(f32(extras, (n, extras.shape[1])), dtype=wp.float32, device=device),
            layout=layout,
            integer_extras=wp.array(i64(integer_extras, (n, integer_extras.shape[1])), dtype=wp.int64, device=device),
        )

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Host copies of every attribute (never views of device memory): means, rotations (w-first),
        log_scales, opacities, features, extras, integer_extras."""
        quat = self.rotations.numpy().reshape(-1, 4)
        return {
            "means": self.means.numpy().reshape(-1, 3).copy(),
            "rotations": np.ascontiguousarray(quat[:, [3, 0, 1, 2]]),
            "log_scales": self.log_scales.numpy().reshape(-1, 3).copy(),
            "opacities": self.opacities.numpy().reshape(-1).copy(),
            "features": self.features.numpy().copy(),
            "extras": self.extras.numpy().copy(),
            "integer_extras": self.integer_extras.numpy().copy(),
        }

    def to_gsplat_numpy(self) -> dict[str, np.ndarray]:
        """Host arrays in gsplat's layout (docs/api.md): ``means`` (N, 3); ``quats`` (N, 4) w-first;
        ``scales`` (N, 3) natural-log; ``opacities`` (N,) logits; ``sh`` (N, K, 3) with K = (d + 1)^2,
        coefficient-major (``sh[:, 0]`` the DC term, as gsplat's sh0 = sh[:, :1], shN = sh[:, 1:]);
        ``extras`` (N, E). float32, fresh copies; and ``integer_extras`` (N, I) int64."""
        host = self.to_numpy()
        n, f = host["features"].shape
        k = f // 3
        sh = np.empty((n, k, 3), np.float32)
        sh[:, 0, :] = host["features"][:, :3]
        sh[:, 1:, :] = host["features"][:, 3:].reshape(n, 3, k - 1).transpose(0, 2, 1)
        return {
            "means": host["means"],
            "quats": host["rotations"],
            "scales": host["log_scales"],
            "opacities": host["opacities"],
            "sh": sh,
            "extras": host["extras"],
            "integer_extras": host["integer_extras"],
        }

    def to_torch(self, device=None) -> dict:
        """``to_gsplat_numpy()``'s arrays as torch tensors on ``device`` (default: this splat set's
        device, e.g. "cuda:0" or "cpu"). PyTorch is imported here and is not a dependency of this
        package: without it this raises ImportError."""
        try:
            import torch
        except ImportError:
            raise ImportError("SplatSet.to_torch() needs PyTorch (pip install torch)") from None
        target = str(device if device is not None else self.device)
        return {name: torch.from_numpy(array).to(target) for name, array in self.to_gsplat_numpy().items()}

    def to(self, device) -> SplatSet:
        """This splat set on ``device`` (itself when it is already there)."""
        device = warp_device(device)
        if device == self.device:
            return self
        return self.clone(device)

    def clone(self, device=None) -> SplatSet:
        """A copy of every array, on ``device`` (default: this splat set's), with the same layout."""
        device = self.device if device is None else device
        return replace(self, **{f.name: wp.clone(getattr(self, f.name), device=device) for f in _ARRAY_FIELDS})

    def with_sh_degree(self, degree: int) -> SplatSet:
        """This splat set with spherical harmonics up to ``degree`` only (0: the base colour alone),
        its other arrays shared; itself when its degree is not above ``degree``. The kept
        coefficients are copied exactly: f_dc, then each channel's first (degree + 1)^2 - 1 f_rest."""
        if isinstance(degree, bool) or not isinstance(degree, numbers.Integral) or not 0 <= degree <= 3:
            raise ValueError(f"an SH degree is a whole number from 0 to 3, got {degree!r}")
        degree = int(degree)
        own = self.sh_degree
        if degree >= own:
            return self
        kept, rest = (degree + 1) ** 2 - 1, (own + 1) ** 2 - 1
        features = wp.empty((self.count, 3 + 3 * kept), dtype=wp.float32, device=self.device)
        wp.copy(features[:, 0:3], self.features[:, 0:3])
        for channel in range(3 if kept else 0):  # f_rest is channel-major: all R, then G, then B
            wp.copy(features[:, 3 + channel * kept : 3 + (channel + 1) * kept], self.features[:, 3 + channel * rest : 3 + channel * rest + kept])
        return replace(self, features=features)

    def kernel_view(self):
        """The arrays bundled as the kernels' ``Splats`` struct."""
        from .kernels.splat_math import Splats

        view = Splats()
        view.means, view.rotations, view.log_scales = self.means, self.rotations, self.log_scales
        view.opacities, view.features, view.extras = self.opacities, self.features, self.extras
        view.integer_extras = self.integer_extras
        return view

    def arrays(self) -> tuple[wp.array, ...]:
        return tuple(getattr(self, f.name) for f in _ARRAY_FIELDS)

    @staticmethod
    def empty(
        count: int, feature_count: int, extra_count: int, device, layout=None, integer_extra_count: int = 0
    ) -> SplatSet:
        """An uninitialised splat set of ``count`` rows (callers fill every row)."""
        return SplatSet(
            means=wp.empty(count, dtype=wp.vec3, device=device),
            rotations=wp.empty(count, dtype=wp.quat, device=device),
            log_scales=wp.empty(count, dtype=wp.vec3, device=device),
            opacities=wp.empty(count, dtype=wp.float32, device=device),
            features=wp.empty((count, feature_count), dtype=wp.float32, device=device),
            extras=wp.empty((count, extra_count), dtype=wp.float32, device=device),
            layout=layout,
            integer_extras=wp.empty((count, integer_extra_count), dtype=wp.int64, device=device),
        )


_ARRAY_FIELDS = [f for f in fields(SplatSet) if f.name != "layout"]
# dtype and dimensions of each array field
_ARRAY_LAYOUT = {"means": (wp.vec3, 1), "rotations": (wp.quat, 1), "log_scales": (wp.vec3, 1), "opacities": (wp.float32, 1),
                 "features": (wp.float32, 2), "extras": (wp.float32, 2), "integer_extras": (wp.int64, 2)}  # fmt: skip


def warp_device(device) -> wp.Device:
    """``device`` as a Warp device; a name ("auto", "cpu", "cuda", "cuda:N") as ``--device`` reads
    it, so that a GPU this machine lacks is the package's InputError, not Warp's RuntimeError."""
    if isinstance(device, str):
        from .device import resolve_device

        return resolve_device(device)
    if device is not None and not isinstance(device, wp.Device):  # Warp's own ValueError named no option
        from .errors import InputError

        raise InputError(f"device must be auto, cpu, cuda, cuda:N or a Warp device, got {device!r}")
    return wp.get_device(device)


def _host_rows(name: str, array, width: int | None, rows: int | None = None) -> np.ndarray:
    """``array`` as a numpy array of ``rows`` rows (any count when None) of ``width`` columns (any
    number when 0; one value a row, (N,) or (N, 1), when None), or a ValueError naming it."""
    a = np.asarray(array)
    if width is None and a.ndim == 2 and a.shape[1] == 1:
        a = a.reshape(-1)
    expected = "(N,)" if width is None else f"(N, {width})" if width else "(N, columns)"
    if a.ndim != (1 if width is None else 2) or (width and a.shape[1] != width) or (rows is not None and a.shape[0] != rows):
        got = "x".join(map(str, a.shape)) or "a scalar"
        raise ValueError(f"{name} must be an array of shape {expected}" + (f" with N = {rows} (as means)" if rows is not None else "")
                         + f", got shape {got}")  # fmt: skip
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):  # no bool, complex, timedelta
        raise ValueError(f"{name} must hold real numbers, got {a.dtype}")
    return a


def _check_values(means, rotations, log_scales, opacities, features, extras) -> None:
    """The value checks a file's rows get on reading (the rules of ``nanogs_warp.domain``, as
    ``nanogs_warp.io.ply.check_values`` applies them, extra properties included), as one InputError
    naming the arrays; on the values as float32 stores them (a float64 beyond its range is infinite
    there, one below its smallest subnormal is 0)."""
    from .domain import LOG_SCALE_LIMIT, not_finite, outside_log_scales, zero_quaternions
    from .errors import InputError

    n = means.shape[0]
    if n == 0:
        return
    bad = np.zeros(n, bool)
    parts = []

    def note(rows, what: str) -> None:
        nonlocal bad
        if rows.any():
            parts.append(f"{np.count_nonzero(rows)} with {what}")
            bad |= rows

    with np.errstate(all="ignore"):
        stored = {}
        for name, values in (("means", means), ("rotations", rotations), ("log_scales", log_scales),
                             ("opacities", opacities), ("features", features), ("extras", extras)):  # fmt: skip
            stored[name] = values = np.asarray(values, dtype=np.float32)
            if values.size:
                note(not_finite(values, opacity=name == "opacities").reshape(n, -1).any(axis=1), f"NaN/Inf {name}")
        note(zero_quaternions(stored["rotations"]), "zero-norm quaternions")
        note(outside_log_scales(stored["log_scales"]).any(axis=1), f"log-scales outside [-{LOG_SCALE_LIMIT:g}, {LOG_SCALE_LIMIT:g}]")
    if parts:
        raise InputError(f"{np.count_nonzero(bad)} of {n} splats are invalid: {'; '.join(parts)}")


def _whole_numbers(name: str, values: np.ndarray) -> np.ndarray:
    """``values`` (integer columns) as int64, or a ValueError where one is not a whole number that
    int64 holds (NaN, 1e30, 0.5, a uint64 above 2^63 - 1): a cast would turn them into other numbers."""
    if np.issubdtype(values.dtype, np.integer):
        if values.dtype == np.uint64 and values.size and values.max() > np.iinfo(np.int64).max:
            raise ValueError(f"{name} holds values above int64's largest, {np.iinfo(np.int64).max}")
        return values.astype(np.int64, copy=False)
    with np.errstate(all="ignore"):
        as_float = values.astype(np.float64)
        bad = ~np.isfinite(as_float) | (np.rint(as_float) != as_float) | (np.abs(as_float) >= 2.0**63)
    if bad.any():
        row, column = np.argwhere(bad)[0]
        raise ValueError(f"{name} must hold whole numbers within int64; row {row}, column {column} holds {values[row, column]}")
    return as_float.astype(np.int64)


def _check_integer_types(values: np.ndarray, layout: PlyLayout | None) -> None:
    """A ValueError where an integer extra lies outside its column's type in ``layout`` (300 in a
    uchar column): written, it would be clipped to another number."""
    names = layout.integer_extra_names if layout is not None else []
    if not names or values.shape[1] != len(names) or not values.size:
        return
    dtypes = layout.extra_dtypes()
    for column, name in enumerate(names):
        info = np.iinfo(dtypes[name])
        outside = (values[:, column] < info.min) | (values[:, column] > info.max)
        if outside.any():
            row = int(np.argmax(outside))
            raise ValueError(f"integer_extras column {column} ({name}, {dtypes[name]}) holds {values[row, column]} in row {row}, "
                             f"outside its type's [{info.min}, {info.max}]")  # fmt: skip


def split_integer_extras(extras: np.ndarray, layout: PlyLayout | None) -> tuple[np.ndarray, np.ndarray]:
    """(float extras, int64 integer extras) from ``extras`` holding either only the float extra
    properties of ``layout`` or all of them: then the integer columns are taken out, rounded (half
    to even; NaN as 0) and clipped to their type."""
    n = extras.shape[0]
    names = layout.integer_extra_names if layout is not None else []
    if not names or extras.shape[1] != len(layout.extra_names):
        return extras, np.zeros((n, 0), np.int64)
    where = {name: k for k, name in enumerate(layout.extra_names)}
    dtypes = layout.extra_dtypes()
    columns = []
    for name in names:
        info = np.iinfo(dtypes[name])
        with np.errstate(invalid="ignore"):
            values = np.rint(np.nan_to_num(extras[:, where[name]].astype(np.float64)))
        columns.append(np.clip(values, info.min, info.max).astype(np.int64))
    floats = [where[name] for name in layout.float_extra_names]
    return np.ascontiguousarray(extras[:, floats]), np.stack(columns, axis=1)


def sh_degree_for_features(feature_count: int) -> int:
    """SH degree d from the number of coefficients per splat, 3 * (d + 1)^2."""
    for degree in range(4):
        if feature_count == 3 * (degree + 1) ** 2:
            return degree
    raise ValueError(f"{feature_count} SH coefficients is not 3 * (d + 1)^2 for d in 0..3")
