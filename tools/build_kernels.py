"""Compiles the package's kernels ahead of time into ``nanogs_warp/compiled/warp-<version>/``, the
archives that ship in the package (see ``nanogs_warp/shipped_kernels.py``). Needs no GPU: Warp's
bundled NVRTC compiles for every GPU architecture, and its bundled Clang the CPU objects (run it on
Linux x86-64, the platform whose CPU objects ship). Run it after changing a kernel (the test suite
says when the shipped archives no longer match the sources) and commit the archives it writes:

    python tools/build_kernels.py            # 1-2 minutes on two cores
    python tools/build_kernels.py --check    # only say whether the shipped archives are current
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="report stale or missing archives; write nothing")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="compilations at once")
    args = parser.parse_args()

    scratch = tempfile.TemporaryDirectory(prefix="nanogs-kernels-")
    import warp as wp

    wp.config.kernel_cache_dir = scratch.name
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    from nanogs_warp.kernel_cache import ALL_MODULES, warp_modules
    from nanogs_warp.shipped_kernels import CPU_PLATFORM, SHIPPED_ARCHS, SHIPPED_PTX_ARCH, archive_name, pack, shipped_dir, ships_cpu, stale_archives

    modules = warp_modules(ALL_MODULES)
    out_dir = shipped_dir()
    if args.check:
        stale = stale_archives(modules)
        for module, why in stale:
            print(f"{archive_name(module)}: {why}")
        print(f"{len(modules) - len(stale)} of {len(modules)} archives current in {out_dir}")
        return 1 if stale else 0

    if not ships_cpu():
        print(f"the CPU objects that ship are built on {' '.join(CPU_PLATFORM)}; this machine is not one", file=sys.stderr)
        return 2
    cpu = wp.get_device("cpu")
    started = time.perf_counter()
    jobs = [(m, a, False) for m in modules for a in SHIPPED_ARCHS] + [(m, SHIPPED_PTX_ARCH, True) for m in modules]
    jobs += [(m, None, None) for m in modules]  # the CPU objects

    def compile_one(job) -> None:
        module, arch, ptx = job
        if arch is None:  # as a CPU launch loads it (one thread a block; compile_aot_module would use 256)
            wp.force_load(device=cpu, modules=[module])
        else:
            wp.compile_aot_module(module, arch=arch, use_ptx=ptx)

    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(compile_one, jobs))
    compiled = time.perf_counter() - started

    out_dir.mkdir(parents=True, exist_ok=True)
    cache_root = Path(wp.config.kernel_cache_dir)
    written = {pack(m, cache_root, out_dir, cpu).name for m in modules}
    for old in out_dir.glob("*.tar.xz"):  # kernel files that no longer exist
        if old.name not in written:
            old.unlink()
    for other in out_dir.parent.glob("warp-*"):  # archives for another Warp version are never loaded
        if other != out_dir:
            for path in other.iterdir():
                path.unlink()
            other.rmdir()
    size = sum((out_dir / name).stat().st_size for name in written)
    print(f"{len(jobs)} binaries ({len(modules)} modules, sm_{'/'.join(map(str, SHIPPED_ARCHS))} CUBIN, "
          f"sm_{SHIPPED_PTX_ARCH} PTX, {' '.join(CPU_PLATFORM)} CPU) compiled in {compiled:.1f} s; {len(written)} archives, {size / 1e6:.2f} MB, in {out_dir}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
