"""Start-up: a quiet, lazy import; `info` without Warp; the kernel cache the user names; `warmup`."""

import os
import subprocess
import sys

import pytest
import typer
import warp as wp
from typer.testing import CliRunner

from nanogs_warp.cli.errors import user_errors
from nanogs_warp.cli.warmup import warmup_command
from nanogs_warp.kernel_cache import SIMPLIFY_MODULES, load_kernels, missing_modules, warp_modules

SAMPLE = "nanogs_warp/data/plant_crop.ply"


def python(code: str, *argv: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, env={**os.environ, **env},
                          cwd=__file__.rsplit("/tests/", 1)[0])  # fmt: skip


def test_import_is_quiet_and_loads_no_warp():
    result = python("import nanogs_warp, sys; print('warp' in sys.modules, nanogs_warp.__version__)")
    assert result.returncode == 0 and result.stdout.split() == ["False", "0.1.0"] and result.stderr == ""


def test_the_api_is_quiet_on_a_machine_without_a_gpu():
    """Warp's own "Could not find or load the NVIDIA CUDA driver" notice was printed by the first call."""
    code = ("import nanogs_warp as n\ns = n.load_ply(%r)\nprint(n.simplify(s, ratio=0.1, device='cpu').count)") % SAMPLE
    result = python(code)
    assert result.returncode == 0 and result.stdout.split() == ["2000"] and result.stderr == "", result.stderr


def test_info_imports_neither_warp_nor_pydantic():
    """pydantic: typer 0.29 and later import it to validate options (pyproject.toml pins typer below)."""
    code = ("import sys\nfrom nanogs_warp.cli.app import app\nsys.argv = ['nanogs-warp', 'info', %r]\n"
            "try:\n    app()\nexcept SystemExit:\n    pass\nprint('warp' in sys.modules, 'pydantic' in sys.modules)") % SAMPLE  # fmt: skip
    result = python(code)
    assert result.returncode == 0 and result.stdout.splitlines()[0].split() == ["file", "plant_crop.ply", "(1,360,498", "bytes,", "binary_little_endian)"]
    assert result.stdout.splitlines()[-1] == "False False"


def test_the_cache_variable_is_honoured(tmp_path):
    code = "from nanogs_warp.device import init_warp; init_warp(); import warp; print(warp.config.kernel_cache_dir)"
    result = python(code, NANOGS_WARP_CACHE=str(tmp_path / "kernels"))
    assert result.returncode == 0 and result.stdout.strip().startswith(str(tmp_path / "kernels"))


def test_a_warp_cache_path_that_cannot_hold_the_cache_is_one_line(tmp_path):
    """Warp's own variable naming a file: Warp failed with a traceback (an internal error)."""
    (tmp_path / "afile").write_text("x")
    result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(tmp_path / "o.ply"),
                             "--ratio", "0.5", "--device", "cpu"], capture_output=True, text=True,
                            env={**os.environ, "NANOGS_WARP_CACHE": "", "WARP_CACHE_PATH": str(tmp_path / "afile")})  # fmt: skip
    assert result.returncode == 2 and result.stderr.startswith("nanogs-warp: error: WARP_CACHE_PATH ")
    assert "cannot create the directory" in result.stderr and not (tmp_path / "o.ply").exists()


def test_a_read_only_cache_serves_what_it_holds(tmp_path):
    """A kernel cache baked into a read-only image: refused as 'not writable' even when it held
    every module. It is used now, and one that lacks a module says so in one line."""
    full, empty = tmp_path / "full", tmp_path / "empty"
    empty.mkdir()
    code = ("import os, sys\nfrom nanogs_warp.cli.entry import main\naccess = os.access\n"
            "os.access = lambda p, m, **k: False if (m & os.W_OK and str(p).startswith(os.environ['NANOGS_WARP_CACHE'])) else access(p, m, **k)\n"
            "sys.argv = ['nanogs-warp', 'simplify', '--sample', '-o', sys.argv[1], '--ratio', '0.1', '--device', 'cpu', '-q', '--preset', 'fast']\n"
            "main()")  # fmt: skip
    fill = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(tmp_path / "a.ply"), "--ratio", "0.1",
                           "--device", "cpu", "-q", "--preset", "fast"], capture_output=True, text=True,
                          env={**os.environ, "NANOGS_WARP_CACHE": str(full)})  # fmt: skip
    assert fill.returncode == 0, fill.stderr
    served = python(code, str(tmp_path / "b.ply"), NANOGS_WARP_CACHE=str(full))
    assert served.returncode == 0, served.stderr
    assert (tmp_path / "b.ply").read_bytes() == (tmp_path / "a.ply").read_bytes()
    lacking = python(code, str(tmp_path / "c.ply"), NANOGS_WARP_CACHE=str(empty), NANOGS_WARP_SHIPPED_KERNELS="0")
    assert lacking.returncode == 2 and lacking.stderr.startswith(f"nanogs-warp: error: kernel cache {empty}/")
    assert "is read-only and lacks " in lacking.stderr and len(lacking.stderr.splitlines()) == 1
    assert not (tmp_path / "c.ply").exists()


def test_missing_modules_sees_the_cache(tmp_path):
    cpu = wp.get_device("cpu")
    load_kernels(cpu, announce=False)
    modules = warp_modules(SIMPLIFY_MODULES)
    assert missing_modules(modules, cpu) == []
    saved = wp.config.kernel_cache_dir
    wp.config.kernel_cache_dir = str(tmp_path)
    try:
        assert missing_modules(modules, cpu) == modules
    finally:
        wp.config.kernel_cache_dir = saved


app = typer.Typer(pretty_exceptions_enable=False)
app.callback()(lambda: None)
app.command("warmup")(user_errors(warmup_command))


def test_warmup_loads_every_module_for_the_cpu():
    result = CliRunner().invoke(app, ["warmup", "--device", "cpu", "--arch", "none"])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("cpu: ") and "module(s) compiled" in result.stdout


def test_warmup_does_not_compile_the_shipped_architectures_again(monkeypatch):
    """Their binaries ship with the package: compiling all seven again took minutes on a machine
    without a GPU (the default there). With shipped kernels switched off they are compiled."""
    from nanogs_warp import kernel_cache
    from nanogs_warp.shipped_kernels import SHIPPED_ARCHS, SWITCH_VARIABLE, shipped_archs

    assert shipped_archs() == SHIPPED_ARCHS
    result = CliRunner().invoke(app, ["warmup", "--device", "cpu", "--arch", "75,90"])
    assert result.exit_code == 0, result.output
    assert "sm_75 (shipped with the package): 0 module(s)" in result.stdout
    assert "sm_90 (shipped with the package): 0 module(s)" in result.stdout
    monkeypatch.setenv(SWITCH_VARIABLE, "0")
    assert shipped_archs() == ()
    compiled = []
    monkeypatch.setattr(wp, "compile_aot_module", lambda module, arch, use_ptx: compiled.append((arch, use_ptx)))
    report = kernel_cache.warmup([], [75], names=("prune",))
    assert report[0][:2] == ("sm_75", 2) and sorted(compiled) == [(75, False), (75, True)]


def test_warmup_bad_arguments_exit_2():
    for args, message in ((["--arch", "9x"], "--arch '9x'"), (["--device", "tpu"], "--device 'tpu'")):
        result = CliRunner().invoke(app, ["warmup", *args])
        assert result.exit_code == 2 and result.stderr.startswith(f"nanogs-warp: error: {message}"), result.output


def test_a_damaged_kernel_cache_is_one_line(tmp_path):
    """Compiled modules overwritten with other bytes: Warp cannot load them, or finds no kernel in
    them (plain Exceptions, internal errors); the command says which cache and what to do."""
    import shutil
    from pathlib import Path

    from warp._src.context import _resolve_launch_block_dim

    from nanogs_warp.kernel_cache import simplify_modules

    cpu = wp.get_device("cpu")
    load_kernels(cpu, simplify_modules())  # in the tests' own cache
    copy = tmp_path / "kernels" / wp.config.version
    for module in warp_modules(simplify_modules()):
        folder = Path(wp.config.kernel_cache_dir) / module.get_module_identifier(_resolve_launch_block_dim(cpu, None))
        shutil.copytree(folder, copy / folder.name)
    damaged = list(copy.rglob("*.o"))
    assert damaged
    for path in damaged:
        path.write_bytes(b"\x00" * 4096)
    result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(tmp_path / "o.ply"),
                             "--ratio", "0.5", "--device", "cpu"], capture_output=True, text=True,
                            env={**os.environ, "NANOGS_WARP_CACHE": str(tmp_path / "kernels")})  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert "a compiled kernel module is damaged" in result.stderr and "delete the directory to compile the kernels again" in result.stderr
    assert not (tmp_path / "o.ply").exists()
    # a module's metadata that is not JSON, its binary gone: Warp's JSONDecodeError was an internal error
    for path in damaged:
        path.unlink()
    for path in copy.rglob("*.meta"):
        path.write_text("garbage")
    result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(tmp_path / "o.ply"),
                             "--ratio", "0.5", "--device", "cpu"], capture_output=True, text=True,
                            env={**os.environ, "NANOGS_WARP_CACHE": str(tmp_path / "kernels")})  # fmt: skip
    assert result.returncode == 2 and "its metadata in the cache is not JSON" in result.stderr, result.stderr
    assert not (tmp_path / "o.ply").exists()


def test_a_gpu_that_stopped_is_not_called_a_damaged_cache(monkeypatch):
    """After a CUDA error that a GPU's context keeps (an illegal memory access), every later kernel
    lookup fails with the damaged-cache message's words: the command names the GPU's error as an
    internal error (exit 1) instead of advising to delete the cache."""
    import types

    import warp._src.context as warp_context

    device = type("FakeDevice", (), {"has_context": True, "context": 1, "__str__": lambda self: "cuda:0"})()
    core = types.SimpleNamespace(wp_cuda_context_check=lambda context: 700)
    fake = types.SimpleNamespace(cuda_devices=[device], core=core, get_error_string=lambda: "an illegal memory access was encountered")
    monkeypatch.setattr(warp_context, "runtime", fake)

    app = typer.Typer()

    @app.command()
    @user_errors
    def lookup() -> None:
        raise Exception("Failed to find forward kernel 'gather_entries' from module 'nanogs_warp.kernels.render' for device 'cuda:0'")

    result = CliRunner().invoke(app, [])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert lines == ["nanogs-warp: error: internal error: the GPU stopped: cuda:0: CUDA error 700 (an illegal memory access was "
                     "encountered) (set NANOGS_DEBUG=1 for details)"], lines  # fmt: skip


@pytest.mark.skipif(wp.get_cuda_device_count() == 0, reason="needs a CUDA GPU")
def test_gpu_fault_reads_a_real_illegal_address_on_cuda(tmp_path):
    """A kernel that writes to address 16 stops the GPU's context (in a process of its own, whose
    context it spoils): ``gpu_fault`` names the error; a fresh process has none."""
    probe = (
        "import warp as wp\n"
        "wp.config.quiet = True\n"
        "from nanogs_warp.device import gpu_fault\n"
        "wp.init()\n"
        "print('before', gpu_fault())\n"
        "@wp.kernel\n"
        "def poke(a: wp.array(dtype=float)):\n"
        "    a[0] = 1.0\n"
        "bad = wp.array(ptr=16, shape=(1,), dtype=float, device='cuda:0')\n"
        "try:\n"
        "    wp.launch(poke, 1, inputs=[bad], device='cuda:0')\n"
        "    wp.synchronize_device('cuda:0')\n"
        "except Exception:\n"
        "    pass\n"
        "print('after', gpu_fault())\n"
    )
    script = tmp_path / "probe.py"  # a file: Warp reads a kernel's source
    script.write_text(probe)
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert "before None" in result.stdout, result.stdout + result.stderr
    assert "after cuda:0: CUDA error" in result.stdout, result.stdout + result.stderr


def test_a_cache_folder_whose_name_is_not_utf8_is_one_line():
    """Warp hands the name to its native code as UTF-8: an undecodable byte was an internal error."""
    from nanogs_warp.errors import InputError
    from nanogs_warp.kernel_cache import use_cache_dir

    with pytest.raises(InputError, match=r"the name is not UTF-8, which Warp needs"):
        use_cache_dir(os.fsdecode(b"/tmp/nanogs-cache-\xff"))
