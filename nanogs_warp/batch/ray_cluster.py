"""The batch on a Ray cluster: each scene is a Ray task that asks for one GPU (or one CPU) and runs
the same :func:`~nanogs_warp.batch.work.process_scene` as a local worker, so outputs, records and
results are the same. Ray is imported only here, and only when ``--ray`` is given."""

from __future__ import annotations

import socket
import time
from collections import deque

from ..errors import InputError
from .scenes import SceneJob, largest_first, scene_timeout, timed_out_error
from .work import SceneResult

INSTALL_HINT = "pip install 'ray>=2.9' (or, from the source tree, pip install '.[ray]')"


def import_ray():
    try:
        import ray
    except ImportError:
        raise InputError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def run_ray(jobs: list[SceneJob], address: str, gpu: bool | None, force: bool, progress,
            timeout_s: float | None = None, readers: int | None = None) -> list[SceneResult]:
    """Runs every job as a Ray task on the cluster at ``address`` (``auto``: the one this machine
    belongs to; ``local``: a private instance started here; a connection already made by the
    caller is used as it is). ``gpu``: tasks ask for a GPU (True), a CPU (False), or a GPU when the
    cluster has any (None). Returns the results in the order the scenes finished.

    At most as many tasks as the cluster has GPUs (or CPUs) are in flight, so a task starts when it
    is submitted and its time limit (``timeout_s``, as for local workers) counts from then; a task
    past it is cancelled, which ends its worker process, and its scene fails."""
    ray = import_ray()
    own = not ray.is_initialized()
    if own:
        try:
            if address == "local":
                ray.init(include_dashboard=False, logging_level="WARNING")
            else:
                ray.init(address=address, logging_level="WARNING")
        except Exception as e:  # noqa: BLE001 - Ray raises ConnectionError, ValueError, RuntimeError...
            hint = " (start a cluster with 'ray start --head', or use --ray local)" if address == "auto" else ""
            raise InputError(f"--ray {address}: cannot start or reach Ray: {' '.join(str(e).split())}{hint}") from None
    try:
        resources = ray.cluster_resources()
        gpus = resources.get("GPU", 0)
        if gpu is None:
            gpu = gpus >= 1
        elif gpu and gpus < 1:
            raise InputError("--ray: the Ray cluster has no GPU; use --devices cpu for CPU tasks")
        slots = max(1, int(gpus if gpu else resources.get("CPU", 1)))
        # Ray starts a fresh worker process for each GPU task (max_calls=1, its default when the
        # decorator asks for GPUs), so Warp always sees the GPU that Ray gave the task.
        task = ray.remote(num_gpus=1, max_retries=2)(_scene_task) if gpu else ray.remote(num_cpus=1, max_retries=2)(_scene_task)
        queued = deque(largest_first(jobs))
        running: dict = {}  # ref -> (job, deadline or None)
        results = []

        def finish(result: SceneResult) -> None:
            results.append(result)
            progress.finished("ray", result)

        while queued or running:
            while queued and len(running) < slots:
                job = queued.popleft()
                limit = scene_timeout(job, gpu, timeout_s)
                running[task.remote(job, force, gpu, readers)] = (job, None if limit is None else time.monotonic() + limit)
            deadlines = [d for _, d in running.values() if d is not None]
            wait_s = max(0.0, min(deadlines) - time.monotonic()) if deadlines else None
            ready, _ = ray.wait(list(running), num_returns=1, timeout=wait_s)
            for ref in ready:
                job, _ = running.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - a crashed task or worker fails its scene only
                    message = " ".join(str(e).split())[:500]
                    result = SceneResult(str(job.input), job.relative, "failed", "ray", error=f"{type(e).__name__}: {message}")
                finish(result)
            now = time.monotonic()
            for ref, (job, limit) in list(running.items()):
                if limit is not None and now >= limit:
                    ray.cancel(ref, force=True)  # kills the worker process that runs it
                    del running[ref]
                    seconds = now - limit + scene_timeout(job, gpu, timeout_s)
                    finish(SceneResult(str(job.input), job.relative, "failed", "ray", round(seconds, 4),
                                       error=timed_out_error(scene_timeout(job, gpu, timeout_s), "its Ray task was cancelled")))  # fmt: skip
        return results
    finally:
        if own:
            ray.shutdown()


def _scene_task(job: SceneJob, force: bool, gpu: bool, readers: int | None = None) -> SceneResult:
    """Runs on a Ray worker: Warp on the GPU Ray assigned (visible as cuda:0) or on the CPU."""
    import warp as wp

    from ..device import init_warp, keep_freed_host_memory
    from ..io.ply_read import set_read_threads
    from .work import process_scene

    set_read_threads(readers)

    init_warp()
    keep_freed_host_memory()
    host = socket.gethostname()
    if gpu:
        import ray

        ids = ray.get_gpu_ids()
        label, device = f"{host}/cuda:{ids[0] if ids else 0}", wp.get_device("cuda:0")
    else:
        label, device = f"{host}/cpu", wp.get_device("cpu")
    return process_scene(job, device, force, device_label=label)
