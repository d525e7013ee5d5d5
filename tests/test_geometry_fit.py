"""The geometry fit (``refinement/geometry_fit.py``): a short refinement of the small outputs' centres,
rotations and scales toward renders of the input, kept only where the held-out views render better.
Its rasteriser, loss and optimiser have their own float64 references (tests/test_render_grad.py,
tests/test_image_loss.py, tests/test_refine.py); here, what the fit may change and when it keeps it."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_size_fit import blob

from nanogs_warp import SimplifyConfig, SplatSet, simplify
from nanogs_warp.refinement import geometry_fit, size_fit
from nanogs_warp.refinement.refine import refine_with_report

GEOMETRY = ("means", "rotations", "log_scales")
APPEARANCE = ("opacities", "features", "extras", "integer_extras")


def test_the_default_fits_the_small_outputs_geometry_and_nothing_else(device):
    """Against the size fit alone: the 10 % output unchanged, the 1 % and 0.5 % ones with other
    centres, rotations and scales, their opacities and colours the same bits (the colour fit, which
    follows and may keep new colours and opacities in either run, left out of both)."""
    splats = blob(3000, 15, device, log_scale=(-4.0, -2.5))
    fitted = simplify(splats, ratio=[0.1, 0.01, 0.005], config=SimplifyConfig(fit_colour=False))
    sized = simplify(splats, ratio=[0.1, 0.01, 0.005], config=SimplifyConfig(fit_geometry=False, fit_colour=False))
    for name in GEOMETRY + APPEARANCE:
        np.testing.assert_array_equal(getattr(fitted[0], name).numpy(), getattr(sized[0], name).numpy())
    for f, s in zip(fitted[1:], sized[1:]):
        assert any(not np.array_equal(getattr(f, name).numpy(), getattr(s, name).numpy()) for name in GEOMETRY)
        for name in APPEARANCE:
            np.testing.assert_array_equal(getattr(f, name).numpy(), getattr(s, name).numpy())
        assert np.isfinite(f.means.numpy()).all() and np.isfinite(f.log_scales.numpy()).all()
    again = simplify(splats, ratio=[0.1, 0.01, 0.005], config=SimplifyConfig(fit_colour=False))  # the same bytes every run
    for a, b in zip(fitted, again):
        for name in GEOMETRY:
            assert getattr(a, name).numpy().tobytes() == getattr(b, name).numpy().tobytes()


def test_an_output_made_too_large_is_shrunk_back_and_kept(device):
    """The input itself with every axis 1.65 times too long: the fit's held-out loss falls, so the
    fitted geometry is kept, and the scales come back toward the input's."""
    reference = blob(400, 21, device, log_scale=(-3.0, -2.0))
    grown = size_fit.resized(reference.clone(), 1.65)
    fit = geometry_fit.GeometryFit(reference)
    out, kept = fit(grown)
    assert kept
    truth = reference.log_scales.numpy().astype(np.float64)
    before = np.abs(grown.log_scales.numpy() - truth).mean()
    after = np.abs(out.log_scales.numpy() - truth).mean()
    assert after < 0.8 * before
    for name in APPEARANCE:
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(grown, name).numpy())


def test_nothing_better_to_find_keeps_the_output_as_it_was(device):
    """The input fitted against itself renders every view exactly: nothing lowers the held-out loss,
    so the output comes back as it was, bit for bit."""
    reference = blob(300, 22, device)
    fit = geometry_fit.GeometryFit(reference)
    out, kept = fit(reference.clone())
    assert not kept
    for name in GEOMETRY + APPEARANCE:
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(reference, name).numpy())


def test_the_fit_is_refinement_with_appearance_frozen(device):
    """``geometry_config`` is ``refine``'s own loop: the same bytes as refine_with_report with the
    opacity and colour learning rates at 0 and one checkpoint."""
    reference = blob(400, 23, device, log_scale=(-3.0, -2.0))
    output = simplify(reference, ratio=0.05, config=SimplifyConfig(fit_size=False, fit_geometry=False))
    fit = geometry_fit.GeometryFit(reference)
    fitted, kept = fit(output)
    config = geometry_fit.geometry_config()
    assert (config.steps, config.reference_views, config.lr_opacities, config.lr_features_dc, config.lr_features_rest) == (
        geometry_fit.STEPS, geometry_fit.VIEWS, 0.0, 0.0, 0.0)
    direct, report = refine_with_report(output, reference, config, checkpoints=(1.0,), training_loss=False,
                                        views=geometry_fit.ReferenceViews(reference, config))
    assert report.kept_step in (0, config.steps) and kept == (report.kept_step > 0)
    for name in GEOMETRY + APPEARANCE:
        assert getattr(fitted, name).numpy().tobytes() == getattr(direct, name).numpy().tobytes()


def test_the_smallest_outputs_get_the_long_fit_on_the_same_views(device, monkeypatch):
    """Outputs of at most target_count(N, LONG_BELOW) splats are fitted by ``geometry_config(long=
    True)`` (LONG_STEPS steps of LONG_VIEWS views, the first LONG_COARSE on the views at half size, the centres' rate
    times LONG_MEANS_RATE, the rotations' and scales' times LONG_RATE), one more splat by the short
    fit (every step at full size), both on the one set of the input's views. (LONG_STEPS and
    LONG_COARSE cut to 45 and 30 here: the routing, not the length.)"""
    monkeypatch.setattr(geometry_fit, "LONG_STEPS", 45)
    monkeypatch.setattr(geometry_fit, "LONG_COARSE", 30)
    short, long = geometry_fit.geometry_config(), geometry_fit.geometry_config(long=True)
    assert (long.steps, long.coarse_steps, long.reference_views, long.size) == (45, 30, short.reference_views, short.size)
    assert short.coarse_steps == 0 and (short.views_per_step, long.views_per_step) == (geometry_fit.STEP_VIEWS, geometry_fit.LONG_VIEWS)
    for name in ("lr_rotations", "lr_log_scales"):
        assert getattr(long, name) == geometry_fit.LONG_RATE * getattr(short, name)
    assert long.lr_means == geometry_fit.LONG_MEANS_RATE * short.lr_means
    assert (long.lr_opacities, long.lr_features_dc, long.lr_features_rest) == (0.0, 0.0, 0.0)

    reference = blob(4000, 24, device, log_scale=(-3.0, -2.0))
    fit = geometry_fit.GeometryFit(reference)
    assert fit.longest == 4  # ceil(0.001 * 4000)
    grown = size_fit.resized(reference.clone(), 1.65)
    for count, config in ((4, long), (5, short)):
        output = SplatSet.from_numpy(**{k: v[:count] for k, v in grown.to_numpy().items()}, device=device)
        fitted, kept = fit(output)
        direct, report = refine_with_report(output, reference, config, checkpoints=(1.0,), training_loss=False,
                                            views=geometry_fit.ReferenceViews(reference, short))
        assert kept == (report.kept_step > 0)
        for name in GEOMETRY + APPEARANCE:
            assert getattr(fitted, name).numpy().tobytes() == getattr(direct, name).numpy().tobytes()
    assert fit.views.serves(reference, long, device) and not fit.views.serves(reference, dataclasses.replace(long, size=128), device)
