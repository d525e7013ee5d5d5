"""The package's Warp kernels and Warp's kernel cache: where the cache is, whether it already holds
the kernels a command needs, loading (or compiling) them in parallel, and ``nanogs-warp warmup``,
which compiles every kernel ahead of time, for instance while a farm's container image is built.

Warp compiles each kernel module the first time it is used on a device and keeps the binary in its
kernel cache: ``$NANOGS_WARP_CACHE`` if set (this package's own variable), else Warp's
``$WARP_CACHE_PATH``, else ``~/.cache/warp/<version>``. Binaries are keyed by the module's
content, the device kind and (for CUDA) the GPU architecture, so one cache directory can serve
several GPU generations once it holds a binary for each.
"""

from __future__ import annotations

import errno
import importlib
import json
import os
import sys
import threading
import time
from pathlib import Path

from .errors import InputError
from .shipped_kernels import SHIPPED_ARCHS

CACHE_VARIABLE = "NANOGS_WARP_CACHE"

# The kernel modules each command launches (their Warp helpers come with them).
SIMPLIFY_MODULES = ("knn", "edges", "cost", "field_cost", "pairing", "compact", "merge", "prune", "splat_size")
EVAL_MODULES = ("render",)
REFINE_MODULES = ("render", "render_grad", "image_loss", "adam")
ALL_MODULES = SIMPLIFY_MODULES + EVAL_MODULES + REFINE_MODULES[1:]

def simplify_modules(config=None) -> tuple[str, ...]:
    """The kernel modules a simplification with ``config`` (a SimplifyConfig) launches: its cost's
    module, pruning only when it prunes, the size fit (with the renderer) only when it fits for size
    or colour and refinement's modules when it fits the geometry or the colours (None: every one of
    SIMPLIFY_MODULES). A module left out would still load when first launched."""
    if config is None:
        return SIMPLIFY_MODULES
    cost = "field_cost" if config.cost == "field" else "cost"
    prune = ("prune",) if config.prune_opacity > 0 else ()
    fit = ("splat_size", "render") if config.fit_size or config.fit_colour else ()
    if config.fit_geometry or config.fit_colour:
        fit += tuple(m for m in REFINE_MODULES if m not in fit)
    optional = ("cost", "field_cost", "prune", "splat_size")
    return tuple(m for m in SIMPLIFY_MODULES if m not in optional) + (cost,) + prune + fit


# GPU architectures compiled by `warmup` on a machine without a GPU: the shipped ones (Turing to Blackwell).
DEFAULT_ARCHS = SHIPPED_ARCHS


def cache_dir_from_environment() -> str | None:
    """The kernel cache directory the user asked for ($NANOGS_WARP_CACHE), if any."""
    return os.environ.get(CACHE_VARIABLE) or None


def _home_expanded(path: str | os.PathLike, what: str) -> Path:
    """``path`` with a leading ``~`` or ``~user`` expanded; InputError where that home is unknown,
    or where the name is not UTF-8 (Warp passes it to its native code as UTF-8)."""
    try:
        expanded = Path(path).expanduser()
    except RuntimeError:  # "Could not determine home directory"
        raise InputError(f"{what} {os.fspath(path)}: its '~' names no home directory known here") from None
    try:
        str(expanded).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{what} {os.fsencode(expanded)!r}: the name is not UTF-8, which Warp needs; choose another folder") from None
    return expanded


def use_cache_dir(path: str | os.PathLike | None, must_write: bool = False) -> None:
    """Points Warp's kernel cache at ``path`` (created if needed); call before Warp initialises.
    None leaves Warp's own choice ($WARP_CACHE_PATH or its default), after checking that a
    $WARP_CACHE_PATH can hold it (Warp would fail on its own with a traceback). An existing folder
    that cannot be written (a cache baked into a read-only image) is used as it is, unless
    ``must_write`` (``warmup``): ``load_kernels`` then says so in one line if it lacks a module."""
    import warp as wp

    from .folders import writable_folder

    def usable(folder: Path, what: str) -> None:
        if must_write or not (folder.is_dir() and os.access(folder, os.R_OK | os.X_OK)):
            writable_folder(folder, what)

    if path is None:
        chosen = os.environ.get("WARP_CACHE_PATH")
        if chosen:
            folder = _home_expanded(chosen, "WARP_CACHE_PATH") / wp.config.version
            usable(folder, f"WARP_CACHE_PATH {chosen}: kernel cache {folder}")
        return
    path = _home_expanded(path, "kernel cache")
    usable(path, f"kernel cache {path}")
    wp.config.kernel_cache_dir = str(path.resolve())


def warp_modules(names=ALL_MODULES) -> list:
    """The Warp modules of the named kernel files (importing them registers their kernels)."""
    import warp as wp

    modules = []
    for name in names:
        python_module = importlib.import_module(f"nanogs_warp.kernels.{name}")
        modules.append(wp.get_module(python_module.__name__))
    return modules


def missing_modules(modules: list, device) -> list:
    """Those of ``modules`` that the kernel cache holds no binary of for ``device``."""
    import warp as wp

    from .shipped_kernels import cache_entry

    root = Path(wp.config.kernel_cache_dir)
    missing = []
    for module in modules:
        try:
            folder, binary = cache_entry(module, device)
            present = (root / folder / binary).exists()
        except Exception:  # noqa: BLE001 - a Warp internal changed: say nothing rather than fail
            present = True
        if not present:
            missing.append(module)
    return missing


def missing_after_shipped(modules: list, device) -> list:
    """Those of ``modules`` that must be compiled for ``device``: neither in the kernel cache nor
    shipped in the package for it (the shipped ones are copied into the cache here)."""
    from .shipped_kernels import install_shipped

    missing = missing_modules(modules, device)
    if missing:
        installed = install_shipped(missing, device)
        missing = [m for m in missing if m not in installed]
    return missing


# (device, module name) pairs whose shipped binaries were copied into the cache, or found there, in
# this process (``use_shipped_kernels``; ``load_kernels`` adds its own)
_SHIPPED_CHECKED: set[tuple[str, str]] = set()
_SHIPPED_LOCK = threading.Lock()


def use_shipped_kernels(device, names) -> None:
    """For the Python API (the commands call ``load_kernels`` before they start): copies into the
    kernel cache the package's shipped binaries of the named modules that it lacks for ``device`` (a
    Warp device), then loads the modules there (compiling what ships for no such device), once a
    process and device, so that a program on a fresh machine compiles nothing that ships. Loaded
    here, under a lock, not on a first launch: the CPU's launches run on several threads at once
    (``parallel``), and two threads whose first launch of a module met in Warp's lazy load crashed
    the process (a segmentation fault, programs that call from several threads)."""
    key = str(device)
    with _SHIPPED_LOCK:
        todo = tuple(name for name in names if (key, name) not in _SHIPPED_CHECKED)
        if todo:
            modules = warp_modules(todo)
            _force_load(modules, [device], len(missing_after_shipped(modules, device)))
            _SHIPPED_CHECKED.update((key, name) for name in todo)


def load_kernels(device, names=SIMPLIFY_MODULES, announce: bool = True) -> float:
    """Loads the named kernel modules on ``device`` (a Warp device), compiling those the cache
    lacks, several at once; when some must be compiled and ``announce`` is true, one line on stderr
    says so first. Returns the seconds it took."""
    import warp as wp

    started = time.perf_counter()
    modules = warp_modules(names)
    missing = missing_after_shipped(modules, device)
    if missing and wp.config.kernel_cache_dir and not os.access(wp.config.kernel_cache_dir, os.W_OK):
        raise InputError(f"kernel cache {wp.config.kernel_cache_dir} is read-only and lacks {len(missing)} compiled kernel "
                         f"module(s) for {device}: fill it with 'nanogs-warp warmup --cache-dir DIR' where it can be "
                         "written, or point NANOGS_WARP_CACHE at a writable folder")  # fmt: skip
    if missing and announce:
        print(f"nanogs-warp: compiling {len(missing)} kernel module(s) for {device} (once; they are kept in "
              f"{wp.config.kernel_cache_dir}; 'nanogs-warp warmup' does this ahead of time)", file=sys.stderr)  # fmt: skip
        sys.stderr.flush()
    _force_load(modules, [device], len(missing))
    with _SHIPPED_LOCK:
        _SHIPPED_CHECKED.update((str(device), name) for name in names)
    return time.perf_counter() - started


def warmup(devices: list, archs: list[int], names=ALL_MODULES) -> list[tuple[str, int, float]]:
    """Compiles every kernel module for each Warp device in ``devices`` (as the commands will load
    them there; the shipped binaries are copied instead where they serve) and, with no GPU needed,
    for each CUDA architecture in ``archs``, both as the CUBIN and as the PTX that Warp picks on
    that GPU with an older or a newer driver (PTX for an older architecture, ``default_ptx_arch``,
    which serves every later one). An architecture whose binaries ship with the package is not
    compiled again. Returns (target, binaries compiled, seconds) per target."""
    from concurrent.futures import ThreadPoolExecutor

    import warp as wp

    from .shipped_kernels import shipped_archs

    modules = warp_modules(names)
    report = []
    for device in devices:
        started = time.perf_counter()
        missing = len(missing_after_shipped(modules, device))
        _force_load(modules, [device], missing)
        report.append((str(device), missing, time.perf_counter() - started))
    from warp._src.context import runtime

    ptx_archs = {arch: min(arch, wp.config.ptx_target_arch or runtime.default_ptx_arch) for arch in archs}
    shipped = shipped_archs()
    for arch in archs:
        if arch in shipped:
            report.append((f"sm_{arch} (shipped with the package)", 0, 0.0))
            continue
        started = time.perf_counter()
        jobs = [(m, arch, False) for m in modules] + [(m, ptx_archs[arch], True) for m in modules]
        with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
            list(pool.map(lambda job: wp.compile_aot_module(job[0], arch=job[1], use_ptx=job[2]), jobs))
        report.append((f"sm_{arch}", len(jobs), time.perf_counter() - started))
    return report


def _force_load(modules: list, devices: list, to_compile: int) -> None:
    """Loads ``modules`` on ``devices``, compiling up to one module per CPU core at once when
    several must be compiled. (Warp's options, precompiled headers included, are left as they are:
    they are part of each binary's key in the cache, so a different setting would compile
    binaries that the commands never load.)"""
    import warp as wp

    workers = min(to_compile, os.cpu_count() or 1)
    try:
        wp.force_load(device=devices, modules=modules, max_workers=workers if workers > 1 else 0)
    except json.JSONDecodeError as e:  # a module's metadata file in the cache is not JSON
        raise RuntimeError(f"Failed to load a kernel module: its metadata in the cache is not JSON ({e})") from e
    except OSError as e:  # the cache's disk is full: not the command's output, which a bare ENOSPC would say
        if e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EIO):
            raise InputError(f"kernel cache {wp.config.kernel_cache_dir}: cannot write the compiled kernels: {e.strerror}") from e
        raise


def damaged_cache(error: BaseException) -> str | None:
    """One line for an error of Warp's that means a compiled module in the kernel cache is damaged
    (it cannot be loaded, or lacks a kernel it must hold); None for any other error."""
    if not str(error).startswith(("Failed to load CPU module", "Failed to load CUDA module", "Failed to load a kernel module",
                                  "Failed to find forward kernel")):
        return None
    import warp as wp

    return (f"kernel cache {wp.config.kernel_cache_dir}: a compiled kernel module is damaged ({error}); "
            "delete the directory to compile the kernels again")
