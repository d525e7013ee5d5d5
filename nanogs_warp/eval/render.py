"""Renders a splat set from pinhole cameras: the standard 3DGS forward rasteriser, on the splats' device.

Once per splat set ``splat_shapes`` (each splat's 3D covariance, opacity and reach), then per view:
``project`` (one thread per splat: cull, EWA 2D covariance, SH colour, tile rectangle and the count
of its tiles that the splat's ellipse reaches), an inclusive scan of those counts, ``emit_entries``
(one (tile, depth) key per reached tile), a stable
radix sort of the keys, ``gather_entries`` (entry-ordered splat data and per-tile ranges) and the
composite: on a GPU one thread per pixel and chunk of its tile's entries, the chunks merged in order
(``composite_chunks``, ``composite_merge``); on the CPU one thread per tile (``composite_tiles``),
with the chunks' arithmetic, so that every device renders the same bits. The conventions are
documented in ``kernels/render.py``.
Views are rendered into one device array and copied to the host once per ``render_views`` call.

On the CPU a launch runs on one core, so the splat-, entry- and pixel-parallel kernels are launched
in chunks from one thread per core (they use no atomics, so the chunks are independent).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import warp as wp

from ..device import device_memory
from ..errors import InputError
from ..kernels import render as kernels
from ..parallel import chunk_launches, cpu_workers, launch_chunks_in_turn
from ..splats import SplatSet
from .cameras import Camera

TILE = 16
# Bytes a (tile, splat) entry takes in the entry buffers: its key and value twice (the radix sort's
# second buffer), then its 2D mean, conic and opacity, colour, box and faint power.
ENTRY_BYTES = 2 * 8 + 2 * 4 + 8 + 16 + 12 + 16 + 4
INDEX_LIMIT = 2**31 - 1  # entries are indexed with int32
# On the GPU a tile's entries are composited in chunks of at most this many, one block each
# (``kernels/render.py``, ``chunk_counts`` to ``composite_merge``): a tile whose list is far longer
# than the others' (a dense cluster seen end-on: 600k entries in one tile of a 6M-splat scene at
# 256 x 256) no longer keeps one block walking it while the rest of the GPU waits.
CHUNK_ENTRIES = 2048
ONE_WALK = 2**31 - 1  # a chunk no tile exceeds: every tile composited in one walk
# On the CPU a launch is cut into this many chunks per worker thread (``_Rasteriser._launch``):
# guitar's and playbot's eight size-fit views 0.46-0.54 -> 0.40 s and 0.87-1.09 -> 0.84-0.85 s on two
# cores against one chunk per worker, the same images.
CHUNKS_PER_WORKER = 4
# ... and each chunk holds at least this many (entry, pixel) pairs of a composite (each a few ns on
# a core), or PROJECT_ROWS splats, EMIT_ROWS splats' entries or GATHER_ROWS entries: a chunk's
# launch holds the GIL for some microseconds, so on many cores the small views of a fit's small
# outputs went out in dozens of chunks of almost no work each, queueing for it.
PAIRS_PER_CHUNK = 1 << 16
PROJECT_ROWS = 1024
EMIT_ROWS = 4096
GATHER_ROWS = 16384


def key_bits(tiles: int) -> int:
    """The bits of an entry's key that the sort orders by: 32 of depth and those of the tile index."""
    return 32 + max(1, int(tiles - 1).bit_length())


def entry_memory(device) -> int:
    """Bytes a view's entry buffers may take on ``device``: half of the memory free now (``device_memory``)."""
    available = device_memory(device)
    if available is None:  # not on this system: no memory bound but int32's
        return INDEX_LIMIT * ENTRY_BYTES
    return available // 2


def rows_per_chunk(rows: int, entries: int) -> int:
    """The fewest rows (tiles, lanes or pixels) a CPU chunk of a composite over ``rows`` rows takes,
    so that it holds about PAIRS_PER_CHUNK (entry, pixel) pairs when ``entries`` (tile, splat)
    entries are composited over their tiles' pixels."""
    return max(1, -(-PAIRS_PER_CHUNK * rows // max(1, entries * kernels.TILE_PIXELS)))


def tile_count(pixels: int) -> int:
    """The 16-pixel tiles that cover ``pixels`` pixels of a row or column."""
    return (int(pixels) + TILE - 1) // TILE


def camera_params(camera: Camera) -> kernels.CameraParams:
    """The kernels' view of ``camera``."""
    rotation = np.asarray(camera.rotation, np.float64).reshape(3, 3)
    translation = np.asarray(camera.translation, np.float64).reshape(3)
    p = kernels.CameraParams()
    p.rotation = wp.mat33(*rotation.ravel().tolist())
    p.translation = wp.vec3(*translation.tolist())
    p.centre = wp.vec3(*(-rotation.T @ translation).tolist())
    p.fx, p.fy = float(camera.fx), float(camera.fy)
    p.cx, p.cy = float(camera.cx), float(camera.cy)
    p.lim_x = 1.3 * 0.5 * camera.width / float(camera.fx)
    p.lim_y = 1.3 * 0.5 * camera.height / float(camera.fy)
    p.width, p.height = int(camera.width), int(camera.height)
    p.tiles_x, p.tiles_y = tile_count(p.width), tile_count(p.height)
    p.near = float(camera.near)
    return p


def _check_camera(camera: Camera) -> None:
    if int(camera.width) < 1 or int(camera.height) < 1:
        raise InputError(f"camera {camera.name!r}: image size {camera.width}x{camera.height} is empty")
    if not (camera.fx > 0 and camera.fy > 0):
        raise InputError(f"camera {camera.name!r}: focal lengths must be positive")


class _Rasteriser:
    """Buffers for one splat set on one device, reused across views (entry buffers grow as needed)."""

    def __init__(self, splats: SplatSet, workers: int | None = None, method: str | None = None,
                 max_entries: int | None = None, chunk: int = CHUNK_ENTRIES):  # fmt: skip
        self.splats = splats
        self.chunk = int(chunk)  # entries a chunk of a tile's list holds ("pixels" method)
        if self.chunk < 1:
            raise ValueError(f"a chunk holds at least one entry, got {chunk}")
        self.max_entries = max_entries  # a view whose tile rectangles hold more (tile, splat) pairs raises InputError
        self.areas = self.area_ends = None  # ``_rectangle_pairs``' rows
        self.device = splats.device
        self.n = splats.count
        self.degree = splats.sh_degree
        if workers is None:
            workers = cpu_workers() if self.device.is_cpu else 1
        self.workers = workers
        if method is None:
            method = "tiles" if self.device.is_cpu else "pixels"
        if method not in ("tiles", "pixels"):
            raise ValueError(f"composite method {method!r}: expected 'tiles' or 'pixels'")
        self.method = method
        self.rows = 0
        self._reserve_rows(self.n)
        self.capacity = 0
        self.chunk_capacity = 0
        self.entry_bytes = ENTRY_BYTES  # what an entry takes in this rasteriser's buffers
        self.tile_start = self.tile_end = None
        self.counts = None
        self.shapes = None  # ``_shapes``
        wp.load_module(kernels, device=self.device)

    def _reserve_rows(self, rows: int) -> None:
        """Room for ``rows`` projected splats (a row per splat and view rendered together)."""
        if rows <= self.rows and self.rows > 0:
            return
        self.rows = rows
        d = self.device
        self.xy = wp.empty(rows, dtype=wp.vec2, device=d)
        self.depth = wp.empty(rows, dtype=wp.float32, device=d)
        self.conic_opacity = wp.empty(rows, dtype=wp.vec4, device=d)
        self.rgb = wp.empty(rows, dtype=wp.vec3, device=d)
        self.box = wp.empty(rows, dtype=wp.vec4, device=d)
        self.faint = wp.empty(rows, dtype=wp.float32, device=d)
        self.rect = wp.empty(rows, dtype=wp.vec4i, device=d)
        self.touched = wp.empty(rows, dtype=wp.int32, device=d)
        self.ends = wp.empty(rows, dtype=wp.int32, device=d)

    def _reserve(self, entries: int) -> None:
        if entries <= self.capacity:
            return
        self.capacity = max(entries, int(self.capacity * 1.5), 1024)
        c, d = self.capacity, self.device
        self.keys = wp.empty(2 * c, dtype=wp.int64, device=d)
        self.values = wp.empty(2 * c, dtype=wp.int32, device=d)
        self.e_xy = wp.empty(c, dtype=wp.vec2, device=d)
        self.e_conic_opacity = wp.empty(c, dtype=wp.vec4, device=d)
        self.e_rgb = wp.empty(c, dtype=wp.vec3, device=d)
        self.e_box = wp.empty(c, dtype=wp.vec4, device=d)
        self.e_faint = wp.empty(c, dtype=wp.float32, device=d)

    def _launch(self, kernel, dim: int, inputs_before: list, inputs_after: list, min_rows: int = 1) -> None:
        """Launches ``kernel`` over ``dim`` threads whose first argument after ``inputs_before`` is the
        first thread's index; on the CPU in up to CHUNKS_PER_WORKER chunks per worker thread of at
        least ``min_rows`` threads each, taken as the workers free up (a view's busy tiles lie
        together, so one chunk each left a worker idle)."""
        chunks = min(self.workers * CHUNKS_PER_WORKER, dim // max(1, min_rows))
        if self.workers <= 1 or dim < 64 or chunks <= 1:
            wp.launch(kernel, dim, inputs=[*inputs_before, 0, *inputs_after], device=self.device)
            return
        bounds = np.linspace(0, dim, chunks + 1).astype(int)
        ranges = [(int(lo), int(hi)) for lo, hi in zip(bounds, bounds[1:]) if hi > lo]
        inputs = [*inputs_before, 0, *inputs_after]
        launch_chunks_in_turn(min(self.workers, chunks), chunk_launches(kernel, ranges, inputs, len(inputs_before), self.device))

    def _project(self, p, tiles: int, kernel=kernels.project, rows: int | None = None, views: str | None = None) -> int:
        """Clears (or makes) the per-tile entry ranges for ``tiles`` tiles and projects every splat
        for camera ``p`` (``kernel``: ``project``; ``project_views`` for an array of cameras, ``rows``
        = views x splats, ``views`` naming them in an error); returns the number of (tile, splat)
        entries the view(s) need."""
        s = self.splats
        rows = self.n if rows is None else rows
        if self.tile_start is None or self.tile_start.shape[0] < tiles:
            self.tile_start = wp.zeros(tiles, dtype=wp.int32, device=self.device)
            self.tile_end = wp.zeros(tiles, dtype=wp.int32, device=self.device)
            if self.method == "tiles":
                pixels = tiles * kernels.TILE_PIXELS
                self.transmittance = wp.empty(pixels, dtype=wp.float32, device=self.device)
                self.colour = wp.empty(pixels, dtype=wp.vec3, device=self.device)
                self.done = wp.empty(pixels, dtype=wp.int32, device=self.device)
                self.chunk_state = wp.empty(pixels, dtype=wp.vec2, device=self.device)
                self.total = wp.empty(pixels, dtype=wp.vec3, device=self.device)
        else:
            self.tile_start.zero_()
            self.tile_end.zero_()
        if self.n == 0:
            return 0
        self._launch(
            kernel,
            rows,
            [s.means, self._shapes(), s.features, self.degree, p],
            [self.xy, self.depth, self.conic_opacity, self.rgb, self.box, self.faint, self.rect, self.touched],
            PROJECT_ROWS,
        )
        wp.utils.array_scan(self.touched[:rows], self.ends[:rows], inclusive=True)
        if rows * tiles <= INDEX_LIMIT:
            count = int(self.ends[rows - 1 : rows].numpy()[0])
        else:  # the int32 running sum may have wrapped: the total in int64, on the host
            count = int(self.touched[:rows].numpy().sum(dtype=np.int64))
        views = views or f"a {p.width}x{p.height} view"
        if self.max_entries is not None:
            pairs = self._rectangle_pairs(rows, tiles)
            if pairs > self.max_entries:
                raise InputError(f"{views} of these {self.n:,} splats spans {pairs:,} (tile, splat) pairs, more than the "
                                 f"{self.max_entries:,} this render allows")  # fmt: skip
        limit = min(INDEX_LIMIT, max(self.capacity, entry_memory(self.device) // self.entry_bytes))  # what it holds, or can
        if count > limit:
            raise InputError(
                f"{views} of these {self.n:,} splats cover{'s' if rows == self.n else ''} {count:,} (tile, splat) pairs "
                f"({count * self.entry_bytes / 2**30:.1f} GiB); {self.device} has room for {limit:,}: "
                "render smaller images (eval --size, --refine-size)"
            )
        return count

    def _rectangle_pairs(self, rows: int, tiles: int) -> int:
        """The (tile, splat) pairs of the ``rows`` projected rows' whole tile rectangles: what ``max_entries``
        bounds. A view's entries leave out the tiles a splat's ellipse misses, but each entry's walk
        still visits every pixel of its box in its tile, so a thin strand across the view costs about
        its rectangle's pairs all the same, and the bound counts those."""
        if self.areas is None or self.areas.shape[0] < rows:
            self.areas = wp.empty(rows, dtype=wp.int32, device=self.device)
            self.area_ends = wp.empty(rows, dtype=wp.int32, device=self.device)
        self._launch(kernels.rect_areas, rows, [], [self.rect, self.areas], PROJECT_ROWS)
        if rows * tiles > INDEX_LIMIT:  # an int32 running sum could wrap: the total in int64, on the host
            return int(self.areas[:rows].numpy().sum(dtype=np.int64))
        wp.utils.array_scan(self.areas[:rows], self.area_ends[:rows], inclusive=True)
        return int(self.area_ends[rows - 1 : rows].numpy()[0])

    def _shapes(self, again: bool = False) -> wp.array:
        """Each splat's view-independent terms (``kernels.splat_shapes``), made on first use and read by
        every view projected after (so the splats must not change in between); ``again``: made anew."""
        if self.shapes is None or again:
            s = self.splats
            if self.shapes is None:
                self.shapes = wp.empty(self.n, dtype=kernels.vec8, device=self.device)
            self._launch(kernels.splat_shapes, self.n, [], [s.rotations, s.log_scales, s.opacities, self.shapes], PROJECT_ROWS)
        return self.shapes

    def render_into(self, camera: Camera, background: wp.vec3, image: wp.array, view: int) -> None:
        """Composites view ``view`` of ``image`` (V, H, W, 3) from ``camera``."""
        p = camera_params(camera)
        tiles = p.tiles_x * p.tiles_y
        count = self._project(p, tiles)
        if count > 0:
            self._reserve(count)
            self._launch(
                kernels.emit_entries,
                self.n,
                [self.depth, self.xy, self.conic_opacity, self.faint, self.rect, self.touched, self.ends, p.tiles_x, self.n, tiles],
                [self.keys, self.values],
                EMIT_ROWS,
            )
            wp.utils.radix_sort_pairs(self.keys, self.values, count, 0, key_bits(tiles))
            self._launch(
                kernels.gather_entries,
                count,
                [self.keys, self.values, count, self.xy, self.conic_opacity, self.rgb, self.box, self.faint],
                [self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint, self.tile_start, self.tile_end],
                GATHER_ROWS,
            )
            entries = [self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint]
        else:  # no entries: every tile range is empty; any arrays of the right type will do
            entries = [self.xy, self.conic_opacity, self.rgb, self.box, self.faint]
        inputs = [*entries, self.tile_start, self.tile_end]
        inputs += [p.width, p.height, p.tiles_x, background, view, tiles]
        if self.method == "tiles":
            self._composite_tiles(tiles, count, inputs, self.chunk, image)
        else:
            self._composite_in_chunks(p, tiles, count, inputs, image)

    def _composite_tiles(self, tiles: int, count: int, inputs: list, chunk: int, image: wp.array) -> None:
        """``composite_tiles`` (the CPU's composite, one thread per tile) of ``count`` entries, each
        tile of more than ``chunk`` entries composited in chunks with the GPU's arithmetic."""
        scratch = [self.transmittance, self.colour, self.done, self.chunk_state, self.total, image]
        self._launch(kernels.composite_tiles, tiles, [*inputs, chunk], scratch, rows_per_chunk(tiles, count))

    def _chunk_counts(self, tiles: int) -> None:
        """Each of ``tiles`` tiles' chunks of at most ``self.chunk`` entries (``counts``) and the most
        entries a tile holds (``longest``, on the device)."""
        if self.counts is None or self.counts.shape[0] < tiles:
            self.counts = wp.empty(tiles, dtype=wp.int32, device=self.device)
            self.chunk_ends = wp.empty(tiles, dtype=wp.int32, device=self.device)
            self.longest = wp.empty(1, dtype=wp.int32, device=self.device)
        self.longest.zero_()
        self._launch(kernels.chunk_counts, tiles, [self.tile_start, self.tile_end, self.chunk], [self.counts, self.longest])

    def _chunk_ranges(self, tiles: int, count: int) -> int:
        """After ``_chunk_counts``: the chunks' tiles and entry ranges, in tile order, and room for a
        colour, a transmittance and a stop per (chunk, pixel). Returns a bound on the chunk count
        (a tile of n entries has at most n / chunk + 1) for the chunk launches, so that the count is
        never read back: the threads beyond the last chunk return at once."""
        wp.utils.array_scan(self.counts[:tiles], self.chunk_ends[:tiles], inclusive=True)
        chunks = count // self.chunk + tiles
        if chunks > self.chunk_capacity or self.chunk_capacity == 0:
            self.chunk_capacity = max(chunks, int(self.chunk_capacity * 1.5), 64)
            c, d, pixels = self.chunk_capacity, self.device, kernels.TILE_PIXELS
            self.chunk_tile = wp.empty(c, dtype=wp.int32, device=d)
            self.chunk_first = wp.empty(c, dtype=wp.int32, device=d)
            self.chunk_last = wp.empty(c, dtype=wp.int32, device=d)
            self.chunk_before = wp.empty(c * pixels, dtype=wp.float32, device=d)
            self.chunk_colour = wp.empty(c * pixels, dtype=wp.vec4, device=d)
            self.chunk_stop = wp.empty(c * pixels, dtype=wp.int32, device=d)
        self._launch(kernels.chunk_ranges, tiles, [self.tile_start, self.tile_end, self.counts, self.chunk_ends, self.chunk],
                     [self.chunk_tile, self.chunk_first, self.chunk_last])  # fmt: skip
        return chunks

    def _composite_in_chunks(self, p, tiles: int, count: int, inputs: list, image: wp.array) -> None:
        """``composite``'s image, each tile's entries split into chunks of at most ``self.chunk``
        composited in parallel and then merged (``kernels/render.py``); ``composite`` itself where
        no tile holds more (five launches fewer, which is most of a small scene's view). ``inputs``:
        ``composite``'s arguments before the first thread's index."""
        pixels = kernels.TILE_PIXELS
        self._chunk_counts(tiles)
        if int(self.longest.numpy()[0]) <= self.chunk:  # every tile is one chunk: the one walk, the same bits
            self._launch(kernels.composite, tiles * pixels, inputs, [image], rows_per_chunk(tiles * pixels, count))
            return
        e_xy, e_co, e_rgb, e_box, e_faint = inputs[:5]
        background, view = inputs[-3:-1]
        chunks = self._chunk_ranges(tiles, count)
        ranges = [self.chunk_ends, self.chunk_tile, self.chunk_first, self.chunk_last]
        size = [p.width, p.height, p.tiles_x]
        self._launch(kernels.chunk_transmittance, chunks * pixels,
                     [e_xy, e_co, e_rgb, e_box, e_faint, self.tile_start, self.tile_end, *ranges, *size, tiles],
                     [self.chunk_before, self.chunk_colour])  # fmt: skip
        self._launch(kernels.chunk_prefix, tiles * pixels, [self.counts, self.chunk_ends], [self.chunk_before])
        self._launch(kernels.composite_chunks, chunks * pixels,
                     [e_xy, e_co, e_rgb, e_box, e_faint, self.tile_start, *ranges, self.chunk_before, *size, tiles],
                     [self.chunk_colour])  # fmt: skip
        self._launch(kernels.composite_merge, tiles * pixels,
                     [self.chunk_colour, self.chunk_before, self.counts, self.chunk_ends, *size, background, view], [image])  # fmt: skip


def _background(background) -> wp.vec3:
    values = [float(v) for v in background]
    if len(values) != 3:
        raise InputError(f"background {background!r}: expected three values (R, G, B)")
    return wp.vec3(*values)


def render(splats: SplatSet, camera: Camera, background=(0.0, 0.0, 0.0)) -> wp.array:
    """Renders one view: a float32 ``wp.array`` of shape (H, W, 3) on the splats' device (linear RGB,
    not clamped to [0, 1]; ``.numpy()`` copies it to the host)."""
    _check_camera(camera)
    image = wp.full((1, camera.height, camera.width, 3), float("nan"), dtype=wp.float32, device=splats.device)
    _Rasteriser(splats).render_into(camera, _background(background), image, 0)
    return image.reshape((camera.height, camera.width, 3))


def render_views(splats: SplatSet, cameras: Sequence[Camera], background=(0.0, 0.0, 0.0),
                 max_entries: int | None = None) -> np.ndarray:  # fmt: skip
    """Renders every camera (all of one image size) into one device array and copies it to the host
    once: float32 (V, H, W, 3). A view whose splats' tile rectangles hold more than ``max_entries``
    (tile, splat) pairs (``_Rasteriser._rectangle_pairs``), or whose entries the device cannot hold,
    raises InputError."""
    return render_views_on_device(splats, cameras, background, max_entries).numpy()


def render_views_on_device(splats: SplatSet, cameras: Sequence[Camera], background=(0.0, 0.0, 0.0),
                           max_entries: int | None = None) -> wp.array:  # fmt: skip
    """``render_views``, the images left on the splats' device: a float32 ``wp.array`` (V, H, W, 3)."""
    cameras = list(cameras)
    if not cameras:
        raise InputError("no cameras to render")
    for camera in cameras:
        _check_camera(camera)
    sizes = {(int(c.width), int(c.height)) for c in cameras}
    if len(sizes) != 1:
        raise InputError(f"render_views needs cameras of one image size, got {sorted(sizes)}")
    (width, height), bg = sizes.pop(), _background(background)
    images = wp.full((len(cameras), height, width, 3), float("nan"), dtype=wp.float32, device=splats.device)
    rasteriser = _Rasteriser(splats, max_entries=max_entries)
    for view, camera in enumerate(cameras):
        rasteriser.render_into(camera, bg, images, view)
    return images
