"""Input files that a seventh round of hostile use found read wrongly: a compressed PLY whose header
holds more than 64 KiB of comments or ends its lines in CR alone (taken for a plain PLY that lacks
every 3DGS property), numbers written as Python writes them (6_4, 1_0) that C readers read
otherwise, an unbundled SOG whose image is a link to itself (an internal error from simplify), an
encrypted SOG archive named by a Python object's repr, and a folder without a name of its own (".")
named as nothing."""

from __future__ import annotations

import subprocess
import sys
import zipfile

import pytest
from scene_factory import random_splat_arrays, random_splats_ply

from nanogs_warp import InputError, SplatSet
from nanogs_warp.io import detect_format, read_splat_arrays, save_splats


def cli(*args):
    return subprocess.run([sys.executable, "-m", "nanogs_warp", *map(str, args)], capture_output=True, text=True, timeout=300)


def _compressed(tmp_path) -> bytes:
    path = tmp_path / "a.compressed.ply"
    save_splats(SplatSet.from_numpy(**random_splat_arrays(300, 1, seed=5)), path)
    return path.read_bytes()


@pytest.mark.parametrize("edit", ["long comments", "CR line ends"])
def test_a_compressed_ply_is_known_by_its_whole_header(tmp_path, edit):
    data = _compressed(tmp_path)
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header, body = data[:end], data[end:]
    if edit == "long comments":  # 70 KiB of comments after the format line: the elements lie past 64 KiB
        first = header.index(b"\n", header.index(b"format")) + 1
        header = header[:first] + (b"comment " + b"x" * 70 + b"\n") * 1000 + header[first:]
    else:
        header = header.replace(b"\n", b"\r")
    path = tmp_path / "edited.compressed.ply"
    path.write_bytes(header + body)
    assert detect_format(path) == "compressed-ply"
    assert read_splat_arrays(path).count == 300


def test_an_element_count_with_an_underscore_is_refused(tmp_path):
    path = tmp_path / "a.ply"
    random_splats_ply(path, 64, seed=1)
    data = path.read_bytes().replace(b"element vertex 64\n", b"element vertex 6_4\n", 1)
    path.write_bytes(data)
    with pytest.raises(InputError, match=r"element count '6_4' is not an integer"):
        read_splat_arrays(path)


@pytest.mark.parametrize("before", [False, True])
def test_an_element_of_rows_without_properties_is_named_so(tmp_path, before):
    """An element that declares rows but no properties was refused as a truncated file, its rows
    counted as a byte each."""
    path = tmp_path / "a.ply"
    random_splats_ply(path, 64, seed=1)
    data = path.read_bytes()
    at = data.index(b"element vertex") if before else data.index(b"end_header")
    path.write_bytes(data[:at] + b"element empty 5\n" + data[at:])
    with pytest.raises(InputError, match=r"element 'empty' has 5 rows but no properties"):
        read_splat_arrays(path)


def test_an_ascii_number_with_an_underscore_is_refused(tmp_path):
    path = tmp_path / "a.ply"
    random_splats_ply(path, 64, seed=1, text=True)
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    body = data[end:]
    digit = next(i for i, c in enumerate(body) if chr(c).isdigit() and chr(body[i + 1]).isdigit())
    path.write_bytes(data[:end] + body[: digit + 1] + b"_" + body[digit + 1 :])
    with pytest.raises(InputError, match="a number with an underscore in the ASCII data"):
        read_splat_arrays(path)
    path.write_bytes(data)
    assert read_splat_arrays(path).count == 64  # the file as written reads


def test_a_sog_image_that_links_to_itself_is_one_line(tmp_path):
    folder = tmp_path / "sog"
    folder.mkdir()
    save_splats(SplatSet.from_numpy(**random_splat_arrays(200, 0, seed=6)), folder / "meta.json")
    (folder / "quats.webp").unlink()
    (folder / "quats.webp").symlink_to("quats.webp")
    result = cli("simplify", folder / "meta.json", "-o", tmp_path / "o.ply", "--ratio", "0.5", "--device", "cpu")
    assert result.returncode == 2 and result.stderr == "nanogs-warp: error: quats.webp: cannot read the file: Too many levels of symbolic links\n"


def test_an_encrypted_sog_member_is_named_without_a_repr(tmp_path):
    path = tmp_path / "a.sog"
    save_splats(SplatSet.from_numpy(**random_splat_arrays(200, 0, seed=7)), path)
    data = bytearray(path.read_bytes())
    for signature in (b"PK\x03\x04", b"PK\x01\x02"):  # the general-purpose flag's bit 0: encrypted
        flag = 6 if signature == b"PK\x03\x04" else 8
        i = data.find(signature)
        while i >= 0:
            data[i + flag] |= 1
            i = data.find(signature, i + 4)
    path.write_bytes(bytes(data))
    assert zipfile.is_zipfile(path)
    with pytest.raises(InputError) as raised:
        read_splat_arrays(path)
    assert "ZipInfo" not in str(raised.value) and "is encrypted" in str(raised.value)


def test_a_folder_without_a_name_of_its_own_is_named(tmp_path):
    """``info ''`` reads the current folder (Path('') is '.'): the message began ": is a directory"."""
    result = subprocess.run([sys.executable, "-m", "nanogs_warp", "info", ""], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 2 and result.stderr == "nanogs-warp: error: .: is a directory without meta.json or lod-meta.json\n"


def test_a_json_files_own_keys_tell_its_kind():
    """``top_level_keys`` (how a renamed meta.json or lod-meta.json is recognised) scans in one pass:
    each key's colon was found on a copy of the rest of the head, quadratic in a head of many keys."""
    from nanogs_warp.io.common import top_level_keys

    head = b'{"means" \r\n: {"quats": 1}, "name": "lodLevels", "lodLevels"\t:[{"x": "y"}], "cut'
    assert top_level_keys(head) == {"means", "name", "lodLevels"}
    assert top_level_keys(b'["means", {"quats": 1}]') == set()
