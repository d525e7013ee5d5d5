"""``batch --workers auto``: two workers on a GPU that holds two of the largest scene, one elsewhere."""

import os
from pathlib import Path

import numpy as np

from nanogs_warp.batch.gpu_workers import GPU_BYTES_PER_SPLAT, GPU_BYTES_PER_WORKER, MEMORY_SHARE, auto_workers, ply_splats, workers_for
from nanogs_warp.io.ply import save_ply
from nanogs_warp.splats import SplatSet


def _ply(path: Path, n: int, rng) -> Path:
    arrays = dict(
        means=rng.normal(size=(n, 3)), rotations=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), log_scales=np.full((n, 3), -3.0),
        opacities=np.zeros(n), features=rng.normal(size=(n, 3)),
    )  # fmt: skip
    save_ply(SplatSet.from_numpy(**arrays, device="cpu"), path)
    return path


def test_two_workers_where_two_scenes_fit():
    largest = 6_000_000
    fits = int(2 * (GPU_BYTES_PER_WORKER + GPU_BYTES_PER_SPLAT * largest) / MEMORY_SHARE) + 1
    assert workers_for("cuda:0", largest, fits) == 2
    assert workers_for("cuda:0", largest, fits - 2 * GPU_BYTES_PER_SPLAT) == 1
    assert workers_for("cpu", largest, 10**15) == 1
    assert workers_for("cuda:0", None, 10**15) == 1  # the largest scene unknown
    assert workers_for("cuda:0", largest, None) == 1  # the GPU's memory unknown


def test_the_largest_file_gives_the_count(tmp_path, rng):
    small, large = _ply(tmp_path / "a.ply", 10, rng), _ply(tmp_path / "b.ply", 300, rng)
    assert ply_splats(large) == 300
    inputs = [(small, small.stat().st_size), (large, large.stat().st_size)]
    assert auto_workers(["cpu"], inputs) == {"cpu": 1}
    other = tmp_path / "c.spz"
    other.write_bytes(b"\0" * 10)
    assert auto_workers(["cpu"], [*inputs, (other, 10)]) == {"cpu": 1}


def test_unreadable_headers_are_not_counted(tmp_path):
    for name, content in [("empty.ply", b""), ("text.ply", b"hello\n"), ("cut.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")]:
        path = tmp_path / name
        path.write_bytes(content)
        assert ply_splats(path) is None, name
    assert ply_splats(tmp_path / "missing.ply") is None
    if hasattr(os, "mkfifo"):  # a pipe named like a scene: not opened (the read would block)
        os.mkfifo(tmp_path / "pipe.ply")
        assert ply_splats(tmp_path / "pipe.ply") is None
    huge = tmp_path / "huge.ply"  # a count no GPU holds twice: one worker
    huge.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999999999999999\nproperty float x\nend_header\n")
    assert workers_for("cuda:0", ply_splats(huge), 141 * 2**30) == 1
