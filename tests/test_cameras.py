"""Orbit cameras derived from a scene, and the INRIA trainer's cameras.json."""

import json

import numpy as np
import pytest

from nanogs_warp.errors import InputError
from nanogs_warp.eval.cameras import Camera, load_cameras_json, orbit_cameras, parse_up, scene_frame
from nanogs_warp.refinement.cameras import training_cameras
from nanogs_warp.splats import SplatSet


def project(camera: Camera, point):
    p = camera.rotation @ np.asarray(point, np.float64) + camera.translation
    return np.array([camera.fx * p[0] / p[2] + camera.cx, camera.fy * p[1] / p[2] + camera.cy]), p[2]


def scene_means(rng, n=500):
    means = rng.normal([1.0, -2.0, 0.5], [1.0, 0.5, 2.0], size=(n, 3))
    means[:10] += 1000.0  # far outliers must not move the centre or the radius much
    return means


@pytest.mark.parametrize("up", ["+x", "-x", "+y", "-y", "+z", "-z"])
def test_orbit_cameras_look_at_the_robust_centre_upright(rng, up):
    means = scene_means(rng)
    cameras = orbit_cameras(means, views=16, size=128, up=up)
    centre, radius = scene_frame(means)
    np.testing.assert_allclose(centre, np.median(means, axis=0))
    expected_radius = 2.2 * np.percentile(np.linalg.norm(means - centre, axis=1), 90)
    assert radius == pytest.approx(expected_radius)
    up_vector = parse_up(up)
    assert len(cameras) == 16 and len({c.name for c in cameras}) == 16
    for camera in cameras:
        np.testing.assert_allclose(camera.rotation @ camera.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(camera.rotation) == pytest.approx(1.0)
        assert np.linalg.norm(camera.centre - centre) == pytest.approx(radius)
        uv, depth = project(camera, centre)
        assert depth > 0
        np.testing.assert_allclose(uv, [64.0, 64.0], atol=1e-9)
        # 60 degree vertical FOV on a square image
        assert camera.fy == pytest.approx(64.0 / np.tan(np.radians(30.0)))
        assert (camera.width, camera.height, camera.fx) == (128, 128, camera.fy)
        # world up points to the top of the image, unless the view looks along the up axis
        forward = camera.rotation[2]
        if abs(forward @ up_vector) < 0.99:
            above, _ = project(camera, centre + 0.01 * radius * up_vector)
            assert above[1] < 64.0


def test_orbit_views_cover_the_sphere(rng):
    cameras = orbit_cameras(scene_means(rng), views=64, size=32)
    directions = np.array([c.rotation[2] for c in cameras])
    np.testing.assert_allclose(directions.mean(axis=0), 0.0, atol=0.05)
    cosines = directions @ directions.T - 2 * np.eye(64)
    nearest = np.degrees(np.arccos(np.clip(cosines.max(axis=1), -1, 1)))
    assert nearest.min() > 15 and nearest.max() < 35  # evenly spread: about 26 degrees apart


def test_orbit_from_a_splat_set_equals_orbit_from_its_means(rng):
    means = scene_means(rng, 100).astype(np.float32)
    n = len(means)
    splats = SplatSet.from_numpy(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3)))
    a, b = orbit_cameras(splats, views=5), orbit_cameras(means, views=5)
    for ca, cb in zip(a, b):
        np.testing.assert_array_equal(ca.rotation, cb.rotation)
        np.testing.assert_array_equal(ca.translation, cb.translation)


def test_near_plane_is_inrias_unless_the_scene_is_small(rng):
    """Cameras keep INRIA's near plane (0.2) around a scene in ordinary units (the orbit's radius is
    over 2 here); in small units it shrinks with the scene, so that it never holds the scene."""
    means = scene_means(rng)

    def cameras(units):
        return orbit_cameras(means * units, views=3) + training_cameras(means * units, 8, 32, 0)

    assert all(camera.near == 0.2 for camera in cameras(1.0))
    for small, smaller in zip(cameras(1e-3), cameras(1e-4)):
        assert small.near == pytest.approx(10.0 * smaller.near, rel=1e-6)
        assert 0 < small.near < 0.2
    for camera in cameras(1e-3)[:3]:  # the orbit: a tenth of its radius
        assert camera.near == pytest.approx(0.1 * np.linalg.norm(camera.centre - np.median(means * 1e-3, 0)), rel=1e-6)


def test_orbit_rejects_bad_requests():
    means = np.zeros((3, 3))
    with pytest.raises(InputError, match="--up"):
        orbit_cameras(means, up="up")
    with pytest.raises(InputError, match="--views"):
        orbit_cameras(means, views=0)
    with pytest.raises(InputError, match="finite"):
        orbit_cameras(np.full((2, 3), np.nan))
    # all centres at one point: radius falls back to 1
    assert np.linalg.norm(orbit_cameras(means, views=1)[0].centre) == pytest.approx(1.0)


def test_look_at_along_the_up_axis_is_still_a_rotation():
    camera = Camera.look_at([0, 5, 0], [0, 0, 0], [0, 1, 0], 10, 10, 8, 8)
    np.testing.assert_allclose(camera.rotation @ camera.rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(camera.rotation[2], [0, -1, 0])


def inria_entry(rng, k, width=1600, height=1040):
    """An entry as the INRIA trainer's camera_to_JSON writes it: camera-to-world rotation and centre."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c2w = q * np.sign(np.linalg.det(q))
    return {
        "id": k,
        "img_name": f"DSC{k:05d}",
        "width": width,
        "height": height,
        "position": rng.normal(size=3).tolist(),
        "rotation": [row.tolist() for row in c2w],
        "fy": 1200.0,
        "fx": 1190.0,
    }


def test_load_cameras_json_round_trips_the_inria_pose(tmp_path, rng):
    entries = [inria_entry(rng, k) for k in range(3)]
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(entries))
    cameras = load_cameras_json(path)
    for entry, camera in zip(entries, cameras):
        c2w, position = np.array(entry["rotation"]), np.array(entry["position"])
        np.testing.assert_allclose(camera.centre, position, atol=1e-12)
        # a point along the camera's +z axis (third column of camera-to-world) is straight ahead
        uv, depth = project(camera, position + 3.0 * c2w[:, 2])
        assert depth == pytest.approx(3.0)
        np.testing.assert_allclose(uv, [800.0, 520.0], atol=1e-9)
        assert camera.name == entry["img_name"]
        assert (camera.width, camera.height, camera.fx, camera.fy) == (1600, 1040, 1190.0, 1200.0)


def test_load_cameras_json_reads_a_near_plane_where_one_is_given(tmp_path, rng):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([inria_entry(rng, 0), inria_entry(rng, 1) | {"near": 0.004}]))
    assert [c.near for c in load_cameras_json(path)] == [0.2, 0.004]


def test_load_cameras_json_rescales_to_the_longest_side(tmp_path, rng):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([inria_entry(rng, 0)]))
    (camera,) = load_cameras_json(path, size=400)
    assert (camera.width, camera.height) == (400, 260)
    assert camera.fx == pytest.approx(1190.0 / 4) and camera.fy == pytest.approx(1200.0 / 4)
    assert (camera.cx, camera.cy) == (200.0, 130.0)


@pytest.mark.parametrize(
    "text, message",
    [("not json", "not JSON"), ("[]", "non-empty"), ('[{"width": 3}]', "malformed"),
     ('[{"id":0,"width":0,"height":2,"position":[0,0,0],"rotation":[[1,0,0],[0,1,0],[0,0,1]],"fx":1,"fy":1}]', "non-positive")],
)  # fmt: skip
def test_load_cameras_json_rejects_bad_files(tmp_path, text, message):
    path = tmp_path / "cameras.json"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_cameras_json(path)
    with pytest.raises(InputError, match="cannot read"):
        load_cameras_json(tmp_path / "missing.json")


@pytest.mark.parametrize(
    "change, message",
    [
        ({"width": float("inf")}, "malformed"),  # JSON Infinity: int() of it overflowed, an internal error
        ({"width": True}, "malformed"),
        ({"width": 1600.5}, "malformed"),
        ({"fx": 1e308}, "non-positive size or focal length"),
        ({"fx": float("inf")}, "non-positive size or focal length"),
        ({"rotation": [[1, 2, 3], [4, 5, 6], [7, 8, 10]]}, "is not a rotation"),
        ({"rotation": [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}, "is not a rotation"),
        ({"rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "is not a rotation"),  # a reflection
        ({"position": [1e300, 0, 0]}, "beyond float32"),
        ({"width": 10, "height": 10}, "renders 10 x 10 pixels"),  # SSIM's window is 11 a side
        ({"width": 9000, "height": 100}, "renders 9000 x 100 pixels"),
        ({"width": 10**30}, "declares 1000000000000000000000000000000 x 100 pixels, beyond"),
        ({"near": 0.0}, "near plane must be a positive number"),
        ({"near": -0.5}, "near plane must be a positive number"),
        ({"near": float("inf")}, "near plane must be a positive number"),
        ({"near": float("nan")}, "near plane must be a positive number"),
        ({"near": "close"}, "malformed"),
    ],
)
def test_load_cameras_json_rejects_cameras_no_render_can_use(tmp_path, rng, change, message):
    """Cameras eval cannot render or compare: one line each, before anything is rendered (they were
    internal errors, or rendered black and reported 'identical')."""
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([inria_entry(rng, 0, width=200, height=100) | change]))
    with pytest.raises(InputError, match=message):
        load_cameras_json(path)


def test_eval_sizes_and_view_counts_are_bounded(tmp_path, rng):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([inria_entry(rng, k, width=8000, height=6000) for k in range(6)]))
    with pytest.raises(InputError, match="pixels over all views is more than"):
        load_cameras_json(path)  # 288 M pixels
    assert len(load_cameras_json(path, size=256)) == 6
    for size in (10, 0, 8193):
        with pytest.raises(InputError, match="--size"):
            load_cameras_json(path, size=size) if size else orbit_cameras(np.zeros((3, 3)), size=size)
    means = np.zeros((3, 3))
    with pytest.raises(InputError, match="--views 4097"):
        orbit_cameras(means, views=4097)
    with pytest.raises(InputError, match="pixels over all views"):
        orbit_cameras(means, views=4096, size=512)
    with pytest.raises(InputError, match="--size 10"):
        orbit_cameras(means, size=10)
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match="nested too deeply"):
        load_cameras_json(path)
