"""tools/stress_scenes.py: the generated stress scenes are the same for the same seed, hold valid
splats, and the unbounded scene places ``eval``'s orbit between its ground's edge and its far shell
(what makes it an outdoor capture's layout rather than an object seen from outside)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "tools"))

from stress_scenes import R_GROUND, SCENES, _wires

from nanogs_warp.eval.cameras import scene_frame

KEYS = ("means", "rotations", "log_scales", "opacities", "features")


@pytest.mark.parametrize("name", sorted(SCENES))
def test_a_scene_is_its_seeds_and_holds_valid_splats(name):
    make = SCENES[name]
    first, again, other = make(np.random.default_rng(7), 0.05), make(np.random.default_rng(7), 0.05), make(np.random.default_rng(8), 0.05)
    for key in KEYS:
        np.testing.assert_array_equal(first[key], again[key])
        assert first[key].dtype == np.float32 and np.isfinite(first[key]).all()
    assert not np.array_equal(first["means"], other["means"])
    n = len(first["means"])
    assert n > 100 and all(len(first[key]) == n for key in KEYS)
    np.testing.assert_allclose(np.linalg.norm(first["rotations"], axis=1), 1.0, atol=1e-5)
    assert first["log_scales"].min() > -9 and first["log_scales"].max() < 2.0  # the unbounded shell: about one unit at scale 1


def test_the_unbounded_scenes_orbit_lies_between_its_ground_and_its_far_shell():
    scene = SCENES["stress_unbounded"](np.random.default_rng(4), 0.2)
    means = scene["means"].astype(np.float64)
    centre, radius = scene_frame(means)
    distance = np.linalg.norm(means, axis=1)
    far = distance > 2 * R_GROUND
    assert 0.03 < far.mean() < 0.1  # a shell of few, large splats
    assert R_GROUND < radius < distance[far].min()
    assert np.abs(centre).max() < 0.2 * R_GROUND
    ground = np.abs(means[:, 1]) == 0
    assert ground.mean() > 0.4 and np.abs(means[ground][:, [0, 2]]).max() <= R_GROUND


def test_a_wires_needles_lie_along_it():
    """``_wires``: on a straight wire along x, every needle's longest axis is the wire's, its two
    other axes alike, its centre within the wire's halo, and about ``density`` needles a radius."""
    radius, length, density = 0.01, 2.0, 2.0
    wire = _wires(np.random.default_rng(3), [np.array([[-1.0, 0.5, 0.2], [1.0, 0.5, 0.2]])], radius, [0.2, 0.3, 0.4], density)
    n = len(wire["means"])
    assert abs(n - density * length / radius) <= 1
    w, x, y, z = wire["rotations"].astype(np.float64).T
    rotation = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)  # fmt: skip
    variances = np.exp(2.0 * wire["log_scales"].astype(np.float64))
    covariances = np.einsum("nij,nj,nkj->nik", rotation, variances, rotation)
    values, vectors = np.linalg.eigh(covariances)
    assert (np.abs(vectors[:, 0, 2]) > 0.9999).all()  # the largest eigenvalue's axis: x
    np.testing.assert_allclose(values[:, 1], values[:, 0], rtol=1e-4)
    long = np.sqrt(values[:, 2]) / radius
    assert ((long >= 2.0 * 0.999) & (long <= 4.0 * 1.001) | (long >= 6.0 * 0.999) & (long <= 12.0 * 1.001)).all()  # or a halo's
    off = np.linalg.norm(wire["means"][:, 1:] - [0.5, 0.2], axis=1)
    assert off.max() < 3.0 * radius and np.abs(wire["means"][:, 0]).max() <= 1.0 + 1e-6
