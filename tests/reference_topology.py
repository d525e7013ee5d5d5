"""Brute-force float64 numpy references for the candidate-topology stage (nanogs_warp.topology)."""

from __future__ import annotations

import numpy as np


def knn_reference(
    means: np.ndarray, k: int, rows: np.ndarray | None = None, chunk: int = 128
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (len(rows), k) of the k nearest other points of each point in `rows` (default: all),
    sorted by (squared distance, tie), and those float64 squared distances. Brute force. The tie is
    the index, or at distance 0 (copies of the point's position) the index counted from the
    point's own, (j - i) mod N."""
    points = np.asarray(means, dtype=np.float64)
    rows = np.arange(points.shape[0]) if rows is None else np.asarray(rows)
    indices = np.empty((rows.size, k), dtype=np.int64)
    distances = np.empty((rows.size, k), dtype=np.float64)
    for begin in range(0, rows.size, chunk):
        part = rows[begin : begin + chunk]
        d2 = ((points[part, None, :] - points[None, :, :]) ** 2).sum(axis=2)
        d2[np.arange(part.size), part] = np.inf  # self excluded
        # everything up to the (k+1)-th smallest distance, then ranked by (distance, index)
        bound = np.partition(d2, k, axis=1)[:, k : k + 1]
        for r in range(part.size):
            near = np.flatnonzero(d2[r] <= bound[r])
            tie = np.where(d2[r, near] == 0.0, (near - part[r]) % points.shape[0], near)
            ranked = near[np.lexsort((tie, d2[r, near]))][:k]
            indices[begin + r] = ranked
            distances[begin + r] = d2[r, ranked]
    return indices, distances


def edges_reference(neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (i < j) of a directed neighbour table in the canonical order: by i;
    within i, first row i's entries above i in row order, then the points above i that list i
    while row i does not list them, ascending."""
    n, k = neighbours.shape
    i = np.repeat(np.arange(n, dtype=np.int64), k)
    j = np.asarray(neighbours, dtype=np.int64).ravel()
    column = np.tile(np.arange(k, dtype=np.int64), n)
    listed = np.isin(j * n + i, i * n + j)  # row j lists i
    own = j > i  # part (a) of segment i
    foreign = (j < i) & ~listed  # part (b) of segment j
    segment = np.r_[i[own], j[foreign]]
    other = np.r_[j[own], i[foreign]]
    part = np.r_[np.zeros(own.sum(), np.int64), np.ones(foreign.sum(), np.int64)]
    secondary = np.r_[column[own], i[foreign]]
    order = np.lexsort((secondary, part, segment))
    return segment[order].astype(np.int32), other[order].astype(np.int32)