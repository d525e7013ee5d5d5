"""The size fit: an output's splats all scaled by the one factor whose renders match the input's
best, at a coarse and at a fine pixel size alike (``SimplifyConfig.fit_size``, on by default).

At every budget the merged splats of some scenes come out too large or too small (a statue's faint
halo spread into every merged splat at 1 %; fur strands and flat panels merged too thin at 10 %
and above), and the right factor is the scene's, not a constant's (docs/quality.md). The fit
measures it: the input and the output are rendered from the same ``VIEWS`` cameras around the scene
(``training_cameras``' sampler, its own stream, ``SIZE`` pixels square) and from the same cameras
zoomed ``ZOOM`` times (pixels that much smaller: most splats of a trained scene are smaller than a
pixel of the coarse views, where a renderer's 0.3-pixel blur makes them look larger than they are,
and the fine views keep the fit from growing splats for that blur alone). A factor's gain is the
smaller of its two PSNR changes (mean over the views, against factor 1); factors STEP^k, |k| <=
MOST_STEPS, are tried outward from 1 while the gain rises, and the best one with a positive gain is
kept (1 otherwise).

The input is rendered once per run, when the first output to fit is reached. A scene that ``eval``
would render rescaled or recentred (``eval.units``) is left as it is, and so is one whose renders
would not fit the device's memory (``render``'s check) or whose splats' tile rectangles would hold
more (tile, splat) pairs than ENTRIES_PER_SPLAT a splat and MIN_ENTRIES more. CPU and CUDA render the same views to the
bit (``kernels/render.py``) and sum their errors in the same order, so they pick the same factor.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace

import numpy as np
import warp as wp

from ..config import target_count
from ..errors import InputError
from ..eval.render import render_views_on_device
from ..eval.units import rendered_as_is
from ..kernels import splat_size as kernels
from ..splats import SplatSet
from .cameras import sampled_means, training_cameras

# Every output is fitted for size; those of at most target_count(N, GEOMETRY_FIT_BELOW) splats (an
# exact ratio) for geometry too (``GeometryFit``): at 10 % the geometry fit gains on the orbit it trains
# around but loses on closer and sharper views, where the size fit gains on both (docs/quality.md)
GEOMETRY_FIT_BELOW = "0.01"
# The merged splats' colours are fitted (``colour_fit``) in every output above COLOUR_FIT_ABOVE of the
# input (an exact ratio), after the geometry fit of those of at most 1 %. The smallest outputs, which
# the geometry fit trains longest (``geometry_fit.LONG_BELOW``), keep the merge's colours: fitted,
# they gained on the orbit but lost up to 0.46 dB on camera sets no decision was made on (a fur
# scene), where at 1 % and above no cell of any set lost (docs/quality.md)
COLOUR_FIT_ABOVE = "0.001"
VIEWS = 4
SIZE = 256
ZOOM = 4.0
STEP = 2.0 ** (1.0 / 12.0)
MOST_STEPS = 6
CAMERA_STREAM = 0x5CA1E  # the random stream of the fit's cameras (``training_cameras``)
# A view whose splats' tile rectangles hold more (tile, splat) pairs than this (a file of huge splats,
# or of long strands across the view: each rectangle most of the view's tiles) is not rendered, and
# the output is not fitted: the fit's time stays near a few passes'.
ENTRIES_PER_SPLAT = 16
MIN_ENTRIES = 1 << 22


def fit_cameras(means: np.ndarray, seed: int = 0) -> tuple[list, list]:
    """The fit's views around ``means`` (``sampled_means``): VIEWS square SIZE-pixel training cameras
    (``training_cameras``' sampler, stream CAMERA_STREAM), and the same zoomed ZOOM times."""
    drawn = training_cameras(means, 4 * VIEWS, SIZE, seed, CAMERA_STREAM)  # one in four is SIZE square
    coarse = [c for c in drawn if c.width == c.height == SIZE][:VIEWS]
    return coarse, [dataclasses.replace(c, fx=c.fx * ZOOM, fy=c.fy * ZOOM) for c in coarse]


def resized(splats: SplatSet, factor: float) -> SplatSet:
    """``splats`` with every axis times ``factor`` (log-scales plus log(factor), in float32)."""
    if factor == 1.0:
        return splats
    out = wp.empty_like(splats.log_scales)
    wp.launch(kernels.resized_log_scales, splats.count, inputs=[splats.log_scales, math.log(factor)], outputs=[out],
              device=splats.device)  # fmt: skip
    return replace(splats, log_scales=out)


def _render(splats: SplatSet, cameras: list) -> wp.array:
    """``render_views_on_device`` (one rasteriser for every view) within the fit's entry limit."""
    return render_views_on_device(splats, cameras, max_entries=ENTRIES_PER_SPLAT * splats.count + MIN_ENTRIES)


def _psnr(reference: wp.array, test: wp.array) -> float:
    """Mean over views of each view's PSNR (both images clamped to [0, 1], as ``eval`` compares
    them), each view's error at least 1e-12: unlike ``metrics.psnr`` never infinite, so that a view
    both render black in (outside the scene) leaves the gains to the others instead of making them
    NaN. The squared errors are summed on the device, row by row in pixel order (the same sums on
    every device), and only the per-row sums come to the host."""
    views, height, width = test.shape[0], test.shape[1], test.shape[2]
    rows = wp.empty((views, height), dtype=wp.float64, device=test.device)
    wp.launch(kernels.squared_error_rows, (views, height), inputs=[reference, test], outputs=[rows], device=test.device)
    mse = rows.numpy().sum(axis=1) / float(height * width * 3)
    return float(np.mean([-10.0 * math.log10(max(float(m), 1e-12)) for m in mse]))


class SizeFit:
    """Fits the outputs of one run against ``reference`` (the run's input, on the device it runs on):
    for size (``size``, ``fitted``), then, with ``geometry``, the small ones' geometry
    (``GeometryFit``), then, with ``colour``, their merged splats' colours (``colour_fit``)."""

    def __init__(self, reference: SplatSet, seed: int = 0, size: bool = True, geometry: bool = False, colour: bool = False):
        self.reference = reference
        self.seed = int(seed)
        self.size, self.geometry, self.colour = size, geometry, colour
        self.largest_geometry = target_count(reference.count, GEOMETRY_FIT_BELOW)
        self.smallest_colour = target_count(reference.count, COLOUR_FIT_ABOVE)
        self._means: np.ndarray | None = None  # the centres that place the cameras (``sampled_means``)
        self._cameras: list | None = None
        self._images: tuple[wp.array, wp.array] | None = None  # the input's coarse and fine views, on its device
        self._skip = False
        self._geometry_fit = None
        self.factors: dict[int, float] = {}  # count -> factor of each output fitted so far
        self.geometry_kept: dict[int, bool] = {}  # count -> whether its geometry fit was kept
        self.colour_kept: dict[int, bool] = {}  # count -> whether its colour fit was kept

    def applies(self, count: int) -> bool:
        """Whether an output of ``count`` splats is fitted for size: every output of the input is."""
        return count <= self.reference.count

    def applies_geometry(self, count: int) -> bool:
        """Whether it is fitted for geometry too, with ``geometry`` (at most GEOMETRY_FIT_BELOW)."""
        return self.geometry and count <= self.largest_geometry

    def applies_colour(self, count: int) -> bool:
        """Whether it is fitted for colour, with ``colour``: every output above COLOUR_FIT_ABOVE, after
        its geometry fit where that runs (which keeps the merge's colours)."""
        return self.colour and self.smallest_colour < count <= self.reference.count

    def _in_frame(self) -> bool:
        """The centres that place the cameras, once; False where the scene is not fitted (one that
        ``eval`` would render rescaled or recentred)."""
        if self._skip:
            return False
        if self._means is None:
            means = sampled_means(self.reference)
            if not rendered_as_is(means):
                self._skip = True
                return False
            self._means = means
        return True

    def _prepare(self) -> bool:
        """Cameras and the input's renders, once; False where the scene is not fitted."""
        if not self._in_frame():
            return False
        if self._images is None:
            means = self._means
            coarse, fine = fit_cameras(means, self.seed)
            self._cameras = [coarse, fine]
            try:
                images = _render(self.reference, coarse + fine)  # one rasteriser for the input's eight views
                self._images = (images[: len(coarse)], images[len(coarse) :])
            except InputError:  # the renders would not fit the device's memory: no fit
                self._skip = True
                return False
        return True

    def _scores(self, splats: SplatSet, base: tuple[float, float] | None = None, floor: float = -math.inf) -> tuple[float, ...]:
        """PSNR of ``splats`` against the input in each view set, the fine views first. With ``base``
        (the output's own scores), the gains over it instead; once a set's gain is at most ``floor``
        the other is not rendered (their smaller one cannot exceed ``floor`` then)."""
        scores = []
        for k in (1, 0):
            value = _psnr(self._images[k], _render(splats, self._cameras[k]))
            if base is not None:
                value -= base[k]
                if value <= floor:
                    return (value,)
            scores.append(value)
        return tuple(reversed(scores))

    def view_gains(self, splats: SplatSet, factors) -> list[tuple[float, float]] | None:
        """For each of ``factors``, the PSNR gains (coarse views, fine views) of ``splats`` resized by it
        over ``splats`` itself: what ``fitted`` compares, each factor rendered in full. None where the
        scene is not fitted. For studies of the rule (``tools/size_fit_rules.py``)."""
        if not self._prepare():
            return None
        base = self._scores(splats)
        return [(0.0, 0.0) if f == 1.0 else self._scores(resized(splats, f), base) for f in factors]

    def __call__(self, splats: SplatSet, merged: wp.array | None = None) -> SplatSet:
        """The fitted splat set (``splats`` itself when nothing gains); its factor goes to ``factors``
        and, with ``geometry``, whether its geometry fit was kept to ``geometry_kept``, with ``colour``
        whether its colour fit was to ``colour_kept``. ``merged``: int32 marks, 1 in each row a merge
        made (the pipeline's ``finish`` argument; None: no row was merged, and no colour is fitted).
        The input itself (a budget of all its splats: nothing pruned or merged) is its own best fit:
        it is returned without rendering anything."""
        if splats is self.reference:
            self.factors[splats.count] = 1.0
            return splats
        fitted, factor = self.fitted(splats) if self.size else (splats, 1.0)
        self.factors[splats.count] = factor
        if self.applies_geometry(splats.count) and self._in_frame():
            fitted = self._fit_geometry(fitted)
        if self.applies_colour(splats.count):
            fitted = self._fit_colour(fitted, merged)
        return fitted

    def _geometry(self):
        """The run's ``GeometryFit``, made once: its renders of the input serve the colour fit too."""
        from .geometry_fit import GeometryFit

        if self._geometry_fit is None:
            self._geometry_fit = GeometryFit(self.reference, self.seed)
        return self._geometry_fit

    def _fit_colour(self, splats: SplatSet, merged: wp.array | None) -> SplatSet:
        """``colour_fit.fitted_colours`` of ``splats``, kept where it gains in the fit's coarse and fine
        views alike (both PSNR gains positive, the size fit's rule); ``splats`` itself otherwise.
        Where its geometry is fitted, its opacities are fitted with its colours first, and where that
        is not kept, its colours alone."""
        from .colour_fit import fitted_colours

        self.colour_kept[splats.count] = False
        if merged is None or not self._prepare():
            return splats
        try:
            base = None
            for opacities in (True, False) if self.applies_geometry(splats.count) else (False,):
                candidate = fitted_colours(splats, merged, self.reference, self._geometry().views, self.seed, opacities)
                if candidate is None:
                    continue
                base = self._scores(splats) if base is None else base
                # floor 0: once one view set's gain is not positive, the other is not rendered
                if min(self._scores(candidate, base, floor=0.0)) > 0.0:
                    self.colour_kept[splats.count] = True
                    return candidate
        except InputError:  # the input's views would not fit the device's memory: not fitted
            pass
        return splats

    def _fit_geometry(self, splats: SplatSet) -> SplatSet:
        """``GeometryFit`` of ``splats`` (its input views made for the first output); ``splats`` itself
        where the input's views would not fit the device's memory."""
        try:
            fitted, self.geometry_kept[splats.count] = self._geometry()(splats)
        except InputError:  # the views would not fit the device's memory: not fitted
            self.geometry_kept[splats.count] = False
            return splats
        return fitted

    def fitted(self, splats: SplatSet) -> tuple[SplatSet, float]:
        """(the fitted splat set, its factor); ``splats`` itself and 1 when no factor gains."""
        if not self.applies(splats.count) or not self._prepare():
            return splats, 1.0
        try:
            base = self._scores(splats)
        except InputError:
            return splats, 1.0

        def gain(k: int, floor: float) -> float:
            """The gain of STEP^k (the smaller of the two sets'), or a value at most ``floor`` once it
            is known not to exceed ``floor``."""
            try:
                return min(self._scores(resized(splats, STEP**k), base, floor))
            except InputError:
                return -math.inf

        best = best_step(gain)
        if best == 0:
            return splats, 1.0
        factor = STEP**best
        return resized(splats, factor), factor


def best_step(gain) -> int:
    """The fit's search: steps k = 1, 2, ... and then -1, -2, ... (|k| <= MOST_STEPS), each way while
    ``gain(k, previous)`` rises; the k of the largest positive gain, 0 when none is. ``gain(k, floor)``
    may return any value at most ``floor`` once it knows the gain cannot exceed it."""
    best, best_gain = 0, 0.0
    for direction in (1, -1):
        k, previous = direction, 0.0
        while abs(k) <= MOST_STEPS:
            g = gain(k, previous)
            if not g > previous:  # the gain stopped rising
                break
            if g > best_gain:
                best, best_gain = k, g
            k, previous = k + direction, g
    return best


def size_fit_for(splats: SplatSet, config) -> SizeFit | None:
    """The size, geometry and colour fits of a run on ``splats`` with ``config`` (a SimplifyConfig), or
    None without any."""
    if not (config.fit_size or config.fit_geometry or config.fit_colour):
        return None
    return SizeFit(splats, config.seed, size=config.fit_size, geometry=config.fit_geometry, colour=config.fit_colour)
