"""INRIA 3DGS ``.ply`` files <-> :class:`SplatSet`: the public API for reading and writing splat files.

Reading checks the header itself first (structure, 3DGS properties, sizes against the file length),
lets plyfile map the file (for the layout, the other elements and the comments), then reads a
binary file's vertex rows itself, on several threads, block by block (:mod:`.ply_read`): each
group of columns (means, features, ...) is copied out of the records as one strided block, its
values checked and its quaternions normalised while the block is in cache; only a block with a
suspicious value sends the load through the exact row-by-row checks. ASCII files and files with a
list element before the vertices are converted from plyfile's array. Writing packs the vertex rows
in chunks of a few MB on several threads, writes them in order behind a header made by plyfile,
into a temporary file that then replaces the target. Every problem with the input becomes an
:class:`InputError` with a one-line message; values are checked on load (NaN/Inf, zero
quaternions, log-scales outside the domain), not on save. The header parser and structure checks
live in :mod:`.ply_header`, the writer in :mod:`.ply_write`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import plyfile

from ..domain import LOG_SCALE_LIMIT, not_finite, outside_log_scales, saturate_opacity_logits, zero_quaternions
from ..errors import InputError
from .open_file import open_regular
from .ply_header import (
    DC_NAMES,
    FLAT_LOG_SCALE,
    MAX_HEADER_BYTES,
    MEAN_NAMES,
    OPACITY_NAMES,
    REQUIRED_NAMES,
    REST_COUNTS,
    ROT_NAMES,
    SCALE_NAMES,
    Element,
    Header,
    check_agreement,
    check_sizes,
    check_structure,
    has_surfels,
    natural,
    one_line,
    parse_header,
    trailing_bytes,
)
from .ply_layout import PlyLayout
from .ply_write import OutputSet, atomic_write, output_properties
from .ply_write import write_ply_stream as _write_ply_stream  # by this name: the tests patch it here
from .ply_read import BlockCheck, Columns, copy_run, read_threads, read_vertex_rows, unit_size

if TYPE_CHECKING:
    from ..splats import SplatSet

DROP_HINT = "load with drop_invalid (CLI: --drop-invalid) to drop them"


# ----------------------------------------------------------------------------------------------
# Public API


def load_ply(path, device="cpu", drop_invalid: bool = False, on_drop=None, digest=None, file_hash=None,
             threads: int | None = None) -> SplatSet:
    """Reads a 3DGS PLY file into a :class:`SplatSet` on ``device`` with its layout filled in.

    Quaternions are normalised (left bit-exact when already unit to float32 precision, so that
    load -> save -> load is bitwise stable). Rows with NaN/Inf in a 3DGS property, a zero-norm
    quaternion or a log-scale outside the numeric domain (``nanogs_warp.domain``) raise
    :class:`InputError`, or are dropped when ``drop_invalid`` is true (then ``on_drop``, if given,
    is called with one line saying how many rows went and why). Opacity logits of +Inf (alpha = 1)
    and -Inf (alpha = 0) are valid: see :func:`saturate_opacity_logits`.
    ``digest`` (a :mod:`hashlib` object) is fed every byte of the file, in order, as it is read
    (on one thread); ``file_hash`` (a :class:`~nanogs_warp.io.ply_read.PieceHash`) gets every piece
    of the file, hashed by the threads that read it. ``threads``: how many threads read the file
    (None: :func:`~nanogs_warp.io.ply_read.read_threads`).
    """
    from ..splats import warp_device

    device = warp_device(device)  # a device this machine lacks: said before the file is read
    arrays, layout = read_splats(path, drop_invalid, digest, on_drop, file_hash=file_hash, threads=threads)
    return _to_splat_set(arrays, layout, device)


def read_splats(path, drop_invalid: bool = False, digest=None, on_drop=None, file_hash=None,
                threads: int | None = None, upload=None) -> tuple[dict[str, np.ndarray], PlyLayout]:
    """load_ply's part on the host, without Warp: the checked host arrays and the layout;
    ``splats_from_host`` makes them a :class:`SplatSet`. The arrays have ``PlyArrays``' names,
    except that the normalised quaternions are either ``rotations`` (w first) or, from a binary
    file, ``quats_xyzw`` (Warp's x, y, z, w order, which a SplatSet on the CPU then shares).
    ``upload`` (a :class:`~nanogs_warp.io.row_upload.RowUpload`), if given, is handed a binary
    file's rows as they are read."""
    name = Path(path).name
    data = _read(path, digest, file_hash, threads, prepare=True, upload=upload)
    a, check = data.arrays, data.check
    notes = []  # said once the values have passed: a file refused gets its one error line alone
    if data.trailing_bytes and on_drop is not None:
        notes.append(f"{name}: {data.trailing_bytes:,} bytes after the data its header declares were ignored (is its "
                     "vertex count smaller than the data's?)")  # fmt: skip
    if data.layout.surfels and on_drop is not None:
        notes.append(f"{name}: 2DGS surfels (scale_0 and scale_1, no scale_2) read as flat 3DGS splats (log-scale "
                     f"{FLAT_LOG_SCALE:g} on the third axis), and written as 3DGS")  # fmt: skip
    if check is not None and not check.suspect:  # every value checked block by block: valid
        if check.infinite_opacity:
            a["opacities"] = saturate_opacity_logits(a["opacities"])
        for line in notes:
            on_drop(line)
        return a, data.layout
    if "quats_xyzw" in a:  # a value to look at row by row: the exact checks, as for any file
        a["rotations"] = a.pop("quats_xyzw")[:, [3, 0, 1, 2]]
    count = a["means"].shape[0]
    wide = [n for n, t in data.layout.properties if np.dtype(t) == np.float64]
    a = checked_rows(a, name, drop_invalid, on_drop, data.layout.float_extra_names, wide)
    for line in notes:
        on_drop(line)
    a["rotations"] = normalize_quaternions(a["rotations"])
    layout = data.layout
    if a["means"].shape[0] != count:  # rows dropped: what indexes them by row goes too
        layout, dropped = layout.without_vertex_indexed()
        if dropped is not None and on_drop is not None:
            on_drop(f"{name}: {dropped}: they index vertices, which dropping rows renumbers")
    return a, layout


def splats_from_host(arrays: dict[str, np.ndarray], layout: PlyLayout, device="cpu") -> SplatSet:
    """A :class:`SplatSet` on ``device`` from :func:`read_splats`' arrays (shared, not copied, on
    the CPU)."""
    return _to_splat_set(arrays, layout, device)


def checked_rows(
    a: dict[str, np.ndarray], name: str, drop_invalid: bool, on_drop=None, extra_names: list[str] | None = None,
    wide: list[str] = (),
) -> dict[str, np.ndarray]:
    """The host arrays with invalid rows refused (InputError) or dropped, and infinite opacity
    logits saturated; shared by every format's reader. ``extra_names``: the names of the float
    extras' columns (a PLY's other properties), which must be finite too; ``wide``: properties the
    file stores as double (held as float32: a finite double beyond its range becomes infinite)."""
    count = a["means"].shape[0]
    check = check_values(a, extra_names)
    bad = check.nonfinite_rows | check.zero_quat_rows | check.out_of_domain_rows
    n_bad = int(np.count_nonzero(bad))
    if n_bad:
        what = _describe_invalid(check, wide)
        if not drop_invalid:
            raise InputError(f"{name}: {n_bad} of {count} splats are invalid ({what}); {DROP_HINT}")
        if n_bad == count:
            raise InputError(f"{name}: all {count} splats are invalid ({what}); none left after dropping them")
        keep = ~bad
        a = {k: v[keep] for k, v in a.items()}
        if on_drop is not None:
            on_drop(f"{name}: dropped {n_bad} of {count} splats ({what})")
    a["opacities"] = saturate_opacity_logits(a["opacities"])
    return a


def refuse_empty(splats: SplatSet, path) -> None:
    """An InputError for a splat set without splats: no reader takes a scene file without one."""
    if splats.count == 0:
        raise InputError(f"{Path(path).name}: an empty splat set cannot be written (a scene file holds at least one splat)")


def save_ply(splats: SplatSet, path, threads: int | None = None, overwrite: bool = True, outputs: OutputSet | None = None) -> None:
    """Writes ``splats`` as a binary little-endian PLY file, atomically.

    Vertex properties follow ``splats.layout`` (names, order, dtypes; integer extras are clipped to
    their type's range); with no layout the INRIA order ``x y z nx ny nz f_dc_* f_rest_*
    opacity scale_* rot_*`` in float32 with zero normals (extras, if any, follow as ``extra_<i>``).
    Other elements, comments and obj_info of the layout are written back unchanged, after the
    vertex element. The data goes to a temporary file beside ``path`` that then replaces it, so a
    failure never leaves a partial file and never touches an existing one. ``threads`` pack the rows
    (None: :func:`~nanogs_warp.io.ply_read.read_threads`, at least two). Without ``overwrite`` an
    existing ``path`` is an InputError and stays as it is. With ``outputs`` the file is staged there
    (``OutputSet``) and appears when the set is published.
    """
    refuse_empty(splats, path)
    host = _host_arrays(splats)
    props = output_properties(splats.layout, host["features"].shape[1] - 3, host["extras"].shape[1],
                              host["integer_extras"].shape[1])  # fmt: skip
    atomic_write(Path(path), lambda stream: _write_ply_stream(stream, host, props, splats.layout, _CHUNK_BYTES, threads),
                 overwrite, outputs)  # fmt: skip


def _host_arrays(splats: SplatSet) -> dict[str, np.ndarray]:
    """The splats' arrays as 2D host arrays for writing: views of the Warp arrays on the CPU (no
    copy), one device-to-host copy each from a GPU; quaternions in Warp's x, y, z, w order."""
    n = splats.count
    arrays = {"means": splats.means, "quats_xyzw": splats.rotations, "log_scales": splats.log_scales,
              "opacities": splats.opacities, "features": splats.features, "extras": splats.extras,
              "integer_extras": splats.integer_extras}  # fmt: skip
    return {key: a.numpy().reshape(n, -1) for key, a in arrays.items()}


def _to_splat_set(a: dict[str, np.ndarray], layout: PlyLayout, device) -> SplatSet:
    """The host arrays as a SplatSet: on the CPU the fresh host arrays become the Warp arrays
    without a copy (Warp keeps a reference to them); on a GPU that set is copied there."""
    import warp as wp  # here, not at the top: reading a file's header and values needs no Warp

    from ..splats import SplatSet, warp_device

    device = warp_device(device)
    cpu = wp.get_device("cpu")
    n = a["means"].shape[0]
    quats = a["quats_xyzw"] if "quats_xyzw" in a else a["rotations"][:, [1, 2, 3, 0]]

    def share(x, dtype, host_dtype=np.float32):
        return wp.array(np.ascontiguousarray(x, dtype=host_dtype), dtype=dtype, device=cpu, copy=False)

    splats = SplatSet(
        means=share(a["means"], wp.vec3),
        rotations=share(quats, wp.quat),
        log_scales=share(a["log_scales"], wp.vec3),
        opacities=share(a["opacities"].reshape(n), wp.float32),
        features=share(a["features"], wp.float32),
        extras=share(a["extras"].reshape(n, -1), wp.float32),
        layout=layout,
        integer_extras=share(a["integer_extras"].reshape(n, -1), wp.int64, np.int64),
    )
    return splats if device.is_cpu else splats.to(device)


# ----------------------------------------------------------------------------------------------
# Reading, shared with `info`


@dataclass
class PlyArrays:
    """A 3DGS PLY file's vertex data as float32 host arrays, before any value check.

    ``arrays`` has ``means`` (N,3), ``rotations`` (N,4, w first, as stored), ``log_scales`` (N,3),
    ``opacities`` (N,), ``features`` (N,F), ``extras`` (N,E) (the extra properties of a float type)
    and ``integer_extras`` (N,I) int64 (those of an integer type, exact).
    """

    arrays: dict[str, np.ndarray]
    layout: PlyLayout
    format: str
    file_bytes: int
    check: BlockCheck | None = None  # read_splats' reading: the block checks' findings (None: not checked)
    trailing_bytes: int = 0  # after the data the header declares (binary files without list properties)

    @property
    def count(self) -> int:
        return self.arrays["means"].shape[0]


@dataclass
class ValueCheck:
    """Which rows hold non-finite values (and in which properties), zero-norm quaternions or finite
    values outside the numeric domain (``nanogs_warp.domain``), and how many opacity logits are
    +Inf / -Inf (valid: alpha 1 / 0, not counted as non-finite)."""

    nonfinite_rows: np.ndarray  # bool (N,)
    nonfinite_by_property: dict[str, int]  # property name -> rows with NaN/Inf, only those > 0
    zero_quat_rows: np.ndarray  # bool (N,), finite quaternions with norm 0
    out_of_domain_rows: np.ndarray  # bool (N,), finite log-scales beyond +-LOG_SCALE_LIMIT
    out_of_domain_by_property: dict[str, int]  # property name -> such rows, only those > 0
    infinite_opacities: tuple[int, int] = (0, 0)  # rows with opacity logit +Inf (alpha 1), -Inf (alpha 0): valid


def read_ply_arrays(path, digest=None, file_hash=None, threads: int | None = None) -> PlyArrays:
    """Reads and structurally checks a 3DGS PLY file; values are not checked (see check_values).
    ``digest`` (a :mod:`hashlib` object, fed in order) or ``file_hash`` (a
    :class:`~nanogs_warp.io.ply_read.PieceHash`), when given, is fed the whole file in the same pass."""
    return _read(path, digest, file_hash, threads, prepare=False)


def _read(path, digest, file_hash, threads, prepare: bool, upload=None) -> PlyArrays:
    path = Path(path)
    name = path.name
    header = None
    try:
        with open_regular(path) as f:
            file_bytes = os.fstat(f.fileno()).st_size
            if file_bytes == 0:
                raise InputError(f"{name}: the file is empty")
            header = parse_header(f.read(MAX_HEADER_BYTES), name)
            vertex_h = check_structure(header, name)
            check_sizes(header, file_bytes, name)
            if header.format == "ascii":
                check_ascii_numbers(f, header.length, name)
            ply = plyfile.PlyData.read(str(path), mmap="r")
            check_agreement(header, ply, name)
            with np.errstate(all="ignore"):
                return _extract(header, vertex_h, ply, path, f, file_bytes, digest, file_hash, threads, prepare, upload)
    except (InputError, MemoryError):
        raise
    except OSError as e:
        raise InputError(f"{name}: cannot read the file: {e.strerror or e}") from e
    except Exception as e:  # any plyfile/numpy parse failure on malformed bytes
        if isinstance(e, UnicodeDecodeError):
            if header is not None and header.format != "ascii":  # plyfile read the data as header lines
                raise InputError(f"{name}: malformed PLY header (its lines end unlike its 'end_header' line)") from e
            raise InputError(f"{name}: malformed PLY file: non-ASCII bytes in ASCII data") from e
        if isinstance(e, plyfile.PlyElementParseError) and _looks_truncated(e, header, path):
            raise InputError(f"{name}: truncated file ({one_line(e)})") from e
        raise InputError(f"{name}: malformed PLY file: {one_line(e)}") from e


def check_ascii_numbers(f, start: int, name: str) -> None:
    """Refuses an ASCII body whose numbers hold an underscore: Python (and so plyfile) reads 1_0 as
    10 where C's strtod, and most readers, read 1; no PLY writer puts one there."""
    for offset in range(start, os.fstat(f.fileno()).st_size, 1 << 24):
        if b"_" in os.pread(f.fileno(), 1 << 24, offset):
            raise InputError(f"{name}: malformed PLY file: a number with an underscore in the ASCII data")


def check_values(arrays: dict[str, np.ndarray], extra_names: list[str] | None = None) -> ValueCheck:
    """Finds rows with NaN/Inf in the 3DGS properties (and in the extras, when their names are
    given), rows whose quaternion is zero and rows with a finite log-scale outside the domain."""
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
        bad = not_finite(values, opacity=key == "opacities")
        rows |= bad.any(axis=1)
        for prop, count in zip(names, np.count_nonzero(bad, axis=0)):
            if count:
                by_prop[prop] = int(count)
    zero = zero_quaternions(arrays["rotations"])
    outside = outside_log_scales(arrays["log_scales"].reshape(n, -1))
    domain_by_prop = {p: int(c) for p, c in zip(SCALE_NAMES, np.count_nonzero(outside, axis=0)) if c}
    logits = arrays["opacities"].reshape(n)
    infinite = (int(np.count_nonzero(np.isposinf(logits))), int(np.count_nonzero(np.isneginf(logits))))
    return ValueCheck(rows, by_prop, zero, outside.any(axis=1), domain_by_prop, infinite)


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


def _extract(header: Header, vertex_h: Element, ply: plyfile.PlyData, path: Path, f, file_bytes: int,
             digest=None, file_hash=None, threads=None, prepare: bool = False, upload=None) -> PlyArrays:
    """The vertex columns as host arrays (float32; int64 for integer extras). A binary vertex element
    at a known offset is read from the file by :func:`~nanogs_warp.io.ply_read.read_vertex_rows` on several threads (with
    ``prepare``: checked block by block and quaternions normalised, as ``quats_xyzw``); otherwise
    plyfile's array is converted, and the file hashed in a pass of its own when asked."""
    n = vertex_h.count
    data = ply["vertex"].data
    if data.shape != (n,):
        raise ValueError(f"vertex data has shape {data.shape}, expected ({n},)")
    fields = data.dtype.fields
    itemsize = data.dtype.itemsize
    names = [p.name for p in vertex_h.props]
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    known = set(REQUIRED_NAMES) | {f"f_rest_{i}" for i in range(n_rest)}
    extra_names = [p for p in names if p not in known]
    extra_set = set(extra_names)
    integer_names = [p.name for p in vertex_h.props if p.name in extra_set and p.dtype.kind in "iu"]
    integer_set = set(integer_names)
    offset = _binary_offset(header, "vertex")
    if offset is None and isinstance(data, np.memmap) and data.flags.c_contiguous:
        # after a list element: at the offset plyfile parsed its way to. The rows are read from the
        # file, never through plyfile's map: a mapped page beyond the end of a file that shrinks
        # while it is read kills the process (SIGBUS), where a read comes back short
        direct = True
        offset = data.offset
    else:  # plyfile found the same first record at the offset: trust it (else use plyfile's array)
        direct = (offset is not None and data.flags.c_contiguous
                  and os.pread(f.fileno(), itemsize, offset) == data[:1].view(np.uint8).tobytes())  # fmt: skip
    quats = ("quats_xyzw", ROT_NAMES[1:] + ROT_NAMES[:1]) if direct and prepare else ("rotations", ROT_NAMES)
    surfels = has_surfels(names)
    groups = {
        "means": MEAN_NAMES,
        quats[0]: quats[1],
        "log_scales": SCALE_NAMES[:2] if surfels else SCALE_NAMES,
        "opacities": OPACITY_NAMES,
        "features": DC_NAMES + tuple(f"f_rest_{i}" for i in range(n_rest)),
        "extras": tuple(p for p in extra_names if p not in integer_set),
        "integer_extras": tuple(integer_names),
    }
    arrays = {key: np.empty((n, len(group)), np.int64 if key == "integer_extras" else np.float32)
              for key, group in groups.items()}  # fmt: skip
    if surfels:  # a 2DGS file: its splats flat, the third axis's column filled before the rows are read
        arrays["log_scales"] = np.full((n, 3), FLAT_LOG_SCALE, np.float32)
    columns = {key: Columns(arrays[key], _runs(fields, group)) for key, group in groups.items()}
    threads = read_threads(file_bytes, threads)
    check = None
    if direct:
        if upload is not None:
            upload.begin(arrays)
        found = read_vertex_rows(f.fileno(), file_bytes, offset, n, itemsize, columns, threads,
                                 unit_size(file_bytes, threads, _READ_UNIT_BYTES),
                                 prepare, file_hash, digest, upload.rows if upload is not None else None)  # fmt: skip
        check = found if prepare else None
    else:
        if digest is not None or file_hash is not None:  # a pass of its own
            read_vertex_rows(f.fileno(), file_bytes, 0, 0, 1, {}, threads, _CHUNK_BYTES, False, file_hash, digest)
        rows = np.ascontiguousarray(data).view(np.uint8).reshape(n, itemsize)
        step = max(1, _CHUNK_BYTES // itemsize)
        for start in range(0, n, step):
            block = rows[start : start + step]
            for plan in columns.values():
                out = plan.out[start : start + step]
                for i, j, dt, off in plan.runs:
                    copy_run(out[:, i:j], block[:, off : off + (j - i) * dt.itemsize], dt)
    arrays["opacities"] = arrays["opacities"].reshape(n)

    others = []
    for e in ply.elements:
        if e.name != "vertex":
            e.data = _detached(e.data, f, path.name)
            others.append(e)
    layout = PlyLayout(
        properties=[(p.name, p.dtype.str[1:]) for p in vertex_h.props],
        extra_names=extra_names,
        other_elements=others,
        comments=list(ply.comments),
        obj_info=list(ply.obj_info),
        surfels=surfels,
    )
    return PlyArrays(arrays, layout, header.format, file_bytes, check, trailing_bytes(header, file_bytes))


_CHUNK_BYTES = 4 << 20  # rows are written by save_ply (and converted from plyfile's array) in chunks of about this size
_READ_UNIT_BYTES = 8 << 20  # the largest unit of rows of a reader thread (ply_read.unit_size)


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


def _detached(data: np.ndarray, f, name: str) -> np.ndarray:
    """An element's rows in memory of their own: those plyfile mapped are read from the file (a
    file that shrank since is one line, where a mapped page beyond its end would kill the process)."""
    if not isinstance(data, np.memmap):
        return np.array(data)
    size = data.size * data.dtype.itemsize
    raw = os.pread(f.fileno(), size, data.offset)
    if len(raw) != size:
        raise InputError(f"{name}: malformed PLY file: the file changed while it was read")
    return np.frombuffer(raw, data.dtype).reshape(data.shape).copy()


def _binary_offset(header: Header, name: str) -> int | None:
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


def _looks_truncated(e: plyfile.PlyElementParseError, header: Header | None, path: Path) -> bool:
    """plyfile's "early end-of-file", or an ASCII line cut short in a file without a final newline."""
    if "early end-of-file" in e.message:
        return True
    if header is None or header.format != "ascii" or "early end-of-line" not in e.message:
        return False
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) not in (b"\n", b"\r")


def _describe_invalid(check: ValueCheck, wide=()) -> str:
    parts = []
    n_nf = int(np.count_nonzero(check.nonfinite_rows))
    if n_nf:
        props = sorted(check.nonfinite_by_property, key=_natural_prop)
        shown = ", ".join(props[:8]) + (f", ... ({len(props)} properties)" if len(props) > 8 else "")
        beyond = " (a double beyond float32's +-3.4e38 counts as Inf)" if set(props) & set(wide) else ""
        parts.append(f"{n_nf} with NaN/Inf values{beyond} in {shown}")
    n_zq = int(np.count_nonzero(check.zero_quat_rows))
    if n_zq:
        parts.append(f"{n_zq} with zero-norm quaternions")
    n_od = int(np.count_nonzero(check.out_of_domain_rows))
    if n_od:
        props = ", ".join(sorted(check.out_of_domain_by_property))
        parts.append(f"{n_od} with log-scales outside [-{LOG_SCALE_LIMIT:g}, {LOG_SCALE_LIMIT:g}] in {props}")
    return "; ".join(parts)


# ----------------------------------------------------------------------------------------------


def _natural_prop(s: str):
    order = {n: i for i, n in enumerate(REQUIRED_NAMES)}
    return (order.get(s, len(order)), natural(s))
