"""Float64 numpy references for the pipeline's kernels, written from the paper's equations."""

from __future__ import annotations

import numpy as np

LOG_2PI = np.log(2.0 * np.pi)


def rotation_matrices(quat_wxyz: np.ndarray) -> np.ndarray:
    q = np.asarray(quat_wxyz, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def covariances(quat_wxyz: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    r = rotation_matrices(quat_wxyz)
    s2 = np.exp(2.0 * np.asarray(log_scales, np.float64))
    return np.einsum("nij,nj,nkj->nik", r, s2, r)


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def log_masses(opacity_logits, log_scales) -> np.ndarray:
    """log w = 3/2 log 2pi + log alpha + sum log s (NanoGS eq. 4)."""
    return 1.5 * LOG_2PI + np.log(sigmoid(opacity_logits)) + np.asarray(log_scales, np.float64).sum(-1)


def log_normal(x: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(x; mu, cov) for x of shape (..., 3) against one Gaussian."""
    d = x - mu
    sol = np.linalg.solve(cov, d.reshape(-1, 3).T).T.reshape(d.shape)
    _, logdet = np.linalg.slogdet(cov)
    return -0.5 * (d * sol).sum(-1) - 0.5 * logdet - 1.5 * LOG_2PI


def mpmm(s: dict, i: int, j: int) -> dict:
    """Mass-preserving moment matching of rows i and j (NanoGS eq. 6-9), float64."""
    lw = log_masses(s["opacities"][[i, j]], s["log_scales"][[i, j]])
    pi = 1.0 / (1.0 + np.exp(lw[1] - lw[0]))
    mu = s["means"][[i, j]].astype(np.float64)
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    mu_m = pi * mu[0] + (1 - pi) * mu[1]
    d = mu - mu_m
    cov_m = pi * (cov[0] + np.outer(d[0], d[0])) + (1 - pi) * (cov[1] + np.outer(d[1], d[1]))
    a = sigmoid(s["opacities"][[i, j]])
    alpha_m = 1 - (1 - a[0]) * (1 - a[1])
    out = {
        "mean": mu_m,
        "cov": cov_m,
        "alpha": alpha_m,
        "features": pi * s["features"][i].astype(np.float64) + (1 - pi) * s["features"][j],
        "pi": pi,
    }
    if s.get("extras") is not None:
        out["extras"] = pi * s["extras"][i].astype(np.float64) + (1 - pi) * s["extras"][j]
    return out


def idivergence(s: dict, i: int, j: int, samples: np.ndarray) -> float:
    """Monte Carlo I(p~_ij || q_m) with the given common samples (z0, z1, z2, u) (Appendix A, eq. 12)."""
    m = mpmm(s, i, j)
    pi = m["pi"]
    mu = s["means"][[i, j]].astype(np.float64)
    r = rotation_matrices(s["rotations"][[i, j]])
    sc = np.exp(s["log_scales"][[i, j]].astype(np.float64))
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    total = 0.0
    for z0, z1, z2, u in np.asarray(samples, np.float64):
        k = 0 if u < pi else 1
        x = mu[k] + r[k] @ (sc[k] * np.array([z0, z1, z2]))
        mix = np.logaddexp(np.log(pi) + log_normal(x, mu[0], cov[0]), np.log1p(-pi) + log_normal(x, mu[1], cov[1]))
        total += mix - log_normal(x, m["mean"], m["cov"])
    return total / len(samples)


def appearance_distance(s: dict, i: int, j: int) -> float:
    d = s["features"][i].astype(np.float64) - s["features"][j]
    return float(d @ d)


def mse_geometry(s: dict, i: int, j: int) -> float:
    d = s["means"][i].astype(np.float64) - s["means"][j]
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    return float(d @ d + ((cov[0] - cov[1]) ** 2).sum())


def greedy_pairs(edge_i, edge_j, costs, vertex_count: int, cap: int) -> list[tuple[int, int]]:
    """Sequential greedy matching: edges by (cost, i, j), take an edge if both ends are free."""
    order = np.lexsort((edge_j, edge_i, costs))
    free = np.ones(vertex_count, bool)
    pairs = []
    for e in order:
        if len(pairs) >= cap:
            break
        i, j = int(edge_i[e]), int(edge_j[e])
        if free[i] and free[j]:
            free[i] = free[j] = False
            pairs.append((i, j))
    return pairs


def prune_keep(opacity_logits: np.ndarray, threshold: float, keep_at_least: int) -> np.ndarray:
    """Rows kept by opacity pruning, ascending (Algorithm 1, lines 3-4)."""
    alpha = (1.0 / (1.0 + np.exp(-opacity_logits.astype(np.float32)))).astype(np.float32)
    tau = min(threshold, float(np.median(alpha.astype(np.float64))))
    keep = np.flatnonzero(alpha.astype(np.float64) >= tau)
    if len(keep) < keep_at_least:
        order = np.argsort(alpha, kind="stable")
        keep = np.sort(order[len(alpha) - keep_at_least :])
    return keep
