"""The CUDA build of every kernel module compiles, on machines without a GPU too (bundled NVRTC),
for the paper's RTX 4090 (sm_89) and Hopper (sm_90)."""

import importlib
import pkgutil

import pytest
import warp as wp

import nanogs_warp.kernels

KERNEL_MODULES = sorted(m.name for m in pkgutil.iter_modules(nanogs_warp.kernels.__path__))


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
