"""The Warp rasteriser against the float64 numpy reference (tests/reference_render.py), per pixel.

Tolerance: 1e-4 absolute per channel on every pixel the reference does not flag as ambiguous (a
threshold decision within float32 rounding, see reference_render.py). Measured on these scenes: the
largest difference is ~2e-6 (float32 against float64 arithmetic), and no ambiguous pixel actually
flipped; fewer than 1% of pixels are flagged.
"""

import numpy as np
import pytest
import reference_render as ref
import warp as wp

import nanogs_warp.eval.render as render_module
from nanogs_warp.errors import InputError
from nanogs_warp.eval.cameras import Camera, orbit_cameras
from nanogs_warp.eval.render import _Rasteriser, render, render_views
from nanogs_warp.splats import SplatSet

TOLERANCE = 1e-4


def random_scene(rng, n, degree, camera_centre=None, behind=0.2, opacity=(0.5, 2.0), log_scale=(np.log(0.08), 0.6)):
    """n splats around the origin; a fraction ``behind`` scattered around the camera instead (behind
    it, straddling the near plane, very close and large on screen)."""
    means = rng.normal(size=(n, 3))
    if camera_centre is not None:
        k = int(n * behind)
        means[:k] = camera_centre + rng.normal(0.0, 0.7, size=(k, 3))
    features = np.concatenate(
        [rng.normal(0.0, 1.0, (n, 3)), rng.normal(0.0, 0.4, (n, 3 * ((degree + 1) ** 2 - 1)))], axis=1
    )
    return dict(
        means=means,
        rotations=rng.normal(size=(n, 4)),
        log_scales=rng.normal(*log_scale, size=(n, 3)),
        opacities=rng.normal(*opacity, size=n),
        features=features,
    )


def random_camera(rng, width=64, height=48):
    """Looks at the origin's neighbourhood from 3-4.5 units, random roll, off-centre principal point."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    fx = rng.uniform(40.0, 70.0)
    camera = Camera.look_at(
        direction * rng.uniform(3.0, 4.5), rng.normal(0.0, 0.3, 3), rng.normal(size=3), fx, fx * rng.uniform(0.9, 1.1), width, height
    )
    camera.cx += rng.uniform(-3.0, 3.0)
    camera.cy += rng.uniform(-3.0, 3.0)
    return camera


def compare(splats: SplatSet, camera, background, image):
    """Checks ``image`` against the reference; where two splats tie in depth, either order passes."""
    arrays = splats.to_numpy()
    expected, ambiguous, stats = ref.render_reference(arrays, camera, background)
    assert image.shape == expected.shape
    assert not np.isnan(image).any(), "a pixel was never written"
    diff = np.abs(image.astype(np.float64) - expected).max(axis=2)
    for pair in stats["ties"]:
        swapped, swapped_ambiguous, _ = ref.render_reference(arrays, camera, background, swap=pair)
        diff = np.minimum(diff, np.abs(image.astype(np.float64) - swapped).max(axis=2))
        ambiguous |= swapped_ambiguous
    assert ambiguous.mean() < 0.05, f"{ambiguous.sum()} ambiguous pixels"
    assert diff[~ambiguous].max() < TOLERANCE, f"max diff {diff[~ambiguous].max():.3g}"
    return stats


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("size", [(64, 48), (70, 45)])
def test_matches_reference(device, rng, degree, size):
    for _ in range(2):
        camera = random_camera(rng, *size)
        splats = SplatSet.from_numpy(**random_scene(rng, 250, degree, camera.centre), device=device)
        background = tuple(rng.uniform(0, 1, 3)) if degree % 2 else (0.0, 0.0, 0.0)
        stats = compare(splats, camera, background, render(splats, camera, background).numpy())
        assert stats["visible"] > 100 and stats["contributions"] > 5000


def test_dense_scene_stops_at_transmittance_limit(device, rng):
    """Opaque, large splats: most pixels stop on INRIA's T * (1 - alpha) < 1e-4 rule."""
    camera = random_camera(rng, 70, 45)
    scene = random_scene(rng, 300, 3, camera.centre, opacity=(4.0, 1.0), log_scale=(np.log(0.25), 0.4))
    splats = SplatSet.from_numpy(**scene, device=device)
    stats = compare(splats, camera, (0.2, 0.5, 1.0), render(splats, camera, (0.2, 0.5, 1.0)).numpy())
    assert stats["terminated"] > 1000


def test_near_plane_is_the_cameras(device, rng):
    """A camera's own near plane culls: splats around the camera, some nearer than it, match the reference."""
    camera = random_camera(rng)
    camera.near = 1.5
    scene = random_scene(rng, 250, 1, camera.centre, behind=0.4)
    splats = SplatSet.from_numpy(**scene, device=device)
    compare(splats, camera, (0.0, 0.0, 0.0), render(splats, camera).numpy())
    depth = (np.asarray(scene["means"]) @ camera.rotation.T + camera.translation)[:, 2]
    assert ((depth > 0.2) & (depth < 1.5)).sum() > 10  # splats that only this near plane culls


@pytest.mark.parametrize("units", [1e-3, 1e3])
def test_orbit_views_do_not_depend_on_the_scene_units(device, rng, units):
    """The same scene stored in other units (centres and scales times ``units``) looks the same from its
    orbit: the near plane follows the orbit when INRIA's 0.2 would cull a small scene whole."""
    scene = random_scene(rng, 300, 2, log_scale=(np.log(0.3), 0.4))
    scaled = dict(scene, means=scene["means"] * units, log_scales=scene["log_scales"] + np.log(units))
    images = [
        render_views(s, orbit_cameras(s, views=4, size=48))
        for s in (SplatSet.from_numpy(**scene, device=device), SplatSet.from_numpy(**scaled, device=device))
    ]
    assert images[0].max() > 0.2  # the scene is in view
    np.testing.assert_allclose(images[1], images[0], atol=2e-3)


def test_splat_straddling_tiles(device):
    """One splat centred on a tile corner, seen head-on: it reaches all four tiles around the corner."""
    camera = Camera(np.eye(3), np.zeros(3), 50.0, 50.0, 32.0, 24.0, 64, 48)
    # pixel index coordinate u = fx x / z + cx - 0.5: put the mean on pixel (15.5, 15.5), between tiles
    z = 2.0
    x, y = (15.5 + 0.5 - 32.0) * z / 50.0, (15.5 + 0.5 - 24.0) * z / 50.0
    scene = dict(
        means=np.array([[x, y, z]]),
        rotations=np.array([[1.0, 0.0, 0.0, 0.0]]),
        log_scales=np.log([[0.1, 0.05, 0.05]]),
        opacities=np.array([3.0]),
        features=np.array([[1.0, 0.5, -0.5]]),
    )
    splats = SplatSet.from_numpy(**scene, device=device)
    image = render(splats, camera).numpy()
    compare(splats, camera, (0.0, 0.0, 0.0), image)
    for ty, tx in [(0, 0), (0, 1), (1, 0), (1, 1)]:
        assert image[ty * 16 : ty * 16 + 16, tx * 16 : tx * 16 + 16].max() > 0.05
    np.testing.assert_allclose(image[15, 15], image[16, 16], rtol=1e-5)  # symmetric about the corner


def test_empty_and_invisible_scenes_show_the_background(device, rng):
    camera = random_camera(rng)
    empty = SplatSet.from_numpy(**random_scene(rng, 0, 0), device=device)
    np.testing.assert_array_equal(render(empty, camera, (0.1, 0.2, 0.3)).numpy(), np.broadcast_to(np.float32([0.1, 0.2, 0.3]), (48, 64, 3)))
    for method in ("tiles", "pixels"):  # the CPU's composite and the GPU's, on either device
        image = wp.full((1, 48, 64, 3), float("nan"), dtype=wp.float32, device=device)
        rasteriser = _Rasteriser(empty, method=method)
        rasteriser.render_into(camera, wp.vec3(0.1, 0.2, 0.3), image, 0)
        np.testing.assert_array_equal(image.numpy()[0], np.broadcast_to(np.float32([0.1, 0.2, 0.3]), (48, 64, 3)))
    behind = random_scene(rng, 50, 1)
    behind["means"] = camera.centre - 2.0 * camera.rotation[2] + rng.normal(0, 0.1, (50, 3))  # behind the camera
    splats = SplatSet.from_numpy(**behind, device=device)
    assert (render(splats, camera, (1.0, 1.0, 1.0)).numpy() == 1.0).all()


def test_batched_views_equal_single_views_and_repeat_bit_identically(device, rng):
    cameras = [random_camera(rng) for _ in range(3)]
    splats = SplatSet.from_numpy(**random_scene(rng, 200, 2), device=device)
    batch = render_views(splats, cameras, (0.0, 0.5, 0.0))
    assert batch.shape == (3, 48, 64, 3) and batch.dtype == np.float32
    for k, camera in enumerate(cameras):
        single = render(splats, camera, (0.0, 0.5, 0.0))
        assert single.device == splats.device
        np.testing.assert_array_equal(single.numpy(), batch[k])
    np.testing.assert_array_equal(render_views(splats, cameras, (0.0, 0.5, 0.0)), batch)


def chunk_every_launch(monkeypatch):
    """Lowers the work a CPU chunk of the renderer's launches must hold to one row."""
    for name in ("PAIRS_PER_CHUNK", "PROJECT_ROWS", "EMIT_ROWS", "GATHER_ROWS"):
        monkeypatch.setattr(render_module, name, 1)


@pytest.mark.parametrize("workers", [1, 3])
def test_tile_and_pixel_composites_are_identical(device, rng, monkeypatch, workers):
    """The CPU's tile-major composite and the GPU's pixel-parallel one agree bit for bit on every
    device, however the launches are chunked (no fused multiply-adds, the portable exp32)."""
    chunk_every_launch(monkeypatch)
    camera = random_camera(rng, 70, 45)
    splats = SplatSet.from_numpy(**random_scene(rng, 300, 3, camera.centre, opacity=(2.0, 2.0)), device=device)
    images = []
    for method in ("tiles", "pixels"):
        image = wp.full((1, 45, 70, 3), float("nan"), dtype=wp.float32, device=device)
        rasteriser = _Rasteriser(splats, workers=workers if device == "cpu" else 1, method=method)
        rasteriser.render_into(camera, wp.vec3(0.3, 0.3, 0.3), image, 0)
        images.append(image.numpy())
    np.testing.assert_array_equal(images[0], images[1])
    assert not np.isnan(images[0]).any()


def test_a_small_view_is_not_cut_into_chunks_of_almost_no_work(rng, monkeypatch):
    """On many cores a view of a few hundred splats goes out in one launch a kernel (each chunk's
    launch would cost more than its work); with the work a chunk must hold lowered, in chunks, and
    the image is the same."""
    assert render_module.rows_per_chunk(256, 300_000) == 1 and render_module.rows_per_chunk(2048, 728) == 721
    camera = random_camera(rng, 64, 48)
    splats = SplatSet.from_numpy(**random_scene(rng, 300, 3, camera.centre), device="cpu")
    chunked = []
    launch_in_turn = render_module.launch_chunks_in_turn

    def counting_launches(workers, commands):
        chunked.append(len(commands))
        launch_in_turn(workers, commands)

    monkeypatch.setattr(render_module, "launch_chunks_in_turn", counting_launches)
    images = []
    for lowered in (False, True):
        if lowered:
            chunk_every_launch(monkeypatch)
        image = wp.full((1, 48, 64, 3), float("nan"), dtype=wp.float32, device="cpu")
        _Rasteriser(splats, workers=16).render_into(camera, wp.vec3(0.0, 0.0, 0.0), image, 0)
        images.append(image.numpy())
        assert (len(chunked) > 0) == lowered
    np.testing.assert_array_equal(images[0], images[1])


@pytest.mark.parametrize("chunk", [1, 7, 2048])
def test_tiles_composited_in_chunks_equal_one_walk(device, rng, chunk):
    """The GPU's composite splits each tile's entries into chunks of ``chunk`` and merges them (where
    a tile holds more), and the CPU's tile composite replays the chunks' arithmetic: the same bits,
    on scenes where pixels stop on T < 1e-4 inside a chunk, and the reference's image. (Chunks
    regroup the one walk's sums: float32 rounding from it, measured 5e-7.)"""
    for trial in range(2):
        camera = random_camera(rng, 70, 45)
        opacity = (4.0, 1.0) if trial else (0.5, 2.0)
        scene = random_scene(rng, 600, 3, camera.centre, opacity=opacity, log_scale=(np.log(0.25), 0.4))
        splats = SplatSet.from_numpy(**scene, device=device)
        images = []
        for method in ("tiles", "pixels"):
            image = wp.full((1, 45, 70, 3), float("nan"), dtype=wp.float32, device=device)
            rasteriser = _Rasteriser(splats, workers=2 if device == "cpu" else 1, method=method, chunk=chunk)
            rasteriser.render_into(camera, wp.vec3(0.2, 0.5, 1.0), image, 0)
            images.append(image.numpy())
        longest = int(rasteriser.longest.numpy()[0])
        if chunk < 10:  # chunked: many chunks a tile
            chunks = int(rasteriser.chunk_ends.numpy()[-1])  # launched for more; those beyond return
            tiles = int((rasteriser.tile_end.numpy() > rasteriser.tile_start.numpy()).sum())
            assert longest > 3 * chunk and chunks > 3 * tiles
        else:  # every tile one chunk: ``composite`` itself
            assert 0 < longest <= chunk
        np.testing.assert_array_equal(images[1], images[0])
        stats = compare(splats, camera, (0.2, 0.5, 1.0), images[1][0])
        assert stats["terminated"] > (1000 if trial else 0)


def test_view_dependent_colour_follows_the_sh_basis(device):
    """A degree-1 splat whose only non-DC coefficient is red's -C1*y term. The SH direction is
    mean - camera centre, so from a camera at -y (direction +y) red is 0.5 - C1 * 0.8, from +y it is
    0.5 + C1 * 0.8 (before compositing)."""
    scene = dict(
        means=np.zeros((1, 3)),
        rotations=np.array([[1.0, 0.0, 0.0, 0.0]]),
        log_scales=np.log([[0.3, 0.3, 0.3]]),
        opacities=np.array([2.0]),
        features=np.concatenate([[[0.0, 0.0, 0.0]], [[0.8, 0.0, 0.0]], np.zeros((1, 6))], axis=1),
    )
    splats = SplatSet.from_numpy(**scene, device=device)
    reds = []
    for eye in ([0.0, -3.0, 0.0], [0.0, 3.0, 0.0]):
        camera = Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 40.0, 40.0, 32, 32)
        image = render(splats, camera).numpy()
        compare(splats, camera, (0.0, 0.0, 0.0), image)
        reds.append(image[16, 16, 0])
    assert reds[0] < reds[1]


def huge_splats(n, device="cpu"):
    """n splats each covering the whole of an orbit view (log-scale 3, faint)."""
    rng = np.random.default_rng(7)
    return SplatSet.from_numpy(
        rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), np.full((n, 3), 3.0), np.full(n, -3.0), rng.normal(size=(n, 3)), device=device
    )


def test_a_view_with_more_tile_entries_than_memory_is_refused(device, monkeypatch):
    """A view whose (tile, splat) pairs would not fit the device's memory is refused in one line
    before any entry buffer is made (a hostile file of huge splats at a large --size ran the
    machine out of memory); one that fits renders. The device's own free memory is asked too."""
    assert render_module.entry_memory(wp.get_device(device)) > 0
    splats = huge_splats(200, device)
    camera = orbit_cameras(splats, views=1, size=64)[0]
    monkeypatch.setattr(render_module, "entry_memory", lambda device: 200 * 16 * render_module.ENTRY_BYTES)  # 16 tiles a splat
    assert np.isfinite(render(splats, camera).numpy()).all()
    monkeypatch.setattr(render_module, "entry_memory", lambda device: 200 * 15 * render_module.ENTRY_BYTES)
    with pytest.raises(InputError, match=r"a 64x64 view of these 200 splats covers 3,200 \(tile, splat\) pairs"):
        render(splats, camera)


def test_tile_entries_beyond_int32_are_counted_in_int64(device, monkeypatch):
    """Where splats x tiles can pass int32, the pairs are summed in int64: a wrapped running sum
    can no longer pass for a small one."""
    monkeypatch.setattr(render_module, "INDEX_LIMIT", 1000)  # 200 splats x 16 tiles pass it
    splats = huge_splats(200, device)
    camera = orbit_cameras(splats, views=1, size=64)[0]
    with pytest.raises(InputError, match="covers 3,200"):
        render(splats, camera)


def _emitted_tiles(splats: SplatSet, camera) -> tuple[_Rasteriser, dict[int, set[int]]]:
    """Projects ``splats`` for ``camera`` and emits their entries (``render_into``'s first steps):
    the rasteriser and, per splat row, the tiles its entries name."""
    from nanogs_warp.eval.render import camera_params
    from nanogs_warp.kernels import render as kernels

    r = _Rasteriser(splats)
    r.rect.fill_(wp.vec4i(-1, -1, -1, -1))  # poison: a row culled before its rectangle keeps an empty one
    p = camera_params(camera)
    tiles = p.tiles_x * p.tiles_y
    count = r._project(p, tiles)
    r._reserve(max(count, 1))
    wp.launch(kernels.emit_entries, r.n, device=r.device,
              inputs=[r.depth, r.xy, r.conic_opacity, r.faint, r.rect, r.touched, r.ends, p.tiles_x, r.n, tiles, 0, r.keys, r.values])  # fmt: skip
    emitted: dict[int, set[int]] = {}
    for key, row in zip(r.keys.numpy()[:count], r.values.numpy()[:count]):
        emitted.setdefault(int(row), set()).add(int(key) >> 32)
    assert sum(len(t) for t in emitted.values()) == count  # no tile twice
    return r, emitted


def _rect_tiles(rect) -> list[tuple[int, int]]:
    x0, y0, x1, y1 = (int(v) for v in rect)
    return [(tx, ty) for ty in range(y0, y1) for tx in range(x0, x1)]


def _pixels_reached(xy, co, faint, box, tx, ty, width, height) -> bool:
    """Whether any pixel of tile (tx, ty) inside the view passes the walks' tests (``composite``'s box
    and power tests in float32, in its order of operations): the tile's entry is needed there."""
    xs = np.arange(16 * tx, min(16 * tx + 16, width), dtype=np.float32)
    ys = np.arange(16 * ty, min(16 * ty + 16, height), dtype=np.float32)
    fpx, fpy = np.meshgrid(xs, ys)
    dx = np.float32(xy[0]) - fpx
    dy = np.float32(xy[1]) - fpy
    power = np.float32(-0.5) * (co[0] * dx * dx + co[2] * dy * dy) - co[1] * dx * dy
    inside = (fpx >= box[0]) & (fpx <= box[1]) & (fpy >= box[2]) & (fpy <= box[3])
    return bool(np.any(inside & (power <= 0.0) & (power >= faint)))


def _ellipse_meets_tile(xy, co, faint, rect, tx, ty, scale) -> bool:
    """float64, by brute force: whether the least of q = a dx^2 + 2 b dx dy + c dy^2 over tile (tx, ty)'s
    rectangle of pixel centres is at most ``scale`` times ``reached_columns``' limit (its rounding
    bound over ``rect`` included): each edge's least value, or 0 with the centre inside."""
    a, b, c = (float(v) for v in co[:3])
    x, y = float(xy[0]), float(xy[1])
    x0, y0, x1, y1 = (int(v) for v in rect)
    far_x = max(abs(x - 16 * x0), abs(x - 16 * x1 + 1))
    far_y = max(abs(y - 16 * y0), abs(y - 16 * y1 + 1))
    limit = 2.0 * (-float(faint) + 1e-6 * 0.5 * ((a + abs(b)) * far_x**2 + (c + abs(b)) * far_y**2))
    dx_lo, dx_hi = x - (16 * tx + 15), x - 16 * tx
    dy_lo, dy_hi = y - (16 * ty + 15), y - 16 * ty
    if dx_lo <= 0 <= dx_hi and dy_lo <= 0 <= dy_hi:
        return True
    q = np.inf
    for dx in (dx_lo, dx_hi):
        dy = np.clip(-b * dx / c, dy_lo, dy_hi)
        q = min(q, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    for dy in (dy_lo, dy_hi):
        dx = np.clip(-b * dy / a, dx_lo, dx_hi)
        q = min(q, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    return q <= scale * limit


def needle_scene(rng, n, length=(0.3, 1.5)):
    """Thin strands of random direction around the origin: one long axis, two short ones."""
    log_scales = np.log(np.stack([rng.uniform(*length, n), rng.uniform(0.002, 0.02, n), rng.uniform(0.002, 0.02, n)], 1))
    return dict(means=rng.normal(0.0, 0.6, (n, 3)), rotations=rng.normal(size=(n, 4)), log_scales=log_scales,
                opacities=rng.normal(1.0, 2.0, n), features=rng.normal(0.0, 1.0, (n, 3)))  # fmt: skip


@pytest.mark.parametrize("kind", ["ordinary", "needles"])
def test_tiles_left_out_are_tiles_no_pixel_would_composite(device, rng, kind):
    """A splat's entries leave out only tiles where every pixel fails the walks' float32 box and
    power tests (so every image, and every gradient, is the one of the whole tile rectangle), and
    they leave out exactly the tiles that a float64 brute-force test finds beyond the splat's ellipse:
    every tile it meets is emitted, and none it misses by more than rounding. Thin strands lose most
    of their rectangle."""
    scene = random_scene(rng, 400, 0, log_scale=(np.log(0.15), 0.8)) if kind == "ordinary" else needle_scene(rng, 300)
    splats = SplatSet.from_numpy(**scene, device=device)
    camera = random_camera(rng, 200, 160)
    r, emitted = _emitted_tiles(splats, camera)
    tiles_x = (camera.width + 15) // 16
    xy, co, faint = r.xy.numpy(), r.conic_opacity.numpy(), r.faint.numpy()
    box, rect, touched = r.box.numpy(), r.rect.numpy(), r.touched.numpy()
    area = kept = 0
    for i in np.flatnonzero((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])):
        tiles = emitted.get(int(i), set())
        assert len(tiles) == touched[i]
        rect_tiles = _rect_tiles(rect[i])
        area += len(rect_tiles)
        kept += len(tiles)
        for tx, ty in rect_tiles:
            tile = ty * tiles_x + tx
            if _pixels_reached(xy[i], co[i], faint[i], box[i], tx, ty, camera.width, camera.height):
                assert tile in tiles, (i, tx, ty)
            if len(rect_tiles) == 1:  # kept without a test
                continue
            if _ellipse_meets_tile(xy[i], co[i], faint[i], rect[i], tx, ty, 1.0 - 1e-6):
                assert tile in tiles, (i, tx, ty)
            if tile in tiles:
                assert _ellipse_meets_tile(xy[i], co[i], faint[i], rect[i], tx, ty, 1.0 + 1e-6), (i, tx, ty)
    assert area > 0
    assert kept < (0.95 if kind == "ordinary" else 0.6) * area, (kept, area)


def test_the_entry_bound_counts_whole_tile_rectangles(device, rng):
    """``max_entries`` (the fits' bound on a view's work) counts every tile of the splats' rectangles,
    not the fewer tiles their ellipses reach: each entry's walk visits every pixel of its box in its
    tile. Thin strands whose reached tiles alone would pass the bound are refused."""
    splats = SplatSet.from_numpy(**needle_scene(rng, 300), device=device)
    camera = random_camera(rng, 200, 160)
    r, emitted = _emitted_tiles(splats, camera)
    rect = r.rect.numpy()
    pairs = int((np.maximum(rect[:, 2] - rect[:, 0], 0) * np.maximum(rect[:, 3] - rect[:, 1], 0)).sum())
    entries = sum(len(t) for t in emitted.values())
    assert entries < pairs - 1
    image = wp.zeros((1, camera.height, camera.width, 3), dtype=wp.float32, device=device)
    _Rasteriser(splats, max_entries=pairs).render_into(camera, wp.vec3(0.0, 0.0, 0.0), image, 0)
    with pytest.raises(InputError, match=f"spans {pairs:,} \\(tile, splat\\) pairs, more than the {pairs - 1:,}"):
        _Rasteriser(splats, max_entries=pairs - 1).render_into(camera, wp.vec3(0.0, 0.0, 0.0), image, 0)
