"""Unique undirected edges of a directed k-nearest-neighbour graph.

Each directed edge (i, j) becomes the int64 key min(i, j) * n + max(i, j); after a radix sort of the
keys, the first key of every run is a unique edge and a prefix sum gives its output position.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _edge_keys(
    neighbours: wp.array2d(dtype=wp.int32), keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32)
):
    # undirected key min * n + max of the directed edge (i, neighbours[i, t])
    i, t = wp.tid()
    n = wp.int64(neighbours.shape[0])
    j = neighbours[i, t]
    e = i * neighbours.shape[1] + t
    keys[e] = wp.int64(wp.min(i, j)) * n + wp.int64(wp.max(i, j))
    values[e] = 0  # unused: the sort carries values along


@wp.kernel
def _mark_unique(keys: wp.array(dtype=wp.int64), first: wp.array(dtype=wp.int32)):
    # 1 where a sorted key starts a run of equal keys
    e = wp.tid()
    starts_run = int(1)
    if e > 0:
        if keys[e] == keys[e - 1]:
            starts_run = 0
    first[e] = starts_run


@wp.kernel
def _compact_edges(
    keys: wp.array(dtype=wp.int64),
    first: wp.array(dtype=wp.int32),
    position: wp.array(dtype=wp.int32),
    n: wp.int64,
    i_out: wp.array(dtype=wp.int32),
    j_out: wp.array(dtype=wp.int32),
):
    # unique keys to (i, j) pairs at their inclusive-scan position - 1
    e = wp.tid()
    if first[e] == 1:
        key = keys[e]
        slot = position[e] - 1
        i_out[slot] = wp.int32(key // n)
        j_out[slot] = wp.int32(key % n)
