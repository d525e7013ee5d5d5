"""Per-stage wall times of the simplification loop, for benchmarks.

Timing a stage synchronises the device before and after it, which slows the pipeline a little;
the pipeline therefore takes a clock only when one is given.
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext

import warp as wp


class StageClock:
    """Seconds per stage for each pass (``passes``), plus stages outside the loop (``setup``)."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self.setup: dict[str, float] = {}
        self.passes: list[dict[str, float]] = []
        self._current = self.setup

    def next_pass(self) -> None:
        self._current = {}
        self.passes.append(self._current)

    @contextmanager
    def stage(self, name: str):
        wp.synchronize_device(self.device)
        start = time.perf_counter()
        yield
        wp.synchronize_device(self.device)
        self._current[name] = self._current.get(name, 0.0) + time.perf_counter() - start

    def totals(self) -> dict[str, float]:
        """Seconds per stage over setup and every pass."""
        out = dict(self.setup)
        for times in self.passes:
            for name, seconds in times.items():
                out[name] = out.get(name, 0.0) + seconds
        return out


def no_clock(name: str):
    return nullcontext()
