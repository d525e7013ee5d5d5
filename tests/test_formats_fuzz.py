"""Malformed files of every format: the readers return a valid scene or raise InputError (never
another exception, never a large allocation for a large declared size in a small file); the CLI
answers one line on stderr, exit code 2, and writes nothing."""

from __future__ import annotations

import gzip
import io
import json
import struct
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scene_factory import random_splat_arrays
from typer.testing import CliRunner

from nanogs_warp import SplatSet
from nanogs_warp.cli.app import app
from nanogs_warp.errors import InputError
from nanogs_warp.io import load_splats, save_splats
from nanogs_warp.io.scene_info import scene_info
from nanogs_warp.io.spz import encode as spz_encode

NAMES = {"splat": "seed.splat", "compressed-ply": "seed.compressed.ply", "spz": "seed.spz", "sog": "seed.sog"}


def _seed_files(folder) -> dict[str, bytes]:
    splats = SplatSet.from_numpy(**random_splat_arrays(6, 1, seed=3))
    out = {}
    for fmt, name in NAMES.items():
        save_splats(splats, folder / name)
        out[fmt] = (folder / name).read_bytes()
    return out


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _seed_files(tmp_path_factory.mktemp("format-seeds"))


@st.composite
def mutated(draw, data: bytes) -> bytes:
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "splice"]))
    if kind == "truncate":
        return data[: draw(st.integers(0, len(data)))]
    at = draw(st.integers(0, max(len(data) - 1, 0)))
    if kind == "flip":
        return data[:at] + bytes([draw(st.integers(0, 255))]) + data[at + 1 :]
    if kind == "insert":
        return data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:]
    if kind == "delete":
        return data[:at] + data[at + draw(st.integers(1, 16)) :]
    return data[:at] + draw(st.sampled_from([b"\xff" * 8, b"\x00" * 8, b"\x7f\xff\xff\xff", b"end_header\n"])) + data[at + 8 :]


def _load_or_input_error(path) -> None:
    try:
        splats = load_splats(path)
    except InputError as e:
        assert "\n" not in str(e)
        return
    values = splats.to_numpy()
    assert splats.count > 0 and all(np.isfinite(values[k]).all() for k in ("means", "log_scales", "features"))


def _rezip(data: bytes, member: str, new: bytes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            dst.writestr(info.filename, new if info.filename == member else src.read(info))
    return out.getvalue()


@pytest.mark.parametrize("fmt", list(NAMES))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_raw_mutations(seeds, tmp_path_factory, fmt, data):
    path = tmp_path_factory.mktemp("fuzz") / NAMES[fmt]
    path.write_bytes(data.draw(mutated(seeds[fmt])))
    _load_or_input_error(path)
    try:
        scene_info(path)
    except InputError:
        pass


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_spz_payload_mutations(seeds, tmp_path_factory, data):
    payload = gzip.decompress(seeds["spz"])
    path = tmp_path_factory.mktemp("fuzz") / "x.spz"
    path.write_bytes(gzip.compress(data.draw(mutated(payload)), mtime=0))
    _load_or_input_error(path)


@pytest.mark.parametrize("member", ["meta.json", "means_l.webp", "quats.webp", "shN_labels.webp"])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_sog_member_mutations(seeds, tmp_path_factory, member, data):
    with zipfile.ZipFile(io.BytesIO(seeds["sog"])) as z:
        original = z.read(member)
    if member == "meta.json":
        meta = json.loads(original)
        key = data.draw(st.sampled_from(["count", "means", "scales", "shN", "version", "quats", "sh0"]))
        meta[key] = data.draw(st.sampled_from([None, -1, 0, 2**40, "x", [], {}, [1.5] * 3, {"files": ["../x"]}]))
        new = json.dumps(meta).encode()
    else:
        new = data.draw(mutated(original))
    path = tmp_path_factory.mktemp("fuzz") / "x.sog"
    path.write_bytes(_rezip(seeds["sog"], member, new))
    _load_or_input_error(path)


def _peak_bytes(fn) -> int:
    tracemalloc.start()
    try:
        with pytest.raises(InputError):
            fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_huge_declared_sizes_allocate_nothing_large(seeds, tmp_path):
    limit = 32 << 20
    spz = tmp_path / "huge.spz"
    spz.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 0xFFFFFFF0, 3, 12, 0, 0) + b"\0" * 64, mtime=0))
    assert _peak_bytes(lambda: load_splats(spz)) < limit

    cply = tmp_path / "huge.compressed.ply"
    head, _, body = seeds["compressed-ply"].partition(b"end_header\n")
    head = head.replace(b"element vertex 6", b"element vertex 1000000000000").replace(b"element chunk 1", b"element chunk 3906250000")
    cply.write_bytes(head + b"end_header\n" + body)
    assert _peak_bytes(lambda: load_splats(cply)) < limit

    with zipfile.ZipFile(io.BytesIO(seeds["sog"])) as z:
        meta = json.loads(z.read("meta.json"))
        webp = z.read("means_l.webp")
    meta["count"] = 2**31
    sog = tmp_path / "huge.sog"
    sog.write_bytes(_rezip(seeds["sog"], "meta.json", json.dumps(meta).encode()))
    assert _peak_bytes(lambda: load_splats(sog)) < limit

    # a WebP whose header declares 16383 x 16383 pixels (VP8L: 14-bit width-1 and height-1)
    assert webp[12:16] == b"VP8L" and webp[20] == 0x2F
    bits = int.from_bytes(webp[21:25], "little")
    bits |= (1 << 28) - 1
    big = webp[:21] + bits.to_bytes(4, "little") + webp[25:]
    sog2 = tmp_path / "bigimage.sog"
    sog2.write_bytes(_rezip(seeds["sog"], "means_l.webp", big))
    assert _peak_bytes(lambda: load_splats(sog2)) < limit


def test_spz_versions_and_flags_we_do_not_read(tmp_path):
    host = SplatSet.from_numpy(**random_splat_arrays(4, 0, seed=1)).to_numpy()
    payload = bytearray(gzip.decompress(spz_encode(host)[0]))
    for offset, value, message in ((4, 4, "version 4"), (4, 1, "version 1"), (12, 4, "SH degree 4"), (14, 2, "extensions")):
        changed = bytearray(payload)
        changed[offset] = value
        path = tmp_path / "x.spz"
        path.write_bytes(gzip.compress(bytes(changed), mtime=0))
        with pytest.raises(InputError, match=message):
            load_splats(path)
    path.write_bytes(struct.pack("<II", 0x5053474E, 4) + b"\0" * 24)
    with pytest.raises(InputError, match="uncompressed SPZ"):
        load_splats(path)


@pytest.mark.parametrize("fmt", list(NAMES))
@pytest.mark.parametrize("cut", [0, 5, 31, 100])
def test_cli_one_line_exit_2_no_output(seeds, tmp_path, fmt, cut):
    bad = tmp_path / NAMES[fmt]
    bad.write_bytes(seeds[fmt][:cut] + (b"\x13" * 7 if cut else b""))
    out = tmp_path / "out.ply"
    result = CliRunner().invoke(app, ["simplify", str(bad), "-o", str(out), "--count", "1", "--device", "cpu"])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nanogs-warp: error: "), result.stderr
    assert "Traceback" not in result.output
    assert not out.exists() and not list(tmp_path.glob(".*.tmp"))
