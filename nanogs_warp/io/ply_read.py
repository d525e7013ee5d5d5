"""Reading a binary PLY's vertex rows on several threads, hashing the file in the same pass, and
the value checks and quaternion normalisation done on each block of rows while it is in cache.

The file is cut into units of a few MB. Each reader thread takes the next unit, reads it with one
``preadv`` into a buffer of its own (the kernel's copy runs without the GIL, in parallel), hashes
it when asked, copies each group of columns (means, quaternions, ...) out of the rows as one
strided block and, for ``prepare``, checks the block's values (min and max per group: NaN and
Inf propagate) and normalises its quaternions, while the rows are still in the CPU's cache. No
Warp here: ``info`` and the batch's readers use it without it.

The file hash (:class:`PieceHash`, the batch's resume records) is the SHA-256 of the
concatenated SHA-256 digests of the file's consecutive 1 MiB pieces: each piece is hashed by the
thread that read it, so hashing runs on every reader thread, not on one.
"""

from __future__ import annotations

import hashlib
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..domain import LOG_SCALE_LIMIT
from .open_file import open_regular

PIECE_BYTES = 1 << 20  # the hash's piece size: part of the hash's definition, never change it
_UNIT_BYTES = 8 << 20  # the largest unit of a reader thread when the file is hashed (whole pieces)
_UNITS_PER_THREAD = 16  # enough units for the threads to even out; fewer, larger units mean fewer GIL round trips
_MAX_THREADS = 8
_THREADS_PER_BYTES = 8 << 20  # one more reader thread per this many bytes of file, up to the cores

_default_threads: int | None = None


def set_read_threads(threads: int | None) -> None:
    """How many threads read (and hash) a file from now on in this process; None: automatic
    (one per 8 MB of file, at most one per CPU core and at most 8)."""
    global _default_threads
    _default_threads = None if threads is None else max(1, int(threads))


def read_threads(file_bytes: int, threads: int | None = None) -> int:
    """The number of threads to read a file of ``file_bytes`` with."""
    if threads is None:
        threads = _default_threads
    if threads is not None:
        return max(1, threads)
    return max(1, min(cpu_count(), _MAX_THREADS, -(-file_bytes // _THREADS_PER_BYTES)))


def cpu_count() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    """A pool of reader threads, started once per process (and per size) and kept."""
    key = (os.getpid(), threads)
    with _pools_lock:
        pool = _pools.get(key)
        if pool is None:
            pool = _pools[key] = ThreadPoolExecutor(threads, thread_name_prefix="nanogs-read")
    return pool


def run_units(work, units: list, threads: int) -> list:
    """``work(unit)`` for every unit on ``threads`` threads (in order on this thread for one);
    returns the results in unit order and raises the first error."""
    if threads <= 1 or len(units) <= 1:
        return [work(u) for u in units]
    return list(_pool(threads).map(work, units))


class PieceHash:
    """The hash of a file that the batch's records keep: the SHA-256 of the concatenated SHA-256
    digests of its consecutive ``PIECE_BYTES`` pieces (the last one shorter; an empty file has
    none), so that the pieces can be hashed on several threads in any order. ``hexdigest()`` once
    every piece is in."""

    def __init__(self, file_bytes: int):
        self.file_bytes = file_bytes
        self.pieces: list[bytes | None] = [None] * -(-file_bytes // PIECE_BYTES)  # none for an empty file

    def update_pieces(self, first_byte: int, data) -> None:
        """Hashes ``data``, the file's bytes from ``first_byte`` (a multiple of PIECE_BYTES), as
        whole pieces (the last one may end the file)."""
        view = memoryview(data).cast("B")
        index = first_byte // PIECE_BYTES
        for start in range(0, len(view), PIECE_BYTES):
            self.pieces[index] = hashlib.sha256(view[start : start + PIECE_BYTES]).digest()
            index += 1

    def hexdigest(self) -> str:
        missing = [i for i, p in enumerate(self.pieces) if p is None]
        if missing:
            raise ValueError(f"{len(missing)} pieces of the file were not hashed")
        return hashlib.sha256(b"".join(self.pieces)).hexdigest()  # type: ignore[arg-type]


def unit_size(file_bytes: int, threads: int, most: int) -> int:
    """A reader thread's unit of work: the file over 16 units a thread, between 1 MiB and ``most``.
    Each unit costs a few dozen GIL round trips (numpy calls between the copies), which another
    busy Python thread (Warp starting beside the read) slows down; 1 MiB units read a 984 MB file
    at half the speed of 8 MiB units in a fresh process (docs/performance.md)."""
    return max(min(most, PIECE_BYTES), min(most, file_bytes // (max(threads, 1) * _UNITS_PER_THREAD)))


def file_piece_hash(path, threads: int | None = None) -> str:
    """The :class:`PieceHash` of a file, read on several threads."""
    with open_regular(Path(path)) as f:
        size = os.fstat(f.fileno()).st_size
        hasher = PieceHash(size)
        threads = read_threads(size, threads)
        units = _hash_units(size, 0, 0, 1, unit_size(size, threads, _UNIT_BYTES))
        reader = _UnitReader(f.fileno(), _unit_bytes(units), hasher)
        run_units(lambda u: reader.read(u), units, threads)
    return hasher.hexdigest()


@dataclass
class Unit:
    """Bytes [start, stop) of the file are read (hashed up to ``hash_stop``, which is a piece
    boundary or the file's end); rows [first_row, stop_row) of the vertex element start inside
    and are converted."""

    start: int
    stop: int
    hash_stop: int
    first_row: int
    stop_row: int


def _hash_units(size: int, vertex_offset: int, rows: int, itemsize: int, unit_bytes: int) -> list[Unit]:
    """Units covering the whole file, each whole pieces (the rows that start in a unit's pieces
    belong to it; the unit is read on to the end of its last row)."""
    units = []
    step = max(PIECE_BYTES, unit_bytes // PIECE_BYTES * PIECE_BYTES)
    for start in range(0, max(size, 1), step):
        stop = min(size, start + step)
        first = min(rows, max(0, -(-(start - vertex_offset) // itemsize)))
        last = min(rows, max(0, -(-(stop - vertex_offset) // itemsize)))
        units.append(Unit(start, max(stop, vertex_offset + last * itemsize) if last > first else stop, stop, first, last))
    return units


def _row_units(vertex_offset: int, rows: int, itemsize: int, unit_bytes: int) -> list[Unit]:
    """Units of whole rows only (nothing hashed)."""
    step = max(1, unit_bytes // itemsize)
    return [Unit(vertex_offset + r * itemsize, vertex_offset + min(rows, r + step) * itemsize, 0, r, min(rows, r + step))
            for r in range(0, rows, step)]  # fmt: skip


def _unit_bytes(units: list[Unit]) -> int:
    return max((u.stop - u.start for u in units), default=0)


class _UnitReader:
    """Reads units into one buffer per thread and hashes them."""

    def __init__(self, fd: int, buffer_bytes: int, hasher: PieceHash | None = None, digest=None):
        self.fd = fd
        self.buffer_bytes = buffer_bytes
        self.hasher = hasher
        self.digest = digest  # a hashlib object fed in order: only with units read in order
        self.local = threading.local()

    def read(self, unit: Unit) -> np.ndarray:
        """The unit's bytes (a view of this thread's buffer, valid until its next unit)."""
        buffer = getattr(self.local, "buffer", None)
        if buffer is None:
            buffer = self.local.buffer = np.empty(max(1, self.buffer_bytes), np.uint8)
        data = buffer[: unit.stop - unit.start]
        view = memoryview(data)
        done = 0
        while done < len(view):
            got = os.preadv(self.fd, [view[done:]], unit.start + done)
            if got <= 0:
                raise ValueError("the file changed while it was read")
            done += got
        if unit.hash_stop > unit.start:
            hashed = data[: unit.hash_stop - unit.start]
            if self.hasher is not None:
                self.hasher.update_pieces(unit.start, hashed)
            if self.digest is not None:
                self.digest.update(memoryview(hashed))
        return data


# ----------------------------------------------------------------------------------------------
# The vertex rows


@dataclass
class Columns:
    """Where one host array's columns come from: ``runs`` of (first column, stop column, dtype,
    byte offset in the record) of properties adjacent in the record with one dtype."""

    out: np.ndarray  # (N, k) float32
    runs: list[tuple[int, int, np.dtype, int]]


@dataclass
class BlockCheck:
    """What the per-block checks found over the whole file."""

    suspect: bool = False  # a value that needs the exact row-by-row check (NaN/Inf, domain, zero quaternion)
    infinite_opacity: bool = False  # an opacity logit of +-Inf (valid; to be saturated)


def read_vertex_rows(fd: int, file_bytes: int, vertex_offset: int, rows: int, itemsize: int,
                     columns: dict[str, Columns], threads: int, unit_bytes: int, prepare: bool = False,
                     hasher: PieceHash | None = None, digest=None, on_rows=None) -> BlockCheck:  # fmt: skip
    """Fills every ``columns[...].out`` from the file's vertex records (``rows`` records of
    ``itemsize`` bytes from byte ``vertex_offset``), on ``threads`` threads. ``hasher`` (a
    :class:`PieceHash`) or ``digest`` (a hashlib object, fed in order: one thread) is fed every
    byte of the file. With ``prepare``, ``columns`` must hold ``quats_xyzw`` (x, y, z, w), which
    is normalised in place as :func:`nanogs_warp.ply.normalize_quaternions` does (rows that are
    zero or not finite are left as they are), and every block's values are checked: the result
    says whether any may be invalid. ``on_rows(first, stop)``, if given, is called (on the reader's
    thread) as soon as rows [first, stop) of every column are filled, checked and normalised."""
    if hasher is not None and hasher.file_bytes != file_bytes:
        raise ValueError("the file changed while it was read")
    if hasher is not None or digest is not None:
        units = _hash_units(file_bytes, vertex_offset, rows, itemsize, unit_size(file_bytes, threads, _UNIT_BYTES))
    else:
        units = _row_units(vertex_offset, rows, itemsize, unit_bytes)
    if digest is not None:
        threads = 1
    reader = _UnitReader(fd, _unit_bytes(units), hasher, digest)
    plans = list(columns.values())

    def work(unit: Unit) -> BlockCheck | None:
        data = reader.read(unit)
        first, stop = unit.first_row, unit.stop_row
        if stop <= first:
            return None
        at = vertex_offset + first * itemsize - unit.start
        raw = data[at : at + (stop - first) * itemsize].reshape(stop - first, itemsize)
        for plan in plans:
            out = plan.out[first:stop]
            for i, j, dt, off in plan.runs:
                copy_run(out[:, i:j], raw[:, off : off + (j - i) * dt.itemsize], dt)
        found = check_block(columns, first, stop) if prepare else None
        if on_rows is not None:
            on_rows(first, stop)
        return found

    check = BlockCheck()
    with np.errstate(all="ignore"):
        for found in run_units(work, units, threads):
            if found is not None:
                check.suspect |= found.suspect
                check.infinite_opacity |= found.infinite_opacity
    return check


def copy_run(out: np.ndarray, raw: np.ndarray, dt: np.dtype) -> None:
    """``out`` ((rows, k) float32) = ``raw`` ((rows, k * itemsize) bytes of records) read as ``dt``.
    Float32 runs are copied row by row as one opaque item, about twice as fast as numpy's
    element-wise strided copy of short rows."""
    if dt == out.dtype and raw.strides[-1] == 1 and out.strides[-1] == out.itemsize:
        if out.shape[1] == 1:
            out[:, 0] = raw.view(dt)[:, 0]
        else:
            run = np.dtype((np.void, raw.shape[1]))
            out.view(run)[:, 0] = raw.view(run)[:, 0]
    else:
        out[...] = raw.view(dt)


_CHECKED = ("means", "features", "log_scales", "extras")  # must be finite; opacities may be +-Inf


def check_block(columns: dict[str, Columns], first: int, stop: int) -> BlockCheck:
    """Rows [first, stop): finite values (min and max: NaN and Inf propagate into them), log-scales
    in the domain, and the quaternions normalised in place; anything else marks the block."""
    found = BlockCheck()
    for key in _CHECKED:
        block = columns[key].out[first:stop]
        if block.size == 0:
            continue
        low, high = float(block.min()), float(block.max())
        if not (np.isfinite(low) and np.isfinite(high)):
            found.suspect = True
        elif key == "log_scales" and (high > LOG_SCALE_LIMIT or low < -LOG_SCALE_LIMIT):
            found.suspect = True
    opacity = columns["opacities"].out[first:stop]
    low, high = float(opacity.min()), float(opacity.max())
    if np.isnan(low) or np.isnan(high):
        found.suspect = True
    elif np.isinf(low) or np.isinf(high):
        found.infinite_opacity = True
    if not normalize_quaternions_xyzw(columns["quats_xyzw"].out[first:stop]):
        found.suspect = True
    return found


def normalize_quaternions_xyzw(q: np.ndarray) -> bool:
    """Normalises the (rows, 4) float32 (x, y, z, w) quaternions in place, bit for bit as
    :func:`nanogs_warp.ply.normalize_quaternions` does (float64, the squares summed as
    ``(w² + y²) + (x² + z²)``, as numpy's einsum sums them there); rows already unit to float32
    precision are left unchanged. Returns False when a row is zero or not finite (those rows are
    left unchanged)."""
    if _already_unit(q):
        return True
    q64 = q.astype(np.float64)
    squares = np.square(q64)
    norm = squares[:, 3] + squares[:, 1]
    norm += squares[:, 0] + squares[:, 2]
    np.sqrt(norm, out=norm)
    valid = bool(norm.min() > 0) and bool(norm.max() < np.inf)  # NaN: False
    off = norm - 1.0
    fix = np.abs(off, out=off) > 1e-6  # NaN: False
    if valid and fix.all():
        q64 /= norm[:, None]
        q[...] = q64
    else:
        fix &= (norm > 0) & (norm < np.inf)
        if fix.any():
            q[fix] = q64[fix] / norm[fix, None]
    return valid


_SAMPLE_ROWS = 64


def _already_unit(q: np.ndarray) -> bool:
    """Whether every row's squared norm, summed in float32, is within 1e-6 of 1: then its float64
    norm is within 7e-7 of 1 (the float32 sum is off by less than 4e-7), below the 1e-6 that
    normalisation corrects, and the rows stay as they are. Files this tool wrote hold unit
    quaternions; a trained scene's are not unit, which the first rows already show."""
    for rows in (q[:_SAMPLE_ROWS], q):
        squared = np.einsum("ij,ij->i", rows, rows)
        if not bool(np.abs(squared - np.float32(1.0)).max(initial=0.0) <= 1e-6):  # NaN: not unit
            return False
        if rows.shape[0] == q.shape[0]:
            break
    return True
