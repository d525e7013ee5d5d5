"""Refinement: a simplified scene optimised toward the original's appearance, its count fixed
(``refine``), with the differentiable rasteriser (``render_grad``: the renderer's forward pass of
``nanogs_warp.eval.render`` and its hand-written backward), the training loss (``image_loss``),
the training cameras (``cameras``) and the settings (``config``).

Named ``refinement`` and not ``refine`` so that ``from nanogs_warp import refine`` stays the
function. Importing this package loads nothing: each module is imported where it is used.
"""
