"""The units a scene is rendered in. The rasterisers work in float32, where the squares of
coordinates and scales beyond about 1e19 overflow and those below 1e-19 vanish; a scene stored in
such units is rendered rescaled by a power of two, cameras and all (``eval`` and ``--refine``)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import warp as wp

from ..splats import SplatSet
from .cameras import Camera, scene_frame

# Orbit radii (``scene_frame``) of scenes rendered in their own units: inside, nothing changes.
RENDERED_RADIUS = (2.0**-40, 2.0**40)


def render_units(reference: SplatSet) -> float:
    """1, or where the reference's orbit radius (``scene_frame``) lies outside RENDERED_RADIUS the
    power of two that brings it to [1/2, 1): the scale at which ``evaluate`` renders every scene
    and the refinement optimises."""
    _, radius = scene_frame(reference.means.numpy())
    if RENDERED_RADIUS[0] <= radius <= RENDERED_RADIUS[1]:
        return 1.0
    return math.ldexp(1.0, -math.frexp(radius)[1])


def rescaled(splats: SplatSet, scale: float) -> SplatSet:
    """``splats`` with centres times ``scale`` (a power of two: exact, clamped to float32's range)
    and log-scales plus log(scale): the same scene in other units."""
    if scale == 1.0:
        return splats
    limit = float(np.finfo(np.float32).max)
    means = np.clip(splats.means.numpy().astype(np.float64) * scale, -limit, limit).astype(np.float32)
    log_scales = (splats.log_scales.numpy().astype(np.float64) + math.log(scale)).astype(np.float32)
    device = splats.device
    return replace(splats, means=wp.array(means, dtype=wp.vec3, device=device), log_scales=wp.array(log_scales, dtype=wp.vec3, device=device))


def rescaled_camera(camera: Camera, scale: float) -> Camera:
    """``camera`` in a world scaled by ``scale``: the same view of the rescaled scene."""
    return replace(camera, translation=np.asarray(camera.translation, np.float64) * scale, near=camera.near * scale)
