"""Encode -> decode round trips of every format within its documented error (docs/formats.md), on
generated scenes of SH degree 0-3 and the shipped sample; detection by content; what is dropped."""

from __future__ import annotations

import json
import re
import zipfile
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from scene_factory import in_units, random_splat_arrays

from nanogs_warp import InputError, SplatSet
from nanogs_warp.io import detect_format, format_for_path, load_splats, save_splats
from nanogs_warp.io.common import SH_C0, morton_order
from nanogs_warp.io.ply import load_ply
from nanogs_warp.io.spz import encode as spz_encode

SAMPLE = Path(str(resources.files("nanogs_warp.data") / "plant_crop.ply"))
ALPHA_ERROR = 0.5 / 255 + 1e-6  # every format: alpha in 8 bits


def scene(n: int, degree: int, seed: int) -> dict[str, np.ndarray]:
    a = random_splat_arrays(n, degree, seed)
    a["features"] *= 0.4  # keep most SH values inside the 8-bit formats' ranges; clipping is tested apart
    return a


def sample() -> dict[str, np.ndarray]:
    a = load_ply(SAMPLE).to_numpy()
    a["extras"] = a["extras"][:, :0]
    return a


def round_trip(tmp_path, arrays, name: str, **kwargs) -> dict[str, np.ndarray]:
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    save_splats(SplatSet.from_numpy(**arrays), path, **kwargs)
    return load_splats(path).to_numpy()


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def angle_deg(q0, q1):
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    dot = np.clip(np.abs(np.einsum("ij,ij->i", q0.astype(np.float64), q1.astype(np.float64))), 0, 1)
    return np.degrees(2 * np.arccos(dot))


def check_alpha_and_rotation(out, ref, max_degrees):
    assert np.all(np.abs(sigmoid(out["opacities"]) - sigmoid(ref["opacities"])) <= ALPHA_ERROR)
    assert np.all(np.isfinite(out["opacities"]))
    assert angle_deg(out["rotations"], ref["rotations"]).max() <= max_degrees


def nearest_codebook_error(original, decoded):
    """Per value, |decoded - original| minus the distance from the original to the nearest value
    the decoded data takes (0 when every value went to its nearest codebook entry)."""
    book = np.unique(decoded)
    if book.size == 0:
        return np.zeros(1)
    x = original.reshape(-1, 1).astype(np.float64)
    nearest = np.abs(x - book[None, :]).min(axis=1)
    return np.abs(decoded.reshape(-1) - original.reshape(-1)) - nearest


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_splat_round_trip(tmp_path, degree):
    a = scene(500, degree, seed=degree)
    out = round_trip(tmp_path, a, "s.splat")
    assert out["features"].shape[1] == 3
    np.testing.assert_array_equal(out["means"], a["means"])
    np.testing.assert_allclose(out["log_scales"], a["log_scales"], atol=2e-6)
    colour = np.clip(0.5 + SH_C0 * a["features"][:, :3].astype(np.float64), 0, 1)
    assert np.abs(0.5 + SH_C0 * out["features"][:, :3] - colour).max() <= 0.5 / 255 + 1e-6
    check_alpha_and_rotation(out, a, 2.0)


def _chunk_span(values: np.ndarray) -> np.ndarray:
    """Per row, the range of its 256-row chunk (rows in file order), per column."""
    n = values.shape[0]
    chunks = -(-n // 256)
    padded = np.concatenate([values, np.repeat(values[-1:], chunks * 256 - n, axis=0)])
    blocks = padded.reshape(chunks, 256, -1)
    return np.repeat(blocks.max(axis=1) - blocks.min(axis=1), 256, axis=0)[:n]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compressed_ply_round_trip(tmp_path, degree):
    a = scene(700, degree, seed=10 + degree)
    out = round_trip(tmp_path, a, "s.compressed.ply")
    ref = {k: v[morton_order(a["means"])] for k, v in a.items()}  # the writer's row order
    steps = np.array([2047.0, 1023.0, 2047.0])  # 11-10-11 bits over each chunk's range
    for key in ("means", "log_scales"):
        bound = 0.5 * _chunk_span(ref[key].astype(np.float64)) / steps + 1e-5
        assert np.all(np.abs(out[key] - ref[key]) <= bound), key
    colour = 0.5 + SH_C0 * ref["features"][:, :3].astype(np.float64)
    bound = 0.5 * _chunk_span(colour) / 255 + 1e-5
    assert np.all(np.abs(0.5 + SH_C0 * out["features"][:, :3] - colour) <= bound)
    rest = ref["features"][:, 3:].astype(np.float64)
    assert out["features"].shape == ref["features"].shape
    assert np.all(np.abs(out["features"][:, 3:] - np.clip(rest, -4, 4)) <= 8 / 256 + 1e-6)
    check_alpha_and_rotation(out, ref, 0.25)


@pytest.mark.parametrize("version", [2, 3])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spz_round_trip(tmp_path, degree, version):
    a = scene(400, degree, seed=20 + degree)
    a["log_scales"] = np.clip(a["log_scales"], -10, 5.9)  # the range SPZ holds
    path = tmp_path / "s.spz"
    data, notes = spz_encode(SplatSet.from_numpy(**a).to_numpy(), version=version)
    path.write_bytes(data)
    assert notes == [] and detect_format(path) == "spz"
    out = load_splats(path).to_numpy()
    assert np.abs(out["means"] - a["means"]).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(out["log_scales"] - a["log_scales"]).max() <= 1 / 32 + 1e-6
    assert np.abs(out["features"][:, :3] - a["features"][:, :3]).max() <= 0.5 / (0.15 * 255) + 1e-6
    rest = np.clip(a["features"][:, 3:], -1, 127 / 128)
    assert out["features"].shape == a["features"].shape
    assert np.abs(out["features"][:, 3:] - rest).max(initial=0) <= 0.5 / 128 + 1e-6
    if version == 3:
        check_alpha_and_rotation(out, a, 0.25)
    else:  # v2 stores x y z in 8 bits and derives w: coarse where w is near 0
        check_alpha_and_rotation(out, a, 20.0)
        assert angle_deg(out["rotations"], a["rotations"]).mean() < 1.5


@pytest.mark.parametrize("name", ["s.sog", "folder/meta.json"])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sog_round_trip(tmp_path, degree, name):
    a = scene(600, degree, seed=30 + degree)
    out = round_trip(tmp_path, a, name)
    ref = {k: v[morton_order(a["means"])] for k, v in a.items()}
    logm = np.sign(ref["means"]) * np.log1p(np.abs(ref["means"].astype(np.float64)))
    step = 0.5 * np.ptp(logm, axis=0) / 65535
    assert np.all(np.abs(out["means"] - ref["means"]) <= (np.abs(ref["means"]) + 1) * np.expm1(step) + 1e-6)
    for key, cols in (("log_scales", slice(None)), ("features", slice(0, 3)), ("features", slice(3, None))):
        excess = nearest_codebook_error(ref[key][:, cols], out[key][:, cols])
        assert excess.max() <= 1e-6, key  # every value went to its nearest codebook entry
    assert out["features"].shape == ref["features"].shape
    assert len(np.unique(out["log_scales"])) <= 256
    check_alpha_and_rotation(out, ref, 1.2)


@pytest.mark.parametrize("name", ["s.splat", "s.compressed.ply", "s.spz", "s.sog"])
def test_shipped_sample_round_trip(tmp_path, name):
    a = sample()
    out = round_trip(tmp_path, a, name)
    assert out["means"].shape == a["means"].shape
    order = np.arange(len(a["means"])) if name.endswith((".splat", ".spz")) else morton_order(a["means"])
    ref = {k: v[order] for k, v in a.items()}
    extent = np.ptp(a["means"], axis=0).max()
    assert np.abs(out["means"] - ref["means"]).max() <= 1e-3 * extent
    check_alpha_and_rotation(out, ref, 2.0)
    assert np.sqrt(np.mean((out["features"][:, :3] - ref["features"][:, :3]) ** 2)) < 0.02


def test_lod_set_round_trip(tmp_path):
    fine, coarse = scene(300, 1, seed=40), scene(40, 1, seed=41)
    from nanogs_warp.io import save_levels

    path = tmp_path / "lod" / "lod-meta.json"
    path.parent.mkdir()
    save_levels([SplatSet.from_numpy(**fine), SplatSet.from_numpy(**coarse)], path)
    meta = json.loads(path.read_text())
    assert meta["counts"] == [300, 40] and meta["lodLevels"] == 2 and meta["count"] == 340
    assert meta["filenames"] == ["0_0/meta.json", "1_0/meta.json"]
    assert meta["tree"]["lods"] == {"0": {"file": 0, "offset": 0, "count": 300}, "1": {"file": 1, "offset": 0, "count": 40}}
    assert detect_format(path) == "lod" and detect_format(path.parent) == "lod"
    assert load_splats(path).count == 300  # the finest level
    assert load_splats(path.parent / "1_0" / "meta.json").count == 40


def test_the_levels_a_lod_meta_names():
    """``lod.level_metas``: each level's meta.json inside the set's folder, once, in order; names
    outside it (absolute, '..') left out; nothing from what is not a version-1 set."""
    from nanogs_warp.io import lod

    path = Path("set") / "lod-meta.json"
    names = ["1_0/meta.json", "0_0/meta.json", "1_0/meta.json", "/etc/x/meta.json", "../up/meta.json", "a/../../b", "", 7]
    data = json.dumps({"version": 1, "filenames": names, "tree": {}}).encode()
    assert lod.level_metas(path, data) == [Path("set/1_0/meta.json"), Path("set/0_0/meta.json")]
    for bad in (b"[1]", b"{", b"\xff", json.dumps({"version": 2, "filenames": names}).encode(),
                json.dumps({"filenames": "0_0/meta.json"}).encode()):
        assert lod.level_metas(path, bad) == []


def test_detection_is_by_content_and_names_pick_the_output(tmp_path):
    a = scene(50, 0, seed=50)
    for name, fmt in (("x.splat", "splat"), ("x.compressed.ply", "compressed-ply"), ("x.spz", "spz"),
                      ("x.sog", "sog"), ("x.ply", "ply")):  # fmt: skip
        save_splats(SplatSet.from_numpy(**a), tmp_path / name)
        assert detect_format(tmp_path / name) == fmt
        renamed = tmp_path / f"renamed_{fmt}.bin"
        (tmp_path / name).rename(renamed)
        if fmt == "splat":  # no signature: known by its extension alone
            with pytest.raises(InputError, match="known by their extension"):
                detect_format(renamed)
        else:
            assert detect_format(renamed) == fmt
        assert format_for_path(tmp_path / name) == fmt
    assert format_for_path(tmp_path / "x.ply", "spz") == "spz"
    save_splats(SplatSet.from_numpy(**a), tmp_path / "forced.ply", format="spz")
    assert detect_format(tmp_path / "forced.ply") == "spz"
    with pytest.raises(InputError, match="needs a name ending in .splat"):  # it could not be read back
        save_splats(SplatSet.from_numpy(**a), tmp_path / "forced.spz", format="splat")
    assert not (tmp_path / "forced.spz").exists()


def test_detection_reads_structure_not_substrings(tmp_path):
    """A file whose size is a multiple of 32 is no .splat file unless named so; a PLY comment that
    mentions a compressed PLY's element, and a SOG meta.json whose value says "lodLevels", keep
    their own formats."""
    (tmp_path / "weights.npy").write_bytes(bytes(32 * 1000))
    with pytest.raises(InputError, match="not a splat file"):
        detect_format(tmp_path / "weights.npy")
    a = scene(40, 1, seed=51)
    save_splats(SplatSet.from_numpy(**a), tmp_path / "x.ply")
    data = (tmp_path / "x.ply").read_bytes()
    at = data.index(b"\n") + 1
    at = data.index(b"\n", at) + 1  # after the format line
    (tmp_path / "c.ply").write_bytes(data[:at] + b"comment from: element chunk / packed_position layout\n" + data[at:])
    assert detect_format(tmp_path / "c.ply") == "ply"
    (tmp_path / "s").mkdir()
    save_splats(SplatSet.from_numpy(**a), tmp_path / "s" / "meta.json")
    meta = json.loads((tmp_path / "s" / "meta.json").read_text())
    meta["asset"] = {"generator": "lodLevels", "nested": {"lodLevels": 3}}
    (tmp_path / "s" / "meta.json").write_text(json.dumps(meta))
    assert detect_format(tmp_path / "s" / "meta.json") == "sog"
    assert load_splats(tmp_path / "s" / "meta.json").count == 40


def test_what_a_format_cannot_hold_is_said_once(tmp_path):
    a = scene(60, 3, seed=60)
    a["extras"] = np.random.default_rng(0).normal(size=(60, 1)).astype(np.float32)
    lines = []
    save_splats(SplatSet.from_numpy(**a), tmp_path / "x.splat", on_loss=lines.append)
    assert len(lines) == 1 and "SH degree 3 -> 0" in lines[0] and "extra_0" in lines[0]
    lines.clear()
    save_splats(SplatSet.from_numpy(**scene(60, 3, seed=61)), tmp_path / "x.spz", on_loss=lines.append)
    assert lines == []


def test_outputs_are_deterministic(tmp_path):
    a = scene(300, 2, seed=70)
    for name in ("x.splat", "x.compressed.ply", "x.spz", "x.sog"):
        first = (round_trip(tmp_path / "a", a, name), (tmp_path / "a" / name).read_bytes())
        second = (tmp_path / "b" / name)
        second.parent.mkdir(exist_ok=True)
        save_splats(SplatSet.from_numpy(**a), second)
        assert first[1] == second.read_bytes(), name


def test_sog_archive_holds_the_published_layout(tmp_path):
    a = scene(100, 3, seed=80)
    save_splats(SplatSet.from_numpy(**a), tmp_path / "x.sog")
    with zipfile.ZipFile(tmp_path / "x.sog") as z:
        names = set(z.namelist())
        meta = json.loads(z.read("meta.json"))
    assert names == {"meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp",
                     "shN_centroids.webp", "shN_labels.webp"}  # fmt: skip
    assert meta["version"] == 2 and meta["count"] == 100
    assert meta["shN"]["bands"] == 3 and meta["shN"]["count"] == 100
    assert len(meta["scales"]["codebook"]) <= 256 and len(meta["sh0"]["codebook"]) <= 256


def test_sog_with_an_unsupported_zip_version_is_one_clear_error(tmp_path):
    """A central-directory entry that declares a zip version Python's zipfile refuses (it raises
    NotImplementedError while opening the archive) is an input error, not a traceback."""
    path = tmp_path / "x.sog"
    save_splats(SplatSet.from_numpy(**scene(20, 0, seed=81)), path)
    data = bytearray(path.read_bytes())
    entry = data.index(b"PK\x01\x02")  # the first central-directory entry: "version needed" at +6
    data[entry + 6 : entry + 8] = (0xFFFF).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="not a readable .sog archive"):
        load_splats(path)


def test_sog_palette_for_large_scenes(tmp_path, monkeypatch):
    from nanogs_warp.io import sog

    monkeypatch.setattr(sog, "PALETTE_LIMIT", 64)  # a k-means palette without a 65k-splat scene
    a = scene(400, 1, seed=90)
    out = round_trip(tmp_path, a, "x.sog")
    ref = a["features"][morton_order(a["means"])]
    assert len(np.unique(out["features"][:, 3:], axis=0)) <= 64
    assert np.sqrt(np.mean((out["features"][:, 3:] - ref[:, 3:]) ** 2)) < np.sqrt(np.mean(ref[:, 3:] ** 2))


def test_compressed_ply_keeps_the_positions_of_a_scene_in_tiny_units(tmp_path):
    """Each chunk stores its positions relative to its bounds: a scene 2^-60 times smaller keeps them
    as the unscaled one does (chunks narrower than 1e-5 units used to collapse to their corner)."""
    a = scene(700, 0, seed=31)
    errors = []
    for exponent in (0, -60):
        b = in_units(a, exponent)
        out = round_trip(tmp_path, b, f"s{exponent}.compressed.ply")
        ref = b["means"][morton_order(b["means"])].astype(np.float64)
        errors.append(np.abs(out["means"] - ref).max() / np.ptp(ref, axis=0).max())
    assert errors[1] == pytest.approx(errors[0], rel=1e-3) and errors[0] < 1e-3


@pytest.mark.parametrize("name", ["s.spz", "s.compressed.ply"])
def test_quantised_formats_say_what_they_clamp_visibly(tmp_path, name):
    """SPZ holds log-scales in [-10, 5.94] and positions to 1/4096 units, compressed PLY log-scales
    in [-20, 20]: a scene in such units writes without a note, one 2^70 times larger or 2^-60 times
    smaller with one line naming what changed by more than a thousandth of its extent."""
    a = scene(300, 0, seed=32)
    a["log_scales"] = np.clip(a["log_scales"], -10, 5.9)
    for exponent, expected in ((0, None), (70, "sizes outside"), (-60, "sizes outside")):
        notes = []
        save_splats(SplatSet.from_numpy(**in_units(a, exponent)), tmp_path / name, on_loss=notes.append)
        if expected is None:
            assert notes == []
        else:
            assert len(notes) == 1 and expected in notes[0], notes
            assert int(re.search(r"([\d,]+) splats clamped", notes[0]).group(1).replace(",", "")) > 250
    if name == "s.spz":
        assert "positions finer than 1/4096 units: rounded" in notes[0]


def test_splat_sizes_beyond_float32_are_clamped_and_said(tmp_path):
    """.splat stores sizes, not their logs: log-scales above 88.7 (inside the input domain of +-100)
    were written as inf, and the tool refused its own output on the next load."""
    a = scene(50, 0, seed=33)
    a["log_scales"][:10] = 95.0
    notes = []
    save_splats(SplatSet.from_numpy(**a), tmp_path / "big.splat", on_loss=notes.append)
    assert len(notes) == 1 and "sizes outside 1.18e-38 to 3.4e+38 units: 10 splats clamped" in notes[0], notes
    back = load_splats(tmp_path / "big.splat").to_numpy()
    assert np.isfinite(back["log_scales"]).all() and back["log_scales"][:10].min() == pytest.approx(88.72, abs=0.01)
    assert load_splats(tmp_path / "big.splat").count == 50
    notes.clear()
    a["log_scales"][:10] = -100.0  # the domain's floor: below float32's normal sizes, stored (and read) as the smallest
    save_splats(SplatSet.from_numpy(**a), tmp_path / "small.splat", on_loss=notes.append)
    back = load_splats(tmp_path / "small.splat").to_numpy()["log_scales"]
    assert notes == [] and back.shape == (50, 3)  # 1e-38 units: no visible change, no note
    np.testing.assert_allclose(back[:10], np.log(np.finfo(np.float32).tiny), rtol=1e-6)
    assert (tmp_path / "small.splat").read_bytes()[12:16] == np.float32(np.finfo(np.float32).tiny).tobytes()  # the file holds what is read


def test_a_small_spz_that_declares_a_huge_scene_is_refused_at_once(tmp_path, monkeypatch):
    """A header may declare more splats than its gzip stream can hold (deflate expands at most 1032
    times): refused before inflating anything. One that it could hold but that this machine's
    available memory could not is refused before inflating too."""
    import gzip
    import struct

    from nanogs_warp.io import spz

    path = tmp_path / "bomb.spz"
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 2**32 - 1, 0, 12, 0, 0) + bytes(1 << 20)))
    with pytest.raises(InputError, match="more than [0-9]+ bytes of gzip data can hold"):
        load_splats(path)
    good = tmp_path / "good.spz"
    save_splats(SplatSet.from_numpy(**random_splat_arrays(200, sh_degree=1)), good)
    monkeypatch.setattr("nanogs_warp.device.available_host_memory", lambda: 1000)
    with pytest.raises(InputError, match="more than the 1,000 bytes of memory available"):
        load_splats(good)
    assert spz.most_inflated(1000) >= 1032 * 1000
