"""A corpus of damaged and odd 3DGS .ply files, made from two seed scenes, for tools/fuzz_run.py.

    python tools/fuzz_corpus.py SAMPLE.ply -o corpus/ [--seed 0] [--splats N]

Seeds: the given scene (the shipped sample, nanogs_warp/data/plant_crop.ply, in the suite) and a
generated scene with SH degree 3 (clustered splats, seeded). Per seed, the families:

  header    vertex counts (one written with an underscore), property types, formats, missing /
            repeated / list properties, unknown elements, CRLF and CR line ends, very long headers,
            missing magic or end_header
  truncate  cuts inside the header, right after it, and across the body
  corrupt   1-40 random body bytes overwritten
  extreme   one row or a tenth of the rows of one property set to a denormal, 1e-38, 1e20,
            -1e38, +-FLT_MAX, +-Inf or NaN
  geometry  1-3 splats, every splat at one position, collinear, coplanar, identical rows, one far
            outlier, clusters of copies, coordinates over sixty decades or from random float bits

The same arguments give the same files, byte for byte. Besides the cases the folder gets
``corpus.jsonl``: one line per case (file, family, what was done). Nothing of it is meant to be
committed; make it where it is needed.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile
from adversarial_scenes import bit_centres, ray_centres  # this folder's

FLT_MAX = float(np.finfo(np.float32).max)
EXTREMES = {
    "denormal": 1e-40,
    "tiny": 1e-38,
    "1e20": 1e20,
    "-1e38": -1e38,
    "max": FLT_MAX,
    "-max": -FLT_MAX,
    "inf": np.inf,
    "-inf": -np.inf,
    "nan": np.nan,
}


@dataclass
class Case:
    family: str
    what: str
    data: bytes


def generated_sh3_scene(n: int, seed: int) -> np.ndarray:
    """An INRIA-layout vertex array with SH degree 3: splats in Gaussian clusters of varied spread."""
    rng = np.random.default_rng(seed)
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(45)]
             + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])  # fmt: skip
    v = np.zeros(n, [(name, "<f4") for name in names])
    centres = rng.uniform(-1.0, 1.0, (8, 3))
    spread = 10.0 ** rng.uniform(-3.0, -1.0, 8)
    which = rng.integers(0, 8, n)
    xyz = centres[which] + rng.normal(size=(n, 3)) * spread[which, None]
    for a, name in enumerate("xyz"):
        v[name] = xyz[:, a]
    for i in range(3):
        v[f"f_dc_{i}"] = rng.normal(scale=0.8, size=n)
        v[f"scale_{i}"] = np.log(spread[which] / 4) + rng.normal(scale=0.3, size=n)
    for i in range(45):
        v[f"f_rest_{i}"] = rng.normal(scale=0.1, size=n)
    v["opacity"] = rng.normal(scale=2.0, size=n)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    for i in range(4):
        v[f"rot_{i}"] = q[:, i]
    return v


def ply_bytes(vertices: np.ndarray, text: bool = False, comments=()) -> bytes:
    ply = plyfile.PlyData([plyfile.PlyElement.describe(vertices, "vertex")], text=text, comments=list(comments))
    from io import BytesIO

    buffer = BytesIO()
    ply.write(buffer)
    return buffer.getvalue()


def split(data: bytes) -> tuple[list[bytes], bytes]:
    """Header lines (without line ends, end_header included) and the body."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].split(b"\n")[:-1], data[end:]


def join(lines: list[bytes], body: bytes, newline: bytes = b"\n") -> bytes:
    return newline.join(lines) + newline + body


def header_cases(data: bytes, n: int, rng: np.random.Generator) -> Iterator[Case]:
    lines, body = split(data)
    vertex = next(i for i, line in enumerate(lines) if line.startswith(b"element vertex"))
    props = [i for i, line in enumerate(lines) if line.startswith(b"property")]
    names = {line.split()[-1]: i for i, line in enumerate(lines) if line.startswith(b"property")}

    def with_line(i: int, new: bytes | None) -> list[bytes]:
        out = list(lines)
        if new is None:
            del out[i]
        else:
            out[i] = new
        return out

    for count in [0, 1, 2, n - 1, n + 1, 2 * n, -1, 2**31, 2**64 + 1]:
        yield Case("header", f"vertex count {count}", join(with_line(vertex, b"element vertex %d" % count), body))
    digits = b"%d" % n
    for text in (b"1e3", b"x", b"", digits[:1] + b"_" + digits[1:]):  # the last: Python's int() reads it, C's readers not
        yield Case("header", f"vertex count {text!r}", join(with_line(vertex, b"element vertex " + text), body))
    for name in (b"x", b"opacity", b"scale_0", b"rot_0", b"f_dc_2"):
        for new_type in (b"uchar", b"int", b"double", b"list uchar float", b"float128"):
            line = b"property " + new_type + b" " + name
            yield Case("header", f"{name.decode()} as {new_type.decode()}", join(with_line(names[name], line), body))
    for fmt in (b"ascii 1.0", b"binary_big_endian 1.0", b"binary_little_endian 2.0", b"binary_middle_endian 1.0"):
        yield Case("header", f"format {fmt.decode()}", join(with_line(1, b"format " + fmt), body))
    for name in (b"x", b"z", b"opacity", b"scale_2", b"rot_3", b"f_dc_1", b"nx"):
        if name in names:
            yield Case("header", f"property {name.decode()} missing", join(with_line(names[name], None), body))
    for name in (b"x", b"rot_0"):
        out = list(lines)
        out.insert(names[name] + 1, lines[names[name]])
        yield Case("header", f"property {name.decode()} repeated", join(out, body))
    out = list(lines)
    out.insert(props[-1] + 1, b"property list uchar int indices")
    yield Case("header", "list property after the vertex properties", join(out, body))
    out = list(lines)
    out.insert(props[0], b"property list uchar float weights")
    yield Case("header", "list property first", join(out, body))
    end = lines.index(b"end_header")
    for element, extra in ((b"element face 0", b""), (b"element face 3", b""), (b"element camera 1", bytes(12))):
        out = list(lines)
        additions = [element]
        if element.startswith(b"element face"):
            additions.append(b"property list uchar int vertex_indices")
        else:
            additions += [b"property float fx", b"property float fy", b"property float fz"]
        out[end:end] = additions
        yield Case("header", f"unknown element after vertex: {element.decode()}", join(out, body + extra))
        out = list(lines)
        out[vertex:vertex] = additions
        yield Case("header", f"unknown element before vertex: {element.decode()}", join(out, extra + body))
    yield Case("header", "CRLF line ends", join(lines, body, b"\r\n"))
    yield Case("header", "CR line ends", join(lines, body, b"\r"))
    for comments in (1000, 40000):
        out = list(lines)
        out[2:2] = [b"comment " + b"z" * 40] * comments
        yield Case("header", f"{comments} comment lines", join(out, body))
    out = list(lines)
    out[2:2] = [b"comment " + b"y" * (2 << 20)]
    yield Case("header", "a 2 MiB comment line", join(out, body))
    yield Case("header", "no ply magic", join(lines[1:], body))
    yield Case("header", "no format line", join(lines[:1] + lines[2:], body))
    yield Case("header", "no end_header", join(lines[:-1], body))
    yield Case("header", "header only", join(lines, b""))
    garbage = rng.integers(32, 127, 200, dtype=np.uint8).tobytes()
    yield Case("header", "a line of printable garbage", join(lines[:3] + [garbage] + lines[3:], body))
    yield Case("header", "non-ASCII bytes in a property name", join(with_line(props[0], b"property float \xff\xfe"), body))


def truncation_cases(data: bytes) -> Iterator[Case]:
    lines, body = split(data)
    header = len(data) - len(body)
    for cut in (0, 1, 3, header // 2, header - 1, header):
        yield Case("truncate", f"cut at byte {cut} of the header", data[:cut])
    for fraction in (0.001, 0.1, 0.5, 0.9, 0.999):
        cut = header + int(fraction * len(body))
        yield Case("truncate", f"cut at {fraction:g} of the body", data[:cut])
    yield Case("truncate", "last byte missing", data[:-1])


def corruption_cases(data: bytes, rng: np.random.Generator, count: int) -> Iterator[Case]:
    _, body = split(data)
    header = len(data) - len(body)
    for c in range(count):
        damaged = bytearray(data)
        hits = int(rng.integers(1, 41))
        where = header + rng.integers(0, len(body), hits)
        damaged_bytes = rng.integers(0, 256, hits, dtype=np.uint8)
        for w, b in zip(where, damaged_bytes):
            damaged[int(w)] = int(b)
        yield Case("corrupt", f"{hits} random body bytes overwritten (#{c})", bytes(damaged))


def extreme_cases(vertices: np.ndarray, rng: np.random.Generator, properties: list[str]) -> Iterator[Case]:
    n = vertices.shape[0]
    row = int(rng.integers(0, n))
    for name in properties:
        for label, value in EXTREMES.items():
            v = vertices.copy()
            v[name][row] = value
            yield Case("extreme", f"{name} = {label} in one row", ply_bytes(v))
    tenth = rng.choice(n, max(1, n // 10), replace=False)
    for name in ("x", "scale_0", "opacity", "rot_0", "f_dc_0"):
        for label in ("denormal", "max", "-max", "nan"):
            v = vertices.copy()
            v[name][tenth] = EXTREMES[label]
            yield Case("extreme", f"{name} = {label} in a tenth of the rows", ply_bytes(v))


def geometry_cases(vertices: np.ndarray, rng: np.random.Generator) -> Iterator[Case]:
    n = vertices.shape[0]
    for m in (1, 2, 3):
        yield Case("geometry", f"{m} splats", ply_bytes(vertices[:m].copy()))
    v = vertices[:3].copy()
    v[["x", "y", "z"]] = v[["x", "y", "z"]][0]
    yield Case("geometry", "3 splats at one position", ply_bytes(v))

    def positions(make: Callable[[np.ndarray], np.ndarray], what: str) -> Case:
        v = vertices.copy()
        xyz = make(np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64))
        for a, name in enumerate("xyz"):
            v[name] = xyz[:, a]
        return Case("geometry", what, ply_bytes(v))

    yield positions(lambda p: np.broadcast_to(p[0], p.shape), "every splat at one position")
    yield positions(lambda p: np.outer(rng.uniform(-1, 1, n), [1.0, 2.0, -0.5]), "collinear")
    yield positions(lambda p: np.c_[p[:, :2], np.zeros(n)], "coplanar (z = 0)")
    yield positions(lambda p: np.c_[np.round(p * 20) / 20], "positions on a coarse lattice")
    half = rng.choice(n, n // 2, replace=False)

    def half_at_one(p):
        p = p.copy()
        p[half] = p[half[0]]
        return p

    yield positions(half_at_one, "half of the splats at one position")
    yield positions(lambda p: ray_centres(n, rng).astype(np.float64), "on one ray over sixty decades")
    yield positions(lambda p: bit_centres(n, rng).astype(np.float64), "coordinates from random float32 bits")
    for label, value in (("1e20", 1e20), ("1e30", 1e30), ("-max", -FLT_MAX)):

        def far(p, value=value):
            p = p.copy()
            p[int(rng.integers(0, n)), 2] = value
            return p

        yield positions(far, f"one splat at z = {label}")
    v = vertices.copy()
    v[:] = v[0]
    yield Case("geometry", "every row identical", ply_bytes(v))
    v = vertices.copy()
    v[:] = v[rng.integers(0, 50, n)]
    yield Case("geometry", "every row a copy of one of 50", ply_bytes(v))


def corpus(sample: bytes, seed: int = 0, splats: int | None = None) -> Iterator[tuple[str, Case]]:
    """(seed name, case) for both seeds, in a fixed order."""
    rng = np.random.default_rng(seed)
    sample_vertices = np.array(plyfile.PlyData.read(_bytes_io(sample))["vertex"].data)
    if splats is not None:
        sample_vertices = sample_vertices[:splats]
        sample = ply_bytes(sample_vertices)
    generated = generated_sh3_scene(splats or 3000, seed)
    for seed_name, vertices, data in (("sample", sample_vertices, sample), ("sh3", generated, ply_bytes(generated))):
        n = vertices.shape[0]
        for case in header_cases(data, n, rng):
            yield seed_name, case
        for case in truncation_cases(data):
            yield seed_name, case
        for case in corruption_cases(data, rng, 32):
            yield seed_name, case
        properties = ["x", "z", "f_dc_0", "opacity", "scale_0", "rot_0"]
        if "f_rest_0" in vertices.dtype.names:
            properties.append("f_rest_0")
        for case in extreme_cases(vertices, rng, properties):
            yield seed_name, case
        for case in geometry_cases(vertices, rng):
            yield seed_name, case
        text = ply_bytes(vertices[: min(n, 500)].copy(), text=True)
        yield seed_name, Case("header", "ASCII file (500 rows)", text)
        yield seed_name, Case("truncate", "ASCII file cut in a row", text[: len(text) * 2 // 3])


def _bytes_io(data: bytes):
    from io import BytesIO

    return BytesIO(data)


def write_corpus(sample_path: Path, folder: Path, seed: int = 0, splats: int | None = None) -> list[dict]:
    """Writes every case to ``folder`` (NNN_seed_family.ply) and ``corpus.jsonl``; returns its lines."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for index, (seed_name, case) in enumerate(corpus(sample_path.read_bytes(), seed, splats)):
        name = f"{index:03d}_{seed_name}_{case.family}.ply"
        (folder / name).write_bytes(case.data)
        entries.append({"file": name, "seed": seed_name, "family": case.family, "what": case.what})
    with (folder / "corpus.jsonl").open("w") as out:
        for entry in entries:
            out.write(json.dumps(entry) + "\n")
    return entries


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sample", type=Path, help="the seed scene (a valid 3DGS .ply)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder for the cases")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--splats", type=int, default=None, help="use the first N splats of the seed scene")
    args = parser.parse_args(argv)
    entries = write_corpus(args.sample, args.output, args.seed, args.splats)
    families: dict[str, int] = {}
    for entry in entries:
        families[entry["family"]] = families.get(entry["family"], 0) + 1
    print(f"{len(entries)} cases in {args.output}: " + ", ".join(f"{k} {v}" for k, v in families.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
