"""The colour fit (``refinement/colour_fit.py``): the pipeline's marks of the rows merges made, what
the fit may change (the merged rows' colours, and their opacities in outputs whose geometry is
fitted; nothing else), when it is kept (the size fit's coarse and fine views both render better),
and which outputs it applies to. Its rasteriser, loss and
optimiser have their own float64 references (tests/test_render_grad.py, tests/test_image_loss.py,
tests/test_refine.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splat_arrays
from test_size_fit import blob
from typer.testing import CliRunner

from nanogs_warp import SimplifyConfig, SplatSet, simplify
from nanogs_warp.cli.app import app
from nanogs_warp.io.ply import save_ply
from nanogs_warp.pipeline import simplify_progressively
from nanogs_warp.refinement import colour_fit, size_fit

UNCHANGED = ("means", "rotations", "log_scales", "opacities", "extras", "integer_extras")


def rows_of(splats: SplatSet) -> np.ndarray:
    """Each row's every value as bytes (one void per row), to find rows among another set's."""
    arrays = splats.to_numpy()
    parts = [np.ascontiguousarray(arrays[k].reshape(splats.count, -1)).view(np.uint8) for k in sorted(arrays)]
    return np.ascontiguousarray(np.concatenate(parts, axis=1)).view(np.dtype((np.void, sum(p.shape[1] for p in parts)))).ravel()


def test_the_marks_are_the_rows_merges_made(device):
    """Every budget's marks: 0 exactly on the rows that are one of the input's rows, bit for bit,
    and 1 on the others (a merge's splat, which random inputs never repeat)."""
    arrays = random_splat_arrays(3000, sh_degree=1, seed=31)
    splats = SplatSet.from_numpy(**arrays, device=device)
    seen = {}

    def finish(merged, marks):
        seen[merged.count] = None if marks is None else marks.numpy().copy()
        return merged

    outputs = dict(simplify_progressively(splats, [3000, 1500, 300, 20], SimplifyConfig(), finish=finish))
    assert seen[3000] is None  # nothing merged
    inputs = rows_of(splats)
    for count in (1500, 300, 20):
        marks = seen[count]
        assert marks.shape == (count,) and set(np.unique(marks)) <= {0, 1}
        np.testing.assert_array_equal(marks, (~np.isin(rows_of(outputs[count]), inputs)).astype(np.int32))
        assert marks.sum() > 0
    assert seen[1500].sum() < 1500 and seen[20].sum() == 20


def merged_with_marks(reference: SplatSet, count: int) -> tuple[SplatSet, wp.array]:
    """The merge of ``reference`` down to ``count`` splats (no fit) and the pipeline's marks of it."""
    got = {}

    def finish(out, marks):
        got["out"], got["marks"] = out, marks
        return out

    list(simplify_progressively(reference, [count], SimplifyConfig(fit_size=False), finish=finish))
    return got["out"], got["marks"]


def recoloured(splats: SplatSet, marks: np.ndarray, shift: float) -> SplatSet:
    """``splats`` with every marked row's DC coefficients moved by ``shift`` (a wrong merged colour)."""
    arrays = splats.to_numpy()
    arrays["features"][marks == 1, :3] += np.float32(shift)
    return SplatSet.from_numpy(**arrays, device=splats.device)


def test_wrong_merged_colours_are_fitted_back_and_kept(device):
    """An output whose merged splats' colours are too dark: the fit brightens them, gains in the size
    fit's coarse and fine views, and is kept; the rows no merge made keep their colours, and
    nothing but colours changes."""
    reference = blob(2000, 32, device, log_scale=(-3.5, -2.5))
    merged, marks = merged_with_marks(reference, 1000)
    host_marks = marks.numpy()
    assert 0 < host_marks.sum() < 1000
    dark = recoloured(merged, host_marks, -0.6)
    fit = size_fit.SizeFit(reference, size=False, colour=True)
    out = fit(dark, marks)
    assert fit.colour_kept[1000]
    for name in UNCHANGED:
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(dark, name).numpy(), err_msg=name)
    before, after = dark.features.numpy(), out.features.numpy()
    np.testing.assert_array_equal(after[host_marks == 0], before[host_marks == 0])
    assert (after[host_marks == 1, :3] - before[host_marks == 1, :3]).mean() > 0.05  # brighter
    coarse, fine = fit._scores(out, fit._scores(dark))
    assert coarse > 0 and fine > 0


@pytest.mark.parametrize("per_pixel", [None, True])
def test_the_fit_back_propagates_colours_alone_to_the_same_bytes(device, monkeypatch, per_pixel):
    """The fit's backward computes the colours' gradients alone (``colours_only``) from the forward's
    kept weights (the CPU's, and with the per-pixel backward a GPU's) and Adam steps only the
    colours; its output is the bytes of the same fit through the whole backward and Adam on every
    group (at rate 0)."""
    from nanogs_warp.refinement import refine
    from nanogs_warp.refinement.render_grad import GradRasteriser

    if per_pixel:
        monkeypatch.setattr(refine, "GradRasteriser", lambda splats: GradRasteriser(splats, per_pixel=True))

    reference = blob(1500, 34, device, log_scale=(-3.5, -2.5))
    merged, marks = merged_with_marks(reference, 700)
    dark = recoloured(merged, marks.numpy(), -0.4)
    backward, asked = GradRasteriser.backward, []

    def recorded(self, image, grad_image, grads, colours_only=False):
        asked.append((colours_only, self.weights_kept))
        backward(self, image, grad_image, grads, colours_only)

    monkeypatch.setattr(GradRasteriser, "backward", recorded)
    fit = size_fit.SizeFit(reference, size=False, colour=True)
    alone = fit(dark, marks)
    assert fit.colour_kept[700] and set(asked) == {(True, True)}

    def whole(self, image, grad_image, grads, colours_only=False):
        backward(self, image, grad_image, grads, False)

    monkeypatch.setattr(GradRasteriser, "backward", whole)
    init = refine._Refiner.__init__

    def every_group(self, *args):
        init(self, *args)
        self.groups = self._groups()

    monkeypatch.setattr(refine._Refiner, "__init__", every_group)
    fit = size_fit.SizeFit(reference, size=False, colour=True)
    out = fit(dark, marks)
    for name in ("features", *UNCHANGED):
        assert getattr(out, name).numpy().tobytes() == getattr(alone, name).numpy().tobytes(), name


def test_with_opacities_the_merged_rows_opacities_are_fitted_too(device):
    """``fitted_colours(..., opacities=True)``: an output whose merged splats are too faint and too
    dark comes back with those rows more opaque and brighter; every row no merge made keeps every
    value, and no merged row changes but in its colour and opacity. Without ``opacities`` the same
    fit leaves every opacity as it was."""
    from nanogs_warp.refinement.geometry_fit import GeometryFit

    reference = blob(2000, 36, device, log_scale=(-3.5, -2.5))
    merged, marks = merged_with_marks(reference, 1000)
    host_marks = marks.numpy()
    arrays = recoloured(merged, host_marks, -0.4).to_numpy()
    arrays["opacities"][host_marks == 1] -= np.float32(2.0)  # too faint
    wrong = SplatSet.from_numpy(**arrays, device=device)
    views = GeometryFit(reference).views
    out = colour_fit.fitted_colours(wrong, marks, reference, views, opacities=True)
    assert out is not None
    for name in ("means", "rotations", "log_scales", "extras", "integer_extras"):
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(wrong, name).numpy(), err_msg=name)
    for name in ("features", "opacities"):
        before, after = getattr(wrong, name).numpy(), getattr(out, name).numpy()
        np.testing.assert_array_equal(after[host_marks == 0], before[host_marks == 0], err_msg=name)
    raised = out.opacities.numpy()[host_marks == 1] - wrong.opacities.numpy()[host_marks == 1]
    assert raised.mean() > 0.05 and np.isfinite(raised).all()
    plain = colour_fit.fitted_colours(wrong, marks, reference, views)
    assert plain.opacities.numpy().tobytes() == wrong.opacities.numpy().tobytes()


def test_the_opacities_are_fitted_where_the_geometry_is(device, monkeypatch):
    """``SizeFit`` asks the colour fit for the opacities in the outputs its geometry fit applies to (at
    most 1 % of the input, with ``geometry``), and where that fit is not kept for the colours alone;
    elsewhere for the colours alone, once."""
    reference = blob(1000, 37, device)
    asked = []

    def recorded(splats, merged, reference, views, seed=0, opacities=False):
        asked.append((splats.count, opacities))
        return None  # not kept

    monkeypatch.setattr(colour_fit, "fitted_colours", recorded)
    marks = wp.ones(1000, dtype=wp.int32, device=device)
    for geometry in (True, False):
        fit = size_fit.SizeFit(reference, size=False, colour=True, geometry=geometry)
        for count in (100, 11, 10, 2):
            small = _first_rows(reference, count)
            assert fit._fit_colour(small, marks[:count]) is small and fit.colour_kept[count] is False
        both = [(10, True), (10, False), (2, True), (2, False)] if geometry else [(10, False), (2, False)]
        assert asked == [(100, False), (11, False), *both], geometry
        asked.clear()


def _first_rows(splats: SplatSet, count: int) -> SplatSet:
    arrays = {k: v[:count] for k, v in splats.to_numpy().items()}
    return SplatSet.from_numpy(**arrays, device=splats.device)


def test_a_fit_that_loses_in_either_view_set_is_not_kept(device, monkeypatch):
    """The size fit's rule: a fitted output that renders one of the two view sets worse (here the
    scores say so) is set aside, and the output comes back as it was."""
    reference = blob(1200, 33, device, log_scale=(-3.5, -2.5))
    merged, marks = merged_with_marks(reference, 600)
    dark = recoloured(merged, marks.numpy(), -0.6)
    scores = size_fit.SizeFit._scores

    def fine_views_worse(self, splats, base=None, floor=-np.inf):
        got = scores(self, splats, base, floor)
        return got if base is None else (got[0], -0.01)

    monkeypatch.setattr(size_fit.SizeFit, "_scores", fine_views_worse)
    fit = size_fit.SizeFit(reference, size=False, colour=True)
    assert fit(dark, marks) is dark and fit.colour_kept[600] is False


def test_which_outputs_get_the_colour_fit(device, monkeypatch):
    """Every output above 0.1 % of the input (after the geometry fit of those of at most 1 %) when the
    configuration asks for it, none without marks (nothing merged); the presets that fit nothing fit
    no colour."""
    reference = blob(1000, 34, device)
    fit = size_fit.SizeFit(reference, colour=True, geometry=True)
    assert fit.applies_colour(1000) and fit.applies_colour(11) and fit.applies_colour(10) and fit.applies_colour(2)
    assert not fit.applies_colour(1) and not fit.applies_colour(1001)
    assert not size_fit.SizeFit(reference).applies_colour(500)
    for preset in ("fast", "paper"):
        assert not SimplifyConfig.preset(preset).fit_colour
    assert SimplifyConfig().fit_colour

    def no_fit(*args, **kwargs):
        raise AssertionError("fitted")

    monkeypatch.setattr(colour_fit, "refine_with_report", no_fit)
    unmerged = reference.clone()
    assert fit(unmerged, None) is unmerged and fit.colour_kept[1000] is False
    # a scene far from the origin for its size is rendered recentred by eval: not fitted
    arrays = random_splat_arrays(1000, seed=35)
    arrays["means"] = (arrays["means"].astype(np.float64) + 1e9).astype(np.float32)
    far = SplatSet.from_numpy(**arrays, device=device)
    small = far.clone()
    marks = wp.ones(1000, dtype=wp.int32, device=device)
    far_fit = size_fit.SizeFit(far, size=False, colour=True)
    assert far_fit(small, marks) is small and far_fit.colour_kept[1000] is False


def saturated_blob(n: int, seed: int, device) -> SplatSet:
    """A ball of nearly opaque splats, each channel of each splat's colour near 0 or near 1: merges
    average colours that the input shows apart, so that a colour fit gains on black and on white
    alike (on a ball of random mid colours and opacities, what the merge loses at 1 % is coverage, and
    its colours then fit the two backgrounds the opposite way)."""
    arrays = random_splat_arrays(n, sh_degree=1, seed=seed)
    rng = np.random.default_rng(seed + 1)
    arrays["log_scales"] = rng.uniform(-4.0, -2.5, size=(n, 3)).astype(np.float32)
    arrays["opacities"] = rng.uniform(2.0, 5.0, size=n).astype(np.float32)
    arrays["features"][:, 3:] *= 0.1
    arrays["features"][:, :3] = rng.choice([-1.7, 1.7], size=(n, 3))
    return SplatSet.from_numpy(**arrays, device=device)


def test_the_default_fits_the_colours_of_every_output_above_a_thousandth(device):
    """Against the default without the colour fit: the geometry-fitted 1 % output differs in colours
    (and opacities, where they were fitted with them) alone (here its fit is kept), the 0.1 % one is
    the same bytes; the same bytes every run. (The 10 % outputs: the tests above.)"""
    splats = saturated_blob(3000, 15, device)
    ratios = [0.01, 0.001]
    fitted = simplify(splats, ratio=ratios)
    plain = simplify(splats, ratio=ratios, config=SimplifyConfig(fit_colour=False))
    for f, p in zip(fitted, plain):
        for name in UNCHANGED:
            if name != "opacities":
                np.testing.assert_array_equal(getattr(f, name).numpy(), getattr(p, name).numpy(), err_msg=name)
    assert not np.array_equal(fitted[0].features.numpy(), plain[0].features.numpy())
    for name in ("features", "opacities"):
        assert getattr(fitted[1], name).numpy().tobytes() == getattr(plain[1], name).numpy().tobytes(), name
    again = simplify(splats, ratio=ratios)
    for f, a in zip(fitted, again):
        assert a.features.numpy().tobytes() == f.features.numpy().tobytes()


def test_the_command_reports_the_colour_fit(tmp_path):
    """``simplify --json`` says for each output above 0.1 % whether its colour fit was kept, and
    ``--no-fit-colour`` leaves the key out."""
    scene = tmp_path / "scene.ply"
    save_ply(blob(3000, 15, wp.get_device("cpu"), log_scale=(-4.0, -2.5)), scene)
    runner = CliRunner()
    result = runner.invoke(app, ["simplify", str(scene), "-o", str(tmp_path / "out.ply"), "--ratio", "0.1,0.01", "--device", "cpu", "--json"])
    assert result.exit_code == 0, result.output
    outputs = json.loads(result.stdout)["outputs"]
    assert all(isinstance(output["colour_fit"], bool) for output in outputs)
    result = runner.invoke(app, ["simplify", str(scene), "-o", str(tmp_path / "off.ply"), "--ratio", "0.1", "--device", "cpu", "--json",
                                 "--no-fit-colour"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "colour_fit" not in json.loads(result.stdout)["outputs"][0]
