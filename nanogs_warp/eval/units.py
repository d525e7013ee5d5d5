"""The units and the origin a scene is rendered in. The rasterisers work in float32, where the
squares of coordinates and scales beyond about 1e19 overflow and those below 1e-19 vanish; a scene
stored in such units is rendered rescaled by a power of two, cameras and all (``eval`` and
``--refine``). A scene far from the origin for its size (a small object at 1e20) is rendered
recentred: there float32, and even float64, cannot tell a camera's position from the centre."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import warp as wp

from ..splats import SplatSet
from .cameras import Camera, scene_frame

# Orbit radii (``scene_frame``) of scenes rendered in their own units: inside, nothing changes.
RENDERED_RADIUS = (2.0**-40, 2.0**40)
# A scene whose centre lies further from the origin than this many orbit radii is rendered recentred:
# float32 coordinates there still resolve 1/4000 of the radius (2^-24 x 2^12).
FAR_CENTRE = 2.0**12


def far_from_origin(centre: np.ndarray, radius: float) -> bool:
    """Whether a scene of this ``scene_frame`` lies more than FAR_CENTRE orbit radii from the origin
    (and is rendered recentred)."""
    return float(np.max(np.abs(centre))) > FAR_CENTRE * radius


def in_rendered_units(radius: float) -> bool:
    """Whether a scene of this orbit radius is rendered in its own units (inside RENDERED_RADIUS)."""
    return RENDERED_RADIUS[0] <= radius <= RENDERED_RADIUS[1]


def rendered_as_is(means: np.ndarray) -> bool:
    """Whether the scene whose centres are ``means`` (all, or a sample) is rendered in its own units
    around its own origin: its ``scene_frame`` near the origin and in rendered units."""
    centre, radius = scene_frame(means)
    return not far_from_origin(centre, radius) and in_rendered_units(radius)


def render_offset(reference: SplatSet) -> np.ndarray | None:
    """None, or the reference's centre (``scene_frame``) where it lies more than FAR_CENTRE orbit
    radii from the origin: the point ``eval`` and the refinement then render every scene around."""
    centre, radius = scene_frame(reference.means.numpy())
    return centre if far_from_origin(centre, radius) else None


def render_units(reference: SplatSet) -> float:
    """1, or where the reference's orbit radius (``scene_frame``) lies outside RENDERED_RADIUS the
    power of two that brings it to [1/2, 1): the scale at which ``evaluate`` renders every scene
    and the refinement optimises."""
    _, radius = scene_frame(reference.means.numpy())
    if in_rendered_units(radius):
        return 1.0
    return math.ldexp(1.0, -math.frexp(radius)[1])


def rescaled(splats: SplatSet, scale: float, offset: np.ndarray | None = None) -> SplatSet:
    """``splats`` with centres (x - offset) times ``scale`` (in float64; with a power of two and no
    offset exact; clamped to float32's range) and log-scales plus log(scale): the same scene in
    other units, around another origin."""
    if scale == 1.0 and offset is None:
        return splats
    limit = float(np.finfo(np.float32).max)
    means = splats.means.numpy().astype(np.float64)
    if offset is not None:
        means -= np.asarray(offset, np.float64)
    means = np.clip(means * scale, -limit, limit).astype(np.float32)
    device = splats.device
    out = replace(splats, means=wp.array(means, dtype=wp.vec3, device=device))
    if scale != 1.0:
        log_scales = (splats.log_scales.numpy().astype(np.float64) + math.log(scale)).astype(np.float32)
        out = replace(out, log_scales=wp.array(log_scales, dtype=wp.vec3, device=device))
    return out


def rescaled_camera(camera: Camera, scale: float, offset: np.ndarray | None = None) -> Camera:
    """``camera`` in the world of ``rescaled(..., scale, offset)``: the same view of that scene."""
    translation = np.asarray(camera.translation, np.float64)
    if offset is not None:
        translation = translation + np.asarray(camera.rotation, np.float64) @ np.asarray(offset, np.float64)
    return replace(camera, translation=translation * scale, near=camera.near * scale)
