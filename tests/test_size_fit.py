"""The size fit (``refinement/size_fit.py``): its kernels against float64, the factor it picks
for outputs made too large or too small on purpose, the outputs it leaves alone, and the command
line's report of it."""

import json
import math

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splat_arrays
from typer.testing import CliRunner

from nanogs_warp import SimplifyConfig, simplify
from nanogs_warp.cli.app import app
from nanogs_warp.io.ply import save_ply
from nanogs_warp.kernels import splat_size as kernels
from nanogs_warp.pipeline import simplify as simplify_merged
from nanogs_warp.refinement import size_fit
from nanogs_warp.splats import SplatSet


def blob(n: int, seed: int, device, log_scale=(-3.0, -2.0)) -> SplatSet:
    """A ball of opaque-ish splats of a few sizes: their renders change visibly with their size."""
    arrays = random_splat_arrays(n, sh_degree=1, seed=seed)
    rng = np.random.default_rng(seed + 1)
    arrays["log_scales"] = rng.uniform(*log_scale, size=(n, 3)).astype(np.float32)
    arrays["opacities"] = rng.uniform(0.0, 3.0, size=n).astype(np.float32)
    return SplatSet.from_numpy(**arrays, device=device)


def test_resized_scales_every_axis_by_the_factor(device, rng):
    """log-scales plus log(factor) in float32, against a float64 reference; nothing else changes."""
    arrays = random_splat_arrays(1000, sh_degree=1, seed=4)
    splats = SplatSet.from_numpy(**arrays, device=device)
    factor = float(rng.uniform(0.5, 2.0))
    poisoned = wp.full(splats.count, wp.vec3(float("nan")), dtype=wp.vec3, device=splats.device)
    wp.launch(kernels.resized_log_scales, splats.count, inputs=[splats.log_scales, math.log(factor)], outputs=[poisoned],
              device=splats.device)  # fmt: skip
    expected = arrays["log_scales"].astype(np.float64) + np.float64(np.float32(math.log(factor)))
    got = poisoned.numpy()
    assert np.isfinite(got).all()
    out = size_fit.resized(splats, factor)
    np.testing.assert_array_equal(got, out.log_scales.numpy())
    np.testing.assert_allclose(got, expected, rtol=0, atol=4e-7 * np.abs(expected).max())
    np.testing.assert_array_equal(got, (arrays["log_scales"] + np.float32(math.log(factor))).astype(np.float32))
    for name in ("means", "rotations", "opacities", "features"):
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(splats, name).numpy())
    assert size_fit.resized(splats, 1.0) is splats


def test_squared_error_rows_and_psnr_against_float64(device, rng):
    """The per-row squared error of two clamped images (``squared_error_rows``, rows poisoned first)
    and the fit's mean PSNR over views, against numpy in float64; a view both render black in (and
    one rendered identically) counts at the 1e-12 floor instead of being infinite."""
    views, height, width = 3, 17, 23
    reference = rng.uniform(-0.3, 1.3, size=(views, height, width, 3)).astype(np.float32)
    test = (reference + rng.normal(0.0, 0.05, size=reference.shape)).astype(np.float32)
    test[2] = reference[2]  # identical view: error 0, at the floor
    rows = wp.full((views, height), float("nan"), dtype=wp.float64, device=device)
    a, b = (wp.array(x, dtype=wp.float32, device=device) for x in (reference, test))
    wp.launch(kernels.squared_error_rows, (views, height), inputs=[a, b], outputs=[rows], device=device)
    diff = np.clip(test, 0, 1).astype(np.float64) - np.clip(reference, 0, 1).astype(np.float64)
    expected_rows = (diff**2).sum(axis=(2, 3))
    got = rows.numpy()
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, expected_rows, rtol=1e-12, atol=0)
    mse = np.maximum((diff**2).mean(axis=(1, 2, 3)), 1e-12)
    assert size_fit._psnr(a, b) == pytest.approx(float(np.mean(-10.0 * np.log10(mse))), rel=1e-12)
    assert mse[2] == 1e-12 and np.isfinite(size_fit._psnr(a, b))


@pytest.mark.parametrize("steps", [3, -2])
def test_the_fit_undoes_a_wrong_size(device, steps):
    """An output that is the input with every axis times STEP^steps is fitted back by STEP^-steps
    (the fit may look at outputs of any size here)."""
    reference = blob(600, 11, device)
    wrong = size_fit.resized(reference, size_fit.STEP**steps)
    fit = size_fit.SizeFit(reference)
    fitted = fit(wrong)
    assert fit.factors[wrong.count] == pytest.approx(size_fit.STEP**-steps)
    np.testing.assert_allclose(fitted.log_scales.numpy(), reference.log_scales.numpy(), atol=2e-6)


def test_the_fit_takes_the_factor_its_rule_names(device):
    """``fitted`` (which stops rendering early) chooses what its rule says of ``view_gains`` (which
    renders every factor): outward from 1 while the smaller gain rises, the best positive one."""
    reference = blob(600, 14, device)
    fit = size_fit.SizeFit(reference)
    # the input grown (the fit shrinks it back), a sparser set (grown), one of larger splats (kept)
    for output in (size_fit.resized(reference, size_fit.STEP**3), blob(300, 15, device), blob(300, 16, device, (-2.6, -1.6))):
        ks = range(-size_fit.MOST_STEPS, size_fit.MOST_STEPS + 1)
        gains = dict(zip(ks, fit.view_gains(output, [size_fit.STEP**k for k in ks])))
        assert gains[0] == (0.0, 0.0)
        best, best_gain = 0, 0.0
        for direction in (1, -1):
            k, previous = direction, 0.0
            while abs(k) <= size_fit.MOST_STEPS and min(gains[k]) > previous:
                if min(gains[k]) > best_gain:
                    best, best_gain = k, min(gains[k])
                k, previous = k + direction, min(gains[k])
        assert fit.fitted(output)[1] == pytest.approx(size_fit.STEP**best, rel=1e-12)


def test_a_right_size_is_kept(device):
    reference = blob(600, 12, device)
    fit = size_fit.SizeFit(reference)
    same = SplatSet.from_numpy(**reference.to_numpy(), device=device)  # the input's values, another set: fitted
    assert fit(same) is same and fit.factors[reference.count] == 1.0
    assert fit._images is not None  # it was rendered and compared


def test_the_input_itself_is_returned_unrendered(device, monkeypatch):
    """A budget of every splat (nothing pruned or merged) yields the input itself, which no fit can
    improve: neither fit renders anything for it, whatever the scene's size."""

    def no_render(*args, **kwargs):
        raise AssertionError("rendered")

    monkeypatch.setattr(size_fit, "_render", no_render)
    monkeypatch.setattr(size_fit.SizeFit, "_fit_geometry", no_render)
    for n in (1, 2, 600):
        reference = blob(n, 20 + n, device)
        fit = size_fit.SizeFit(reference, geometry=True)
        assert fit(reference) is reference and fit.factors[n] == 1.0 and n not in fit.geometry_kept
        out = simplify(reference, count=n)  # (a set of its own, the input's values)
        for name, values in reference.to_numpy().items():
            np.testing.assert_array_equal(out.to_numpy()[name], values)


def test_every_output_is_fitted_for_size_and_far_scenes_are_left_alone(device):
    """The size fit takes every output, the geometry fit (when asked for) those of at most 1 %."""
    reference = blob(1000, 13, device)
    fit = size_fit.SizeFit(reference)
    assert fit.applies(1000) and fit.applies(1)
    assert not fit.applies_geometry(10)  # no geometry fit asked for
    both = size_fit.SizeFit(reference, geometry=True)
    assert both.applies_geometry(10) and not both.applies_geometry(11)
    too_long = size_fit.STEP**3
    shrunk = fit(size_fit.resized(reference, too_long))  # every axis 2^(3/12) too long: taken back
    assert fit.factors[1000] == pytest.approx(1 / too_long, rel=1e-9)
    np.testing.assert_allclose(shrunk.log_scales.numpy(), reference.log_scales.numpy(), atol=1e-5)
    # a scene far from the origin for its size is rendered recentred by eval: not fitted
    arrays = random_splat_arrays(1000, seed=14)
    arrays["means"] = (arrays["means"].astype(np.float64) + 1e9).astype(np.float32)
    far = SplatSet.from_numpy(**arrays, device=device)
    small = size_fit.resized(simplify_merged(far, count=5), 1.5)
    assert size_fit.SizeFit(far)(small) is small


def test_huge_splats_are_not_fitted(device, monkeypatch):
    """Splats that each cover every tile of a view would make the fit's renders take as long as
    N x tiles entries: past ENTRIES_PER_SPLAT a splat the output is left as it is."""
    reference = blob(500, 17, device, log_scale=(2.0, 3.0))
    wrong = size_fit.resized(reference, size_fit.STEP**2)
    monkeypatch.setattr(size_fit, "MIN_ENTRIES", 0)
    assert size_fit.SizeFit(reference)(wrong) is wrong
    monkeypatch.setattr(size_fit, "MIN_ENTRIES", 1 << 22)  # the same scene within the limit: fitted
    fit = size_fit.SizeFit(reference)
    fit(wrong)
    assert fit.factors[500] < 1


def test_simplify_fits_by_default_and_only_there(device):
    """``nanogs_warp.simplify`` is the merge, then the size fit of every output (here the size fit
    alone; the geometry fit of those at or below 1 % after it: tests/test_geometry_fit.py; the
    colour fit of the others: tests/test_colour_fit.py); the paper and fast presets and
    fit_size=False are the merge alone."""
    splats = blob(3000, 15, device, log_scale=(-4.0, -2.5))
    fitted = simplify(splats, ratio=[0.2, 0.1, 0.01], config=SimplifyConfig(fit_geometry=False, fit_colour=False))
    merged = simplify_merged(splats, ratio=[0.2, 0.1, 0.01])
    for f, m in zip(fitted, merged):
        ratio = np.exp(f.log_scales.numpy().astype(np.float64) - m.log_scales.numpy())
        assert np.allclose(ratio, ratio.flat[0], rtol=1e-5)  # one factor for every axis of every splat
        assert any(size_fit.STEP**k == pytest.approx(ratio.flat[0], rel=1e-5) for k in range(-size_fit.MOST_STEPS, size_fit.MOST_STEPS + 1))
        for name in ("means", "rotations", "opacities", "features"):
            np.testing.assert_array_equal(getattr(f, name).numpy(), getattr(m, name).numpy())
    unfitted = simplify(splats, ratio=0.01, config=SimplifyConfig(fit_size=False, fit_geometry=False, fit_colour=False))
    np.testing.assert_array_equal(unfitted.log_scales.numpy(), simplify_merged(splats, ratio=0.01).log_scales.numpy())
    for preset in (SimplifyConfig.paper(), SimplifyConfig.preset("fast")):
        assert not preset.fit_size and not preset.fit_geometry and not preset.fit_colour


def test_cli_reports_the_factor(tmp_path):
    splats = blob(3000, 16, "cpu", log_scale=(-4.0, -2.5))
    source = tmp_path / "blob.ply"
    save_ply(splats, source)
    runner = CliRunner()
    result = runner.invoke(app, ["simplify", str(source), "-o", str(tmp_path / "o.ply"), "--ratio", "0.2,0.1,0.01", "--device", "cpu", "--json"])
    assert result.exit_code == 0, result.output
    outputs = json.loads(result.stdout)["outputs"]
    assert all(output["size_factor"] > 0 for output in outputs)
    assert "geometry_fit" not in outputs[0] and "geometry_fit" not in outputs[1] and isinstance(outputs[2]["geometry_fit"], bool)
    settings = json.loads(result.stdout)["settings"]
    assert settings["fit_size"] is True and settings["fit_geometry"] is True and settings["fit_colour"] is True
    for flags, keys in ((["--no-fit-size"], {"geometry_fit"}), (["--no-fit-geometry"], {"size_factor"}),
                        (["--no-fit-size", "--no-fit-geometry"], set())):  # fmt: skip
        result = runner.invoke(app, ["simplify", str(source), "-o", str(tmp_path / "n.ply"), "--ratio", "0.01", "--device", "cpu",
                                     "--json", "-w", *flags])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert keys == {"size_factor", "geometry_fit"} & set(json.loads(result.stdout)["outputs"][0])
