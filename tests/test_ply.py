"""PLY reading and writing: round trips, layouts, every rejected input, atomic writes, `info`."""

from __future__ import annotations

import errno
import json
import os
import re
from importlib import resources

import numpy as np
import plyfile
import pytest
from scene_factory import (
    random_splat_arrays,
    random_splats_ply,
    write_2dgs_copy,
    write_splats_ply,
)

from nanogs_warp.cli.info import format_info
from nanogs_warp.errors import InputError
from nanogs_warp.io import ply
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.io.scene_info import scene_info
from nanogs_warp.splats import SplatSet

INRIA = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
KEYS = ("means", "rotations", "log_scales", "opacities", "features", "extras", "integer_extras")


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def assert_bitwise_equal(got: dict, want: dict):
    for key in KEYS:
        assert got[key].shape == want[key].shape, key
        np.testing.assert_array_equal(bits(got[key]), bits(want[key]), err_msg=key)


def header_of(path) -> list[str]:
    data = open(path, "rb").read()
    end = data.index(b"end_header")
    return data[:end].decode().splitlines()


def vertex_names(path) -> list[str]:
    return [line.split()[-1] for line in header_of(path) if line.startswith("property")]


def edit_header(path, old: bytes, new: bytes, count: int = 1):
    """Replaces text in the header only (the binary body may hold the same bytes)."""
    data = open(path, "rb").read()
    end = data.index(b"end_header")
    head = data[:end]
    assert old in head, old
    open(path, "wb").write(head.replace(old, new, count) + data[end:])


# ----------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize(
    "options",
    [
        dict(),
        dict(byte_order=">"),
        dict(text=True),
        dict(dtype="f8"),
        dict(dtype="f8", byte_order=">"),
        dict(shuffle=True),
        dict(text=True, dtype="f8", shuffle=True),
    ],
    ids=["le", "be", "ascii", "float64", "float64-be", "shuffled", "ascii-float64-shuffled"],
)
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_round_trip(tmp_path, options, sh_degree):
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    want = random_splats_ply(src, 40, sh_degree=sh_degree, seed=sh_degree, **options)
    splats = load_ply(src)
    assert splats.count == 40 and splats.sh_degree == sh_degree
    assert_bitwise_equal(splats.to_numpy(), want)
    save_ply(splats, out)
    again = load_ply(out)
    assert_bitwise_equal(again.to_numpy(), want)
    # names, order and dtypes follow the input; the output is always binary little-endian
    assert again.layout.properties == splats.layout.properties
    assert vertex_names(out) == vertex_names(src)
    assert header_of(out)[1] == "format binary_little_endian 1.0"
    if options.get("dtype") == "f8":
        assert {t for _, t in again.layout.properties} == {"f8"}


def test_load_onto_device_and_save_from_it(tmp_path, device):
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    want = random_splats_ply(src, 64, sh_degree=2, seed=5, extra_props=("foo",))
    splats = load_ply(src, device=device)
    assert str(splats.device) == device and all(a.device == splats.device for a in splats.arrays())
    assert_bitwise_equal(splats.to_numpy(), want)
    save_ply(splats, out)
    assert out.read_bytes() == src.read_bytes()


def test_layout_describes_file(tmp_path):
    path = tmp_path / "s.ply"
    random_splats_ply(path, 5, sh_degree=1, extra_props=(("red", "u1"), "foo"))
    layout = load_ply(path).layout
    assert [n for n, _ in layout.properties] == vertex_names(path)
    assert dict(layout.properties)["red"] == "u1" and dict(layout.properties)["x"] == "f4"
    assert layout.extra_names == ["nx", "ny", "nz", "red", "foo"]
    features = [n for n, _ in layout.properties if n.startswith("f_")]
    assert features == ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]


@pytest.mark.parametrize(
    "options", [dict(), dict(byte_order=">"), dict(text=True), dict(dtype="f8")], ids=["le", "be", "ascii", "float64"]
)
def test_a_2dgs_file_reads_as_flat_splats_and_writes_as_3dgs(tmp_path, options):
    full, surfels, out = tmp_path / "3dgs.ply", tmp_path / "2dgs.ply", tmp_path / "out.ply"
    want = random_splats_ply(full, 40, sh_degree=1, seed=8, **options)
    write_2dgs_copy(full, surfels, options.get("byte_order", "<"), options.get("text", False))
    notes = []
    splats = load_ply(surfels, on_drop=notes.append)
    want["log_scales"][:, 2] = -30.0  # ply_header.FLAT_LOG_SCALE
    assert_bitwise_equal(splats.to_numpy(), want)
    assert splats.layout.surfels and "scale_2" not in dict(splats.layout.properties)
    assert notes == ["2dgs.ply: 2DGS surfels (scale_0 and scale_1, no scale_2) read as flat 3DGS splats "
                     "(log-scale -30 on the third axis), and written as 3DGS"]  # fmt: skip
    save_ply(splats, out)
    assert vertex_names(out) == vertex_names(full)  # scale_2 after scale_1, of scale_1's type
    assert dict(load_ply(out).layout.properties) == dict(load_ply(full).layout.properties)
    again = load_ply(out)
    assert not again.layout.surfels
    assert_bitwise_equal(again.to_numpy(), want)


def test_a_2dgs_file_in_info(tmp_path):
    full, surfels = tmp_path / "3dgs.ply", tmp_path / "2dgs.ply"
    want = random_splats_ply(full, 30, seed=9)
    write_2dgs_copy(full, surfels)
    assert scene_info(full)["model"] == "3DGS" and "model" not in format_info(scene_info(full))
    info = scene_info(surfels)
    assert info["model"] == "2DGS"
    assert [p["name"] for p in info["properties"]] == vertex_names(surfels)
    two_axes = np.exp(want["log_scales"][:, :2].astype(np.float64))  # the file's axes, not the load's third
    assert info["scale"]["min"] == two_axes.min() and info["scale"]["max"] == two_axes.max()
    assert "model       2DGS (no scale_2): read as flat 3DGS splats, written as 3DGS" in format_info(info)


@pytest.mark.parametrize(("removed", "missing"), [(("scale_1", "scale_2"), "scale_1, scale_2"), (("scale_0",), "scale_0")])
def test_scales_missing_otherwise_than_a_2dgs_file(tmp_path, removed, missing):
    path = tmp_path / "s.ply"
    random_splats_ply(path, 5, seed=10)
    for name in removed:
        edit_header(path, f"property float {name}\n".encode(), b"")
    with pytest.raises(InputError, match=f"^s.ply: not a 3DGS splat file: missing vertex properties {missing}$"):
        load_ply(path)


def test_extras_other_elements_and_comments_survive(tmp_path):
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    camera = np.array([(1.5, 2.0, 7), (3.0, -1.0, 9)], [("fx", "f8"), ("fy", "f4"), ("id", "i2")])
    face = np.empty(2, [("vertex_indices", "O")])
    face["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([2, 3, 4, 5], "i4")]
    extra = (("red", "u1"), ("temp", "i2"), ("big", "u4"), ("w64", "f8"), "foo")
    want = write_splats_ply(
        src, random_splat_arrays(30, 1, seed=4), byte_order=">", extra_props=extra, seed=4,
        comments=["made by a test", "second comment"], obj_info=["scanner 1"],
        other_elements=[plyfile.PlyElement.describe(camera, "camera"),
                        plyfile.PlyElement.describe(face, "face", val_types={"vertex_indices": "i4"})],
    )  # fmt: skip
    splats = load_ply(src)
    assert splats.layout.extra_names == ["nx", "ny", "nz", "red", "temp", "big", "w64", "foo"]
    assert_bitwise_equal(splats.to_numpy(), want)
    save_ply(splats, out)
    back = plyfile.PlyData.read(str(out))
    assert back.comments == ["made by a test", "second comment"]
    assert back.obj_info == ["scanner 1"]
    assert [e.name for e in back.elements] == ["vertex", "camera", "face"]
    assert back["camera"].data.dtype == np.dtype([("fx", "<f8"), ("fy", "<f4"), ("id", "<i2")])
    np.testing.assert_array_equal(back["camera"].data, camera.astype(back["camera"].data.dtype))
    assert [list(v) for v in back["face"].data["vertex_indices"]] == [[0, 1, 2], [2, 3, 4, 5]]
    vertex = back["vertex"].data
    assert vertex.dtype["red"] == np.dtype("u1") and vertex.dtype["big"] == np.dtype("<u4")
    np.testing.assert_array_equal(vertex["temp"], want["integer_extras"][:, 1])
    assert_bitwise_equal(load_ply(out).to_numpy(), want)


@pytest.mark.parametrize("with_list", [False, True], ids=["plain", "list"])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_elements_before_vertex(tmp_path, with_list, byte_order):
    """The vertex element need not come first (read from its offset, or from plyfile's array when a
    list element before it makes the offset unknown); on save it is written first."""
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    want = random_splats_ply(src, 300, sh_degree=1, seed=7, byte_order=byte_order)
    data = plyfile.PlyData.read(str(src), mmap=False)
    if with_list:
        first = np.empty(3, [("vertex_indices", "O")])
        first["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([5], "i4"), np.array([], "i4")]
    else:
        first = np.array([(1, 2.5), (3, -1.0)], [("id", "u2"), ("f", "f8")])
    data.elements = [plyfile.PlyElement.describe(first, "before"), *data.elements]
    data.write(str(src))
    splats = load_ply(src)
    assert_bitwise_equal(splats.to_numpy(), want)
    save_ply(splats, out)
    back = plyfile.PlyData.read(str(out))
    assert [e.name for e in back.elements] == ["vertex", "before"]
    assert_bitwise_equal(load_ply(out).to_numpy(), want)


def test_many_chunks(tmp_path, monkeypatch):
    """Rows are converted and written in chunks; a chunk of a few rows gives the same result."""
    monkeypatch.setattr(ply, "_CHUNK_BYTES", 7 * 68)  # 7 rows of 17 float32
    monkeypatch.setattr(ply, "_READ_UNIT_BYTES", 7 * 68)
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    want = random_splats_ply(src, 100, seed=3)
    splats = load_ply(src)
    assert_bitwise_equal(splats.to_numpy(), want)
    save_ply(splats, out)
    assert out.read_bytes() == src.read_bytes()


@pytest.mark.parametrize("layout", ["binary", "ascii", "element_after", "list_before", "many_chunks"])
def test_digest_sees_the_whole_file_once(tmp_path, monkeypatch, layout):
    """load_ply(digest=...) hashes the file in the pass that parses it (or in a pass of its own
    when the vertex offset is unknown): the digest is the file's SHA-256 in every layout."""
    import hashlib

    src = tmp_path / "in.ply"
    want = random_splats_ply(src, 300, sh_degree=1, seed=5, text=layout == "ascii")
    if layout in ("element_after", "list_before"):
        data = plyfile.PlyData.read(str(src), mmap=False)
        other = np.empty(3, [("vertex_indices", "O")])
        other["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([5], "i4"), np.array([], "i4")]
        element = plyfile.PlyElement.describe(other, "face")
        data.elements = [*data.elements, element] if layout == "element_after" else [element, *data.elements]
        data.write(str(src))
    if layout == "many_chunks":
        monkeypatch.setattr(ply, "_CHUNK_BYTES", 7 * 68)
        monkeypatch.setattr(ply, "_READ_UNIT_BYTES", 7 * 68)
    digest = hashlib.sha256()
    assert_bitwise_equal(load_ply(src, digest=digest).to_numpy(), want)
    assert digest.hexdigest() == hashlib.sha256(src.read_bytes()).hexdigest()


def test_float_values_of_integer_extras_are_rounded_and_clipped(tmp_path):
    """``SplatSet.from_numpy`` given every extra property in ``extras`` (the integer ones as floats,
    no ``integer_extras``) rounds and clips the integer ones to their type."""
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    random_splats_ply(src, 5, extra_props=(("red", "u1"), ("temp", "i2")))
    splats = load_ply(src)
    host = splats.to_numpy()
    every = np.concatenate([host["extras"], host.pop("integer_extras")], axis=1).astype(np.float32)
    assert splats.layout.extra_names == ["nx", "ny", "nz", "red", "temp"]
    every[:, 3] = [300.7, -5.0, 3.6, np.nan, 254.5]
    every[:, 4] = [1e9, -1e9, -2.4, 7.5, np.inf]
    save_ply(SplatSet.from_numpy(**dict(host, extras=every), layout=splats.layout), out)
    vertex = plyfile.PlyData.read(str(out))["vertex"].data
    np.testing.assert_array_equal(vertex["red"], [255, 0, 4, 0, 254])  # rint: half to even
    np.testing.assert_array_equal(vertex["temp"], [32767, -32768, -2, 8, 32767])


def test_save_without_layout_uses_inria_order(tmp_path):
    out = tmp_path / "plain.ply"
    arrays = random_splat_arrays(12, sh_degree=2, seed=1)
    save_ply(SplatSet.from_numpy(**arrays), out)
    assert vertex_names(out) == INRIA + [f"f_rest_{i}" for i in range(24)] + TAIL
    assert all(line.startswith("property float ") for line in header_of(out) if line.startswith("property"))
    vertex = plyfile.PlyData.read(str(out))["vertex"].data
    assert not vertex["nx"].any() and not vertex["nz"].any()
    np.testing.assert_array_equal(vertex["rot_0"], arrays["rotations"][:, 0])  # w first
    splats = load_ply(out)
    assert splats.layout.extra_names == ["nx", "ny", "nz"]
    got = splats.to_numpy()
    for key in KEYS[:5]:
        np.testing.assert_array_equal(bits(got[key]), bits(arrays[key]), err_msg=key)


def test_save_after_sh_degree_change_rewrites_f_rest(tmp_path):
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    random_splats_ply(src, 8, sh_degree=2, shuffle=True, seed=2)
    splats = load_ply(src)
    host = splats.to_numpy()
    host["features"] = np.ascontiguousarray(host["features"][:, :12])  # degree 2 -> 1
    save_ply(SplatSet.from_numpy(**host, layout=splats.layout), out)
    again = load_ply(out)
    assert again.sh_degree == 1
    np.testing.assert_array_equal(again.to_numpy()["features"], host["features"])


def test_quaternions_are_normalised_w_first(tmp_path):
    path = tmp_path / "q.ply"
    arrays = random_splat_arrays(50, seed=6)
    scale = np.random.default_rng(6).uniform(0.3, 3.0, (50, 1)).astype(np.float32)
    raw = arrays["rotations"] * scale
    arrays["rotations"] = raw.copy()
    arrays["rotations"][0] = [2.0, 0.0, 0.0, 0.0]
    arrays["rotations"][1] = [0.0, 0.0, 0.0, 1e-30]  # tiny but not zero
    write_splats_ply(path, arrays)
    splats = load_ply(path)
    got = splats.to_numpy()["rotations"]
    want = arrays["rotations"].astype(np.float64)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    np.testing.assert_allclose(got, want, atol=2e-7)
    np.testing.assert_allclose(np.linalg.norm(got.astype(np.float64), axis=1), 1.0, atol=2e-7)
    np.testing.assert_array_equal(got[:2], [[1, 0, 0, 0], [0, 0, 0, 1]])
    xyzw = splats.rotations.numpy()
    np.testing.assert_array_equal(xyzw[0], [0, 0, 0, 1])  # Warp order: w last


def test_unit_quaternions_are_kept_bit_exact(tmp_path):
    path = tmp_path / "u.ply"
    arrays = random_splats_ply(path, 200, seed=8)
    np.testing.assert_array_equal(bits(load_ply(path).to_numpy()["rotations"]), bits(arrays["rotations"]))


def test_shipped_sample_loads():
    sample = resources.files("nanogs_warp.data") / "plant_crop.ply"
    with resources.as_file(sample) as path:
        assert os.path.getsize(path) < 3_000_000
        splats = load_ply(path)
        assert splats.count == 20_000 and splats.sh_degree == 0
        host = splats.to_numpy()
        assert all(np.isfinite(host[k]).all() for k in KEYS)
        assert vertex_names(path) == INRIA + TAIL
        assert any("CC-BY-4.0" in c for c in splats.layout.comments)


# ----------------------------------------------------------------------------------------------
# Rejected inputs: every one an InputError whose single line names the file and the problem


def expect_error(path, *fragments, **kwargs) -> str:
    with pytest.raises(InputError) as info:
        load_ply(path, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(os.path.basename(str(path)) + ":"), message
    for fragment in fragments:
        assert re.search(fragment, message), (fragment, message)
    return message


@pytest.fixture
def good(tmp_path):
    """A valid little-endian SH-degree-2 file of 10 splats (the tests edit it)."""
    path = tmp_path / "scene.ply"
    random_splats_ply(path, 10, sh_degree=2, seed=1)
    return path


def test_missing_file(tmp_path):
    expect_error(tmp_path / "nope.ply", "no such file")


def test_directory(tmp_path):
    (tmp_path / "dir.ply").mkdir()
    expect_error(tmp_path / "dir.ply", "directory")


def test_empty_file(tmp_path):
    (tmp_path / "e.ply").write_bytes(b"")
    expect_error(tmp_path / "e.ply", "empty")


@pytest.mark.parametrize("content", [b"hello world\n", b"\x00\x01\x02" * 50, b"plyx\nformat", b"PLY\n"])
def test_not_a_ply(tmp_path, content):
    (tmp_path / "n.ply").write_bytes(content)
    expect_error(tmp_path / "n.ply", "not a PLY file")


def test_truncated_body(good):
    data = good.read_bytes()
    good.write_bytes(data[:-7])
    expect_error(good, "truncated", "'vertex'")


def test_truncated_header(good):
    good.write_bytes(good.read_bytes()[:60])
    expect_error(good, "truncated PLY header")


def test_end_header_not_alone_on_its_line(good):
    data = good.read_bytes()
    good.write_bytes(data.replace(b"end_header\n", b"end_header \n", 1))
    expect_error(good, "'end_header' must be alone on its line")


def test_binary_header_lines_ending_unlike_end_header(good):
    """LF lines, then 'end_header' CR LF: plyfile takes the data for header lines. (CR LF throughout is
    read as it should be.)"""
    data = good.read_bytes()
    good.write_bytes(data.replace(b"end_header\n", b"end_header\r\n", 1))
    expect_error(good, "its lines end unlike its 'end_header' line")
    end = data.index(b"end_header\n") + len(b"end_header\n")
    good.write_bytes(data[:end].replace(b"\n", b"\r\n") + data[end:])
    assert load_ply(good).count > 0


def test_truncated_ascii(tmp_path):
    path = tmp_path / "a.ply"
    random_splats_ply(path, 10, text=True)
    data = path.read_bytes()
    path.write_bytes(data[: data.rindex(b"\n", 0, len(data) - 1) - 20])
    expect_error(path, "truncated")


def test_malformed_ascii_value(tmp_path):
    path = tmp_path / "a.ply"
    random_splats_ply(path, 4, text=True)
    data = path.read_bytes()
    end = data.index(b"end_header\n") + 11
    path.write_bytes(data[:end] + b"abc" + data[end + 1 :])
    expect_error(path, "malformed", "vertex")


@pytest.mark.parametrize(
    "old, new, fragments",
    [
        (b"element vertex 10", b"element points 10", ["no 'vertex' element", "points"]),
        (b"format binary_little_endian 1.0", b"format binary_middle_endian 1.0", ["header", "format"]),
        (b"property float x\n", b"property float x\nbanana split\n", ["malformed PLY header", "line 5", "banana split"]),
        (b"property float x\n", b"property float x\nproperty float x\n", ["'x' appears twice"]),
        (b"property float x\n", b"property quad x\n", ["unknown property type 'quad'"]),
        (b"element vertex 10", b"element vertex ten", ["not an integer"]),
        (b"element vertex 10", b"element vertex -3", ["negative"]),
        (b"element vertex 10", b"element vertex 10000000000000", ["truncated", "10000000000000 rows"]),
        (b"element vertex 10", b"element vertex 11", ["truncated"]),
        (b"property float opacity\n", b"", ["missing vertex properties opacity"]),
        (b"property float x\n", b"property list uchar float x\n", ["list properties", r"\bx\b"]),
        (b"property float f_rest_23\n", b"", ["23 f_rest_", "0, 9, 24 or 45"]),
        (b"property float f_rest_8\n", b"property float f_rest_24\n", ["missing f_rest_8", "unexpected f_rest_24"]),
        (b"property float opacity", b"property uint opacity", ["must be float", r"opacity \(uint\)"]),
    ],
    ids=["no-vertex", "bad-format", "garbage-line", "duplicate", "bad-type", "count-text", "count-negative",
         "count-huge", "count-plus-one", "missing", "list", "rest-count", "rest-gap", "int-required"],
)
def test_header_errors(good, old, new, fragments):
    edit_header(good, old, new)
    expect_error(good, *fragments)


def test_missing_properties_are_all_named(good):
    edit_header(good, b"property float scale_1\n", b"")
    edit_header(good, b"property float rot_3\n", b"")
    edit_header(good, b"property float y\n", b"")
    expect_error(good, "missing vertex properties y, scale_1, rot_3")


def test_zero_vertices(tmp_path):
    path = tmp_path / "z.ply"
    random_splats_ply(path, 3)
    data = path.read_bytes()
    path.write_bytes(data[: data.index(b"end_header\n") + 11].replace(b"element vertex 3", b"element vertex 0"))
    expect_error(path, "0 rows")


def test_non_ascii_header(good):
    edit_header(good, b"element vertex", b"comment \xff\xfe\nelement vertex")
    expect_error(good, "non-ASCII")


def make_invalid(path, text=False):
    """10 splats: row 2 NaN opacity, row 5 +Inf scale_1 and -Inf f_rest_3, row 7 zero quaternion."""
    arrays = random_splat_arrays(10, sh_degree=1, seed=3)
    arrays["opacities"][2] = np.nan
    arrays["log_scales"][5, 1] = np.inf
    arrays["features"][5, 6] = -np.inf
    arrays["rotations"][7] = 0.0
    write_splats_ply(path, arrays, text=text)
    return arrays


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_invalid_values_are_reported(tmp_path, text):
    path = tmp_path / "bad.ply"
    make_invalid(path, text)
    message = expect_error(path, "3 of 10 splats are invalid", "2 with NaN/Inf values in opacity, scale_1, f_rest_3",
                           "1 with zero-norm quaternions", "--drop-invalid")  # fmt: skip
    assert "f_rest_0" not in message


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_drop_invalid(tmp_path, text):
    path = tmp_path / "bad.ply"
    arrays = make_invalid(path, text)
    splats = load_ply(path, drop_invalid=True)
    keep = [0, 1, 3, 4, 6, 8, 9]
    assert splats.count == 7
    got = splats.to_numpy()
    for key in ("means", "log_scales", "opacities", "features"):
        np.testing.assert_array_equal(got[key], arrays[key][keep], err_msg=key)
    np.testing.assert_allclose(np.linalg.norm(got["rotations"], axis=1), 1.0, atol=2e-7)


def test_float64_overflowing_float32_is_invalid(tmp_path):
    path = tmp_path / "big.ply"
    arrays = random_splat_arrays(4, seed=2)
    arrays["means"] = arrays["means"].astype(np.float64)
    arrays["means"][1, 2] = 1e300
    write_splats_ply(path, arrays, dtype="f8")
    expect_error(path, "1 of 4", r"NaN/Inf values \(a double beyond float32's \+-3.4e38 counts as Inf\) in z")
    assert load_ply(path, drop_invalid=True).count == 3


def test_log_scales_outside_the_domain_are_invalid(tmp_path):
    """Finite log-scales beyond +-LOG_SCALE_LIMIT: refused with counts and property names, dropped
    on request, counted by info; the limits themselves are accepted."""
    from nanogs_warp.domain import LOG_SCALE_LIMIT

    path = tmp_path / "huge.ply"
    arrays = random_splat_arrays(8, seed=4)
    arrays["log_scales"][1, 0] = 4e17
    arrays["log_scales"][3, 2] = -np.nextafter(np.float32(LOG_SCALE_LIMIT), np.float32(np.inf))
    arrays["log_scales"][3, 0] = 1e3
    arrays["log_scales"][5] = [LOG_SCALE_LIMIT, -LOG_SCALE_LIMIT, 0.0]  # inside
    arrays["opacities"][6] = np.nan
    write_splats_ply(path, arrays)
    expect_error(path, "3 of 8 splats are invalid", "1 with NaN/Inf values in opacity",
                 r"2 with log-scales outside \[-100, 100\] in scale_0, scale_2", "--drop-invalid")  # fmt: skip
    kept = load_ply(path, drop_invalid=True).to_numpy()
    np.testing.assert_array_equal(kept["log_scales"], arrays["log_scales"][[0, 2, 4, 5, 7]])
    info = scene_info(path)
    assert info["out_of_domain"] == {"scale_0": 2, "scale_2": 1} and info["out_of_domain_rows"] == 2
    assert "log-scales  2 splats beyond +-100" in format_info(info)


def test_drop_invalid_leaving_nothing(tmp_path):
    path = tmp_path / "all.ply"
    arrays = random_splat_arrays(3, seed=1)
    arrays["rotations"][:] = 0.0
    write_splats_ply(path, arrays)
    expect_error(path, "all 3 splats are invalid", "none left", drop_invalid=True)


# ----------------------------------------------------------------------------------------------
# Atomic writes


def small_splats(tmp_path):
    random_splats_ply(tmp_path / "src.ply", 6, seed=5)
    return load_ply(tmp_path / "src.ply")


def test_write_to_missing_directory(tmp_path):
    target = tmp_path / "absent" / "out.ply"
    with pytest.raises(InputError, match="does not exist"):
        save_ply(small_splats(tmp_path), target)
    assert not target.parent.exists()


def test_write_to_a_directory_path(tmp_path):
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(InputError, match="is a directory"):
        save_ply(small_splats(tmp_path), tmp_path / "d.ply")


def test_unwritable_directory_permission_denied(tmp_path, monkeypatch):
    """Simulated EACCES (the tests may run as root, which ignores directory modes)."""
    splats = small_splats(tmp_path)
    out_dir = tmp_path / "ro"
    out_dir.mkdir()
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if os.path.dirname(os.fspath(path)) == str(out_dir):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(ply.os, "open", refuse)
    with pytest.raises(InputError, match="permission denied") as info:
        save_ply(splats, out_dir / "out.ply")
    assert "\n" not in str(info.value)
    assert os.listdir(out_dir) == []


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root ignores directory modes")
def test_unwritable_directory_real(tmp_path):
    splats = small_splats(tmp_path)
    out_dir = tmp_path / "ro"
    out_dir.mkdir()
    out_dir.chmod(0o500)
    try:
        with pytest.raises(InputError, match="permission denied"):
            save_ply(splats, out_dir / "out.ply")
        assert os.listdir(out_dir) == []
    finally:
        out_dir.chmod(0o700)


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), RuntimeError("boom")])
def test_failed_write_leaves_existing_output_untouched(tmp_path, monkeypatch, failure):
    splats = small_splats(tmp_path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    target = out_dir / "scene.ply"
    target.write_bytes(b"previous result")

    def fail_midway(stream, *args):
        stream.write(b"ply\nformat binary_little_endian 1.0\n" + b"\0" * 1000)
        raise failure

    monkeypatch.setattr(ply, "_write_ply_stream", fail_midway)
    with pytest.raises(InputError if isinstance(failure, OSError) else RuntimeError) as info:
        save_ply(splats, target)
    if isinstance(failure, OSError):
        assert "No space left on device" in str(info.value)
    assert target.read_bytes() == b"previous result"
    assert os.listdir(out_dir) == ["scene.ply"]


def test_successful_write_replaces_and_leaves_no_temp(tmp_path):
    splats = small_splats(tmp_path)
    target = tmp_path / "out.ply"
    target.write_bytes(b"old")
    save_ply(splats, target)
    assert load_ply(target).count == 6
    assert sorted(os.listdir(tmp_path)) == ["out.ply", "src.ply"]
    assert (target.stat().st_mode & 0o777) == (0o666 & ~_umask())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ----------------------------------------------------------------------------------------------
# info


def test_scene_info_reports_bad_values(tmp_path):
    path = tmp_path / "bad.ply"
    make_invalid(path)
    info = scene_info(path)
    assert info["count"] == 10 and info["sh_degree"] == 1 and info["format"] == "binary_little_endian"
    assert info["nonfinite"] == {"opacity": 1, "scale_1": 1, "f_rest_3": 1}
    assert info["nonfinite_rows"] == 2 and info["zero_norm_quaternions"] == 1
    assert [p["name"] for p in info["properties"]] == vertex_names(path)
    json.dumps(info)  # JSON-ready
    text = format_info(info)
    assert "NaN/Inf     2 splats" in text and "zero quats  1" in text


def test_scene_info_statistics(tmp_path):
    path = tmp_path / "s.ply"
    arrays = random_splats_ply(path, 100, sh_degree=3, extra_props=("foo",), seed=9)
    info = scene_info(path)
    assert info["sh_degree"] == 3 and info["extra_properties"] == ["nx", "ny", "nz", "foo"]
    np.testing.assert_allclose(info["bbox"]["min"], arrays["means"].min(0), rtol=1e-6)
    np.testing.assert_allclose(info["bbox"]["max"], arrays["means"].max(0), rtol=1e-6)
    alpha = 1 / (1 + np.exp(-arrays["opacities"].astype(np.float64)))
    assert info["opacity"]["median"] == pytest.approx(np.median(alpha))
    assert info["opacity"]["mean"] == pytest.approx(alpha.mean())
    assert info["scale"]["max"] == pytest.approx(np.exp(arrays["log_scales"].astype(np.float64)).max())
    assert info["nonfinite"] == {} and info["zero_norm_quaternions"] == 0
    assert "f_rest_0..44:f4" in format_info(info)


def test_scene_info_rejects_broken_files(good):
    edit_header(good, b"property float opacity\n", b"")
    with pytest.raises(InputError, match="missing vertex properties opacity"):
        scene_info(good)


def test_nan_in_another_property_is_invalid_like_any(tmp_path):
    """A NaN or Inf in a property outside the 3DGS model (here the normal nx) makes its row invalid
    as in any other: refused in one line naming it, dropped with drop_invalid, and counted by info."""
    arrays = random_splat_arrays(50, sh_degree=0, seed=3)
    path = tmp_path / "normals.ply"
    save_ply(SplatSet.from_numpy(**arrays), path)  # INRIA layout: nx ny nz written as zeros
    ply = plyfile.PlyData.read(str(path))
    vertex = ply["vertex"].data.copy()
    vertex["nx"][7] = np.nan
    vertex["ny"][9] = np.inf
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))
    with pytest.raises(InputError, match=r"2 of 50 splats are invalid \(2 with NaN/Inf values in nx, ny\)"):
        load_ply(path)
    dropped = []
    loaded = load_ply(path, drop_invalid=True, on_drop=dropped.append)
    assert loaded.count == 48 and np.isfinite(loaded.extras.numpy()).all() and "nx, ny" in dropped[0]
    info = scene_info(path)
    assert info["nonfinite_rows"] == 2 and info["nonfinite"] == {"nx": 1, "ny": 1}


def test_bytes_after_the_declared_data_are_said(tmp_path):
    """A binary file longer than its header declares (a vertex count smaller than the data's, or
    bytes appended) is read as declared, with one note saying how many bytes were ignored."""
    path = tmp_path / "scene.ply"
    random_splats_ply(path, 40, sh_degree=1, seed=2)
    notes = []
    assert load_ply(path, on_drop=notes.append).count == 40 and notes == []
    with open(path, "ab") as f:
        f.write(b"\0" * 100)
    assert load_ply(path, on_drop=notes.append).count == 40
    assert len(notes) == 1 and "100 bytes after the data its header declares were ignored" in notes[0]
    assert scene_info(path)["trailing_bytes"] == 100 and "100 bytes after the declared data" in format_info(scene_info(path))


def test_a_refused_file_gets_its_error_and_no_note(tmp_path):
    """What a load says about a file it reads (bytes after the declared data, 2DGS surfels) is said
    only once its values have passed: a refused file gets its one error line, nothing before it."""
    full, surfels = tmp_path / "3dgs.ply", tmp_path / "2dgs.ply"
    arrays = random_splat_arrays(40, seed=13)
    arrays["means"][3, 1] = np.nan
    write_splats_ply(full, arrays)
    write_2dgs_copy(full, surfels)
    with open(surfels, "ab") as f:
        f.write(b"\0" * 64)
    notes = []
    with pytest.raises(InputError, match=r"^2dgs.ply: 1 of 40 splats are invalid \(1 with NaN/Inf values in y\)"):
        load_ply(surfels, on_drop=notes.append)
    assert notes == []
    assert load_ply(surfels, drop_invalid=True, on_drop=notes.append).count == 39
    assert [n.split(": ", 1)[1][:12] for n in notes] == ["dropped 1 of", "64 bytes aft", "2DGS surfels"]


def test_a_control_character_in_the_header_is_one_line(tmp_path):
    """A NUL (or another control character) in a property name is refused, not carried into the
    output's header; tabs between words are fine."""
    path = tmp_path / "scene.ply"
    random_splats_ply(path, 10, sh_degree=0, seed=1)
    data = path.read_bytes()
    (tmp_path / "nul.ply").write_bytes(data.replace(b"property float opacity", b"property float opa\0city", 1))
    with pytest.raises(InputError, match="control character"):
        load_ply(tmp_path / "nul.ply")
    (tmp_path / "comment.ply").write_bytes(data.replace(b"end_header", b"comment a\0b\nend_header", 1))
    with pytest.raises(InputError, match="control character"):
        load_ply(tmp_path / "comment.ply")
    (tmp_path / "tabs.ply").write_bytes(data.replace(b"property float opacity", b"property\tfloat\topacity", 1))
    assert load_ply(tmp_path / "tabs.ply").count == 10
