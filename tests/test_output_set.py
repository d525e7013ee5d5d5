"""OutputSet: a run's files appear together when published, or not at all."""

from pathlib import Path

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


def test_a_shared_folder_another_set_removed_is_made_again(tmp_path):
    """Two scenes of a batch write one folder: the one that made it failed and removed it, still
    empty, after the other had found it there; the other's healthy output then failed for a
    missing folder."""
    folder = tmp_path / "out" / "x"
    first, second = OutputSet(), OutputSet()
    first.make_folder(folder)
    second.make_folder(folder)  # found there
    first.discard()
    assert not folder.exists()
    _write(second, folder / "b.ply", b"b")
    assert [(path.name, identity is not None) for path, identity in second.publish()] == [("b.ply", True)]
    assert (folder / "b.ply").read_bytes() == b"b"
    with pytest.raises(InputError, match="does not exist"):  # a folder no set asked for is never made
        _write(OutputSet(), tmp_path / "elsewhere" / "c.ply", b"c")


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


def test_an_interrupt_while_publishing_waits_for_the_last_file(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM) arriving while the files are moved into place is acted on once the last
    one is: the set is whole, then the interrupt ends the command."""
    import os
    import signal

    from nanogs_warp.io import ply_write

    outputs = OutputSet()
    for name in ("a.ply", "b.ply", "c.ply"):
        _write(outputs, tmp_path / name, name.encode())
    replace = os.replace
    calls = []

    def interrupted_replace(source, target):
        calls.append(target)
        if len(calls) == 1:
            signal.raise_signal(signal.SIGINT)
        return replace(source, target)

    monkeypatch.setattr(ply_write.os, "replace", interrupted_replace)
    with pytest.raises(KeyboardInterrupt):
        outputs.publish()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "b.ply", "c.ply"] and len(calls) == 3
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_failure_while_publishing_keeps_what_replaced_older_files(tmp_path, monkeypatch):
    """A move that fails part way (an OSError) removes the new files that replaced nothing and the
    rest; a file that already replaced an older one stays (the older one is gone)."""
    import os

    from nanogs_warp.io import ply_write

    (tmp_path / "old.ply").write_bytes(b"older")
    outputs = OutputSet(overwrite=True)
    for name in ("old.ply", "new.ply", "last.ply"):
        _write(outputs, tmp_path / name, name.encode())
    replace = os.replace

    def failing_replace(source, target):
        if Path(target).name == "last.ply":
            raise OSError(28, "No space left on device")
        return replace(source, target)

    monkeypatch.setattr(ply_write.os, "replace", failing_replace)
    with pytest.raises(InputError, match="last.ply: cannot write the file: No space left on device"):
        outputs.publish()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.ply"] and (tmp_path / "old.ply").read_bytes() == b"old.ply"


def test_retired_files_go_once_the_set_is_in_place(tmp_path):
    """Files retired (an older output's that the new one makes stale) are removed after the staged
    ones are moved, each once however often named, with their folders where left empty; never a
    kept file (an input); and none when the set is discarded."""
    old = tmp_path / "old"
    old.mkdir()
    (old / "a.webp").write_bytes(b"a")
    (old / "b.webp").write_bytes(b"b")
    (tmp_path / "input.json").write_bytes(b"i")
    outputs = OutputSet(keep=[tmp_path / "input.json"])
    outputs.retire([old / "a.webp"] * 50_000 + [old / "b.webp", tmp_path / "input.json"])
    assert outputs._retired == [old / "a.webp", old / "b.webp"]
    _write(outputs, tmp_path / "new.ply", b"n")
    assert (old / "a.webp").exists()  # not before the new files are in place
    outputs.publish()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["input.json", "new.ply"]
    (old).mkdir()
    (old / "a.webp").write_bytes(b"a")
    outputs = OutputSet()
    outputs.retire([old / "a.webp"])
    _write(outputs, tmp_path / "other.ply", b"o")
    outputs.discard()
    assert (old / "a.webp").read_bytes() == b"a" and not (tmp_path / "other.ply").exists()


def test_a_signal_in_the_gaps_of_a_write_leaves_nothing(tmp_path, monkeypatch):
    """Three gaps a signal landed in (the eighth hostile round: 4 of 9 tries left a LOD set's 19
    temporary files): just after the temporary file was opened, just after a folder was made, and
    just before the staged files were taken to be moved."""
    import contextlib
    import os

    from nanogs_warp.io import ply_write

    real_open = os.open

    def open_then_interrupted(*args, **kwargs):
        real_open(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(ply_write.os, "open", open_then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomic_write(tmp_path / "a.ply", lambda stream: stream.write(b"a"))
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []

    outputs = OutputSet()
    real_mkdir = Path.mkdir

    def mkdir_then_interrupted(self, *args, **kwargs):
        real_mkdir(self, *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "mkdir", mkdir_then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        outputs.make_folder(tmp_path / "new" / "deeper")
    monkeypatch.undo()
    outputs.discard()
    assert list(tmp_path.iterdir()) == []

    outputs = OutputSet()
    for name in ("b.ply", "c.ply"):
        _write(outputs, tmp_path / name, name.encode())

    @contextlib.contextmanager
    def interrupted_on_entry():
        raise KeyboardInterrupt
        yield

    monkeypatch.setattr(ply_write, "signals_held", interrupted_on_entry)
    with pytest.raises(KeyboardInterrupt):
        outputs.publish()
    outputs.discard()  # as the command's own cleanup does
    assert list(tmp_path.iterdir()) == []


def test_a_held_signal_is_acted_on_where_the_block_ends():
    """Its handler runs as the block ends, so its exception comes from there (raised later, it could
    land in a __del__, which swallows it: the command then went on and exited 0)."""
    import signal

    from nanogs_warp.io.ply_write import signals_held

    def end(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, end)
    try:
        after = []
        with pytest.raises(SystemExit) as caught:
            with signals_held():
                signal.raise_signal(signal.SIGTERM)
                after.append("inside")
            after.append("after")
        assert caught.value.code == 128 + signal.SIGTERM and after == ["inside"]
        assert signal.getsignal(signal.SIGTERM) is end
    finally:
        signal.signal(signal.SIGTERM, previous)
