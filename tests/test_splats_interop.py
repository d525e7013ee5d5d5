"""SplatSet for the PyTorch world: len(), the gsplat layout (w-first quaternions, SH as (N, K, 3)),
to_torch(). The layout is checked against the PLY property names themselves."""

import numpy as np
import pytest
from scene_factory import random_splats_ply

from nanogs_warp.io.ply import load_ply
from nanogs_warp.splats import SplatSet


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_gsplat_layout_against_ply_names(tmp_path, sh_degree):
    path = tmp_path / "s.ply"
    random_splats_ply(path, 50, sh_degree=sh_degree, seed=sh_degree)
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"].data
    splats = load_ply(path)
    g = splats.to_gsplat_numpy()
    k = (sh_degree + 1) ** 2
    assert len(splats) == 50 and g["sh"].shape == (50, k, 3) and g["quats"].shape == (50, 4)
    for c in range(3):
        np.testing.assert_array_equal(g["sh"][:, 0, c], vertex[f"f_dc_{c}"])
        for j in range(1, k):  # f_rest is channel-major: coefficient j of channel c
            np.testing.assert_array_equal(g["sh"][:, j, c], vertex[f"f_rest_{c * (k - 1) + j - 1}"])
    for q in range(4):  # rot_0 is w
        np.testing.assert_array_equal(g["quats"][:, q], vertex[f"rot_{q}"])
    np.testing.assert_array_equal(g["scales"][:, 1], vertex["scale_1"])
    np.testing.assert_array_equal(g["opacities"], vertex["opacity"])
    np.testing.assert_array_equal(g["means"][:, 2], vertex["z"])
    # fresh copies: changing them leaves the splat set alone
    g["means"][:] = 0
    assert np.any(splats.to_numpy()["means"] != 0)


def test_len_is_count():
    arrays = dict(means=np.zeros((3, 3)), rotations=np.tile([1.0, 0, 0, 0], (3, 1)), log_scales=np.zeros((3, 3)),
                  opacities=np.zeros(3), features=np.zeros((3, 3)))  # fmt: skip
    assert len(SplatSet.from_numpy(**arrays)) == 3


def test_to_torch(tmp_path):
    torch = pytest.importorskip("torch")  # PyTorch is not a dependency: the one test that needs it
    path = tmp_path / "s.ply"
    random_splats_ply(path, 20, sh_degree=2, seed=3)
    splats = load_ply(path)
    tensors = splats.to_torch()
    expected = splats.to_gsplat_numpy()
    assert set(tensors) == set(expected)
    for name, tensor in tensors.items():
        assert isinstance(tensor, torch.Tensor) and tensor.device.type == "cpu"
        np.testing.assert_array_equal(tensor.numpy(), expected[name])


def test_documented_way_back_from_the_gsplat_layout(tmp_path):
    """docs/api.md's formula turns gsplat's (N, K, 3) SH back into the PLY order."""
    path = tmp_path / "s.ply"
    random_splats_ply(path, 30, sh_degree=2, seed=9)
    splats = load_ply(path)
    g = splats.to_gsplat_numpy()
    sh, n = g["sh"], len(splats)
    features = np.concatenate([sh[:, 0, :], sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)], axis=1)
    np.testing.assert_array_equal(features, splats.to_numpy()["features"])
    back = SplatSet.from_numpy(g["means"], g["quats"], g["scales"], g["opacities"], features, g["extras"])
    for key, value in back.to_numpy().items():
        np.testing.assert_array_equal(value, splats.to_numpy()[key])


def test_fewer_sh_bands_keep_each_channels_first_coefficients(tmp_path, device):
    """``with_sh_degree`` against the PLY names: f_dc, then f_rest_{c (k' - 1) + j} of the kept
    degree from f_rest_{c (k - 1) + j} of the input's, for every pair of degrees."""
    from plyfile import PlyData

    for own in range(4):
        path = tmp_path / f"s{own}.ply"
        random_splats_ply(path, 40, sh_degree=own, seed=own)
        vertex = PlyData.read(str(path))["vertex"].data
        splats = load_ply(path, device=device)
        for degree in range(4):
            fewer = splats.with_sh_degree(degree)
            if degree >= own:
                assert fewer is splats
                continue
            k = (degree + 1) ** 2
            f = fewer.features.numpy()
            assert f.shape == (40, 3 * k) and fewer.sh_degree == degree and fewer.means is splats.means
            expected = [vertex[f"f_dc_{c}"] for c in range(3)]
            expected += [vertex[f"f_rest_{c * ((own + 1) ** 2 - 1) + j}"] for c in range(3) for j in range(k - 1)]
            np.testing.assert_array_equal(f, np.stack(expected, axis=1))
    for bad in (4, -1, True, 1.0, "0"):  # True and 1.0 were taken as 1, "0" raised a bare comparison TypeError
        with pytest.raises(ValueError, match="a whole number from 0 to 3"):
            splats.with_sh_degree(bad)
    assert splats.with_sh_degree(np.int64(1)).sh_degree == 1
