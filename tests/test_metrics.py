"""Image metrics against hand computations and scikit-image; evaluation, PNG output and the eval CLI."""

import json
import math
import struct
import zlib

import numpy as np
import pytest
import skimage.metrics as skimage_metrics
import typer
from typer.testing import CliRunner

from nanogs_warp.cli.eval import eval_command, parse_background
from nanogs_warp.errors import InputError
from nanogs_warp.eval import metrics
from nanogs_warp.eval.cameras import orbit_cameras
from nanogs_warp.eval.evaluate import IDENTICAL_VIEW_DB, compare_images, evaluate, format_table, write_images, write_png
from nanogs_warp.io import ply
from nanogs_warp.splats import SplatSet


def test_psnr_by_hand():
    a = np.zeros((4, 5, 3))
    b = a.copy()
    b[0, 0, 0] = 0.5  # MSE = 0.25 / 60
    assert metrics.psnr(a, b) == pytest.approx(10 * math.log10(60 / 0.25))
    assert metrics.psnr(a, a) == math.inf
    with pytest.raises(ValueError, match="shape"):
        metrics.psnr(a, b[:3])


def skimage_ssim(a, b):
    channel_axis = -1 if a.ndim == 3 else None
    return skimage_metrics.structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=channel_axis
    )


@pytest.mark.parametrize("shape", [(48, 64, 3), (11, 17, 3), (30, 25)])
@pytest.mark.parametrize("noise", [0.01, 0.2])
def test_ssim_equals_scikit_image(rng, shape, noise):
    a = rng.random(shape)
    a = 0.5 * a + 0.5 * np.roll(a, 1, axis=0)  # some structure
    b = np.clip(a + rng.normal(0, noise, shape), 0, 1)
    assert metrics.ssim(a, b) == pytest.approx(skimage_ssim(a, b), abs=1e-12)


def test_ssim_of_flat_and_identical_images(rng):
    flat = np.full((20, 20, 3), 0.3)
    assert metrics.ssim(flat, flat) == pytest.approx(1.0)
    assert metrics.ssim(flat, flat + 0.1) == pytest.approx(skimage_ssim(flat, flat + 0.1), abs=1e-12)
    image = rng.random((16, 16, 3)).astype(np.float32)
    assert metrics.ssim(image, image) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="at least 11"):
        metrics.ssim(image[:10], image[:10])


def test_foreground_rule_psnr_and_colour_shift():
    background = (0.0, 0.0, 1.0)
    reference = np.broadcast_to(np.array(background), (4, 4, 3)).copy()
    reference[0, :2] = [0.5, 0.5, 0.5]  # two foreground pixels
    reference[1, 0] = [0.0, 0.0, 1.0 - 0.5 / 510]  # within tolerance: background
    test = reference.copy()
    test[0, 0] += [0.1, -0.1, 0.0]
    test[3, 3] = [1.0, 1.0, 1.0]  # outside the foreground: ignored by both
    mask = metrics.foreground_mask(reference, background)
    assert mask.sum() == 2 and mask[0, :2].all()
    mse = (0.1**2 + 0.1**2) / 6  # 2 pixels x 3 channels
    assert metrics.foreground_psnr(reference, test, background) == pytest.approx(10 * math.log10(1 / mse))
    np.testing.assert_allclose(metrics.colour_shift(reference, test, background), [0.05, -0.05, 0.0])
    empty = np.broadcast_to(np.array(background), (4, 4, 3))
    assert math.isnan(metrics.foreground_psnr(empty, test, background))
    assert np.isnan(metrics.colour_shift(empty, test, background)).all()


def small_scene(rng, n, device="cpu"):
    features = np.concatenate([rng.normal(0, 1, (n, 3)), rng.normal(0, 0.2, (n, 9))], axis=1)
    return SplatSet.from_numpy(
        rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(-2.0, 0.3, (n, 3)), rng.normal(1, 1, n), features,
        device=device,
    )  # fmt: skip


def read_png(path):
    """Decodes the PNGs write_png makes: 8-bit RGB, one IDAT, filter type 0 on every row."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, {}
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        chunks[kind] = body
        pos += 12 + length
    width, height, depth, colour_type = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, colour_type) == (8, 2) and b"IEND" in chunks
    raw = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(height, 1 + 3 * width)
    assert (raw[:, 0] == 0).all()
    return raw[:, 1:].reshape(height, width, 3)


def test_png_round_trip(tmp_path, rng):
    image = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    write_png(tmp_path / "a.png", image)
    np.testing.assert_array_equal(read_png(tmp_path / "a.png"), image)


def test_evaluate_identical_and_degraded_scenes(device, rng, tmp_path):
    reference = small_scene(rng, 200, device)
    arrays = reference.to_numpy()
    half = SplatSet.from_numpy(*(arrays[k][::2] for k in ("means", "rotations", "log_scales", "opacities", "features")), device=device)
    cameras = orbit_cameras(reference, views=3, size=32)
    images = {}
    result = evaluate(reference, [reference, half], cameras, background=(0.0, 0.0, 0.0), names=["same", "half"], images=images)
    same, degraded = result["tests"]
    assert result["views"] == 3 and result["reference"]["count"] == 200 and result["device"] == str(reference.device)
    assert same["psnr"]["mean"] == math.inf and same["ssim"]["mean"] == pytest.approx(1.0)
    assert same["colour_shift"]["mean"] == [0.0, 0.0, 0.0]
    assert degraded["count"] == 100 and degraded["ratio"] == 0.5
    assert degraded["psnr"]["worst"] <= degraded["psnr"]["mean"] < 60
    assert degraded["ssim"]["worst"] <= degraded["ssim"]["mean"] < 1
    assert degraded["psnr"]["worst_view"] in result["view_names"]
    per_view = [metrics.psnr(r, t) for r, t in zip(images["reference"], images["tests"][1])]
    assert degraded["psnr"]["mean"] == pytest.approx(np.mean(per_view))
    assert all(0.0 <= im.min() and im.max() <= 1.0 for im in images["reference"])  # clamped like saved images
    table = format_table(result)
    assert "same" in table and "half" in table and "inf" in table
    degraded["psnr"]["worst_view"] = "v" + "x" * 5_000_000 + "z"  # a hostile cameras file's name
    lines = format_table(result).splitlines()  # shown by its ends: no column pads every line to it
    assert max(len(line) for line in lines) < 200 and lines[-1].endswith("xxz") and "vxx" in lines[-1]
    # one identical view among others: counted as 100 dB in the mean, not inf (which hid the rest)
    mixed = compare_images(images["reference"], [images["reference"][0], *images["tests"][1][1:]], result["view_names"])
    assert mixed["views"][0]["psnr"] == math.inf and mixed["psnr"]["worst"] == pytest.approx(min(per_view[1:]))
    assert mixed["psnr"]["mean"] == pytest.approx(np.mean([IDENTICAL_VIEW_DB, *per_view[1:]]))

    paths = write_images(tmp_path / "out", images["reference"], images["tests"][1], result["view_names"])
    assert [p.name for p in paths] == ["view_000.png", "view_001.png", "view_002.png", "contact_sheet.png"]
    strip = read_png(paths[0])
    assert strip.shape == (32, 3 * 32 + 4, 3)
    np.testing.assert_array_equal(strip[:, :32], np.round(images["reference"][0].astype(np.float64) * 255).astype(np.uint8))  # in float64, as written
    diff = np.clip(np.abs(images["tests"][1][0].astype(np.float64) - images["reference"][0]) * 4, 0, 1)
    np.testing.assert_array_equal(strip[:, 68:], np.round(diff * 255).astype(np.uint8))
    assert read_png(paths[-1]).shape == (2 * 32 + 4, 2 * 100 + 4, 3)  # 3 strips on a 2 x 2 grid


def test_parse_background():
    assert parse_background("0,0.5,1") == (0.0, 0.5, 1.0)
    assert parse_background("white") == (1.0, 1.0, 1.0)
    for bad in ("1,2,3", "0,0", "red"):
        with pytest.raises(InputError, match="--background"):
            parse_background(bad)


def test_eval_cli(tmp_path, rng):
    reference = small_scene(rng, 150)
    arrays = reference.to_numpy()
    fewer = SplatSet.from_numpy(*(arrays[k][:100] for k in ("means", "rotations", "log_scales", "opacities", "features")))
    ply.save_ply(reference, tmp_path / "ref.ply")
    ply.save_ply(fewer, tmp_path / "fewer.ply")
    app = typer.Typer()
    app.command("eval")(eval_command)
    app.command("other")(lambda: None)  # two commands, so "eval" is a sub-command as in the real CLI
    args = ["eval", str(tmp_path / "ref.ply"), str(tmp_path / "ref.ply"), str(tmp_path / "fewer.ply"), "--views", "2",
            "--size", "24", "--device", "cpu", "--background", "1,1,1"]  # fmt: skip
    result = CliRunner().invoke(app, [*args, "--json", "--images", str(tmp_path / "imgs")])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert [t["count"] for t in out["tests"]] == [150, 100]
    assert out["tests"][0]["identical"] and out["tests"][0]["psnr"]["mean"] is None  # inf -> null
    assert not out["tests"][1]["identical"] and out["tests"][1]["psnr"]["mean"] > 0
    assert sorted(p.name for p in (tmp_path / "imgs" / "fewer").iterdir())[0] == "contact_sheet.png"
    table = CliRunner().invoke(app, args)
    assert table.exit_code == 0 and "fewer.ply" in table.stdout and "PSNR" in table.stdout
