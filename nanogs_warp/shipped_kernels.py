"""The package's kernels, compiled ahead of time and shipped inside it, so that a fresh machine (a
farm node that starts as a new container, a CI runner) loads them instead of compiling them.

``nanogs_warp/compiled/warp-<version>/<kernel file>.tar.xz`` holds, for one kernel file, the
binaries Warp itself would write into its kernel cache:
- a CUBIN for each architecture in ``SHIPPED_ARCHS`` (what Warp loads when the driver is older than
  its CUDA toolkit, as on most machines today) and the PTX for sm_75 (what it loads with a newer
  driver, on any GPU from Turing on);
- the CPU object for Linux on x86-64 (``CPU_PLATFORM``), compiled for the generic x86-64 target
  (``kernels/options.py``), which any such machine runs;
with each module's metadata. Each binary is named, as in the cache, by the module's content hash
(and a CPU object by the compiler's version and target), so it is only ever used for exactly the
kernels it was compiled from, and only by the Warp version that compiled it. When a command needs a
module that its kernel cache lacks, the matching binary is copied into the cache (file by file,
through a temporary name) and Warp loads it from there as if it had compiled it. Anything not
shipped (another GPU architecture, another Warp, a changed kernel, the CPU of another platform) is
compiled as before, and so is everything when ``NANOGS_WARP_SHIPPED_KERNELS=0`` (to compare the
shipped binaries with a compile of one's own, or to rule them out).

``tools/build_kernels.py`` builds the archives with Warp's bundled compilers (no GPU needed; the CPU
objects on Linux x86-64), and ``tests/test_shipped_kernels.py`` fails when they no longer match the
kernels' sources.
"""

from __future__ import annotations

import io
import lzma
import os
import platform
import tarfile
import tempfile
from pathlib import Path

# CUBINs shipped: Turing, Ampere (data centre and consumer), Ada, Hopper, Blackwell (data centre and consumer).
SHIPPED_ARCHS = (75, 80, 86, 89, 90, 100, 120)
# The PTX that Warp compiles for any GPU of sm_75 or later when the driver is newer than its toolkit.
SHIPPED_PTX_ARCH = 75

PACKAGE_ROOT = Path(__file__).parent / "compiled"
SWITCH_VARIABLE = "NANOGS_WARP_SHIPPED_KERNELS"  # "0": compile every kernel instead
CPU_PLATFORM = ("Linux", "x86_64")  # the platform whose CPU objects ship


def ships_cpu() -> bool:
    """Whether this machine is of the platform whose CPU objects ship (and can build them)."""
    return (platform.system(), platform.machine().lower().replace("amd64", "x86_64")) == CPU_PLATFORM


def shipped_dir(version: str | None = None) -> Path:
    """Where the archives for Warp ``version`` (default: the running one) live."""
    if version is None:
        import warp as wp

        version = wp.config.version
    return PACKAGE_ROOT / f"warp-{version}"


def shipped_archs() -> tuple[int, ...]:
    """The CUDA architectures whose binaries ship for the running Warp (a command copies them into
    its kernel cache when it needs them); none where shipped kernels are switched off."""
    if os.environ.get(SWITCH_VARIABLE, "").strip() == "0" or not shipped_dir().is_dir():
        return ()
    return SHIPPED_ARCHS


def archive_name(module) -> str:
    """The archive of a Warp module: its kernel file's name (``nanogs_warp.kernels.knn`` -> ``knn.tar.xz``)."""
    return module.name.rsplit(".", 1)[-1] + ".tar.xz"


def cache_entry(module, device) -> tuple[str, str]:
    """(folder, file) of the binary that Warp loads for ``module`` on ``device``, inside its kernel cache."""
    from warp._src.context import _resolve_launch_block_dim  # the block size a launch would use

    block_dim = _resolve_launch_block_dim(device, None if device.is_cpu else module.options["block_dim"])
    return module.get_module_identifier(block_dim), module._get_compile_output_name(device, block_dim=block_dim)


def install_shipped(modules: list, device, root: Path | None = None) -> list:
    """Copies the shipped binaries of ``modules`` for ``device`` (a Warp device) into the kernel
    cache ``root`` (default: Warp's), one module per thread (the decompression runs outside the
    interpreter). Returns the modules installed; the others are left to Warp to compile (none
    shipped for this device, platform, Warp version or source, or an archive that cannot be read)."""
    import warp as wp

    if os.environ.get(SWITCH_VARIABLE, "").strip() == "0" or not modules:
        return []
    root = Path(wp.config.kernel_cache_dir if root is None else root)
    archives = shipped_dir()
    workers = min(len(modules), os.cpu_count() or 1)
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers, thread_name_prefix="nanogs-kernels") as pool:
            done = list(pool.map(lambda m: _install(m, device, root, archives), modules))
    else:
        done = [_install(m, device, root, archives) for m in modules]
    return [m for m, ok in zip(modules, done) if ok]


def _install(module, device, root: Path, archives: Path) -> bool:
    """Copies ``module``'s shipped binary for ``device`` and its metadata into the cache ``root``;
    False where there is none to copy, or the cache cannot take it."""
    try:
        folder, binary = cache_entry(module, device)
    except Exception:  # noqa: BLE001 - a device Warp cannot compile for (it says so itself), or a changed Warp internal
        return False
    wanted = [f"{folder}/{folder}.meta", f"{folder}/{binary}"]  # the meta first: a binary is never without it
    try:
        archive = archives / archive_name(module)
        if not archive.is_file():
            return False
        with tarfile.open(archive, "r:xz") as tar:
            files = {m.name: m for m in tar.getmembers() if m.isfile()}
            if not all(name in files for name in wanted):
                return False
            contents = [tar.extractfile(files[name]).read() for name in wanted]
    except (OSError, tarfile.TarError, lzma.LZMAError, EOFError):
        return False
    try:
        target = root / folder
        target.mkdir(parents=True, exist_ok=True)
        for name, data in zip(wanted, contents):
            _write_new(target / name.split("/", 1)[1], data)
    except OSError:  # a cache that cannot take it (full, read-only): Warp compiles, and says why if it cannot
        return False
    return True


def _write_new(path: Path, data: bytes) -> None:
    """Writes ``path`` through a temporary file and a rename, unless it exists (another process may be
    writing the same cache: whichever rename lands, the bytes are the same)."""
    if path.exists():
        return
    handle, temporary = tempfile.mkstemp(prefix=path.name + ".", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as f:
            f.write(data)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def pack(module, cache_root: Path, out_dir: Path, cpu=None) -> Path:
    """Writes ``out_dir``/``archive_name(module)`` from the binaries that ``cache_root`` (a kernel
    cache that Warp compiled them into) holds: ``expected_members``, the CPU object for the Warp
    device ``cpu`` if given. The archive is the same bytes for the same binaries (sorted members, no
    times or owners)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for name in expected_members(module, cpu):
            data = (cache_root / name).read_bytes()
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(data), 0o644, 0
            tar.addfile(info, io.BytesIO(data))
    out = out_dir / archive_name(module)
    out.write_bytes(lzma.compress(buffer.getvalue(), preset=9 | lzma.PRESET_EXTREME))
    return out


def expected_members(module, cpu=None) -> list[str]:
    """The files an up-to-date archive of ``module`` holds: for CUDA its metadata, a CUBIN per
    shipped arch and the PTX; with ``cpu`` (a Warp CPU device) the metadata and object for it too."""
    block_dim = module.options["block_dim"]  # what a CUDA launch uses
    folder = module.get_module_identifier(block_dim)
    names = [f"{folder}.meta"]
    names += [module._get_compile_output_name(None, output_arch=a, use_ptx=False, block_dim=block_dim) for a in SHIPPED_ARCHS]
    names.append(module._get_compile_output_name(None, output_arch=SHIPPED_PTX_ARCH, use_ptx=True, block_dim=block_dim))
    members = [f"{folder}/{name}" for name in names]
    if cpu is not None:
        cpu_folder, cpu_object = cache_entry(module, cpu)
        members += [f"{cpu_folder}/{cpu_folder}.meta", f"{cpu_folder}/{cpu_object}"]
    return sorted(members)


def stale_archives(modules: list) -> list[tuple[object, str]]:
    """(module, why) for each of ``modules`` whose shipped archive is missing, unreadable or built
    from other sources than the module's present ones (for the running Warp version). On the
    platform whose CPU objects ship, its CPU object must be there too; elsewhere it is not asked."""
    import warp as wp

    cpu = wp.get_device("cpu") if ships_cpu() else None
    stale = []
    for module in modules:
        archive = shipped_dir() / archive_name(module)
        try:
            with tarfile.open(archive, "r:xz") as tar:
                held = sorted(m.name for m in tar.getmembers())
        except FileNotFoundError:
            stale.append((module, "missing"))
            continue
        except (OSError, tarfile.TarError, lzma.LZMAError, EOFError) as e:
            stale.append((module, f"unreadable ({e})"))
            continue
        expected = expected_members(module, cpu)
        if (held != expected) if cpu is not None else not set(expected) <= set(held):
            stale.append((module, "built from other sources (the kernels changed since)"))
    return stale
