"""Outputs and inputs that a fifth round of hostile use found wrong: a symbolic link as the output,
an output that is one of the files a scene is read from, a record that cannot be written, small
files that declare huge scenes, numbers too large for a float, and budgets below 1e-60."""

from __future__ import annotations

import errno
import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import plyfile
import pytest
import warp as wp
from scene_factory import random_splat_arrays, random_splats_ply, write_splats_ply
from typer.testing import CliRunner

from nanogs_warp import InputError, SplatSet
from nanogs_warp.batch import work
from nanogs_warp.batch.scenes import find_scenes
from nanogs_warp.budgets import parse_budgets
from nanogs_warp.cli.app import app
from nanogs_warp.io import load_splats, save_levels, save_splats
from nanogs_warp.io.ply_write import OutputSet, atomic_write
from nanogs_warp.temporaries import process_space, remove_stale_temporaries, temporary_path
from nanogs_warp.pipeline import SimplifyConfig, simplify


def cli(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "nanogs_warp", *args], capture_output=True, text=True, timeout=300, **kwargs)


def test_an_output_that_is_a_link_is_written_through(tmp_path):
    """A link at the output's path keeps pointing where it did, and the file it names gets the
    output; before, the link itself was replaced (``-o /dev/stdout -w`` replaced /dev/stdout)."""
    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 200, seed=1)
    target = tmp_path / "real.ply"
    target.write_bytes(b"old")
    (tmp_path / "link.ply").symlink_to("real.ply")
    stdout_link = tmp_path / "stdout.ply"
    stdout_link.symlink_to("/proc/self/fd/1")
    common = ["--ratio", "0.5", "--device", "cpu", "--preset", "fast", "-w", "-q"]
    assert cli("simplify", str(scene), "-o", str(tmp_path / "link.ply"), *common).returncode == 0
    assert (tmp_path / "link.ply").is_symlink() and load_splats(target).count == 100
    if os.path.exists("/proc/self/fd/1"):
        with open(tmp_path / "captured", "wb") as captured:
            done = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(stdout_link), *common],
                                  stdout=captured, stderr=subprocess.PIPE, text=True, timeout=300)  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert stdout_link.is_symlink() and os.readlink(stdout_link) == "/proc/self/fd/1"
        assert load_splats(tmp_path / "captured").count == 100
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "to_fifo.ply").symlink_to(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        atomic_write(tmp_path / "to_fifo.ply", lambda stream: stream.write(b"x"))
    assert (tmp_path / "to_fifo.ply").is_symlink() and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def _job(tmp_path, scene):
    (job,) = find_scenes(str(scene), tmp_path / "out", parse_budgets("0.5", None), SimplifyConfig.preset("fast"), False)
    return job


def test_a_batch_output_that_is_one_of_its_scenes_files_is_refused(tmp_path):
    """An unbundled SOG whose image is named as the scene's output would be: the output would replace
    the input's own image (simplify refused it; batch wrote over it)."""
    arrays = random_splat_arrays(300, 1, seed=2)
    folder = tmp_path / "scenes" / "sog"
    folder.mkdir(parents=True)
    save_splats(SplatSet.from_numpy(**arrays), folder / "meta.json")
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "quats.webp").rename(folder / "meta_0.5.ply")
    meta["quats"]["files"] = ["meta_0.5.ply"]
    (folder / "meta.json").write_text(json.dumps(meta))
    before = (folder / "meta_0.5.ply").read_bytes()
    (tmp_path / "m.json").write_text(json.dumps([str(folder / "meta.json")]))
    (job,) = find_scenes(str(tmp_path / "m.json"), folder, parse_budgets("0.5", None), SimplifyConfig.preset("fast"), False)
    assert job.output_path(job.budgets[0]) == folder / "meta_0.5.ply"
    result = work.process_scene(job, wp.get_device("cpu"))
    assert result.status == "failed" and "is one of the files the run reads" in result.error
    assert (folder / "meta_0.5.ply").read_bytes() == before and not job.record_path.exists()


def test_a_record_that_cannot_be_written_leaves_no_outputs(tmp_path, monkeypatch):
    """A full disk at the record: the scene fails in one line naming it, and its outputs go too
    (outputs without a record were left, though the docs promise none)."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 200, seed=3)
    job = _job(tmp_path, scenes)

    def full(path, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(work, "write_json_atomic", full)
    result = work.process_scene(job, wp.get_device("cpu"))
    assert result.status == "failed"
    assert result.error == f"cannot write its record {job.record_path.name}: No space left on device"
    assert not [p for p in job.out_dir.iterdir()]
    (tmp_path / "blocked").write_text("a file where the output folder would go")
    (job,) = find_scenes(str(scenes), tmp_path / "blocked", parse_budgets("0.5", None), SimplifyConfig.preset("fast"), False)
    monkeypatch.undo()
    result = work.process_scene(job, wp.get_device("cpu"))
    assert result.status == "failed" and result.error.endswith("cannot create the directory: File exists"), result.error


def test_a_record_that_cannot_be_written_takes_back_the_file_written_through_a_link(tmp_path, monkeypatch):
    """An output path that is a symbolic link is written through. A full disk at the record then
    removed the user's link (the identity taken was the link's) and left the file written
    through it."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 200, seed=3)
    job = _job(tmp_path, scenes)
    job.out_dir.mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    for budget in job.budgets:
        job.output_path(budget).symlink_to(tmp_path / "elsewhere" / f"{budget.label}.ply")

    def full(path, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(work, "write_json_atomic", full)
    result = work.process_scene(job, wp.get_device("cpu"))
    assert result.status == "failed" and "No space left on device" in result.error
    assert all(job.output_path(budget).is_symlink() for budget in job.budgets)
    assert list((tmp_path / "elsewhere").iterdir()) == []


def test_another_nodes_outputs_are_never_taken_back(tmp_path, monkeypatch):
    """Two nodes writing one shared folder: a node whose record (or whose second output) cannot be
    written took back its outputs by name, deleting the files the other node had put there since,
    though the other's record listed them. Only a file that is still this run's is removed."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 200, seed=3)
    job = _job(tmp_path, scenes)

    def other_node_then_full(path, data):  # the other node publishes its outputs, then this node's record fails
        for budget in job.budgets:
            theirs = job.out_dir / f".theirs_{budget.label}"
            theirs.write_bytes(b"the other node's output")
            os.replace(theirs, job.output_path(budget))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(work, "write_json_atomic", other_node_then_full)
    result = work.process_scene(job, wp.get_device("cpu"))
    assert result.status == "failed" and "cannot write its record" in result.error
    assert all(job.output_path(b).read_bytes() == b"the other node's output" for b in job.budgets)

    files = OutputSet()  # an output set whose second file cannot be moved: the first goes only if still its own
    first, second = tmp_path / "first.ply", tmp_path / "second.ply"
    for path in (first, second):
        tmp = temporary_path(path)
        tmp.write_bytes(b"ours")
        files.stage(tmp, path)
    real_replace = os.replace

    def replace(source, target):
        if Path(target) == second:  # meanwhile another writer's file took the first one's place
            (tmp_path / ".x").write_bytes(b"theirs")
            real_replace(tmp_path / ".x", first)
            raise OSError(errno.ENOENT, os.strerror(errno.ENOENT))
        real_replace(source, target)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(InputError, match="second.ply: cannot write the file"):
        files.publish()
    monkeypatch.undo()
    assert first.read_bytes() == b"theirs" and not second.exists() and sorted(p.name for p in tmp_path.glob(".*.tmp")) == []


def test_a_temporary_of_another_machine_or_container_is_left_alone(tmp_path):
    """A writer's temporary names its process id and its process space (this machine and PID
    namespace, this boot): another space's file whose process id is not alive here was removed as a
    killed writer's, though its writer, on another node of a shared folder, was still writing it."""
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    pid = int(gone.stdout)
    out = tmp_path / "o.ply"
    mine = temporary_path(out)
    assert mine.name.startswith(f".o.ply.{os.getpid()}-{process_space()}") and mine.name.endswith(".tmp")
    other_machine = "%04x" % ((int(process_space()[:4], 16) + 1) % (1 << 16)) + process_space()[4:]
    killed_here = tmp_path / f".o.ply.{pid}-{process_space()}abcd.tmp"
    elsewhere = tmp_path / f".o.ply.{pid}-{other_machine}abcd.tmp"
    for path in (killed_here, elsewhere):
        path.write_bytes(b"partial")
    assert remove_stale_temporaries([out]) == [killed_here]
    assert not killed_here.exists() and elsewhere.exists()


@pytest.mark.skipif(not os.path.exists("/proc/sys/kernel/random/boot_id"), reason="Linux tells a machine's boot")
def test_a_temporary_of_an_earlier_boot_of_this_machine_is_removed(tmp_path):
    """A writer lost with its machine (a power cut, a crashed node) left its temporary under the
    boot it ran in, whose process ids say nothing now: it stayed for ever. One this machine's
    earlier boot last wrote before this boot began is removed, whatever its process id; one of
    another boot written since (a namesake machine writing a shared folder now) stays."""
    out = tmp_path / "o.ply"
    space = process_space()
    earlier_boot = space[:4] + "%04x" % ((int(space[4:], 16) + 1) % (1 << 16))
    before = tmp_path / f".o.ply.{os.getpid()}-{earlier_boot}abcd.tmp"  # a live process id: not what decides
    since = tmp_path / f".o.ply.{os.getpid()}-{earlier_boot}ef01.tmp"
    for path in (before, since):
        path.write_bytes(b"partial")
    os.utime(before, (0, 0))  # 1970: before any boot
    assert remove_stale_temporaries([out]) == [before]
    assert since.exists()


def _webp(pixels: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(pixels, "RGBA").save(out, format="WEBP", lossless=True, exact=True)
    return out.getvalue()


def test_a_sog_whose_images_hold_more_pixels_than_their_stored_bytes_can_is_refused(tmp_path):
    """A 2 KB .sog of deflated, zero-padded constant images declared millions of splats: the pixel
    bound counted the images' inflated bytes. It counts the bytes they take in the archive now."""
    side = 4096
    padding = b"\0" * 70_000  # deflates to almost nothing; counted inflated, it allowed 72M pixels
    meta = {"version": 2, "count": side * side, "means": {"mins": [0, 0, 0], "maxs": [1, 1, 1], "files": ["l.webp", "u.webp"]},
            "scales": {"codebook": [-3.0], "files": ["s.webp"]}, "quats": {"files": ["q.webp"]},
            "sh0": {"codebook": [0.5], "files": ["c.webp"]}}  # fmt: skip
    path = tmp_path / "bomb.sog"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("meta.json", json.dumps(meta))
        for name, colour in (("l.webp", (1, 2, 3, 255)), ("u.webp", (1, 2, 3, 255)), ("q.webp", (128, 128, 128, 252)),
                             ("s.webp", (0, 0, 0, 255)), ("c.webp", (0, 0, 0, 200))):  # fmt: skip
            z.writestr(name, _webp(np.full((side, side, 4), colour, np.uint8)) + padding)
    assert path.stat().st_size < 10_000
    with pytest.raises(InputError, match="far more than its .* bytes can hold"):
        load_splats(path)


def test_small_files_that_declare_more_than_memory_holds_are_refused(tmp_path, monkeypatch):
    """Decoding costs about 24 bytes a value: an SPZ, a .splat or a SOG that declares more splats
    than the available memory could decode is one line before any work (an SPZ gzip bomb passed the
    check on its inflated bytes and took 12 GB); so is a file larger than memory, and an unbundled
    SOG's image is read only as far as its scene's pixels need (a sparse 4 GB image was read whole)."""
    from nanogs_warp import device

    arrays = random_splat_arrays(2000, 3, seed=4)
    for name in ("s.spz", "s.splat", "s.sog"):
        save_splats(SplatSet.from_numpy(**arrays), tmp_path / name)
    folder = tmp_path / "u"
    folder.mkdir()
    save_splats(SplatSet.from_numpy(**arrays), folder / "meta.json")
    with open(folder / "quats.webp", "r+b") as image:
        image.truncate(4 << 30)  # sparse: no room taken on the disk
    with pytest.raises(InputError, match="quats.webp: 4294967296 bytes is more than"):
        load_splats(folder / "meta.json")
    monkeypatch.setattr(device, "available_host_memory", lambda: 1 << 18)
    for name in ("s.spz", "s.splat", "s.sog"):
        with pytest.raises(InputError, match=f"{name}: (decoding its 2,000 splats needs about|.* more than the 262,144 bytes of memory)"):
            load_splats(tmp_path / name)
    monkeypatch.setattr(device, "available_host_memory", lambda: 1 << 30)
    assert load_splats(tmp_path / "s.spz").count == 2000


def test_numbers_too_large_for_a_float_are_refused_by_name(tmp_path):
    """An integer of 400 digits in a SOG's meta.json, a count or a cost weight: math.isfinite
    raised OverflowError (an internal error)."""
    folder = tmp_path / "u"
    folder.mkdir()
    save_splats(SplatSet.from_numpy(**random_splat_arrays(100, 0, seed=5)), folder / "meta.json")
    meta = json.loads((folder / "meta.json").read_text())
    meta["scales"]["codebook"][0] = 10**400
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="scales.codebook must be 1 to 256 numbers"):
        load_splats(folder / "meta.json")
    splats = SplatSet.from_numpy(**random_splat_arrays(50, 0, seed=6))
    with pytest.raises(InputError, match="target counts must be between 1 and the input's 50 splats"):
        simplify(splats, count=10**400)
    with pytest.raises(InputError, match="--lambda-geo must be a finite number"):
        SimplifyConfig(lambda_geo=10**400).validate()


def test_budgets_below_1e_60_keep_their_own_labels():
    """Every ratio below 1e-60 targets one splat, but is named as typed (it was named 1e-61, and two
    such ratios were "the same budget")."""
    assert [b.label for b in parse_budgets("1e-300,2e-300,0.5", None)] == ["1e-300", "2e-300", "0.5"]
    assert [b.target(10**6) for b in parse_budgets("1e-300", None)] == [1]


def test_subnormal_splat_scales_read_as_zero_ones(tmp_path):
    """A .splat scale of 0 reads as the smallest normal float32 (a splat too small for exp); a
    subnormal one, smaller still, reads the same instead of being refused as beyond -100."""
    arrays = random_splat_arrays(10, 0, seed=7)
    save_splats(SplatSet.from_numpy(**arrays), tmp_path / "s.splat")
    data = bytearray((tmp_path / "s.splat").read_bytes())
    rows = np.frombuffer(data, np.float32).reshape(10, 8)
    rows[0, 3], rows[1, 4] = 0.0, 1e-45
    (tmp_path / "s.splat").write_bytes(bytes(data))
    scales = load_splats(tmp_path / "s.splat").to_numpy()["log_scales"]
    assert scales[0, 0] == scales[1, 1] == np.float32(np.log(np.finfo(np.float32).tiny))


def test_an_unbundled_sog_written_again_leaves_none_of_the_older_ones_images(tmp_path):
    """Writing an SH-0 SOG over an SH-3 one in its folder: the older SH palette's images went stale
    beside the new meta.json. They go now, as a level-of-detail set's stale levels do."""
    folder = tmp_path / "u"
    folder.mkdir()
    save_splats(SplatSet.from_numpy(**random_splat_arrays(200, 3, seed=8)), folder / "meta.json")
    assert {"shN_centroids.webp", "shN_labels.webp"} <= set(os.listdir(folder))
    (folder / "notes.webp").write_bytes(b"not the SOG's")
    save_splats(SplatSet.from_numpy(**random_splat_arrays(200, 0, seed=8)), folder / "meta.json")
    assert sorted(os.listdir(folder)) == ["means_l.webp", "means_u.webp", "meta.json", "notes.webp", "quats.webp", "scales.webp", "sh0.webp"]
    assert load_splats(folder / "meta.json").count == 200


def test_eval_images_never_replace_an_input(tmp_path):
    """A test scene at the path of one of eval's images (``--images d`` with the scene at
    d/<its label>/view_000.png) was replaced by the PNG."""
    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 100, seed=9)
    inside = tmp_path / "d" / "view_000.png"
    inside.mkdir(parents=True)
    (inside / "view_000.png").write_bytes(scene.read_bytes())
    done = cli("eval", str(scene), str(inside / "view_000.png"), "--images", str(tmp_path / "d"), "--device", "cpu",
               "--views", "2", "--size", "32", "-q")  # fmt: skip
    assert done.returncode == 2 and "is one of the files the run reads" in done.stderr, done.stderr
    assert (inside / "view_000.png").read_bytes() == scene.read_bytes()


def test_a_missing_level_of_a_lod_set_is_named(tmp_path):
    """"meta.json: no such file" did not say which level of the set was missing."""
    arrays = random_splat_arrays(100, 0, seed=10)
    folder = tmp_path / "lod"
    folder.mkdir()
    save_levels([SplatSet.from_numpy(**arrays), simplify(SplatSet.from_numpy(**arrays), count=20)], folder / "lod-meta.json")
    (folder / "0_0" / "meta.json").unlink()
    with pytest.raises(InputError, match=r"^lod-meta.json: its finest level 0_0/meta.json: meta.json: no such file$"):
        load_splats(folder / "lod-meta.json")


def _faces(rows: list[list[int]]) -> plyfile.PlyElement:
    data = np.empty(len(rows), [("vertex_indices", "O")])
    data["vertex_indices"] = [np.array(r, np.int32) for r in rows]
    return plyfile.PlyElement.describe(data, "face")


def test_rows_dropped_on_load_take_the_elements_that_index_them(tmp_path):
    """--drop-invalid at ratio 1: no merge renumbered the rows, but the load did, and a face element
    kept its indices (to the wrong splats, one past the end). It goes now, in one note."""
    arrays = random_splat_arrays(5, 0, seed=11)
    arrays["means"][1, 0] = np.nan
    write_splats_ply(tmp_path / "f.ply", arrays, other_elements=[_faces([[2, 3, 4]])])
    lines = []
    splats = load_splats(tmp_path / "f.ply", drop_invalid=True, on_drop=lines.append)
    assert splats.count == 4 and splats.layout.other_elements == []
    assert lines[-1] == "f.ply: dropped PLY element(s) 'face' (1 rows): they index vertices, which dropping rows renumbers"
    with pytest.raises(InputError, match="1 of 5 splats are invalid"):
        load_splats(tmp_path / "f.ply")


def test_mapped_rows_of_a_file_that_shrank_are_one_line(tmp_path):
    """plyfile maps elements of fixed-size rows; reading a mapped page beyond the end of a file
    that shrank kills the process (SIGBUS). Such rows are read from the file instead: a short
    read is one line. A list element before the vertices no longer sends them through the map."""
    from nanogs_warp.io.ply import _detached

    arrays = random_splat_arrays(300, 1, seed=13)
    values = np.empty(1000, [("v", "f4")])
    values["v"] = np.arange(1000)
    extra = plyfile.PlyElement.describe(values, "extra")
    write_splats_ply(tmp_path / "e.ply", arrays, other_elements=[extra])
    ply = plyfile.PlyData.read(str(tmp_path / "e.ply"), mmap="r")
    mapped = ply["extra"].data
    assert isinstance(mapped, np.memmap)
    with open(tmp_path / "e.ply", "rb") as f:
        assert np.array_equal(_detached(mapped, f, "e.ply")["v"], values["v"])
    os.truncate(tmp_path / "e.ply", mapped.offset + 100)
    with open(tmp_path / "e.ply", "rb") as f, pytest.raises(InputError, match="the file changed while it was read"):
        _detached(mapped, f, "e.ply")
    meta = np.empty(1, [("idx", "O")])
    meta["idx"] = [np.array([5, 6], np.int32)]
    first = tmp_path / "listfirst.ply"
    write_splats_ply(tmp_path / "plain.ply", arrays)
    plain = plyfile.PlyData.read(str(tmp_path / "plain.ply"))
    plyfile.PlyData([plyfile.PlyElement.describe(meta, "meta"), plain["vertex"]], text=False).write(str(first))
    a, b = load_splats(first).to_numpy(), load_splats(tmp_path / "plain.ply").to_numpy()
    assert all(np.array_equal(a[k], b[k]) for k in ("means", "rotations", "log_scales", "opacities", "features"))


def test_batch_says_what_the_merge_dropped_in_the_scene_notes(tmp_path):
    """The warning that vertex-indexing elements went was printed raw (a Python warning with its
    source line) and even with -q; it is the scene's note now."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    write_splats_ply(scenes / "f.ply", random_splat_arrays(100, 0, seed=14), other_elements=[_faces([[0, 1, 2]])])
    done = cli("batch", str(scenes), "-o", str(tmp_path / "out"), "--ratio", "0.5", "--preset", "fast", "--devices", "cpu", "-q", "--json")
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    (scene,) = json.loads(done.stdout)["scenes"]
    assert scene["notes"] == ["dropped PLY element(s) 'face' (1 rows): they index vertices, which simplification renumbers"]


@pytest.mark.parametrize("args, message", [
    (["warmup", "--device", "cpu", "--arch", "73"], "--arch 73: this Warp's NVRTC compiles for "),
    (["warmup", "--device", "cpu", "--arch", "none", "--cache-dir", "~nosuchuser/x"], "kernel cache ~nosuchuser/x: its '~' names no home"),
])  # fmt: skip
def test_kernel_cache_arguments_warp_would_fail_on_are_one_line(args, message, tmp_path):
    done = cli(*args, cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.startswith(f"nanogs-warp: error: {message}"), done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_a_scene_stopped_while_written_leaves_no_folder(tmp_path, monkeypatch):
    """Ctrl-C while a batch scene's outputs are written: they go, and so does the output folder the
    scene made (an interrupted batch left its empty output root)."""
    import nanogs_warp.io as io

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 200, seed=15)
    job = _job(tmp_path, scenes)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(io, "save_splats", interrupted)
    with pytest.raises(KeyboardInterrupt):
        work.process_scene(job, wp.get_device("cpu"))
    assert not (tmp_path / "out").exists()


def test_eval_views_the_host_cannot_hold_are_refused_first(tmp_path, monkeypatch):
    """An 8192 x 8192 eval of a 1-splat scene took 17.5 GB and 107 s; views whose comparison needs
    more than the available memory are one line now, before any rendering."""
    from nanogs_warp import device
    from nanogs_warp.eval.cameras import load_cameras_json

    scene = tmp_path / "s.ply"
    random_splats_ply(scene, 50, seed=16)
    monkeypatch.setattr(device, "available_host_memory", lambda: 1 << 30)
    result = CliRunner().invoke(app, ["eval", str(scene), str(scene), "--device", "cpu", "--size", "4096", "--views", "1"])
    assert result.exit_code == 2, result.output
    assert "1 view(s) of up to 16,777,216 pixels for 2 scenes need about 4,999,610,368 bytes of memory, more than the 1,073,741,824 available" in result.stderr
    huge = tmp_path / "cams.json"
    huge.write_text(json.dumps([{"img_name": "v", "width": 10**400, "height": 64, "position": [0, 0, -5],
                                 "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "fx": 60, "fy": 60}]))  # fmt: skip
    with pytest.raises(InputError, match="camera 0 declares .* x 64 pixels, beyond 2,147,483,648 a side"):
        load_cameras_json(huge, size=256)


def test_api_levels_and_targets_are_checked(tmp_path):
    """save_levels([]) wrote a LOD set no reader took (with Infinity in its JSON); levels out of order
    were written as a set whose "finest" level was the smallest; simplify_progressively read '21'
    as the targets 2 and 1, and 100.9 as 100."""
    from nanogs_warp import simplify_progressively

    splats = SplatSet.from_numpy(**random_splat_arrays(60, 0, seed=17))
    small = simplify(splats, count=10)
    with pytest.raises(InputError, match="no levels to write"):
        save_levels([], tmp_path / "lod-meta.json")
    with pytest.raises(InputError, match=r"levels go finest first \(counts that never grow\), got counts \[10, 60\]"):
        save_levels([small, splats], tmp_path / "lod-meta.json")
    with pytest.raises(TypeError, match="each level must be a SplatSet, got str"):
        save_levels(["a.ply"], tmp_path / "a.ply")
    assert not (tmp_path / "lod-meta.json").exists()
    for targets, message in (("21", "targets must be whole numbers"), ([100.9], "count must be a whole number"),
                             ([True], "count must be a whole number")):  # fmt: skip
        with pytest.raises(InputError, match=message):
            list(simplify_progressively(splats, targets))


def test_image_names_fit_a_file_name_in_bytes():
    """Names were cut to 100 characters: 100 CJK letters are 300 bytes, past a file name's 255, and
    eval --images failed after rendering with 'File name too long'."""
    from nanogs_warp.cli.eval import image_folders
    from nanogs_warp.eval.evaluate import _safe_name

    assert len(_safe_name("中" * 100).encode()) <= 100 and _safe_name("中" * 100).startswith("中")
    folders = image_folders(["文" * 40 + "/" + "名" * 70, "字" * 40 + "/" + "名" * 70])
    assert all(len(f.encode()) <= 100 for f in folders) and len(set(folders)) == 2
    # a 2,000,000-letter camera name was cut one letter a time, the rest measured each time: minutes
    assert _safe_name("a" * 2_000_000) == "a" * 100
    from nanogs_warp.eval.evaluate import fit_bytes

    assert fit_bytes("名" * 1_000_000, 10) == "名" * 3 and fit_bytes("ab名" * 500_000, 5, keep_end=True) == "ab名"
