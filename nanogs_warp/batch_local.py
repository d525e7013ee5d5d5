"""The batch on this machine: one worker process per device (``spawn``; each initialises Warp and
sees only its own GPU). The parent holds the queue, largest scene first, and hands the next scene
to whichever worker is free; each worker talks to it over its own pipe, so a worker killed at any
moment (the out-of-memory killer) cannot block the others. The parent sees a worker die at once
(its process sentinel), fails the scene it had begun and starts another worker in its place."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import wait

from .batch_scenes import SceneJob, largest_first
from .batch_work import SceneResult
from .errors import InputError

_PASS_EVENT_EVERY_S = 0.25
_MAX_RESTARTS = 3  # per device: a worker that keeps dying is not started again


def parse_devices(text: str) -> list[str]:
    """``auto`` (every GPU, else the CPU), ``all`` (every GPU), ``cpu`` or ``cuda:0,cuda:1`` ->
    device names, checked against this machine."""
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    if names == ["cpu"]:
        return ["cpu"]
    from .device import init_warp

    import warp as wp

    init_warp()
    gpus = wp.get_cuda_device_count()
    if names == ["auto"]:
        return [f"cuda:{i}" for i in range(gpus)] or ["cpu"]
    if names == ["all"]:
        if gpus == 0:
            raise InputError("--devices all: no CUDA GPU is available on this machine")
        return [f"cuda:{i}" for i in range(gpus)]
    devices = []
    for name in names:
        if name == "cuda":
            name = "cuda:0"
        ordinal = name.split(":", 1)[1] if name.startswith("cuda:") else None
        if name != "cpu" and not (ordinal and ordinal.isdigit()):
            raise InputError(f"--devices {text!r}: expected auto, all, cpu or a list like cuda:0,cuda:1")
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
    job: SceneJob | None = None
    started: bool = False  # the worker has begun `job`
    stopping: bool = False  # sent None: it will exit
    closed: bool = False  # its pipe is at end-of-file: it is exiting
    reaped: bool = False  # its exit has been dealt with


def run_local(jobs: list[SceneJob], devices: list[str], workers_per_device: int, force: bool, progress) -> list[SceneResult]:
    """Runs every job on worker processes, ``workers_per_device`` per device; returns the results
    in the order the scenes finished. ``progress`` gets started / advanced / finished calls."""
    context = multiprocessing.get_context("spawn")
    pending = deque(largest_first(jobs))
    results: list[SceneResult] = []
    workers: dict[str, _Worker] = {}
    restarts = dict.fromkeys(devices, 0)
    broken: dict[str, str] = {}  # device -> why its worker could not start Warp
    serial = iter(range(1 << 30))

    def start(device: str) -> None:
        name = f"w{next(serial)}"
        here, there = context.Pipe()
        process = context.Process(target=worker_main, args=(name, device, _visible_gpu(device), there, force),
                                  name=f"nanogs-batch-{name}", daemon=True)  # fmt: skip
        process.start()
        there.close()
        workers[name] = _Worker(name, device, process, here)

    def feed(worker: _Worker) -> None:
        worker.job, worker.started = (pending.popleft() if pending else None), False
        worker.stopping = worker.job is None
        try:
            worker.conn.send(worker.job)
        except OSError:  # it has just died: reap() hands the job back
            pass

    def handle(worker: _Worker, event) -> None:
        kind, payload = event
        if kind == "ready":
            feed(worker)
        elif kind == "broken":
            broken[worker.device] = payload
        elif kind == "started":
            worker.started = True
            progress.started(worker.name, worker.device, worker.job)
        elif kind == "pass":
            progress.advanced(worker.name, payload)
        elif kind == "finished":
            worker.job = None
            results.append(payload)
            progress.finished(worker.name, payload)
            feed(worker)

    def receive(worker: _Worker) -> None:
        """Handles whatever the worker has sent; EOF just means it has exited."""
        try:
            while not worker.closed and worker.conn.poll():
                handle(worker, worker.conn.recv())
        except (EOFError, OSError):
            worker.closed = True

    def reap(worker: _Worker) -> None:
        """A worker has exited: fails the scene it had begun (or hands back the one it had not),
        and starts another worker in its place while scenes wait."""
        receive(worker)  # what it sent before it exited comes first
        worker.reaped = True
        worker.conn.close()
        job, worker.job = worker.job, None
        if job is not None and worker.started:
            reason = _exit_reason(worker.process.exitcode)
            result = SceneResult(str(job.input), job.relative, "failed", worker.device,
                                 error=f"the worker process died ({reason}); out of memory?")  # fmt: skip
            results.append(result)
            progress.finished(worker.name, result)
        elif job is not None:
            pending.appendleft(job)
        if pending and worker.device not in broken and restarts[worker.device] < _MAX_RESTARTS:
            restarts[worker.device] += 1
            start(worker.device)

    for _ in range(workers_per_device):
        for device in devices:
            if len(workers) < len(pending):
                start(device)
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
            by_handle = {w.conn: w for w in live if not w.closed} | {w.process.sentinel: w for w in live}
            for ready in wait(list(by_handle)):
                worker = by_handle[ready]
                if worker.reaped:
                    continue
                if ready is worker.conn:
                    receive(worker)
                else:  # its process sentinel: it has exited
                    worker.process.join()
                    reap(worker)
    finally:
        _stop(workers.values())
    return results


def worker_main(name: str, device: str, visible_gpu: str | None, conn, force: bool) -> None:
    """A worker process: pins its GPU, initialises Warp, then simplifies the scenes it is sent
    until it is sent None or its parent is gone."""
    if visible_gpu is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = visible_gpu  # before Warp initialises CUDA
    try:
        try:
            import warp as wp

            from .device import init_warp, keep_freed_host_memory

            init_warp()
            keep_freed_host_memory()
            warp_device = wp.get_device("cpu" if device == "cpu" else "cuda:0")
        except Exception as e:  # noqa: BLE001 - reported to the parent, which fails the scenes
            conn.send(("broken", f"cannot start Warp on {device}: {type(e).__name__}: {e}"))
            return
        _serve(device, warp_device, conn, force)
    except (KeyboardInterrupt, EOFError, BrokenPipeError):  # Ctrl-C (the parent reports it), or no parent
        return


def _serve(device: str, warp_device, conn, force: bool) -> None:
    from .batch_work import process_scene

    conn.send(("ready", None))
    while (job := conn.recv()) is not None:
        conn.send(("started", None))
        last = [0.0]

        def on_pass(report, last=last):
            now = time.monotonic()
            if now - last[0] >= _PASS_EVENT_EVERY_S:
                last[0] = now
                conn.send(("pass", (report.index, report.count_before, report.count_after)))

        conn.send(("finished", process_scene(job, warp_device, force, device_label=device, on_pass=on_pass)))


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


def _stop(workers) -> None:
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
        if not worker.conn.closed:
            worker.conn.close()
