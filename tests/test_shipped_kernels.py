"""The kernels shipped compiled in the package: they match the kernels' sources (else
`python tools/build_kernels.py` must be run again), they land in an empty kernel cache as the files
Warp would have compiled and give the same outputs, and a damaged or missing archive only means
compiling as before."""

import io
import lzma
import os
import subprocess
import sys
import tarfile
import types

import pytest
import warp as wp

from nanogs_warp.kernel_cache import ALL_MODULES, SIMPLIFY_MODULES, missing_modules, warp_modules
from nanogs_warp.shipped_kernels import (
    SHIPPED_ARCHS,
    SHIPPED_PTX_ARCH,
    archive_name,
    install_shipped,
    shipped_dir,
    ships_cpu,
    stale_archives,
)

SHIPPED = shipped_dir().is_dir()
needs_shipped = pytest.mark.skipif(not SHIPPED, reason=f"no kernels are shipped for Warp {wp.config.version} (tools/build_kernels.py)")


def fake_gpu(arch: int, output: str):
    """A stand-in for a CUDA device of compute capability ``arch`` for which Warp loads ``output``
    ("cubin", or "ptx" as with a driver newer than Warp's toolkit): the questions Warp asks a
    device to name the binary it loads."""
    compile_arch = min(arch, SHIPPED_PTX_ARCH) if output == "ptx" else arch
    return types.SimpleNamespace(is_cpu=False, arch=arch, get_cuda_output_format=lambda preferred=None: output,
                                 get_cuda_compile_arch=lambda: compile_arch, _get_cuda_arch_suffix=lambda a: "")  # fmt: skip


def archive_files(module) -> dict[str, bytes]:
    with tarfile.open(shipped_dir() / archive_name(module), "r:xz") as tar:
        return {m.name: tar.extractfile(m).read() for m in tar.getmembers()}


@needs_shipped
def test_shipped_archives_match_the_kernels_sources():
    stale = stale_archives(warp_modules(ALL_MODULES))
    assert not stale, "run `python tools/build_kernels.py` and commit its archives: " + ", ".join(
        f"{archive_name(m)} {why}" for m, why in stale)


@needs_shipped
@pytest.mark.parametrize("arch, output", [(90, "cubin"), (86, "cubin"), (120, "cubin"), (90, "ptx"), (100, "ptx")])
def test_shipped_binaries_fill_an_empty_cache(tmp_path, arch, output):
    modules = warp_modules(SIMPLIFY_MODULES)
    gpu = fake_gpu(arch, output)
    saved = wp.config.kernel_cache_dir
    wp.config.kernel_cache_dir = str(tmp_path)
    try:
        assert missing_modules(modules, gpu) == modules
        assert install_shipped(modules, gpu) == modules
        assert missing_modules(modules, gpu) == []
    finally:
        wp.config.kernel_cache_dir = saved
    suffix = f".sm{SHIPPED_PTX_ARCH}.ptx" if output == "ptx" else f".sm{arch}.cubin"
    for module in modules:
        shipped = archive_files(module)
        folder = module.get_module_identifier(module.options["block_dim"])  # the CUDA binaries' folder
        written = {f"{folder}/{p.name}": p.read_bytes() for p in (tmp_path / folder).iterdir()}
        assert sorted(written) == sorted(n for n in shipped if n.startswith(folder + "/") and n.endswith((".meta", suffix)))
        assert all(written[n] == shipped[n] for n in written)
    assert not list(tmp_path.rglob("*.part"))


@needs_shipped
def test_an_architecture_not_shipped_is_left_to_compile(tmp_path):
    modules = warp_modules(SIMPLIFY_MODULES)
    assert 61 not in SHIPPED_ARCHS
    assert install_shipped(modules, fake_gpu(61, "cubin"), root=tmp_path) == []
    assert list(tmp_path.iterdir()) == []


@needs_shipped
def test_a_damaged_archive_is_left_to_compile(tmp_path, monkeypatch):
    """Archives cut short, of other bytes, or holding other files: no error, nothing written."""
    import nanogs_warp.shipped_kernels as shipped

    module = warp_modules(("knn",))[0]
    good = (shipped_dir() / archive_name(module)).read_bytes()
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        info = tarfile.TarInfo("other/other.meta")
        info.size = 2
        tar.addfile(info, io.BytesIO(b"{}"))
    copies = tmp_path / "archives"
    cache = tmp_path / "cache"
    for damaged in (good[: len(good) // 2], b"\x00" * 1000, lzma.compress(buffer.getvalue()), b""):
        copies.mkdir(exist_ok=True)
        (copies / archive_name(module)).write_bytes(damaged)
        monkeypatch.setattr(shipped, "shipped_dir", lambda version=None: copies)
        assert install_shipped([module], fake_gpu(90, "cubin"), root=cache) == []
    assert not cache.exists() or list(cache.rglob("*.cubin")) == []


@pytest.mark.skipif(not SHIPPED or not ships_cpu(), reason="the CPU objects ship for Linux x86-64 only")
def test_a_fresh_cache_compiles_nothing_on_the_cpu(tmp_path):
    """Linux x86-64, an empty kernel cache: the CPU objects come from the package (no compile
    notice), and the output is the same bytes as with the kernels compiled here."""
    modules = warp_modules(SIMPLIFY_MODULES)
    cpu = wp.get_device("cpu")
    assert install_shipped(modules, cpu, root=tmp_path / "direct") == modules
    outputs = []
    for cache, shipped in (("fresh", "1"), ("compiled", "0")):
        out = tmp_path / f"out{len(outputs)}.ply"
        result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(out), "--ratio", "0.3",
                                 "--no-fit-size", "--device", "cpu"], capture_output=True, text=True,
                                env={**os.environ, "NANOGS_WARP_CACHE": str(tmp_path / cache), "NANOGS_WARP_SHIPPED_KERNELS": shipped})  # fmt: skip
        assert result.returncode == 0, result.stderr
        assert ("compiling" in result.stderr) == (shipped == "0"), result.stderr
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]


@pytest.mark.skipif(not SHIPPED or not ships_cpu(), reason="the CPU objects ship for Linux x86-64 only")
def test_the_python_api_compiles_nothing_on_a_fresh_cache(tmp_path):
    """A program that imports the package (no command, so no ``load_kernels``) on an empty kernel
    cache: ``simplify`` with every fit (1 %: size, colour and geometry) loads the shipped CPU
    objects. Warp leaves the C++ it compiled beside each binary it builds; none may appear."""
    cache = tmp_path / "fresh"
    program = (
        "import nanogs_warp as ng\n"
        "from nanogs_warp.data import sample_path\n"
        "out = ng.simplify(ng.load_ply(sample_path()), ratio=0.01, device='cpu')\n"
        "print(out.count)\n"
    )
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                            env={**os.environ, "NANOGS_WARP_CACHE": str(cache), "NANOGS_WARP_SHIPPED_KERNELS": "1"})  # fmt: skip
    assert result.returncode == 0, result.stderr
    loaded = {p.parent.name.rsplit("_", 1)[0] for p in cache.rglob("*.o")}
    assert {"wp_nanogs_warp.kernels.knn", "wp_nanogs_warp.kernels.render", "wp_nanogs_warp.kernels.render_grad"} <= loaded, loaded
    assert sorted(p.name for p in cache.rglob("*.cpp")) == []


@pytest.mark.skipif(not SHIPPED or not ships_cpu(), reason="the CPU objects ship for Linux x86-64 only")
def test_batch_compiles_nothing_on_a_fresh_cache(tmp_path):
    """``batch`` on an empty kernel cache, to a budget every fit runs at: its worker loads the
    shipped CPU objects of the fits' modules too (they were compiled in the first scene before)."""
    from nanogs_warp.data import sample_path

    scenes = tmp_path / "in"
    scenes.mkdir()
    (scenes / "a.ply").write_bytes(sample_path().read_bytes())
    cache = tmp_path / "fresh"
    result = subprocess.run([sys.executable, "-m", "nanogs_warp", "batch", str(scenes), "-o", str(tmp_path / "out"), "--ratio", "0.01",
                             "--devices", "cpu", "-q"], capture_output=True, text=True,
                            env={**os.environ, "NANOGS_WARP_CACHE": str(cache), "NANOGS_WARP_SHIPPED_KERNELS": "1"})  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "compiling" not in result.stderr, result.stderr
    assert sorted(p.name for p in cache.rglob("*.cpp")) == []


def test_the_switch_turns_shipped_kernels_off(tmp_path, monkeypatch):
    modules = warp_modules(("knn",))
    monkeypatch.setenv("NANOGS_WARP_SHIPPED_KERNELS", "0")
    assert install_shipped(modules, fake_gpu(90, "cubin"), root=tmp_path) == []
    monkeypatch.setenv("NANOGS_WARP_SHIPPED_KERNELS", "1")
    assert install_shipped(modules, fake_gpu(90, "cubin"), root=tmp_path) == (modules if SHIPPED else [])


@pytest.mark.skipif(wp.get_cuda_device_count() == 0 or not SHIPPED, reason="needs a CUDA GPU and shipped kernels")
def test_a_fresh_cache_compiles_nothing_on_cuda(tmp_path):
    """An empty kernel cache on a GPU: the command loads the shipped binaries (no compile notice),
    twice, and writes the same bytes as with the kernels compiled here (the size fit's renderer
    included)."""
    outputs = []
    for cache, shipped in (("fresh", "1"), ("fresh", "1"), ("compiled", "0")):
        out = tmp_path / f"out{len(outputs)}.ply"
        result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(out), "--ratio", "0.01",
                                 "--device", "cuda:0"], capture_output=True, text=True,
                                env={**os.environ, "NANOGS_WARP_CACHE": str(tmp_path / cache), "NANOGS_WARP_SHIPPED_KERNELS": shipped})  # fmt: skip
        assert result.returncode == 0, result.stderr
        assert ("compiling" in result.stderr) == (shipped == "0"), result.stderr
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]


def test_a_device_warp_cannot_name_a_binary_for_is_left_to_warp(tmp_path):
    """A GPU older than Warp's toolkit supports (Warp raises when asked which binary it loads):
    nothing installed, no error here (Warp reports it when the command starts the device)."""
    def refuse():
        raise RuntimeError("CUDA 13.4 requires sm_75 or higher, but sm_70 was specified")

    old = types.SimpleNamespace(is_cpu=False, arch=70, get_cuda_output_format=lambda preferred=None: "cubin",
                                get_cuda_compile_arch=refuse, _get_cuda_arch_suffix=lambda a: "")  # fmt: skip
    assert install_shipped(warp_modules(("knn",)), old, root=tmp_path) == []
    assert list(tmp_path.iterdir()) == []


@needs_shipped
def test_a_cache_that_cannot_take_the_binaries_is_left_to_warp(tmp_path):
    """The cache's folder for the module is a file (as on a full or read-only disk, writing fails):
    nothing installed, no error here."""
    module = warp_modules(("knn",))[0]
    gpu = fake_gpu(90, "cubin")
    folder = module.get_module_identifier(module.options["block_dim"])
    (tmp_path / folder).write_text("not a folder")
    assert install_shipped([module], gpu, root=tmp_path) == []
