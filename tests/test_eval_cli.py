"""nanogs-warp eval as a person meets it: quiet mode, distinct labels for test scenes of the same
file name, and a contact sheet whose cells are labelled, the worst view marked in red."""

import json
import shutil
import zlib

import numpy as np
import pytest
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.cli.eval import scene_labels
from nanogs_warp.eval.evaluate import WORST_COLOUR, contact_sheet, view_label
from nanogs_warp.eval.glyphs import draw_text, text_width


def read_png(path):
    """The RGB pixels of a PNG written by nanogs_warp.eval.evaluate.write_png (filter 0, 8-bit RGB)."""
    data = path.read_bytes()
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    at, idat = 8, b""
    while at < len(data):
        length = int.from_bytes(data[at : at + 4], "big")
        if data[at + 4 : at + 8] == b"IDAT":
            idat += data[at + 8 : at + 8 + length]
        at += 12 + length
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(height, 1 + 3 * width)
    return raw[:, 1:].reshape(height, width, 3)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    random_splats_ply(root / "ref.ply", 200, seed=4)
    for folder, count in (("paper", 120), ("ours", 80)):
        (root / folder).mkdir()
        random_splats_ply(root / folder / "scene_0.1.ply", count, seed=4)
    return root


def run(*args):
    return CliRunner().invoke(app, ["eval", *(str(a) for a in args)])


def test_same_file_names_get_distinct_labels(scenes, tmp_path):
    tests = [scenes / "paper" / "scene_0.1.ply", scenes / "ours" / "scene_0.1.ply"]
    result = run(scenes / "ref.ply", *tests, "--views", "4", "--size", "24", "--device", "cpu", "--json", "--images", tmp_path)
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert [t["label"] for t in out["tests"]] == ["paper/scene_0.1", "ours/scene_0.1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ours_scene_0.1", "paper_scene_0.1"]
    assert "wrote 5 images" in result.stderr and "\r" not in result.stderr  # no progress off a terminal


def test_scene_labels():
    assert scene_labels(["a/x.ply", "b/y.ply"]) == ["x", "y"]
    assert scene_labels(["p/a/x.ply", "q/a/x.ply", "b/z.ply"]) == ["p/a/x", "q/a/x", "z"]
    assert scene_labels(["a/x.ply", "a/x.ply"]) == ["x", "x (2)"]


def test_quiet_prints_nothing_but_json(scenes, tmp_path):
    args = [scenes / "ref.ply", scenes / "ours" / "scene_0.1.ply", "--views", "2", "--size", "16", "--device", "cpu"]
    quiet = run(*args, "-q", "--images", tmp_path)
    assert quiet.exit_code == 0 and quiet.stdout == "" and quiet.stderr == ""
    assert (tmp_path / "scene_0.1" / "contact_sheet.png").is_file()
    loud = run(*args)
    assert "PSNR" in loud.stdout
    as_json = run(*args, "-q", "--json")
    assert json.loads(as_json.stdout)["command"] == "eval" and as_json.stderr == ""


def test_contact_sheet_is_labelled_and_marks_the_worst_view(scenes, tmp_path):
    result = run(scenes / "ref.ply", scenes / "ours" / "scene_0.1.ply", "--views", "4", "--size", "40", "--device", "cpu",
                 "--json", "--images", tmp_path)  # fmt: skip
    assert result.exit_code == 0, result.output
    test = json.loads(result.stdout)["tests"][0]
    sheet = read_png(tmp_path / "scene_0.1" / "contact_sheet.png")
    strip = read_png(tmp_path / "scene_0.1" / "view_000.png")
    # the label band under each cell holds dark text; the worst view's cell is framed in red
    red = np.all(sheet == WORST_COLOUR, axis=2)
    assert red.sum() > 4 * strip.shape[1]
    worst = [v["name"] for v in test["views"]].index(test["psnr"]["worst_view"])
    columns = 2  # ceil(sqrt(4))
    dark = np.all(sheet < 64, axis=2)
    title_rows = np.flatnonzero(dark[:, : strip.shape[1]].any(axis=1))
    assert title_rows.min() < 12  # the scene names on top
    ys, xs = np.nonzero(red)
    cell_x = xs.min() + 2
    assert (cell_x // (strip.shape[1] + 4)) == worst % columns


def test_contact_sheet_text_matches_the_metrics():
    """The label drawn under a cell is exactly view_label's text for that view."""
    strips = [np.zeros((10, 300, 3), np.uint8) for _ in range(2)]
    labels = [view_label("view_000", 23.4142, 0.81234), view_label("view_001", float("inf"), 1.0)]
    assert labels == ["view_000  PSNR 23.41  SSIM 0.812", "view_001  PSNR inf  SSIM 1.000"]
    sheet = contact_sheet(strips, labels=labels, worst=0)
    expected = np.full((11, 300, 3), 255, np.uint8)
    draw_text(expected, labels[1], 1, 2)
    cell = sheet[-11:, 300 + 4 : 600 + 4]
    assert np.array_equal(np.all(cell < 64, axis=2), np.all(expected < 64, axis=2))
    assert text_width(labels[0]) < 300


def test_a_label_longer_than_its_image_draws_only_what_shows(monkeypatch):
    """A camera name of millions of characters (a hostile cameras file) draws the characters that
    reach the image, not all of them (it took minutes), with the same pixels as drawing every one."""
    from nanogs_warp.eval import glyphs

    image = np.zeros((12, 40, 3), np.uint8)
    expected = image.copy()
    draw_text(expected, "ABCDEFGHIJ", -8, 2, (255, 255, 255))  # the first ten cover the 40 pixels
    drawn = []
    glyph = glyphs._glyph
    monkeypatch.setattr(glyphs, "_glyph", lambda ch: drawn.append(ch) or glyph(ch))
    draw_text(image, "ABCDEFGHIJ" + "x" * 5_000_000, -8, 2, (255, 255, 255))
    assert np.array_equal(image, expected)
    assert len(drawn) <= 10  # "A" lies wholly left of the image: at most B to J and one more


@pytest.mark.parametrize("exponent", [-70, 70])
def test_a_scene_in_tiny_or_huge_units_evaluates_as_at_unit_size(exponent):
    """The renderer works in float32, where squared coordinates of ~1e21 overflow and of ~1e-21
    vanish: ``evaluate`` renders such scenes rescaled by a power of two, so the same scenes in units
    2^70 times larger or smaller compare as they do unscaled (to the rounding of the log-scales)."""
    from scene_factory import in_units, random_splat_arrays

    from nanogs_warp.eval.cameras import orbit_cameras
    from nanogs_warp.eval.evaluate import evaluate
    from nanogs_warp.splats import SplatSet

    reference = random_splat_arrays(300, seed=7)
    test = {k: v[:150].copy() for k, v in reference.items()}

    results = []
    for e in (0, exponent):
        ref, tst = (SplatSet.from_numpy(**in_units(a, e), device="cpu") for a in (reference, test))
        results.append(evaluate(ref, [tst], orbit_cameras(ref, views=4, size=32), device="cpu")["tests"][0])
    assert 5.0 < results[0]["psnr"]["mean"] < 60.0
    for metric in ("psnr", "ssim", "fg_psnr"):
        assert results[1][metric]["mean"] == pytest.approx(results[0][metric]["mean"], abs=0.02)


def _on_a_grid(arrays, offset):
    """The scene with centres on a 1/8 grid within +-16, moved by ``offset``: every centre exact in
    float32 before and after the move (below 2^21, float32 steps are 1/8 at most)."""
    moved = dict(arrays)
    moved["means"] = (np.clip(np.round(arrays["means"] * 8.0), -128, 128) / 8.0 + offset).astype(np.float32)
    return moved


def test_a_scene_far_from_the_origin_evaluates_as_at_the_origin(tmp_path):
    """Far from the origin for its size, float32 (and float64, at 1e20) cannot place the cameras or
    the splats around a scene: ``eval`` renders it recentred, with the figures it has at the origin;
    a cluster at 1e20 was an internal error."""
    from scene_factory import random_splat_arrays, write_splats_ply

    reference = random_splat_arrays(300, seed=7)
    test = {k: v[:150].copy() for k, v in reference.items()}
    figures = []
    for offset in (0.0, 2.0**20):
        paths = [tmp_path / f"{name}_{offset:g}.ply" for name in ("ref", "test")]
        for path, arrays in zip(paths, (reference, test)):
            write_splats_ply(path, _on_a_grid(arrays, offset))
        cameras = tmp_path / f"cameras_{offset:g}.json"  # the same trainer's camera, moved with the scene
        cameras.write_text(json.dumps([{"id": 0, "img_name": "a", "width": 40, "height": 30, "fx": 35.0, "fy": 35.0,
                                        "position": [offset, offset, offset - 40.0], "rotation": np.eye(3).tolist()}]))  # fmt: skip
        for extra in ((), ("--cameras", cameras)):
            result = run(*paths, "--device", "cpu", "--size", "32", "--views", "4", "--json", *extra)
            assert result.exit_code == 0, result.output
            figures.append(json.loads(result.stdout)["tests"][0])
    for plain, far in ((figures[0], figures[2]), (figures[1], figures[3])):
        assert 5.0 < plain["psnr"]["mean"] < 60.0
        for metric in ("psnr", "ssim", "fg_psnr"):
            assert far[metric]["mean"] == pytest.approx(plain[metric]["mean"], abs=0.01)

    cluster = random_splat_arrays(300, seed=1)
    cluster["means"][:] = 1e20
    write_splats_ply(tmp_path / "cluster.ply", cluster)
    result = run(tmp_path / "cluster.ply", tmp_path / "cluster.ply", "--device", "cpu", "--size", "32", "--views", "2", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["tests"][0]["identical"]


def test_an_images_folder_that_cannot_be_made_is_refused_before_rendering(scenes, tmp_path):
    (tmp_path / "afile").write_text("x")
    args = [scenes / "ref.ply", scenes / "ours" / "scene_0.1.ply", "--views", "2", "--size", "16", "--device", "cpu"]
    for folder, message in ((tmp_path / "afile" / "sub", "cannot create the directory"), (tmp_path / "afile", "not a directory"),
                            ("", "give a folder")):  # fmt: skip
        result = run(*args, "--images", folder)
        assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_long_view_names_make_short_file_names(tmp_path):
    from nanogs_warp.eval.evaluate import write_images

    image = np.zeros((12, 12, 3), np.float32)
    written = write_images(tmp_path / "img", [image], [image], ["v" * 400])
    assert written[0].name == "v" * 100 + ".png" and written[0].exists()


def test_invalid_rows_are_refused_or_dropped(scenes, tmp_path):
    """A scene with a NaN row: one line and exit 2, or with --drop-invalid evaluated without it."""
    from plyfile import PlyData

    reference = scenes / "ref.ply"
    bad = tmp_path / "bad.ply"
    shutil.copy(reference, bad)
    ply = PlyData.read(str(bad), mmap=False)
    ply["vertex"].data["opacity"][3] = np.nan
    ply.write(str(bad))
    refused = run(bad, reference, "--device", "cpu", "--views", "2", "--size", "32")
    assert refused.exit_code == 2 and "--drop-invalid" in refused.stderr
    result = run(bad, reference, "--device", "cpu", "--views", "2", "--size", "32", "--drop-invalid", "--json")
    assert result.exit_code == 0, result.output
    assert "dropped 1 of 200" in result.stderr and json.loads(result.stdout)["tests"][0]["count"] == 200


def test_each_test_scene_gets_its_own_images_folder_inside_images(scenes, tmp_path):
    """A test scene named '...ply' (label '..') writes inside --images, not beside it; labels that
    differ only before their last 100 characters still get folders of their own."""
    from nanogs_warp.cli.eval import image_folders

    assert image_folders(["..", ".", ".hidden", "a/b", "a_b"]) == ["scene_1", "scene_2", "hidden", "a_b", "a_b_5"]
    long = ["x" + "y" * 150, "z" + "y" * 150]
    assert len(set(image_folders(long))) == 2 and all(len(n) <= 100 for n in image_folders(long))
    shutil.copy(scenes / "ours" / "scene_0.1.ply", tmp_path / "...ply")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "view_000.png").write_text("mine")
    result = run(scenes / "ref.ply", tmp_path / "...ply", "--views", "1", "--size", "16", "--device", "cpu", "--images", tmp_path / "run" / "imgs", "-q")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "run" / "view_000.png").read_text() == "mine" and sorted(p.name for p in (tmp_path / "run").iterdir()) == ["imgs", "view_000.png"]
    assert (tmp_path / "run" / "imgs" / "scene_1" / "view_000.png").is_file()


def test_cameras_for_a_scene_in_small_units_carry_their_near_plane(tmp_path):
    """Cameras a few millimetres from a scene stored in metres lie inside INRIA's 0.2 near plane:
    every view rendered bare background and eval reported the scenes identical without a word. A
    cameras file may give each camera's ``near`` (``tools/refine_quality.py`` writes it); without
    one, a reference that renders as bare background in every view is said in one warning line."""
    from scene_factory import in_units, random_splat_arrays, write_splats_ply

    arrays = in_units(random_splat_arrays(300, seed=5), -10)  # about a millimetre across
    write_splats_ply(tmp_path / "ref.ply", arrays)
    write_splats_ply(tmp_path / "test.ply", {k: v[:150] for k, v in arrays.items()})
    camera = {"id": 0, "img_name": "a", "width": 40, "height": 30, "fx": 30.0, "fy": 30.0,
              "position": [0.0, 0.0, -0.005], "rotation": np.eye(3).tolist()}  # fmt: skip
    (tmp_path / "inria.json").write_text(json.dumps([camera]))
    (tmp_path / "near.json").write_text(json.dumps([camera | {"near": 0.0005}]))
    plain = run(tmp_path / "ref.ply", tmp_path / "test.ply", "--cameras", tmp_path / "inria.json", "--device", "cpu", "--json")
    assert plain.exit_code == 0, plain.output
    assert json.loads(plain.stdout)["tests"][0]["identical"]
    assert plain.stderr.count("\n") == 1 and "renders as bare background in every view" in plain.stderr
    assert "(0.2 world units)" in plain.stderr
    near = run(tmp_path / "ref.ply", tmp_path / "test.ply", "--cameras", tmp_path / "near.json", "--device", "cpu", "--json")
    assert near.exit_code == 0, near.output
    assert near.stderr == "" and 5.0 < json.loads(near.stdout)["tests"][0]["psnr"]["mean"] < 60.0
