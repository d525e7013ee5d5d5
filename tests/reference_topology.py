"""Brute-force float64 numpy references for the candidate-topology stage (nanogs_warp.topology)."""

import numpy as np


def knn_reference(means: np.ndarray, k: int, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """(N, k) indices of each point's k nearest other points, sorted by (distance, index), and their
    float64 squared distances. Brute force over all pairs, in row chunks."""
    points = np.asarray(means, dtype=np.float64)
    n = points.shape[0]
    indices = np.empty((n, k), dtype=np.int64)
    distances = np.empty((n, k), dtype=np.float64)
    columns = np.arange(n)
    for begin in range(0, n, chunk):
        rows = np.arange(begin, min(begin + chunk, n))
        d2 = ((points[rows, None, :] - points[None, :, :]) ** 2).sum(axis=2)
        d2[np.arange(rows.size), rows] = np.inf  # self excluded
        # every point tied with the k-th nearest must be ranked by index: take all up to the (k+1)-th
        part = np.argpartition(d2, k, axis=1)[:, : k + 1]
        kth = np.take_along_axis(d2, part, axis=1).max(axis=1, keepdims=True)
        for r, row in enumerate(rows):
            near = columns[d2[r] <= kth[r]]
            ranked = near[np.lexsort((near, d2[r, near]))][:k]
            indices[row] = ranked
            distances[row] = d2[r, ranked]
    return indices, distances


def edges_reference(neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (i < j, sorted by (i, j)) of a directed neighbour table."""
    n, k = neighbours.shape
    i = np.repeat(np.arange(n, dtype=np.int64), k)
    j = np.asarray(neighbours, dtype=np.int64).ravel()
    pairs = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1), axis=0)
    return pairs[:, 0].astype(np.int32), pairs[:, 1].astype(np.int32)
