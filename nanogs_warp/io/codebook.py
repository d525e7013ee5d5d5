"""Codebooks for SOG: a 256-entry 1-D k-means over values, and a k-means palette over rows."""

from __future__ import annotations

import numpy as np


def kmeans_1d(values: np.ndarray, size: int = 256, iterations: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(codebook (<= size,) ascending, indices uint8 shaped like ``values``): every value's
    nearest codebook entry. Exact when the values take at most ``size`` distinct values;
    otherwise Lloyd's iterations on the sorted values (prefix sums, no loops over the data) from
    the quantiles of density^(1/3), the high-resolution optimum of a 1-D quantiser, which gives
    the sparse tails more entries than plain quantiles do."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    distinct = np.unique(flat)
    if distinct.shape[0] <= size:
        book = distinct
    else:
        data = np.sort(flat)
        prefix = np.concatenate([[0.0], np.cumsum(data)])
        book = _companded_quantiles(data, size)
        for _ in range(iterations):
            cuts = np.searchsorted(data, (book[1:] + book[:-1]) / 2.0)
            starts = np.concatenate([[0], cuts])
            stops = np.concatenate([cuts, [data.shape[0]]])
            counts = stops - starts
            sums = prefix[stops] - prefix[starts]
            updated = np.where(counts > 0, sums / np.maximum(counts, 1), book)
            updated = np.unique(updated)
            if updated.shape == book.shape and np.array_equal(updated, book):
                break
            book = updated
    return book, nearest_in_sorted(book, flat).astype(np.uint8).reshape(np.shape(values))


def _companded_quantiles(data: np.ndarray, size: int, bins: int = 4096) -> np.ndarray:
    counts, edges = np.histogram(data, bins=bins)
    mass = np.cbrt(counts.astype(np.float64))
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    targets = (np.arange(size) + 0.5) / size * cdf[-1]
    return np.unique(np.interp(targets, cdf, edges))


def nearest_in_sorted(book: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of an ascending codebook for every value."""
    i = np.clip(np.searchsorted(book, x), 1, max(book.shape[0] - 1, 1))
    if book.shape[0] == 1:
        return np.zeros(x.shape, np.int64)
    left = book[i - 1]
    return np.where(np.abs(x - left) <= np.abs(book[i] - x), i - 1, i)


def kmeans_rows(rows: np.ndarray, size: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """(centroids (size, D), labels (N,)) of Lloyd's k-means over the rows, seeded with rows at
    evenly spaced positions (in the caller's order, Morton order for SOG), float32 distances."""
    x = np.ascontiguousarray(rows, dtype=np.float32)
    n = x.shape[0]
    block = max(1, (1 << 24) // size)  # rows per distance block: 64 MB of float32 distances
    centroids = x[np.linspace(0, n - 1, size).astype(np.int64)].copy()
    labels = _assign(x, centroids, block)
    for _ in range(iterations):
        counts = np.bincount(labels, minlength=size).astype(np.float64)
        sums = np.zeros((size, x.shape[1]), np.float64)
        np.add.at(sums, labels, x)
        filled = counts > 0
        centroids[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        labels = _assign(x, centroids, block)
    return centroids.astype(np.float64), labels


def _assign(x: np.ndarray, centroids: np.ndarray, block: int) -> np.ndarray:
    norms = np.einsum("ij,ij->i", centroids, centroids)
    labels = np.empty(x.shape[0], np.int64)
    for start in range(0, x.shape[0], block):
        chunk = x[start : start + block]
        labels[start : start + block] = np.argmin(norms[None, :] - 2.0 * (chunk @ centroids.T), axis=1)
    return labels
