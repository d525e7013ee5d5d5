"""The batch on a Ray cluster: each scene is a Ray task that asks for one GPU (or one CPU) and runs
the same :func:`~nanogs_warp.batch_work.process_scene` as a local worker, so outputs, records and
results are the same. Ray is imported only here, and only when ``--ray`` is given."""

from __future__ import annotations

import socket

from .batch_scenes import SceneJob, largest_first
from .batch_work import SceneResult
from .errors import InputError

INSTALL_HINT = "pip install 'nanogs-warp[ray]'"


def import_ray():
    try:
        import ray
    except ImportError:
        raise InputError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def run_ray(jobs: list[SceneJob], address: str, gpu: bool | None, force: bool, progress) -> list[SceneResult]:
    """Runs every job as a Ray task on the cluster at ``address`` (``auto``: the one this machine
    belongs to; ``local``: a private instance started here; a connection already made by the
    caller is used as it is). ``gpu``: tasks ask for a GPU (True), a CPU (False), or a GPU when the
    cluster has any (None). Returns the results in the order the scenes finished."""
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
        gpus = ray.cluster_resources().get("GPU", 0)
        if gpu is None:
            gpu = gpus >= 1
        elif gpu and gpus < 1:
            raise InputError("--ray: the Ray cluster has no GPU; use --devices cpu for CPU tasks")
        # Ray starts a fresh worker process for each GPU task (max_calls=1, its default when the
        # decorator asks for GPUs), so Warp always sees the GPU that Ray gave the task.
        task = ray.remote(num_gpus=1, max_retries=2)(_scene_task) if gpu else ray.remote(num_cpus=1, max_retries=2)(_scene_task)
        refs = {task.remote(job, force, gpu): job for job in largest_first(jobs)}
        waiting, results = list(refs), []
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=1)
            for ref in ready:
                try:
                    result = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - a crashed task or worker fails its scene only
                    job = refs[ref]
                    message = " ".join(str(e).split())[:500]
                    result = SceneResult(str(job.input), job.relative, "failed", "ray", error=f"{type(e).__name__}: {message}")
                results.append(result)
                progress.finished("ray", result)
        return results
    finally:
        if own:
            ray.shutdown()


def _scene_task(job: SceneJob, force: bool, gpu: bool) -> SceneResult:
    """Runs on a Ray worker: Warp on the GPU Ray assigned (visible as cuda:0) or on the CPU."""
    import warp as wp

    from .batch_work import process_scene
    from .device import init_warp, keep_freed_host_memory

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
