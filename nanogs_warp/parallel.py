"""Row-parallel launches that use every CPU core.

A Warp launch on the CPU runs on one core. A kernel whose thread t touches only row t of its
per-row arrays (and reads shared arrays, with no atomics) can be split into contiguous chunks of
rows, each launched from its own Python thread (Warp releases the GIL during a launch). On a GPU
this is one ordinary launch.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import warp as wp

# Below this many rows, one launch is faster than starting threads.
MIN_ROWS_TO_SPLIT = 16384


def cpu_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def launch_rows(kernel, rows: int, arguments: Callable[[slice], list], device) -> None:
    """Launches ``kernel`` over ``rows`` threads; ``arguments(rows_slice)`` returns the kernel's
    argument list with every per-row array sliced to ``rows_slice``."""
    device = wp.get_device(device)
    workers = cpu_workers() if device.is_cpu else 1
    if workers == 1 or rows < MIN_ROWS_TO_SPLIT:
        wp.launch(kernel, rows, inputs=arguments(slice(0, rows)), device=device)
        return
    bounds = [rows * w // workers for w in range(workers + 1)]
    chunks = [slice(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]
    with ThreadPoolExecutor(len(chunks)) as pool:
        for future in [pool.submit(wp.launch, kernel, c.stop - c.start, inputs=arguments(c), device=device) for c in chunks]:
            future.result()
