"""The closed-form face plane of a covariance (its smallest eigenvector and the product of the two
largest eigenvalues) against numpy's float64 eigendecomposition."""

import numpy as np
import warp as wp

from nanogs_warp.kernels.splat_math import face_plane


@wp.kernel
def _face_planes(a: wp.array(dtype=wp.mat33d), normals: wp.array(dtype=wp.vec3d), faces: wp.array(dtype=wp.float64)):
    t = wp.tid()
    n, c0, c1, face = face_plane(a[t])
    normals[t] = n
    faces[t] = face


def _run(matrices, device):
    a = wp.array(matrices, dtype=wp.mat33d, device=device)
    normals = wp.full(len(matrices), wp.vec3d(np.nan, np.nan, np.nan), dtype=wp.vec3d, device=device)  # poisoned
    faces = wp.full(len(matrices), np.nan, dtype=wp.float64, device=device)
    wp.launch(_face_planes, len(matrices), inputs=[a], outputs=[normals, faces], device=device)
    return normals.numpy(), faces.numpy()


def _random_covariances(rng, n, log_spread):
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    values = np.exp(rng.uniform(-log_spread, 0.0, size=(n, 3)) * 2.0)
    return np.einsum("nij,nj,nkj->nik", q, values, q)


def test_face_plane_matches_eigh(device, rng):
    for spread in (1.0, 4.0, 9.0):  # scale ratios up to e^9 (variance ratios up to ~6e7)
        matrices = _random_covariances(rng, 400, spread)
        normals, faces = _run(matrices, device)
        values, vectors = np.linalg.eigh(matrices)  # ascending
        np.testing.assert_allclose(np.abs((normals * vectors[:, :, 0]).sum(1)), 1.0, atol=1e-6)
        np.testing.assert_allclose(faces, values[:, 1] * values[:, 2], rtol=1e-6)


def test_face_plane_of_degenerate_shapes(device):
    """A sphere (any plane), a needle (the plane holds its axis) and a flat disk (its normal)."""
    needle_axis = np.array([1.0, 2.0, 2.0]) / 3.0
    disk_normal = np.array([0.0, 0.6, 0.8])
    matrices = np.stack([
        np.eye(3) * 0.25,
        1e-6 * np.eye(3) + (1.0 - 1e-6) * np.outer(needle_axis, needle_axis),
        np.eye(3) - (1.0 - 1e-8) * np.outer(disk_normal, disk_normal),
    ])  # fmt: skip
    normals, faces = _run(matrices, device)
    assert np.all(np.isfinite(normals)) and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    np.testing.assert_allclose(faces, [0.0625, 1e-6, 1.0], rtol=1e-6)
    assert abs(normals[1] @ needle_axis) < 1e-6
    assert abs(abs(normals[2] @ disk_normal) - 1.0) < 1e-9
