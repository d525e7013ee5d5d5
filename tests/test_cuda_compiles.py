"""The CUDA build of every kernel module compiles, on machines without a GPU too (bundled NVRTC),
for the paper's RTX 4090 (sm_89) and Hopper (sm_90); and the pipeline's modules compile to the
same arithmetic as the CPU's: no fused multiply-add, no approximate or library math."""

import importlib
import pkgutil
import re

import pytest
import warp as wp

import nanogs_warp.kernels
from nanogs_warp.kernel_cache import ALL_MODULES

KERNEL_MODULES = sorted(m.name for m in pkgutil.iter_modules(nanogs_warp.kernels.__path__))
# Kernel files whose results must be the same bits on every device: every one (the simplification
# pipeline, the renderer of the size fit, eval and refinement, refinement's backward, loss and
# optimiser), and the files of device functions that they compile in.
PORTABLE_MODULES = sorted(set(ALL_MODULES + ("splat_math", "field", "portable_math")))


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_compiles_for_cuda(name, tmp_path):
    module = importlib.import_module(f"nanogs_warp.kernels.{name}")
    if not any(isinstance(v, wp.Kernel) for v in vars(module).values()):
        pytest.skip(f"{name} defines functions only; they compile inside the modules that use them")
    kernels = [k.key for k in vars(module).values() if isinstance(k, wp.Kernel)]
    outputs = sorted(wp.compile_aot_module(module, arch=[89, 90], use_ptx=True, module_dir=tmp_path))
    assert len(outputs) == 2
    for path, arch in zip(outputs, (89, 90)):
        ptx = path.read_text()
        assert f".target sm_{arch}" in ptx
        assert all(name in ptx for name in kernels)
        if name in PORTABLE_MODULES:
            check_portable_ptx(ptx)


def check_portable_ptx(ptx: str) -> None:
    """Every floating-point instruction of the PTX is one that IEEE 754 rounds correctly and that
    ptxas may not change: add, sub, mul, div, sqrt and rcp in round-to-nearest (``.rn``: never
    contracted), comparisons, min/max, abs, neg and conversions. No ``fma`` (neither a contraction,
    which NVRTC makes unless ``--fmad=false``, nor one from libdevice's exp/log/pow/sin/cos, nor from
    Warp's matrix product) and no ``.approx`` or ``.ftz`` instruction."""
    instructions = re.findall(r"^\s*(?:@!?%p\d+\s+)?([a-z][a-z0-9_]*(?:\.[a-z0-9_]+)*)", ptx, re.M)
    assert "ret" in instructions, "no instruction found: the PTX parse is wrong"
    floating = [op for op in instructions if re.search(r"\.f(16|32|64)\b", op)]
    bad = set()
    for op in floating:
        base = op.split(".")[0]
        if base in ("fma", "mad") or ".approx" in op or ".ftz" in op or ".full" in op:
            bad.add(op)
        elif base in ("add", "sub", "mul", "div", "sqrt", "rcp") and "rn" not in op.split("."):
            bad.add(op)
        elif base in ("ex2", "lg2", "sin", "cos", "tanh", "rsqrt"):
            bad.add(op)
    assert not bad, f"instructions that round differently from the CPU build: {sorted(bad)}"


@pytest.mark.parametrize("name", PORTABLE_MODULES)
def test_pipeline_modules_do_not_fuse_multiply_adds(name):
    """fuse_fp off: LLVM's strict FP-op fusion on the CPU (no contraction into FMA with
    -march=native), NVRTC's --fmad=false on CUDA."""
    importlib.import_module(f"nanogs_warp.kernels.{name}")
    assert wp.get_module(f"nanogs_warp.kernels.{name}").options["fuse_fp"] is False


@wp.kernel
def _contractible(a: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    # this test file's module keeps Warp's default fuse_fp (on): NVRTC fuses the multiply-add
    out[0] = a[0] * a[1] + a[2]


def test_ptx_check_finds_contraction(tmp_path):
    """The PTX check fails on what it is there to catch: a multiply-add built with fuse_fp on."""
    import sys

    this = sys.modules[__name__]
    assert wp.get_module(this.__name__).options["fuse_fp"] is True
    (path,) = wp.compile_aot_module(this, arch=[90], use_ptx=True, module_dir=tmp_path)
    with pytest.raises(AssertionError, match="fma"):
        check_portable_ptx(path.read_text())
