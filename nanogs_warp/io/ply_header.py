"""Strict PLY header parsing and the structure and size checks of a 3DGS splat file.

The header is parsed here (strictly, mirroring plyfile's grammar) so that structure and sizes are
checked before plyfile allocates anything. Also holds the 3DGS property names shared by reading
(:mod:`nanogs_warp.io.ply`) and writing (:mod:`nanogs_warp.io.ply_write`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import plyfile

from ..errors import InputError

# Required vertex properties, grouped as SplatSet stores them; f_rest_* follow f_dc_* in `features`.
MEAN_NAMES = ("x", "y", "z")
DC_NAMES = ("f_dc_0", "f_dc_1", "f_dc_2")
OPACITY_NAMES = ("opacity",)
SCALE_NAMES = ("scale_0", "scale_1", "scale_2")
ROT_NAMES = ("rot_0", "rot_1", "rot_2", "rot_3")  # w, x, y, z
REQUIRED_NAMES = MEAN_NAMES + DC_NAMES + OPACITY_NAMES + SCALE_NAMES + ROT_NAMES
# 2D Gaussian splatting (2DGS) stores flat splats, surfels, with scale_0 and scale_1 only. Such a file
# is read with this log-scale on the third axis: e^-30 (about 1e-13) of a scene unit, flat in any
# unit a scene is stored in, inside the numeric domain (``nanogs_warp.domain``), and its square
# (about 1e-26) still a normal float32 in a covariance.
FLAT_LOG_SCALE = -30.0
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest_* count -> SH degree
NORMAL_NAMES = ("nx", "ny", "nz")

FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")

# Scalar type names plyfile accepts in a header (PLY names and numpy codes) -> numpy dtype.
_TYPES = {
    **dict.fromkeys(("int8", "char", "i1"), "i1"),
    **dict.fromkeys(("uint8", "uchar", "u1", "b1"), "u1"),
    **dict.fromkeys(("int16", "short", "i2"), "i2"),
    **dict.fromkeys(("uint16", "ushort", "u2"), "u2"),
    **dict.fromkeys(("int32", "int", "i4"), "i4"),
    **dict.fromkeys(("uint32", "uint", "u4"), "u4"),
    **dict.fromkeys(("float32", "float", "f4"), "f4"),
    **dict.fromkeys(("float64", "double", "f8"), "f8"),
}
MAX_HEADER_BYTES = 1 << 20
_INTEGER = re.compile(r"[+-]?[0-9]+")
_END_HEADER = re.compile(rb"(?:\r\n|\r|\n)end_header(?:\r\n|\r|\n)")
_NEWLINE = re.compile(r"\r\n|\r|\n")


@dataclass
class Prop:
    name: str
    dtype: np.dtype | None  # None for list properties
    is_list: bool = False
    len_dtype: np.dtype | None = None
    type_name: str = ""


@dataclass
class Element:
    name: str
    count: int
    props: list[Prop]


@dataclass
class Header:
    format: str
    elements: list[Element]
    length: int  # bytes up to and including the end_header line

    def element(self, name: str) -> Element | None:
        return next((e for e in self.elements if e.name == name), None)


def parse_header(head: bytes, name: str) -> Header:
    if not head.startswith(b"ply") or head[3:4] not in (b"\n", b"\r"):
        raise InputError(f"{name}: not a PLY file (it does not start with 'ply')")
    m = _END_HEADER.search(head)
    if m is None:
        if re.search(rb"(?:\r|\n)end_header", head):
            raise InputError(f"{name}: malformed PLY header ('end_header' must be alone on its line)")
        if len(head) < MAX_HEADER_BYTES:
            raise InputError(f"{name}: truncated PLY header (no 'end_header' line)")
        raise InputError(f"{name}: no 'end_header' line in the first {MAX_HEADER_BYTES >> 20} MiB")
    try:
        text = head[: m.start()].decode("ascii")
    except UnicodeDecodeError:
        raise InputError(f"{name}: malformed PLY header (non-ASCII bytes)") from None

    def fail(lineno: int, msg: str):
        raise InputError(f"{name}: malformed PLY header (line {lineno}: {msg})")

    fmt = None
    elements: list[Element] = []
    element_names: set[str] = set()
    prop_names: set[str] = set()  # the last element's property names so far
    lines = _NEWLINE.split(text)
    for lineno, raw in enumerate(lines[1:], start=2):
        line = raw.strip()
        if not line:
            continue
        if not line.replace("\t", " ").isprintable():  # a NUL or another control character: no tool reads it back
            fail(lineno, f"a control character in {line[:40]!r}")
        keyword, *fields = line.split()
        rest = line[len(keyword) :]
        if keyword in ("comment", "obj_info"):  # plyfile's reading keeps them
            continue
        if keyword == "format":
            if fmt is not None or elements:
                fail(lineno, "unexpected 'format' line")
            if len(fields) != 2 or fields[0] not in FORMATS or fields[1] != "1.0":
                fail(lineno, f"unsupported format {rest.strip()!r}")
            fmt = fields[0]
        elif fmt is None:
            fail(lineno, "expected a 'format' line first")
        elif keyword == "element":
            if len(fields) != 2:
                fail(lineno, "expected 'element NAME COUNT'")
            if not _INTEGER.fullmatch(fields[1]):  # digits only: Python's int() also takes 6_4, which C readers read as 6
                fail(lineno, f"element count {fields[1]!r} is not an integer")
            count = int(fields[1])
            if count < 0:
                fail(lineno, f"element {fields[0]!r} has a negative count")
            if fields[0] in element_names:
                fail(lineno, f"element {fields[0]!r} appears twice")
            element_names.add(fields[0])
            elements.append(Element(fields[0], count, []))
            prop_names = set()
        elif keyword == "property":
            if not elements:
                fail(lineno, "property before any element")
            if fields and fields[0] == "list":
                if len(fields) != 4 or fields[1] not in _TYPES or fields[2] not in _TYPES:
                    fail(lineno, "expected 'property list LENTYPE TYPE NAME'")
                prop = Prop(fields[3], None, True, np.dtype(_TYPES[fields[1]]), "list")
            else:
                if len(fields) != 2:
                    fail(lineno, "expected 'property TYPE NAME'")
                if fields[0] not in _TYPES:
                    fail(lineno, f"unknown property type {fields[0]!r}")
                prop = Prop(fields[1], np.dtype(_TYPES[fields[0]]), type_name=fields[0])
            if prop.name in prop_names:
                fail(lineno, f"property {prop.name!r} appears twice in element {elements[-1].name!r}")
            prop_names.add(prop.name)
            elements[-1].props.append(prop)
        else:
            fail(lineno, f"unexpected line {line[:40]!r}")
    if fmt is None:
        raise InputError(f"{name}: malformed PLY header (no 'format' line)")
    return Header(fmt, elements, m.end())


def has_surfels(names) -> bool:
    """Whether vertex properties ``names`` are a 2DGS file's: scale_0 and scale_1 without scale_2."""
    return "scale_0" in names and "scale_1" in names and "scale_2" not in names


def check_structure(header: Header, name: str) -> Element:
    vertex = header.element("vertex")
    if vertex is None:
        found = ", ".join(e.name for e in header.elements) or "none"
        raise InputError(f"{name}: no 'vertex' element (elements: {found})")
    if vertex.count == 0:
        raise InputError(f"{name}: the 'vertex' element has 0 rows")
    lists = [p.name for p in vertex.props if p.is_list]
    if lists:
        raise InputError(f"{name}: vertex list properties are not supported ({', '.join(lists)})")
    props = {p.name: p for p in vertex.props}
    missing = [n for n in REQUIRED_NAMES if n not in props and not (n == "scale_2" and has_surfels(props))]
    if missing:
        raise InputError(f"{name}: not a 3DGS splat file: missing vertex properties {', '.join(missing)}")
    rest = [p.name for p in vertex.props if p.name.startswith("f_rest_")]
    if len(rest) not in REST_COUNTS:
        raise InputError(
            f"{name}: {len(rest)} f_rest_* properties; 3DGS files have 0, 9, 24 or 45 (SH degree 0..3)"
        )
    expected = {f"f_rest_{i}" for i in range(len(rest))}
    if set(rest) != expected:
        odd = sorted(set(rest) - expected, key=natural)
        gone = sorted(expected - set(rest), key=natural)
        raise InputError(
            f"{name}: f_rest_* properties are not numbered f_rest_0..f_rest_{len(rest) - 1} "
            f"(missing {', '.join(gone)}; unexpected {', '.join(odd)})"
        )
    not_float = [f"{n} ({props[n].type_name})" for n in REQUIRED_NAMES + tuple(sorted(expected, key=natural))
                 if n in props and props[n].dtype.kind != "f"]
    if not_float:
        raise InputError(f"{name}: 3DGS properties must be float or double: {', '.join(not_float)}")
    return vertex


def check_sizes(header: Header, file_bytes: int, name: str) -> None:
    """Rejects element counts that cannot fit in the file, before anything is allocated."""
    body = file_bytes - header.length
    needed = 0
    for e in header.elements:
        if not e.props and e.count:  # rows of no bytes: a reader would loop over them without reading
            raise InputError(f"{name}: element {e.name!r} has {e.count} rows but no properties")
        if header.format == "ascii":
            # every value takes a character and a separator; every row at least a line break
            row = max(2 * len(e.props), 1)
        else:
            row = max(sum((p.len_dtype if p.is_list else p.dtype).itemsize for p in e.props), 1)
        needed += e.count * row
        exact = header.format != "ascii" and not any(p.is_list for p in e.props)
        if needed > body + (0 if exact else 1):
            raise InputError(
                f"{name}: truncated file: element {e.name!r} ({e.count} rows) needs {'' if exact else 'at least '}"
                f"{needed} bytes after the header, but only {max(body, 0)} follow"
            )


def trailing_bytes(header: Header, file_bytes: int) -> int:
    """Bytes of a binary file after the data its header declares (0 for ASCII files and files with
    list properties, whose data length is not known from the header alone)."""
    if header.format == "ascii" or any(p.is_list for e in header.elements for p in e.props):
        return 0
    declared = sum(e.count * sum(p.dtype.itemsize for p in e.props) for e in header.elements)
    return max(0, file_bytes - header.length - declared)


def check_agreement(header: Header, ply: plyfile.PlyData, name: str) -> None:
    ours = [(e.name, e.count, [p.name for p in e.props]) for e in header.elements]
    theirs = [(e.name, e.count, [p.name for p in e.properties]) for e in ply.elements]
    if ours != theirs:
        raise InputError(f"{name}: malformed PLY header (it parses ambiguously)")


# ----------------------------------------------------------------------------------------------
# Helpers shared with `ply` and `ply_write`


def one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text or type(e).__name__


def natural(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]
