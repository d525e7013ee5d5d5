"""The geometry fit: a small output's splat centres, rotations and scales fitted to renders of the
input (``SimplifyConfig.fit_geometry``, on by default), after the size fit.

A short refinement (``refine``: STEPS Adam steps at SIZE pixels, trained on VIEWS views of the
input from ``training_cameras``, checked on held-out views) with the opacity and colour learning
rates at 0: a merged splat's place, orientation and extent move to what the input shows, while its
opacity and colour stay the merge's. Refining opacity and colour as well gains more on the orbit
but loses on close views of semi-transparent strands (docs/quality.md); so does training on fewer
or smaller views. The result is kept only where it renders the held-out views of the input better
than the size-fitted output did (``refine``'s checkpoint rule, one checkpoint at the end).
"""

from __future__ import annotations

from ..splats import SplatSet
from .config import RefineConfig
from .refine import ReferenceViews, refine_with_report

STEPS = 40
VIEWS = 16
SIZE = 256


def geometry_config(seed: int = 0) -> RefineConfig:
    """The refinement the geometry fit runs: STEPS steps, VIEWS training views of SIZE pixels,
    centres, rotations and scales only."""
    return RefineConfig(steps=STEPS, size=SIZE, reference_views=VIEWS, seed=seed, lr_opacities=0.0,
                        lr_features_dc=0.0, lr_features_rest=0.0)  # fmt: skip


class GeometryFit:
    """Fits the outputs of one run against ``reference`` (the run's input, on its device). The
    input's views are rendered once, for the first output fitted, and shared by the others."""

    def __init__(self, reference: SplatSet, seed: int = 0):
        self.reference = reference
        self.config = geometry_config(seed)
        self.views = ReferenceViews(reference, self.config)

    def __call__(self, splats: SplatSet) -> tuple[SplatSet, bool]:
        """(the fitted splat set, whether the fitted geometry was kept: ``splats``' own otherwise)."""
        fitted, report = refine_with_report(splats, self.reference, self.config, views=self.views, checkpoints=(1.0,),
                                            training_loss=False)  # fmt: skip
        return fitted, report.kept_step > 0
