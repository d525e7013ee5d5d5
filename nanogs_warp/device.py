"""Warp start-up and the user's choice of device (Warp is imported only by the functions that need it)."""

from __future__ import annotations

import ctypes
import os
import sys
import tempfile
import threading
import time

from .errors import InputError, debugging

# Warp's native library prints these when a machine has no NVIDIA driver, or a driver and no GPU it
# may use (a container without one, CUDA_VISIBLE_DEVICES empty: "CUDA error 100"); there "no GPU" is
# the expected state, and --device cuda reports it as an error of its own.
_NO_GPU_NOTICES = ("Could not find or load the NVIDIA CUDA driver", "no CUDA-capable device is detected")


def available_host_memory() -> int | None:
    """Bytes of host memory available now (Linux's MemAvailable, page cache included as the kernel
    counts it; elsewhere the free pages), or None where the system does not say."""
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def device_memory(device) -> int | None:
    """Bytes of ``device``'s memory free now: a GPU's, or for the CPU the host's available memory
    (page cache included as the kernel counts it); None where the system does not say."""
    import warp as wp

    device = wp.get_device(device)
    return int(device.free_memory) if device.is_cuda else available_host_memory()


def memory_short(need: int, device=None) -> int | None:
    """The memory available now (the host's, or with ``device`` that device's: ``device_memory``)
    where ``need`` bytes are more than it (the caller refuses the work in one line, naming both);
    None where they fit, or where the system does not say."""
    available = available_host_memory() if device is None else device_memory(device)
    return available if available is not None and need > available else None


def quiet_warp() -> None:
    """Warp's start-up banner and module-load lines off (on with NANOGS_DEBUG=1), and the kernel
    cache at $NANOGS_WARP_CACHE when that is set and no directory was chosen before."""
    import warp as wp

    from .kernel_cache import cache_dir_from_environment, use_cache_dir

    wp.config.log_level = wp.LOG_INFO if debugging() else wp.LOG_WARNING
    if wp.config.kernel_cache_dir is None:
        use_cache_dir(cache_dir_from_environment())


_start_lock = threading.Lock()
_started: list[bool] = []  # [True] once Warp has been started (or found started) in this process


def init_warp() -> None:
    """Initialises Warp once a process, quietly (NANOGS_DEBUG=1: with Warp's own messages): the
    expected notices that no GPU is there are dropped, anything else Warp's native code prints is
    passed on to stderr (``start_up_messages``). The kernel cache is $NANOGS_WARP_CACHE when set and
    no directory was chosen before. A Warp the program started itself is left as it is (its log
    level, its kernel cache). Safe from several threads at once: stderr (file descriptor 2) is
    captured only while the first of them starts Warp, and never touched again; every call did so
    before, and two threads at once could leave the process's stderr on a deleted file."""
    if _started:
        return
    with _start_lock:
        if _started:
            return
        if not _warp_started_by_the_program():
            _start_quietly()
        _started.append(True)


_device_locks: dict[str, threading.RLock] = {}


def device_lock(device) -> threading.RLock:
    """The lock that the package's calls on ``device`` (a Warp device) hold while they work there:
    calls of a program's threads on one device run one at a time (several threads' simplifications
    at once on one GPU met illegal memory accesses, and a call keeps a device busy by itself);
    calls on different devices run at once. Re-entrant: a call may make others on its device."""
    return _device_locks.setdefault(str(device), threading.RLock())  # one lock a device: setdefault is atomic


def _warp_started_by_the_program() -> bool:
    try:
        from warp._src.context import runtime
    except ImportError:  # another Warp layout: started here as before (wp.init is idempotent)
        return False
    return runtime is not None


def _start_quietly() -> None:
    import warp as wp

    quiet_warp()
    if sys.stderr is not None:
        sys.stderr.flush()
    try:
        captured_file = tempfile.TemporaryFile(mode="w+b")
    except OSError:  # no temporary folder can be written (a read-only /tmp): Warp starts uncaptured
        wp.init()
        return
    saved = os.dup(2)
    with captured_file as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        for line in start_up_messages(captured.read().decode(errors="replace")):
            if sys.stderr is not None:
                print(line, file=sys.stderr)


def start_up_messages(output: str) -> list[str]:
    """The lines of what Warp's native code printed while starting that a user should see: all but
    the blank ones and the notices that no GPU is there (``_NO_GPU_NOTICES``)."""
    return [line for line in output.splitlines() if line.strip() and not any(notice in line for notice in _NO_GPU_NOTICES)]


def keep_freed_host_memory() -> bool:
    """Has glibc's malloc keep freed memory for reuse instead of handing it back to the system.

    Every pass frees tens of MB of scratch and allocates it again; by default malloc maps blocks
    above a few MB afresh each time, and the system zeroes every new page (page faults: about a
    tenth of a CPU run). The commands call this once for their own process. Returns whether the
    setting took (False off glibc)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, 1 << 30)) and bool(mallopt(m_trim_threshold, (1 << 31) - 1))


def gpu_fault() -> str | None:
    """The CUDA error a GPU's context holds, in words ("cuda:0: CUDA error 700 (...)"), or None.
    After such an error (an illegal memory access, say) every later launch and kernel lookup on
    that GPU fails, which must not read as a damaged kernel cache. Only GPUs whose context Warp has
    made are asked; nothing is started for the question."""
    if "warp" not in sys.modules:
        return None
    try:
        from warp._src.context import runtime
    except ImportError:
        return None
    if runtime is None:
        return None
    try:  # asked while another error is reported: the question itself must not fail
        for device in getattr(runtime, "cuda_devices", ()):
            if device.has_context:
                code = runtime.core.wp_cuda_context_check(device.context)
                if code:
                    return f"{device}: CUDA error {code} ({runtime.get_error_string()})"
    except Exception:  # noqa: BLE001
        return None
    return None


def resolve_device(name: str):
    """``auto`` (the first GPU, else the CPU), ``cpu``, ``cuda`` or ``cuda:N`` -> a Warp device."""
    import warp as wp

    init_warp()
    name = name.strip().lower()
    gpus = wp.get_cuda_device_count()
    if name == "auto":
        return wp.get_device("cuda:0" if gpus > 0 else "cpu")
    if name == "cpu":
        return wp.get_device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if gpus == 0:
            raise InputError(f"--device {name}: no CUDA GPU is available on this machine")
        ordinal = 0 if name == "cuda" else name.split(":", 1)[1]
        if not str(ordinal).isdigit() or int(ordinal) >= gpus:
            raise InputError(f"--device {name}: this machine has {gpus} CUDA GPU(s), cuda:0 to cuda:{gpus - 1}")
        return wp.get_device(f"cuda:{int(ordinal)}")
    raise InputError(f"--device {name!r}: expected auto, cpu, cuda or cuda:N")


class WarpStart:
    """Initialises Warp and resolves ``--device`` on a background thread, then loads the kernel
    ``modules`` there (see :func:`~nanogs_warp.kernel_cache.load_kernels`), so that a command can
    read its input meanwhile. Import Warp and the kernel definitions before: that is Python work,
    which the read would slow and be slowed by; the device's start and the binaries' load run mostly
    outside the interpreter. ``device()`` waits and returns the device, or raises what the thread
    raised; call ``wait()`` before reporting an error of your own (the thread briefly redirects
    stderr while Warp starts). ``stages`` holds the seconds of ``warp_init`` and ``kernels`` once
    done."""

    def __init__(self, name: str, modules: tuple[str, ...] = (), announce: bool = True):
        self._device = None
        self._resolved_device = None
        self._resolved = threading.Event()
        self._error: BaseException | None = None
        self.stages: dict[str, float] = {}
        self._thread = threading.Thread(target=self._run, args=(name, modules, announce), name="nanogs-warp-start", daemon=True)
        self._thread.start()

    def _run(self, name: str, modules, announce: bool) -> None:
        try:
            begun = time.perf_counter()
            try:
                device = self._resolved_device = resolve_device(name)
            finally:
                self._resolved.set()
            ready = time.perf_counter()
            if modules:
                from .kernel_cache import load_kernels

                load_kernels(device, modules, announce=announce)
            self.stages.update(warp_init=ready - begun, kernels=time.perf_counter() - ready)
            self._device = device
        except BaseException as e:  # noqa: BLE001 - handed to the caller by device()
            self._error = e

    def wait(self) -> None:
        self._thread.join()

    def resolved_device(self):
        """The device once Warp has started, before the kernels are loaded (None if that failed;
        ``device()`` then raises the error)."""
        self._resolved.wait()
        return self._resolved_device

    def device(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._device


def process_age() -> float | None:
    """Seconds since this process started (Linux; None elsewhere), to 10 ms: what the interpreter
    and the imports took before a command's own clock starts."""
    try:
        with open("/proc/self/stat", "rb") as f:
            start_ticks = int(f.read().rsplit(b")", 1)[1].split()[19])
        with open("/proc/uptime", "rb") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None
