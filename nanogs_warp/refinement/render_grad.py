"""The differentiable rasteriser: ``eval/render.py``'s forward pass, which keeps what the backward pass needs,
and the backward pass (``kernels/render_grad.py``) from dL/dimage to every splat parameter.

The forward launches ``eval/render.py``'s kernels in the same order on the same data, so the image is the
renderer's, bit for bit (where a tile holds more than ``CHUNK_ENTRIES`` entries, the renderer
composites it in chunks and the two differ by float32 rounding; the backward replays this forward's
single walk, ``composite``, which every device computes alike); the only addition is a numbering of
the emitted entries, so that after the sort each splat's entries can be found in emit order. Where
no backward walks the tiles again (a held-out view, or the colours' backward from weights the
forward kept), the forward composites long tiles in chunks as the renderer does.
Gradients are summed in a fixed order (per entry over each of the tile's ``LANES`` lanes' pixel rows
in row order, then the lanes in order; per splat over its entries in emit order; per view in the
order views are back-propagated) with the portable float32 arithmetic of ``kernels/render.py``, so
every device, and every rerun, gives the same bytes. A GPU computes each (entry, pixel) term on a
thread of its own and sums them afterwards in that order (``per_pixel``); where those terms would not
fit its memory, it sums them as the CPU does, one thread per tile.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import warp as wp

from ..eval.cameras import Camera
from ..eval.render import (
    EMIT_ROWS, GATHER_ROWS, INDEX_LIMIT, ONE_WALK, _Rasteriser, camera_params, entry_memory, key_bits, rows_per_chunk,
    tile_count,
)
from ..kernels import render as kernels
from ..kernels import render_grad as grad_kernels
from ..parallel import launch_rows_from
from ..splats import SplatSet


@dataclass
class SplatGradients:
    """dL/d(parameter) for each differentiable splat array, same shapes and types as the SplatSet's."""

    means: wp.array
    rotations: wp.array
    log_scales: wp.array
    opacities: wp.array
    features: wp.array

    @staticmethod
    def zeros_like(splats: SplatSet) -> SplatGradients:
        d, n = splats.device, splats.count
        return SplatGradients(
            means=wp.zeros(n, dtype=wp.vec3, device=d),
            rotations=wp.zeros(n, dtype=wp.quat, device=d),
            log_scales=wp.zeros(n, dtype=wp.vec3, device=d),
            opacities=wp.zeros(n, dtype=wp.float32, device=d),
            features=wp.zeros(splats.features.shape, dtype=wp.float32, device=d),
        )

    def arrays(self) -> tuple[wp.array, ...]:
        return (self.means, self.rotations, self.log_scales, self.opacities, self.features)

    def zero_(self) -> None:
        for a in self.arrays():
            a.zero_()


# Bytes an entry adds for the backward pass (``_reserve_grad``): three int32 indices and its
# gradients (2D mean, conic, opacity, colour); and per lane where several threads share a tile.
GRAD_ENTRY_BYTES = 3 * 4 + 8 + 12 + 4 + 12
LANE_BYTES = 8 + 12 + 4 + 12


# Bytes the per-pixel slots add: per entry its area and its slots' end; per (entry, pixel) pair its
# weight (``forward``'s ``keep_weights``) and, for the per-pixel backward, its terms.
PIXEL_ENTRY_BYTES = 2 * 4
WEIGHT_BYTES = 4
PIXEL_BYTES = 8 + 12 + 4 + 12


# The CPU keeps a view's weights (``forward``'s ``keep_weights``) only while its entries reach at most
# this many pixels a pixel on average (their slots): beyond, writing and reading the weights back costs
# more than walking the tiles again. The 10 % output of playbot (500k splats) has 58 a pixel, and its
# run is 7 % faster for keeping them; a fuzz case whose splats outgrow a 20,000-splat scene has
# 1,000-1,600, and its run took 49 s and 2.2 GB with them against 43 s and 0.65 GB without
# (docs/performance.md).
KEPT_PAIRS_PER_PIXEL = 256


def camera_array(cameras: Sequence[Camera], device) -> wp.array:
    """The cameras' ``camera_params`` in one array on ``device``."""
    return wp.array([camera_params(c) for c in cameras], dtype=kernels.CameraParams, device=device)


LANES = 16  # the backward's threads per tile (each owns every 16th row): a GPU's, and the CPU's too


class GradRasteriser(_Rasteriser):
    """Renders one view at a time of a splat set whose parameters may change between views, and
    back-propagates dL/dimage of the last view rendered."""

    def __init__(
        self, splats: SplatSet, workers: int | None = None, method: str | None = None, lanes: int | None = None,
        lanes_in_turn: bool | None = None, per_pixel: bool | None = None,
    ):  # fmt: skip
        super().__init__(splats, workers, method)
        if lanes is None:
            # threads per tile in the backward pass, on every device: a lane sums its own rows, so
            # the lane count fixes the gradients' summation order (the same bits on the CPU and a GPU)
            lanes = LANES
        if lanes not in (1, 2, 4, 8, 16):
            raise ValueError(f"lanes {lanes}: expected 1, 2, 4, 8 or 16")
        self.lanes = lanes
        if per_pixel is None:  # a GPU: a thread per pixel, the terms summed as 16 lanes sum them
            per_pixel = not self.device.is_cpu and lanes == LANES
        if per_pixel and lanes != LANES:
            raise ValueError(f"the per-pixel backward sums as {LANES} lanes do, not {lanes}")
        self.per_pixel = per_pixel
        if lanes_in_turn is None:  # the CPU: one thread per tile sums its lanes in turn, the same sums
            lanes_in_turn = self.device.is_cpu or per_pixel  # (per pixel: where its buffers do not fit)
        self.lanes_in_turn = lanes_in_turn and lanes > 1
        self.lane_buffers = lanes > 1 and not self.lanes_in_turn
        self.entry_bytes += GRAD_ENTRY_BYTES + (lanes * LANE_BYTES if self.lane_buffers else 0)
        self.entry_bytes += PIXEL_ENTRY_BYTES
        self.pair_bytes = WEIGHT_BYTES + (PIXEL_BYTES if per_pixel else 0)
        self.pixel_capacity = 0
        self.stops = None  # per pixel of the last view, the entry its per-pixel backward finished at
        self.weights_kept = False  # whether the last forward kept its weights (``forward``'s ``keep_weights``)
        wp.load_module(grad_kernels, device=self.device)
        self.grad_capacity = 0
        self.scratch_pixels = 0
        self.chunk_scratch_pixels = 0
        self.count = 0

    def _reserve_grad(self, entries: int) -> None:
        if entries <= self.grad_capacity:
            return
        c, d = self.capacity, self.device  # the forward buffers' capacity, >= entries
        self.grad_capacity = c
        self.slot_splat = wp.empty(c, dtype=wp.int32, device=d)
        self.entry_splat = wp.empty(c, dtype=wp.int32, device=d)
        self.entry_of_slot = wp.empty(c, dtype=wp.int32, device=d)
        self.e_g_xy = wp.empty(c, dtype=wp.vec2, device=d)
        self.e_g_conic = wp.empty(c, dtype=wp.vec3, device=d)
        self.e_g_opacity = wp.empty(c, dtype=wp.float32, device=d)
        self.e_g_rgb = wp.empty(c, dtype=wp.vec3, device=d)
        self.areas = wp.empty(c, dtype=wp.int32, device=d)
        self.slot_ends = wp.empty(c, dtype=wp.int32, device=d)
        if self.lane_buffers:
            lanes = c * self.lanes
            self.lane_xy = wp.empty(lanes, dtype=wp.vec2, device=d)
            self.lane_conic = wp.empty(lanes, dtype=wp.vec3, device=d)
            self.lane_opacity = wp.empty(lanes, dtype=wp.float32, device=d)
            self.lane_rgb = wp.empty(lanes, dtype=wp.vec3, device=d)

    def _rows(self, kernel, rows: int, inputs: list, min_rows: int) -> None:
        """``kernel(first, *inputs)`` over ``rows`` rows, split over CPU cores when worthwhile."""
        if rows > 0:
            launch_rows_from(kernel, rows, inputs, self.device, min_rows=min_rows)

    def forward(
        self, cameras: Sequence[Camera], background: wp.vec3, image: wp.array, params: wp.array | None = None,
        keep_weights: bool = False, walked_back: bool = True,
    ) -> None:  # fmt: skip
        """Renders ``cameras`` together into ``image`` (V, H, W, 3; H, W at least the largest view's),
        view v into the top-left corner of image[v], and keeps the views' entries for ``backward``.
        Each view's pixels are ``render.render``'s of that camera alone, bit for bit (the views'
        splats are projected into rows of their own and their tiles numbered one view after the
        other: ``kernels/render.py``), where a backward may walk the tiles again (``walked_back``)
        as one walk each, except in tiles of more than ``CHUNK_ENTRIES`` entries (the module's
        docstring); outside a view's own size image[v] holds nothing of use. ``walked_back=False``
        with one camera: no backward follows (a held-out view's loss), and the view is composited
        as the renderer composites it, long tiles in chunks side by side.
        ``params``: the cameras' ``camera_params`` already on the device (``camera_array``), else
        made here (a copy to the device, which waits for it). ``keep_weights``: for a backward of
        the colours alone (``backward``'s ``colours_only``), the composite keeps each entry's weight
        at each pixel (``_composite_weights_in_chunks`` on a GPU, ``composite_tile_weights`` on the CPU;
        the same pixels and weights), so that that backward need not walk the tiles again; its tiles
        of more than ``CHUNK_ENTRIES`` entries are composited in chunks side by side, as
        ``render.render`` composites them."""
        views, n = len(cameras), self.n
        tiles_x = max(tile_count(c.width) for c in cameras)
        view_tiles = tiles_x * max(tile_count(c.height) for c in cameras)
        tiles = views * view_tiles
        self.cams = camera_array(cameras, self.device) if params is None else params
        self._reserve_rows(views * n)
        named = f"a {cameras[0].width}x{cameras[0].height} view" if views == 1 else f"{views} views"
        self._shapes(again=True)  # the splats may have changed since the last forward
        count = self._project(self.cams, tiles, kernels.project_views, views * n, named)
        if count > 0:
            self._reserve(count)
            self._reserve_grad(count)
            self._launch(
                kernels.emit_entries,
                views * n,
                [self.depth, self.xy, self.conic_opacity, self.faint, self.rect, self.touched, self.ends, tiles_x, n, view_tiles],
                [self.keys, self.values],
                EMIT_ROWS,
            )
            self._rows(grad_kernels.number_slots, count, [self.values, self.slot_splat], 16384)
            wp.utils.radix_sort_pairs(self.keys, self.values, count, 0, key_bits(tiles))
            self._rows(
                grad_kernels.order_entries, count, [self.values, self.slot_splat, self.entry_splat, self.entry_of_slot], 16384
            )
            self._launch(
                kernels.gather_entries,
                count,
                [self.keys, self.entry_splat, count, self.xy, self.conic_opacity, self.rgb, self.box, self.faint],
                [self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint, self.tile_start, self.tile_end],
                GATHER_ROWS,
            )
            entries = [self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint]
        else:
            entries = [self.xy, self.conic_opacity, self.rgb, self.box, self.faint]
        inputs = [*entries, self.tile_start, self.tile_end]
        inputs += [image.shape[2], image.shape[1], tiles_x, background, 0, view_tiles]
        self.weights_kept = keep_weights and count > 0 and self._reserve_slots(count, tiles, tiles_x, view_tiles)
        if self.weights_kept:
            weighted = [*entries, self.tile_start, self.tile_end, self.cams, tiles_x, view_tiles, background, self.slot_ends]
            pixels = tiles * kernels.TILE_PIXELS
            if self.per_pixel:  # a GPU: a thread per (chunk, pixel)
                self._composite_weights_in_chunks(entries, tiles, tiles_x, view_tiles, count, background, image)
            else:  # the CPU: a thread per tile, entry by entry
                self._reserve_scratch(pixels)
                self._reserve_chunk_scratch(pixels)
                self._rows(
                    grad_kernels.composite_tile_weights, tiles,
                    [*weighted, self.chunk, self.bw_transmittance, self.bw_front, self.bw_done, self.bw_chunk_state, self.bw_total,
                     image, self.p_weight, self.stops],
                    rows_per_chunk(tiles, count),
                )  # fmt: skip
        elif not walked_back and views == 1:  # ``render.render``'s image: no walk is replayed
            if self.method == "tiles":
                self._composite_tiles(tiles, count, inputs, self.chunk, image)
            else:
                self._composite_in_chunks(camera_params(cameras[0]), tiles, count, inputs, image)
        elif self.method == "tiles":
            self._composite_tiles(tiles, count, inputs, ONE_WALK, image)  # the backward replays one walk
        else:
            pixels = tiles * kernels.TILE_PIXELS
            self._launch(kernels.composite, pixels, inputs, [image], rows_per_chunk(pixels, count))
        self.count, self.tiles, self.tiles_x, self.view_tiles = count, tiles, tiles_x, view_tiles

    def _composite_weights_in_chunks(
        self, entries: list, tiles: int, tiles_x: int, view_tiles: int, count: int, background: wp.vec3, image: wp.array
    ) -> None:  # fmt: skip
        """The forward's image, weights and stops (``keep_weights``) on a GPU, each tile's entries cut into
        chunks of at most ``self.chunk`` walked side by side (``render.render``'s chunks, for several
        views: ``kernels/render_grad.py``'s ``chunk_own_transmittance`` to ``merge_chunk_weights``).
        A tile of one chunk is ``render.composite``'s one walk, bit for bit; a long tile's pixel no
        longer walks its whole list alone (a 6M-splat scene's 10 % output has tiles of 10^5 entries)."""
        e_xy, e_co, e_rgb, e_box, e_faint = entries
        pixels = kernels.TILE_PIXELS
        self._chunk_counts(tiles)
        chunks = self._chunk_ranges(tiles, count)
        ranges = [self.chunk_ends, self.chunk_tile, self.chunk_first, self.chunk_last]
        views = [self.cams, tiles_x, view_tiles]
        self._rows(grad_kernels.chunk_own_transmittance, chunks * pixels,
                   [e_xy, e_co, e_rgb, e_box, e_faint, self.tile_start, self.tile_end, *ranges, *views, tiles, self.slot_ends,
                    self.p_weight, self.chunk_before, self.chunk_colour, self.chunk_stop], 2048)  # fmt: skip
        self._launch(kernels.chunk_prefix, tiles * pixels, [self.counts, self.chunk_ends], [self.chunk_before])
        self._rows(grad_kernels.composite_chunk_weights, chunks * pixels,
                   [e_xy, e_co, e_rgb, e_box, e_faint, self.tile_start, *ranges, self.chunk_before, *views, tiles, self.slot_ends,
                    self.p_weight, self.chunk_colour, self.chunk_stop], 2048)  # fmt: skip
        self._rows(grad_kernels.merge_chunk_weights, tiles * pixels,
                   [self.chunk_colour, self.chunk_before, self.chunk_stop, self.counts, self.chunk_ends, self.tile_end, *views,
                    background, image, self.stops], 2048)  # fmt: skip

    def backward(self, image: wp.array, grad_image: wp.array, grads: SplatGradients, colours_only: bool = False) -> None:
        """Adds to ``grads`` the gradient of L given dL/dimage ``grad_image`` (V, H, W, 3) for the views
        last rendered by ``forward`` into ``image`` (the splats unchanged since), view after view.
        ``colours_only``: the colours' gradients alone (``grads.features``, the same bits; no other
        array is touched), in a fraction of the time."""
        if self.count == 0:
            return
        if colours_only and self.weights_kept:  # the colours' gradients from the forward's weights
            self._rows(
                grad_kernels.sum_weighted_colours, self.count,
                [self.keys, self.e_box, self.cams, self.tiles_x, self.view_tiles, self.slot_ends, self.p_weight, self.stops,
                 grad_image, self.e_g_rgb], 16384,
            )  # fmt: skip
            self._splat_backward(grads, 1)
            return
        self._reserve_scratch(self.tiles * kernels.TILE_PIXELS)
        per_entry = [self.e_g_xy, self.e_g_conic, self.e_g_opacity, self.e_g_rgb]
        per_lane = [self.lane_xy, self.lane_conic, self.lane_opacity, self.lane_rgb] if self.lane_buffers else per_entry
        colours = int(colours_only)
        inputs = [self.lanes, colours, self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint, self.tile_start, self.tile_end,
                  self.cams, self.tiles_x, self.view_tiles, image, grad_image, self.bw_transmittance, self.bw_front,
                  self.bw_done]  # fmt: skip
        if not (self.per_pixel and self._pixel_terms(image, grad_image, per_entry, colours)):
            if self.lanes_in_turn:
                tiles = self.tiles
                per_chunk = rows_per_chunk(tiles, self.count)
                self._rows(grad_kernels.composite_backward_lanes_in_turn, tiles, [*inputs, *per_entry], per_chunk)
            else:
                lanes = self.tiles * self.lanes
                per_chunk = max(8, rows_per_chunk(lanes, self.count))
                self._rows(grad_kernels.composite_backward, lanes, [*inputs, *per_lane], per_chunk)
            if self.lane_buffers:
                self._rows(grad_kernels.sum_lanes, self.count, [self.lanes, *per_lane, *per_entry], 16384)
        self._splat_backward(grads, colours)

    def _reserve_scratch(self, pixels: int) -> None:
        """Per-pixel state for ``pixels`` pixels: transmittance, colour (or colour in front) and done."""
        if self.scratch_pixels < pixels:
            d = self.device
            self.scratch_pixels = pixels
            self.bw_transmittance = wp.empty(pixels, dtype=wp.float32, device=d)
            self.bw_front = wp.empty(pixels, dtype=wp.vec3, device=d)
            self.bw_done = wp.empty(pixels, dtype=wp.int32, device=d)

    def _reserve_chunk_scratch(self, pixels: int) -> None:
        """Per-pixel state of the tile walk's chunks (``composite_tile_weights``) for ``pixels`` pixels:
        the transmittance before the chunk and the chunk's own, and the colour of the chunks before."""
        if self.chunk_scratch_pixels < pixels:
            self.chunk_scratch_pixels = pixels
            self.bw_chunk_state = wp.empty(pixels, dtype=wp.vec2, device=self.device)
            self.bw_total = wp.empty(pixels, dtype=wp.vec3, device=self.device)

    def _reserve_slots(self, count: int, tiles: int, tiles_x: int, view_tiles: int) -> bool:
        """The per-pixel slots of the ``count`` entries just sorted (``pixel_areas``, their running
        sum in ``slot_ends``) and the buffers for their terms, and a stop per pixel of ``tiles``
        tiles. False where the slots would not fit the device."""
        d = self.device
        if count * kernels.TILE_PIXELS > INDEX_LIMIT:
            return False  # the slots' int32 offsets could wrap
        where = [self.keys, self.e_box, self.cams, tiles_x, view_tiles]
        self._rows(grad_kernels.pixel_areas, count, [*where, self.areas], 16384)
        wp.utils.array_scan(self.areas[:count], self.slot_ends[:count], inclusive=True)
        bound = count * kernels.TILE_PIXELS  # an entry reaches at most its tile's pixels
        pixels = tiles * kernels.TILE_PIXELS
        pairs = None
        if not self.per_pixel:  # the CPU's kept weights (its only slots): not where entries pile up on each pixel
            pairs = int(self.slot_ends[count - 1 : count].numpy()[0])
            if pairs > KEPT_PAIRS_PER_PIXEL * pixels:
                return False
        if bound > self.pixel_capacity:  # else the slots fit without reading their count back (a wait for the GPU)
            if pairs is None:
                pairs = int(self.slot_ends[count - 1 : count].numpy()[0])
            if pairs > self.pixel_capacity or self.pixel_capacity == 0:  # (none yet: a view whose entries reach no pixel)
                memory = entry_memory(d)
                if pairs * self.pair_bytes > memory:
                    return False
                # room for twice this bound where it takes at most an eighth of that memory: the
                # next views' slots then fit without a read-back while their entries stay that few
                room = max(pairs, min(2 * bound, memory // (8 * self.pair_bytes), INDEX_LIMIT))
                self.pixel_capacity = c = max(room, int(self.pixel_capacity * 1.5), 1024)
                self.p_weight = wp.empty(c, dtype=wp.float32, device=d)
                if self.per_pixel:
                    self.p_xy = wp.empty(c, dtype=wp.vec2, device=d)
                    self.p_conic = wp.empty(c, dtype=wp.vec3, device=d)
                    self.p_opacity = wp.empty(c, dtype=wp.float32, device=d)
                    self.p_rgb = wp.empty(c, dtype=wp.vec3, device=d)
        if self.stops is None or self.stops.shape[0] < pixels:
            self.stops = wp.empty(pixels, dtype=wp.int32, device=d)
        return True

    def _pixel_terms(self, image: wp.array, grad_image: wp.array, per_entry: list, colours: int) -> bool:
        """The per-pixel backward into ``per_entry``: each (entry, pixel) term in its own slot, then
        every entry's terms summed (``kernels/render_grad.py``). False, doing nothing, where the
        slots would not fit the device (the lanes then give the same sums)."""
        count = self.count
        if not self._reserve_slots(count, self.tiles, self.tiles_x, self.view_tiles):
            return False
        where = [self.keys, self.e_box, self.cams, self.tiles_x, self.view_tiles]
        pixels = self.tiles * kernels.TILE_PIXELS
        terms = [self.p_xy, self.p_conic, self.p_opacity, self.p_rgb]
        self._rows(
            grad_kernels.composite_backward_pixels,
            pixels,
            [self.e_xy, self.e_conic_opacity, self.e_rgb, self.e_box, self.e_faint, self.tile_start, self.tile_end,
             self.cams, self.tiles_x, self.view_tiles, colours, image, grad_image, self.slot_ends, *terms, self.stops],
            max(2048, rows_per_chunk(pixels, count)),
        )  # fmt: skip
        self._rows(grad_kernels.sum_pixels, count, [*where, colours, self.slot_ends, *terms, self.stops, *per_entry], 16384)
        return True

    def _splat_backward(self, grads: SplatGradients, colours: int) -> None:
        s = self.splats
        self._rows(
            grad_kernels.splat_backward,
            self.n,
            [s.means, s.rotations, s.log_scales, s.opacities, s.features, self.degree, colours, self.cams,
             self.touched, self.ends, self.entry_of_slot,
             self.e_g_xy, self.e_g_conic, self.e_g_opacity, self.e_g_rgb,
             grads.means, grads.rotations, grads.log_scales, grads.opacities, grads.features],
            2048,
        )  # fmt: skip
