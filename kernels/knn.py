"""Exact k nearest neighbours on Morton-ordered cell grids of every level.

Points are sorted once by a 63-bit Morton code (21 bits per axis over a cube around the points;
far outliers are clamped into its boundary cells, which reach to infinity outwards). A cell of
level l (side 2^l quanta) is then a contiguous range of the sorted points, those whose codes share
the prefix ``code >> 3l``, so one sort serves every level. Each level in use gets an open-addressing
hash table from cell prefix to its range: exact keys, so distant cells never share a bucket.

Each point searches at the finest level whose own cell holds k+1 points (read off windows of k+1
consecutive codes). It seeds its k best with the ~1.5k points around it in Morton order: their
distances are binned in eighth octaves, and only the bins up to the one holding the k-th smallest are
inserted, nearest bin first (a counting sort), so the list fills almost in order. It then visits
rings of cells around its own cell, skipping cells, and blocks of 8 sorted points inside them, that
lie farther than its current k-th distance, and stops once the next ring cannot hold anything nearer.
Inside a cell the sorted points are visited through an implicit tree over the sorted order (nodes of
8, 64, 512, ... consecutive points, each with its bounding box and the range of its original
indices), so a crowded cell costs a few nodes, not a scan. A point that has not finished after
RING_LIMIT rings (a far outlier clamped into the cube's boundary cells, whose rings would cross the
whole grid) goes on at the top level, one cell holding every point, through the same tree.

Candidates rank by (squared distance, tie), one int64 key. The tie is the candidate's original index
when the distance is positive; at distance zero (a copy of the query's position) it is the index
counted from the query, (j - i) mod N, so each copy of a duplicated position lists the copies that
follow it, not all of them the same k lowest-index ones. The result is exact and independent of the
order in which threads or cells run, with one bound on the work below.

Termination: every loop is bounded by its inputs (noted beside it). Squared distances of finite
points may overflow float32 to +inf (coordinates beyond ~1e19 apart); they then rank by the tie
alone (the index), and a node of the tree whose box is that far is skipped when its smallest index
ranks after the query's current k-th; a query still scans each point once per level it visits
(at most two) at worst.
The host therefore measures a scene whose extent is far from 1 in a copy of its points scaled by a
power of two (``scaled_points``, ``nanogs_warp.topology.measured_points``): then only far outliers
can overflow, and a query scans everything only for them.

Work limit: where no power of two helps (coordinates spread over forty and more decades, as random
bytes give), most squared distances are 0 or +inf and tie, and every query would scan a large part
of the scene: N^2 in all. So a query stops once its work (candidates examined, tree nodes stepped
through, cells looked up) reaches L = WORK_BASE + WORK_PER_NEIGHBOUR k, keeping the best k it met,
and marks its row inexact. If at most L queries stopped, a second launch searches them again without
the limit (far outliers are few: their rows stay exact); otherwise the rows stay as they are. Either
way the work is at most 2 L N. The queries of ordinary scenes stay below L (at most 3,934 at
k = 16 in the twelve scenes of docs/quality.md, where L = 4,096, and a few above it at k = 24, then
searched again), so their graphs are exact; the stopping point depends only on the inputs, so the
result is the same on every device.
"""

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

KMAX = wp.constant(32)
GRID_BITS = wp.constant(21)  # bits per axis of the Morton code
LEVELS = wp.constant(22)  # level l has cells of side 2^l quanta; level 21 is the whole cube
EMPTY = wp.constant(wp.int64(-1))  # free hash slot
BLOCK = wp.constant(8)  # sorted points per pruning box (a level-1 node)
NODE_LEVELS = wp.constant(7)  # implicit tree over the sorted points: level s nodes hold 8^s points
RING_LIMIT = wp.constant(6)  # rings searched at a point's own level before it goes on at the top level
SLACK = wp.constant(1.000001)  # box distances are compared with this relative slack for rounding
# A query's work (the candidates it examines, the tree nodes it steps through and the cells it looks
# up) is limited to WORK_BASE + WORK_PER_NEIGHBOUR k; see the module's docstring.
WORK_BASE = wp.constant(2048)
WORK_PER_NEIGHBOUR = wp.constant(128)
NO_WORK_LIMIT = wp.constant(2147483647)
INEXACT = wp.constant(wp.int64(-1))  # the reach of a query that stopped at its limit: not exact

# Knuth's multiplicative hash constant (2^64 / golden ratio).
HASH_MUL = wp.constant(wp.uint64(0x9E3779B97F4A7C15))

# Masks that spread 21 bits to every third bit of an int64 (Morton encoding).
SPREAD_0 = wp.constant(wp.int64(0x1FFFFF))
SPREAD_1 = wp.constant(wp.int64(0x1F00000000FFFF))
SPREAD_2 = wp.constant(wp.int64(0x1F0000FF0000FF))
SPREAD_3 = wp.constant(wp.int64(0x100F00F00F00F00F))
SPREAD_4 = wp.constant(wp.int64(0x10C30C30C30C30C3))
SPREAD_5 = wp.constant(wp.int64(0x1249249249249249))

# A candidate ranks by (squared distance, index) as one int64: a non-negative float's bits are ordered.
topk_keys = wp.types.vector(length=KMAX, dtype=wp.int64)
NO_KEY = wp.constant(wp.int64(0x7F8000007FFFFFFF))  # (+inf, largest index)
LOW_32 = wp.constant(wp.int64(0xFFFFFFFF))
# The seed: the 2h+1 points around i in Morton order, h = k - k/4, and the whole blocks holding them.
SEED_MAX = wp.constant(2 * (KMAX - KMAX // 4) + 2 * BLOCK)  # seed points, at most
seed_dists = wp.types.vector(length=SEED_MAX, dtype=wp.float32)
seed_slots = wp.types.vector(length=SEED_MAX, dtype=wp.int32)
# Histogram of the seed's squared distances in eighth octaves: float bits >> 20 (exponent and three
# mantissa bits) are monotonic in a non-negative float.
BINS = wp.constant(64)
BIN_SHIFT = wp.constant(20)
bin_counts = wp.types.vector(length=BINS + 1, dtype=wp.int32)
block_ints = wp.types.vector(length=BLOCK, dtype=wp.int32)
block_floats = wp.types.vector(length=BLOCK, dtype=wp.float32)


@wp.func
def _spread_bits(v: int) -> wp.int64:
    x = wp.int64(v) & SPREAD_0
    x = (x | (x << wp.int64(32))) & SPREAD_1
    x = (x | (x << wp.int64(16))) & SPREAD_2
    x = (x | (x << wp.int64(8))) & SPREAD_3
    x = (x | (x << wp.int64(4))) & SPREAD_4
    x = (x | (x << wp.int64(2))) & SPREAD_5
    return x


@wp.func
def morton_code(c: wp.vec3i) -> wp.int64:
    """Interleaves three 21-bit cell coordinates into a 63-bit Morton code (x in the lowest bit)."""
    return _spread_bits(c[0]) | (_spread_bits(c[1]) << wp.int64(1)) | (_spread_bits(c[2]) << wp.int64(2))


@wp.func
def grid_coords(p: wp.vec3, lo: wp.vec3, inv_quantum: float) -> wp.vec3i:
    """Level-0 cell of a point: its quantised position in the bounding cube, 21 bits per axis."""
    u = (p - lo) * inv_quantum
    top = float((1 << GRID_BITS) - 1)
    return wp.vec3i(int(wp.clamp(u[0], 0.0, top)), int(wp.clamp(u[1], 0.0, top)), int(wp.clamp(u[2], 0.0, top)))


@wp.func
def shared_level(a: wp.int64, b: wp.int64) -> int:
    """Finest level whose cells hold both codes: the bit length of their difference, in triples."""
    x = a ^ b
    x = x | (x >> wp.int64(1))
    x = x | (x >> wp.int64(2))
    x = x | (x >> wp.int64(4))
    x = x | (x >> wp.int64(8))
    x = x | (x >> wp.int64(16))
    x = x | (x >> wp.int64(32))
    return (wp.bit_count(x) + 2) / 3


@wp.func
def _slot_hash(key: wp.int64, mask: int) -> int:
    h = wp.uint64(key) * HASH_MUL
    return int(h >> wp.uint64(33)) & mask


@wp.func
def find_cell(keys: wp.array(dtype=wp.int64), base: int, mask: int, key: wp.int64) -> int:
    """Slot of a cell in its level's hash table (linear probing), or -1 if the cell is empty."""
    slot = _slot_hash(key, mask)
    while True:  # ends: a table is at most half full, so an EMPTY slot lies within its size
        stored = keys[base + slot]
        if stored == key:
            return base + slot
        if stored == EMPTY:
            return -1
        slot = (slot + 1) & mask
    return -1


@wp.func
def _gap(u: float, cell: int, offset: int, side: float, margin: float) -> float:
    """Lower bound on the distance along one axis from coordinate u (in `cell`) to the points of cell
    + offset. Points outside the cube are clamped into its boundary cells, which therefore reach to
    infinity outwards: only the face towards u counts, and u itself may lie outside its cell."""
    g = float(0.0)
    if offset > 0:
        g = float(cell + offset) * side - u
    elif offset < 0:
        g = u - float(cell + offset + 1) * side
    return wp.max(g - margin, 0.0)


@wp.func
def _ring_gap(u: float, cell: int, ring: int, side: float, cells_per_axis: int) -> float:
    """Distance along one axis from u to the cells `ring` steps away (either way), inf if none exist."""
    g = float(wp.inf)
    if cell + ring < cells_per_axis:
        g = float(cell + ring) * side - u
    if cell - ring >= 0:
        g = wp.min(g, u - float(cell - ring + 1) * side)
    return g


@wp.func
def squared_distance(query: wp.vec3, candidate: wp.vec3) -> float:
    """|candidate - query|^2 as the query computes it: the one expression used wherever a
    candidate's key must match the query's bit for bit (``nanogs_warp.kernels.edges``)."""
    return wp.length_sq(candidate - query)


@wp.func
def tie_rank(d: float, query: int, candidate: int, n: int) -> int:
    """Rank among candidates at the same squared distance d: the candidate's index, or at d = 0 its
    index counted from the query's, (candidate - query) mod n, in [1, n)."""
    tie = candidate
    if d == 0.0:
        tie = candidate - query
        if tie < 0:
            tie += n
    return tie


@wp.func
def neighbour_key(d: float, query: int, candidate: int, n: int) -> wp.int64:
    """A candidate's rank as one int64: its squared distance's bits (a non-negative float's bits
    are ordered), then its tie rank."""
    return (wp.int64(wp.cast(d, wp.int32)) << wp.int64(32)) | wp.int64(tie_rank(d, query, candidate, n))


@wp.func
def key_index(key: wp.int64, query: int, n: int) -> int:
    """The candidate index of a key of ``query``'s row (``neighbour_key`` inverted)."""
    tie = int(key & LOW_32)
    if (key >> wp.int64(32)) == wp.int64(0):
        tie += query
        if tie >= n:
            tie -= n
    return tie


@wp.func
def tie_lower_bound(query: int, first: int, last: int, n: int) -> int:
    """Lower bound of the zero-distance tie rank over candidates with indices in [first, last]."""
    bound = int(0)
    if query < first:
        bound = first - query
    elif query > last:
        bound = first - query + n
    return bound


@wp.func
def key_distance(key: wp.int64) -> float:
    """The squared distance of a key."""
    return wp.cast(wp.int32(key >> wp.int64(32)), wp.float32)


@wp.func
def _seed_bin(d: float, bin0: int) -> int:
    """Eighth-octave bin of a seed distance, counted from bin0 (first and last bins open)."""
    return wp.clamp((wp.cast(d, wp.int32) >> BIN_SHIFT) - bin0, 0, BINS - 1)


@wp.func
def _box_distance(p: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> float:
    """Squared distance from p to the box [lo, hi]."""
    g = wp.max(wp.max(lo - p, p - hi), wp.vec3(0.0))
    return wp.length_sq(g)


@wp.kernel
def partial_boxes(
    first: int,
    points: wp.array(dtype=wp.vec3),
    parts: int,
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    bad: wp.array(dtype=int),
):
    # part t (thread first + t): the axis-aligned bounding box of points t, t + parts, t + 2 parts, ...
    # (neighbouring threads read neighbouring points) and how many of them are not finite
    t = first + wp.tid()
    part_lo = wp.vec3(wp.inf)
    part_hi = wp.vec3(-wp.inf)
    count = int(0)
    for i in range(t, points.shape[0], parts):
        p = points[i]
        if wp.isfinite(p):
            part_lo = wp.min(part_lo, p)
            part_hi = wp.max(part_hi, p)
        else:
            count += 1
    lo[t] = part_lo
    hi[t] = part_hi
    bad[t] = count


@wp.kernel
def merged_box(
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    bad: wp.array(dtype=int),
    threads: int,
    box: wp.array(dtype=wp.vec3),
    bad_total: wp.array(dtype=int),
):
    # the parts' boxes merged into box[0], box[1] (set to +inf, -inf before) and their non-finite
    # points counted in bad_total[0] (0 before): thread t merges parts t, t + threads, ..., then one
    # atomic each (a minimum, a maximum and an integer sum: the same result in any order). One launch,
    # never split over CPU threads.
    t = wp.tid()
    part_lo = wp.vec3(wp.inf)
    part_hi = wp.vec3(-wp.inf)
    count = int(0)
    for p in range(t, lo.shape[0], threads):
        part_lo = wp.min(part_lo, lo[p])
        part_hi = wp.max(part_hi, hi[p])
        count += bad[p]
    wp.atomic_min(box, 0, part_lo)
    wp.atomic_max(box, 1, part_hi)
    wp.atomic_add(bad_total, 0, count)


FLOAT32_MAX = wp.constant(wp.float64(3.4028234663852886e38))
FLOAT32_SMALLEST_NORMAL = wp.constant(wp.float64(1.1754943508222875e-38))


@wp.func
def _scaled_coordinate(x: float, scale: wp.float64) -> float:
    """x times scale (a power of two) in float64, exact, then clamped to float32's finite range and
    set to zero below its smallest normal: the same bits on every device, flushing or not."""
    v = wp.clamp(wp.float64(x) * scale, -FLOAT32_MAX, FLOAT32_MAX)
    if wp.abs(v) < FLOAT32_SMALLEST_NORMAL:
        v = wp.float64(0.0)
    return wp.float32(v)


@wp.kernel
def scaled_points(points: wp.array(dtype=wp.vec3), scale: wp.float64, out: wp.array(dtype=wp.vec3)):
    # the points times a power of two (``_scaled_coordinate``): distances scale exactly, so their order is kept
    i = wp.tid()
    p = points[i]
    out[i] = wp.vec3(_scaled_coordinate(p[0], scale), _scaled_coordinate(p[1], scale), _scaled_coordinate(p[2], scale))


@wp.kernel
def _sample_axis(points: wp.array(dtype=wp.vec3), stride: int, axis: int, out: wp.array(dtype=float)):
    # one coordinate of every stride-th point, for quantiles
    t = wp.tid()
    out[t] = points[t * stride][axis]


@wp.kernel
def morton_codes(
    first: int,
    points: wp.array(dtype=wp.vec3),
    given: wp.array(dtype=wp.int32),
    lo: wp.vec3,
    inv_quantum: float,
    codes: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
):
    # Morton code of each point's level-0 cell, paired with the point's index for sorting; the
    # points taken in the order ``given`` (empty: their own), which a stable sort keeps within a cell;
    # thread t handles row first + t
    t = first + wp.tid()
    i = t
    if given.shape[0] > 0:
        i = given[t]
    codes[t] = morton_code(grid_coords(points[i], lo, inv_quantum))
    order[t] = i


@wp.func
def _ordered_bits(x: float) -> int:
    """The top 21 of x's 32 bits, read as an order: negative floats reversed below the positive
    ones, so the result grows with x at every magnitude alike (a float's bits are its log-scale)."""
    i = wp.int64(wp.cast(x, wp.int32))
    m = i + wp.int64(2147483648)
    if i < wp.int64(0):
        m = wp.int64(-1) - i
    return int(m >> wp.int64(11))


@wp.kernel
def float_morton_codes(points: wp.array(dtype=wp.vec3), codes: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32)):
    # Morton code of each point's coordinates' float bits (``_ordered_bits``): an order that keeps
    # near points near at every scale, where the grid's cells are too coarse to tell them apart
    i = wp.tid()
    p = points[i]
    codes[i] = morton_code(wp.vec3i(_ordered_bits(p[0]), _ordered_bits(p[1]), _ordered_bits(p[2])))
    order[i] = i


@wp.kernel
def _gather_points(first: int, points: wp.array(dtype=wp.vec3), order: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.vec3)):
    # points in Morton order (thread t handles row first + t)
    i = first + wp.tid()
    out[i] = points[order[i]]


@wp.kernel
def _leaf_nodes(
    points: wp.array(dtype=wp.vec3),
    order: wp.array(dtype=wp.int32),
    node_lo: wp.array(dtype=wp.vec3),
    node_hi: wp.array(dtype=wp.vec3),
    node_first: wp.array(dtype=wp.int32),
    node_last: wp.array(dtype=wp.int32),
):
    # level-1 nodes (blocks of BLOCK consecutive sorted points): bounding box and the smallest and
    # largest original index; loop bounded by BLOCK
    b = wp.tid()
    lo = points[b * BLOCK]
    hi = lo
    first = order[b * BLOCK]
    last = first
    for j in range(b * BLOCK + 1, wp.min(b * BLOCK + BLOCK, points.shape[0])):
        lo = wp.min(lo, points[j])
        hi = wp.max(hi, points[j])
        first = wp.min(first, order[j])
        last = wp.max(last, order[j])
    node_lo[b] = lo
    node_hi[b] = hi
    node_first[b] = first
    node_last[b] = last


@wp.kernel
def _parent_nodes(
    child_base: int,
    children: int,
    parent_base: int,
    node_lo: wp.array(dtype=wp.vec3),
    node_hi: wp.array(dtype=wp.vec3),
    node_first: wp.array(dtype=wp.int32),
    node_last: wp.array(dtype=wp.int32),
):
    # node b of a level: union of its (up to) 8 children of the level below; loop bounded by 8
    b = wp.tid()
    c = child_base + 8 * b
    lo = node_lo[c]
    hi = node_hi[c]
    first = node_first[c]
    last = node_last[c]
    for t in range(1, wp.min(8, children - 8 * b)):
        lo = wp.min(lo, node_lo[c + t])
        hi = wp.max(hi, node_hi[c + t])
        first = wp.min(first, node_first[c + t])
        last = wp.max(last, node_last[c + t])
    node_lo[parent_base + b] = lo
    node_hi[parent_base + b] = hi
    node_first[parent_base + b] = first
    node_last[parent_base + b] = last


@wp.kernel
def _window_levels(
    codes: wp.array(dtype=wp.int64),
    k: int,
    window_level: wp.array(dtype=wp.int32),
    split_histogram: wp.array(dtype=wp.int32),
):
    # level of the smallest cell holding sorted points a..a+k; histogram of the levels at which
    # consecutive points part (level l has 1 + #(splits above l) cells)
    a = wp.tid()
    n = codes.shape[0]
    if a + k < n:
        window_level[a] = shared_level(codes[a], codes[a + k])
    if a + 1 < n:
        wp.atomic_add(split_histogram, shared_level(codes[a], codes[a + 1]), 1)


@wp.kernel
def _search_levels(
    first: int,
    window_level: wp.array(dtype=wp.int32),
    k: int,
    search_level: wp.array(dtype=wp.int32),
    searched: wp.array(dtype=wp.int32),
):
    # per point (from `first` on): the finest level whose own cell holds >= k+1 points (the best
    # window of k+1 consecutive points through it); searched[level] = 1 for the levels in use (the
    # same value from every thread: no atomics needed)
    i = first + wp.tid()
    n = search_level.shape[0]
    level = int(LEVELS - 1)
    for a in range(wp.max(i - k, 0), wp.min(i, n - 1 - k) + 1):  # at most k + 1 windows
        level = wp.min(level, window_level[a])
    search_level[i] = level
    searched[level] = 1


@wp.kernel
def _insert_cells(
    codes: wp.array(dtype=wp.int64),
    first_level: int,
    last_level: int,
    level_base: wp.array(dtype=wp.int32),
    level_mask: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int64),
    starts: wp.array(dtype=wp.int32),
):
    # hash-table insert of every cell (in each level built) at its first sorted point
    i = wp.tid()
    code = codes[i]
    for level in range(first_level, last_level + 1):
        mask = level_mask[level]
        if mask >= 0:
            shift = wp.int64(3 * level)
            key = code >> shift
            first = True
            if i > 0:
                first = (codes[i - 1] >> shift) != key
            if first:
                base = level_base[level]
                slot = _slot_hash(key, mask)
                while wp.atomic_cas(keys, base + slot, EMPTY, key) != EMPTY:  # at most half full: ends
                    slot = (slot + 1) & mask
                starts[base + slot] = i


@wp.kernel
def _close_cells(
    first: int,
    codes: wp.array(dtype=wp.int64),
    first_level: int,
    last_level: int,
    level_base: wp.array(dtype=wp.int32),
    level_mask: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int32),
):
    # end of every cell's range, written by its last sorted point (rows from `first` on)
    i = first + wp.tid()
    n = codes.shape[0]
    code = codes[i]
    for level in range(first_level, last_level + 1):
        mask = level_mask[level]
        if mask >= 0:
            shift = wp.int64(3 * level)
            key = code >> shift
            last = True
            if i < n - 1:
                last = (codes[i + 1] >> shift) != key
            if last:
                ends[find_cell(keys, level_base[level], mask, key)] = i + 1


@wp.kernel
def _knn_query(
    first: int,
    retry: int,
    points: wp.array(dtype=wp.vec3),
    order: wp.array(dtype=wp.int32),
    search_level: wp.array(dtype=wp.int32),
    k: int,
    lo: wp.vec3,
    inv_quantum: float,
    quantum: float,
    margin: float,
    level_base: wp.array(dtype=wp.int32),
    level_mask: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int64),
    starts: wp.array(dtype=wp.int32),
    ends: wp.array(dtype=wp.int32),
    node_base: wp.array(dtype=wp.int32),
    node_lo: wp.array(dtype=wp.vec3),
    node_hi: wp.array(dtype=wp.vec3),
    node_first: wp.array(dtype=wp.int32),
    node_last: wp.array(dtype=wp.int32),
    stopped: wp.array(dtype=wp.int32),
    stopped_total: wp.array(dtype=wp.int32),
    neighbours: wp.array2d(dtype=wp.int32),
    reach: wp.array(dtype=wp.int64),
    candidates: wp.array(dtype=wp.int32),
):
    # exact k nearest neighbours of sorted point i (from `first` on): seed, then rings of cells
    # around its own cell; the best k are kept as (distance bits << 32 | tie rank) by insertion sort.
    # Local arrays: best 256 B, seed 2 x 256 B + histogram 260 B, block filter 64 B.
    # The first launch (retry 0) stops a query at its work limit (stopped[i] = 1); the second (retry 1,
    # stopped_total the inclusive sum of stopped) searches those again without a limit when they are
    # at most that limit in number, and leaves everything as it is otherwise.
    i = first + wp.tid()
    n = points.shape[0]
    work_limit = WORK_BASE + WORK_PER_NEIGHBOUR * k
    if retry != 0:
        if stopped[i] == 0 or stopped_total[n - 1] > work_limit:
            return
        work_limit = NO_WORK_LIMIT
    p = points[i]
    row = order[i]
    level = search_level[i]
    base = level_base[level]
    mask = level_mask[level]
    cell = grid_coords(p, lo, inv_quantum)
    cx = cell[0] >> level
    cy = cell[1] >> level
    cz = cell[2] >> level
    side = quantum * float(1 << level)
    cells_per_axis = 1 << (GRID_BITS - level)
    u = p - lo
    # points outside the cube sit in its boundary cells: float32 rounding of u grows with |u|
    margin_p = margin + 2.5e-7 * wp.max(wp.max(wp.abs(u[0]), wp.abs(u[1])), wp.abs(u[2]))

    best = topk_keys()
    for t in range(k):
        best[t] = NO_KEY
    worst = NO_KEY  # best[k - 1]
    worst_d = float(wp.inf)  # its squared distance
    visited = int(0)  # candidates examined
    work = int(0)  # candidates, tree steps and cell lookups
    filled = int(0)  # keys in best (seed only)
    # the seed: blocks holding the 2h+1 points around i in Morton order (at least k besides i)
    h = k - k / 4
    seed = wp.max(wp.min(i - h, n - 1 - 2 * h), 0)
    seed_first = seed / BLOCK
    seed_last = wp.min(seed + 2 * h, n - 1) / BLOCK
    seed_begin = seed_first * BLOCK
    m = wp.min(seed_last * BLOCK + BLOCK, n) - seed_begin
    visited += m
    work += m
    # seed distances, branch-free (i itself: inf), and the smallest positive one
    sd = seed_dists()
    d_min = float(wp.inf)
    for t in range(m):
        d = squared_distance(p, points[seed_begin + t])
        d = wp.where(seed_begin + t == i, float(wp.inf), d)
        sd[t] = d
        d_min = wp.min(d_min, wp.where(d > 0.0, d, float(wp.inf)))
    # histogram in eighth octaves from d_min's (first bin takes smaller, last bin larger distances)
    hist = bin_counts()
    bin0 = wp.cast(d_min, wp.int32) >> BIN_SHIFT
    for t in range(m):
        hist[_seed_bin(sd[t], bin0)] += 1
    # tighter start threshold: the bin `top` that holds the k-th smallest seed distance; the `cum` >= k
    # seed points up to it bound the k-th neighbour, so no point of a later bin can be one
    cum = int(0)
    top = int(0)
    while top < BINS - 1:  # at most BINS - 1 steps
        cum += hist[top]
        if cum >= k:
            break
        top += 1
    if top == BINS - 1:
        cum = m  # not reached before the open last bin: keep every seed point
    # counting sort of the seed by bin (bins past `top` pooled): inserted nearest bin first, the
    # keys arrive almost sorted and the insertions shift little
    start = int(0)
    for b in range(top + 2):
        c = hist[b]
        hist[b] = start
        start += c
    perm = seed_slots()
    for t in range(m):
        b = wp.min(_seed_bin(sd[t], bin0), top + 1)
        perm[hist[b]] = t
        hist[b] += 1
    for r in range(cum):
        t = perm[r]
        key = neighbour_key(sd[t], row, order[seed_begin + t], n)
        if key < worst and seed_begin + t != i:
            s = wp.min(filled, k - 1)  # fill tracking: empty slots are never shifted
            filled += 1
            while s > 0 and best[s - 1] > key:  # at most k - 1 steps
                best[s] = best[s - 1]
                s -= 1
            best[s] = key
            worst = best[k - 1]
    worst_d = key_distance(worst)
    cj = block_ints()  # a block's points within worst_d
    cd = block_floats()
    ring = int(0)
    # Rings: at most RING_LIMIT + 1 at the search level, then ring 0 at the top level (one cell), and
    # the top level has no ring 1; a level whose cells are all visited ends the search.
    while work < work_limit:
        if ring > 0:
            # nothing unseen lies nearer than the nearest cell of this ring (inf: no cells left)
            ring_gap = wp.min(wp.min(_ring_gap(u[0], cx, ring, side, cells_per_axis),
                                       _ring_gap(u[1], cy, ring, side, cells_per_axis)),
                                _ring_gap(u[2], cz, ring, side, cells_per_axis))
            if ring_gap == wp.inf:
                break
            gap = ring_gap - margin_p
            if gap > 0.0 and gap * gap > worst_d:
                break
            if ring > RING_LIMIT:  # go on at the top level: one cell, every point (each met once more at most)
                level = LEVELS - 1
                cx = 0
                cy = 0
                cz = 0
                side = float(wp.inf)  # never used: the top level has only ring 0, whose gaps are 0
                cells_per_axis = 1
                ring = 0
        r = ring  # the ring's half-width in cells
        for dx in range(-r, r + 1):
            x = cx + dx
            gx = _gap(u[0], cx, dx, side, margin_p)
            gx = gx * gx
            if x < 0 or x >= cells_per_axis or gx > worst_d:
                continue
            for dy in range(-r, r + 1):
                y = cy + dy
                gy = _gap(u[1], cy, dy, side, margin_p)
                gy = gx + gy * gy
                if y < 0 or y >= cells_per_axis or gy > worst_d:
                    continue
                # inside the ring's shell only the two z faces remain unless x or y is on the shell
                step = 2 * r
                if step == 0 or wp.abs(dx) == r or wp.abs(dy) == r:
                    step = 1
                for dz in range(-r, r + 1, step):
                    z = cz + dz
                    gz = _gap(u[2], cz, dz, side, margin_p)
                    if z < 0 or z >= cells_per_axis or gy + gz * gz > worst_d or work >= work_limit:
                        continue
                    begin = int(0)  # the top level's one cell holds every point
                    end = n
                    if level < LEVELS - 1:
                        work += 1
                        slot = find_cell(keys, base, mask, morton_code(wp.vec3i(x, y, z)))
                        if slot < 0:
                            continue
                        begin = starts[slot]
                        end = ends[slot]
                    # The cell's sorted range through the implicit tree: at each position the
                    # largest aligned node inside the range (a level-1 node, a block, may stick
                    # out); pruned nodes are skipped whole, others entered, blocks filtered. Each
                    # step moves on or enters a smaller node: at most NODE_LEVELS steps per block.
                    q = begin
                    top_cap = wp.where(end - begin >= 64, int(NODE_LEVELS), 1)  # small cells: blocks only
                    cap = top_cap
                    while q < end and work < work_limit:
                        work += 1
                        level_s = int(1)
                        size = int(BLOCK)
                        while level_s < cap and (q & (8 * size - 1)) == 0 and q + 8 * size <= end:
                            level_s += 1
                            size *= 8
                        node_start = q - (q & (size - 1))
                        b = q / size
                        nd = b  # level 1 comes first in the node arrays
                        if level_s > 1:
                            nd += node_base[level_s]
                        skip = bool(False)
                        if level_s == 1 and b >= seed_first and b <= seed_last:
                            skip = True  # scanned with the seed
                        if not skip:
                            box_d = _box_distance(p, node_lo[nd], node_hi[nd])
                            if box_d > worst_d * SLACK:
                                skip = True
                            elif worst_d == 0.0:  # ties at distance 0 rank by index from the query
                                bound = tie_lower_bound(row, node_first[nd], node_last[nd], n)
                                skip = wp.int64(bound) > (worst & LOW_32)
                            elif box_d == wp.inf:  # so is every distance in it (worst_d too): they rank by index
                                skip = wp.int64(node_first[nd]) > (worst & LOW_32)
                        if skip or level_s == 1:
                            if not skip:
                                j = wp.max(begin, node_start)
                                block_end = wp.min(end, node_start + BLOCK)
                                visited += block_end - j
                                work += block_end - j
                                # branch-free filter of the block, then insertion of the few kept
                                nc = int(0)
                                while j < block_end:  # at most BLOCK steps
                                    d = squared_distance(p, points[j])
                                    cj[nc] = j
                                    cd[nc] = d
                                    nc += wp.where(d <= worst_d and j != i, 1, 0)
                                    j += 1
                                for c in range(nc):
                                    key = neighbour_key(cd[c], row, order[cj[c]], n)
                                    if key < worst:
                                        t = k - 1
                                        while t > 0 and best[t - 1] > key:  # at most k - 1 steps
                                            t -= 1
                                        if t == 0 or best[t - 1] != key:  # the top level meets points again
                                            s = k - 1
                                            while s > t:  # at most k - 1 steps
                                                best[s] = best[s - 1]
                                                s -= 1
                                            best[t] = key
                                            worst = best[k - 1]
                                            worst_d = key_distance(worst)
                            q = node_start + size
                            cap = top_cap
                        else:
                            cap = level_s - 1  # enter the node: its first child next
        ring += 1

    for t in range(k):
        neighbours[row, t] = wp.int32(key_index(best[t], row, n))
    exact = work < work_limit
    stopped[i] = wp.where(exact, 0, 1)
    if reach.shape[0] > 0:
        reach[row] = wp.where(exact, best[k - 1], INEXACT)
    if candidates.shape[0] > 0:
        candidates[row] = visited
