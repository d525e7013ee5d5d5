"""Candidate topology: the exact k-nearest-neighbour graph of the splat centres and its undirected edges.

Everything runs on the device of the input; the host reads only scalars and small samples: a
bounding box, a sorted sample of up to 16,384 coordinates per axis (for quantiles), a 22-bin
histogram of the levels where neighbours part, 22 flags of the levels searched and the edge count.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass

import numpy as np
import warp as wp

from nanogs_warp.kernels import edges as edge_kernels
from nanogs_warp.kernels import knn as knn_kernels
from nanogs_warp.parallel import cpu_workers, in_turn, launch_rows_from

KMAX = knn_kernels.KMAX
INEXACT = knn_kernels.INEXACT  # a reach entry whose query stopped at its work limit
_LEVELS = knn_kernels.LEVELS
_GRID_CELLS = 1 << knn_kernels.GRID_BITS
_NODE_LEVELS = knn_kernels.NODE_LEVELS
_QUANTILE_SAMPLES = 16384  # points sampled per axis for the quantisation cube
_BOX_PARTS = 4096  # the bounding box is reduced from this many parts' boxes
_QUANTILE_TAIL = 0.001  # fraction of the sample left out at each end
_QUARTILE_REACH = 1000.0  # interquartile ranges (a normal distribution's 99.8% spans 4.6)
_LARGEST_SIDE = 2.0**120  # of the quantisation cube (float32 holds up to 2^128)
# Cube sides whose points are measured as they are (``measured_points``): squared distances across
# such a cube stay far inside float32's normal range (2^-126 to 2^128), down to a millionth of its side.
MEASURED_SIDE = (2.0**-40, 2.0**40)
# A scaled scene's typical spacing is kept at least this (squared: 2^-80, far inside float32's normal
# range), by a larger scale where the cube's side allows: at most 2^62 after scaling, so that squared
# distances across the cube (three axes) stay below 2^126.
FINEST_SPACING = 2.0**-40
_LARGEST_MEASURED_EXPONENT = 62


@dataclass
class Edges:
    """Unique undirected edges, i < j, grouped by i in ascending order. Within a group: i's own
    neighbours above i in kNN order (nearest first), then the points above i that list i while i
    does not list them, ascending. A canonical order, the same on every device; the pairing breaks
    cost ties by it."""

    i: wp.array  # int32, length count
    j: wp.array  # int32
    count: int


def knn_graph(
    means: wp.array, k: int, candidates: wp.array | None = None, reach: wp.array | None = None, cube: tuple | None = None
) -> wp.array:
    """(N, k) int32 array on means.device: for each point its k nearest OTHER points (self excluded),
    sorted by (squared distance, index) ascending. Requires 1 <= k <= min(KMAX, N-1).

    A query whose search would take more than a work limit keeps the best k it met, unless few did
    (``nanogs_warp.kernels.knn``, "Work limit"): on scenes whose float32 distances mostly tie.

    ``candidates``, if given (int32, length N), receives the number of points each query examined;
    ``reach``, if given (int64, length N), each point's k-th neighbour as one key, its squared
    distance's float32 bits << 32 | its index, or ``INEXACT`` where the query stopped at the limit
    (``candidate_edges`` uses it). The distances are those
    of ``measured_points(means)``: ``means`` themselves unless their extent is far from 1. ``cube``:
    that function's cube, when ``means`` are its points already.
    """
    n = means.shape[0]
    if not 1 <= k <= min(KMAX, n - 1):
        raise ValueError(f"k must be in [1, min({KMAX}, N-1)] for N = {n} points, got {k}")
    device = means.device
    if candidates is None:
        candidates = wp.empty(0, dtype=wp.int32, device=device)
    elif candidates.shape[0] != n:
        raise ValueError(f"candidates must have length {n}, got {candidates.shape[0]}")
    if reach is None:
        reach = wp.empty(0, dtype=wp.int64, device=device)
    elif reach.shape[0] != n:
        raise ValueError(f"reach must have length {n}, got {reach.shape[0]}")

    if cube is None:
        means, cube = measured_points(means)
    lo, quantum, margin = cube
    codes, order = _morton_order(means, lo, quantum)
    search_level, tables, crowded = _cell_tables(codes, k)
    if crowded:  # k + 1 points share a level-0 cell: order each cell's points by their float bits
        order = _morton_order(means, lo, quantum, given=_float_bit_order(means))[1]
    points = wp.empty(n, dtype=wp.vec3, device=device)
    launch_rows_from(knn_kernels._gather_points, n, [means, order, points], device)
    nodes = _tree_nodes(points, order)

    neighbours = wp.full((n, k), -1, dtype=wp.int32, device=device)
    stopped = wp.empty(n, dtype=wp.int32, device=device)
    stopped_total = wp.empty(n, dtype=wp.int32, device=device)
    search = [points, order, search_level, k, lo, 1.0 / quantum, quantum, margin, *tables, *nodes]
    search += [stopped, stopped_total, neighbours, reach, candidates]
    # Every query within its work limit; then, if few stopped at it, those again without one.
    launch_rows_from(knn_kernels._knn_query, n, [0, *search], device, min_rows=512)  # ~2 us a query on a CPU core
    wp.utils.array_scan(stopped, stopped_total, inclusive=True)
    launch_rows_from(knn_kernels._knn_query, n, [1, *search], device, min_rows=4096)
    return neighbours


def candidate_edges(neighbours: wp.array, means: wp.array | None = None, reach: wp.array | None = None) -> Edges:
    """Union of directed kNN edges as undirected, deduplicated, i < j, in the order ``Edges`` describes.

    For the exact kNN graph of ``means`` with its ``reach`` (from ``knn_graph``), whether row j
    lists i is one comparison; for any other table of neighbours (no ``reach``), a scan of row j.

    ``neighbours`` is an (N, k) int32 table, k <= 32, whose row i lists k distinct points other than
    i. No global sort: every edge (a, b), a < b, is counted into and written to the segment of a
    (see ``nanogs_warp.kernels.edges``). Scratch memory is 12 bytes per point (a bit mask, a count
    and an offset) besides the output; the host reads one scalar, the edge count.
    """
    n, k = neighbours.shape
    device = neighbours.device
    if n * k == 0:
        empty = wp.empty(0, dtype=wp.int32, device=device)
        return Edges(i=empty, j=wp.empty(0, dtype=wp.int32, device=device), count=0)
    if k > edge_kernels.MAX_K:
        raise ValueError(f"candidate_edges takes at most {edge_kernels.MAX_K} neighbours per row, got {k}")
    if n * k >= 2**31:
        raise ValueError(f"{n} x {k} neighbours overflow the int32 edge offsets")
    rows = neighbours
    if k % 4 == 0 and neighbours.is_contiguous and neighbours.ptr % 16 == 0:
        rows = neighbours.reshape((n, k // 4, 4)).view(wp.vec4i)  # the same memory, a quarter of the loads
    if reach is None:
        means = wp.empty(0, dtype=wp.vec3, device=device)
        reach = wp.empty(0, dtype=wp.int64, device=device)
    foreign = wp.empty(n, dtype=wp.uint32, device=device)
    count = wp.empty(n, dtype=wp.int32, device=device)
    launch_rows_from(edge_kernels._classify_rows, n, [rows, k, means, reach, foreign, count], device, min_rows=4096)
    # the kernels with atomics: one launch each, never split over CPU threads
    wp.launch(edge_kernels._count_foreign, n, inputs=[neighbours, foreign], outputs=[count], device=device)
    offsets = wp.empty(n + 1, dtype=wp.int32, device=device)
    offsets[:1].zero_()
    wp.utils.array_scan(count, offsets[1:], inclusive=True)
    total = int(offsets[n:].numpy()[0])
    i = wp.full(total, -1, dtype=wp.int32, device=device)
    j = wp.full(total, -1, dtype=wp.int32, device=device)
    wp.launch(
        edge_kernels._place_foreign, n, inputs=[neighbours, foreign, offsets], outputs=[count, j], device=device
    )
    launch_rows_from(edge_kernels._finish_segments, n, [rows, k, offsets, i, j], device, min_rows=4096)
    return Edges(i=i, j=j, count=total)


class KnnTopology:
    """The topology stage as the pipeline calls it: splats -> candidate edges of their kNN graph.

    k shrinks to N-1 when fewer than k+1 splats are left. ``stage`` (benchmarks) is a context
    manager factory that times the two steps, "knn" and "edges".
    """

    MAX_K = KMAX

    def __init__(self, k: int):
        if not 1 <= k <= KMAX:
            raise ValueError(f"k must be in [1, {KMAX}], got {k}")
        self.k = k

    def __call__(self, splats, stage: Callable[[str], AbstractContextManager] = lambda name: nullcontext()) -> Edges:
        with stage("knn"):
            points, cube = measured_points(splats.means)
            reach = wp.empty(splats.count, dtype=wp.int64, device=splats.means.device)
            neighbours = knn_graph(points, min(self.k, splats.count - 1), reach=reach, cube=cube)
        with stage("edges"):
            return candidate_edges(neighbours, points, reach)


def _level_groups(used: np.ndarray, workers: int) -> list[tuple[int, int]]:
    """The searched levels cut into up to ``workers`` contiguous ranges (first, last) of about as
    many levels each (a level's insert work is about the same at every level: each point checks
    whether it starts a cell)."""
    return [(int(part[0]), int(part[-1])) for part in np.array_split(used, max(1, min(workers, len(used))))]


def measured_points(means: wp.array) -> tuple[wp.array, tuple[wp.vec3, float, float]]:
    """The points whose float32 distances the kNN search compares, and their quantisation cube
    (corner, quantum, margin: ``_quantisation_cube``). These are ``means`` themselves when the cube's
    side lies within MEASURED_SIDE; otherwise ``means`` times a power of two: the one that brings the
    side to [1/2, 1), or a larger one, up to the one that brings it to [2^61, 2^62), where the
    points' typical spacing would otherwise fall below FINEST_SPACING (clusters far apart, each
    fine: float32 would square their neighbours' distances to zero). Scaling by a power of two is
    exact, so the neighbours stay those of ``means``; without it, a scene whose extent is ~1e19 or
    more would overflow its squared distances to inf (every query would then scan every point) and a
    tiny one would compute with subnormals (slow on CPUs, flushed to zero on some devices).
    Coordinates that the scaling would take past float32's range are clamped to it (far outliers
    stay far), below its smallest normal set to 0."""
    cube, spacing = _quantisation_cube(means)
    lo, quantum, margin = cube
    side = quantum * _GRID_CELLS
    if MEASURED_SIDE[0] <= side <= MEASURED_SIDE[1]:
        return means, cube
    exponent = math.frexp(side)[1]  # side in [2^(exponent - 1), 2^exponent)
    scale = math.ldexp(1.0, -exponent)
    if 0.0 < spacing * scale < FINEST_SPACING:
        needed = math.ldexp(1.0, math.frexp(FINEST_SPACING / spacing)[1])  # spacing * needed >= FINEST_SPACING
        scale = max(scale, min(needed, math.ldexp(1.0, _LARGEST_MEASURED_EXPONENT - exponent)))
    points = wp.empty_like(means)
    wp.launch(knn_kernels.scaled_points, means.shape[0], inputs=[means, scale], outputs=[points], device=means.device)
    corner = wp.vec3(*(float(c) * scale for c in lo))  # float32 corner times a power of two: exact
    return points, (corner, quantum * scale, margin * scale)


def bounding_box(means: wp.array) -> tuple[np.ndarray, np.ndarray, int]:
    """The axis-aligned bounding box of the finite points (float64 corners; +inf and -inf where none
    is) and how many points are not finite: the boxes of up to _BOX_PARTS interleaved parts (on
    every CPU core), then merged."""
    n, device = means.shape[0], means.device
    parts = max(1, min(n, _BOX_PARTS))
    part_lo = wp.empty(parts, dtype=wp.vec3, device=device)
    part_hi = wp.empty(parts, dtype=wp.vec3, device=device)
    part_bad = wp.empty(parts, dtype=int, device=device)
    launch_rows_from(knn_kernels.partial_boxes, parts, [means, parts, part_lo, part_hi, part_bad], device, min_rows=256)
    box = wp.array([[np.inf] * 3, [-np.inf] * 3], dtype=wp.vec3, device=device)
    bad = wp.zeros(1, dtype=int, device=device)
    threads = min(parts, 64)
    wp.launch(knn_kernels.merged_box, threads, inputs=[part_lo, part_hi, part_bad, threads], outputs=[box, bad], device=device)
    lo, hi = box.numpy().astype(np.float64)
    return lo, hi, int(bad.numpy()[0])


def _quantisation_cube(means: wp.array) -> tuple[tuple[wp.vec3, float, float], float]:
    """Corner and level-0 cell side (quantum) of the cube that quantises the points to 21 bits per
    axis, and the margin by which cell-distance lower bounds are lowered for float32 rounding; and
    the points' typical spacing: the smallest, over the axes, of the median positive gap between
    consecutive sampled coordinates (0 where no axis has two distinct ones).

    The cube spans the bounding box, cut down to three times the width of the central 99.8% of the
    points (per axis, from a sample) and to 1000 interquartile ranges around the central half: far
    outliers would otherwise stretch the cells until dense clusters fall into one level-0 cell.
    Points outside the cube are clamped into its boundary cells.
    """
    device = means.device
    n = means.shape[0]
    box_lo, box_hi, bad = bounding_box(means)
    if bad > 0:
        raise ValueError(f"means contain {bad} non-finite points")

    lo, hi = box_lo.copy(), box_hi.copy()
    stride = max(1, n // _QUANTILE_SAMPLES)
    m = (n + stride - 1) // stride
    keys = wp.empty(2 * m, dtype=wp.float32, device=device)
    values = wp.zeros(2 * m, dtype=wp.int32, device=device)
    tail = int(_QUANTILE_TAIL * (m - 1))
    spacings = []
    for axis in range(3):
        wp.launch(knn_kernels._sample_axis, m, inputs=[means, stride, axis], outputs=[keys], device=device)
        wp.utils.radix_sort_pairs(keys, values, m)
        sample = keys[:m].numpy().astype(np.float64)
        gaps = np.diff(sample)
        gaps = gaps[gaps > 0.0]
        if gaps.size:
            spacings.append(float(np.median(gaps)))
        q_lo, q_hi = sample[tail], sample[m - 1 - tail]
        width = q_hi - q_lo
        lo[axis], hi[axis] = max(lo[axis], q_lo - width), min(hi[axis], q_hi + width)
        # more far outliers than the tails leave out: the cube reaches no further than
        # _QUARTILE_REACH interquartile ranges from the central half
        q25, q75 = sample[(m - 1) // 4], sample[3 * (m - 1) // 4]
        if q75 > q25:
            lo[axis] = max(lo[axis], q25 - _QUARTILE_REACH * (q75 - q25))
            hi[axis] = min(hi[axis], q75 + _QUARTILE_REACH * (q75 - q25))
    side = float(np.max(hi - lo))
    if side <= 0.0:  # the central points coincide: fall back to the whole box, or to a unit cube
        lo, side = box_lo, float(np.max(box_hi - box_lo)) or 1.0
    # cell sides (quantum x 2^level) stay finite in float32 whatever the coordinates; points beyond
    # the cube fall into its boundary cells as ever
    side = min(side, _LARGEST_SIDE)
    quantum = side / _GRID_CELLS
    # Positions are taken relative to `lo` (a correctly rounded float32 difference), so a point's
    # computed cell and the cell's bounds err by well under a quantum; two quanta cover both.
    return (wp.vec3(*lo), quantum, 2.0 * quantum), min(spacings, default=0.0)


def _morton_order(means: wp.array, lo: wp.vec3, quantum: float, given: wp.array | None = None) -> tuple[wp.array, wp.array]:
    """Sorted Morton codes and the sorting permutation. One sort serves every level: a level's cells
    are contiguous ranges of the sorted points. Within a level-0 cell the points keep the order
    ``given`` (the radix sort is stable; default: index order)."""
    n, device = means.shape[0], means.device
    codes = wp.empty(2 * n, dtype=wp.int64, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    given = wp.empty(0, dtype=wp.int32, device=device) if given is None else given
    launch_rows_from(knn_kernels.morton_codes, n, [means, given, lo, 1.0 / quantum, codes, order], device)
    wp.utils.radix_sort_pairs(codes, order, n, end_bit=3 * knn_kernels.GRID_BITS)
    return codes[:n], order[:n]


def _float_bit_order(means: wp.array) -> wp.array:
    """The points in the Morton order of their coordinates' float bits: near points stay near at
    every scale. Given to ``_morton_order`` where k + 1 points crowd a level-0 cell, as in a scene
    whose coordinates span dozens of orders of magnitude (its level-0 cells and the cube's boundary
    cells, which hold the far points, fill up): the tree over the sorted points (``_tree_nodes``)
    then stays tight there, where every query used to scan the cell whole. The neighbours found are
    the same in any order within a cell; only the work differs."""
    n, device = means.shape[0], means.device
    codes = wp.empty(2 * n, dtype=wp.int64, device=device)
    order = wp.empty(2 * n, dtype=wp.int32, device=device)
    wp.launch(knn_kernels.float_morton_codes, n, inputs=[means], outputs=[codes, order], device=device)
    wp.utils.radix_sort_pairs(codes, order, n, end_bit=3 * knn_kernels.GRID_BITS)
    return order[:n]


def _tree_nodes(points: wp.array, order: wp.array) -> list[wp.array]:
    """The implicit tree over the sorted points: level s (1..NODE_LEVELS) has a node per 8^s
    consecutive points with its bounding box and smallest and largest original index, all levels in
    flat arrays: [node_base (per level, index 0 unused), node_lo, node_hi, node_first, node_last]."""
    n, device = points.shape[0], points.device
    counts = [0] + [-(-n // 8**s) for s in range(1, _NODE_LEVELS + 1)]
    base = np.zeros(_NODE_LEVELS + 1, dtype=np.int32)
    base[2:] = np.cumsum(counts[1:-1])
    total = int(sum(counts))
    node_lo = wp.empty(total, dtype=wp.vec3, device=device)
    node_hi = wp.empty(total, dtype=wp.vec3, device=device)
    node_first = wp.empty(total, dtype=wp.int32, device=device)
    node_last = wp.empty(total, dtype=wp.int32, device=device)
    arrays = [node_lo, node_hi, node_first, node_last]
    wp.launch(knn_kernels._leaf_nodes, counts[1], inputs=[points, order], outputs=arrays, device=device)
    for s in range(2, _NODE_LEVELS + 1):
        inputs = [int(base[s - 1]), counts[s - 1], int(base[s])]
        wp.launch(knn_kernels._parent_nodes, counts[s], inputs=inputs, outputs=arrays, device=device)
    return [wp.array(base, dtype=wp.int32, device=device), *arrays]


def _cell_tables(codes: wp.array, k: int) -> tuple[wp.array, list, bool]:
    """Each sorted point's search level, hash tables cell -> sorted range for the levels searched
    (at most half full): [level_base, level_mask, keys, starts, ends], and whether level 0 is
    searched (some k + 1 points share a level-0 cell). None depends on the order of the points
    within a level-0 cell."""
    n, device = codes.shape[0], codes.device
    window_level = wp.empty(n - k, dtype=wp.int32, device=device)
    split_histogram = wp.zeros(_LEVELS, dtype=wp.int32, device=device)
    wp.launch(knn_kernels._window_levels, n, inputs=[codes, k], outputs=[window_level, split_histogram], device=device)
    search_level = wp.empty(n, dtype=wp.int32, device=device)
    searched = wp.zeros(_LEVELS, dtype=wp.int32, device=device)
    launch_rows_from(knn_kernels._search_levels, n, [window_level, k, search_level, searched], device)

    splits = split_histogram.numpy()
    used = np.flatnonzero(searched.numpy())
    cells = np.array([1 + int(splits[level + 1 :].sum()) for level in range(_LEVELS)])  # points part below a level
    base = np.zeros(_LEVELS, dtype=np.int32)
    mask = np.full(_LEVELS, -1, dtype=np.int32)
    total = 0
    for level in used:
        capacity = 1 << (2 * int(cells[level]) - 1).bit_length()
        base[level], mask[level] = total, capacity - 1
        total += capacity
    level_base = wp.array(base, dtype=wp.int32, device=device)
    level_mask = wp.array(mask, dtype=wp.int32, device=device)
    keys = wp.full(total, knn_kernels.EMPTY, dtype=wp.int64, device=device)
    starts = wp.empty(total, dtype=wp.int32, device=device)
    ends = wp.empty(total, dtype=wp.int32, device=device)
    tables = [level_base, level_mask]
    # inserting uses atomics: on the CPU, levels (separate tables) are shared out between cores instead of rows
    def insert(levels: tuple[int, int]) -> None:
        wp.launch(knn_kernels._insert_cells, n, inputs=[codes, *levels, *tables], outputs=[keys, starts], device=device)

    groups = _level_groups(used, cpu_workers() if device.is_cpu else 1)
    if len(groups) > 1:
        wp.load_module(knn_kernels._insert_cells.module, device=device)
    in_turn(len(groups), groups, insert)
    levels = [codes, int(used[0]), int(used[-1]), *tables]
    launch_rows_from(knn_kernels._close_cells, n, [*levels, keys, ends], device)
    return search_level, [level_base, level_mask, keys, starts, ends], bool(used[0] == 0)
