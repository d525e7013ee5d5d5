"""``parallel.in_turn``: every item once, on the calling thread and the pool's, the first failure re-raised."""

import threading

import numpy as np
import pytest
import warp as wp

from nanogs_warp import parallel
from nanogs_warp.parallel import chunk_launches, in_turn, launch_chunks_in_turn


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_every_item_once_on_the_calling_thread_and_the_pool(workers):
    seen, threads, lock = [], set(), threading.Lock()
    together = threading.Barrier(workers)

    def work(item):
        if item < workers:  # each of the first items waits for the others: one on each thread
            together.wait(timeout=10)
        with lock:
            seen.append(item)
            threads.add(threading.get_ident())

    in_turn(workers, range(50), work)
    assert sorted(seen) == list(range(50))
    assert len(threads) == workers and threading.get_ident() in threads  # the calling thread works too
    if workers == 1:
        assert seen == list(range(50))  # one thread: in order


def test_the_first_failure_is_re_raised_and_no_item_is_taken_after_it():
    taken, lock = [], threading.Lock()

    def work(item):
        with lock:
            taken.append(item)
        if item == 3:
            raise ValueError("item 3")

    with pytest.raises(ValueError, match="item 3"):
        in_turn(2, range(1000), work)
    assert 3 in taken and len(taken) < 10  # the threads stop at their next item


def test_no_items_and_one_item():
    calls = []
    in_turn(4, [], calls.append)
    in_turn(4, [7], calls.append)
    assert calls == [7]


def test_a_call_from_a_pool_thread_runs_there_instead_of_waiting_behind_itself():
    from nanogs_warp.parallel import worker_pool

    inner = []

    def outer(_):  # on the one-thread pool that in_turn(2, ...) hands items to
        in_turn(2, range(5), inner.append)
        return threading.current_thread().name

    name = worker_pool(1).submit(outer, None).result(timeout=10)
    assert name.startswith("nanogs-warp") and inner == list(range(5))


@pytest.mark.parametrize(
    ("cores", "rows", "per_worker", "min_rows", "expected"),
    [
        (32, 100_000, 4, 4096, 24),  # cheap rows: as many chunks as min_rows allows, above one a worker
        (32, 1_000_000, 4, 4096, 128),  # enough rows: chunks_per_worker a worker
        (32, 40_000, 4, 4096, 9),  # fewer rows than workers x min_rows: fewer workers, one chunk each
        (2, 100_000, 4, 4096, 8),
        (2, 5_000, 4, 4096, 1),
    ],
)
def test_row_chunks_cover_the_rows_in_chunks_of_at_least_min_rows(monkeypatch, cores, rows, per_worker, min_rows, expected):
    monkeypatch.setattr(parallel, "cpu_workers", lambda: cores)
    workers, chunks = parallel.row_chunks(rows, "cpu", per_worker, min_rows)
    assert len(chunks) == expected
    assert workers == max(1, min(cores, rows // min_rows))
    assert chunks[0][0] == 0 and chunks[-1][1] == rows
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:]))
    assert len(chunks) == 1 or min(b - a for a, b in chunks) >= min_rows


@wp.kernel
def _scaled_rows(scale: float, first: int, values: wp.array(dtype=float), out: wp.array(dtype=float), firsts: wp.array(dtype=int)):
    r = first + wp.tid()
    out[r] = scale * values[r]
    firsts[r] = first


@pytest.mark.parametrize("workers", [1, 3])
def test_chunk_launches_run_each_chunk_with_its_own_first_row_and_size(rng, workers):
    """Chunks of three sizes (the first of each size packed, the others copies of it with their
    own first row), the first row in the middle of the arguments: every row written once, by its
    own chunk, as one launch would write it."""
    chunks = [(0, 3), (3, 7), (7, 10), (10, 14), (14, 19), (19, 22)]
    values = wp.array(rng.normal(size=22).astype(np.float32), dtype=float, device="cpu")
    out = wp.full(22, float("nan"), dtype=float, device="cpu")
    firsts = wp.full(22, -1, dtype=int, device="cpu")
    commands = chunk_launches(_scaled_rows, chunks, [2.5, 0, values, out, firsts], 1, "cpu")
    assert len(commands) == len(chunks)
    launch_chunks_in_turn(workers, commands)
    np.testing.assert_array_equal(out.numpy(), np.float32(2.5) * values.numpy())
    np.testing.assert_array_equal(firsts.numpy(), np.repeat([a for a, _ in chunks], [b - a for a, b in chunks]))
