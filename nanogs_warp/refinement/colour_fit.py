"""The colour fit: the merged splats' colours of every output above 0.1 % (``size_fit.COLOUR_FIT_ABOVE``)
fitted to renders of the input (``SimplifyConfig.fit_colour``, on by default), after the size fit
and, for the 1 % outputs, after the geometry fit, which moves their splats but keeps the merge's
opacities and colours: there the merged splats' opacities are fitted with their colours.

A merge averages its pair's colours with weights, and the merged splat's colour is only an estimate
of what the pair showed; an input splat that no merge touched has the colour the input was trained
to. So the fit is the geometry fit's short refinement (``geometry_fit.STEPS`` steps of
``geometry_fit.STEP_VIEWS`` views on the same views of the input, kept only where its held-out
views render better, on black and on white alike) with every rate at 0 but the colours' (3DGS's,
``RefineConfig``'s defaults); of its result only the merged rows' colours are taken: every row that
no merge made keeps its own colour, and no other value changes. In an output whose geometry was fitted (at most
``size_fit.GEOMETRY_FIT_BELOW`` of the input) the merged rows' opacities are fitted and taken too
(3DGS's opacity rate), in OPACITY_STEPS steps: a splat moved and reshaped to what the input shows
keeps an opacity the merge chose for its old shape. There it gained in every scene and camera set
measured, where at 10 %, with no geometry fit, it lost up to 0.46 dB (docs/quality.md); where it is
not kept (the rule below), the colours are fitted alone. A fitted colour must not buy the coarse
views' likeness with the fine ones', as the renderers' blur would let it (docs/quality.md):
``SizeFit`` keeps the result only where it gains in the size fit's coarse and fine views alike, the
size fit's own rule. Its backward is the colours' alone (``GradRasteriser.backward``'s
``colours_only``, from the forward's kept weights; with the opacities, the whole backward). On an
H200 the forward of the fit of a 6M-splat scene's 600,000-splat output, its long tiles composited in
chunks, is about 0.11 s of GPU time (docs/performance.md); ``--no-fit-colour`` saves the fits.
"""

from __future__ import annotations

import dataclasses

import warp as wp

from ..compact import with_merged_appearance
from ..splats import SplatSet
from .config import RefineConfig
from .geometry_fit import STEPS, geometry_config
from .refine import ReferenceViews, refine_with_report

# The fit with opacities: twice the geometry fit's short steps, on the same views (40 of them, as
# before: the pool is the geometry fit's). Against 40 steps it gained in every scene and camera set
# measured (docs/quality.md).
OPACITY_STEPS = 2 * STEPS


def colour_config(seed: int = 0, opacities: bool = False) -> RefineConfig:
    """The refinement the colour fit runs: the geometry fit's (its steps, views and cameras), colours only,
    at refinement's default rates (3DGS's); with ``opacities``, opacities too, for OPACITY_STEPS steps."""
    config = dataclasses.replace(geometry_config(seed), lr_means=0.0, lr_log_scales=0.0, lr_rotations=0.0, lr_opacities=0.0,
                                 lr_features_dc=RefineConfig.lr_features_dc, lr_features_rest=RefineConfig.lr_features_rest)  # fmt: skip
    if not opacities:
        return config
    return dataclasses.replace(config, lr_opacities=RefineConfig.lr_opacities, steps=OPACITY_STEPS)


def fitted_colours(splats: SplatSet, merged: wp.array, reference: SplatSet, views: ReferenceViews, seed: int = 0,
                   opacities: bool = False) -> SplatSet | None:  # fmt: skip
    """``splats`` with its merged rows' colours (and, with ``opacities``, their opacities) fitted toward
    ``reference`` (on ``views``, the geometry fit's renders of it) and every other value as it was
    (the refinement also renormalises quaternions: those stay ``splats``' own); None where the fit
    did not render the held-out views better. ``merged``: int32 marks, 1 in each row a merge made."""
    fitted, report = refine_with_report(splats, reference, colour_config(seed, opacities), views=views, checkpoints=(1.0,),
                                        training_loss=False)  # fmt: skip
    if report.kept_step == 0:
        return None
    return with_merged_appearance(splats, fitted, merged, opacities)
