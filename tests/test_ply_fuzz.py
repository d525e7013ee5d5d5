"""Malformed PLY bytes: load_ply (and scene_info) either return a valid result or raise InputError.

Valid seed files of several kinds are mutated: truncated, bytes flipped, inserted or deleted, header
lines deleted, duplicated, swapped or renamed, element counts and property types changed. Any
exception other than InputError fails the test.
"""

from __future__ import annotations

import json

import numpy as np
import plyfile
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scene_factory import random_splats_ply

from nanogs_warp.errors import InputError
from nanogs_warp.io.ply import load_ply
from nanogs_warp.io.scene_info import scene_info

SEEDS = [  # (n, sh_degree, byte_order, text, dtype, shuffle, extras, other elements)
    (3, 0, "<", False, "f4", False, (), False),
    (2, 1, ">", False, "f8", True, (("red", "u1"),), False),
    (3, 0, "<", True, "f4", False, (), False),
    (2, 3, "<", False, "f4", False, (), True),
    (2, 2, "<", True, "f8", True, (("id", "i4"),), True),
    (4, 0, ">", False, "f4", False, ("foo",), True),
]
TYPES = [b"uchar", b"char", b"short", b"ushort", b"int", b"uint", b"float", b"double", b"float32", b"int8",
         b"list uchar int", b"list int float", b"quad", b""]  # fmt: skip
NAMES = [b"x", b"vertex", b"face", b"f_rest_0", b"f_rest_99", b"opacity", b"rot_0", b"", b"1.0", b"list",
         b"\xff", b"binary_big_endian", b"ascii", b"end_header"]  # fmt: skip
COUNTS = [b"-1", b"0", b"1", b"2", b"3", b"5", b"1000", b"2147483648", b"18446744073709551617", b"1e3", b"x"]


def _seed_bytes(tmp_path_factory) -> list[bytes]:
    folder = tmp_path_factory.mktemp("fuzz-seeds")
    out = []
    for k, (n, sh, order, text, dtype, shuffle, extras, others) in enumerate(SEEDS):
        path = folder / f"seed{k}.ply"
        random_splats_ply(path, n, sh, seed=k, byte_order=order, text=text, dtype=dtype,
                          extra_props=extras, shuffle=shuffle)  # fmt: skip
        if others:
            data = plyfile.PlyData.read(str(path), mmap=False)  # it is rewritten below
            face = np.empty(2, [("vertex_indices", "O")])
            face["vertex_indices"] = [np.array([0, 1], "i4"), np.array([1, 0, 1], "i4")]
            cam = np.array([(1.0, 2)], [("f", "f4"), ("id", "u2")])
            data.elements = [*data.elements, plyfile.PlyElement.describe(face, "face"),
                             plyfile.PlyElement.describe(cam, "camera")]  # fmt: skip
            data.comments = ["fuzz seed"]
            data.write(str(path))
        out.append(path.read_bytes())
    return out


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _seed_bytes(tmp_path_factory)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz") / "case.ply"


def split_header(data: bytes) -> tuple[list[bytes], bytes]:
    end = data.find(b"end_header\n")
    if end < 0:
        return data.split(b"\n"), b""
    return data[:end].split(b"\n")[:-1] + [b"end_header"], data[end + 11 :]


@st.composite
def mutation(draw, data: bytes) -> bytes:
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "line-delete", "line-dup", "line-swap",
                                 "rename", "count", "type", "format"]))  # fmt: skip
    if kind == "truncate":
        return data[: draw(st.integers(0, len(data)))]
    if kind == "flip":
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        return data[:at] + bytes([data[at] ^ draw(st.integers(1, 255))]) + data[at + 1 :] if data else data
    if kind == "insert":
        at = draw(st.integers(0, len(data)))
        return data[:at] + draw(st.binary(min_size=1, max_size=8)) + data[at:]
    if kind == "delete":
        at = draw(st.integers(0, len(data)))
        return data[:at] + data[at + draw(st.integers(1, 16)) :]
    lines, body = split_header(data)
    i = draw(st.integers(0, len(lines) - 1))
    if kind == "line-delete":
        del lines[i]
    elif kind == "line-dup":
        lines.insert(i, lines[i])
    elif kind == "line-swap":
        j = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[j] = lines[j], lines[i]
    elif kind == "rename":
        words = lines[i].split(b" ")
        words[draw(st.integers(0, len(words) - 1))] = draw(st.sampled_from(NAMES))
        lines[i] = b" ".join(words)
    elif kind == "count":
        elements = [k for k, line in enumerate(lines) if line.startswith(b"element")] or [i]
        k = draw(st.sampled_from(elements))
        lines[k] = b" ".join(lines[k].split(b" ")[:2] + [draw(st.sampled_from(COUNTS))])
    elif kind == "type":
        props = [k for k, line in enumerate(lines) if line.startswith(b"property")] or [i]
        k = draw(st.sampled_from(props))
        words = lines[k].split(b" ")
        lines[k] = b" ".join([words[0], draw(st.sampled_from(TYPES)), words[-1]])
    elif kind == "format":
        lines[min(1, len(lines) - 1)] = b"format " + draw(
            st.sampled_from([b"ascii", b"binary_little_endian", b"binary_big_endian", b"binary"])) + b" 1.0"
    return b"\n".join(lines) + b"\n" + body


@st.composite
def mutated_file(draw, seeds):
    if draw(st.integers(0, 9)) == 0:  # pure noise, sometimes behind a plausible first line
        return draw(st.sampled_from([b"", b"ply\n", b"ply\nformat ascii 1.0\n"])) + draw(st.binary(max_size=200))
    data = draw(st.sampled_from(seeds))
    for _ in range(draw(st.integers(1, 3))):
        data = draw(mutation(data))
    return data


def check_outcome(path):
    """load_ply and scene_info: a valid result or one InputError line; anything else fails."""
    for drop in (False, True):
        try:
            splats = load_ply(path, drop_invalid=drop)
        except InputError as e:
            assert str(e) and "\n" not in str(e)
            continue
        host = splats.to_numpy()
        assert splats.count >= 1
        for key in ("means", "rotations", "log_scales", "opacities", "features"):
            assert np.isfinite(host[key]).all(), key
        norms = np.linalg.norm(host["rotations"].astype(np.float64), axis=1)
        np.testing.assert_allclose(norms, 1.0, atol=1e-6)
        assert host["extras"].shape == (splats.count, len(splats.layout.float_extra_names))
        assert host["integer_extras"].shape == (splats.count, len(splats.layout.integer_extra_names))
    try:
        json.dumps(scene_info(path))
    except InputError as e:
        assert str(e) and "\n" not in str(e)


def test_mutated_files(seeds, scratch):
    @settings(max_examples=200, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])  # fmt: skip
    @given(st.data())
    def run(data):
        scratch.write_bytes(data.draw(mutated_file(seeds)))
        check_outcome(scratch)

    run()


def test_seed_files_load(seeds, scratch):
    for data in seeds:
        scratch.write_bytes(data)
        assert load_ply(scratch).count >= 1


@pytest.mark.parametrize("which", [0, 2, 3], ids=["binary", "ascii", "binary-with-elements"])
def test_every_truncation(seeds, scratch, which):
    """Every proper prefix of a file is rejected with InputError. (An ASCII file cut inside its last
    line still parses, as its last number may just be shorter: those cuts are not checked.)"""
    data = seeds[which]
    end = data.rindex(b"\n", 0, len(data) - 1) + 1 if which == 2 else len(data)
    for cut in range(end):
        scratch.write_bytes(data[:cut])
        with pytest.raises(InputError):
            load_ply(scratch)
