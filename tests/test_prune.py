"""Opacity pruning (Algorithm 1, lines 3-4) against tests/reference.py's prune_keep: threshold
min(tau, median opacity), keep alpha >= threshold, and the keep-at-least fallback.

The inputs are built so that the rule's edges decide the result: the median is below tau and many
splats sit exactly on it (logit 0 gives alpha = 0.5 exactly in float32, on every device), and ties at
the fallback's cut. A strict comparison, a dropped median or a different tie order all fail here."""

import numpy as np
import pytest
from reference import prune_keep
from scene_factory import random_splat_arrays

from nanogs_warp.prune import prune_low_opacity
from nanogs_warp.splats import SplatSet


def splats_with_opacities(logits, device):
    arrays = random_splat_arrays(len(logits), seed=len(logits))
    arrays["opacities"] = np.asarray(logits, np.float32)
    # the extras carry the row index, so the kept rows can be read back from the result
    arrays["extras"] = np.arange(len(logits), dtype=np.float32)[:, None]
    return SplatSet.from_numpy(**arrays, device=device)


def kept_rows(logits, threshold, keep_at_least, device):
    pruned = prune_low_opacity(splats_with_opacities(logits, device), threshold, keep_at_least)
    return pruned.extras.numpy()[:, 0].astype(np.int64)


def check(logits, threshold, keep_at_least, device):
    expected = prune_keep(np.asarray(logits, np.float32), threshold, keep_at_least)
    np.testing.assert_array_equal(kept_rows(logits, threshold, keep_at_least, device), expected)
    return expected


def test_median_below_tau_keeps_the_ties(device, rng):
    """tau = 0.9 is above the median 0.5: the threshold is the median, and every splat at exactly
    0.5 stays (>=, not >)."""
    logits = np.r_[np.zeros(9), rng.uniform(-6, -0.5, 6), rng.uniform(0.5, 6, 6)]
    rng.shuffle(logits)
    kept = check(logits, 0.9, 1, device)
    assert len(kept) == 15  # the 9 on the median and the 6 above it
    # without the median rule, only the 6 above 0.9's logit (2.197) or so would stay
    assert np.all(1 / (1 + np.exp(-logits[kept])) >= 0.5)


def test_tau_below_median_keeps_ties_at_tau(device, rng):
    """tau = 0.5 below the median: threshold tau itself, and the splats at exactly 0.5 stay."""
    logits = np.r_[np.zeros(5), rng.uniform(-6, -0.5, 4), rng.uniform(0.5, 6, 12)]
    rng.shuffle(logits)
    kept = check(logits, 0.5, 1, device)
    assert len(kept) == 17


def test_even_count_median_is_the_mean_of_the_middle_two(device):
    """Even n: the median is the mean of the middle two; a splat between tau and the lower middle
    value is dropped, one at the median's exact value (two equal middle values) kept."""
    logits = np.array([-3.0, -2.0, -1.0, 0.0, 0.0, 1.0, 2.0, 3.0], np.float32)
    assert list(check(logits, 0.99, 1, device)) == [3, 4, 5, 6, 7]
    logits = np.array([-3.0, -2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 3.0], np.float32)
    assert list(check(logits, 0.99, 1, device)) == [4, 5, 6, 7]


def test_keep_at_least_takes_the_most_opaque_later_rows_first(device):
    """The fallback: when the rule keeps fewer than keep_at_least, the keep_at_least most opaque
    stay, among equal opacities the later rows."""
    logits = np.array([3.0, 0.0, 0.0, 0.0, 3.0, 4.0, 5.0, 6.0], np.float32)
    # the median is sigmoid(3): the rule keeps rows 0, 4, 5, 6, 7
    assert list(check(logits, 0.999, 5, device)) == [0, 4, 5, 6, 7]
    assert list(check(logits, 0.999, 6, device)) == [0, 3, 4, 5, 6, 7]
    assert list(check(logits, 0.999, 7, device)) == [0, 2, 3, 4, 5, 6, 7]
    assert list(check(logits, 0.999, 8, device)) == list(range(8))


def test_zero_threshold_prunes_nothing(device, rng):
    logits = rng.normal(scale=3.0, size=50).astype(np.float32)
    assert len(check(logits, 0.0, 1, device)) == 50


@pytest.mark.parametrize("n", [1, 2, 3, 101, 1000])
def test_random_opacities_with_repeats(device, rng, n):
    logits = rng.choice(rng.normal(scale=3.0, size=max(1, n // 3)), size=n).astype(np.float32)
    for threshold in (0.05, 0.3, 0.7, 1.0):
        check(logits, threshold, max(1, n // 4), device)
