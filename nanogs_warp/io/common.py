"""What the splat formats share: activations, 8-bit opacity, quaternion packing, spatial order,
bounded reads and the plain INRIA layout of scenes that come from a non-PLY file."""

from __future__ import annotations

import math
import os
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from .open_file import open_regular
from .ply_layout import PlyLayout
from .ply_write import output_properties

SH_C0 = 0.28209479177387814  # the degree-0 SH basis: colour = 0.5 + SH_C0 * f_dc
SQRT1_2 = float(np.sqrt(0.5))


def rest_per_channel(feature_count: int) -> int:
    """SH coefficients per colour channel beyond the DC term: 0, 3, 8 or 15."""
    return feature_count // 3 - 1


def plain_layout(n_rest: int) -> PlyLayout:
    """The layout of a scene read from a non-PLY file: INRIA order, float32, zero normals."""
    return PlyLayout(properties=output_properties(None, n_rest, 0), extra_names=[])


def sigmoid(logits: np.ndarray) -> np.ndarray:
    """float64 sigmoid without overflow; +-Inf give exactly 1 and 0."""
    x = np.asarray(logits, dtype=np.float64)
    with np.errstate(over="ignore"):
        return np.exp(-np.logaddexp(0.0, -x))


def opacity_to_byte(logits: np.ndarray) -> np.ndarray:
    """alpha = sigmoid(logit) in 8 bits: round(255 alpha)."""
    return np.clip(np.rint(sigmoid(logits) * 255.0), 0, 255).astype(np.uint8)


def byte_to_opacity_logit(codes: np.ndarray) -> np.ndarray:
    """The logit of alpha = code / 255, with codes 0 and 255 read as alpha 0.25/255 and
    1 - 0.25/255 (inside their rounding intervals): finite logits of +-6.93, never +-Inf."""
    alpha = np.clip(np.asarray(codes, dtype=np.float64) / 255.0, 0.25 / 255.0, 1.0 - 0.25 / 255.0)
    return np.log(alpha / (1.0 - alpha)).astype(np.float32)


def unit_quaternions(q: np.ndarray) -> np.ndarray:
    """Rows normalised in float64 (zero rows stay zero)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))
    return q / np.where(norm > 0, norm, 1.0)[:, None]


def largest_positive(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index of the largest |component|, q with its sign flipped so that component is >= 0)."""
    q = unit_quaternions(q)
    largest = np.argmax(np.abs(q), axis=1)
    sign = np.where(q[np.arange(q.shape[0]), largest] < 0, -1.0, 1.0)
    return largest, q * sign[:, None]


def smallest_three(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index of the largest component, the other three in order), after largest_positive."""
    largest, q = largest_positive(q)
    keep = np.ones_like(q, dtype=bool)
    keep[np.arange(q.shape[0]), largest] = False
    return largest, q[keep].reshape(-1, 3)


def from_smallest_three(largest: np.ndarray, three: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) from the largest component's index and the other three; the largest is
    sqrt(1 - |three|^2), clamped at 0."""
    n = largest.shape[0]
    three = np.asarray(three, dtype=np.float64)
    q = np.zeros((n, 4), np.float64)
    keep = np.ones((n, 4), dtype=bool)
    keep[np.arange(n), largest] = False
    q[keep] = three.reshape(-1)
    q[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.einsum("ij,ij->i", three, three)))
    return q


def morton_order(means: np.ndarray) -> np.ndarray:
    """A stable permutation of the rows along a Z-order curve of their centres (10 bits per axis
    over the finite bounding box), so that consecutive rows are near each other in space."""
    m = np.asarray(means, dtype=np.float64)
    finite = np.isfinite(m).all(axis=1)
    if not finite.any():
        return np.arange(m.shape[0])
    lo = m[finite].min(axis=0)
    span = np.maximum(m[finite].max(axis=0) - lo, 1e-30)
    cells = np.where(finite[:, None], np.clip((m - lo) / span * 1023.0, 0, 1023), 0).astype(np.uint64)
    code = np.zeros(m.shape[0], np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + 2 - axis)
    return np.argsort(code, kind="stable")


def channel_major_to_interleaved(rest: np.ndarray) -> np.ndarray:
    """f_rest (N, 3K) as stored in PLY (all R coefficients, then G, then B) -> (N, K, 3)."""
    n = rest.shape[0]
    return rest.reshape(n, 3, -1).transpose(0, 2, 1)


def interleaved_to_channel_major(rest: np.ndarray) -> np.ndarray:
    """(N, K, 3) -> f_rest (N, 3K) in PLY order."""
    n = rest.shape[0]
    return np.ascontiguousarray(rest.transpose(0, 2, 1).reshape(n, -1))


def read_file_bytes(path: Path, limit: int | None = None) -> bytes:
    """The whole file, with open/read errors as InputError (and a size limit, when given); a file
    larger than the machine's available memory is refused before it is read (a sparse file of
    terabytes takes no room on a disk)."""
    from ..device import memory_short

    name = path.name
    with open_regular(path) as f:
        try:
            size = os.fstat(f.fileno()).st_size
            if limit is not None and size > limit:
                raise InputError(f"{name}: {size} bytes is more than the {limit} this format allows")
            available = memory_short(size)
            if available is not None:
                raise InputError(f"{name}: {size:,} bytes is more than the {available:,} bytes of memory available")
            return f.read()
        except OSError as e:
            raise InputError(f"{name}: cannot read the file: {e.strerror or e}") from e


def top_level_keys(head: bytes) -> set[str]:
    """The keys of the JSON object that ``head`` starts (as far as ``head`` goes), those of the
    outermost object only: a file is told by its own keys, not by a string that happens to sit in
    a value or a nested object. Read as ASCII; escapes are kept as written."""
    keys, depth, at, n = set(), 0, 0, len(head)
    while at < n:
        c = head[at]
        if c == 0x22:  # a string: find its end, skipping escaped characters
            end = at + 1
            while end < n and head[end] != 0x22:
                end += 2 if head[end] == 0x5C else 1
            colon = end + 1
            while colon < n and head[colon] in b" \t\r\n":  # no copy of the rest: a scan in linear time
                colon += 1
            if depth == 1 and colon < n and head[colon] == 0x3A:
                keys.add(head[at + 1 : end].decode("ascii", "replace"))
            at = end + 1
            continue
        if c in b"{[":
            depth += 1
        elif c in b"}]":
            depth -= 1
        at += 1
    return keys


# What decoding costs a value of a splat (its 14 values and its SH coefficients): the decoders' float64
# arrays and their temporaries, then the float32 arrays they return.
DECODE_BYTES_PER_VALUE = 24


def check_decoded_memory(name: str, count: int, coefficients: int) -> None:
    """Refuses, before any work, ``count`` splats of ``coefficients`` SH coefficients each whose
    decoding (about DECODE_BYTES_PER_VALUE bytes a value) this machine's available memory could not
    hold: a small compressed file that declares a huge scene ends in one line, not in exhausted
    memory."""
    from ..device import memory_short

    need = count * (14 + coefficients) * DECODE_BYTES_PER_VALUE
    available = memory_short(need)
    if available is not None:
        raise InputError(f"{name}: decoding its {count:,} splats needs about {need:,} bytes of memory, more than the "
                         f"{available:,} available")  # fmt: skip


# Deflate expands at most 1032 times (zlib's documented limit), plus the gzip header's few bytes.
DEFLATE_MOST_EXPANSION = 1032


def most_inflated(compressed_bytes: int) -> int:
    """The most bytes a gzip stream of ``compressed_bytes`` bytes can hold."""
    return DEFLATE_MOST_EXPANSION * compressed_bytes + 1024


def gunzip_bounded(data: bytes, limit: int, name: str) -> bytes:
    """The gzip stream's content, refusing more than ``limit`` bytes (nothing larger is allocated),
    and refusing before any work a ``limit`` (of what ``data`` can hold: ``most_inflated``) that
    this machine's available memory could not hold: a small file that declares a huge scene
    ends in one line, not in exhausted memory."""
    from ..device import memory_short

    need = min(limit, most_inflated(len(data)))
    available = memory_short(need)
    if available is not None:
        raise InputError(f"{name}: its header declares {limit:,} bytes of data, more than the {available:,} bytes of memory "
                         "available")  # fmt: skip
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = d.decompress(data, limit + 1)
        if len(out) > limit:
            raise InputError(f"{name}: the compressed data holds more than the {limit} bytes its header declares")
        out += d.flush()
    except zlib.error as e:
        raise InputError(f"{name}: corrupt gzip data ({e})") from None
    if len(out) > limit:
        raise InputError(f"{name}: the compressed data holds more than the {limit} bytes its header declares")
    if not d.eof:
        raise InputError(f"{name}: truncated gzip data")
    return out


def host_arrays(means, rotations, log_scales, opacities, features) -> dict[str, np.ndarray]:
    """Decoded attributes as the float32 arrays every reader returns (rotations w first)."""
    n = means.shape[0]
    return {
        "means": np.ascontiguousarray(means, dtype=np.float32),
        "rotations": np.ascontiguousarray(rotations, dtype=np.float32),
        "log_scales": np.ascontiguousarray(log_scales, dtype=np.float32),
        "opacities": np.ascontiguousarray(np.reshape(opacities, n), dtype=np.float32),
        "features": np.ascontiguousarray(features, dtype=np.float32),
        "extras": np.zeros((n, 0), np.float32),
        "integer_extras": np.zeros((n, 0), np.int64),
    }


# A format's clamp worth a warning: one that moves a splat's centre or changes its size by more
# than this fraction of the scene's extent (less is below a pixel of a view of the whole scene).
VISIBLE_FRACTION = 1e-3


def scene_extent(means: np.ndarray, log_scales: np.ndarray) -> float:
    """The scene's size for the notes on what a format rounds or clamps: the larger of its centres'
    widest spread and its largest splat's (one splat alone has a size, not a spread)."""
    if means.shape[0] == 0:
        return 0.0
    spread = float(np.ptp(means.astype(np.float64), axis=0).max())
    with np.errstate(all="ignore"):
        largest = float(np.exp(np.clip(log_scales.astype(np.float64), -700.0, 700.0)).max()) if log_scales.size else 0.0
    return max(spread, largest)


def clamped_scales_note(log_scales: np.ndarray, means: np.ndarray, lowest: float, highest: float) -> list[str]:
    """A note when the format's log-scale range [lowest, highest] changes some splat's size by more
    than VISIBLE_FRACTION of the scene's extent (a scene stored in other units than the format
    expects); none otherwise."""
    if log_scales.size == 0:
        return []
    extent = scene_extent(means, log_scales)
    ls = log_scales.astype(np.float64)
    change = np.abs(np.exp(ls) - np.exp(np.clip(ls, lowest, highest)))
    count = int(np.count_nonzero((change > VISIBLE_FRACTION * extent).any(axis=1)))
    if not count:
        return []
    return [f"sizes outside {math.exp(lowest):.3g} to {math.exp(highest):.3g} units: {count:,} splats clamped, "
            f"by more than {VISIBLE_FRACTION:g} of the scene's extent ({extent:.3g})"]


def dropped_parts(host: dict[str, np.ndarray], layout: PlyLayout | None, max_sh_degree: int) -> list[str]:
    """What a format that holds SH up to ``max_sh_degree`` and no extra properties drops from
    these splats: higher SH bands, extra per-splat properties (all-zero normals are not counted),
    other PLY elements and header comments."""
    parts = []
    features = host["features"].shape[1]
    degree = {3: 0, 12: 1, 27: 2, 48: 3}[features]
    if degree > max_sh_degree:
        kept = 3 * (max_sh_degree + 1) ** 2
        parts.append(f"SH degree {degree} -> {max_sh_degree} ({features - kept} coefficients per splat)")
    extras = host["extras"]
    floats = list(layout.float_extra_names) if layout is not None else [f"extra_{i}" for i in range(extras.shape[1])]
    zero_normals = {nm for i, nm in enumerate(floats) if nm in ("nx", "ny", "nz") and not extras[:, i].any()}
    names = list(layout.extra_names) if layout is not None else floats
    lost = [nm for nm in names if nm not in zero_normals]
    if lost:
        shown = ", ".join(lost[:6]) + (f", ... ({len(lost)} properties)" if len(lost) > 6 else "")
        parts.append(f"extra properties {shown}")
    if layout is not None and layout.other_elements:
        parts.append("PLY elements " + ", ".join(e.name for e in layout.other_elements))
    if layout is not None and (layout.comments or layout.obj_info):
        parts.append("PLY header comments")
    return parts
