"""Writing a :class:`SplatSet`'s host arrays as a binary little-endian 3DGS PLY file.

Packs the vertex rows in chunks, block by block, behind a header made by plyfile, into a temporary
file that then replaces the target (see :func:`nanogs_warp.io.ply.save_ply`, the public entry point).
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import signal
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import plyfile

from ..errors import InputError
from ..file_identity import file_identity
from ..temporaries import remove_if_still, remove_stale_temporaries, temporary_path, through_links  # noqa: F401 - re-exported
from .ply_header import (
    DC_NAMES,
    MEAN_NAMES,
    NORMAL_NAMES,
    OPACITY_NAMES,
    REQUIRED_NAMES,
    ROT_NAMES,
    SCALE_NAMES,
    one_line,
)
from .ply_layout import PlyLayout
from .ply_read import read_threads

_INRIA_HEAD = MEAN_NAMES + NORMAL_NAMES + DC_NAMES
_INRIA_TAIL = OPACITY_NAMES + SCALE_NAMES + ROT_NAMES


def output_properties(
    layout: PlyLayout | None, n_rest: int, n_extra: int, n_integer_extra: int = 0
) -> list[tuple[str, str]]:
    """The vertex properties to write: the layout's (the f_rest block resized to ``n_rest``), or
    without a layout the INRIA ones in float32 and ``n_extra`` float extras ``extra_<i>``.
    ``n_extra`` and ``n_integer_extra`` are the splats' float and integer extra columns."""
    rest = [f"f_rest_{i}" for i in range(n_rest)]
    if layout is None:
        if n_integer_extra:
            raise ValueError(f"{n_integer_extra} integer extras need a layout that names and types them")
        names = list(_INRIA_HEAD) + rest + list(_INRIA_TAIL) + [f"extra_{i}" for i in range(n_extra)]
        return [(n, "f4") for n in names]
    counts = (len(layout.float_extra_names), len(layout.integer_extra_names))
    if counts != (n_extra, n_integer_extra):
        raise ValueError(f"layout names {counts[0]} float and {counts[1]} integer extras but the splats have "
                         f"{n_extra} and {n_integer_extra}")  # fmt: skip
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
    if layout.surfels and "scale_2" not in names:  # a 2DGS file's layout: written as 3DGS
        at = next(i for i, (n, _) in enumerate(props) if n == "scale_1")
        props.insert(at + 1, ("scale_2", props[at][1]))
        names.add("scale_2")
    missing = [n for n in REQUIRED_NAMES + tuple(layout.extra_names) if n not in names]
    if missing:
        raise ValueError(f"layout lacks properties {missing}")
    return props


def write_ply_stream(stream, host: dict[str, np.ndarray], props: list[tuple[str, str]], layout,
                     chunk_bytes: int, threads: int | None = None) -> None:
    """Writes the header (via plyfile), the vertex rows in packed chunks of about ``chunk_bytes``,
    then the other elements (serialised by plyfile) to a binary stream. ``host`` holds 2D float32
    arrays ``means``, ``log_scales``, ``opacities``, ``features``, ``extras`` and the quaternions,
    as ``rotations`` (w first, as in the file) or ``quats_xyzw`` (Warp's order), and, when the
    layout has integer extras, their int64 ``integer_extras``. Chunks are packed on ``threads``
    threads (at least two when there are several chunks) and written in order, each by the thread
    that packed it, so that packing the next chunks overlaps writing this one."""
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
    step = max(1, chunk_bytes // dtype.itemsize)
    chunks = list(range(0, n, step))
    if len(chunks) == 1:
        rows = np.empty(n, dtype)
        _pack_rows(plan, rows, 0)
        stream.write(memoryview(rows.view(np.uint8)))
    else:
        _write_chunks(stream, plan, dtype, n, step, chunks, max(2, read_threads(n * dtype.itemsize, threads)))
    if others:
        tail = plyfile.PlyData(others, text=False, byte_order="<")
        body = io.BytesIO()
        tail.write(body)
        stream.write(body.getbuffer()[len(tail.header) + 1 :])


def _write_chunks(stream, plan, dtype: np.dtype, n: int, step: int, chunks: list[int], threads: int) -> None:
    """Packs the chunks on ``threads`` threads, one buffer each, and writes them in order: a thread
    packs its chunk, waits for the previous chunk to be written, writes its own and takes the next.
    After an error no later chunk is written (the caller removes the file)."""
    local = threading.local()
    turns = [threading.Event() for _ in chunks]
    failed = threading.Event()

    def pack_and_write(k: int) -> None:
        try:
            buffer = getattr(local, "buffer", None)
            if buffer is None:
                buffer = local.buffer = np.empty(step, dtype)
            rows = buffer[: min(step, n - chunks[k])]
            _pack_rows(plan, rows, chunks[k])
            if k > 0:
                turns[k - 1].wait()
            if failed.is_set():
                return
            stream.write(memoryview(rows.view(np.uint8)))
        except BaseException:
            failed.set()
            raise
        finally:
            turns[k].set()

    pool = ThreadPoolExecutor(threads, thread_name_prefix="nanogs-write")
    try:
        for future in [pool.submit(pack_and_write, k) for k in range(len(chunks))]:
            future.result()
    finally:
        failed.set()
        for turn in turns:  # no thread waits for ever
            turn.set()
        pool.shutdown(wait=True)


def _pack_plan(host, props, layout, dtype) -> list[tuple[int, np.dtype, int, np.ndarray | None]]:
    """Runs of output properties that come from adjacent columns of one host array:
    (byte offset, dtype, count, source columns (N, count) or None for zeros)."""
    n = host["means"].shape[0]
    where: dict[str, tuple[str, int]] = {}
    for group, names in (("means", MEAN_NAMES), ("rotations", ROT_NAMES), ("log_scales", SCALE_NAMES),
                         ("opacities", OPACITY_NAMES)):
        where.update({nm: (group, i) for i, nm in enumerate(names)})
    if "quats_xyzw" in host:  # rot_0 (w) is the last column; rot_1..rot_3 the first three
        where.update({nm: ("quats_xyzw", (i + 3) % 4) for i, nm in enumerate(ROT_NAMES)})
    for i in range(host["features"].shape[1]):
        where[DC_NAMES[i] if i < 3 else f"f_rest_{i - 3}"] = ("features", i)
    if layout is None:
        where.update({f"extra_{i}": ("extras", i) for i in range(host["extras"].shape[1])})
    else:
        where.update({nm: ("extras", i) for i, nm in enumerate(layout.float_extra_names)})
        where.update({nm: ("integer_extras", i) for i, nm in enumerate(layout.integer_extra_names)})
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
        block = raw[:, off : off + k * dt.itemsize]
        if columns is None:
            block.view(np.dtype((np.void, block.shape[1])))[:, 0] = b"\0" * block.shape[1]
            continue
        values = columns[start:stop]
        if dt.kind in "iu":  # integer extras (int64): clipped to the type
            info = np.iinfo(dt)
            values = np.clip(values, info.min, info.max)
        copy_columns(block, values, dt)


def copy_columns(block: np.ndarray, values: np.ndarray, dt: np.dtype) -> None:
    """``block`` ((rows, k * itemsize) bytes of packed records) = ``values`` (rows, k) as ``dt``.
    When no conversion is needed each row's run is copied as one opaque item, about twice as fast
    as numpy's element-wise strided copy of short rows."""
    if values.dtype == dt and values.strides[-1] == dt.itemsize and block.strides[-1] == 1:
        run = np.dtype((np.void, values.shape[1] * dt.itemsize))
        block.view(run)[:, 0] = values.view(run)[:, 0]
    else:
        block.view(dt)[...] = values


class OutputSet:
    """A run's output files, each written under a temporary name beside its path (``atomic_write``
    with ``outputs``) and all moved into place together by ``publish``, or all removed by
    ``discard``: a run that fails part way (a full disk at its third file, a signal) leaves none of
    them, and no folder it made for them. Without ``overwrite`` a file that appeared at one of the
    paths is an InputError at ``publish``. Files may be added from another thread. ``keep``: files
    never written over nor retired (``retire``), whatever an older output says of them: the run's
    inputs."""

    def __init__(self, overwrite: bool = True, keep=()):
        self.overwrite = overwrite
        self._keep = {os.path.realpath(p) for p in keep}
        self._staged: list[tuple[Path, Path]] = []  # (temporary, path)
        self._folders: list[Path] = []  # made for the outputs, outermost first
        self._wanted: set[Path] = set()  # every folder make_folder was asked for, made here or found
        self._retired: list[Path] = []  # older outputs' files that the staged ones make stale
        self._lock = threading.Lock()

    def stage(self, tmp: Path, path: Path) -> None:
        """Adds a written temporary file, to be moved to ``path``; InputError where ``path`` is one
        of the files kept (the run's inputs: an output would replace what it was made from)."""
        if os.path.realpath(path) in self._keep:
            raise InputError(f"{path.name}: is one of the files the run reads ({path}); choose another output path")
        with self._lock:
            self._staged.append((tmp, path))

    def make_folder(self, folder: Path) -> None:
        """Makes ``folder`` and its missing parents, remembered for ``discard``; InputError if it cannot."""
        missing = [f for f in (folder, *folder.parents) if not f.exists()][::-1]
        with self._lock:  # remembered first: a signal during mkdir must not leave them
            self._folders += [f for f in missing if f not in self._folders]
            self._wanted.add(folder)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise InputError(f"{folder}: cannot create the directory: {e.strerror or e}") from e

    def wants(self, folder: Path) -> bool:
        """Whether ``folder`` was made (or found) by ``make_folder``: one to make again if another
        writer's ``discard`` removed it, empty, since (two scenes of a batch sharing a folder)."""
        return folder in self._wanted

    def retire(self, paths) -> None:
        """Files of an older output that the staged ones replace as a whole without writing over
        them (a level-of-detail set's levels beyond the new set's): removed once every staged file
        is in place, and their folders with them where left empty; kept if the run fails."""
        with self._lock:
            known = set(self._retired)
            for path in map(Path, paths):
                if path not in known and os.path.realpath(path) not in self._keep:
                    self._retired.append(path)
                    known.add(path)

    def publish(self) -> list[tuple[Path, tuple[int, int] | None]]:
        """Moves every staged file into place, in the order staged, with SIGINT, SIGTERM and SIGHUP
        held until the last is moved (``signals_held``), then removes the retired files. If one
        cannot be moved, the rest are removed, and so are the files already moved that replaced
        nothing (InputError); one that replaced an older file (``overwrite``) stays, as the older
        one is gone, and the retired files stay. Returns each file moved, as (the path it was moved
        to, links followed; the identity of the file moved), for ``remove_if_still``."""
        placed = []  # the paths moved into place that replaced nothing, with the identity of the file moved
        published = []
        done = 0
        with signals_held():
            with self._lock:  # taken inside: a signal just before would have found nothing to discard
                staged, self._staged = self._staged, []
            try:
                for tmp, path in staged:
                    existed = os.path.lexists(path)
                    moved = file_identity(tmp, follow_links=False)
                    if self.overwrite or not _linked(tmp, path):
                        os.replace(tmp, path)
                    done += 1
                    published.append((path, moved))
                    if not existed and moved is not None:
                        placed.append((path, moved))
            except BaseException as e:
                for path_moved, identity in placed:
                    remove_if_still(path_moved, identity)
                self._staged = staged[done:]
                self.discard()
                if isinstance(e, OSError):
                    raise InputError(f"{path.name}: cannot write the file: {e.strerror or one_line(e)}") from e
                raise
            with self._lock:
                retired, self._retired = self._retired, []
            for path in retired:
                _remove(path)
            for folder in dict.fromkeys(path.parent for path in retired):
                try:
                    folder.rmdir()  # only where nothing else is left in it
                except OSError:
                    pass
        with self._lock:
            self._folders = []
        return published

    def discard(self) -> None:
        """Removes every staged file and the folders made for them (where empty)."""
        with self._lock:
            staged, self._staged = self._staged, []
            folders, self._folders = self._folders, []
            self._retired = []
        for tmp, _ in staged:
            _remove(tmp)
        for folder in reversed(folders):
            try:
                folder.rmdir()
            except OSError:
                pass


@contextlib.contextmanager
def signals_held():
    """SIGINT, SIGTERM and SIGHUP that arrive in the block are acted on when it ends: the handlers
    in place are restored and the first such signal raised again. Only on the main thread (Python
    sets handlers there alone); elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {}
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        number = getattr(signal, name, None)
        if number is not None and signal.getsignal(number) not in (None, signal.SIG_IGN):  # one ignored stays so
            previous[number] = signal.signal(number, lambda received, frame: pending.append(received))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        if pending:  # the handler's exception raised here, not in whatever runs next (a __del__ would swallow it)
            handler = previous[pending[0]]
            if callable(handler):
                handler(pending[0], None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(pending[0])


def _remove(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def refuse_no_file(path: Path) -> None:
    """An InputError where ``path`` (links already followed) is a folder, or something there is no
    regular file (a FIFO, a device): no file can be written in its place."""
    if path.is_dir():
        raise InputError(f"{path.name}: is a directory")
    if path.exists() and not path.is_file():
        raise InputError(f"{path.name}: exists and is not a regular file")


def atomic_write(path: Path, write, overwrite: bool = True, outputs: OutputSet | None = None) -> None:
    """Calls ``write(stream)`` on a new temporary file beside ``path`` and moves it into place;
    without ``overwrite`` only where no file is (a file that appeared since it was checked, say by
    another run writing the same name, is an InputError and stays as it is). With ``outputs`` the
    temporary file is left to ``outputs.publish`` instead (``OutputSet``). A symbolic link at
    ``path`` is written through: the file it names is replaced and the link stays
    (``through_links``)."""
    path = through_links(path)
    name = path.name
    directory = path.parent
    refuse_no_file(path)
    remake = outputs is not None and outputs.wants(directory)
    if not remake and not directory.is_dir():
        raise InputError(f"{name}: cannot write: directory {str(directory)!r} does not exist")
    tmp = temporary_path(path)
    created = True  # before the file exists: a signal just after os.open must not leave it behind
    try:
        for attempt in range(3):
            if remake:
                outputs.make_folder(directory)
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
                break
            except FileExistsError:  # another writer's (the names are random): not this one's to remove
                created = False
                raise
            except FileNotFoundError:  # the folder removed, empty, by another scene's writer that failed
                if not remake or attempt == 2:
                    raise
        with os.fdopen(fd, "wb") as f:
            write(f)
        if outputs is not None:
            outputs.stage(tmp, path)
        elif overwrite or not _linked(tmp, path):
            os.replace(tmp, path)
        created = False
    except OSError as e:
        if isinstance(e, PermissionError) or e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise InputError(f"{name}: cannot write to {str(directory)!r}: permission denied") from e
        raise InputError(f"{name}: cannot write the file: {e.strerror or one_line(e)}") from e
    finally:
        if created:
            _remove(tmp)


TEMPORARY_EXTRA_BYTES = 1 + 1 + 7 + 1 + 12 + 4  # ".<name>.<pid>-<12 hex>.tmp": pids below 10^7
LONGEST_OUTPUT_NAME = 255 - TEMPORARY_EXTRA_BYTES  # a file name's bytes on common file systems, less the temporary's


def check_name_length(path: Path) -> None:
    """An InputError where ``path``'s name is too long for its temporary file to be made beside it."""
    length = len(os.fsencode(path.name))
    if length > LONGEST_OUTPUT_NAME:
        raise InputError(f"output name {path.name[:40]}... is {length} bytes long; at most {LONGEST_OUTPUT_NAME} can be written")


def _linked(tmp: Path, path: Path) -> bool:
    """Puts ``tmp`` in place as ``path`` only if no file is there (a hard link, then the temporary's
    name removed): True when done; False where the file system has no hard links (the caller then
    renames it, as with ``overwrite``). A file already at ``path`` is an InputError."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise InputError(f"output {path} already exists; pass --overwrite (-w) to replace it") from None
    except OSError as e:
        if e.errno in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK):
            return False
        raise
    os.unlink(tmp)
    return True

