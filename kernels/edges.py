"""Unique undirected edges of a directed k-nearest-neighbour graph, built without a global sort.

The output is cut into one segment per point a: the edges (a, b) with b > a. Segment a holds
  (a) every neighbour b > a of row a, in row order (the entries of a row are distinct), then
  (b) every row b > a that lists a while row a does not list b, ascending.
A pair listed by both rows is taken from (a) only, so every undirected edge appears exactly once.

  _classify_rows    per row: how many entries go to (a), and a bit mask of the entries (i -> j),
                    j < i, that go to part (b) of segment j ("foreign" entries); whether row j
                    lists i is one comparison for an exact kNN graph with its reach, else a scan
  _count_foreign    per row, atomic: adds each foreign entry to its segment's length
  (scan)            segment offsets
  _place_foreign    per row, atomic: writes each foreign entry into its segment's part (b)
  _finish_segments  per row: writes part (a) in front of part (b), sorts part (b) and writes the
                    segment's i

Kernels without atomics may be split over CPU threads; the two atomic kernels must be single
launches on the CPU (CPU atomics are plain read-modify-writes). Part (b) lands in an order that
depends on the order the rows run in; sorting it makes the output independent of that order.

The rows are read through ``rows``: the (N, k) int32 table itself, or, where k is a multiple of 4,
the same memory viewed as (N, k/4) vec4i (a quarter of the loads; CPU array accesses are costly).
"""

from typing import Any

import warp as wp

from .knn import INEXACT, neighbour_key, squared_distance
from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

MAX_K = wp.constant(32)  # foreign entries of a row are bits of a uint32
# Part (b) is insertion-sorted up to this length, heap-sorted beyond it (a point listed by many rows)
# unless already in order: O(m log m) whatever order it arrives in.
SMALL_PART = wp.constant(32)


@wp.func
def _lane(chunk: wp.int32, w: int) -> wp.int32:
    return chunk


@wp.func
def _lane(chunk: wp.vec4i, w: int) -> wp.int32:
    return chunk[w]


@wp.func
def _count_equal(chunk: wp.int32, value: wp.int32) -> int:
    return wp.where(chunk == value, 1, 0)


@wp.func
def _count_equal(chunk: wp.vec4i, value: wp.int32) -> int:
    return (
        wp.where(chunk[0] == value, 1, 0)
        + wp.where(chunk[1] == value, 1, 0)
        + wp.where(chunk[2] == value, 1, 0)
        + wp.where(chunk[3] == value, 1, 0)
    )


@wp.func
def row_lists(
    rows: wp.array2d(dtype=Any), j: int, i: int, means: wp.array(dtype=wp.vec3), reach: wp.array(dtype=wp.int64)
) -> bool:
    """Whether row j lists i. Rows of an exact kNN graph with ``reach`` (row j's k-th neighbour as
    its key, ``knn.neighbour_key``, the distance computed as the query computes it): one
    comparison. Otherwise (no ``reach``, or a row its query left inexact: ``knn.INEXACT``) a scan
    of row j."""
    if reach.shape[0] > 0 and reach[j] != INEXACT:
        d = squared_distance(means[j], means[i])  # row j's query, candidate i
        return neighbour_key(d, j, i, means.shape[0]) <= reach[j]
    listed = int(0)
    for c in range(rows.shape[1]):  # bounded by the row's width
        listed += _count_equal(rows[j, c], i)
    return listed > 0


@wp.kernel
def _classify_rows(
    first: int,
    rows: wp.array2d(dtype=Any),
    k: int,
    means: wp.array(dtype=wp.vec3),
    reach: wp.array(dtype=wp.int64),
    foreign: wp.array(dtype=wp.uint32),
    count: wp.array(dtype=wp.int32),
):
    # count[i] = entries of row i above i (part (a) of segment i); bit t of foreign[i] set where
    # j = entry t < i and row j does not list i (part (b) of segment j)
    i = first + wp.tid()
    chunks = rows.shape[1]
    width = k // chunks
    above = int(0)
    mask = wp.uint32(0)
    t = int(0)
    for u in range(chunks):
        own = rows[i, u]
        for w in range(4):  # unrolled; lanes past the chunk's width are skipped
            if w < width:
                j = _lane(own, w)
                above += wp.where(j > i, 1, 0)
                if j < i:
                    if not row_lists(rows, j, i, means, reach):
                        mask = mask | (wp.uint32(1) << wp.uint32(t))
                t += 1
    foreign[i] = mask
    count[i] = above


@wp.kernel
def _count_foreign(
    neighbours: wp.array2d(dtype=wp.int32), foreign: wp.array(dtype=wp.uint32), count: wp.array(dtype=wp.int32)
):
    # count[j] += foreign entries (i -> j): count becomes each segment's length
    i = wp.tid()
    mask = foreign[i]
    while mask != wp.uint32(0):  # one step per set bit: at most 32
        low = mask & (wp.uint32(0) - mask)  # the lowest set bit: entry t
        mask = mask ^ low
        t = int(wp.bit_count(low - wp.uint32(1)))
        wp.atomic_add(count, neighbours[i, t], 1)


@wp.kernel
def _place_foreign(
    neighbours: wp.array2d(dtype=wp.int32),
    foreign: wp.array(dtype=wp.uint32),
    offsets: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
):
    # foreign entry (i -> j): i goes to the highest free slot of segment j, counting count[j] down
    # from the segment's length to the length of its part (a). Rows run from the last one so that,
    # where threads run in order (the CPU), every part (b) comes out ascending.
    i = neighbours.shape[0] - 1 - wp.tid()
    mask = foreign[i]
    while mask != wp.uint32(0):  # one step per set bit: at most 32
        low = mask & (wp.uint32(0) - mask)
        mask = mask ^ low
        t = int(wp.bit_count(low - wp.uint32(1)))
        j = neighbours[i, t]
        slot = wp.atomic_sub(count, j, 1) - 1
        edge_j[offsets[j] + slot] = i


@wp.func
def _sift_down(values: wp.array(dtype=wp.int32), base: int, root: int, size: int):
    # max-heap of values[base : base + size]: moves values[base + root] down to its place
    r = int(root)
    v = values[base + r]
    while 2 * r + 1 < size:  # r at least doubles each step: at most log2(size) steps
        c = 2 * r + 1
        if c + 1 < size:
            if values[base + c + 1] > values[base + c]:
                c += 1
        w = values[base + c]
        if w <= v:
            break
        values[base + r] = w
        r = c
    values[base + r] = v


@wp.func
def _sort_part(values: wp.array(dtype=wp.int32), start: int, stop: int):
    # ascending sort of the distinct values[start:stop], in place
    size = stop - start
    if size <= SMALL_PART:
        for e in range(start + 1, stop):
            v = values[e]
            f = int(e)
            while f > start:  # at most SMALL_PART steps
                w = values[f - 1]
                if w <= v:
                    break
                values[f] = w
                f -= 1
            values[f] = v
    else:
        ordered = bool(True)
        for e in range(start + 1, stop):
            if values[e - 1] > values[e]:
                ordered = False
                break
        if not ordered:
            r = size // 2
            while r > 0:  # size / 2 steps
                r -= 1
                _sift_down(values, start, r, size)
            last = size - 1
            while last > 0:  # size - 1 steps
                top = values[start]
                values[start] = values[start + last]
                values[start + last] = top
                _sift_down(values, start, 0, last)
                last -= 1


@wp.kernel
def _finish_segments(
    first: int,
    rows: wp.array2d(dtype=Any),
    k: int,
    offsets: wp.array(dtype=wp.int32),
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
):
    # segment i: part (a), row i's entries above i in row order, written in front of part (b) (already
    # in place behind it), which is sorted; i throughout
    i = first + wp.tid()
    start = offsets[i]
    stop = offsets[i + 1]
    chunks = rows.shape[1]
    width = k // chunks
    a = start
    for u in range(chunks):
        own = rows[i, u]
        for w in range(4):  # unrolled; lanes past the chunk's width are skipped
            if w < width:
                j = _lane(own, w)
                if j > i:
                    edge_j[a] = j
                    a += 1
    _sort_part(edge_j, a, stop)
    for e in range(start, stop):
        edge_i[e] = i


for _rows in (wp.array2d(dtype=wp.int32), wp.array2d(dtype=wp.vec4i)):
    wp.overload(_classify_rows, {"rows": _rows})
    wp.overload(_finish_segments, {"rows": _rows})
