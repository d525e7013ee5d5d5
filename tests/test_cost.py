"""Edge costs against float64 numpy references; the Monte Carlo estimate against a high-sample one."""

import numpy as np
import pytest
import reference
import warp as wp
from scene_factory import in_units, random_splat_arrays

from nanogs_warp.cost import RunnallsCost
from nanogs_warp.kernels import cost as kernels
from nanogs_warp.kernels.splat_math import jacobi_sweeps, jacobi_sweeps_in_lanes
from nanogs_warp.splats import SplatSet
from nanogs_warp.topology import Edges


def cost_unit(arrays):
    """The unit the field costs come in: the power of two 2^-e with E_ref in [2^e, 2^(e+1))."""
    return 2.0 ** -np.floor(np.log2(reference.reference_energy(arrays)))


def near_pairs(rng, arrays, n_edges):
    """Edges between splats, with j's centre moved near i's so that the costs are moderate."""
    n = len(arrays["means"])
    ei = rng.integers(0, n, n_edges).astype(np.int32)
    ej = (ei + rng.integers(1, n, n_edges)).astype(np.int32) % n
    arrays["means"][ej] = arrays["means"][ei] + rng.normal(scale=0.05, size=(n_edges, 3)).astype(np.float32)
    return ei, ej


def launch_idiv(splats, ei, ej, samples, device, lambda_geo=1.0, lambda_app=1.0):
    costs = wp.full(len(ei), np.nan, dtype=float, device=device)  # poisoned
    wp.launch(
        kernels.idivergence_costs, len(ei),
        inputs=[wp.array(ei, device=device), wp.array(ej, device=device), splats.means, splats.rotations,
                splats.log_scales, splats.opacities, splats.features,
                wp.array(samples.astype(np.float32), dtype=wp.vec3, device=device), lambda_geo, lambda_app],
        outputs=[costs], device=device,
    )  # fmt: skip
    return costs.numpy()


@pytest.mark.parametrize("n_samples", [1, 4])
def test_idivergence_matches_reference(device, rng, n_samples):
    arrays = random_splat_arrays(64, sh_degree=1, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 200)
    samples = rng.normal(size=(n_samples, 3))
    splats = SplatSet.from_numpy(**arrays, device=device)
    got = launch_idiv(splats, ei, ej, samples, device, lambda_geo=1.0, lambda_app=0.5)
    want = [
        reference.idivergence(arrays, i, j, samples.astype(np.float32)) + 0.5 * reference.appearance_distance(arrays, i, j)
        for i, j in zip(ei, ej)
    ]
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-4)


def test_idivergence_converges_to_high_sample_estimate(device, rng):
    """With many common samples the kernel's estimate (both components at each z, q_m's entropy in
    closed form) agrees with a plain 400k-sample Monte Carlo of the paper's KL: x drawn from the
    mixture, log p~(x) - log q_m(x) averaged."""
    arrays = random_splat_arrays(2, sh_degree=0, seed=5)
    arrays["opacities"][:] = 0.0
    arrays["log_scales"][:] = np.log([[0.3, 0.1, 0.05], [0.2, 0.2, 0.1]])
    arrays["means"][1] = arrays["means"][0] + np.float32([0.25, -0.1, 0.05])
    splats = SplatSet.from_numpy(**arrays, device=device)
    got = launch_idiv(splats, np.int32([0]), np.int32([1]), rng.normal(size=(16384, 3)), device, lambda_app=0.0)[0]
    m = reference.mpmm(arrays, 0, 1)
    pi = m["pi"]
    mu = arrays["means"][:2].astype(np.float64)
    cov = reference.covariances(arrays["rotations"][:2], arrays["log_scales"][:2])
    first = rng.uniform(size=400_000) < pi
    x = np.where(first[:, None], rng.multivariate_normal(mu[0], cov[0], 400_000), rng.multivariate_normal(mu[1], cov[1], 400_000))
    log_p = np.logaddexp(np.log(pi) + reference.log_normal(x, mu[0], cov[0]), np.log1p(-pi) + reference.log_normal(x, mu[1], cov[1]))
    want = float(np.mean(log_p - reference.log_normal(x, m["mean"], m["cov"])))
    assert want > 0.01
    assert abs(got - want) < 0.1 * want


def test_reference_estimator_matches_closed_form_kl():
    """The reference's Monte Carlo machinery against the closed-form KL of two single Gaussians."""
    rng = np.random.default_rng(0)
    mu_a, mu_b = np.zeros(3), np.array([0.3, -0.2, 0.1])
    cov_a = np.diag([0.2, 0.1, 0.05]) ** 2
    cov_b = np.diag([0.25, 0.15, 0.1]) ** 2
    x = rng.multivariate_normal(mu_a, cov_a, size=400_000)
    mc = np.mean(reference.log_normal(x, mu_a, cov_a) - reference.log_normal(x, mu_b, cov_b))
    inv_b = np.linalg.inv(cov_b)
    d = mu_b - mu_a
    closed = 0.5 * (np.trace(inv_b @ cov_a) + d @ inv_b @ d - 3 + np.log(np.linalg.det(cov_b) / np.linalg.det(cov_a)))
    assert abs(mc - closed) < 0.01 * closed


def test_identical_splats_cost_only_appearance(device):
    """A pair of identical splats is its own moment match: zero geometric cost for every sample."""
    arrays = random_splat_arrays(2, sh_degree=0, seed=9)
    for key in ("means", "rotations", "log_scales", "opacities"):
        arrays[key][1] = arrays[key][0]
    splats = SplatSet.from_numpy(**arrays, device=device)
    samples = np.random.default_rng(1).normal(size=(8, 3))
    got = launch_idiv(splats, np.int32([0]), np.int32([1]), samples, device, lambda_app=0.0)[0]
    assert abs(got) < 1e-6


def test_mse_matches_reference(device, rng):
    arrays = random_splat_arrays(32, sh_degree=2, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 100)
    splats = SplatSet.from_numpy(**arrays, device=device)
    costs = wp.full(len(ei), np.nan, dtype=float, device=device)
    wp.launch(
        kernels.mse_costs, len(ei),
        inputs=[wp.array(ei, device=device), wp.array(ej, device=device), splats.means, splats.rotations,
                splats.log_scales, splats.features, 2.0, 0.25],
        outputs=[costs], device=device,
    )  # fmt: skip
    want = [2.0 * reference.mse_geometry(arrays, i, j) + 0.25 * reference.appearance_distance(arrays, i, j) for i, j in zip(ei, ej)]
    np.testing.assert_allclose(costs.numpy(), want, rtol=1e-4, atol=1e-6)


def test_common_samples_are_shared_and_seeded(device):
    def draw(seed, pass_index):
        out = wp.full(4, np.nan, dtype=wp.vec3, device=device)
        wp.launch(kernels.draw_common_samples, 4, inputs=[seed, pass_index], outputs=[out], device=device)
        return out.numpy()

    a, b = draw(0, 0), draw(0, 0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, draw(1, 0)) and not np.array_equal(a, draw(0, 1))


# -- the Runnalls cost -------------------------------------------------------------------------


def runnalls(arrays, ei, ej, device, **kwargs):
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
    return RunnallsCost(**kwargs)(splats, edges, pass_index=0).numpy()


def test_runnalls_kernels_write_every_output(device, rng):
    """Per-splat terms and edge costs over NaN-poisoned outputs: every slot written, finite."""
    arrays = random_splat_arrays(50, sh_degree=2, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 300)
    splats = SplatSet.from_numpy(**arrays, device=device)
    covariances = wp.full(50, wp.mat33d(*([np.nan] * 9)), dtype=wp.mat33d, device=device)
    weights = wp.full(50, np.nan, dtype=wp.float64, device=device)
    log_dets = wp.full(50, np.nan, dtype=wp.float64, device=device)
    wp.launch(
        kernels.runnalls_splat_terms, 50,
        inputs=[splats.rotations, splats.log_scales, splats.opacities], outputs=[covariances, weights, log_dets],
        device=device,
    )  # fmt: skip
    assert np.all(np.isfinite(covariances.numpy())) and np.all(weights.numpy() > 0)
    want_log_dets = np.linalg.slogdet(reference.covariances(arrays["rotations"], arrays["log_scales"]))[1]
    np.testing.assert_allclose(log_dets.numpy(), want_log_dets, rtol=1e-12, atol=1e-9)
    costs = wp.full(len(ei), np.nan, dtype=float, device=device)
    wp.launch(
        kernels.runnalls_costs, len(ei),
        inputs=[wp.array(ei, device=device), wp.array(ej, device=device), splats.means, covariances, weights,
                log_dets, splats.features, 1.0, 1.0, 0.25],
        outputs=[costs], device=device,
    )  # fmt: skip
    got = costs.numpy()
    want = np.array([reference.runnalls_cost(arrays, i, j) for i, j in zip(ei, ej)])
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * want.max())


@pytest.mark.parametrize("mass_exponent", [0.0, 0.25, 1.0])
def test_runnalls_matches_reference(device, rng, mass_exponent):
    arrays = random_splat_arrays(64, sh_degree=1, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 200)
    got = runnalls(arrays, ei, ej, device, lambda_geo=1.0, lambda_app=0.5, mass_exponent=mass_exponent)
    want = np.array([reference.runnalls_cost(arrays, i, j, 1.0, 0.5, mass_exponent) for i, j in zip(ei, ej)])
    assert np.all(got >= 0)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * want.max())


def test_runnalls_zero_for_identical_and_scale_free(device, rng):
    """Identical splats cost 0; with mass exponent 0 the costs do not change when the scene is scaled."""
    arrays = random_splat_arrays(64, sh_degree=0, seed=5)
    same = {k: v.copy() for k, v in arrays.items()}
    for key in same:
        same[key][1::2] = same[key][0::2]
    pairs = np.arange(64, dtype=np.int32)
    np.testing.assert_allclose(runnalls(same, pairs[0::2], pairs[1::2], device), 0.0, atol=1e-6)
    ei, ej = near_pairs(rng, arrays, 100)
    scaled = {k: v.copy() for k, v in arrays.items()}
    scaled["means"] *= 10.0
    scaled["log_scales"] += np.float32(np.log(10.0))
    a = runnalls(arrays, ei, ej, device, mass_exponent=0.0)
    b = runnalls(scaled, ei, ej, device, mass_exponent=0.0)
    np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6 * a.max())


@pytest.mark.parametrize("operator", ["coverage", "mpmm"])
def test_field_cost_matches_reference(device, rng, operator):
    """The field cost of the operator's own merged splat against the float64 numpy reference."""
    from nanogs_warp.cost import FieldCost
    from nanogs_warp.kernels import field_cost

    arrays = random_splat_arrays(24, sh_degree=2, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 12)
    splats = SplatSet.from_numpy(**arrays, device=device)
    want_covariances = reference.covariances(arrays["rotations"], arrays["log_scales"])
    f = arrays["features"].astype(np.float64)
    want_norms = ((0.5 + 0.28209479177387814 * f[:, :3]) ** 2).sum(1) + (f[:, 3:] ** 2).sum(1) / (4 * np.pi)
    # the per-splat terms against the references, over poisoned outputs
    want_alphas = reference.sigmoid(arrays["opacities"].astype(np.float64))
    want_log_weights = np.log(want_alphas * reference.footprint(arrays["log_scales"]))
    covariances = wp.full(24, wp.mat33d(*([np.nan] * 9)), dtype=wp.mat33d, device=device)
    colour_norms = wp.full(24, np.nan, dtype=wp.float64, device=device)
    alphas = wp.full(24, np.nan, dtype=wp.float64, device=device)
    log_weights = wp.full(24, np.nan, dtype=wp.float64, device=device)
    wp.launch(
        field_cost.splat_terms, 24, inputs=[splats.rotations, splats.log_scales, splats.opacities, splats.features],
        outputs=[covariances, colour_norms, alphas, log_weights], device=device,
    )  # fmt: skip
    np.testing.assert_allclose(covariances.numpy(), want_covariances, rtol=1e-6, atol=1e-12 * np.abs(want_covariances).max())
    np.testing.assert_allclose(colour_norms.numpy(), want_norms, rtol=1e-12)
    np.testing.assert_allclose(alphas.numpy(), want_alphas, rtol=1e-14)
    np.testing.assert_allclose(log_weights.numpy(), want_log_weights, rtol=1e-12, atol=1e-12)
    # the edge costs from the references' per-splat terms
    covariances = wp.array(want_covariances, dtype=wp.mat33d, device=device)
    colour_norms = wp.array(want_norms, dtype=wp.float64, device=device)
    alphas = wp.array(want_alphas, dtype=wp.float64, device=device)
    log_weights = wp.array(want_log_weights, dtype=wp.float64, device=device)
    costs = wp.full(len(ei), np.nan, dtype=float, device=device)  # poisoned
    energy = reference.reference_energy(arrays)
    unit = cost_unit(arrays)
    wp.launch(
        field_cost.field_costs, len(ei),
        inputs=[wp.array(ei, device=device), wp.array(ej, device=device), splats.kernel_view(), covariances,
                colour_norms, alphas, log_weights, FieldCost.OPERATOR_IDS[operator], FieldCost.growth, 1.0, 0.5, 7.0,
                wp.array([energy, unit], dtype=wp.float64, device=device)],
        outputs=[costs], device=device,
    )  # fmt: skip
    merge = reference.coverage_merge if operator == "coverage" else reference.mpmm
    want = [unit * reference.field_cost(arrays, i, j, merge(arrays, i, j), 1.0, 0.5, 7.0, energy) for i, j in zip(ei, ej)]
    contrast = [unit * 7.0 * energy * reference.base_colour_change(arrays, i, j) for i, j in zip(ei, ej)]
    assert max(contrast) > 1e-3 * max(want)  # the contrast term is part of what is checked
    # the cost is a difference of overlaps of similar size: float32 output, float64 cancellation
    np.testing.assert_allclose(costs.numpy(), want, rtol=1e-4, atol=1e-6 * max(want))


@pytest.mark.parametrize("count,chunk", [(1, 256), (255, 256), (257, 256), (1000, 7)])
def test_reference_energy_matches_reference(device, rng, count, chunk):
    """E_ref, the geometric mean of a^2 s_a s_b, against float64 numpy: one chunk, a chunk and a bit,
    many small chunks (the CPU launch splits them over threads); faint and saturated opacities."""
    from nanogs_warp.cost import reference_energy

    arrays = random_splat_arrays(count, sh_degree=0, seed=int(rng.integers(1 << 30)))
    arrays["opacities"][: count // 3] = rng.uniform(-40, 40, size=count // 3).astype(np.float32)
    got = reference_energy(SplatSet.from_numpy(**arrays, device=device), chunk).numpy()
    assert got.shape == (2,)
    np.testing.assert_allclose(got[0], reference.reference_energy(arrays), rtol=1e-10)
    assert got[1] == cost_unit(arrays) and 1.0 <= got[0] * got[1] < 2.0


def test_field_cost_scores_the_default_operator_growth():
    """The field cost scores the coverage operator's own merge: both take the growth exponent from
    one constant, and the reference's default is the same measured value."""
    import inspect

    from nanogs_warp.cost import FieldCost
    from nanogs_warp.operators import COVERAGE_GROWTH, CoverageMomentMatching

    assert FieldCost().growth == CoverageMomentMatching().growth == COVERAGE_GROWTH
    assert inspect.signature(reference.coverage_merge).parameters["growth"].default == COVERAGE_GROWTH


def test_field_cost_has_no_scene_unit(device, rng):
    """Positions and scales 10x larger: every field cost, the contrast term included, is 100x
    larger (areas) in the same unit, so the order of the merges does not depend on the scene's
    units. The costs come in a power of two near E_ref (which grows 100x too): both as the scaled
    scene's unit gives them."""
    from nanogs_warp.cost import FieldCost

    arrays = random_splat_arrays(64, sh_degree=1, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 40)
    scaled = {k: v.copy() for k, v in arrays.items()}
    scaled["means"] *= np.float32(10.0)
    scaled["log_scales"] += np.float32(np.log(10.0))
    costs = []
    for a in (arrays, scaled):
        splats = SplatSet.from_numpy(**a, device=device)
        edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
        costs.append(FieldCost()(splats, edges, 0).numpy().astype(np.float64) / cost_unit(a))
    np.testing.assert_allclose(costs[1], 100.0 * costs[0], rtol=1e-4, atol=1e-6 * costs[1].max())


@pytest.mark.parametrize("exponent", [-70, 70])
def test_field_costs_of_a_scene_in_tiny_or_huge_units(device, rng, exponent):
    """The same splats 2^70 times smaller or larger: the same float32 costs, bit for bit (the unit
    follows E_ref by whole powers of two, and scaling by a power of two is exact), where unscaled
    they would fall below float32's normals or overflow it."""
    from nanogs_warp.cost import FieldCost

    arrays = random_splat_arrays(64, sh_degree=1, seed=int(rng.integers(1 << 30)))
    ei, ej = near_pairs(rng, arrays, 40)
    costs = []
    for a in (arrays, in_units(arrays, exponent)):
        splats = SplatSet.from_numpy(**a, device=device)
        edges = Edges(wp.array(ei, device=device), wp.array(ej, device=device), len(ei))
        costs.append(FieldCost()(splats, edges, 0).numpy())
    assert np.all(costs[0] > 0) and np.all(costs[0] < 1e30)
    # log-scales + 70 ln 2 round in float32: the costs agree to float32's resolution of the scales
    np.testing.assert_allclose(costs[1], costs[0], rtol=1e-4, atol=1e-6 * costs[0].max())


def test_colour_contrast_ignores_colours_beyond_display_range(device):
    """Two splats whose base colours are both beyond 1 in every channel (raw trainer output, f_dc up
    to 15) look alike: the contrast term adds nothing; a visible difference adds lambda_c E_ref |db|^2."""
    from nanogs_warp.cost import FieldCost

    arrays = random_splat_arrays(2, sh_degree=0, seed=5)
    arrays["features"][0, :3] = 15.0
    arrays["features"][1, :3] = 4.0
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = Edges(wp.array(np.int32([0]), device=device), wp.array(np.int32([1]), device=device), 1)
    with_term, without = (FieldCost(lambda_contrast=w)(splats, edges, 0).numpy()[0] for w in (30.0, 0.0))
    assert with_term == without
    arrays["features"][1, :3] = -1.0  # base colour 0.218: visible
    splats = SplatSet.from_numpy(**arrays, device=device)
    with_term, without = (FieldCost(lambda_contrast=w)(splats, edges, 0).numpy()[0] for w in (30.0, 0.0))
    want = 30.0 * reference.reference_energy(arrays) * reference.base_colour_change(arrays, 0, 1) * cost_unit(arrays)
    np.testing.assert_allclose(with_term - without, want, rtol=1e-3)


def test_gaussian_overlap_closed_form_matches_quadrature(rng):
    """The product-of-Gaussians integral the field cost and the coverage opacity are built on."""
    for _ in range(6):
        m = rng.normal(size=(2, 2, 2))
        a, b = (x @ x.T + 0.05 * np.eye(2) for x in m)
        mu_a, mu_b = rng.normal(scale=0.5, size=(2, 2))
        want = reference.quadrature_overlap_2d(mu_a, a, mu_b, b)
        np.testing.assert_allclose(reference.gaussian_overlap_2d(mu_a, a, mu_b, b), want, rtol=1e-6)


def test_gaussian_products_closed_form_match_quadrature(rng):
    """The integrals of three and four Gaussians that the composited pair adds."""
    for powers in [(2, 1, 0), (1, 2, 0), (2, 2, 0), (1, 1, 1)]:
        m = rng.normal(size=(3, 2, 2))
        covs = [x @ x.T + 0.05 * np.eye(2) for x in m]
        mus = rng.normal(scale=0.5, size=(3, 2))
        want = reference.quadrature_product_2d(powers, mus, covs)
        np.testing.assert_allclose(reference.gaussian_product_2d(powers, mus, covs), want, rtol=1e-6)


def test_field_cost_of_a_splat_merged_with_its_copy(device):
    """Two identical splats of alpha a = 0.45 become one of the same shape with alpha 2a = 0.9 under
    the coverage operator (nothing to grow). Face-on, the pair composited is 2a G - a^2 G^2, so the
    opacity field changes by a^2 G^2, and the cost is a^4 int G^4 = a^4 (pi / 2) s_a s_b, s_a and s_b
    the two largest scales (int G^n dA = 2 pi sqrt(det) / n for a peak-one 2D Gaussian); the two
    edge-on views compare with the sum 2a G, which the merged splat matches exactly. In closed form,
    without the reference implementation."""
    from nanogs_warp.cost import FieldCost

    arrays = random_splat_arrays(2, sh_degree=0, seed=3)
    arrays["means"][1] = arrays["means"][0]
    arrays["rotations"][1] = arrays["rotations"][0]
    arrays["log_scales"][1] = arrays["log_scales"][0]
    arrays["features"][1] = arrays["features"][0]
    a = 0.45
    arrays["opacities"][:] = np.log(a / (1 - a))
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = Edges(wp.array(np.int32([0]), device=device), wp.array(np.int32([1]), device=device), 1)
    got = FieldCost(operator="coverage", lambda_app=0.0, lambda_contrast=0.0)(splats, edges, 0).numpy()[0]
    s = np.sort(np.exp(arrays["log_scales"][0].astype(np.float64)))
    want = a**4 * np.pi / 2 * s[2] * s[1] * cost_unit(arrays)
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_field_cost_of_a_far_pair_matches_reference(device):
    """Two splats a thousand scales apart: G_i G_j vanishes (kappa underflows to 0), so the
    composited terms are exactly 0 and the cost is the plain field change, finite, as the float64
    reference computes it."""
    from nanogs_warp.cost import FieldCost

    arrays = random_splat_arrays(2, sh_degree=1, seed=11)
    arrays["log_scales"][:] = np.log(0.5)
    arrays["means"][1] = arrays["means"][0] + np.float32([1000.0, 0.0, 0.0])
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = Edges(wp.array(np.int32([0]), device=device), wp.array(np.int32([1]), device=device), 1)
    got = FieldCost(lambda_contrast=0.0)(splats, edges, 0).numpy()[0]
    want = reference.field_cost(arrays, 0, 1, reference.coverage_merge(arrays, 0, 1)) * cost_unit(arrays)
    assert np.isfinite(got) and want > 0
    np.testing.assert_allclose(got, want, rtol=1e-4)


@wp.kernel
def _sweeps_one(a: wp.array(dtype=wp.mat33d), diagonal: wp.array(dtype=wp.vec3d), rotation: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    d, r = jacobi_sweeps(a[i])
    diagonal[i] = d
    rotation[i] = r


@wp.kernel
def _sweeps_in_lanes(a: wp.array(dtype=wp.mat33d), diagonal: wp.array(dtype=wp.vec3d), rotation: wp.array(dtype=wp.mat33d)):
    g = 4 * wp.tid()
    d0, r0, d1, r1, d2, r2, d3, r3 = jacobi_sweeps_in_lanes(a[g], a[g + 1], a[g + 2], a[g + 3])
    diagonal[g] = d0
    rotation[g] = r0
    diagonal[g + 1] = d1
    rotation[g + 1] = r1
    diagonal[g + 2] = d2
    rotation[g + 2] = r2
    diagonal[g + 3] = d3
    rotation[g + 3] = r3


def test_jacobi_sweeps_in_lanes_are_the_scalar_sweeps(device, rng):
    """Four matrices' sweeps side by side give each the bits of its own sweeps, whatever its lanes'
    neighbours need: random ones over 300 orders of magnitude, diagonal ones, ones with some zero
    off-diagonal entries, repeated eigenvalues, rank one plus a floor, and NaN and infinite entries,
    shuffled across the lanes."""
    n = 4096
    q = rng.normal(size=(n, 3, 3))
    a = q @ np.transpose(q, (0, 2, 1)) * 10.0 ** rng.uniform(-150, 150, size=(n, 1, 1))
    kinds = rng.integers(0, 6, n)
    a[kinds == 1] = np.eye(3) * rng.uniform(0.1, 10.0, size=(int((kinds == 1).sum()), 3, 1))
    zeroed = kinds == 2
    a[zeroed, 0, 2] = a[zeroed, 2, 0] = 0.0
    a[kinds == 3] = np.eye(3) * 2.5
    d = rng.normal(size=(n, 3, 1))
    a[kinds == 4] = (d @ np.transpose(d, (0, 2, 1)) + 1e-10 * np.eye(3))[kinds == 4]
    a[kinds == 5, 1, 1] = rng.choice([np.nan, np.inf, -np.inf], int((kinds == 5).sum()))
    matrices = wp.array(a, dtype=wp.mat33d, device=device)
    got = []
    for kernel, threads in ((_sweeps_one, n), (_sweeps_in_lanes, n // 4)):
        diagonal = wp.full(n, wp.vec3d(np.nan, np.nan, np.nan), dtype=wp.vec3d, device=device)  # poisoned
        rotation = wp.full(n, wp.mat33d(*([np.nan] * 9)), dtype=wp.mat33d, device=device)
        wp.launch(kernel, threads, inputs=[matrices, diagonal, rotation], device=device)
        got.append((diagonal.numpy(), rotation.numpy()))
    finite = kinds != 5
    assert np.isfinite(got[0][0][finite]).all() and np.isfinite(got[0][1][finite]).all()
    assert got[0][0].tobytes() == got[1][0].tobytes()
    assert got[0][1].tobytes() == got[1][1].tobytes()


@pytest.mark.parametrize("operator", ["coverage", "mpmm"])
def test_field_costs_in_lanes_are_the_field_costs(device, rng, operator):
    """The CPU's kernel (four edges a thread) gives every edge's cost the bits of the one-edge kernel's,
    the last group of four only partly filled, over poisoned outputs."""
    from nanogs_warp.cost import FieldCost, reference_energy
    from nanogs_warp.kernels import field_cost
    from nanogs_warp.topology import KnnTopology

    arrays = random_splat_arrays(600, sh_degree=1, seed=int(rng.integers(1 << 30)))
    arrays["log_scales"][::7] = rng.uniform(-12.0, 1.0, size=(86, 3)).astype(np.float32)  # flat and large ones too
    splats = SplatSet.from_numpy(**arrays, device=device)
    edges = KnnTopology(8)(splats)
    count = edges.count - (edges.count % 4 == 0)  # a partial last group
    ei, ej = edges.i[:count], edges.j[:count]
    n = splats.count
    covariances = wp.empty(n, dtype=wp.mat33d, device=device)
    colour_norms = wp.empty(n, dtype=wp.float64, device=device)
    alphas = wp.empty(n, dtype=wp.float64, device=device)
    log_weights = wp.empty(n, dtype=wp.float64, device=device)
    wp.launch(
        field_cost.splat_terms, n, inputs=[splats.rotations, splats.log_scales, splats.opacities, splats.features],
        outputs=[covariances, colour_norms, alphas, log_weights], device=device,
    )  # fmt: skip
    fc = FieldCost(operator=operator)
    terms = [splats.kernel_view(), covariances, colour_norms, alphas, log_weights, fc.OPERATOR_IDS[operator], fc.growth,
             fc.lambda_geo, fc.lambda_app, fc.lambda_contrast, reference_energy(splats)]  # fmt: skip
    one = wp.full(count, np.nan, dtype=float, device=device)  # poisoned
    wp.launch(field_cost.field_costs, count, inputs=[ei, ej, *terms, one], device=device)
    lanes = wp.full(count, np.nan, dtype=float, device=device)
    wp.launch(field_cost.field_costs_in_lanes, -(-count // 4), inputs=[0, count, ei, ej, *terms, lanes], device=device)
    assert count % 4 != 0 and not np.isnan(one.numpy()).any()
    assert one.numpy().tobytes() == lanes.numpy().tobytes()
    if device == "cpu":  # and FieldCost itself uses the lanes there, on two threads
        whole = FieldCost(operator=operator)(splats, Edges(ei, ej, count), 0)
        assert whole.numpy().tobytes() == one.numpy().tobytes()
