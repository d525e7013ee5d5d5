"""OutputSet: a run's files appear together when published, or not at all."""

import pytest

from nanogs_warp.errors import InputError
from nanogs_warp.io.ply_write import OutputSet, atomic_write


def _write(outputs, path, data: bytes):
    atomic_write(path, lambda stream: stream.write(data), outputs.overwrite, outputs)


def test_files_appear_only_when_published(tmp_path):
    outputs = OutputSet()
    outputs.make_folder(tmp_path / "a" / "b")
    _write(outputs, tmp_path / "a" / "b" / "one.ply", b"1")
    _write(outputs, tmp_path / "two.ply", b"2")
    assert not (tmp_path / "two.ply").exists() and not (tmp_path / "a" / "b" / "one.ply").exists()
    outputs.publish()
    assert (tmp_path / "a" / "b" / "one.ply").read_bytes() == b"1" and (tmp_path / "two.ply").read_bytes() == b"2"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b", "one.ply", "two.ply"]  # no temporary file


def test_discard_removes_the_files_and_the_folders_it_made(tmp_path):
    (tmp_path / "kept").mkdir()
    outputs = OutputSet()
    outputs.make_folder(tmp_path / "kept" / "new" / "deeper")
    _write(outputs, tmp_path / "kept" / "new" / "deeper" / "x.ply", b"x")
    _write(outputs, tmp_path / "y.ply", b"y")
    outputs.discard()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["kept"]


def test_a_file_that_appeared_meanwhile_stops_the_set(tmp_path):
    """Without overwrite, a file put at one of the paths before publishing is an InputError: it stays,
    and none of the set's files appear (those moved before it are taken back)."""
    outputs = OutputSet(overwrite=False)
    _write(outputs, tmp_path / "first.ply", b"1")
    _write(outputs, tmp_path / "second.ply", b"2")
    (tmp_path / "second.ply").write_bytes(b"another run's")
    with pytest.raises(InputError, match="already exists"):
        outputs.publish()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["second.ply"]
    assert (tmp_path / "second.ply").read_bytes() == b"another run's"


def test_an_existing_file_is_replaced_with_overwrite(tmp_path):
    (tmp_path / "out.ply").write_bytes(b"old")
    outputs = OutputSet(overwrite=True)
    _write(outputs, tmp_path / "out.ply", b"new")
    assert (tmp_path / "out.ply").read_bytes() == b"old"
    outputs.publish()
    assert (tmp_path / "out.ply").read_bytes() == b"new"
