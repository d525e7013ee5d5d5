"""Degenerate covariances: splats flat or thin far beyond float64's resolution of a covariance
(log-scales down to -30 beside scales near 1: variance ratios up to e^60).

Every covariance is regularised as Sigma + 1e-12 tr(Sigma) I (kernels/splat_math.py), so such
pairs get real costs from every cost and merge like any other, where they used to be marked
unmergeable and merged last. Checked against the float64 references (which regularise alike), in
the pipeline (exact counts, finite outputs that render) and in the merge order."""

import numpy as np
import pytest
import reference
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp.cost import FieldCost, IDivergenceCost, RunnallsCost
from nanogs_warp.kernels import cost as cost_kernels
from nanogs_warp.pipeline import SimplifyConfig, simplify
from nanogs_warp.splats import SplatSet
from nanogs_warp.topology import Edges

UNMERGEABLE = 3.0e38


def rotation_wxyz(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_matrix(q):
    return reference.rotation_matrices(q[None])[0]


def degenerate_pairs(rng, n_pairs, sh_degree=1):
    """n_pairs pairs (2p, 2p + 1): coplanar flat disks (one log-scale -30 or -25, the others in
    [-3, -1]), offset in their plane by about a disk's size; needles (two log-scales -30 or -25)
    offset along their axis; and a flat disk beside a round splat. The thin axes are any of the
    three (a random permutation per pair). Returns the arrays and the edges."""
    n = 2 * n_pairs
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    q = rotation_wxyz(rng, n_pairs)
    for p in range(n_pairs):
        i, j = 2 * p, 2 * p + 1
        kind = p % 3
        r = quat_matrix(q[p])
        perm = rng.permutation(3)  # local axis perm[t] holds the t-th of (big, big, thin)
        big = rng.uniform(-3.0, -1.0, size=(2, 2))
        thin = rng.choice([-30.0, -25.0], size=2)
        local = np.zeros(3)
        if kind == 0:  # coplanar flat disks
            values = ([big[0, 0], big[0, 1], thin[0]], [big[1, 0], big[1, 1], thin[1]])
            local[perm[:2]] = rng.normal(scale=np.exp(big[0].max()), size=2)
        elif kind == 1:  # needles along one axis
            values = ([big[0, 0], thin[0], thin[1]], [big[1, 0], thin[1], thin[0]])
            local[perm[0]] = rng.normal(scale=np.exp(big[0, 0]))
        else:  # a flat disk and a round splat
            values = ([big[0, 0], big[0, 1], thin[0]], [big[1, 0]] * 3)
            local = rng.normal(scale=np.exp(big[0].max()), size=3)
        for row, v in zip((i, j), values):
            arrays["log_scales"][row, perm] = v
        arrays["rotations"][i] = arrays["rotations"][j] = q[p]
        arrays["means"][i] = rng.normal(size=3)
        arrays["means"][j] = arrays["means"][i] + (r @ local if kind != 2 else local)
    for key in ("means", "rotations", "log_scales"):
        arrays[key] = arrays[key].astype(np.float32)
    ei = np.arange(0, n, 2, dtype=np.int32)
    return arrays, ei, ei + 1


def costs_of(cost, arrays, ei, ej, device):
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    return cost(splats, edges, 0).numpy()


def test_runnalls_costs_of_degenerate_pairs_match_reference(device, rng):
    arrays, ei, ej = degenerate_pairs(rng, 60)
    got = costs_of(RunnallsCost(), arrays, ei, ej, device)
    want = np.array([reference.runnalls_cost(arrays, i, j) for i, j in zip(ei, ej)])
    assert np.all(np.isfinite(got)) and got.max() < 1e30
    # B is a difference of log dets (tens in size) whose smallest eigenvalues float64 resolves to
    # about 1e-4 after regularisation: an absolute tolerance on that scale
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3 * np.abs(want).max())


def test_idiv_costs_of_degenerate_pairs_match_reference(device, rng):
    arrays, ei, ej = degenerate_pairs(rng, 60)
    samples = np.array([[0.3, -1.1, 0.7], [-0.5, 0.4, 1.9], [1.2, 0.1, -0.6]], np.float32)
    splats = SplatSet.from_numpy(**arrays, device=device)
    costs = wp.full(len(ei), np.nan, dtype=float, device=device)  # poisoned
    wp.launch(
        cost_kernels.idivergence_costs, len(ei),
        inputs=[wp.array(ei, device=device), wp.array(ej, device=device), splats.means, splats.rotations,
                splats.log_scales, splats.opacities, splats.features, wp.array(samples, dtype=wp.vec3, device=device),
                1.0, 0.0],
        outputs=[costs], device=device,
    )  # fmt: skip
    got = costs.numpy()
    want = np.array([reference.idivergence(arrays, i, j, samples) for i, j in zip(ei, ej)])
    assert np.all(np.isfinite(got)) and np.abs(got).max() < 1e30
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3 * np.abs(want).max())


@pytest.mark.parametrize("operator", ["coverage", "mpmm"])
def test_field_costs_of_flat_disks_match_quadrature(device, rng, operator):
    arrays, ei, ej = degenerate_pairs(rng, 9)
    flat = slice(0, None, 3)  # the coplanar disks: the quadrature grid resolves them in their plane
    ei, ej = ei[flat], ej[flat]
    got = costs_of(FieldCost(operator=operator), arrays, ei, ej, device)
    merge = reference.coverage_merge if operator == "coverage" else reference.mpmm
    unit = 2.0 ** -np.floor(np.log2(reference.reference_energy(arrays)))  # the field costs' unit
    want = [unit * reference.field_cost(arrays, i, j, merge(arrays, i, j), lambda_contrast=FieldCost.lambda_contrast) for i, j in zip(ei, ej)]
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-4 * max(want))


@pytest.mark.parametrize("cost", ["field", "runnalls", "idiv"])
def test_every_degenerate_pair_has_a_real_cost(device, rng, cost):
    """No pair of finite degenerate splats is unmergeable, and for a pair of identical ones the
    Runnalls bound (mass exponent 0: the bound alone) is about 0."""
    arrays, ei, ej = degenerate_pairs(rng, 90)
    costs = {"field": FieldCost(), "runnalls": RunnallsCost(mass_exponent=0.0), "idiv": IDivergenceCost(samples=8)}[cost]
    got = costs_of(costs, arrays, ei, ej, device)
    assert np.all(np.isfinite(got)) and np.all(got < 1e30)
    same = {k: v.copy() for k, v in arrays.items()}
    for key in same:
        same[key][ej] = same[key][ei]
    twins = costs_of(costs, same, ei, ej, device)
    assert np.all(twins < 1e30)
    if cost == "runnalls":
        np.testing.assert_allclose(twins, 0.0, atol=1e-5)


def flat_scene(rng, n, sh_degree=1):
    """A scene of flat disks and needles (log-scales down to -30) among ordinary splats."""
    arrays = random_splat_arrays(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    ls = arrays["log_scales"]
    kind = rng.integers(0, 3, n)
    ls[kind == 0, 2] = rng.uniform(-30.0, -20.0, (kind == 0).sum())
    ls[kind == 1, 1:] = rng.uniform(-30.0, -20.0, ((kind == 1).sum(), 2))
    arrays["log_scales"] = np.ascontiguousarray(np.take_along_axis(ls, rng.permuted(np.tile([0, 1, 2], (n, 1)), axis=1), axis=1))
    arrays["means"] = (arrays["means"] * np.float32(0.3)).astype(np.float32)
    return arrays


@pytest.mark.parametrize("preset", ["default", "fast", "paper"])
def test_scene_of_degenerate_splats_reaches_the_counts_and_renders(device, rng, preset):
    from nanogs_warp.eval.cameras import orbit_cameras
    from nanogs_warp.eval.render import render_views

    arrays = flat_scene(rng, 1500)
    splats = SplatSet.from_numpy(**arrays, device=device)
    results = simplify(splats, ratio=[0.1, 0.01], config=SimplifyConfig.preset(preset))
    assert [r.count for r in results] == [150, 15]
    for r in results:
        out = r.to_numpy()
        for key in ("means", "rotations", "log_scales", "opacities", "features"):
            assert np.all(np.isfinite(out[key])), key
        assert out["log_scales"].min() >= -30.0
        images = render_views(r, orbit_cameras(splats, views=2, size=48))
        assert np.all(np.isfinite(images)) and images.max() > 0


def test_degenerate_twins_merge_first(device, rng):
    """Pairs of identical flat disks and needles cost almost nothing under the field cost: the
    first pass merges every twin with its twin, where unmergeable costs used to put them last.
    (Alpha a = 0.01: the coverage merge of two is the same splat at alpha 2a, and the pair
    composited, 2a G - a^2 G^2, differs from it by a^2 G^2: a cost of a^4 int G^4, below that of
    any other edge of a twin. The Runnalls cost weighs pairs by mass, so lighter pairs may go first
    there: its twins are checked for a bound of about 0 in
    ``test_every_degenerate_pair_has_a_real_cost``.)"""
    from nanogs_warp.pairing import select_pairs
    from nanogs_warp.topology import KnnTopology
    from nanogs_warp.timing import no_clock

    arrays = flat_scene(rng, 400)
    twins = np.arange(0, 80, 2)
    arrays["opacities"][twins] = np.log(0.01 / 0.99)
    for key in arrays:
        arrays[key][twins + 1] = arrays[key][twins]
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = KnnTopology(8)(splats, no_clock)
    costs = FieldCost()(splats, edges, 0)
    pairs = select_pairs(edges, costs, splats.count, cap=splats.count // 2)
    chosen = set(zip(pairs.i.numpy().tolist(), pairs.j.numpy().tolist()))
    assert {(int(t), int(t) + 1) for t in twins} <= chosen
