"""Integer extra properties (uchar ... uint) are carried exactly: a merge takes the value of the
pair's heavier splat (the larger merge weight; the pair's first splat on a tie), never a float
average; reading and writing keep every value of 32 bits, which float32 cannot hold."""

import json

import numpy as np
import plyfile
import pytest
import reference
import warp as wp
from scene_factory import random_splat_arrays, write_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.data import sample_path
from nanogs_warp.io import save_splats
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.operators import OPERATORS
from nanogs_warp.pairing import Pairs
from nanogs_warp.splats import SplatSet

# Values a float32 rounds (2^24 + 1, the int32 and uint32 extremes), and int64 ones beyond float64.
HARD = np.array([16_777_217, -2_147_483_648, 2_147_483_647, 4_294_967_295, 2**53 + 1, -(2**62) - 3], np.int64)
REFERENCES = {"mpmm": reference.mpmm, "area": reference.area_merge, "coverage": reference.coverage_merge}
POISON = -777


def merge_pairs(arrays, integers, pairs_ij, operator, device):
    """Runs ``operator`` on ``pairs_ij`` with every row kept in place; the rows it must write are
    poisoned first. Returns the output's host arrays."""
    n = len(arrays["means"])
    source = SplatSet.from_numpy(**arrays, integer_extras=integers, device=device)
    poisoned = {key: value.copy() for key, value in arrays.items()}
    poisoned_integers = integers.copy()
    for value in poisoned.values():
        value[pairs_ij[:, 0]] = np.nan
    poisoned_integers[pairs_ij[:, 0]] = POISON
    out = SplatSet.from_numpy(**poisoned, integer_extras=poisoned_integers, device=device, validate=False)
    pairs = Pairs(wp.array(pairs_ij[:, 0].astype(np.int32), device=device),
                  wp.array(pairs_ij[:, 1].astype(np.int32), device=device), len(pairs_ij))  # fmt: skip
    OPERATORS[operator]()(source, pairs, out, wp.array(np.arange(n, dtype=np.int32), device=device))
    np.testing.assert_array_equal(source.integer_extras.numpy(), integers)  # the source is never changed
    return out.to_numpy()


@pytest.mark.parametrize("operator", sorted(OPERATORS))
def test_a_merge_takes_the_heavier_splats_integers(device, rng, operator):
    n = 256
    arrays = random_splat_arrays(n, sh_degree=1, seed=int(rng.integers(1 << 30)))
    arrays["extras"] = rng.normal(size=(n, 2)).astype(np.float32)
    integers = rng.integers(-(2**62), 2**62, size=(n, 3))
    integers[: len(HARD), 0] = HARD
    integers[:, 1] = 16_777_217 + 2 * np.arange(n)  # odd, above 2^24: no float32 holds them
    perm = rng.permutation(n)
    pairs_ij = np.stack([perm[: n // 2], perm[n // 2 :]], 1)
    ties = pairs_ij[:40]  # equal weights: the same opacity and scales (rotations differ)
    for key in ("opacities", "log_scales"):
        arrays[key][ties[:, 1]] = arrays[key][ties[:, 0]]
    after = merge_pairs(arrays, integers, pairs_ij, operator, device)
    source = dict(arrays, integer_extras=integers)
    heavier_j = 0
    for i, j in pairs_ij:
        ref = REFERENCES[operator](source, i, j)
        assert ref["pi"] == 0.5 or abs(ref["pi"] - 0.5) > 1e-9  # no pair so close that rounding decides
        np.testing.assert_array_equal(after["integer_extras"][i], ref["integer_extras"])
        np.testing.assert_allclose(after["extras"][i], ref["extras"], rtol=1e-5, atol=1e-6)  # floats: weighted
        heavier_j += ref["pi"] < 0.5
    np.testing.assert_array_equal(after["integer_extras"][ties[:, 0]], integers[ties[:, 0]])  # ties: i's
    assert 20 < heavier_j < 100  # both sides of the pair win, so the test can tell them apart
    untouched = np.setdiff1d(np.arange(n), pairs_ij[:, 0])
    np.testing.assert_array_equal(after["integer_extras"][untouched], integers[untouched])


def test_the_reference_picks_the_heavier_and_i_on_a_tie():
    values = np.array([[1], [2]], np.int64)
    assert reference.heavier_values(values, 0, 1, 0.75) == 1 and reference.heavier_values(values, 0, 1, 0.25) == 2
    assert reference.heavier_values(values, 0, 1, 0.5) == 1


def hard_scene(path, n: int = 400, seed: int = 5) -> dict:
    """A PLY file with integer extras of every width, ``id`` unique and odd above 2^24, and one
    float extra; returns what load_ply gives back."""
    arrays = random_splat_arrays(n, sh_degree=1, seed=seed)
    write_splats_ply(path, arrays, extra_props=(("label", "u1"), ("id", "i4"), "foo", ("flags", "u4"),
                                                ("small", "i1"), ("wide", "u2")), seed=seed)  # fmt: skip
    data = plyfile.PlyData.read(str(path))
    vertex = data["vertex"].data.copy()
    vertex["id"] = 16_777_217 + 2 * np.arange(n)
    vertex["flags"] = 4_294_967_295 - np.arange(n)
    vertex["small"][:2] = [-128, 127]
    vertex["wide"][:2] = [0, 65535]
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))
    return vertex


def test_reading_and_writing_keep_every_integer(tmp_path):
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    vertex = hard_scene(src)
    splats = load_ply(src)
    assert splats.layout.integer_extra_names == ["label", "id", "flags", "small", "wide"]
    assert splats.layout.float_extra_names == ["nx", "ny", "nz", "foo"]
    host = splats.to_numpy()
    assert host["integer_extras"].dtype == np.int64 and host["extras"].shape == (400, 4)
    np.testing.assert_array_equal(host["integer_extras"][:, 1], vertex["id"])
    np.testing.assert_array_equal(host["integer_extras"][:, 2], vertex["flags"])
    save_ply(splats, out)
    assert out.read_bytes() == src.read_bytes()



def test_integer_extras_outside_their_columns_type_are_refused(tmp_path):
    """300 in a uchar column was written as 255 and -1 as 0: carried exactly means refused instead."""
    hard_scene(tmp_path / "in.ply")
    splats = load_ply(tmp_path / "in.ply")
    host = splats.to_numpy()
    arrays = {k: host[k] for k in ("means", "rotations", "log_scales", "opacities", "features", "extras")}
    for column, value in ((0, 256), (0, -1), (1, 2**31), (4, 65536)):  # label: uchar, id: int, wide: ushort
        integers = host["integer_extras"].copy()
        integers[7, column] = value
        with pytest.raises(ValueError, match=rf"integer_extras column {column} \({splats.layout.integer_extra_names[column]}"):
            SplatSet.from_numpy(**arrays, integer_extras=integers, layout=splats.layout, device="cpu")
    same = SplatSet.from_numpy(**arrays, integer_extras=host["integer_extras"], layout=splats.layout, device="cpu")
    save_ply(same, tmp_path / "out.ply")
    assert (tmp_path / "out.ply").read_bytes() == (tmp_path / "in.ply").read_bytes()

def test_files_without_integer_extras_keep_one_float_array():
    splats = load_ply(sample_path())
    assert splats.extras.shape == (20_000, 3) and splats.integer_extras.shape == (20_000, 0)
    assert splats.layout.integer_extra_names == []


def test_simplify_writes_each_splat_integers_from_one_input_splat(tmp_path):
    """Every output row's integers are those of one input splat, exactly (all of its integer
    properties from the same one); a float average of the odd ids above 2^24 could not be."""
    src = tmp_path / "in.ply"
    vertex = hard_scene(src)
    result = CliRunner().invoke(app, ["simplify", str(src), "-o", str(tmp_path / "out.ply"), "--ratio", "0.1,0.01",
                                      "--device", "cpu", "--json"])  # fmt: skip
    assert result.exit_code == 0, result.output
    names = ["label", "id", "flags", "small", "wide"]
    rows = {tuple(int(v) for v in row) for row in zip(*(vertex[n] for n in names))}
    for written in json.loads(result.stdout)["outputs"]:
        out = plyfile.PlyData.read(written["path"])["vertex"].data
        assert [out.dtype[n] for n in names] == [vertex.dtype[n] for n in names]
        assert len(out) == written["count"] < len(vertex)
        assert all(tuple(int(v) for v in row) in rows for row in zip(*(out[n] for n in names)))


def test_formats_without_extra_properties_name_the_integer_ones(tmp_path):
    src = tmp_path / "in.ply"
    hard_scene(src, n=50)
    lost = []
    save_splats(load_ply(src), tmp_path / "out.splat", on_loss=lost.append)
    assert len(lost) == 1 and "label, id, foo, flags, small, wide" in lost[0]
