"""INRIA 3DGS ``.ply`` files <-> :class:`SplatSet`: the only module that reads or writes splat files.

Reading checks the header itself first (structure, 3DGS properties, sizes against the file length),
then lets plyfile read the data (a memory map for binary files) and copies each group of columns
(means, features, ...) out of the record array as one strided block. Writing packs the vertex rows
in chunks of a few MB, block by block, behind a header made by plyfile, into a temporary file that
then replaces the target. Every problem with the input becomes an :class:`InputError` with a
one-line message; values are checked on load (NaN/Inf, zero quaternions), not on save.
"""

from __future__ import annotations

import errno
import io
import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile
import warp as wp

from .errors import InputError
from .splats import PlyLayout, SplatSet

# Required vertex properties, grouped as SplatSet stores them; f_rest_* follow f_dc_* in `features`.
MEAN_NAMES = ("x", "y", "z")
DC_NAMES = ("f_dc_0", "f_dc_1", "f_dc_2")
OPACITY_NAMES = ("opacity",)
SCALE_NAMES = ("scale_0", "scale_1", "scale_2")
ROT_NAMES = ("rot_0", "rot_1", "rot_2", "rot_3")  # w, x, y, z
REQUIRED_NAMES = MEAN_NAMES + DC_NAMES + OPACITY_NAMES + SCALE_NAMES + ROT_NAMES
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest_* count -> SH degree
NORMAL_NAMES = ("nx", "ny", "nz")

FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
DROP_HINT = "load with drop_invalid (CLI: --drop-invalid) to drop them"

# Scalar type names plyfile accepts in a header (PLY names and numpy codes) -> numpy dtype.
_TYPES = {
    **dict.fromkeys(("int8", "char", "i1"), "i1"),
    **dict.fromkeys(("uint8", "uchar", "u1", "b1"), "u1"),
    **dict.fromkeys(("int16", "short", "i2"), "i2"),
    **dict.fromkeys(("uint16", "ushort", "u2"), "u2"),
    **dict.fromkeys(("int32", "int", "i4"), "i4"),
    **dict.fromkeys(("uint32", "uint", "u4"), "u4"),
    **dict.fromkeys(("float32", "float", "f4"), "f4"),
    **dict.fromkeys(("float64", "double", "f8"), "f8"),
}
_MAX_HEADER_BYTES = 1 << 20
_END_HEADER = re.compile(rb"(?:\r\n|\r|\n)end_header(?:\r\n|\r|\n)")
_NEWLINE = re.compile(r"\r\n|\r|\n")


# ----------------------------------------------------------------------------------------------
# Public API


def load_ply(path, device="cpu", drop_invalid: bool = False) -> SplatSet:
    """Reads a 3DGS PLY file into a :class:`SplatSet` on ``device`` with its layout filled in.

    Quaternions are normalised (left bit-exact when already unit to float32 precision, so that
    load -> save -> load is bitwise stable). Rows with NaN/Inf in a 3DGS property or a zero-norm
    quaternion raise :class:`InputError`, or are dropped when ``drop_invalid`` is true.
    """
    data = read_ply_arrays(path)
    name = Path(path).name
    a = data.arrays
    check = check_values(a)
    bad = check.nonfinite_rows | check.zero_quat_rows
    n_bad = int(np.count_nonzero(bad))
    if n_bad:
        what = _describe_invalid(check)
        if not drop_invalid:
            raise InputError(f"{name}: {n_bad} of {data.count} splats are invalid ({what}); {DROP_HINT}")
        if n_bad == data.count:
            raise InputError(f"{name}: all {data.count} splats are invalid ({what}); none left after dropping them")
        keep = ~bad
        a = {k: v[keep] for k, v in a.items()}
    a["rotations"] = normalize_quaternions(a["rotations"])
    return _to_splat_set(a, data.layout, device)


def save_ply(splats: SplatSet, path) -> None:
    """Writes ``splats`` as a binary little-endian PLY file, atomically.

    Vertex properties follow ``splats.layout`` (names, order, dtypes; integer extras are rounded and
    clipped to their type's range); with no layout the INRIA order ``x y z nx ny nz f_dc_* f_rest_*
    opacity scale_* rot_*`` in float32 with zero normals (extras, if any, follow as ``extra_<i>``).
    Other elements, comments and obj_info of the layout are written back unchanged, after the
    vertex element. The data goes to a temporary file beside ``path`` that then replaces it, so a
    failure never leaves a partial file and never touches an existing one.
    """
    host = splats.to_numpy()
    props = _output_properties(splats.layout, host["features"].shape[1] - 3, host["extras"].shape[1])
    _atomic_write(Path(path), lambda stream: _write_ply_stream(stream, host, props, splats.layout))


def _to_splat_set(a: dict[str, np.ndarray], layout: PlyLayout, device) -> SplatSet:
    """SplatSet.from_numpy, but on the CPU the fresh host arrays become the Warp arrays without a
    copy (Warp keeps a reference to them); this saves a quarter of the load time."""
    device = wp.get_device(device)
    if not device.is_cpu:
        return SplatSet.from_numpy(a["means"], a["rotations"], a["log_scales"], a["opacities"],
                                   a["features"], a["extras"], layout=layout, device=device)
    n = a["means"].shape[0]

    def share(x, dtype):
        return wp.array(np.ascontiguousarray(x, dtype=np.float32), dtype=dtype, device=device, copy=False)

    return SplatSet(
        means=share(a["means"], wp.vec3),
        rotations=share(a["rotations"][:, [1, 2, 3, 0]], wp.quat),
        log_scales=share(a["log_scales"], wp.vec3),
        opacities=share(a["opacities"].reshape(n), wp.float32),
        features=share(a["features"], wp.float32),
        extras=share(a["extras"].reshape(n, -1), wp.float32),
        layout=layout,
    )


# ----------------------------------------------------------------------------------------------
# Reading, shared with `info`


@dataclass
class PlyArrays:
    """A 3DGS PLY file's vertex data as float32 host arrays, before any value check.

    ``arrays`` has ``means`` (N,3), ``rotations`` (N,4, w first, as stored), ``log_scales`` (N,3),
    ``opacities`` (N,), ``features`` (N,F) and ``extras`` (N,E).
    """

    arrays: dict[str, np.ndarray]
    layout: PlyLayout
    format: str
    file_bytes: int

    @property
    def count(self) -> int:
        return self.arrays["means"].shape[0]


@dataclass
class ValueCheck:
    """Which rows hold non-finite values (and in which properties) or zero-norm quaternions."""

    nonfinite_rows: np.ndarray  # bool (N,)
    nonfinite_by_property: dict[str, int]  # property name -> rows with NaN/Inf, only those > 0
    zero_quat_rows: np.ndarray  # bool (N,), finite quaternions with norm 0


def read_ply_arrays(path) -> PlyArrays:
    """Reads and structurally checks a 3DGS PLY file; values are not checked (see check_values)."""
    path = Path(path)
    name = path.name
    header = None
    try:
        with _open_for_reading(path) as f:
            file_bytes = os.fstat(f.fileno()).st_size
            if file_bytes == 0:
                raise InputError(f"{name}: the file is empty")
            header = _parse_header(f.read(_MAX_HEADER_BYTES), name)
        vertex_h = _check_structure(header, name)
        _check_sizes(header, file_bytes, name)
        ply = plyfile.PlyData.read(str(path), mmap="r")
        _check_agreement(header, ply, name)
        with np.errstate(all="ignore"):
            return _extract(header, vertex_h, ply, path, file_bytes)
    except (InputError, MemoryError):
        raise
    except OSError as e:
        raise InputError(f"{name}: cannot read the file: {e.strerror or e}") from e
    except Exception as e:  # any plyfile/numpy parse failure on malformed bytes
        if isinstance(e, UnicodeDecodeError):
            raise InputError(f"{name}: malformed PLY file: non-ASCII bytes in ASCII data") from e
        if isinstance(e, plyfile.PlyElementParseError) and _looks_truncated(e, header, path):
            raise InputError(f"{name}: truncated file ({_one_line(e)})") from e
        raise InputError(f"{name}: malformed PLY file: {_one_line(e)}") from e


def check_values(arrays: dict[str, np.ndarray], extra_names: list[str] | None = None) -> ValueCheck:
    """Finds rows with NaN/Inf in the 3DGS properties (and in the extras, when their names are
    given) and rows whose quaternion is zero."""
    n = arrays["means"].shape[0]
    rows = np.zeros(n, bool)
    by_prop: dict[str, int] = {}
    n_rest = arrays["features"].shape[1] - 3
    groups = [
        ("means", MEAN_NAMES),
        ("features", DC_NAMES + tuple(f"f_rest_{i}" for i in range(n_rest))),
        ("opacities", OPACITY_NAMES),
        ("log_scales", SCALE_NAMES),
        ("rotations", ROT_NAMES),
    ]
    if extra_names is not None:
        groups.append(("extras", tuple(extra_names)))
    for key, names in groups:
        values = arrays[key].reshape(n, -1)
        if np.isfinite(values).all():  # the common case, ~5x faster than the row-wise test
            continue
        bad = ~np.isfinite(values)
        rows |= bad.any(axis=1)
        for prop, count in zip(names, np.count_nonzero(bad, axis=0)):
            if count:
                by_prop[prop] = int(count)
    q = arrays["rotations"].astype(np.float64)
    with np.errstate(all="ignore"):
        zero = np.einsum("ij,ij->i", q, q) == 0  # exact in float64 for float32 inputs
    return ValueCheck(rows, by_prop, zero)


def normalize_quaternions(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (float32) from non-zero finite ones; rows already unit to float32 precision
    are returned bit-for-bit unchanged, so normalising twice changes nothing."""
    q64 = q.astype(np.float64)
    norm = np.sqrt(np.einsum("ij,ij->i", q64, q64))
    fix = np.abs(norm - 1.0) > 1e-6
    out = np.array(q, dtype=np.float32, copy=True)
    if fix.any():
        out[fix] = (q64[fix] / norm[fix, None]).astype(np.float32)
    return out


def sh_degree_for_rest_count(count: int) -> int:
    return REST_COUNTS[count]


# ----------------------------------------------------------------------------------------------
# Header: parsed here (strictly, mirroring plyfile's grammar) so that structure and sizes are
# checked before plyfile allocates anything.


@dataclass
class _Prop:
    name: str
    dtype: np.dtype | None  # None for list properties
    is_list: bool = False
    len_dtype: np.dtype | None = None
    type_name: str = ""


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Prop]


@dataclass
class _Header:
    format: str
    elements: list[_Element]
    length: int  # bytes up to and including the end_header line

    def element(self, name: str) -> _Element | None:
        return next((e for e in self.elements if e.name == name), None)


def _parse_header(head: bytes, name: str) -> _Header:
    if not head.startswith(b"ply") or head[3:4] not in (b"\n", b"\r"):
        raise InputError(f"{name}: not a PLY file (it does not start with 'ply')")
    m = _END_HEADER.search(head)
    if m is None:
        if len(head) < _MAX_HEADER_BYTES:
            raise InputError(f"{name}: truncated PLY header (no 'end_header' line)")
        raise InputError(f"{name}: no 'end_header' line in the first {_MAX_HEADER_BYTES >> 20} MiB")
    try:
        text = head[: m.start()].decode("ascii")
    except UnicodeDecodeError:
        raise InputError(f"{name}: malformed PLY header (non-ASCII bytes)") from None

    def fail(lineno: int, msg: str):
        raise InputError(f"{name}: malformed PLY header (line {lineno}: {msg})")

    fmt = None
    elements: list[_Element] = []
    lines = _NEWLINE.split(text)
    for lineno, raw in enumerate(lines[1:], start=2):
        line = raw.strip()
        if not line:
            continue
        keyword, *fields = line.split()
        rest = line[len(keyword) :]
        if keyword in ("comment", "obj_info"):  # plyfile's reading keeps them
            continue
        if keyword == "format":
            if fmt is not None or elements:
                fail(lineno, "unexpected 'format' line")
            if len(fields) != 2 or fields[0] not in FORMATS or fields[1] != "1.0":
                fail(lineno, f"unsupported format {rest.strip()!r}")
            fmt = fields[0]
        elif fmt is None:
            fail(lineno, "expected a 'format' line first")
        elif keyword == "element":
            if len(fields) != 2:
                fail(lineno, "expected 'element NAME COUNT'")
            try:
                count = int(fields[1])
            except ValueError:
                fail(lineno, f"element count {fields[1]!r} is not an integer")
            if count < 0:
                fail(lineno, f"element {fields[0]!r} has a negative count")
            if any(e.name == fields[0] for e in elements):
                fail(lineno, f"element {fields[0]!r} appears twice")
            elements.append(_Element(fields[0], count, []))
        elif keyword == "property":
            if not elements:
                fail(lineno, "property before any element")
            if fields and fields[0] == "list":
                if len(fields) != 4 or fields[1] not in _TYPES or fields[2] not in _TYPES:
                    fail(lineno, "expected 'property list LENTYPE TYPE NAME'")
                prop = _Prop(fields[3], None, True, np.dtype(_TYPES[fields[1]]), "list")
            else:
                if len(fields) != 2:
                    fail(lineno, "expected 'property TYPE NAME'")
                if fields[0] not in _TYPES:
                    fail(lineno, f"unknown property type {fields[0]!r}")
                prop = _Prop(fields[1], np.dtype(_TYPES[fields[0]]), type_name=fields[0])
            if any(p.name == prop.name for p in elements[-1].props):
                fail(lineno, f"property {prop.name!r} appears twice in element {elements[-1].name!r}")
            elements[-1].props.append(prop)
        else:
            fail(lineno, f"unexpected line {line[:40]!r}")
    if fmt is None:
        raise InputError(f"{name}: malformed PLY header (no 'format' line)")
    return _Header(fmt, elements, m.end())


def _check_structure(header: _Header, name: str) -> _Element:
    vertex = header.element("vertex")
    if vertex is None:
        found = ", ".join(e.name for e in header.elements) or "none"
        raise InputError(f"{name}: no 'vertex' element (elements: {found})")
    if vertex.count == 0:
        raise InputError(f"{name}: the 'vertex' element has 0 rows")
    lists = [p.name for p in vertex.props if p.is_list]
    if lists:
        raise InputError(f"{name}: vertex list properties are not supported ({', '.join(lists)})")
    props = {p.name: p for p in vertex.props}
    missing = [n for n in REQUIRED_NAMES if n not in props]
    if missing:
        raise InputError(f"{name}: not a 3DGS splat file: missing vertex properties {', '.join(missing)}")
    rest = [p.name for p in vertex.props if p.name.startswith("f_rest_")]
    if len(rest) not in REST_COUNTS:
        raise InputError(
            f"{name}: {len(rest)} f_rest_* properties; 3DGS files have 0, 9, 24 or 45 (SH degree 0..3)"
        )
    expected = {f"f_rest_{i}" for i in range(len(rest))}
    if set(rest) != expected:
        odd = sorted(set(rest) - expected, key=_natural)
        gone = sorted(expected - set(rest), key=_natural)
        raise InputError(
            f"{name}: f_rest_* properties are not numbered f_rest_0..f_rest_{len(rest) - 1} "
            f"(missing {', '.join(gone)}; unexpected {', '.join(odd)})"
        )
    not_float = [f"{n} ({props[n].type_name})" for n in REQUIRED_NAMES + tuple(sorted(expected, key=_natural))
                 if props[n].dtype.kind != "f"]
    if not_float:
        raise InputError(f"{name}: 3DGS properties must be float or double: {', '.join(not_float)}")
    return vertex


def _check_sizes(header: _Header, file_bytes: int, name: str) -> None:
    """Rejects element counts that cannot fit in the file, before anything is allocated."""
    body = file_bytes - header.length
    needed = 0
    for e in header.elements:
        if header.format == "ascii":
            # every value takes a character and a separator; every row at least a line break
            row = max(2 * len(e.props), 1)
        else:
            row = max(sum((p.len_dtype if p.is_list else p.dtype).itemsize for p in e.props), 1)
        needed += e.count * row
        exact = header.format != "ascii" and not any(p.is_list for p in e.props)
        if needed > body + (0 if exact else 1):
            raise InputError(
                f"{name}: truncated file: element {e.name!r} ({e.count} rows) needs {'' if exact else 'at least '}"
                f"{needed} bytes after the header, but only {max(body, 0)} follow"
            )


def _check_agreement(header: _Header, ply: plyfile.PlyData, name: str) -> None:
    ours = [(e.name, e.count, [p.name for p in e.props]) for e in header.elements]
    theirs = [(e.name, e.count, [p.name for p in e.properties]) for e in ply.elements]
    if ours != theirs:
        raise InputError(f"{name}: malformed PLY header (it parses ambiguously)")


def _extract(header: _Header, vertex_h: _Element, ply: plyfile.PlyData, path: Path, file_bytes: int) -> PlyArrays:
    n = vertex_h.count
    data = ply["vertex"].data
    if data.shape != (n,):
        raise ValueError(f"vertex data has shape {data.shape}, expected ({n},)")
    fields = data.dtype.fields
    names = [p.name for p in vertex_h.props]
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    known = set(REQUIRED_NAMES) | {f"f_rest_{i}" for i in range(n_rest)}
    extra_names = [p for p in names if p not in known]
    groups = {
        "means": MEAN_NAMES,
        "rotations": ROT_NAMES,
        "log_scales": SCALE_NAMES,
        "opacities": OPACITY_NAMES,
        "features": DC_NAMES + tuple(f"f_rest_{i}" for i in range(n_rest)),
        "extras": tuple(extra_names),
    }
    arrays = {key: np.empty((n, len(group)), np.float32) for key, group in groups.items()}
    plans = [(arrays[key], _runs(fields, group)) for key, group in groups.items()]
    for start, rows in _vertex_chunks(header, data, path):
        stop = start + rows.shape[0]
        for out, runs in plans:
            for i, j, dt, off in runs:
                out[start:stop, i:j] = rows[:, off : off + (j - i) * dt.itemsize].view(dt)
    arrays["opacities"] = arrays["opacities"].reshape(n)

    others = []
    for e in ply.elements:
        if e.name != "vertex":
            e.data = np.array(e.data)  # detach from the memory map
            others.append(e)
    layout = PlyLayout(
        properties=[(p.name, p.dtype.str[1:]) for p in vertex_h.props],
        extra_names=extra_names,
        other_elements=others,
        comments=list(ply.comments),
        obj_info=list(ply.obj_info),
    )
    return PlyArrays(arrays, layout, header.format, file_bytes)


_CHUNK_BYTES = 4 << 20  # rows are converted (and written) in chunks of about this size


def _runs(fields, names) -> list[tuple[int, int, np.dtype, int]]:
    """Runs [i, j) of properties adjacent in the record with one dtype: (i, j, dtype, byte offset)."""
    runs = []
    i = 0
    while i < len(names):
        dt, off = fields[names[i]][:2]
        j = i + 1
        while j < len(names) and fields[names[j]][:2] == (dt, off + (j - i) * dt.itemsize):
            j += 1
        runs.append((i, j, dt, off))
        i = j
    return runs


def _vertex_chunks(header: _Header, data: np.ndarray, path: Path):
    """(first row, (rows, itemsize) uint8 view) chunks of the vertex records. A binary vertex
    element at a known offset is read from the file into one reused cache-sized buffer (about
    twice as fast as touching plyfile's memory map); otherwise plyfile's array is sliced."""
    n, itemsize = data.shape[0], data.dtype.itemsize
    step = max(1, _CHUNK_BYTES // itemsize)
    offset = _binary_offset(header, "vertex")
    if offset is not None and data.flags.c_contiguous:
        with open(path, "rb") as f:
            f.seek(offset)
            # plyfile found the same first record there: trust the offset (else use plyfile's array)
            if f.read(itemsize) == data[:1].view(np.uint8).tobytes():
                f.seek(offset)
                buffer = np.empty((min(step, n), itemsize), np.uint8)
                for start in range(0, n, step):
                    rows = buffer[: min(step, n - start)]
                    if f.readinto(memoryview(rows).cast("B")) != rows.nbytes:
                        raise ValueError("the file changed while it was read")
                    yield start, rows
                return
    if not data.flags.c_contiguous:
        data = np.ascontiguousarray(data)
    rows = data.view(np.uint8).reshape(n, itemsize)
    for start in range(0, n, step):
        yield start, rows[start : start + step]


def _binary_offset(header: _Header, name: str) -> int | None:
    """Byte offset of element ``name`` in a binary file, when no list property comes before it."""
    if header.format == "ascii":
        return None
    offset = header.length
    for e in header.elements:
        if e.name == name:
            return offset
        if any(p.is_list for p in e.props):
            return None
        offset += e.count * sum(p.dtype.itemsize for p in e.props)
    return None


def _looks_truncated(e: plyfile.PlyElementParseError, header: _Header | None, path: Path) -> bool:
    """plyfile's "early end-of-file", or an ASCII line cut short in a file without a final newline."""
    if "early end-of-file" in e.message:
        return True
    if header is None or header.format != "ascii" or "early end-of-line" not in e.message:
        return False
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) not in (b"\n", b"\r")


def _describe_invalid(check: ValueCheck) -> str:
    parts = []
    n_nf = int(np.count_nonzero(check.nonfinite_rows))
    if n_nf:
        props = sorted(check.nonfinite_by_property, key=_natural_prop)
        shown = ", ".join(props[:8]) + (f", ... ({len(props)} properties)" if len(props) > 8 else "")
        parts.append(f"{n_nf} with NaN/Inf values in {shown}")
    n_zq = int(np.count_nonzero(check.zero_quat_rows))
    if n_zq:
        parts.append(f"{n_zq} with zero-norm quaternions")
    return "; ".join(parts)


def _open_for_reading(path: Path):
    name = path.name
    try:
        if path.is_dir():
            raise InputError(f"{name}: is a directory, not a PLY file")
        return open(path, "rb")
    except FileNotFoundError:
        raise InputError(f"{name}: no such file") from None
    except PermissionError:
        raise InputError(f"{name}: permission denied") from None


# ----------------------------------------------------------------------------------------------
# Writing


_INRIA_HEAD = MEAN_NAMES + NORMAL_NAMES + DC_NAMES
_INRIA_TAIL = OPACITY_NAMES + SCALE_NAMES + ROT_NAMES


def _output_properties(layout: PlyLayout | None, n_rest: int, n_extra: int) -> list[tuple[str, str]]:
    rest = [f"f_rest_{i}" for i in range(n_rest)]
    if layout is None:
        names = list(_INRIA_HEAD) + rest + list(_INRIA_TAIL) + [f"extra_{i}" for i in range(n_extra)]
        return [(n, "f4") for n in names]
    if len(layout.extra_names) != n_extra:
        raise ValueError(f"layout names {len(layout.extra_names)} extras but the splats have {n_extra}")
    props = list(layout.properties)
    old_rest = [i for i, (n, _) in enumerate(props) if n.startswith("f_rest_")]
    if len(old_rest) != n_rest:  # SH degree changed: new f_rest block where the old one began
        if old_rest:
            at, dtype = old_rest[0], props[old_rest[0]][1]
        else:
            at = max(i for i, (n, _) in enumerate(props) if n in DC_NAMES) + 1
            dtype = dict(props)["f_dc_0"]
        props = [p for i, p in enumerate(props) if i not in set(old_rest)]
        props[at:at] = [(n, dtype) for n in rest]
    names = {n for n, _ in props}
    missing = [n for n in REQUIRED_NAMES + tuple(layout.extra_names) if n not in names]
    if missing:
        raise ValueError(f"layout lacks properties {missing}")
    return props


def _write_ply_stream(stream, host: dict[str, np.ndarray], props: list[tuple[str, str]], layout) -> None:
    """Writes the header (via plyfile), the vertex rows in packed chunks, then the other elements
    (serialised by plyfile) to a binary stream."""
    n = host["means"].shape[0]
    dtype = np.dtype([(nm, "<" + dt) for nm, dt in props])
    others = list(layout.other_elements) if layout is not None else []
    vertex = plyfile.PlyElement("vertex", [plyfile.PlyProperty(nm, dt) for nm, dt in props], n)
    ply = plyfile.PlyData(
        [vertex, *others],
        text=False,
        byte_order="<",
        comments=list(layout.comments) if layout is not None else [],
        obj_info=list(layout.obj_info) if layout is not None else [],
    )
    stream.write(ply.header.encode("ascii") + b"\n")
    plan = _pack_plan(host, props, layout, dtype)
    step = max(1, _CHUNK_BYTES // dtype.itemsize)
    buffer = np.empty(min(step, n), dtype)
    for start in range(0, n, step):
        rows = buffer[: min(step, n - start)]
        _pack_rows(plan, rows, start)
        stream.write(memoryview(rows.view(np.uint8)))
    if others:
        tail = plyfile.PlyData(others, text=False, byte_order="<")
        body = io.BytesIO()
        tail.write(body)
        stream.write(body.getbuffer()[len(tail.header) + 1 :])


def _pack_plan(host, props, layout, dtype) -> list[tuple[int, np.dtype, int, np.ndarray | None]]:
    """Runs of output properties that come from adjacent columns of one host array:
    (byte offset, dtype, count, source columns (N, count) or None for zeros)."""
    n = host["means"].shape[0]
    where: dict[str, tuple[str, int]] = {}
    for group, names in (("means", MEAN_NAMES), ("rotations", ROT_NAMES), ("log_scales", SCALE_NAMES),
                         ("opacities", OPACITY_NAMES)):
        where.update({nm: (group, i) for i, nm in enumerate(names)})
    for i in range(host["features"].shape[1]):
        where[DC_NAMES[i] if i < 3 else f"f_rest_{i - 3}"] = ("features", i)
    extra_names = layout.extra_names if layout is not None else [f"extra_{i}" for i in range(host["extras"].shape[1])]
    where.update({nm: ("extras", i) for i, nm in enumerate(extra_names)})
    sources = {k: v.reshape(n, -1) for k, v in host.items()}
    plan = []
    i = 0
    while i < len(props):
        src = where.get(props[i][0])  # None: a normal written as zero (no layout)
        dt, off = dtype.fields[props[i][0]][:2]
        j = i + 1
        while (src is not None and j < len(props) and where.get(props[j][0]) == (src[0], src[1] + j - i)
               and dtype.fields[props[j][0]][0] == dt):
            j += 1
        columns = None if src is None else sources[src[0]][:, src[1] : src[1] + (j - i)]
        plan.append((off, dt, j - i, columns))
        i = j
    return plan


def _pack_rows(plan, rows: np.ndarray, start: int) -> None:
    raw = rows.view(np.uint8).reshape(rows.shape[0], rows.dtype.itemsize)
    stop = start + rows.shape[0]
    for off, dt, k, columns in plan:
        block = raw[:, off : off + k * dt.itemsize].view(dt)
        if columns is None:
            block[...] = 0
            continue
        values = columns[start:stop]
        if dt.kind in "iu":  # integer extras: round and clip the float32 values to the type
            info = np.iinfo(dt)
            values = np.clip(np.rint(np.nan_to_num(values.astype(np.float64))), info.min, info.max)
        block[...] = values


def _atomic_write(path: Path, write) -> None:
    """Calls ``write(stream)`` on a new temporary file beside ``path`` and moves it into place."""
    name = path.name
    directory = path.parent
    if path.is_dir():
        raise InputError(f"{name}: is a directory")
    if not directory.is_dir():
        raise InputError(f"{name}: cannot write: directory {str(directory)!r} does not exist")
    tmp = directory / f".{name}.{secrets.token_hex(6)}.tmp"
    created = False
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        created = True
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
        created = False
    except OSError as e:
        if isinstance(e, PermissionError) or e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise InputError(f"{name}: cannot write to {str(directory)!r}: permission denied") from e
        raise InputError(f"{name}: cannot write the file: {e.strerror or _one_line(e)}") from e
    finally:
        if created:
            try:
                os.unlink(tmp)
            except OSError:
                pass


# ----------------------------------------------------------------------------------------------


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text or type(e).__name__


def _natural(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _natural_prop(s: str):
    order = {n: i for i, n in enumerate(REQUIRED_NAMES)}
    return (order.get(s, len(order)), _natural(s))
