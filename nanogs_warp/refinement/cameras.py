"""Training cameras for refinement: a seeded sampler around (and, in large scenes, inside) a scene.

Independent of ``cameras.orbit_cameras`` (the evaluation orbit): positions are random directions at
random distances, so the views refinement trains on are never the orbit's.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from ..eval.cameras import Camera, near_plane

DISTANCE = (1.2, 3.0)  # x the 90th-percentile distance of the centres from the scene's centre
FOV_Y_DEG = (40.0, 75.0)
INSIDE_FRACTION = 0.125  # of the views in a large scene
LARGE_SCENE = 3.0  # 99th / 90th percentile distance above which a scene counts as large (a background)


SPREAD_SAMPLE = 1 << 16  # at most this many centres (every k-th) place the cameras


def sampled_means(splats) -> np.ndarray:
    """The centres of ``splats`` (a SplatSet) that place the cameras of the size fit, the geometry fit
    and refinement: every k-th, at most about SPREAD_SAMPLE (a strided copy). The median and the
    percentiles of every centre of a 6M-splat scene took seconds on the host."""
    return splats.means[:: max(1, splats.count // SPREAD_SAMPLE)].numpy()


def scene_spread(means: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(robust centre, 90th and 99th percentiles of the centres' distances from it)."""
    means = np.asarray(means, np.float64).reshape(-1, 3)
    means = means[np.isfinite(means).all(axis=1)]
    if len(means) == 0:
        raise InputError("the reference scene has no splat with a finite centre to place cameras around")
    centre = np.median(means, axis=0)
    distances = np.linalg.norm(means - centre, axis=1)
    p90, p99 = (float(v) for v in np.percentile(distances, [90, 99]))
    return centre, (p90 if p90 > 0 else 1.0), (p99 if p99 > 0 else 1.0)


def image_sizes(size: int) -> list[tuple[int, int]]:
    """(width, height) of the training views: square, landscape, portrait and a half-size square."""
    three_quarters, half = max(1, round(0.75 * size)), max(1, round(0.5 * size))
    return [(size, size), (size, three_quarters), (three_quarters, size), (half, half)]


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([0.0, 0.0, 1.0])


TRAINING_STREAM = 0x7EF1  # the random stream of the training cameras
VALIDATION_STREAM = 0x7A11D  # another stream: held-out cameras drawn the same way, never trained on


def training_cameras(means: np.ndarray, count: int, size: int, seed: int, stream: int = TRAINING_STREAM) -> list[Camera]:
    """``count`` cameras from a generator seeded with ``seed``: most at 1.2-3x the 90th-percentile
    radius looking at the scene's centre (a target jittered by a fifth of that radius), random
    roll, vertical field of view 40-75 degrees, sizes from ``image_sizes(size)``, the near plane
    ``near_plane`` of the nearest of those distances; in a large scene
    (99th-percentile radius above 3x the 90th) one in eight from inside, looking outwards. ``stream``
    picks an independent set for the same seed (``VALIDATION_STREAM``: the held-out views)."""
    centre, p90, p99 = scene_spread(means)
    rng = np.random.default_rng([seed, stream])
    sizes = image_sizes(size)
    large = p99 > LARGE_SCENE * p90
    near = near_plane(DISTANCE[0] * p90)  # INRIA's 0.2 unless the scene is stored in small units
    cameras = []
    for k in range(count):
        width, height = sizes[k % len(sizes)]
        fov = math.radians(rng.uniform(*FOV_Y_DEG))
        focal = 0.5 * height / math.tan(0.5 * fov)
        up = _unit(rng)
        if large and rng.uniform() < INSIDE_FRACTION:
            position = centre + _unit(rng) * rng.uniform(0.0, 0.5) * p90
            target = position + _unit(rng)
        else:
            position = centre + _unit(rng) * rng.uniform(*DISTANCE) * p90
            target = centre + rng.normal(0.0, 0.2 * p90, 3)
        cameras.append(Camera.look_at(position, target, up, focal, focal, width, height, f"train_{k:04d}", near))
    return cameras
