"""The whole simplification: exact counts, invariants, determinism, one pass against numpy."""

import math

import numpy as np
import pytest
import reference
import warp as wp
from scene_factory import in_units, random_splat_arrays

from nanogs_warp.errors import InputError
from nanogs_warp.pipeline import SimplifyConfig, simplify, simplify_progressively
from nanogs_warp.splats import SplatSet


def clustered_scene(n, seed, sh_degree=1):
    """Splats in a few tight clusters of different density, like a trained scene."""
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=seed)
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (6, 3))
    spread = np.array([0.002, 0.01, 0.03, 0.1, 0.2, 0.5])
    which = rng.integers(0, 6, n)
    arrays["means"] = (centres[which] + rng.normal(size=(n, 3)) * spread[which, None]).astype(np.float32)
    arrays["log_scales"] = (np.log(spread[which, None] / 5) + rng.normal(scale=0.3, size=(n, 3))).astype(np.float32)
    return arrays


def assert_valid(out: dict, input_means: np.ndarray):
    for key, value in out.items():
        assert np.all(np.isfinite(value)), key
    np.testing.assert_allclose(np.linalg.norm(out["rotations"], axis=1), 1.0, atol=1e-5)
    lo, hi = input_means.min(0), input_means.max(0)
    tol = 1e-5 * (hi - lo).max()
    assert np.all(out["means"] >= lo - tol) and np.all(out["means"] <= hi + tol)


CONFIGS = {
    "default": SimplifyConfig(),
    "paper": SimplifyConfig.paper(),
    "area-mse": SimplifyConfig(operator="area", cost="mse", k=8),
}


@pytest.mark.parametrize("config", sorted(CONFIGS))
@pytest.mark.parametrize("ratio", [0.5, 0.1, 0.01, 0.001])
def test_exact_target_count(device, ratio, config):
    arrays = clustered_scene(3000, seed=1)
    splats = SplatSet.from_numpy(**arrays, device=device)
    out = simplify(splats, ratio=ratio, config=CONFIGS[config])
    assert out.count == max(1, math.ceil(ratio * 3000))
    assert out.device == wp.get_device(device)
    assert_valid(out.to_numpy(), arrays["means"])


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_same_input_same_output(device, config):
    arrays = clustered_scene(2000, seed=2, sh_degree=2)
    runs = [
        simplify(SplatSet.from_numpy(**arrays, device=device), ratio=0.05, config=CONFIGS[config]).to_numpy()
        for _ in range(2)
    ]
    for key in runs[0]:
        assert runs[0][key].tobytes() == runs[1][key].tobytes(), key


def test_seed_changes_the_monte_carlo_cost(device):
    arrays = clustered_scene(1500, seed=3)
    a = simplify(SplatSet.from_numpy(**arrays, device=device), ratio=0.1, config=SimplifyConfig.paper(seed=0))
    b = simplify(SplatSet.from_numpy(**arrays, device=device), ratio=0.1, config=SimplifyConfig.paper(seed=1))
    assert not np.array_equal(a.means.numpy(), b.means.numpy())


def test_budgets_continue_one_progressive_merge(device):
    """Several budgets in one run: the first equals a run to that budget alone, all are exact."""
    arrays = clustered_scene(2500, seed=4)
    splats = SplatSet.from_numpy(**arrays, device=device)
    results = {t: s.to_numpy() for t, s in simplify_progressively(splats, [250, 25, 3])}
    assert {t: len(r["means"]) for t, r in results.items()} == {250: 250, 25: 25, 3: 3}
    alone = simplify(SplatSet.from_numpy(**arrays, device=device), count=250).to_numpy()
    for key in alone:
        assert alone[key].tobytes() == results[250][key].tobytes(), key


def test_pruning_keeps_the_most_opaque_when_short_of_target(device):
    """tau' = min(tau, median) drops the 300 least opaque; a 900 target keeps the 900 most opaque."""
    arrays = clustered_scene(1000, seed=5)
    arrays["opacities"][:] = np.repeat(np.float32([-10.0, -8.0, 4.0]), [300, 300, 400])
    pruned = simplify(SplatSet.from_numpy(**arrays, device=device), count=700, config=SimplifyConfig.paper(prune_opacity=0.5))
    assert sorted(pruned.opacities.numpy().tolist()) == [-8.0] * 300 + [4.0] * 400
    out = simplify(SplatSet.from_numpy(**arrays, device=device), count=900, config=SimplifyConfig.paper(prune_opacity=0.5))
    assert sorted(out.opacities.numpy().tolist()) == [-10.0] * 200 + [-8.0] * 300 + [4.0] * 400


@pytest.mark.parametrize("n,count", [(1, 1), (2, 1), (3, 1), (17, 2)])
def test_tiny_inputs(device, n, count):
    arrays = clustered_scene(n, seed=6)
    out = simplify(SplatSet.from_numpy(**arrays, device=device), count=count, config=SimplifyConfig(prune_opacity=0.0))
    assert out.count == count
    assert_valid(out.to_numpy(), arrays["means"])


def test_impossible_targets(device):
    splats = SplatSet.from_numpy(**clustered_scene(10, seed=7), device=device)
    for kwargs in ({"ratio": 0.0}, {"ratio": 1.5}, {"count": 0}, {"count": 11}, {}):
        with pytest.raises(InputError):
            simplify(splats, **kwargs)


def test_one_pass_matches_numpy(device):
    """One pass from the float64 references: brute-force kNN, I-divergence, greedy pairs, MPMM."""
    n, k = 400, 8
    arrays = clustered_scene(n, seed=8)
    arrays["opacities"] = np.abs(arrays["opacities"]) + 1.0  # nothing pruned
    target = 300
    config = SimplifyConfig.paper(k=k, prune_opacity=0.0, seed=3)
    out = simplify(SplatSet.from_numpy(**arrays, device=device), count=target, config=config).to_numpy()

    # reference: kNN graph -> edges -> costs with the same common samples -> greedy -> MPMM -> compaction
    from nanogs_warp.kernels import cost as cost_kernels

    samples = wp.empty(1, dtype=wp.vec3, device=device)
    wp.launch(cost_kernels.draw_common_samples, 1, inputs=[3, 0], outputs=[samples], device=device)
    means = arrays["means"].astype(np.float64)
    d2 = ((means[:, None] - means[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    nbr = np.argsort(d2, axis=1, kind="stable")[:, :k]
    edges = sorted({(min(i, j), max(i, j)) for i in range(n) for j in nbr[i]})
    ei, ej = np.array(edges).T
    costs = np.array(
        [reference.idivergence(arrays, i, j, samples.numpy()) + reference.appearance_distance(arrays, i, j) for i, j in edges],
        dtype=np.float32,
    )
    pairs = reference.greedy_pairs(ei, ej, costs, n, n - target)
    assert len(pairs) == n - target
    absorbed = {j for _, j in pairs}
    kept = [r for r in range(n) if r not in absorbed]
    assert len(out["means"]) == len(kept)
    merged_at = {i: reference.mpmm(arrays, i, j) for i, j in pairs}
    for row, r in enumerate(kept):
        if r in merged_at:
            np.testing.assert_allclose(out["means"][row], merged_at[r]["mean"], rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(reference.sigmoid(out["opacities"][row]), merged_at[r]["alpha"], rtol=1e-5)
        else:
            np.testing.assert_array_equal(out["means"][row], arrays["means"][r])


def test_default_neighbours_by_scene_size():
    config = SimplifyConfig()
    assert config.k is None
    assert config.neighbours(4_721) == 24 and config.neighbours(65_535) == 24
    assert config.neighbours(65_536) == 16 and config.neighbours(5_000_000) == 16
    assert SimplifyConfig(k=7).neighbours(100) == 7 and SimplifyConfig(k=7).neighbours(10**6) == 7


@pytest.mark.parametrize("n, k", [(3_000, 24), (70_000, 16)])
def test_default_run_uses_the_neighbours_of_its_size(n, k):
    arrays = clustered_scene(n, seed=21, sh_degree=0)
    splats = SplatSet.from_numpy(**arrays, device="cpu")
    default = simplify(splats, count=n // 3).to_numpy()
    explicit = simplify(splats, count=n // 3, config=SimplifyConfig(k=k)).to_numpy()
    other = simplify(splats, count=n // 3, config=SimplifyConfig(k=40 - k)).to_numpy()
    for key in default:
        np.testing.assert_array_equal(default[key], explicit[key])
    assert not np.array_equal(default["means"], other["means"])


def test_stage_clock_times_every_stage_of_every_pass(device):
    from nanogs_warp.timing import StageClock

    arrays = clustered_scene(2_000, seed=5)
    clock = StageClock(device)
    passes = []
    list(simplify_progressively(SplatSet.from_numpy(**arrays, device=device), [20], clock=clock, on_pass=passes.append))
    assert len(clock.passes) == len(passes) >= 6
    for times in clock.passes:
        assert list(times) == ["knn", "edges", "cost", "pairing", "compaction", "merge"]
        assert all(seconds > 0.0 for seconds in times.values())
    assert list(clock.setup) == ["prune"]


@pytest.mark.parametrize("operator", ["coverage", "mpmm"])
def test_field_cost_and_pass_fraction_reach_the_target(device, operator):
    """The field cost with either operator, merging at most a quarter of the splats a pass: exact
    counts at every budget, finite values, and more passes than taking whole matchings."""
    from nanogs_warp.pipeline import SimplifyConfig, simplify_progressively

    splats = SplatSet.from_numpy(**random_splat_arrays(3000, sh_degree=1, seed=11), device=device)
    passes = {}
    for fraction in (0.5, 0.25):
        config = SimplifyConfig(cost="field", operator=operator, pass_fraction=fraction)
        reports = []
        for target, result in simplify_progressively(splats, [300, 30], config, on_pass=reports.append):
            assert result.count == target
            a = result.to_numpy()
            assert all(np.isfinite(v).all() for v in a.values())
        passes[fraction] = len(reports)
        assert all(r.count_before - r.count_after <= math.ceil(fraction * r.count_before) for r in reports)
    assert passes[0.25] > passes[0.5]


def test_pass_limit_grows_with_the_halvings():
    from nanogs_warp.pipeline import pass_limit

    assert pass_limit(1000, 1000) == 32
    assert pass_limit(1000, 500) == 40
    assert pass_limit(1000, 1) == 32 + 8 * 10
    assert pass_limit(6_000_000, 6_000) == 32 + 8 * 10


def test_as_many_budgets_as_passes_allow_and_more():
    """A pass stops at the next budget, so each budget may add a pass: 150 budgets of a 400-splat
    scene (more than pass_limit's 104 passes) all arrive, each with its exact count."""
    from nanogs_warp.pipeline import pass_limit

    splats = SplatSet.from_numpy(**clustered_scene(400, seed=3), device="cpu")
    counts = list(range(1, 151))
    assert pass_limit(400, 1) < len(counts)
    for config in (SimplifyConfig.preset("fast"), SimplifyConfig()):
        assert [s.count for s in simplify(splats, count=counts, config=config)] == counts


@pytest.mark.parametrize("kept", [0, 1])
def test_a_stuck_merge_stops_with_an_error(device, monkeypatch, kept):
    """A pass that merges nothing, or so little that the pass bound runs out, ends the run with an
    error that says so, never a spin (the pairing is forced to keep `kept` pairs a pass)."""
    import nanogs_warp.pipeline as pipeline

    real = pipeline.select_pairs

    def few_pairs(edges, costs, vertex_count, cap, method="auto"):
        pairs = real(edges, costs, vertex_count, cap, method)
        return pairs.first(min(pairs.count, kept))

    monkeypatch.setattr(pipeline, "select_pairs", few_pairs)
    splats = SplatSet.from_numpy(**clustered_scene(200, seed=8), device=device)
    expected = "merged nothing" if kept == 0 else "passes without reaching"
    with pytest.raises(RuntimeError, match=expected):
        simplify(splats, count=20)


@pytest.mark.parametrize("exponent", [-64, 64])
def test_a_scene_in_tiny_or_huge_units_simplifies_as_at_unit_size(device, exponent):
    """The same scene in units 2^64 times smaller or larger simplifies like the unscaled one, at its
    scale: the kNN measures a copy scaled back exactly (at 2^64 float32 squared distances overflow,
    at 2^-64 they vanish), and merged splats are not held above a fixed size. The merges' float64
    logs round differently at another scale, so pairs may differ where costs nearly tie: compared
    are the sizes and places of the merged splats, not their bytes."""
    arrays = clustered_scene(3000, seed=5)
    scaled = in_units(arrays, exponent)
    base = simplify(SplatSet.from_numpy(**arrays, device=device), ratio=0.01).to_numpy()
    got = simplify(SplatSet.from_numpy(**scaled, device=device), ratio=0.01).to_numpy()
    assert got["means"].shape == base["means"].shape
    assert_valid(got, scaled["means"])
    sizes = np.sort(got["log_scales"].astype(np.float64).max(1) - exponent * math.log(2.0))
    np.testing.assert_allclose(np.median(sizes), np.median(np.sort(base["log_scales"].max(1))), atol=0.05)
    np.testing.assert_allclose(np.sort(got["means"].astype(np.float64) * 2.0**-exponent, axis=0),
                               np.sort(base["means"].astype(np.float64), axis=0), atol=0.02)  # fmt: skip


def test_outputs_stay_in_the_input_domain(device):
    """Splats at the domain's log-scale bounds (e^+-100) merge into splats within them: every output
    is a valid input again (a merge of two e^100 splats used to store e^101, which a load refuses)."""
    from nanogs_warp.domain import LOG_SCALE_LIMIT

    arrays = random_splat_arrays(2000, seed=9)
    rng = np.random.default_rng(9)
    arrays["log_scales"] = rng.choice([-LOG_SCALE_LIMIT, -99.9, 0.0, 99.9, LOG_SCALE_LIMIT], size=(2000, 3)).astype(np.float32)
    out = simplify(SplatSet.from_numpy(**arrays, device=device), ratio=0.01).to_numpy()
    assert_valid(out, arrays["means"])
    assert np.abs(out["log_scales"]).max() <= LOG_SCALE_LIMIT
    assert np.abs(out["log_scales"]).max() == LOG_SCALE_LIMIT  # the bound was reached, and held
