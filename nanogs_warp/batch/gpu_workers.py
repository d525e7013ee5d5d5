"""How many worker processes ``batch --workers auto`` starts on each device.

One worker leaves a GPU idle while its Python launches the geometry fit's small kernels and
between scenes; a second worker on the same GPU fills those gaps (on H200s, twelve 6M-splat
scenes to three budgets: 0.86-0.87 scenes/s with one worker, 1.07-1.09 with two, before the
geometry fit's long fit of the smallest outputs made the GPU the limit; docs/performance.md).
Each worker needs the GPU memory of the scene it works on, so a GPU gets the second worker only
where two of the batch's largest scene fit in its memory. The CPU gets one: its worker already
spreads every kernel over the cores.

Under CUDA MPS (``batch --mps``, ``mps.py``) the workers' kernels run side by side instead of in
turns, and more of them keep the GPU fuller: GPU_WORKERS_MPS, as many as the memory holds (on an
H200, sixteen 6M-splat scenes to three budgets: 0.53 scenes/s steady with two workers without MPS,
0.67 with two under MPS, 0.99 with four, 1.19 with six; docs/performance.md).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

GPU_WORKERS = 2  # workers on a GPU that has the memory for them
GPU_WORKERS_MPS = 6  # the same under MPS
# A worker's peak GPU memory per splat of its scene, with a margin: the mempool's high-water mark
# over a default three-budget run on an H200 was 488 bytes a splat at 6M splats and 601 at 500k
# (docs/performance.md), here about doubled; plus the worker's CUDA context and kernels.
GPU_BYTES_PER_SPLAT = 1024
GPU_BYTES_PER_WORKER = 1 << 30
MEMORY_SHARE = 0.8  # of a GPU's total memory that the workers may plan to take
HEADER_BYTES = 1 << 16  # read of the largest input for its count (a 3DGS header takes about 2 kB)


def ply_splats(path: Path) -> int | None:
    """The vertex count in a PLY file's header, or None for another format or a header that does
    not read (the worker reports such a file when it gets to it)."""
    from ..io.ply_header import parse_header

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None  # a FIFO or a device would block the read, or never end it
        with open(path, "rb") as f:
            head = f.read(HEADER_BYTES)
        vertex = parse_header(head, str(path)).element("vertex")
    except Exception:  # noqa: BLE001 - any unreadable or hostile header: not counted
        return None
    return int(vertex.count) if vertex is not None and vertex.count >= 0 else None


def workers_for(device: str, largest: int | None, total_memory: int | None, most: int = GPU_WORKERS) -> int:
    """Workers for ``device`` ("cpu" or "cuda:N"): on a GPU of ``total_memory`` bytes, as many of
    ``most`` as it holds of the largest scene (``largest`` splats), at least one; one on the CPU
    and wherever either is unknown."""
    if device == "cpu" or largest is None or total_memory is None:
        return 1
    each = GPU_BYTES_PER_WORKER + GPU_BYTES_PER_SPLAT * max(1, largest)
    return max(1, min(most, int(MEMORY_SHARE * total_memory // each)))


def auto_workers(devices: list[str], inputs: list[tuple[Path, int]], mps: bool = False) -> dict[str, int]:
    """``workers_for`` each device, for a batch of ``inputs`` (path, file size): its largest scene
    is the largest file's PLY header count; up to GPU_WORKERS_MPS a GPU under MPS (``mps``), else
    GPU_WORKERS. Where some input is not a plain PLY (a compressed format holds more splats in
    fewer bytes) the largest is not known: one worker each."""
    gpus = [d for d in devices if d != "cpu"]
    largest = None
    plain = all(p.name.lower().endswith(".ply") and not p.name.lower().endswith(".compressed.ply") for p, _ in inputs)
    if gpus and inputs and plain:
        largest = ply_splats(max(inputs, key=lambda job: job[1])[0])
    memory: dict[str, int | None] = {}
    if gpus and largest is not None:
        import warp as wp

        for d in gpus:
            try:
                memory[d] = int(wp.get_device(d).total_memory)
            except Exception:  # noqa: BLE001 - a device Warp cannot describe: one worker
                memory[d] = None
    most = GPU_WORKERS_MPS if mps else GPU_WORKERS
    return {d: workers_for(d, largest, memory.get(d), most) for d in devices}
