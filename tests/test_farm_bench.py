"""tools/farm_bench.py's steady-state rate: counted once every worker has finished a scene."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "tools"))

from farm_bench import steady_rate  # noqa: E402


def test_one_worker_counts_from_the_first_finish():
    assert steady_rate([1.0, 2.0, 3.0, 4.0], 1) == pytest.approx(1.0)
    assert steady_rate([1.0, 2.0, 3.0, 4.0], 0) == pytest.approx(1.0)  # no start seen: one worker


def test_workers_that_finish_together_give_the_rate_they_keep():
    """Two workers finishing a scene each every 10 s: 0.2 scenes/s, not the 5 / 20.1 s that counting
    from the first finish would give."""
    finished = [10.0, 10.1, 20.0, 20.1, 30.0, 30.1]
    assert steady_rate(finished, 2) == pytest.approx(0.2)
    six = [10.0 + 0.01 * k for k in range(6)] + [20.0 + 0.01 * k for k in range(6)]
    assert steady_rate(six, 6) == pytest.approx(6 / (20.05 - 10.05))


def test_no_rate_without_a_scene_after_the_pipeline_filled():
    assert steady_rate([5.0, 5.1], 2) is None
    assert steady_rate([5.0], 1) is None
    assert steady_rate([], 1) is None
    assert steady_rate([3.0, 3.0, 3.0], 1) is None  # no time between them
