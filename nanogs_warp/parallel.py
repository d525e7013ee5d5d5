"""Row-parallel launches that use every CPU core.

A Warp launch on the CPU runs on one core. A kernel whose thread t touches only row t of its
per-row arrays (and reads shared arrays, with no atomics: CPU atomics are not atomic across
concurrent launches) can be split into contiguous chunks of rows, each launched from its own Python
thread (Warp releases the GIL during a launch). On a GPU this is one ordinary launch.

Two calling conventions:

- ``launch_rows``: the kernel sees only its chunk; ``arguments(rows_slice)`` slices every per-row
  array to the chunk.
- ``launch_rows_from``: the kernel's first argument is the chunk's first row and thread t handles
  row ``first + t``; the other arguments are passed whole.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import warp as wp

# Fewest rows per worker thread for a cheap kernel (tens of ns per row): below this, one launch is
# faster than handing chunks to threads. Costly kernels pass a smaller ``min_rows``.
MIN_ROWS_TO_SPLIT = 16384


_pools: dict[tuple[int, int], ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()
POOL_THREADS = "nanogs-warp"  # the name prefix of the pools' threads


def worker_pool(workers: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads, started once per process and kept: starting threads costs
    about as much as a small launch (keyed by process id, so a forked child starts its own; one
    pool a key even when threads of the caller's ask at once)."""
    key = (os.getpid(), workers)
    pool = _pools.get(key)
    if pool is None:
        with _pools_lock:
            pool = _pools.get(key)
            if pool is None:
                pool = _pools[key] = ThreadPoolExecutor(workers, thread_name_prefix=POOL_THREADS)
    return pool


def cpu_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def row_chunks(
    rows: int, device, chunks_per_worker: int = 1, min_rows: int = MIN_ROWS_TO_SPLIT
) -> tuple[int, list[tuple[int, int]]]:
    """(workers, [(first, stop), ...]): the contiguous row chunks a launch over ``rows`` rows is cut
    into on ``device``: ``chunks_per_worker`` a worker, at least ``min_rows`` rows a chunk (each
    chunk's launch holds the GIL for some microseconds: with dozens of cores, many small chunks
    would queue for it), at least one a worker. One chunk off the CPU."""
    device = wp.get_device(device)
    min_rows = max(1, min_rows)
    workers = max(1, min(cpu_workers(), rows // min_rows)) if device.is_cpu else 1
    if workers == 1:
        return 1, [(0, rows)]
    chunks = max(workers, min(workers * max(1, chunks_per_worker), rows // min_rows))
    bounds = [rows * c // chunks for c in range(chunks + 1)]
    return workers, [(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]


def in_turn(workers: int, items: Sequence, work: Callable) -> None:
    """``work(item)`` for every item, ``workers`` at a time: on this thread and ``workers - 1`` of a
    pool's, each taking the next item as it frees up. This thread works too, where waiting for the
    pool instead cost a second hand-over to a thread a launch (on the 2-core machine two chunks of
    a small launch took 146-205 us through the pool, 102 us with one on this thread; one launch
    alone 25 us). Re-raises the first failure, once every thread has stopped taking items."""
    if workers <= 1 or len(items) <= 1 or threading.current_thread().name.startswith(POOL_THREADS):
        for item in items:  # (on a pool thread itself: its helpers could wait behind it for ever)
            work(item)
        return
    pending = iter(items)
    lock = threading.Lock()
    failures: list[BaseException] = []

    def take() -> None:
        while not failures:
            with lock:
                item = next(pending, pending)  # the iterator itself marks the end
            if item is pending:
                return
            try:
                work(item)
            except BaseException as error:  # noqa: BLE001 - re-raised on the calling thread
                failures.append(error)

    helpers = [worker_pool(workers - 1).submit(take) for _ in range(min(workers, len(items)) - 1)]
    try:
        take()
    finally:
        for helper in helpers:
            helper.result()
    if failures:
        raise failures[0]


def _launch_chunks(kernel, workers: int, chunks: list[tuple[int, int]], inputs_of: Callable, device) -> None:
    if len(chunks) == 1:
        first, stop = chunks[0]
        wp.launch(kernel, stop - first, inputs=inputs_of(first, stop), device=device)
        return
    wp.load_module(kernel.module, device=device)  # compile once, before the threads race to it

    def launch(chunk: tuple[int, int]) -> None:
        first, stop = chunk
        wp.launch(kernel, stop - first, inputs=inputs_of(first, stop), device=device)

    in_turn(workers, chunks, launch)


def chunk_launches(kernel, chunks: Sequence[tuple[int, int]], inputs: list, first_at: int, device) -> list:
    """One launch command per chunk (first, stop) of a launch's threads: ``kernel(*inputs)`` over
    stop - first threads with the chunk's first thread's index at ``inputs[first_at]``.

    The arguments are packed once per chunk size (a split launch's chunks come in at most two
    sizes) and each chunk's command copies them, its first index packed alone. Packing is most of
    ``wp.launch``'s time on a CPU (about 30 us for a few arrays, against 3 us for a recorded
    command's launch) and it holds the GIL: with 16 cores the chunks of one launch queued for it,
    and launches split 16 ways ran slower than split 8 ways. CPU launches only: a CUDA command also
    holds its parameters' addresses, which a copy would not update (a GPU launch is never split)."""
    if not wp.get_device(device).is_cpu:
        raise ValueError(f"chunk_launches splits CPU launches, not {device}'s")
    packed: dict[int, wp.Launch] = {}
    commands = []
    for first, stop in chunks:
        base = packed.get(stop - first)
        if base is None:
            arguments = list(inputs)
            arguments[first_at] = first
            base = packed[stop - first] = wp.launch(kernel, stop - first, inputs=arguments, device=device, record_cmd=True)
            commands.append(base)
            continue
        command = wp.Launch(kernel, base.device, hooks=base.hooks, params=list(base.params), bounds=base.bounds)
        command.set_param_at_index(first_at, first)
        commands.append(command)
    return commands


def launch_chunks_in_turn(workers: int, commands: Sequence) -> None:
    """``chunk_launches``' commands, ``workers`` at a time (``in_turn``)."""
    in_turn(workers, commands, lambda command: command.launch())


def launch_rows(
    kernel, rows: int, arguments: Callable[[slice], list], device, chunks_per_worker: int = 1, min_rows: int = MIN_ROWS_TO_SPLIT
) -> None:
    """Launches ``kernel`` over ``rows`` threads; ``arguments(rows_slice)`` returns the kernel's
    argument list with every per-row array sliced to ``rows_slice``."""
    device = wp.get_device(device)
    workers, chunks = row_chunks(rows, device, chunks_per_worker, min_rows)
    _launch_chunks(kernel, workers, chunks, lambda first, stop: arguments(slice(first, stop)), device)


def launch_rows_from(
    kernel, rows: int, inputs: list, device, chunks_per_worker: int = 4, min_rows: int = MIN_ROWS_TO_SPLIT
) -> None:
    """Launches ``kernel(first, *inputs)`` over rows 0..rows-1: thread t of a chunk handles row
    ``first + t``. Several chunks per worker (default 4) even out dense and sparse regions."""
    device = wp.get_device(device)
    workers, chunks = row_chunks(rows, device, chunks_per_worker, min_rows)
    if len(chunks) == 1:
        wp.launch(kernel, rows, inputs=[0, *inputs], device=device)
        return
    # the commands are packed on this thread, which loads (compiles) the module before any pool thread runs
    launch_chunks_in_turn(workers, chunk_launches(kernel, chunks, [0, *inputs], 0, device))
