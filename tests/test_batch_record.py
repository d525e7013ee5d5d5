"""A batch scene's record names the kind of device it ran on."""

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
