"""Refinement: distil a simplified scene toward the original's appearance, with the splat count fixed.

Each step renders the simplified scene from a few training cameras (``cameras``), compares it
with the original's render of the same camera by L1 + 0.2 (1 - SSIM) (``image_loss``), back-propagates
through the rasteriser (``render_grad``) and takes an Adam step on every parameter group with 3DGS's
per-group learning rates (the means' scaled by the scene's extent and decayed tenfold over the run).
The original's renders are made once, for a pool of cameras the steps then draw from, half of them
on a black background and half on white (``BACKGROUNDS``). No splat is
added or removed; after each step quaternions are renormalised and log-scales and opacity logits are
clamped to finite ranges. Everything stays on the splats' device; the host reads one scalar per
progress report. The same inputs, seed and device give the same bytes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..errors import InputError
from ..device import device_lock, memory_short
from ..kernel_cache import REFINE_MODULES, use_shipped_kernels
from ..eval.render import _Rasteriser
from ..eval.units import render_offset, render_units, rendered_as_is, rescaled
from ..kernels import adam as adam_kernels
from ..kernels import image_loss as image_kernels
from ..parallel import launch_rows_from
from ..splats import SplatSet, warp_device
from .cameras import VALIDATION_STREAM, sampled_means, scene_spread, training_cameras
from .config import RefineConfig
from .image_loss import MIN_PIXELS_TO_SPLIT, ImageLoss, Targets, loss_view, target_views
from .render_grad import GradRasteriser, SplatGradients, camera_array

LOSS_VIEWS = 8  # pool views on which the training loss before and after is measured
VALIDATION_VIEWS = 8  # held-out views (never trained on) that choose which checkpoint to return
CHECKPOINTS = (0.25, 0.5, 0.75, 1.0)  # fractions of the run at which the held-out loss is measured
# View k of a set of reference views (training or held out) is rendered on BACKGROUNDS[k % 2], and a
# step trains on views of one background (``step_views``). On black alone, a pixel that one splat
# covers shows only its opacity times its colour, so a fit may trade one for the other unseen there
# and show it on every other background; on white the pixel shows the opacity too (docs/quality.md,
# "The fits trained on black and white backgrounds").
BACKGROUNDS = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
# Memory a refinement takes on its device, measured on the CPU (the bundled sample, --refine-size 512
# and 1024): about 930 bytes a pixel of a training view for a step's renders, gradients and SSIM maps
# (times the views a step renders together), and 12 (RGB float32) a pixel for every reference view
# kept. 4096-pixel views at the default 128 reference views need about 44 GB. Where they fit, each
# reference view also keeps its blurred terms, G*Y and G*Y^2 (``image_loss.target_views``), 24 bytes
# a pixel more, which a step then need not blur again: the same bits, sooner.
STEP_BYTES_PER_PIXEL = 1000
VIEW_BYTES_PER_PIXEL = 12
MOMENT_BYTES_PER_PIXEL = 24


def _need(config: RefineConfig, pool: int, view_bytes: int) -> int:
    views = pool + VALIDATION_VIEWS
    return config.size * config.size * (STEP_BYTES_PER_PIXEL * config.views_per_step + view_bytes * views)


def check_memory(config: RefineConfig, pool: int, device) -> None:
    """Refuses, before any rendering, a refinement whose views would not fit ``device``'s memory
    (a GPU's free memory, the host's available memory for the CPU)."""
    need = _need(config, pool, VIEW_BYTES_PER_PIXEL)
    available = memory_short(need, device)
    if available is not None:
        memory = "memory" if device.is_cpu else f"{device}'s memory"
        raise InputError(f"refining with {pool + VALIDATION_VIEWS} reference views of {config.size}x{config.size} pixels needs about "
                         f"{need:,} bytes of {memory}, more than the {available:,} available: give a smaller "
                         f"--refine-size or fewer --refine-steps")  # fmt: skip


def view_pool(config: RefineConfig) -> int:
    """How many training views a refinement of ``config`` renders of the original (at most one a step)."""
    return max(1, min(config.reference_views, config.steps * config.views_per_step))


@dataclass
class RefineReport:
    """What a refinement did: steps, seconds (total and per phase), training loss before and after
    (mean over the first ``LOSS_VIEWS`` training views) and on held-out views, for the input and for
    the returned parameters (``kept_step``: the step whose parameters are returned; 0 = the input)."""

    steps: int
    count: int
    loss_before: float = math.nan
    loss_after: float = math.nan
    seconds: float = 0.0
    seconds_reference: float = 0.0
    seconds_forward: float = 0.0
    seconds_backward: float = 0.0
    seconds_optimiser: float = 0.0
    views: int = 0
    validation_before: float = math.nan
    validation_after: float = math.nan
    kept_step: int = 0

    def to_json(self) -> dict:
        return {
            "steps": self.steps,
            "count": self.count,
            "loss_before": round(self.loss_before, 6),
            "loss_after": round(self.loss_after, 6),
            "seconds": round(self.seconds, 4),
            "seconds_reference": round(self.seconds_reference, 4),
            "seconds_forward": round(self.seconds_forward, 4),
            "seconds_backward": round(self.seconds_backward, 4),
            "seconds_optimiser": round(self.seconds_optimiser, 4),
            "reference_views": self.views,
            "validation_before": round(self.validation_before, 6),
            "validation_after": round(self.validation_after, 6),
            "kept_step": self.kept_step,
        }


@dataclass
class _Group:
    """One parameter array seen flat, with its Adam moments and per-column learning rates."""

    param: wp.array
    grad: wp.array
    rates: wp.array
    columns: int
    decays: bool
    m: wp.array = field(init=False)
    v: wp.array = field(init=False)

    def __post_init__(self):
        self.m = wp.zeros(self.param.shape[0], dtype=wp.float32, device=self.param.device)
        self.v = wp.zeros(self.param.shape[0], dtype=wp.float32, device=self.param.device)


def _flat(a: wp.array) -> wp.array:
    return a.view(wp.float32).flatten() if a.dtype != wp.float32 else a.flatten()


def _copy(splats: SplatSet, device) -> SplatSet:
    return splats.clone(device)


def view_background(k: int) -> wp.vec3:
    """The background of view k of a set of reference views (``BACKGROUNDS``)."""
    return wp.vec3(*BACKGROUNDS[k % len(BACKGROUNDS)])


def backgrounds_of(views: int) -> int:
    """How many backgrounds a set of ``views`` reference views shows (``view_background``): a set of
    one is all black."""
    return min(views, len(BACKGROUNDS))


def _render_views(reference: SplatSet, cameras, device, moments: bool = True) -> Targets:
    """``reference`` rendered from each camera k on ``view_background(k)`` into one stack (V, H, W, 3),
    H and W the largest views': view k in the top-left corner of [k] (zeros beyond its size); with its
    blurred terms where ``moments`` (``target_views``)."""
    rasteriser = _Rasteriser(reference)
    height, width = max(c.height for c in cameras), max(c.width for c in cameras)
    stack = wp.zeros((len(cameras), height, width, 3), dtype=wp.float32, device=device)
    for k, camera in enumerate(cameras):
        rasteriser.render_into(camera, view_background(k), stack, k)
    return target_views(stack, [(c.width, c.height) for c in cameras], moments)


class ReferenceViews:
    """The original's renders that refinement trains on (a pool of training cameras) and chooses its
    checkpoint by (held-out cameras), for one reference scene and configuration. They depend on
    nothing else, so every output refined toward the same original in a run can share them: a
    multi-budget ``simplify --refine`` renders them once instead of once a budget (about 100 MB at
    the default 128 views of 256 pixels). Made on first use (``render``), so one can be made for a
    run before it is known to be needed."""

    def __init__(self, reference: SplatSet, config: RefineConfig, device=None):
        self.source, self.config = reference, config
        self.device = wp.get_device(device if device is not None else reference.device)
        # views that cannot fit are refused when made (before a run merges and fits), and again when
        # rendered, when the device's free memory is what it will be
        check_memory(config, view_pool(config), self.device)
        self.cameras: list | None = None  # None until rendered
        self.scale, self.offset, self.reference, self.extent = 1.0, None, reference, 1.0
        self.targets: Targets | None = None  # the training views' stack (``_render_views``)
        self.held_out: list = []
        self.held_out_targets: Targets | None = None
        self._halved: tuple[list, Targets] | None = None

    @property
    def moments(self) -> bool:
        """Whether the views keep their targets' blurred terms (``render`` keeps them where they fit)."""
        return self.targets is None or self.targets.moments is not None

    def serves(self, reference: SplatSet, config: RefineConfig, device) -> bool:
        """Whether these are the views a refinement of ``config`` toward ``reference`` on ``device``
        would render: the same cameras (pool, size, seed), whatever its steps and learning rates."""
        same_views = view_pool(config) == view_pool(self.config) and (config.size, config.seed) == (self.config.size, self.config.seed)
        return reference is self.source and same_views and wp.get_device(device) == self.device

    def halved(self) -> tuple[list, Targets]:
        """The training views at half their size (rendered first where they were not): each camera
        with half the focal lengths, principal point and pixels, and each target its 2x2 pixel blocks
        averaged (pixel i covers [i, i + 1) of the image plane: a block's centre is the half-size
        pixel's). Made once, on the views' device."""
        self.render()
        if self._halved is None:
            cameras = [dataclasses.replace(c, fx=0.5 * c.fx, fy=0.5 * c.fy, cx=0.5 * c.cx, cy=0.5 * c.cy,
                                           width=c.width // 2, height=c.height // 2) for c in self.cameras]  # fmt: skip
            full = self.targets.images
            _, height, width, _ = full.shape
            targets = wp.zeros((len(cameras), height // 2, width // 2, 3), dtype=wp.float32, device=self.device)
            for k, c in enumerate(cameras):
                launch_rows_from(image_kernels.halved, c.height * c.width,
                                 [full[k][: 2 * c.height, : 2 * c.width], targets[k][: c.height, : c.width]], self.device,
                                 chunks_per_worker=1, min_rows=MIN_PIXELS_TO_SPLIT)  # fmt: skip
            self._halved = (cameras, target_views(targets, [(c.width, c.height) for c in cameras], self.moments))
        return self._halved

    def render(self) -> float:
        """Renders the views unless done before; returns the seconds it took (0 when it had been)."""
        if self.cameras is not None:
            return 0.0
        started = time.perf_counter()
        means = sampled_means(self.source)  # the cameras' places (every centre up to 131,071 splats)
        if rendered_as_is(means):
            self.reference = self.source.to(self.device)
        else:
            # a scene in units of ~1e20 or ~1e-20, or far from the origin for its size: optimised
            # rescaled and recentred (eval/units.py), and handed back where it was
            self.offset = render_offset(self.source)
            self.scale = render_units(rescaled(self.source, 1.0, self.offset))
            self.reference = rescaled(self.source, self.scale, self.offset).to(self.device)
            means = self.reference.means.numpy()
        c = self.config
        _, p90, _ = scene_spread(means)
        self.extent = 2.2 * p90  # the scene's extent, which scales the means' learning rate
        pool = view_pool(c)
        check_memory(c, pool, self.device)
        moments = memory_short(_need(c, pool, VIEW_BYTES_PER_PIXEL + MOMENT_BYTES_PER_PIXEL), self.device) is None
        cameras = training_cameras(means, pool, c.size, c.seed)
        self.targets = _render_views(self.reference, cameras, self.device, moments)
        # held-out views, drawn like the training views from another stream
        self.held_out = training_cameras(means, VALIDATION_VIEWS, c.size, c.seed, VALIDATION_STREAM)
        self.held_out_targets = _render_views(self.reference, self.held_out, self.device, moments)
        wp.synchronize_device(self.device)
        self.cameras = cameras
        return time.perf_counter() - started


class _Refiner:
    def __init__(self, simplified: SplatSet, extent: float, config: RefineConfig, device):
        """``simplified`` as ``ReferenceViews`` rescales it; ``extent``: the rescaled original's
        (``ReferenceViews.extent``)."""
        self.config, self.device = config, device
        self.splats = _copy(simplified, device)
        self.extent = extent
        self.grads = SplatGradients.zeros_like(self.splats)
        self.rasteriser = GradRasteriser(self.splats)
        self.images: dict[tuple[int, int, int], tuple[wp.array, wp.array, ImageLoss]] = {}
        self.groups = self._groups()
        # every rate but the colours' 0 (the colour fit): the backward computes the colours' gradients
        # alone, and Adam leaves the other groups be (a rate of 0 would not move them anyway)
        self.colours_only = not any((config.lr_means, config.lr_rotations, config.lr_log_scales, config.lr_opacities))
        if self.colours_only:
            self.groups = self.groups[-1:]
        wp.load_module(adam_kernels, device=device)

    def _rates(self, values: list[float]) -> wp.array:
        return wp.array(np.asarray(values, np.float32), dtype=wp.float32, device=self.device)

    def _groups(self) -> list[_Group]:
        c, s, g = self.config, self.splats, self.grads
        features = s.features.shape[1]
        return [
            _Group(_flat(s.means), _flat(g.means), self._rates([c.lr_means * self.extent] * 3), 3, True),
            _Group(_flat(s.rotations), _flat(g.rotations), self._rates([c.lr_rotations] * 4), 4, False),
            _Group(_flat(s.log_scales), _flat(g.log_scales), self._rates([c.lr_log_scales] * 3), 3, False),
            _Group(_flat(s.opacities), _flat(g.opacities), self._rates([c.lr_opacities]), 1, False),
            _Group(_flat(s.features), _flat(g.features),
                   self._rates([c.lr_features_dc] * 3 + [c.lr_features_rest] * (features - 3)), features, False),
        ]  # fmt: skip

    def buffers(self, cameras) -> tuple[wp.array, wp.array, ImageLoss]:
        """The image and dL/dimage buffers (V, H, W, 3) and the loss's for rendering ``cameras`` together."""
        key = (len(cameras), max(c.width for c in cameras), max(c.height for c in cameras))
        if key not in self.images:
            views, width, height = key
            d = self.device
            self.images[key] = (
                wp.empty((views, height, width, 3), dtype=wp.float32, device=d),
                wp.empty((views, height, width, 3), dtype=wp.float32, device=d),
                ImageLoss(height, width, d, views),
            )
        return self.images[key]

    def loss_views(self, cameras, chosen: list[int], weight: float) -> list:
        """``loss_view`` of view v against targets[chosen[v]], each weighted ``weight``."""
        return [loss_view(k, c.width, c.height, self.config.ssim_weight, weight) for k, c in zip(chosen, cameras)]

    def views_loss(self, cameras, chosen: list[int], targets: Targets, weight: float, params: wp.array | None = None,
                   specs: wp.array | None = None, step: bool = False) -> tuple[wp.array, wp.array, ImageLoss]:  # fmt: skip
        """Renders ``cameras`` together on the background of targets[chosen[0]] (``view_background``:
        every chosen view's, ``step_views``) and compares view v with targets[chosen[v]], each weighted
        ``weight``; returns the image, dL/dimage and the loss (``backward`` then adds weight dL/dparams
        of each view, view after view). ``params`` and ``specs``: the cameras'
        ``camera_array`` and ``loss_views`` already on the device (else copied there here, each copy
        a wait for the device). ``step``: a training step's views, which ``backward`` follows."""
        image, grad_image, loss = self.buffers(cameras)
        self.rasteriser.forward(cameras, view_background(chosen[0]), image, params, keep_weights=step and self.colours_only,
                                walked_back=step)  # fmt: skip
        if specs is None:
            specs = wp.array(self.loss_views(cameras, chosen, weight), dtype=image_kernels.LossView, device=self.device)
        loss.of_views(image, targets, grad_image, specs)
        return image, grad_image, loss

    def view_losses(self, cameras, targets: Targets) -> list[float]:
        """The loss of each of ``cameras`` against the first of ``targets``, one view at a time."""
        return [self.views_loss([c], [k], targets, 1.0)[2].value() for k, c in enumerate(cameras)]

    def mean_loss(self, cameras, targets: Targets) -> float:
        """The mean of ``view_losses``."""
        return float(np.mean(self.view_losses(cameras, targets)))

    def background_losses(self, cameras, targets: Targets) -> np.ndarray:
        """The mean of ``view_losses`` over each background's views (view k on ``view_background(k)``):
        float64, one a background."""
        losses = self.view_losses(cameras, targets)
        backgrounds = backgrounds_of(len(losses))
        return np.array([np.mean(losses[b::backgrounds]) for b in range(backgrounds)])

    def adam(self, step: int) -> None:
        c = self.config
        beta1, beta2, eps = 0.9, 0.999, 1e-15
        c1, c2 = 1.0 - beta1 ** (step + 1), 1.0 - beta2 ** (step + 1)
        decay = c.lr_means_final ** (step / max(1, c.steps - 1))
        for g in self.groups:
            scale = decay if g.decays else 1.0
            launch_rows_from(
                adam_kernels.adam_step, g.param.shape[0],
                [g.grad, g.rates, g.columns, scale, beta1, beta2, eps, c1, c2, g.m, g.v, g.param], self.device,
            )  # fmt: skip
        lo, hi = c.log_scale_range
        s = self.splats
        launch_rows_from(
            adam_kernels.constrain_splats, s.count,
            [lo, hi + math.log(self.extent), *c.logit_range, s.rotations, s.log_scales, s.opacities], self.device,
        )  # fmt: skip


def step_views(pool: int, steps: int, views_per_step: int, seed: int) -> list[list[int]]:
    """The pool views each step trains on: step s on ``views_per_step`` views of background s mod 2
    (``view_background``; all of them black in a pool of one), each background's views drawn in
    permutations of their own, so that every one of them is drawn once before any is drawn again."""
    rng = np.random.default_rng([seed, 0xADA])
    backgrounds = backgrounds_of(pool)
    orders: list[list[int]] = [[] for _ in range(backgrounds)]
    steps_views = []
    for step in range(steps):
        order, members = orders[step % backgrounds], range(step % backgrounds, pool, backgrounds)
        chosen = []
        for _ in range(views_per_step):
            if not order:
                order.extend(members[i] for i in rng.permutation(len(members)).tolist())
            chosen.append(order.pop())
        steps_views.append(chosen)
    return steps_views


def _on_its_device(refine_fn):
    """``refine_fn`` holding the ``device_lock`` of the device it runs on: a program's threads refine
    one at a time on a device."""

    @functools.wraps(refine_fn)
    def holding(simplified, reference, config=None, device=None, *args, **kwargs):
        on = device if device is not None else getattr(simplified, "device", None)  # not a SplatSet: refine_fn says so
        with device_lock(warp_device(on)) if on is not None else contextlib.nullcontext():
            return refine_fn(simplified, reference, config, device, *args, **kwargs)

    return holding


@_on_its_device
def refine_with_report(
    simplified: SplatSet,
    reference: SplatSet,
    config: RefineConfig | None = None,
    device=None,
    on_step: Callable[[int, int], None] | None = None,
    timing: bool = False,
    views: ReferenceViews | None = None,
    checkpoints: tuple[float, ...] = CHECKPOINTS,
    training_loss: bool = True,
) -> tuple[SplatSet, RefineReport]:
    """``refine``, also returning what it did. ``on_step(step, steps)`` is called after each step;
    ``timing`` synchronises the device between phases so that the per-phase seconds are exact.
    ``views``: the original's renders shared with other refinements toward the same ``reference``
    with the same ``config`` and ``device`` (``ReferenceViews``; made here when None). The result
    is the same bytes either way. ``checkpoints``: the fractions of the run at which the held-out
    loss is measured; ``training_loss``: whether the report measures the training loss before and
    after (renders of ``LOSS_VIEWS`` views each; NaN when not)."""
    for name, value in (("simplified", simplified), ("reference", reference)):
        if not isinstance(value, SplatSet):
            raise TypeError(f"{name} must be a SplatSet (nanogs_warp.load_ply reads one from a file), got {type(value).__name__}")
    config = config or RefineConfig()
    config.validate()
    device = warp_device(device if device is not None else simplified.device)  # a name as --device reads it
    use_shipped_kernels(device, REFINE_MODULES)  # as the commands load them: no compile where they ship
    if views is not None and not views.serves(reference, config, device):
        raise ValueError("these reference views were made for another reference scene, configuration or device")
    started = time.perf_counter()
    report = RefineReport(steps=config.steps, count=simplified.count)
    if simplified.count == 0 or config.steps == 0:
        out = _copy(simplified, device)
        report.seconds = time.perf_counter() - started
        return out, report

    if views is None:
        views = ReferenceViews(reference, config, device)
    report.seconds_reference = views.render()
    refiner = _Refiner(rescaled(simplified, views.scale, views.offset), views.extent, config, device)
    cameras, targets = views.cameras, views.targets
    pool = len(cameras)
    report.views = pool
    loss_views = min(LOSS_VIEWS, pool) if training_loss else 0
    if loss_views:
        report.loss_before = refiner.mean_loss(cameras[:loss_views], targets)
    # The held-out views: the run returns the checkpoint (or the input) that renders them best,
    # so a run that overfits its training views never hands back a scene worse than it started;
    # best on each background's views (``background_losses``), so that it never buys the likeness
    # on one background with the other's.
    held_out, held_out_targets = views.held_out, views.held_out_targets
    kept_losses = refiner.background_losses(held_out, held_out_targets)
    report.validation_before = report.validation_after = float(np.mean(kept_losses))
    best = _copy(refiner.splats, device)
    checkpoints = {max(1, round(f * config.steps)) for f in checkpoints}

    coarse_cameras, coarse_targets = views.halved() if config.coarse_steps > 0 else ([], None)
    weight = 1.0 / config.views_per_step
    # Every step's views, drawn before the first: their cameras and loss weights go to the device
    # in one copy each, not one a step (each copy waits for the device)
    schedule = []
    for step, chosen in enumerate(step_views(pool, config.steps, config.views_per_step, config.seed)):
        step_cameras = coarse_cameras if step < config.coarse_steps else cameras
        schedule.append((chosen, [step_cameras[k] for k in chosen]))
    step_params = camera_array([c for _, step_cameras in schedule for c in step_cameras], device)
    step_specs = wp.array([spec for chosen, step_cameras in schedule for spec in refiner.loss_views(step_cameras, chosen, weight)],
                          dtype=image_kernels.LossView, device=device)  # fmt: skip
    sync = (lambda: wp.synchronize_device(device)) if timing else (lambda: None)
    for step, (chosen, step_cameras) in enumerate(schedule):
        refiner.grads.zero_()
        step_targets = coarse_targets if step < config.coarse_steps else targets
        t1 = time.perf_counter()
        # the step's views rendered together, their gradients added view by view: the bytes of
        # rendering and back-propagating them one at a time, in fewer launches
        first, last = step * config.views_per_step, (step + 1) * config.views_per_step
        image, grad_image, _ = refiner.views_loss(step_cameras, chosen, step_targets, weight, step_params[first:last],
                                                  step_specs[first:last], step=True)  # fmt: skip
        sync()
        t2 = time.perf_counter()
        refiner.rasteriser.backward(image, grad_image, refiner.grads, refiner.colours_only)
        sync()
        report.seconds_forward += t2 - t1
        report.seconds_backward += time.perf_counter() - t2
        t4 = time.perf_counter()
        refiner.adam(step)
        sync()
        report.seconds_optimiser += time.perf_counter() - t4
        if step + 1 in checkpoints:
            losses = refiner.background_losses(held_out, held_out_targets)
            if (losses < kept_losses).all():
                kept_losses, report.validation_after, report.kept_step = losses, float(np.mean(losses)), step + 1
                for target, source in zip(best.arrays(), refiner.splats.arrays()):
                    wp.copy(target, source)
        if on_step is not None:
            on_step(step + 1, config.steps)
    if report.kept_step != config.steps:
        for target, source in zip(refiner.splats.arrays(), best.arrays()):
            wp.copy(target, source)
    if loss_views:
        report.loss_after = refiner.mean_loss(cameras[:loss_views], targets)
    out = rescaled(best, 1.0 / views.scale, None if views.offset is None else -views.offset * views.scale)
    wp.synchronize_device(device)
    report.seconds = time.perf_counter() - started
    return out, report


def refine(
    simplified: SplatSet,
    reference: SplatSet,
    steps: int = RefineConfig.steps,
    size: int = RefineConfig.size,
    seed: int = RefineConfig.seed,
    device=None,
) -> SplatSet:
    """``simplified`` optimised so that its renders match ``reference``'s from training cameras around
    the scene: a new SplatSet on ``device`` (default: the simplified scene's) with the same count,
    layout and extras. The inputs are not modified."""
    config = RefineConfig(steps=steps, size=size, seed=seed)
    return refine_with_report(simplified, reference, config, device)[0]
