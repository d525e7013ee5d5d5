"""A batch scene's record names the kind of device it ran on."""

import os
import json

import warp as wp
from scene_factory import random_splats_ply

from nanogs_warp.batch.scenes import find_scenes
from nanogs_warp.batch.work import process_scene
from nanogs_warp.budgets import parse_budgets
from nanogs_warp.pipeline import SimplifyConfig


def test_record_names_the_device_kind(tmp_path, device):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 120, seed=5)
    (job,) = find_scenes(str(scenes), tmp_path / "out", parse_budgets("0.1", None), SimplifyConfig(), False)
    result = process_scene(job, wp.get_device(device))
    assert result.status == "done", result.error
    record = json.loads(job.record_path.read_text())
    assert record["device"] == str(wp.get_device(device))
    assert record["device_kind"] == wp.get_device(device).name  # "CPU" or the GPU's model
    assert record["device_kind"] and record["device_kind"] != record["device"]


def test_a_record_that_is_not_a_small_regular_file_is_no_record(tmp_path):
    """A FIFO, a device or a huge file in a record's place reads as no record (the scene is redone)
    at once: it blocked until the scene timed out, or read /dev/zero until memory ran out."""
    from nanogs_warp.batch.work import RECORD_LIMIT, read_record

    fifo = tmp_path / "g.nanogs.json"
    os.mkfifo(fifo)
    assert read_record(fifo) is None
    zero = tmp_path / "z.nanogs.json"
    zero.symlink_to("/dev/zero")
    assert read_record(zero) is None
    big = tmp_path / "b.nanogs.json"
    big.write_bytes(b"{" + b" " * RECORD_LIMIT + b"}")
    assert read_record(big) is None
    good = tmp_path / "ok.nanogs.json"
    good.write_text('{"format": 1}')
    assert read_record(good) == {"format": 1}
