"""PLY reading and writing on several threads: the same arrays, errors, hashes and bytes whatever the
thread count and the size of the units the file is cut into; the batch's piece hash; outputs of
``batch --readers N`` byte-identical to a plain ``simplify``."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import plyfile
import pytest
from scene_factory import random_splat_arrays, random_splats_ply, write_splats_ply
from typer.testing import CliRunner

from nanogs_warp.io import ply, ply_read, ply_write
from nanogs_warp.cli.app import app
from nanogs_warp.errors import InputError
from nanogs_warp.io.ply import load_ply, normalize_quaternions, read_ply_arrays, save_ply
from nanogs_warp.io.ply_read import PieceHash, file_piece_hash

KEYS = ("means", "rotations", "log_scales", "opacities", "features", "extras")
PIECE = 1000  # bytes per hashed piece in these tests (1 MiB in use): many pieces in a small file
runner = CliRunner()


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def assert_bitwise_equal(got: dict, want: dict):
    for key in KEYS:
        assert got[key].shape == want[key].shape, key
        np.testing.assert_array_equal(bits(got[key]), bits(want[key]), err_msg=key)


def piece_hash(data: bytes, piece: int) -> str:
    """The batch's hash written out: SHA-256 over the SHA-256 of each piece."""
    digests = [hashlib.sha256(data[i : i + piece]).digest() for i in range(0, len(data), piece)]
    return hashlib.sha256(b"".join(digests)).hexdigest()


@pytest.fixture(params=["large", "small"])
def units(request, monkeypatch):
    """Whole 1 MB units (one per file here), or units of a few rows and pieces of 1000 bytes, so
    that rows straddle units and pieces and every thread gets several units."""
    monkeypatch.setattr(ply_read, "PIECE_BYTES", PIECE)
    if request.param == "small":
        monkeypatch.setattr(ply, "_CHUNK_BYTES", 7 * 68)
        monkeypatch.setattr(ply, "_READ_UNIT_BYTES", 7 * 68)
        monkeypatch.setattr(ply_read, "_UNIT_BYTES", 3 * PIECE)
    return request.param


def make_layout(path, layout: str, n: int = 300) -> dict:
    """A scene file in one of the layouts the reader handles; returns what a load gives back."""
    if layout == "ascii":
        return random_splats_ply(path, n, sh_degree=1, seed=5, text=True)
    if layout == "big_endian":
        return random_splats_ply(path, n, sh_degree=2, seed=6, byte_order=">")
    if layout == "double":
        return random_splats_ply(path, n, sh_degree=1, seed=7, dtype="f8", extra_props=(("id", "u2"),))
    if layout == "shuffled_extras":
        return random_splats_ply(path, n, sh_degree=3, seed=8, shuffle=True, extra_props=("a", ("b", "i1"), "c"))
    want = random_splats_ply(path, n, sh_degree=1, seed=9)
    if layout in ("element_before", "element_after", "list_before"):
        data = plyfile.PlyData.read(str(path), mmap=False)
        if layout == "list_before":
            other = np.empty(3, [("vertex_indices", "O")])
            other["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([5], "i4"), np.array([], "i4")]
        else:
            other = np.array([(1, 2.5), (3, -1.0)], [("id", "u2"), ("f", "f8")])
        element = plyfile.PlyElement.describe(other, "other")
        data.elements = [element, *data.elements] if layout != "element_after" else [*data.elements, element]
        data.write(str(path))
    return want


LAYOUTS = ["binary", "big_endian", "double", "shuffled_extras", "element_before", "element_after", "list_before", "ascii"]


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_same_arrays_and_hash_on_any_thread_count(tmp_path, units, layout, threads):
    src = tmp_path / "in.ply"
    want = make_layout(src, layout)
    data = src.read_bytes()
    hasher = PieceHash(len(data))
    assert_bitwise_equal(load_ply(src, file_hash=hasher, threads=threads).to_numpy(), want)
    assert hasher.hexdigest() == piece_hash(data, PIECE)
    digest = hashlib.sha256()
    assert_bitwise_equal(load_ply(src, digest=digest, threads=threads).to_numpy(), want)
    assert digest.hexdigest() == hashlib.sha256(data).hexdigest()
    raw = read_ply_arrays(src, threads=threads).arrays  # info's reading: w first, as stored
    np.testing.assert_array_equal(bits(raw["rotations"]), bits(want["rotations"]))


def test_unit_size_evens_out_the_threads_within_its_bounds():
    mib = 1 << 20
    assert ply_read.unit_size(984_000_000, 8, 8 * mib) == 7_687_500  # 16 units a thread
    assert ply_read.unit_size(82_000_000, 2, 8 * mib) == 2_562_500
    assert ply_read.unit_size(4_000_000, 8, 8 * mib) == mib  # at least one piece
    assert ply_read.unit_size(10_000_000_000, 1, 8 * mib) == 8 * mib  # at most the bound
    assert ply_read.unit_size(10_000, 1, 476) == 476  # a bound below 1 MiB (tests) is the size


@pytest.mark.parametrize("units_per_thread", [16, 1])  # 1: units of several pieces
@pytest.mark.parametrize("size", [0, 1, PIECE - 1, PIECE, 3 * PIECE, 7 * PIECE + 5])
def test_file_piece_hash(tmp_path, monkeypatch, size, units_per_thread):
    monkeypatch.setattr(ply_read, "PIECE_BYTES", PIECE)
    monkeypatch.setattr(ply_read, "_UNIT_BYTES", 2 * PIECE)
    monkeypatch.setattr(ply_read, "_UNITS_PER_THREAD", units_per_thread)
    path = tmp_path / "f.bin"
    path.write_bytes(np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes())
    for threads in (1, 3):
        assert file_piece_hash(path, threads) == piece_hash(path.read_bytes(), PIECE)


def test_piece_hash_of_real_size_pieces(tmp_path):
    path = tmp_path / "f.bin"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, (5 << 20) + 3, dtype=np.uint8).tobytes())
    assert file_piece_hash(path, 2) == piece_hash(path.read_bytes(), 1 << 20)


def test_a_file_that_changed_size_is_refused(tmp_path):
    src = tmp_path / "in.ply"
    random_splats_ply(src, 50)
    with pytest.raises(InputError, match="in.ply: malformed PLY file: the file changed while it was read"):
        load_ply(src, file_hash=PieceHash(src.stat().st_size + 1))


def invalid_scene(path, n: int = 400) -> dict:
    """Invalid rows in the first, middle and last units, and +-Inf opacities (valid) elsewhere."""
    arrays = random_splat_arrays(n, sh_degree=1, seed=11)
    arrays["means"][0, 1] = np.nan
    arrays["features"][n // 2, 7] = np.inf
    arrays["rotations"][n // 2 + 1] = 0.0
    arrays["log_scales"][n - 1, 2] = 250.0
    arrays["opacities"][[3, n - 5]] = [np.inf, -np.inf]
    write_splats_ply(path, arrays)
    return arrays


@pytest.mark.parametrize("threads", [1, 3])
def test_invalid_rows_anywhere_are_found(tmp_path, units, threads):
    path = tmp_path / "bad.ply"
    arrays = invalid_scene(path)
    with pytest.raises(InputError) as info:
        load_ply(path, threads=threads)
    assert str(info.value) == (
        "bad.ply: 4 of 400 splats are invalid (2 with NaN/Inf values in y, f_rest_4; 1 with zero-norm quaternions; "
        "1 with log-scales outside [-100, 100] in scale_2); load with drop_invalid (CLI: --drop-invalid) to drop them")
    dropped = []
    got = load_ply(path, drop_invalid=True, on_drop=dropped.append, threads=threads).to_numpy()
    assert dropped == ["bad.ply: dropped 4 of 400 splats (2 with NaN/Inf values in y, f_rest_4; 1 with zero-norm "
                       "quaternions; 1 with log-scales outside [-100, 100] in scale_2)"]  # fmt: skip
    keep = np.setdiff1d(np.arange(400), [0, 200, 201, 399])
    np.testing.assert_array_equal(got["means"], arrays["means"][keep])
    big = np.finfo(np.float32).max
    assert got["opacities"][2] == big and got["opacities"][395 - 3] == -big  # saturated (rows 0, 200, 201 dropped before them)


@pytest.mark.parametrize("threads", [1, 3])
def test_infinite_opacities_alone_are_saturated(tmp_path, units, threads):
    path = tmp_path / "inf.ply"
    arrays = random_splat_arrays(300, seed=12)
    arrays["opacities"][[0, 150, 299]] = [np.inf, -np.inf, np.inf]
    write_splats_ply(path, arrays)
    got = load_ply(path, threads=threads).to_numpy()["opacities"]
    big = np.finfo(np.float32).max
    np.testing.assert_array_equal(got[[0, 150, 299]], [big, -big, big])
    rest = np.setdiff1d(np.arange(300), [0, 150, 299])
    np.testing.assert_array_equal(got[rest], arrays["opacities"][rest])


@pytest.mark.parametrize("threads", [1, 3])
def test_quaternions_are_normalised_as_before(tmp_path, units, threads):
    """Block by block, in Warp's order, bit for bit as normalize_quaternions normalises them."""
    path = tmp_path / "q.ply"
    arrays = random_splat_arrays(500, seed=13)
    rng = np.random.default_rng(13)
    scale = np.exp(rng.uniform(-30, 30, (500, 1))).astype(np.float32)
    arrays["rotations"] = (arrays["rotations"] * scale).astype(np.float32)
    arrays["rotations"][::7] = random_splat_arrays(500, seed=14)["rotations"][::7]  # unit: kept as they are
    write_splats_ply(path, arrays)
    splats = load_ply(path, threads=threads)
    want = normalize_quaternions(arrays["rotations"])
    np.testing.assert_array_equal(bits(splats.to_numpy()["rotations"]), bits(want))
    np.testing.assert_array_equal(bits(splats.rotations.numpy()), bits(want[:, [1, 2, 3, 0]]))


@pytest.mark.parametrize("off", [2.0, 1.0 + 1.5e-6, 1.0 + 0.9e-6, 1.0 - 1.2e-6])
def test_nearly_unit_quaternions_among_unit_ones(tmp_path, units, off):
    """Blocks of unit quaternions are left as they are without the float64 pass; one row past the
    1e-6 tolerance far into a block is still normalised, bit for bit as normalize_quaternions does."""
    path = tmp_path / "q.ply"
    arrays = random_splat_arrays(500, seed=15)
    arrays["rotations"][300] *= np.float32(off)
    write_splats_ply(path, arrays)
    want = normalize_quaternions(arrays["rotations"])
    got = load_ply(path, threads=2).to_numpy()["rotations"]
    np.testing.assert_array_equal(bits(got), bits(want))
    changed = np.flatnonzero((bits(want) != bits(arrays["rotations"])).any(axis=1))
    assert set(changed) <= {300}


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_writes_on_any_thread_count_give_the_same_bytes(tmp_path, monkeypatch, threads):
    monkeypatch.setattr(ply, "_CHUNK_BYTES", 7 * 68)  # many chunks
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    random_splats_ply(src, 300, seed=3)
    ply_read.set_read_threads(threads)
    try:
        save_ply(load_ply(src), out)
    finally:
        ply_read.set_read_threads(None)
    assert out.read_bytes() == src.read_bytes()


def test_a_failed_chunk_leaves_no_file(tmp_path, monkeypatch):
    monkeypatch.setattr(ply, "_CHUNK_BYTES", 7 * 68)
    src, out = tmp_path / "in.ply", tmp_path / "out.ply"
    random_splats_ply(src, 300, seed=3)
    splats = load_ply(src)
    pack = ply_write._pack_rows

    def failing(plan, rows, start):
        if start >= 100:
            raise OSError(28, "No space left on device")
        pack(plan, rows, start)

    monkeypatch.setattr(ply_write, "_pack_rows", failing)
    with pytest.raises(InputError, match="out.ply: cannot write the file: No space left on device"):
        save_ply(splats, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.ply"]


def test_batch_readers_give_the_bytes_of_a_plain_simplify(tmp_path):
    scenes = tmp_path / "in"
    scenes.mkdir()
    for i, n in enumerate((3000, 1100)):
        random_splats_ply(scenes / f"s{i}.ply", n, sh_degree=i, seed=20 + i)
    result = runner.invoke(app, ["batch", str(scenes), "-o", str(tmp_path / "batch"), "--ratio", "0.1,0.01",
                                 "--devices", "cpu", "--readers", "3", "--json"])  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["settings"]["readers"] == 3
    for i in range(2):
        name = f"s{i}.ply"
        single = runner.invoke(app, ["simplify", str(scenes / name), "-o", str(tmp_path / "single") + "/",
                                     "--ratio", "0.1,0.01", "--device", "cpu", "-q"])  # fmt: skip
        assert single.exit_code == 0, single.output
        for ratio in ("0.1", "0.01"):
            output = f"s{i}_{ratio}.ply"
            assert (tmp_path / "batch" / output).read_bytes() == (tmp_path / "single" / output).read_bytes(), output
        record = json.loads((tmp_path / "batch" / f"s{i}.nanogs.json").read_text())
        assert record["format"] == 2
        assert record["input"]["sha256_pieces"] == piece_hash((scenes / name).read_bytes(), 1 << 20)


def test_batch_readers_must_be_positive(tmp_path):
    random_splats_ply(tmp_path / "a.ply", 50)
    result = runner.invoke(app, ["batch", str(tmp_path), "-o", str(tmp_path / "out"), "--count", "5", "--readers", "0"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines()[-1] == "nanogs-warp: error: --readers must be at least 1, got 0"


def test_a_record_of_the_previous_format_is_redone(tmp_path):
    """Records that kept the plain SHA-256 (format 1) do not match: the scene is simplified again."""
    scenes = tmp_path / "in"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 300, seed=2)
    args = ["batch", str(scenes), "-o", str(tmp_path / "out"), "--count", "30", "--devices", "cpu", "--json"]
    assert json.loads(runner.invoke(app, args).stdout)["done"] == 1
    record_path = tmp_path / "out" / "a.nanogs.json"
    record = json.loads(record_path.read_text())
    assert json.loads(runner.invoke(app, args).stdout)["skipped"] == 1
    record["format"] = 1
    record["input"]["sha256"] = hashlib.sha256((scenes / "a.ply").read_bytes()).hexdigest()
    del record["input"]["sha256_pieces"]
    record_path.write_text(json.dumps(record))
    assert json.loads(runner.invoke(app, args).stdout)["done"] == 1


def test_checking_a_configuration_imports_no_warp():
    """simplify checks its options before Warp starts (on another thread, while the input is read)."""
    code = ("import sys; from nanogs_warp.cli import options as o; o.method_config('paper', k=8).validate(); "
            "print('warp' in sys.modules)")  # fmt: skip
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_configuration_names_match_the_kernel_registries():
    from nanogs_warp.config import COST_NAMES, FIELD_COST_OPERATORS, MAX_K, OPERATOR_NAMES
    from nanogs_warp.cost import COSTS, FieldCost
    from nanogs_warp.operators import OPERATORS
    from nanogs_warp.topology import KnnTopology

    assert COST_NAMES == tuple(COSTS) and OPERATOR_NAMES == tuple(OPERATORS)
    assert FIELD_COST_OPERATORS == tuple(FieldCost.OPERATOR_IDS) and MAX_K == KnnTopology.MAX_K


@pytest.mark.parametrize("preset", ["default", "fast", "paper"])
def test_simplify_loads_only_the_kernels_it_launches(tmp_path, preset):
    """Warp's start-up (on its own thread) loads exactly the kernel modules the run then launches:
    none is loaded later, in the middle of the passes."""
    import os

    from nanogs_warp.config import SimplifyConfig
    from nanogs_warp.kernel_cache import simplify_modules

    command = [sys.executable, "-m", "nanogs_warp", "simplify", "--sample", "-o", str(tmp_path / "s.ply"),
               "--ratio", "0.1,0.01", "--device", "cpu", "--preset", preset]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "NANOGS_DEBUG": "1"})
    assert result.returncode == 0, result.stderr
    loaded = [line.split()[1].rsplit(".", 1)[1] for line in (result.stdout + result.stderr).splitlines()
              if line.startswith("Module nanogs_warp.")]  # Warp prints them on stdout
    assert sorted(loaded) == sorted(simplify_modules(SimplifyConfig.preset(preset)))


def test_simplify_says_where_its_time_went(tmp_path):
    result = runner.invoke(app, ["simplify", "--sample", "-o", str(tmp_path / "s.ply"), "--ratio", "0.1,0.01", "--device", "cpu",
                                 "--json"])  # fmt: skip
    assert result.exit_code == 0, result.output
    seconds = json.loads(result.stdout)["seconds"]
    stages = seconds["stages"]
    assert {"read", "warp_wait", "warp_import", "warp_init", "kernels", "upload", "simplify", "download", "write",
            "write_wait"} <= set(stages)  # fmt: skip
    assert all(v >= 0 for v in stages.values())
    assert stages["read"] + stages["warp_wait"] <= seconds["read"] + 1e-3 <= seconds["total"] + 2e-3


def test_the_command_ends_without_teardown_but_with_its_output_and_exit_code(tmp_path):
    """main() ends the process at once when the command is done: stdout (a pipe here) still holds
    the whole output, and the exit code is the command's."""
    base = [sys.executable, "-m", "nanogs_warp"]
    done = subprocess.run([*base, "simplify", "--sample", "-o", str(tmp_path / "s.ply"), "--count", "500", "--device", "cpu",
                           "--json"], capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert [o["count"] for o in json.loads(done.stdout)["outputs"]] == [500]
    assert load_ply(tmp_path / "s.ply").count == 500
    again = subprocess.run([*base, "simplify", "--sample", "-o", str(tmp_path / "s.ply"), "--count", "5"], capture_output=True, text=True)
    assert again.returncode == 2 and again.stdout == ""
    assert again.stderr.strip().endswith("already exists; pass --overwrite (-w) to replace it")
    helped = subprocess.run([*base, "--help"], capture_output=True, text=True)
    assert helped.returncode == 0 and "simplify" in helped.stdout
