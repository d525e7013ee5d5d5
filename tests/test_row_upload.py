"""Rows copied to the device while a PLY file is read (``nanogs_warp.io.row_upload``): the same
splat set, bit for bit, as reading the file and then copying it, whatever the read changes after a
unit is done (infinite opacities saturated, suspect rows checked again or dropped). On the CPU
the copies are asked for explicitly (the command shares the host arrays there instead)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splats_ply

from nanogs_warp.io import read_any_splats
from nanogs_warp.io.ply import splats_from_host
from nanogs_warp.io.row_upload import RowUpload


def _bits(splats) -> dict[str, np.ndarray]:
    out = {}
    for name in ("means", "rotations", "log_scales", "opacities", "features", "extras", "integer_extras"):
        a = np.ascontiguousarray(getattr(splats, name).numpy())
        out[name] = a.view(np.uint8).reshape(a.shape[0], -1) if a.size else a
    return out


def _read_both(path, device, drop_invalid=False):
    upload = RowUpload(lambda: wp.get_device(device), cpu=True)
    arrays, layout = read_any_splats(path, drop_invalid=drop_invalid, upload=upload)
    got = upload.splats(arrays, layout)
    plain_arrays, plain_layout = read_any_splats(path, drop_invalid=drop_invalid)
    return got, splats_from_host(plain_arrays, plain_layout).to(device)


@pytest.mark.parametrize("case", ["plain", "infinite_opacity", "suspect_dropped", "not_unit_quaternions"])
def test_rows_copied_while_read_give_the_plain_read(tmp_path, device, case):
    path = tmp_path / "s.ply"
    n = 40_000 if case == "plain" else 3000  # 7 MB: read in several units, copied in several ranges
    arrays = random_splats_ply(path, n, sh_degree=2, seed=3, extra_props=(("label", "u1"), "foo"))
    if case != "plain":
        data = dict(arrays)
        if case == "infinite_opacity":
            data["opacities"] = data["opacities"].copy()
            data["opacities"][[5, 2900]] = [np.inf, -np.inf]
        elif case == "suspect_dropped":
            data["means"] = data["means"].copy()
            data["means"][1234, 1] = np.nan
        else:
            data["rotations"] = data["rotations"] * np.float32(3.0)
        from scene_factory import write_splats_ply

        write_splats_ply(path, data, extra_props=(("label", "u1"), "foo"))
    got, want = _read_both(path, device, drop_invalid=case == "suspect_dropped")
    assert got is not None and got.device == wp.get_device(device) and got.layout == want.layout
    assert got.count == want.count == (2999 if case == "suspect_dropped" else n)
    for name, bits in _bits(want).items():
        np.testing.assert_array_equal(_bits(got)[name], bits, err_msg=name)


def test_nothing_is_copied_to_the_cpu_or_for_other_formats(tmp_path):
    path = tmp_path / "s.ply"
    random_splats_ply(path, 500, seed=1)
    upload = RowUpload(lambda: wp.get_device("cpu"))  # the CPU shares the host arrays instead
    arrays, layout = read_any_splats(path, upload=upload)
    assert upload.splats(arrays, layout) is None
    ascii_path = tmp_path / "a.ply"
    random_splats_ply(ascii_path, 50, seed=1, text=True)
    upload = RowUpload(lambda: wp.get_device("cpu"), cpu=True)
    arrays, layout = read_any_splats(ascii_path, upload=upload)
    assert upload.splats(arrays, layout) is None  # never begun: not read by rows


def test_a_failed_read_or_device_stops_the_uploader(tmp_path):
    from nanogs_warp.errors import InputError

    path = tmp_path / "s.ply"
    random_splats_ply(path, 500, seed=1)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])  # truncated: refused before any row
    upload = RowUpload(lambda: wp.get_device("cpu"), cpu=True)
    with pytest.raises(InputError, match="truncated"):
        read_any_splats(path, upload=upload)
    upload.cancel()

    def no_device():
        raise InputError("--device cuda:9: no such GPU")

    path.write_bytes(data)
    upload = RowUpload(no_device, cpu=True)
    arrays, layout = read_any_splats(path, upload=upload)
    assert upload.splats(arrays, layout) is None


def test_adjacent_row_ranges_are_copied_as_one():
    from nanogs_warp.io.row_upload import _merged

    assert _merged([(0, 5), (5, 9), (12, 20), (20, 21), (30, 31)]) == [(0, 9), (12, 21), (30, 31)]
    assert _merged([]) == []


def test_a_copy_that_fails_falls_back_to_the_plain_upload(tmp_path, monkeypatch):
    """Out of device memory, say: the uploader stops, drains the reader's ranges and copies nothing."""
    from nanogs_warp.io import row_upload

    def no_memory(*args):
        raise RuntimeError("Failed to allocate")

    monkeypatch.setattr(row_upload, "_device_array", no_memory)
    path = tmp_path / "s.ply"
    random_splats_ply(path, 40_000, seed=1)
    upload = RowUpload(lambda: wp.get_device("cpu"), cpu=True)
    arrays, layout = read_any_splats(path, upload=upload)
    assert upload.splats(arrays, layout) is None


def test_the_upload_lets_go_of_the_host_arrays(tmp_path):
    """Once the splat set is made (or the upload gave up), the uploader keeps no host array: the
    caller's references are the last, so the command frees the read's memory for the results'
    copies back to the host."""
    import weakref

    path = tmp_path / "s.ply"
    random_splats_ply(path, 40_000, seed=2)

    def no_device():
        raise RuntimeError("no such GPU")

    for device in (lambda: wp.get_device("cpu"), no_device):
        upload = RowUpload(device, cpu=True)
        arrays, layout = read_any_splats(path, upload=upload)
        refs = [weakref.ref(a) for a in arrays.values()]
        splats = upload.splats(arrays, layout)
        assert (splats is None) == (device is no_device)
        del arrays
        assert all(ref() is None for ref in refs)
        if splats is not None:
            assert splats.count == 40_000 and splats.device == wp.get_device("cpu")

    upload = RowUpload(lambda: wp.get_device("cpu"), cpu=True)  # a read that failed after its start
    arrays, layout = read_any_splats(path, upload=upload)
    refs = [weakref.ref(a) for a in arrays.values()]
    upload.cancel()
    del arrays
    assert all(ref() is None for ref in refs)
