"""The geometry fit: a small output's splat centres, rotations and scales fitted to renders of the
input (``SimplifyConfig.fit_geometry``, on by default), after the size fit.

A short refinement (``refine``: STEPS Adam steps of STEP_VIEWS views each, rendered and
back-propagated together, at SIZE pixels, trained on VIEWS views of the input from
``training_cameras``, checked on held-out views) with the opacity and colour learning rates at 0: a merged splat's place, orientation and extent move to what the input shows, while its
opacity and colour stay the merge's. Refining opacity and colour as well gains more on the orbit
but loses on close views of semi-transparent strands (docs/quality.md); so does training on fewer
or smaller views. The result is kept only where it renders the held-out views of the input better
(those on black and those on white alike: ``refine``'s backgrounds) than the size-fitted output
did (``refine``'s checkpoint rule, one checkpoint at the end).

The smallest outputs (at most LONG_BELOW of the input's splats, each splat standing for a thousand
originals or more) are fitted longer: LONG_STEPS steps of LONG_VIEWS views each (rendered and
back-propagated together, their gradients averaged) at LONG_RATE times the learning rates
(LONG_MEANS_RATE for the centres), on the same views. Their splats must move further than a larger
output's to where the input shows them; forty steps at 3DGS's rates leave most of that gain, and
Adam moves a centre by about its rate a step: at 24 times 3DGS's rate (decaying tenfold) a centre
can travel about a fifth of the scene's extent in 125 steps. Eight views a step average out more of
a single view's noise than the 400 one-view steps of an earlier default, at the same travel, in a
tenth of the launches (docs/quality.md, docs/performance.md); they cost the CPU twice the pixels of
four, for the budget whose margin over the other tools is thinnest. The first LONG_COARSE of
those steps train on the same views at half their size (``ReferenceViews.halved``): the same
quality for a quarter of the pixels (on the CPU, where a step's cost is its pixels').
"""

from __future__ import annotations

import dataclasses

from ..config import target_count
from ..splats import SplatSet
from .config import RefineConfig
from .refine import ReferenceViews, refine_with_report

STEPS = 40
STEP_VIEWS = 2  # views a step trains on together (their gradients averaged)
VIEWS = 40
SIZE = 256
LONG_BELOW = "0.001"  # outputs of at most target_count(N, LONG_BELOW) splats get the long fit (an exact ratio)
LONG_STEPS = 125
LONG_VIEWS = 8  # views a long-fit step trains on together
LONG_RATE = 6.0  # the long fit's learning rates of rotations and scales, times the short fit's
LONG_MEANS_RATE = 24.0  # the long fit's learning rate of the centres, times the short fit's
LONG_COARSE = 93  # of the long fit's steps, the first (three quarters) train on the views at half their size


def geometry_config(seed: int = 0, long: bool = False) -> RefineConfig:
    """The refinement the geometry fit runs: STEPS steps of STEP_VIEWS views (with ``long``, LONG_STEPS of
    LONG_VIEWS views, the first LONG_COARSE on the views at half size, the centres' rate
    LONG_MEANS_RATE and the rotations' and scales' LONG_RATE times the short fit's), VIEWS training
    views of SIZE pixels, centres, rotations and scales only."""
    config = RefineConfig(steps=STEPS, size=SIZE, views_per_step=STEP_VIEWS, reference_views=VIEWS, seed=seed,
                          lr_opacities=0.0, lr_features_dc=0.0, lr_features_rest=0.0)  # fmt: skip
    if not long:
        return config
    return dataclasses.replace(config, steps=LONG_STEPS, coarse_steps=LONG_COARSE, views_per_step=LONG_VIEWS,
                               lr_means=config.lr_means * LONG_MEANS_RATE,
                               lr_rotations=config.lr_rotations * LONG_RATE,
                               lr_log_scales=config.lr_log_scales * LONG_RATE)  # fmt: skip


class GeometryFit:
    """Fits the outputs of one run against ``reference`` (the run's input, on its device). The
    input's views are rendered once, for the first output fitted, and shared by the others (the
    short and the long fit train on the same views)."""

    def __init__(self, reference: SplatSet, seed: int = 0):
        self.reference = reference
        self.config = geometry_config(seed)
        self.long_config = geometry_config(seed, long=True)
        self.longest = target_count(reference.count, LONG_BELOW)
        self.views = ReferenceViews(reference, self.config)

    def __call__(self, splats: SplatSet) -> tuple[SplatSet, bool]:
        """(the fitted splat set, whether the fitted geometry was kept: ``splats``' own otherwise)."""
        config = self.long_config if splats.count <= self.longest else self.config
        fitted, report = refine_with_report(splats, self.reference, config, views=self.views, checkpoints=(1.0,),
                                            training_loss=False)  # fmt: skip
        return fitted, report.kept_step > 0
