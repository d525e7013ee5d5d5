"""The batch on this machine: worker processes per device (``spawn``; each initialises Warp and
sees only its own GPU; by default two on a GPU with the memory for them, six under CUDA MPS,
one elsewhere: ``gpu_workers``, ``mps``). The parent holds the queue, largest scene first, and keeps two scenes
assigned to each worker, so that a worker reads and parses the next scene while the current one
is on its device, and writes the outputs of the last one in the background. Each worker talks to
the parent over its own pipe, so a worker killed at any moment (the out-of-memory killer) cannot
block the others. The parent sees a worker die at once (its process sentinel), fails the scene it
was working on, hands back the others and starts another worker in its place. The scene a worker
is working on (the oldest it holds) has a time limit; past it, the parent kills the worker (the
only way to stop a GPU kernel that does not end), fails that scene and goes on."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from multiprocessing.connection import wait

from ..errors import InputError
from ..temporaries import remove_stale_temporaries
from .gpu_workers import auto_workers
from .scenes import SceneJob, largest_first, scene_timeout, timed_out_error
from .work import SceneResult

_PASS_EVENT_EVERY_S = 0.25
_MAX_RESTARTS = 3  # per device: a worker that keeps dying is not started again
_SCENES_PER_WORKER = 2  # the one it works on and the one it reads meanwhile
_MAX_HANDBACKS = 2  # a scene handed back more often than this (its workers kept dying) fails


def parse_devices(text: str) -> list[str]:
    """``auto`` (every GPU, else the CPU), ``all`` (every GPU), ``cpu``, ``cuda:0,cuda:1``, or
    ``all,cpu`` / ``auto,cpu`` (every GPU and the CPU) -> device names, checked against this machine."""
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    if names == ["cpu"]:
        return ["cpu"]
    from ..device import init_warp

    import warp as wp

    init_warp()
    gpus = wp.get_cuda_device_count()
    every_gpu = [f"cuda:{i}" for i in range(gpus)]
    if names == ["auto"]:
        return every_gpu or ["cpu"]
    if names in (["all"], ["all", "cpu"], ["cpu", "all"]):
        if gpus == 0:
            raise InputError(f"--devices {text}: no CUDA GPU is available on this machine")
        return every_gpu + (["cpu"] if "cpu" in names else [])
    if names in (["auto", "cpu"], ["cpu", "auto"]):
        return every_gpu + ["cpu"]
    devices = []
    for name in names:
        if name == "cuda":
            name = "cuda:0"
        ordinal = name.split(":", 1)[1] if name.startswith("cuda:") else None
        if name != "cpu" and not (ordinal and ordinal.isdigit()):
            raise InputError(f"--devices {text!r}: expected auto, all, cpu, all,cpu or a list like cuda:0,cuda:1")
        if ordinal is not None and int(ordinal) >= gpus:
            raise InputError(f"--devices {name}: this machine has {gpus} CUDA GPU(s)")
        if name in devices:
            raise InputError(f"--devices {text!r}: {name} is given twice")
        devices.append(name)
    if not devices:
        raise InputError("--devices is empty")
    return devices


@dataclass
class _Worker:
    name: str  # "w0", ...
    device: str  # as the user names it: "cpu", "cuda:1"
    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection  # the parent's end of the worker's pipe
    jobs: list[SceneJob] = field(default_factory=list)  # sent and not finished, oldest (the one it works on) first
    reading: set[str] = field(default_factory=set)  # scenes it has begun to read
    simplifying: list[str] = field(default_factory=list)  # scenes it has begun to simplify, in order
    head_since: float = 0.0  # when jobs[0] became the oldest
    stopping: bool = False  # sent None: it will exit
    closed: bool = False  # its pipe is at end-of-file: it is exiting
    reaped: bool = False  # its exit has been dealt with


def run_local(
    jobs: list[SceneJob],
    devices: list[str],
    workers_per_device: int | None,
    force: bool,
    progress,
    timeout_s: float | None = None,
    readers: int | None = None,
    mps: bool = False,
) -> list[SceneResult]:
    """Runs every job on worker processes, ``workers_per_device`` per device (None: as many as
    ``gpu_workers.auto_workers`` gives each, ``mps``: the GPUs' workers under MPS); returns the results
    in the order the scenes finished. ``progress`` gets started / advanced / finished calls.
    ``timeout_s``: each scene's time limit on its worker (None: scaled with its size, see
    :func:`~nanogs_warp.batch.scenes.scene_timeout`; 0: none). ``readers``: threads per worker
    that read each input (None: :func:`default_readers`)."""
    context = multiprocessing.get_context("spawn")
    if workers_per_device is None:
        per_device = auto_workers(devices, [(job.input, job.size) for job in jobs], mps)
    else:
        per_device = dict.fromkeys(devices, workers_per_device)
    if readers is None:
        readers = default_readers(sum(per_device.values()))
    pending = deque(largest_first(jobs))
    results: list[SceneResult] = []
    workers: dict[str, _Worker] = {}
    restarts = dict.fromkeys(devices, 0)
    handbacks: dict[str, int] = {}
    broken: dict[str, str] = {}  # device -> why its worker could not start Warp
    serial = iter(range(1 << 30))

    def start(device: str) -> None:
        name = f"w{next(serial)}"
        here, there = context.Pipe()
        process = context.Process(target=worker_main, args=(name, device, _visible_gpu(device), there, force, readers, os.getpid()),
                                  name=f"nanogs-batch-{name}", daemon=True)  # fmt: skip
        process.start()
        there.close()
        workers[name] = _Worker(name, device, process, here)

    def fail(worker: _Worker, job: SceneJob, error: str, seconds: float = 0.0) -> None:
        result = SceneResult(str(job.input), job.relative, "failed", worker.device, round(seconds, 4), error=error)
        results.append(result)
        progress.finished(worker.name, result)

    def new_head(worker: _Worker) -> None:
        worker.head_since = time.monotonic()
        if worker.jobs:
            progress.started(worker.name, worker.device, worker.jobs[0])

    def feed(worker: _Worker) -> None:
        """Tops the worker up to _SCENES_PER_WORKER scenes; tells it to exit when none is left."""
        sent = []
        while len(worker.jobs) + len(sent) < _SCENES_PER_WORKER and pending:
            sent.append(pending.popleft())
        if not sent and not worker.jobs and not worker.stopping:
            sent, worker.stopping = [None], True
        was_idle = not worker.jobs
        for job in sent:
            if job is not None:
                worker.jobs.append(job)
            try:
                worker.conn.send(job)
            except OSError:  # it has just died: reap() hands the jobs back
                pass
        if was_idle and worker.jobs:
            new_head(worker)

    def handle(worker: _Worker, event) -> None:
        kind, payload = event
        if kind == "ready":
            feed(worker)
        elif kind == "broken":
            broken[worker.device] = payload
        elif kind == "reading":
            worker.reading.add(payload)
        elif kind == "started":
            worker.simplifying.append(payload)
        elif kind == "pass":
            progress.advanced(worker.name, payload)
        elif kind == "finished":
            index = next(i for i, j in enumerate(worker.jobs) if j.relative == payload.relative)
            del worker.jobs[index]
            worker.reading.discard(payload.relative)
            if payload.relative in worker.simplifying:
                worker.simplifying.remove(payload.relative)
            results.append(payload)
            progress.finished(worker.name, payload)
            if index == 0:
                new_head(worker)
            feed(worker)

    def receive(worker: _Worker) -> None:
        """Handles whatever the worker has sent; EOF just means it has exited. (Only the pipe's own
        errors close it: one of the progress's, caught here, left a batch waiting on a live worker.)"""
        while not worker.closed:
            try:
                if not worker.conn.poll():
                    return
                event = worker.conn.recv()
            except (EOFError, OSError):
                worker.closed = True
                return
            handle(worker, event)

    def reap(worker: _Worker, timed_out: tuple[SceneJob, str, float] | None = None) -> None:
        """A worker has exited (or was killed because a scene ran past its time limit:
        ``timed_out`` is that scene, the error and its seconds): fails the scene it was working on,
        hands back the others, and starts another worker in its place while scenes wait."""
        receive(worker)  # what it sent before it exited comes first
        worker.reaped = True
        worker.conn.close()
        held, worker.jobs = worker.jobs, []
        # what it was writing when it died (killed past a time limit, or by the out-of-memory killer)
        _remove_temporaries(held)
        culprit, seconds = None, 0.0
        if timed_out is not None:
            culprit, error, seconds = timed_out  # no one, if it finished just before the kill
        elif held:
            begun = [j for j in held if j.relative in worker.simplifying]
            culprit = begun[-1] if begun else (held[0] if held[0].relative in worker.reading else None)
            reason = _exit_reason(worker.process.exitcode)
            error = f"the worker process died ({reason}); out of memory?"
        for job in reversed(held):
            if job is culprit:
                fail(worker, job, error, seconds)
            elif handbacks.get(job.relative, 0) >= _MAX_HANDBACKS:
                fail(worker, job, f"its worker process was stopped {_MAX_HANDBACKS + 1} times while it held this scene")
            else:
                handbacks[job.relative] = handbacks.get(job.relative, 0) + 1
                pending.appendleft(job)
        if pending and worker.device not in broken and (timed_out is not None or restarts[worker.device] < _MAX_RESTARTS):
            if timed_out is None:
                restarts[worker.device] += 1
            start(worker.device)

    def deadline(worker: _Worker) -> float | None:
        if not worker.jobs or worker.reaped:
            return None
        limit = scene_timeout(worker.jobs[0], worker.device != "cpu", timeout_s)
        return None if limit is None else worker.head_since + limit

    for round_ in range(min(max(per_device.values()), len(pending))):  # never more workers than scenes
        for device in devices:
            if round_ < per_device[device] and len(workers) < len(pending):
                start(device)
    interrupted = True  # until the loop ends by itself: a signal, an error
    try:
        while len(results) < len(jobs):
            live = [w for w in workers.values() if not w.reaped]
            if not live:
                why = "; ".join(f"{d}: {m}" for d, m in broken.items()) or "every worker process died"
                for job in pending:
                    result = SceneResult(str(job.input), job.relative, "failed", "-", error=f"no worker left ({why})")
                    results.append(result)
                    progress.finished("-", result)
                pending.clear()
                break
            now = time.monotonic()
            for worker in live:
                limit = deadline(worker)
                if limit is not None and now >= limit:
                    receive(worker)  # it may have just finished
                    limit = deadline(worker)
                    if limit is not None and now >= limit:
                        seconds = now - worker.head_since
                        error = timed_out_error(limit - worker.head_since, "its worker process was replaced")
                        worker.process.kill()
                        worker.process.join()
                        reap(worker, timed_out=(worker.jobs[0], error, seconds))
            live = [w for w in workers.values() if not w.reaped]
            if not live:  # the last worker was stopped past its time limit: done, or none left
                continue
            deadlines = [d for d in map(deadline, live) if d is not None]
            wait_s = max(0.0, min(deadlines) - time.monotonic()) if deadlines else None
            by_handle = {w.conn: w for w in live if not w.closed} | {w.process.sentinel: w for w in live}
            for ready in wait(list(by_handle), timeout=wait_s):
                worker = by_handle[ready]
                if worker.reaped:
                    continue
                if ready is worker.conn:
                    receive(worker)
                else:  # its process sentinel: it has exited
                    worker.process.join()
                    reap(worker)
        interrupted = False
    finally:
        _stop(workers.values(), interrupted)
    return results


def default_readers(workers: int) -> int:
    """Reader threads per worker: this machine's cores shared out among ``workers``, 1 to 8."""
    from ..io.ply_read import cpu_count

    return max(1, min(8, cpu_count() // max(1, workers)))


def worker_main(name: str, device: str, visible_gpu: str | None, conn, force: bool, readers: int = 1, parent: int | None = None) -> None:
    """A worker process: pins its GPU, initialises Warp, then simplifies the scenes it is sent
    until it is sent None or its parent (process ``parent``) is gone; each input is read on
    ``readers`` threads. SIGTERM, SIGHUP and SIGINT stop it, the scene being written finished first
    (``_end_on_signals``). The process then ends at once with its code, without the interpreter's
    teardown: every output is written by then, and the teardown joins the read pool's threads, which
    a signal arriving during it could leave waiting for ever (a worker orphaned, never ending)."""
    code = 0
    try:
        _work(name, device, visible_gpu, conn, force, readers, parent)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    except BaseException:  # noqa: BLE001 - an internal error: its traceback, then the exit code the parent reports
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):  # a closed pipe, a closed file, or none
                pass
        os._exit(code)


def _work(name: str, device: str, visible_gpu: str | None, conn, force: bool, readers: int, parent: int | None) -> None:
    _end_on_signals()
    if parent is not None:
        _stop_with_parent(parent)
    for stream in ("stdout", "stderr"):  # the batch started with one closed (>&-): discarded, as there
        if getattr(sys, stream) is None:
            setattr(sys, stream, open(os.devnull, "w"))  # noqa: SIM115 - the process's own stream
    if visible_gpu is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = visible_gpu  # before Warp initialises CUDA
    from ..io.ply_read import set_read_threads

    set_read_threads(readers)
    try:
        try:
            import warp as wp

            from ..device import init_warp, keep_freed_host_memory
            from ..kernel_cache import ALL_MODULES, load_kernels

            init_warp()
            keep_freed_host_memory()
            warp_device = wp.get_device("cpu" if device == "cpu" else "cuda:0")
            load_kernels(warp_device, ALL_MODULES, announce=name == "w0")  # the fits' too, before any scene's clock starts
        except Exception as e:  # noqa: BLE001 - reported to the parent, which fails the scenes
            conn.send(("broken", f"cannot start Warp on {device}: {type(e).__name__}: {e}"))
            return
        _serve(device, warp_device, conn, force)
    except (KeyboardInterrupt, EOFError, BrokenPipeError):  # Ctrl-C (the parent reports it), or no parent
        return


def _serve(device: str, warp_device, conn, force: bool) -> None:
    """Three stages on three threads, joined by queues: read (and hash) the next scene, simplify
    the current one on the device (this thread), write the last one's outputs. At most one read
    scene waits for the device and one simplified scene for the writer, so memory stays bounded."""
    from .work import read_scene, simplify_scene, write_scene

    lock = threading.Lock()

    def send(message) -> None:
        """To the parent; if it is gone, the receiver sees end-of-file and the stages wind down."""
        with lock:
            try:
                conn.send(message)
            except OSError:
                pass

    jobs: queue.Queue = queue.Queue()
    read: queue.Queue = queue.Queue()
    to_write: queue.Queue = queue.Queue(maxsize=1)
    free_slot = threading.Semaphore(1)

    def receiver() -> None:
        try:
            while (job := conn.recv()) is not None:
                jobs.put(job)
        except (EOFError, OSError):
            pass
        jobs.put(None)

    def reader() -> None:
        while (job := jobs.get()) is not None:
            free_slot.acquire()
            send(("reading", job.relative))
            read.put(read_scene(job, force, device))
        read.put(None)

    written = threading.Event()  # the writer is done: an Event, as a join interrupted by a signal breaks the thread's state

    def writer() -> None:
        try:
            while (scene := to_write.get()) is not None:
                send(("finished", write_scene(scene)))
        finally:
            written.set()

    threads = [threading.Thread(target=t, name=f"nanogs-batch-{t.__name__}", daemon=True) for t in (receiver, reader, writer)]
    for thread in threads:
        thread.start()
    send(("ready", None))
    last = [0.0]

    def on_pass(report):
        _end_if_signalled()
        now = time.monotonic()
        if now - last[0] >= _PASS_EVENT_EVERY_S:
            last[0] = now
            send(("pass", (report.index, report.count_before, report.count_after)))

    try:
        while (scene := read.get()) is not None:
            _end_if_signalled()
            free_slot.release()
            send(("started", scene.job.relative))
            simplify_scene(scene, warp_device, on_pass)
            to_write.put(scene)
    finally:  # also on a signal: the scene being written (and one waiting for the writer) is finished
        _finish_writing(to_write, written)


def _finish_writing(to_write: queue.Queue, written: threading.Event) -> None:
    """Tells the writer thread to end once it has written what it holds, and waits until it has
    (``written``). An ending signal that arrives meanwhile waits too (it ended the worker
    mid-write), then ends it. Not ``Thread.join``: Python 3.11's, interrupted by the signal's
    exception, marks the thread stopped while it still runs, and the next join returns at once."""
    for step in (lambda: to_write.put(None), written.wait):
        while True:
            try:
                step()
                break
            except SystemExit:  # the first ending signal: kept in _signalled, raised again below
                pass
    _end_if_signalled()


_signalled: list[int] = []  # the exit code of the first ending signal a worker received


def _end_if_signalled() -> None:
    """Raises the first ending signal's SystemExit again. The handler's own can be swallowed: raised
    inside a finaliser (Warp's ``array.__del__``), it is only printed, and the worker went on with its
    scenes, its handlers by then ignoring the batch's SIGTERM. ``_serve`` calls this between merge
    passes and between scenes."""
    if _signalled:
        raise SystemExit(_signalled[0])


def _end_on_signals() -> None:
    """SIGTERM, SIGHUP and SIGINT end the worker as SystemExit(128 + signal) the first time and are
    ignored after that, so that ``_serve`` finishes the scene being written before the process ends
    (``_end_if_signalled`` raises it again where the first was swallowed). A process group's Ctrl-C,
    ``timeout`` or ``scancel`` reaches the workers too, and by default they died at once, leaving the
    temporary files of the outputs they were writing. SIGHUP and SIGINT stay ignored where the batch
    was started with them ignored."""
    names = [name for name in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, name)]

    def ignore(signum, frame):
        pass

    def end(signum, frame):
        # a no-op handler, not SIG_IGN: a second signal already pending (a process group's SIGINT and
        # the batch's SIGTERM) then raised "OSError: Signal 15 ignored due to race condition" in
        # place of the SystemExit, and the worker ended with a traceback, its scene unfinished
        for name in names:
            signal.signal(getattr(signal, name), ignore)
        _signalled.append(128 + signum)
        raise SystemExit(128 + signum)

    printed = sys.unraisablehook

    def unraisable(report) -> None:  # the handler's SystemExit swallowed by a finaliser: raised again later, not printed
        if not (isinstance(report.exc_value, SystemExit) and _signalled):
            printed(report)

    sys.unraisablehook = unraisable
    for name in names:
        number = getattr(signal, name)
        if name != "SIGTERM" and signal.getsignal(number) == signal.SIG_IGN:
            continue  # ignored by whoever started the batch (``nohup``, a background job): still ignored
        signal.signal(number, end)  # SIGTERM always: it is how the batch itself stops its workers


def _stop_with_parent(parent: int) -> None:
    """Has the kernel send this worker SIGTERM when the batch process is gone (Linux's
    PR_SET_PDEATHSIG; a batch killed with SIGKILL left its workers simplifying the scenes they held)."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return
    pr_set_pdeathsig = 1
    if prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0) == 0 and os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)  # it was gone before the request was made


def _visible_gpu(device: str) -> str | None:
    """The CUDA_VISIBLE_DEVICES entry that shows a worker only ``cuda:N`` (of the parent's list)."""
    if device == "cpu":
        return None
    ordinal = int(device.split(":")[1])
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is None:
        return str(ordinal)
    return [v.strip() for v in visible.split(",")][ordinal]


def _exit_reason(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            pass
    return f"exit code {code}"


def _remove_temporaries(jobs: list[SceneJob]) -> None:
    """What a killed worker was writing for ``jobs``: their outputs' and records' temporaries."""
    remove_stale_temporaries([path for job in jobs for path in (job.record_path, *map(job.output_path, job.budgets))])


def _stop(workers, interrupted: bool = False) -> None:
    """Ends the workers: each is sent None and given 5 s to finish, or, when the batch was
    ``interrupted`` (a signal, an error), SIGTERM at once and 60 s to finish the scene it is writing
    (``_end_on_signals``), instead of going on with the scenes it holds."""
    if interrupted:
        for worker in workers:
            if not worker.reaped and worker.process.is_alive():
                worker.process.terminate()
        deadline = time.monotonic() + 60.0
        for worker in workers:
            worker.process.join(max(0.0, deadline - time.monotonic()))
    for worker in workers:
        if not worker.reaped and not worker.stopping and worker.process.is_alive():
            try:
                worker.conn.send(None)
            except OSError:
                pass
    deadline = time.monotonic() + 5.0
    for worker in workers:
        worker.process.join(max(0.0, deadline - time.monotonic()))
        if worker.process.is_alive():
            worker.process.terminate()
            worker.process.join(2.0)
        if worker.process.is_alive():  # deaf to SIGTERM (a kernel that never returns): the batch must end
            worker.process.kill()
            worker.process.join(5.0)
            _remove_temporaries(worker.jobs)
        if not worker.conn.closed:
            worker.conn.close()
