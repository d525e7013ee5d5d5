"""Brute-force float64 numpy references for the candidate-topology stage (nanogs_warp.topology)."""

from __future__ import annotations

import numpy as np


def knn_reference(
    means: np.ndarray, k: int, rows: np.ndarray | None = None, chunk: int = 128
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (len(rows), k) of the k nearest other points of each point in `rows` (default: all),
    sorted by (squared distance, index), and those float64 squared distances. Brute force."""
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
            ranked = near[np.lexsort((near, d2[r, near]))][:k]
            indices[begin + r] = ranked
            distances[begin + r] = d2[r, ranked]
    return indices, distances


def edges_reference(neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (i < j, sorted by (i, j)) of a directed neighbour table."""
    n, k = neighbours.shape
    i = np.repeat(np.arange(n, dtype=np.int64), k)
    j = np.asarray(neighbours, dtype=np.int64).ravel()
    pairs = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1), axis=0)
    return pairs[:, 0].astype(np.int32), pairs[:, 1].astype(np.int32)
