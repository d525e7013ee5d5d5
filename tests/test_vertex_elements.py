"""PLY elements that index vertices (a mesh's faces and edges) are dropped from simplified outputs
with a one-line warning, instead of being written with indices that point at the wrong splats."""

import warnings

import numpy as np
import plyfile
import pytest
from scene_factory import random_splat_arrays, random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app
from nanogs_warp.errors import NanogsWarning
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.pipeline import simplify
from nanogs_warp.splats import SplatSet


def with_elements(path, n):
    """A scene plus a face element (vertex indices), an edge element and an unrelated element."""
    random_splats_ply(path, n, seed=2)
    ply = plyfile.PlyData.read(str(path), mmap=False)  # the file is rewritten below
    faces = np.empty(3, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32), np.array([3, 4, 5], np.int32), np.array([n - 1, 0, 1], np.int32)]
    edges = np.array([(0, 1), (1, 2)], dtype=[("vertex1", "i4"), ("vertex2", "i4")])
    camera = np.array([(1.0, 2.0)], dtype=[("fx", "f4"), ("fy", "f4")])
    elements = [ply["vertex"], plyfile.PlyElement.describe(faces, "face", val_types={"vertex_indices": "i4"}),
                plyfile.PlyElement.describe(edges, "edge"), plyfile.PlyElement.describe(camera, "camera")]  # fmt: skip
    plyfile.PlyData(elements, text=False, byte_order="<").write(str(path))


def test_library_drops_them_with_a_warning(tmp_path):
    path = tmp_path / "mesh.ply"
    with_elements(path, 200)
    splats = load_ply(path)
    with pytest.warns(NanogsWarning, match=r"dropped PLY element\(s\) 'face' \(3 rows\), 'edge' \(2 rows\)"):
        small = simplify(splats, count=20)
    assert [e.name for e in small.layout.other_elements] == ["camera"]
    assert [e.name for e in splats.layout.other_elements] == ["face", "edge", "camera"]  # the input is unchanged
    save_ply(small, tmp_path / "small.ply")
    assert [e.name for e in plyfile.PlyData.read(str(tmp_path / "small.ply")).elements] == ["vertex", "camera"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning when the rows stay the input's
        assert simplify(splats, count=200).layout is splats.layout


def test_cli_warns_in_one_line(tmp_path):
    path = tmp_path / "mesh.ply"
    with_elements(path, 200)
    result = CliRunner().invoke(app, ["simplify", str(path), "-o", str(tmp_path / "o.ply"), "--count", "20,10", "--device", "cpu"])
    assert result.exit_code == 0, result.output
    lines = result.stderr.strip().splitlines()
    assert lines == ["nanogs-warp: warning: dropped PLY element(s) 'face' (3 rows), 'edge' (2 rows): they index vertices, which simplification renumbers"]
    for name in ("o_20.ply", "o_10.ply"):
        assert [e.name for e in plyfile.PlyData.read(str(tmp_path / name)).elements] == ["vertex", "camera"]
    quiet = CliRunner().invoke(app, ["simplify", str(path), "-o", str(tmp_path / "q.ply"), "--count", "20", "--device", "cpu", "-q"])
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_splats_without_a_layout():
    splats = SplatSet.from_numpy(**random_splat_arrays(50, seed=1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert simplify(splats, count=5).layout is None
