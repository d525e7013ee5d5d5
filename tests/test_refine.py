"""Refinement: Adam and the constraints against numpy, a perturbed scene converging back toward the
original, determinism, the count invariant, and a CPU refine of the shipped sample."""

from importlib import resources

import numpy as np
import pytest
import reference_refine as ref
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp import InputError, load_ply, refine
from nanogs_warp.kernels import adam as adam_kernels
from nanogs_warp.pipeline import simplify
from nanogs_warp.refinement.cameras import training_cameras
from nanogs_warp.refinement.refine import RefineConfig, refine_with_report
from nanogs_warp.splats import SplatSet


def test_adam_matches_reference(device, rng):
    n, columns, steps = 1000, 5, 4
    param = rng.normal(size=n).astype(np.float32)
    grads = [rng.normal(size=n).astype(np.float32) for _ in range(steps)]
    rates = rng.uniform(1e-3, 1e-1, columns).astype(np.float32)
    scales = [1.0, 0.8, 0.5, 0.3]
    p = wp.array(param, dtype=wp.float32, device=device)
    m = wp.zeros(n, dtype=wp.float32, device=device)
    v = wp.zeros(n, dtype=wp.float32, device=device)
    r = wp.array(rates, dtype=wp.float32, device=device)
    for t, g in enumerate(grads):
        c1, c2 = 1 - 0.9 ** (t + 1), 1 - 0.999 ** (t + 1)
        wp.launch(adam_kernels.adam_step, n, [0, wp.array(g, dtype=wp.float32, device=device), r, columns, scales[t],
                                              0.9, 0.999, 1e-15, c1, c2, m, v, p], device=device)  # fmt: skip
    expected = ref.adam(param, grads, rates, columns, scales=scales)
    assert np.abs(p.numpy() - expected).max() <= 1e-6 + 1e-5 * np.abs(expected).max()


def test_constraints(device):
    rotations = wp.array(np.array([[0, 0, 0, 0], [0, 0, 3, 4], [1, 1, 1, 1]], np.float32), dtype=wp.quat, device=device)
    log_scales = wp.array(np.array([[-30, 0, 9], [1, 2, 3], [-1, -2, -3]], np.float32), dtype=wp.vec3, device=device)
    opacities = wp.array(np.array([-50, 0.5, 50], np.float32), dtype=wp.float32, device=device)
    wp.launch(adam_kernels.constrain_splats, 3, [0, -20.0, 2.5, -20.0, 20.0, rotations, log_scales, opacities], device=device)
    np.testing.assert_allclose(rotations.numpy(), [[0, 0, 0, 1], [0, 0, 0.6, 0.8], [0.5, 0.5, 0.5, 0.5]], atol=1e-7)
    np.testing.assert_array_equal(log_scales.numpy(), [[-20, 0, 2.5], [1, 2, 2.5], [-1, -2, -3]])
    np.testing.assert_array_equal(opacities.numpy(), [-20, 0.5, 20])


def _toy_scene(seed, device):
    arrays = random_splat_arrays(60, sh_degree=1, seed=seed)
    arrays["log_scales"] = np.full((60, 3), np.log(0.15), np.float32) + arrays["log_scales"] * 0.05
    arrays["opacities"] = np.abs(arrays["opacities"]) + 0.5
    return arrays


def test_perturbed_copy_converges_toward_original(device):
    arrays = _toy_scene(1, device)
    original = SplatSet.from_numpy(**arrays, device=device)
    rng = np.random.default_rng(2)
    perturbed_arrays = dict(arrays)
    perturbed_arrays["features"] = arrays["features"] + rng.normal(0.0, 0.3, arrays["features"].shape).astype(np.float32)
    perturbed_arrays["means"] = arrays["means"] + rng.normal(0.0, 0.03, arrays["means"].shape).astype(np.float32)
    perturbed = SplatSet.from_numpy(**perturbed_arrays, device=device)
    config = RefineConfig(steps=300, size=48, reference_views=32, lr_features_dc=1e-2, lr_features_rest=1e-2)
    out, report = refine_with_report(perturbed, original, config)
    assert report.loss_after < 0.2 * report.loss_before
    dc_before = np.abs(perturbed_arrays["features"][:, :3] - arrays["features"][:, :3]).mean()
    dc_after = np.abs(out.to_numpy()["features"][:, :3] - arrays["features"][:, :3]).mean()
    assert dc_after < 0.4 * dc_before


def test_refine_is_deterministic_and_keeps_the_count(device):
    arrays = _toy_scene(3, device)
    reference = SplatSet.from_numpy(**arrays, device=device)
    small = simplify(reference, count=20)
    config = RefineConfig(steps=12, size=40, reference_views=6)
    first, report = refine_with_report(small, reference, config)
    second, _ = refine_with_report(small, reference, config)
    a, b = first.to_numpy(), second.to_numpy()
    for key in a:
        assert a[key].tobytes() == b[key].tobytes(), key
    assert first.count == small.count == 20 and report.count == 20
    assert all(np.isfinite(v).all() for v in a.values())
    np.testing.assert_allclose(np.linalg.norm(a["rotations"], axis=1), 1.0, atol=1e-6)
    assert not np.array_equal(a["means"], small.to_numpy()["means"]), "refinement changed nothing"


def test_outputs_share_the_original_s_renders(device, monkeypatch):
    """Two outputs refined with one ``ReferenceViews`` (as a multi-budget run does): the same bytes as
    each refined alone, with the original rendered once instead of twice; views made for other
    cameras are refused."""
    import nanogs_warp.refinement.refine as refine_module

    arrays = _toy_scene(3, device)
    reference = SplatSet.from_numpy(**arrays, device=device)
    smalls = simplify(reference, count=[30, 12])
    config = RefineConfig(steps=8, size=40, reference_views=6)
    alone = [refine_with_report(small, reference, config)[0].to_numpy() for small in smalls]
    renders = []
    original = refine_module._render_views
    monkeypatch.setattr(refine_module, "_render_views", lambda *a: renders.append(len(a[1])) or original(*a))
    views = refine_module.ReferenceViews(reference, config)
    shared = [refine_with_report(small, reference, config, views=views) for small in smalls]
    assert renders == [6, refine_module.VALIDATION_VIEWS]  # the pool and the held-out views, once
    assert shared[0][1].seconds_reference > 0.0 and shared[1][1].seconds_reference == 0.0
    for a, (b, _) in zip(alone, shared):
        b = b.to_numpy()
        for key in a:
            assert a[key].tobytes() == b[key].tobytes(), key
    # they serve another configuration with the same cameras (more steps, other rates: the same bytes
    # as rendering its own) and refuse one with other cameras (size, seed, pool)
    longer = RefineConfig(steps=9, size=40, reference_views=6, lr_means=3.2e-4)
    a = refine_with_report(smalls[0], reference, longer)[0].to_numpy()
    b = refine_with_report(smalls[0], reference, longer, views=views)[0].to_numpy()
    assert renders == [6, refine_module.VALIDATION_VIEWS, 6, refine_module.VALIDATION_VIEWS]  # only the one alone rendered
    for key in a:
        assert a[key].tobytes() == b[key].tobytes(), key
    for other in (RefineConfig(steps=9, size=48, reference_views=6), RefineConfig(steps=9, size=40, reference_views=6, seed=1),
                  RefineConfig(steps=5, size=40, reference_views=6)):  # a pool of 5 views: one a step
        with pytest.raises(ValueError, match="another reference scene"):
            refine_with_report(smalls[0], reference, other, views=views)


def test_refine_the_shipped_sample_on_the_cpu():
    reference = load_ply(str(resources.files("nanogs_warp.data") / "plant_crop.ply"), device="cpu")
    small = simplify(reference, ratio=0.02)
    before = small.to_numpy()
    out, report = refine_with_report(small, reference, RefineConfig(steps=6, size=48, reference_views=6))
    after = out.to_numpy()
    assert out.count == small.count and out.layout is small.layout
    np.testing.assert_array_equal(after["extras"], before["extras"])
    assert report.loss_after < report.loss_before
    np.testing.assert_array_equal(small.to_numpy()["means"], before["means"])  # input untouched
    assert refine(small, reference, steps=0).to_numpy()["means"].tobytes() == before["means"].tobytes()


def test_training_cameras_are_seeded_and_varied():
    means = np.random.default_rng(0).normal(size=(500, 3))
    a = training_cameras(means, 20, 64, 7)
    b = training_cameras(means, 20, 64, 7)
    c = training_cameras(means, 20, 64, 8)
    assert all(np.array_equal(x.rotation, y.rotation) and np.array_equal(x.translation, y.translation) for x, y in zip(a, b))
    assert not np.array_equal(a[0].translation, c[0].translation)
    assert len({(x.width, x.height) for x in a}) == 4
    centre = np.median(means, axis=0)
    p90 = np.percentile(np.linalg.norm(means - centre, axis=1), 90)
    distances = np.array([np.linalg.norm(x.centre - centre) for x in a]) / p90
    assert distances.min() >= 1.2 - 1e-9 and distances.max() <= 3.0 + 1e-9


def test_bad_settings_are_input_errors():
    arrays = random_splat_arrays(10)
    splats = SplatSet.from_numpy(**arrays, device="cpu")
    with pytest.raises(InputError):
        refine(splats, splats, size=8)
    with pytest.raises(InputError):
        refine(splats, splats, steps=-1)


def test_refinement_that_hurts_held_out_views_returns_its_input():
    """Learning rates far too large wreck the scene; the held-out views see it and the input comes
    back unchanged, byte for byte, with kept_step 0."""
    reference = load_ply(str(resources.files("nanogs_warp.data") / "plant_crop.ply"), device="cpu")
    small = simplify(reference, ratio=0.02)
    wild = RefineConfig(steps=4, size=48, reference_views=4, lr_means=50.0, lr_opacities=50.0, lr_log_scales=50.0)
    out, report = refine_with_report(small, reference, wild)
    assert report.kept_step == 0
    assert report.validation_after == report.validation_before
    for key, value in small.to_numpy().items():
        assert out.to_numpy()[key].tobytes() == value.tobytes(), key


def test_refinement_returns_its_best_held_out_checkpoint():
    reference = load_ply(str(resources.files("nanogs_warp.data") / "plant_crop.ply"), device="cpu")
    small = simplify(reference, ratio=0.02)
    out, report = refine_with_report(small, reference, RefineConfig(steps=8, size=48, reference_views=8))
    assert report.kept_step in (0, 2, 4, 6, 8)
    assert report.validation_after <= report.validation_before
    assert report.kept_step > 0, "a sane run should improve on views it never trained on"


@pytest.mark.parametrize("last, kept", [((0.85, 0.7), 4), ((0.85, 0.9), 2)])
def test_a_checkpoint_is_kept_only_where_every_background_s_held_out_views_render_better(monkeypatch, last, kept):
    """The held-out losses of each background (``background_losses``, black then white) at the four
    checkpoints of a four-step run, scripted: a checkpoint better on one background and worse on the
    other is not kept, one better on both than the last kept one is, and its mean is reported."""
    import nanogs_warp.refinement.refine as refine_module

    scripted = iter([(1.0, 1.0), (0.5, 1.2), (0.9, 0.8), (0.95, 0.5), last])
    monkeypatch.setattr(refine_module._Refiner, "background_losses", lambda *a: np.array(next(scripted)))
    reference = SplatSet.from_numpy(**_toy_scene(3, "cpu"), device="cpu")
    small = simplify(reference, count=20)
    _, report = refine_with_report(small, reference, RefineConfig(steps=4, size=40, reference_views=4))
    assert report.kept_step == kept and report.validation_before == 1.0
    assert report.validation_after == pytest.approx(np.mean(last if kept == 4 else (0.9, 0.8)))


@pytest.mark.parametrize("exponent", [-70, 70])
def test_a_scene_in_tiny_or_huge_units_refines_as_at_unit_size(exponent):
    """The rasteriser works in float32 (squares of ~1e21 overflow, of ~1e-21 vanish): a scene in
    units 2^70 times larger or smaller is refined rescaled by a power of two and handed back in its
    own units, with the losses and the result of the unscaled scene (to the rounding of log-scales)."""
    from nanogs_warp.eval.units import rescaled

    reference = SplatSet.from_numpy(**_toy_scene(5, "cpu"), device="cpu")
    small = simplify(reference, count=20)
    config = RefineConfig(steps=8, size=40, reference_views=6)
    plain, plain_report = refine_with_report(small, reference, config)
    scale = 2.0**exponent
    out, report = refine_with_report(rescaled(small, scale), rescaled(reference, scale), config)
    assert report.kept_step == plain_report.kept_step > 0
    assert report.loss_after == pytest.approx(plain_report.loss_after, rel=1e-3)
    got, want = out.to_numpy(), plain.to_numpy()
    np.testing.assert_allclose(got["means"].astype(np.float64) / scale, want["means"], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(got["log_scales"] - exponent * np.log(2.0), want["log_scales"], atol=1e-3)


def test_a_scene_far_from_the_origin_refines_as_at_the_origin():
    """A scene 2^20 of its sizes from the origin (centres on a grid float32 holds exactly there) is
    refined recentred and handed back in place: the losses and the result of the scene at the origin."""
    from nanogs_warp.eval.units import rescaled

    arrays = _toy_scene(5, "cpu")
    arrays["means"] = (np.round(arrays["means"] * 8.0) / 8.0).astype(np.float32)
    reference = SplatSet.from_numpy(**arrays, device="cpu")
    offset = np.array([2.0**20, -(2.0**20), 2.0**19])
    far_small = rescaled(simplify(reference, count=20), 1.0, -offset)  # its centres rounded to float32 there
    small = rescaled(far_small, 1.0, offset)  # the same splats at the origin (exact)
    config = RefineConfig(steps=8, size=40, reference_views=6)
    plain, plain_report = refine_with_report(small, reference, config)
    out, report = refine_with_report(far_small, rescaled(reference, 1.0, -offset), config)
    assert report.kept_step == plain_report.kept_step > 0
    assert report.loss_after == pytest.approx(plain_report.loss_after, rel=1e-3)
    got, want = out.to_numpy(), plain.to_numpy()
    np.testing.assert_allclose(got["means"].astype(np.float64) - offset, want["means"], atol=0.25)  # float32 steps there: 1/8
    np.testing.assert_allclose(got["log_scales"], want["log_scales"], atol=1e-5)


@pytest.mark.parametrize("steps, size, message", [(100_001, 256, "--refine-steps"), (10**20, 256, "--refine-steps"),
                                                  (10, 4097, "--refine-size"), (10, 20_000, "--refine-size")])  # fmt: skip
def test_refinement_sizes_and_steps_are_bounded(steps, size, message):
    """--refine-size 20000 ran the machine out of memory, and a step count of 1e20 never ended."""
    with pytest.raises(InputError, match=message):
        RefineConfig(steps=steps, size=size).validate()
    RefineConfig(steps=100_000, size=4096).validate()


def test_coarse_steps_train_on_the_views_at_half_size(device):
    """``coarse_steps``: the first steps train on ``ReferenceViews.halved`` (each camera at half its
    size, each target's 2x2 blocks averaged). A run whose every step is coarse gives the bytes of a
    run on views whose training cameras and targets are those halved ones; the held-out views stay
    full size."""
    import dataclasses

    import nanogs_warp.refinement.refine as refine_module

    reference = SplatSet.from_numpy(**_toy_scene(5, device), device=device)
    small = simplify(reference, count=15)
    config = RefineConfig(steps=6, size=64, reference_views=4, coarse_steps=6)
    views = refine_module.ReferenceViews(reference, config)
    coarse = refine_with_report(small, reference, config, views=views)[0].to_numpy()
    cameras, targets = views.halved()
    assert [(c.width, c.height) for c in cameras] == [(c.width // 2, c.height // 2) for c in views.cameras]
    standing_in = refine_module.ReferenceViews(reference, config)
    standing_in.render()
    standing_in.cameras, standing_in.targets = cameras, targets
    fine = refine_with_report(small, reference, dataclasses.replace(config, coarse_steps=0), views=standing_in)[0].to_numpy()
    for key in coarse:
        assert coarse[key].tobytes() == fine[key].tobytes(), key
    full = refine_with_report(small, reference, dataclasses.replace(config, coarse_steps=0), views=views)[0].to_numpy()
    assert not np.array_equal(full["means"], coarse["means"])
    with pytest.raises(InputError, match="coarse steps"):
        RefineConfig(steps=6, coarse_steps=7).validate()


def test_a_halved_camera_sees_the_blocks_of_the_full_one(device):
    """A half-size camera (half the focal lengths and principal point) puts a small splat where the
    full-size view's 2x2 blocks have it: the brightness-weighted centroids, in pixel indices,
    agree within a tenth of a half-size pixel (x' = (x - 0.5) / 2; a principal point (c - 0.5) / 2
    would be a quarter off)."""
    import nanogs_warp.refinement.refine as refine_module
    from nanogs_warp.eval.render import render_views_on_device

    arrays = random_splat_arrays(1, seed=4)
    arrays["means"] = np.array([[0.13, -0.07, 0.0]], np.float32)
    arrays["log_scales"] = np.full((1, 3), np.log(0.02), np.float32)
    arrays["opacities"] = np.array([3.0], np.float32)
    splat = SplatSet.from_numpy(**arrays, device=device)
    config = RefineConfig(steps=1, size=128, reference_views=1, coarse_steps=1)
    views = refine_module.ReferenceViews(splat, config)
    views.render()
    camera, half_camera = views.cameras[0], views.halved()[0][0]
    full, half = (render_views_on_device(splat, [c]).numpy()[0].sum(axis=2) for c in (camera, half_camera))

    def centroid(image):
        ys, xs = np.mgrid[: image.shape[0], : image.shape[1]]
        return np.array([(xs * image).sum(), (ys * image).sum()]) / image.sum()

    assert full.sum() > 0 and half.sum() > 0
    np.testing.assert_allclose(centroid(half), (centroid(full) - 0.5) / 2.0, atol=0.1)


def test_the_memory_check_counts_every_view_a_step_renders(monkeypatch):
    """A step's renders, gradients and loss maps are made for each of the views it renders together:
    ``check_memory`` asks for STEP_BYTES_PER_PIXEL a pixel of each."""
    import nanogs_warp.refinement.refine as refine_module

    needs = []
    monkeypatch.setattr(refine_module, "memory_short", lambda need, device: needs.append(need))
    for views in (1, 4):
        refine_module.check_memory(RefineConfig(size=64, views_per_step=views), 10, wp.get_device("cpu"))
    assert needs[1] - needs[0] == 3 * 64 * 64 * refine_module.STEP_BYTES_PER_PIXEL


def test_views_whose_blurred_terms_do_not_fit_refine_to_the_same_bytes(device, monkeypatch):
    """Reference views keep their targets' blurred terms (G*Y, G*Y^2) where their 24 bytes a pixel
    more fit the device; where they do not, each step blurs its own views' targets: the same bytes,
    coarse steps and held-out views included."""
    import nanogs_warp.refinement.refine as refine_module

    reference = SplatSet.from_numpy(**_toy_scene(7, device), device=device)
    small = simplify(reference, count=15)
    config = RefineConfig(steps=6, size=48, reference_views=4, coarse_steps=3)
    kept = refine_module.ReferenceViews(reference, config)
    refined, report = refine_with_report(small, reference, config, views=kept)
    assert kept.moments and kept.targets.moments is not None and kept.halved()[1].moments is not None
    short = refine_module.memory_short
    monkeypatch.setattr(refine_module, "memory_short", lambda need, device: 0 if need > 10**12 else short(need, device))
    monkeypatch.setattr(refine_module, "MOMENT_BYTES_PER_PIXEL", 10**12)
    unkept = refine_module.ReferenceViews(reference, config)
    again, report_again = refine_with_report(small, reference, config, views=unkept)
    assert not unkept.moments and unkept.targets.moments is None and unkept.halved()[1].moments is None
    for key, value in refined.to_numpy().items():
        assert value.tobytes() == again.to_numpy()[key].tobytes(), key
    assert (report.loss_before, report.loss_after, report.validation_after) == (
        report_again.loss_before, report_again.loss_after, report_again.validation_after)


@pytest.mark.parametrize("pool, views_per_step", [(1, 2), (2, 1), (5, 2), (40, 8)])
def test_each_step_trains_on_views_of_one_background(pool, views_per_step):
    """``step_views``: step s draws its views from those of background s mod 2 (view k is on
    ``view_background(k)``; a pool of one is all black), each background's views in permutations of
    their own: each of them is drawn once before any is drawn again. Seeded: the same views again,
    other ones for another seed."""
    import nanogs_warp.refinement.refine as refine_module

    steps = 30
    drawn = refine_module.step_views(pool, steps, views_per_step, seed=3)
    assert drawn == refine_module.step_views(pool, steps, views_per_step, seed=3)
    backgrounds = min(pool, len(refine_module.BACKGROUNDS))
    for step, chosen in enumerate(drawn):
        assert len(chosen) == views_per_step and all(k % backgrounds == step % backgrounds for k in chosen), (step, chosen)
    for b in range(backgrounds):
        members = list(range(b, pool, backgrounds))
        sequence = [k for step, chosen in enumerate(drawn) if step % backgrounds == b for k in chosen]
        for start in range(0, len(sequence) - len(members) + 1, len(members)):
            assert sorted(sequence[start : start + len(members)]) == members
    if pool > backgrounds:  # some background has views to order
        assert drawn != refine_module.step_views(pool, steps, views_per_step, seed=4)


def test_reference_views_are_rendered_on_black_and_white(device):
    """The training and held-out views of ``ReferenceViews``: view k is the original rendered on
    ``view_background(k)``, black and white in turn, bit for bit what the renderer gives alone."""
    import nanogs_warp.refinement.refine as refine_module
    from nanogs_warp.eval.render import render_views_on_device

    reference = SplatSet.from_numpy(**_toy_scene(9, device), device=device)
    views = refine_module.ReferenceViews(reference, RefineConfig(steps=8, size=40, reference_views=4))
    views.render()
    assert [tuple(refine_module.view_background(k)) for k in range(3)] == [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)]
    for cameras, targets in ((views.cameras, views.targets), (views.held_out, views.held_out_targets)):
        images = targets.images.numpy()
        for k, camera in enumerate(cameras):
            alone = render_views_on_device(reference, [camera], tuple(refine_module.view_background(k))).numpy()[0]
            shown = images[k][: camera.height, : camera.width]  # the view's own size, top left
            assert shown.tobytes() == alone.tobytes(), k
            # pixels the splats miss show the background
            assert (shown == float(k % 2)).all(axis=2).any(), k


def _one_colour_splats(opacity: float, colour: float, device) -> SplatSet:
    """Eight round splats of one opacity and grey colour on the corners of a cube."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    arrays = random_splat_arrays(8, seed=11)
    arrays["means"] = corners
    arrays["log_scales"] = np.full((8, 3), np.log(0.3), np.float32)
    arrays["opacities"] = np.full(8, np.log(opacity / (1.0 - opacity)), np.float32)
    arrays["features"] = np.full((8, 3), (colour - 0.5) / 0.28209479177387814, np.float32)
    return SplatSet.from_numpy(**arrays, device=device)


def test_a_fit_tells_a_splat_s_opacity_from_its_colour(device, monkeypatch):
    """On black a splat of opacity a and colour c shows a c G at every pixel (a G below the 0.99
    clamp), so a fit on black views alone sees only the product: from (0.9, 0.3) toward a
    reference's (0.5, 0.8) it raises both, and the opacity ends above where it started. On white the
    splat shows 1 - a G (1 - c) as well, and a fit on both backgrounds brings the opacity down toward
    0.5. The fit's backward takes the background from the rendered colour, so only the targets and
    the forward's background differ."""
    import nanogs_warp.refinement.refine as refine_module

    reference = _one_colour_splats(0.5, 0.8, device)
    start = _one_colour_splats(0.9, 0.3, device)
    config = RefineConfig(steps=40, size=48, reference_views=8, lr_means=0.0, lr_rotations=0.0, lr_log_scales=0.0,
                          lr_opacities=0.1, lr_features_dc=0.05)  # fmt: skip

    def opacity_after():
        out, report = refine_with_report(start, reference, config)
        assert report.kept_step > 0
        return float(np.mean(1.0 / (1.0 + np.exp(-out.to_numpy()["opacities"]))))

    both = opacity_after()
    monkeypatch.setattr(refine_module, "BACKGROUNDS", ((0.0, 0.0, 0.0),))
    black = opacity_after()
    assert black > 0.93 and both < 0.85, (black, both)
