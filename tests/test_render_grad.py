"""The differentiable rasteriser: its forward is the renderer's, its backward the float64 finite
differences of the float64 reference renderer (tests/reference_render.py), for every parameter group.

Loss L = sum(w * image) with random weights w, so dL/dimage = w. Central differences in float64 with
step h; a parameter whose difference changes between h and h/4 (a pixel crossing a threshold: alpha
1/255, a tile-rectangle edge) is left out, as the forward is not differentiable there. Tolerance:
1e-3 relative to the largest gradient of the group, 2% of the group's norm over all parameters;
measured: at most 3e-6 of either (float32 against float64).
"""

import numpy as np
import pytest
import reference_render as ref
import warp as wp
from test_render import random_camera, random_scene

from nanogs_warp.eval.render import render
from nanogs_warp.refinement.render_grad import GradRasteriser, SplatGradients
from nanogs_warp.splats import SplatSet

GROUPS = ("means", "rotations", "log_scales", "opacities", "features")


def _scene(rng, n, degree, device):
    camera = random_camera(rng)
    arrays = random_scene(rng, n, degree, camera_centre=camera.centre, behind=0.1, opacity=(0.0, 1.0), log_scale=(np.log(0.25), 0.3))
    return SplatSet.from_numpy(**arrays, device=device), camera


def _forward_backward(splats, camera, weights, method=None, lanes=None, lanes_in_turn=None, per_pixel=None):
    rasteriser = GradRasteriser(splats, method=method, lanes=lanes, lanes_in_turn=lanes_in_turn, per_pixel=per_pixel)
    h, w = camera.height, camera.width
    image = wp.full((1, h, w, 3), float("nan"), dtype=wp.float32, device=splats.device)
    rasteriser.forward([camera], wp.vec3(0.1, 0.2, 0.3), image)
    grads = SplatGradients.zeros_like(splats)  # backward adds to these
    g_image = wp.array(weights[None].astype(np.float32), dtype=wp.float32, device=splats.device)
    rasteriser.backward(image, g_image, grads)
    return image.numpy()[0], grads


@pytest.mark.parametrize("method", ["tiles", "pixels"])
def test_forward_is_the_renderer(device, rng, method):
    splats, camera = _scene(rng, 60, 3, device)
    expected = render(splats, camera, (0.1, 0.2, 0.3)).numpy()
    image, _ = _forward_backward(splats, camera, rng.normal(size=(camera.height, camera.width, 3)), method)
    # the renderer's own compositing method gives the same bits; the other one rounds its sums in
    # another order on a GPU (one thread per pixel against a tile's replay)
    assert np.abs(image - expected).max() <= 1e-6


def _reference_loss(arrays, camera, weights):
    image, _, _ = ref.render_reference(arrays, camera, (0.1, 0.2, 0.3))
    return float((image * weights).sum())


def _finite_differences(arrays, camera, weights, group, h):
    """dL/d(group) by central differences in float64; NaN where the difference is not smooth."""
    base = {k: v.astype(np.float64) for k, v in arrays.items()}
    values = base[group]
    out = np.full(values.shape, np.nan)
    for index in np.ndindex(values.shape):
        estimates = []
        for step in (h, h / 4):
            saved = values[index]
            values[index] = saved + step
            plus = _reference_loss(base, camera, weights)
            values[index] = saved - step
            minus = _reference_loss(base, camera, weights)
            values[index] = saved
            estimates.append((plus - minus) / (2 * step))
        if abs(estimates[0] - estimates[1]) <= 1e-3 * (1.0 + abs(estimates[1])):
            out[index] = estimates[1]
    return out


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_backward_matches_finite_differences(device, rng, degree):
    splats, camera = _scene(rng, 6, degree, device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    image, grads = _forward_backward(splats, camera, weights)
    arrays = splats.to_numpy()
    got = {k: getattr(grads, k).numpy().reshape(arrays[k].shape) for k in GROUPS}
    got["rotations"] = got["rotations"][:, [3, 0, 1, 2]]  # Warp's x, y, z, w -> the file's w first
    assert all(np.isfinite(g).all() for g in got.values())
    for group in GROUPS:
        expected = _finite_differences(arrays, camera, weights, group, 1e-4)
        smooth = np.isfinite(expected)
        assert smooth.mean() > 0.8, f"{group}: too few smooth parameters to test"
        scale = np.abs(expected[smooth]).max()
        assert scale > 0, f"{group}: no gradient at all (a scene that tests nothing)"
        error = np.abs(got[group][smooth] - expected[smooth])
        assert error.max() <= 1e-3 * scale + 1e-6, f"{group}: max error {error.max():.3g} of {scale:.3g}"
        assert np.linalg.norm(error) <= 0.02 * np.linalg.norm(expected[smooth]), group


def test_backward_is_deterministic(device, rng):
    splats, camera = _scene(rng, 300, 3, device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    first = [a.numpy().copy() for a in _forward_backward(splats, camera, weights)[1].arrays()]
    second = [a.numpy().copy() for a in _forward_backward(splats, camera, weights)[1].arrays()]
    for a, b in zip(first, second):
        assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("lanes", [4, 16])
def test_lanes_per_tile_give_the_same_gradients(device, rng, lanes):
    """Several threads per tile (the GPU's way) sum the same terms in another order: equal to float32
    rounding (measured: about 1e-6 of the largest component), and the same bytes on a rerun."""
    splats, camera = _scene(rng, 300, 3, device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    one = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=1)[1].arrays()]
    many = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=lanes)[1].arrays()]
    again = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=lanes)[1].arrays()]
    for a, b, c in zip(one, many, again):
        assert np.abs(a - b).max() <= 1e-5 * np.abs(a).max()
        assert b.tobytes() == c.tobytes()


@pytest.mark.parametrize("lanes", [4, 16])
def test_lanes_summed_in_turn_give_the_same_bytes(device, rng, lanes):
    """The CPU's backward (one thread per tile summing its lanes in turn) against the GPU's (a thread
    per lane, then ``sum_lanes``), on one device: the same bytes, in a view whose edge tiles are
    partial and whose pixels saturate (early termination)."""
    camera = random_camera(rng, width=70, height=45)
    arrays = random_scene(rng, 800, 2, camera_centre=camera.centre, behind=0.1, opacity=(0.3, 1.0), log_scale=(np.log(0.3), 0.3))
    splats = SplatSet.from_numpy(**arrays, device=device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    threads = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=lanes, lanes_in_turn=False)[1].arrays()]
    in_turn = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=lanes, lanes_in_turn=True)[1].arrays()]
    assert any(np.abs(a).max() > 0 for a in threads)
    for a, b in zip(threads, in_turn):
        assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("lanes", [1, 16])
def test_the_backward_buffers_count_in_the_memory_bound(monkeypatch, lanes):
    """A view that fits the forward rasteriser's memory bound but not the backward pass's buffers
    as well is refused by the refinement's rasteriser, in one line (``InputError``)."""
    import nanogs_warp.eval.render as render_module
    from test_render import huge_splats

    from nanogs_warp.errors import InputError
    from nanogs_warp.eval.cameras import orbit_cameras

    splats = huge_splats(200, "cpu")
    camera = orbit_cameras(splats, views=1, size=64)[0]
    monkeypatch.setattr(render_module, "entry_memory", lambda device: 200 * 16 * render_module.ENTRY_BYTES)
    assert np.isfinite(render(splats, camera).numpy()).all()
    rasteriser = GradRasteriser(splats, lanes=lanes)
    image = wp.zeros((1, 64, 64, 3), dtype=wp.float32, device="cpu")
    with pytest.raises(InputError, match="^a 64x64 view of these 200 splats covers 3,200"):
        rasteriser.forward([camera], wp.vec3(0.0, 0.0, 0.0), image)
    with pytest.raises(InputError, match="^2 views of these 200 splats cover 6,400"):  # two views together
        rasteriser.forward([camera, camera], wp.vec3(0.0, 0.0, 0.0), wp.zeros((2, 64, 64, 3), dtype=wp.float32, device="cpu"))


@pytest.mark.parametrize("size", [(70, 45), (32, 32)])
def test_per_pixel_backward_gives_the_lanes_bytes(device, rng, size):
    """The GPU's backward (a thread per pixel, each (entry, pixel) term in its own slot, then summed
    per entry) against 16 lanes (a thread per row, then ``sum_lanes``) and the CPU's lanes in turn,
    on one device: the same bytes, in views with partial edge tiles, saturated pixels (early
    termination) and entries whose boxes reach part of a tile."""
    width, height = size
    camera = random_camera(rng, width=width, height=height)
    arrays = random_scene(rng, 800, 2, camera_centre=camera.centre, behind=0.1, opacity=(0.3, 1.0), log_scale=(np.log(0.3), 0.6))
    splats = SplatSet.from_numpy(**arrays, device=device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    image, per_pixel = _forward_backward(splats, camera, weights, lanes=16, per_pixel=True)
    pixels = [a.numpy().copy() for a in per_pixel.arrays()]
    assert np.isfinite(image).all()
    assert all(np.abs(a).max() > 0 for a in pixels)
    for lanes_in_turn in (False, True):
        lanes = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, lanes=16, lanes_in_turn=lanes_in_turn,
                                                             per_pixel=False)[1].arrays()]  # fmt: skip
        for a, b in zip(pixels, lanes):
            assert a.tobytes() == b.tobytes()


def test_per_pixel_backward_falls_back_to_the_lanes(device, rng, monkeypatch):
    """Where its (entry, pixel) slots would not fit the device, the per-pixel backward leaves the
    work to the lanes: the same bytes."""
    import nanogs_warp.refinement.render_grad as render_grad

    splats, camera = _scene(rng, 300, 1, device)
    weights = rng.normal(size=(camera.height, camera.width, 3))
    expected = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, per_pixel=True)[1].arrays()]
    monkeypatch.setattr(render_grad, "entry_memory", lambda device: 100)
    got = [a.numpy().copy() for a in _forward_backward(splats, camera, weights, per_pixel=True)[1].arrays()]
    for a, b in zip(expected, got):
        assert a.tobytes() == b.tobytes()


def test_per_pixel_backward_of_a_view_whose_entries_reach_no_pixel(device):
    """A splat just off the image's right edge, inside one tile row: its reach box touches the last
    tile column but no pixel centre, so the view has an entry (a one-tile rectangle keeps its tile)
    and not one (entry, pixel) slot. Its gradients are zero,
    by either backward (the per-pixel one once failed there for want of a buffer)."""
    from nanogs_warp.eval.cameras import Camera

    camera = Camera.look_at(np.array([0.0, 0.0, -5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 50.0, 50.0, 32, 32, "edge", 0.2)
    splats = SplatSet.from_numpy(means=np.array([[-1.85, 0.5, 0.0]]), rotations=np.array([[1.0, 0.0, 0.0, 0.0]]),
                                 log_scales=np.full((1, 3), np.log(1e-3)), opacities=np.array([2.0]),
                                 features=np.ones((1, 3)), device=device)  # fmt: skip
    weights = np.ones((camera.height, camera.width, 3))
    for per_pixel in (True, False):
        rasteriser = GradRasteriser(splats, per_pixel=per_pixel)
        image = wp.zeros((1, 32, 32, 3), dtype=wp.float32, device=device)
        rasteriser.forward([camera], wp.vec3(0.0, 0.0, 0.0), image)
        assert rasteriser.count > 0 and image.numpy().max() == 0.0
        grads = SplatGradients.zeros_like(splats)
        rasteriser.backward(image, wp.array(weights[None].astype(np.float32), dtype=wp.float32, device=device), grads)
        assert all(not np.any(a.numpy()) for a in grads.arrays()), per_pixel


@pytest.mark.parametrize("backward", ["per_pixel", "lanes", "lanes_in_turn"])
def test_views_rendered_together_give_the_bytes_of_one_at_a_time(device, rng, backward):
    """Several views of different sizes (one not a whole number of tiles) rendered and back-propagated
    together: each view's pixels are those of its camera rendered alone, and the gradients those of
    back-propagating the views one after another into the same arrays, to the bit."""
    sizes = [(48, 48), (48, 36), (36, 48), (24, 24), (45, 29)]
    cameras = [random_camera(rng, width=w, height=h) for w, h in sizes]
    arrays = random_scene(rng, 300, 2, camera_centre=cameras[0].centre, behind=0.1, opacity=(0.2, 1.0), log_scale=(np.log(0.3), 0.6))
    splats = SplatSet.from_numpy(**arrays, device=device)
    options = {"per_pixel": dict(lanes=16, per_pixel=True), "lanes": dict(lanes=16, lanes_in_turn=False, per_pixel=False),
               "lanes_in_turn": dict(lanes=16, lanes_in_turn=True, per_pixel=False)}[backward]  # fmt: skip
    weights = [rng.normal(size=(c.height, c.width, 3)).astype(np.float32) for c in cameras]
    one_at_a_time = SplatGradients.zeros_like(splats)
    rasteriser = GradRasteriser(splats, **options)
    alone = []
    for camera, w in zip(cameras, weights):
        image = wp.full((1, camera.height, camera.width, 3), float("nan"), dtype=wp.float32, device=device)
        rasteriser.forward([camera], wp.vec3(0.1, 0.2, 0.3), image)
        rasteriser.backward(image, wp.array(w[None], dtype=wp.float32, device=device), one_at_a_time)
        alone.append(image.numpy()[0])
    width, height = max(w for w, _ in sizes), max(h for _, h in sizes)
    image = wp.full((len(cameras), height, width, 3), float("nan"), dtype=wp.float32, device=device)
    g_image = np.full((len(cameras), height, width, 3), np.nan, np.float32)  # NaN outside each view: never read
    for v, (camera, w) in enumerate(zip(cameras, weights)):
        g_image[v, : camera.height, : camera.width] = w
    together = SplatGradients.zeros_like(splats)
    rasteriser = GradRasteriser(splats, **options)
    rasteriser.forward(cameras, wp.vec3(0.1, 0.2, 0.3), image)
    rasteriser.backward(image, wp.array(g_image, dtype=wp.float32, device=device), together)
    images = image.numpy()
    for v, camera in enumerate(cameras):
        assert images[v, : camera.height, : camera.width].tobytes() == alone[v].tobytes()
    for a, b in zip(one_at_a_time.arrays(), together.arrays()):
        a, b = a.numpy(), b.numpy()
        assert np.isfinite(b).all() and np.abs(b).max() > 0
        assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("backward", ["weights", "tile_weights", "tile_weights_refused", "per_pixel", "lanes", "lanes_in_turn"])
def test_colours_alone_are_the_whole_backward_colour_bytes(device, rng, backward, monkeypatch):
    """The colour fit's backward (``colours_only``) on views rendered together, with partial edge
    tiles and saturated pixels: the colours' gradients are the whole pass's to the bit, and no other
    gradient array is touched (NaN in, NaN out); from the forward's kept weights (``keep_weights``,
    the per-pixel backward's and the tiles', a GPU's and the CPU's) too, whose forward renders each
    view's pixels to the bit. The tiles keep no weights where more entries reach a pixel than
    ``KEPT_PAIRS_PER_PIXEL`` on average (lowered here to 1), and walk the tiles again."""
    from nanogs_warp.refinement import render_grad

    if backward == "tile_weights_refused":
        monkeypatch.setattr(render_grad, "KEPT_PAIRS_PER_PIXEL", 1)
    cameras = [random_camera(rng, width=w, height=h) for w, h in [(48, 40), (45, 29)]]
    arrays = random_scene(rng, 500, 2, camera_centre=cameras[0].centre, behind=0.1, opacity=(0.3, 1.0), log_scale=(np.log(0.3), 0.6))
    splats = SplatSet.from_numpy(**arrays, device=device)
    options = {"per_pixel": dict(lanes=16, per_pixel=True), "lanes": dict(lanes=16, lanes_in_turn=False, per_pixel=False),
               "lanes_in_turn": dict(lanes=16, lanes_in_turn=True, per_pixel=False),
               "weights": dict(per_pixel=True), "tile_weights": dict(per_pixel=False),
               "tile_weights_refused": dict(per_pixel=False)}[backward]  # fmt: skip
    g_image = wp.array(rng.normal(size=(2, 40, 48, 3)).astype(np.float32), dtype=wp.float32, device=device)
    results, images = [], []
    for colours_only in (False, True):
        rasteriser = GradRasteriser(splats, **options)
        image = wp.full((2, 40, 48, 3), float("nan"), dtype=wp.float32, device=device)
        keep = colours_only and "weights" in backward
        rasteriser.forward(cameras, wp.vec3(0.1, 0.2, 0.3), image, keep_weights=keep)
        assert rasteriser.weights_kept == (keep and backward != "tile_weights_refused")
        grads = SplatGradients.zeros_like(splats)
        for a in grads.arrays()[:-1]:
            a.fill_(float("nan"))
        rasteriser.backward(image, g_image, grads, colours_only=colours_only)
        results.append([a.numpy().copy() for a in grads.arrays()])
        images.append(image.numpy())
    for v, camera in enumerate(cameras):
        own = np.s_[v, : camera.height, : camera.width]
        assert images[0][own].tobytes() == images[1][own].tobytes()
    whole, colours = results
    assert np.abs(whole[-1]).max() > 0 and np.isfinite(whole[-1]).all()
    assert whole[-1].tobytes() == colours[-1].tobytes()
    assert all(np.isnan(a).all() for a in colours[:-1])


@pytest.mark.parametrize("chunk", [1, 7])
def test_weights_kept_in_chunks_are_the_renderers_chunks(device, rng, chunk):
    """The colour fit's forward (``keep_weights``) composites a tile of more than a chunk of entries in
    chunks, as the renderer does: on two views of different sizes rendered together, with ``chunk``
    entries a chunk and pixels that stop on T < 1e-4 inside chunks, a GPU's kernels (``per_pixel``:
    a thread per chunk and pixel) and the CPU's tile walk give each view the renderer's chunked image
    of that camera alone, bit for bit, and the same colours' gradients, which are the one-walk
    pass's to float32 rounding. A held-out view (``walked_back=False``) is the renderer's too."""
    from nanogs_warp.eval.render import _Rasteriser

    cameras = [random_camera(rng, width=w, height=h) for w, h in [(48, 40), (45, 29)]]
    arrays = random_scene(rng, 600, 2, camera_centre=cameras[0].centre, behind=0.1, opacity=(4.0, 1.0), log_scale=(np.log(0.25), 0.4))
    splats = SplatSet.from_numpy(**arrays, device=device)
    background = wp.vec3(0.1, 0.2, 0.3)
    g_image = wp.array(rng.normal(size=(2, 40, 48, 3)).astype(np.float32), dtype=wp.float32, device=device)
    alone = []
    for camera in cameras:
        image = wp.full((1, camera.height, camera.width, 3), float("nan"), dtype=wp.float32, device=device)
        renderer = _Rasteriser(splats, chunk=chunk)
        renderer.render_into(camera, background, image, 0)
        assert (renderer.tile_end.numpy() - renderer.tile_start.numpy()).max() > 3 * chunk  # several chunks a tile
        alone.append(image.numpy()[0])
    colours = {}
    for per_pixel, method in ((True, None), (False, None), (False, "tiles"), (False, "pixels")):  # a GPU's and the CPU's
        rasteriser = GradRasteriser(splats, method=method, per_pixel=per_pixel)
        rasteriser.chunk = chunk
        image = wp.full((2, 40, 48, 3), float("nan"), dtype=wp.float32, device=device)
        rasteriser.forward(cameras, background, image, keep_weights=True)
        assert rasteriser.weights_kept
        grads = SplatGradients.zeros_like(splats)
        rasteriser.backward(image, g_image, grads, colours_only=True)
        colours[per_pixel, method] = grads.features.numpy()
        for v, camera in enumerate(cameras):
            assert image.numpy()[v, : camera.height, : camera.width].tobytes() == alone[v].tobytes()
        held_out = wp.full((1, 40, 48, 3), float("nan"), dtype=wp.float32, device=device)
        rasteriser.forward(cameras[:1], background, held_out, walked_back=False)
        assert held_out.numpy()[0].tobytes() == alone[0].tobytes()
    assert len({c.tobytes() for c in colours.values()}) == 1
    one_walk = GradRasteriser(splats)
    image = wp.full((2, 40, 48, 3), float("nan"), dtype=wp.float32, device=device)
    one_walk.forward(cameras, background, image)
    grads = SplatGradients.zeros_like(splats)
    one_walk.backward(image, g_image, grads, colours_only=True)
    whole = grads.features.numpy()
    chunked = colours[True, None]
    assert np.abs(whole).max() > 0 and np.isfinite(chunked).all()
    np.testing.assert_allclose(chunked, whole, rtol=0, atol=1e-4 * np.abs(whole).max())


def test_a_pixel_whose_transmittance_runs_out_between_chunks_stops_there(device):
    """Where the transmittance before a chunk is 0 (the chunks before it took it below 1e-4 between
    them, though no walk stopped: float32 regrouping can do that), the chunk is not walked, and the
    pixel's stop is its first entry, so that no weight of it or of a later chunk is read back. One
    16 x 16 view, one tile of four entries in two chunks, the transmittance before the second set by
    hand; the first is walked by ``chunk_own_transmittance``, the second by ``composite_chunk_weights``."""
    from nanogs_warp.eval.cameras import Camera
    from nanogs_warp.kernels import render_grad as grad_kernels
    from nanogs_warp.refinement.render_grad import camera_array

    camera = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 20.0, 20.0, 16, 16)
    cams = camera_array([camera], device)
    pixels = 256

    def ints(values):
        return wp.array(np.asarray(values, np.int32), dtype=wp.int32, device=device)

    # each entry an opaque-ish disc over the whole tile, its pixel (x, y)'s slot 256 k + 16 y + x
    e_xy = wp.array(np.full((4, 2), 7.5, np.float32), dtype=wp.vec2, device=device)
    e_co = wp.array(np.tile(np.float32([1e-4, 0.0, 1e-4, 0.3]), (4, 1)), dtype=wp.vec4, device=device)
    e_rgb = wp.array(np.tile(np.float32([1.0, 0.5, 0.25]), (4, 1)), dtype=wp.vec3, device=device)
    e_box = wp.array(np.tile(np.float32([0.0, 15.0, 0.0, 15.0]), (4, 1)), dtype=wp.vec4, device=device)
    e_faint = wp.array(np.full(4, -1e30, np.float32), dtype=wp.float32, device=device)
    slot_ends = ints(np.arange(1, 5) * pixels)
    ranges = [ints([2]), ints([0, 0]), ints([0, 2]), ints([2, 4])]  # chunk_ends, chunk_tile, chunk_first, chunk_last
    before = np.ones(2 * pixels, np.float32)
    before[pixels:] = 0.0  # the second chunk: nothing gets through
    before = wp.array(before, dtype=wp.float32, device=device)
    weights = wp.full(4 * pixels, float("nan"), dtype=wp.float32, device=device)
    colour = wp.empty(2 * pixels, dtype=wp.vec4, device=device)
    chunk_stop = wp.full(2 * pixels, -7, dtype=wp.int32, device=device)
    own = wp.full(2 * pixels, float("nan"), dtype=wp.float32, device=device)
    tile_start, tile_end = ints([0]), ints([4])
    # the first chunk is walked with its own transmittance, the second (its transmittance before set to 0) after
    wp.launch(grad_kernels.chunk_own_transmittance, 2 * pixels,
              inputs=[0, e_xy, e_co, e_rgb, e_box, e_faint, tile_start, tile_end, *ranges, cams, 1, 1, 1, slot_ends, weights,
                      own, colour, chunk_stop],
              device=device)  # fmt: skip
    wp.launch(grad_kernels.composite_chunk_weights, 2 * pixels,
              inputs=[0, e_xy, e_co, e_rgb, e_box, e_faint, tile_start, *ranges, before, cams, 1, 1, 1, slot_ends, weights, colour,
                      chunk_stop],
              device=device)  # fmt: skip
    # the first chunk's own transmittance is its walk's (the same products), the last chunk's is not made
    own = own.numpy().reshape(2, pixels)
    assert own[0].tobytes() == colour.numpy().reshape(2, pixels, 4)[0, :, 3].tobytes() and np.isnan(own[1]).all()
    stops_by_chunk = chunk_stop.numpy().reshape(2, pixels)
    assert (stops_by_chunk[0] == 2).all() and (stops_by_chunk[1] == 2).all()  # no stop in the first; the second skipped
    w = weights.numpy().reshape(4, pixels)
    assert np.isfinite(w[:2]).all() and (w[:2] > 0).all() and np.isnan(w[2:]).all()
    colours = colour.numpy().reshape(2, pixels, 4)
    assert (colours[0, :, 3] > 0.0).all() and (colours[1] == [0.0, 0.0, 0.0, -1.0]).all()
    image = wp.full((1, 16, 16, 3), float("nan"), dtype=wp.float32, device=device)
    stops = wp.full(pixels, -7, dtype=wp.int32, device=device)
    wp.launch(grad_kernels.merge_chunk_weights, pixels,
              inputs=[0, colour, before, chunk_stop, ints([2]), ranges[0], ints([4]), cams, 1, 1, wp.vec3(0.0, 0.0, 1.0), image, stops],
              device=device)  # fmt: skip
    assert (stops.numpy() == 2).all()
    expected = colours[0, :, :3] + np.float32([0.0, 0.0, 1.0]) * colours[0, :, 3:4]
    assert image.numpy().reshape(pixels, 3).tobytes() == expected.astype(np.float32).tobytes()
