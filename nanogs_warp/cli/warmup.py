"""``nanogs-warp warmup``: compile every kernel ahead of time into Warp's kernel cache (or a given
directory), so that no command compiles on first use, e.g. while a farm's container image is built.

Registered in ``app.py`` as ``app.command("warmup")(user_errors(warmup_command))``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import InputError


def warmup_command(
    device: Annotated[str, typer.Option("--device", help="Devices to compile for: auto (the CPU and every GPU), cpu, cuda (every GPU), cuda:N, or a list such as cpu,cuda:0.", metavar="DEVICE")] = "auto",
    arch: Annotated[Optional[str], typer.Option("--arch", help="Also compile for these CUDA architectures, with or without such a GPU, e.g. 75,80,86,89,90,100,120 (Turing to Blackwell), or none. Architectures whose binaries ship with the package (75,80,86,89,90,100,120 for this Warp) are not compiled again. [default: none with a GPU present; the shipped list on a machine without one]", show_default=False, metavar="ARCH")] = None,
    cache_dir: Annotated[Optional[str], typer.Option("--cache-dir", metavar="DIRECTORY", help="The kernel cache to fill. Commands use it when NANOGS_WARP_CACHE (or Warp's WARP_CACHE_PATH) names it. [default: NANOGS_WARP_CACHE, else Warp's cache]", show_default=False)] = None,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="Print nothing but errors.")] = False,
) -> None:
    """Compile every kernel for this machine's devices (and other GPU architectures) into the
    kernel cache, so that later commands only load them."""
    from ..device import init_warp
    from ..kernel_cache import DEFAULT_ARCHS, cache_dir_from_environment, use_cache_dir, warmup

    archs = _parse_archs(arch)
    if cache_dir is not None and not cache_dir.strip():
        raise InputError("--cache-dir: give a directory")
    use_cache_dir(Path(cache_dir) if cache_dir is not None else cache_dir_from_environment(), must_write=True)
    init_warp()
    import warp as wp

    devices = _parse_devices(device, wp)
    from warp._src.context import runtime

    supported = getattr(runtime, "nvrtc_supported_archs", None)
    unknown = [a for a in archs or () if supported and a not in supported]
    if unknown:  # NVRTC would fail on each module, leaving its staging folders in the cache
        raise InputError(f"--arch {arch}: this Warp's NVRTC compiles for {','.join(map(str, sorted(supported)))}, "
                         f"not {','.join(map(str, unknown))}")  # fmt: skip
    if archs is None:
        archs = [] if wp.get_cuda_device_count() > 0 else list(DEFAULT_ARCHS)
    if not quiet:
        typer.echo(f"nanogs-warp warmup: compiling into {wp.config.kernel_cache_dir}", err=True)
    for target, modules, seconds in warmup(devices, archs):
        if not quiet:
            typer.echo(f"{target}: {modules} module(s) compiled in {seconds:.1f} s")


def _parse_archs(text: str | None) -> list[int] | None:
    if text is None:
        return None
    if text.strip().lower() == "none":
        return []
    archs = []
    for part in (p.strip().lower().removeprefix("sm_") for p in text.split(",")):
        if not part.isdigit() or not 50 <= int(part) <= 200:
            raise InputError(f"--arch {text!r}: expected compute capabilities such as 75,80,86,89,90")
        archs.append(int(part))
    return list(dict.fromkeys(archs))  # each once


def _parse_devices(text: str, wp) -> list:
    gpus = wp.get_cuda_device_count()
    devices = []
    for name in (t.strip().lower() for t in text.split(",") if t.strip()):
        if name == "auto":
            devices += ["cpu"] + [f"cuda:{i}" for i in range(gpus)]
        elif name == "cpu":
            devices.append("cpu")
        elif name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit()):
            if gpus == 0:
                raise InputError(f"--device {name}: no CUDA GPU is available on this machine (use --arch to compile for GPUs)")
            ordinals = range(gpus) if name == "cuda" else [int(name[5:])]
            if max(ordinals) >= gpus:
                raise InputError(f"--device {name}: this machine has {gpus} CUDA GPU(s)")
            devices += [f"cuda:{i}" for i in ordinals]
        else:
            raise InputError(f"--device {text!r}: expected auto, cpu, cuda, cuda:N or a list of them")
    if not devices:
        raise InputError("--device is empty")
    return [wp.get_device(d) for d in dict.fromkeys(devices)]
