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


# Every covariance keeps each eigenvalue at least RIDGE times its trace (kernels/splat_math.py): a
# splat's axis variances are floored at RIDGE times their sum, a moment match adds RIDGE times its
# between-mean dispersion to every variance.
RIDGE = 1e-10


def axis_variances(log_scales: np.ndarray) -> np.ndarray:
    """max(s_k^2, RIDGE sum_j s_j^2) per row."""
    s2 = np.exp(2.0 * np.asarray(log_scales, np.float64).reshape(-1, 3))
    return np.maximum(s2, RIDGE * s2.sum(-1, keepdims=True))


def matched(pi: float, mu: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moment match of two Gaussians (rows of mu, cov) with weights pi, 1 - pi; the dispersion floor."""
    mu_m = pi * mu[0] + (1 - pi) * mu[1]
    d = mu - mu_m
    cov_m = pi * (cov[0] + np.outer(d[0], d[0])) + (1 - pi) * (cov[1] + np.outer(d[1], d[1]))
    return mu_m, cov_m + RIDGE * (pi * d[0] @ d[0] + (1 - pi) * d[1] @ d[1]) * np.eye(3)


def covariances(quat_wxyz: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    r = rotation_matrices(quat_wxyz)
    return np.einsum("nij,nj,nkj->nik", r, axis_variances(log_scales), r)


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


# Merged opacities stay at or below 254/255, the largest 8-bit alpha that is not an infinite logit.
MERGED_ALPHA_MAX = 254.0 / 255.0


def mpmm(s: dict, i: int, j: int) -> dict:
    """Mass-preserving moment matching of rows i and j (NanoGS eq. 6-9), float64."""
    lw = log_masses(s["opacities"][[i, j]], s["log_scales"][[i, j]])
    pi = 1.0 / (1.0 + np.exp(lw[1] - lw[0]))
    mu = s["means"][[i, j]].astype(np.float64)
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    mu_m, cov_m = matched(pi, mu, cov)
    a = sigmoid(s["opacities"][[i, j]])
    alpha_m = min(1 - (1 - a[0]) * (1 - a[1]), MERGED_ALPHA_MAX)
    out = {
        "mean": mu_m,
        "cov": cov_m,
        "alpha": alpha_m,
        "features": pi * s["features"][i].astype(np.float64) + (1 - pi) * s["features"][j],
        "pi": pi,
    }
    if s.get("extras") is not None:
        out["extras"] = pi * s["extras"][i].astype(np.float64) + (1 - pi) * s["extras"][j]
    if s.get("integer_extras") is not None:
        out["integer_extras"] = heavier_values(s["integer_extras"], i, j, pi)
    return out


def _weighted_pair(s: dict, i: int, j: int, log_w: np.ndarray) -> dict:
    """Moment match of rows i and j with weights exp(log_w) (2,), float64: pi, mean, cov,
    features, extras."""
    pi = 1.0 / (1.0 + np.exp(log_w[1] - log_w[0]))
    mu = s["means"][[i, j]].astype(np.float64)
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    mu_m, cov_m = matched(pi, mu, cov)
    out = {
        "pi": pi,
        "mean": mu_m,
        "cov": cov_m,
        "features": pi * s["features"][i].astype(np.float64) + (1 - pi) * s["features"][j],
    }
    if s.get("extras") is not None:
        out["extras"] = pi * s["extras"][i].astype(np.float64) + (1 - pi) * s["extras"][j]
    if s.get("integer_extras") is not None:
        out["integer_extras"] = heavier_values(s["integer_extras"], i, j, pi)
    return out


def heavier_values(values: np.ndarray, i: int, j: int, pi: float) -> np.ndarray:
    """Integer properties of a merge: the row of the heavier splat (weight pi of i against 1 - pi
    of j), i's on a tie; never an average."""
    return values[i] if pi >= 0.5 else values[j]


def area_proxy(log_scales) -> np.ndarray:
    """s0 s1 + s0 s2 + s1 s2 per row."""
    sc = np.exp(np.asarray(log_scales, np.float64).reshape(-1, 3))
    return sc[:, 0] * sc[:, 1] + sc[:, 0] * sc[:, 2] + sc[:, 1] * sc[:, 2]


def footprint(log_scales) -> np.ndarray:
    """Product of the two largest scales per row (the face-on footprint)."""
    sc = np.sort(np.exp(np.asarray(log_scales, np.float64).reshape(-1, 3)), axis=1)
    return sc[:, 1] * sc[:, 2]


def area_merge(s: dict, i: int, j: int) -> dict:
    """The area operator, float64: weights w = alpha (s0 s1 + s0 s2 + s1 s2); weighted moments,
    features, extras; alpha_m = (w_i + w_j) / area(Sigma_m), clamped to 1. Also returns ``mass``
    (w_i + w_j) and ``alpha_unclamped``."""
    rows = [i, j]
    w = sigmoid(s["opacities"][rows]) * area_proxy(s["log_scales"][rows])
    out = _weighted_pair(s, i, j, np.log(w))
    values = np.clip(np.linalg.eigvalsh(out["cov"]), 1e-300, None)
    sc = np.sqrt(values)
    area_m = sc[0] * sc[1] + sc[0] * sc[2] + sc[1] * sc[2]
    out["mass"] = w.sum()
    out["alpha_unclamped"] = w.sum() / area_m
    out["alpha"] = min(out["alpha_unclamped"], MERGED_ALPHA_MAX)
    return out


def view_planes(cov_m: np.ndarray) -> list[np.ndarray]:
    """The three planes seen along the axes of a merged covariance: 2 x 3 projections onto each pair
    of its eigenvectors (face-on first)."""
    _, vectors = np.linalg.eigh(cov_m)  # ascending
    c0, c1, c2 = vectors[:, 2], vectors[:, 1], vectors[:, 0]
    return [np.stack([c0, c1]), np.stack([c0, c2]), np.stack([c1, c2])]


def gaussian_overlap_2d(mu_a, a, mu_b, b) -> float:
    """int G_a G_b dA of two peak-one 2D Gaussians (closed form: a product of Gaussians)."""
    s = a + b
    d = mu_a - mu_b
    return float(2 * np.pi * np.sqrt(np.linalg.det(a) * np.linalg.det(b) / np.linalg.det(s)) * np.exp(-0.5 * d @ np.linalg.solve(s, d)))


def gaussian_product_2d(powers, mus, covs) -> float:
    """int prod_k G_k^(n_k) dA of peak-one 2D Gaussians (closed form: their product is a Gaussian),
    0 when a Gaussian with a nonzero power is degenerate."""
    lam = np.zeros((2, 2))
    b = np.zeros(2)
    k = 0.0
    for n, mu, c in zip(powers, mus, covs):
        if n == 0:
            continue
        if np.linalg.det(c) <= 0:
            return 0.0
        p = np.linalg.inv(c)
        lam += n * p
        b += n * p @ mu
        k += n * mu @ p @ mu
    return float(2 * np.pi / np.sqrt(np.linalg.det(lam)) * np.exp(min(-0.5 * (k - b @ np.linalg.solve(lam, b)), 0.0)))


def quadrature_product_2d(powers, mus, covs, points: int = 801) -> float:
    """``gaussian_product_2d`` by brute-force quadrature on a grid (for checking the closed form)."""
    reach = 7.0 * np.sqrt(max(np.linalg.eigvalsh(c).max() for c in covs))
    centre = np.mean(mus, axis=0)
    t = np.linspace(-reach, reach, points)
    gx, gy = np.meshgrid(t + centre[0], t + centre[1], indexing="ij")
    pts = np.stack([gx, gy], -1)
    total = np.ones(gx.shape)
    for n, mu, c in zip(powers, mus, covs):
        d = pts - mu
        total = total * np.exp(-0.5 * np.einsum("...i,ij,...j->...", d, np.linalg.inv(c), d)) ** n
    return float(total.sum() * (t[1] - t[0]) ** 2)


def fitted_opacity(alpha_pair, mus, covs, mu_m, cov_m) -> float:
    """The opacity a minimising sum over the three views of int (a_i G_i + a_j G_j - a G_m)^2 dA."""
    num = den = 0.0
    for plane in view_planes(cov_m):
        pm, cm = plane @ mu_m, plane @ cov_m @ plane.T
        num += sum(a * gaussian_overlap_2d(plane @ mu, plane @ c @ plane.T, pm, cm) for a, mu, c in zip(alpha_pair, mus, covs))
        den += gaussian_overlap_2d(pm, cm, pm, cm)
    return num / den


def coverage_merge(s: dict, i: int, j: int, growth: float = 0.5) -> dict:
    """The coverage operator, float64: weights w = alpha s_a s_b; weighted moments, features,
    extras; with (c0, c1) the two major axes of Sigma_m, coverage C = sum_k alpha_k sqrt(det(P
    Sigma_k P^T)), P = [c0 c1]^T, and ratio r = C / (s0 s1)_m; where r > 1 the variances along c0, c1
    grow by r^growth; alpha_m = the opacity fitted over three views (``fitted_opacity``), at most
    254/255. Also returns ``coverage``, ``ratio`` (before growth) and ``alpha_fit`` (uncapped)."""
    rows = [i, j]
    alpha = sigmoid(s["opacities"][rows])
    out = _weighted_pair(s, i, j, np.log(alpha * footprint(s["log_scales"][rows])))
    values, vectors = np.linalg.eigh(out["cov"])  # ascending
    c0, c1 = vectors[:, 2], vectors[:, 1]
    plane = np.stack([c0, c1])
    cov = covariances(s["rotations"][rows], s["log_scales"][rows])
    coverage = sum(a * np.sqrt(max(np.linalg.det(plane @ c @ plane.T), 0.0)) for a, c in zip(alpha, cov))
    ratio = coverage / np.sqrt(values[2] * values[1])
    grow = ratio**growth if ratio > 1 else 1.0
    values = values * np.array([1.0, grow, grow])
    out["cov"] = vectors @ np.diag(values) @ vectors.T
    out["coverage"] = coverage
    out["ratio"] = ratio
    mus = s["means"][rows].astype(np.float64)
    out["alpha_fit"] = fitted_opacity(alpha, mus, cov, out["mean"], out["cov"])
    out["alpha"] = min(out["alpha_fit"], MERGED_ALPHA_MAX)
    return out


def runnalls_cost(s: dict, i: int, j: int, lambda_geo=1.0, lambda_app=1.0, mass_exponent=0.25) -> float:
    """W^gamma [lambda_geo B + lambda_app 4 pi (1 - pi) ||f_i - f_j||^2], w = alpha x area proxy,
    B = 1/2 [log det Sigma_m - pi log det Sigma_i - (1 - pi) log det Sigma_j] (Runnalls' bound)."""
    rows = [i, j]
    w = sigmoid(s["opacities"][rows]) * area_proxy(s["log_scales"][rows])
    m = _weighted_pair(s, i, j, np.log(w))
    pi = m["pi"]
    log_det = np.log(axis_variances(s["log_scales"][rows])).sum(-1)
    bound = max(0.5 * (np.linalg.slogdet(m["cov"])[1] - pi * log_det[0] - (1 - pi) * log_det[1]), 0.0)
    app = 4.0 * pi * (1 - pi) * appearance_distance(s, i, j)
    return float(w.sum() ** mass_exponent * (lambda_geo * bound + lambda_app * app))


def idivergence(s: dict, i: int, j: int, samples: np.ndarray) -> float:
    """Monte Carlo I(p~_ij || q_m) with the given common normals z (rows (z0, z1, z2); Appendix A,
    eq. 12): E_p~[log p~] from both components at the same z, weighted pi and 1 - pi, and
    E_p~[-log q_m] as q_m's entropy (q_m has p~'s mean and covariance); |z|^2 in each component's
    own density at its own point replaced by its mean 3 (the control variate ``+ (|z|^2 - 3) / 2``)."""
    m = mpmm(s, i, j)
    pi = m["pi"]
    mu = s["means"][[i, j]].astype(np.float64)
    r = rotation_matrices(s["rotations"][[i, j]])
    sc = np.sqrt(axis_variances(s["log_scales"][[i, j]]))
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    weights = (pi, 1.0 - pi)
    total = 0.0
    for z in np.asarray(samples, np.float64)[:, :3]:
        for k in (0, 1):
            x = mu[k] + r[k] @ (sc[k] * z)
            mix = np.logaddexp(np.log(pi) + log_normal(x, mu[0], cov[0]), np.log1p(-pi) + log_normal(x, mu[1], cov[1]))
            total += weights[k] * mix
        total += 0.5 * (z @ z - 3.0)
    entropy = 0.5 * (3 * np.log(2 * np.pi) + np.linalg.slogdet(m["cov"])[1] + 3)
    return total / len(samples) + entropy


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
    """Rows kept by opacity pruning, ascending (Algorithm 1, lines 3-4). Alpha as the kernel computes
    it: the float64 sigmoid of ``kernels/portable_math.py`` (the same bits on every device), rounded
    to float32."""
    from portable_math_reference import sigmoid64

    alpha = sigmoid64(opacity_logits.astype(np.float32).astype(np.float64)).astype(np.float32)
    tau = min(threshold, float(np.median(alpha.astype(np.float64))))
    keep = np.flatnonzero(alpha.astype(np.float64) >= tau)
    if len(keep) < keep_at_least:
        order = np.argsort(alpha, kind="stable")
        keep = np.sort(order[len(alpha) - keep_at_least :])
    return keep


def reference_energy(s: dict) -> float:
    """E_ref of the field cost's colour contrast term, float64: the geometric mean over the splats of
    a^2 s_a s_b, s_a s_b the two largest scales."""
    a = np.maximum(sigmoid(s["opacities"]), 1e-300)
    log_scales = np.sort(s["log_scales"].astype(np.float64), axis=1)
    return float(np.exp(np.mean(2 * np.log(a) + log_scales[:, 1] + log_scales[:, 2])))


def base_colour_change(s: dict, i: int, j: int) -> float:
    """|b_i - b_j|^2, b = clamp(0.5 + C0 f_dc, 0, 1) per channel."""
    b = np.clip(0.5 + 0.28209479177387814 * s["features"][[i, j], :3].astype(np.float64), 0.0, 1.0)
    return float(((b[0] - b[1]) ** 2).sum())


def field_cost(s: dict, i: int, j: int, merged: dict, lambda_geo=1.0, lambda_app=1.0, lambda_contrast=0.0, energy=None) -> float:
    """The field cost, float64: the squared L2 change of the opacity field and of the
    direction-averaged SH colour field, seen along each of the three axes of the merged splat
    ``merged`` (mean, cov, alpha, pi), every Gaussian projected onto the plane of the other two as a
    peak-one 2D Gaussian, summed over the three views; face-on, the opacity field of the pair is
    composited, a_i G_i + a_j G_j - a_i a_j G_i G_j, in the two other views and for the colour it is
    the sum. Each integral of a product of Gaussians in closed form (``gaussian_overlap_2d``,
    ``gaussian_product_2d``, both checked against quadrature in the tests)."""
    cov = covariances(s["rotations"][[i, j]], s["log_scales"][[i, j]])
    mus = [s["means"][i].astype(np.float64), s["means"][j].astype(np.float64), merged["mean"]]
    a = list(sigmoid(s["opacities"][[i, j]])) + [merged["alpha"]]
    f = s["features"].astype(np.float64)
    fm = merged["pi"] * f[i] + (1 - merged["pi"]) * f[j]
    feats = [f[i], f[j], fm]
    sign = [1.0, 1.0, -1.0]

    def dot(fa, fb):
        return ((0.5 + 0.28209479177387814 * fa[:3]) * (0.5 + 0.28209479177387814 * fb[:3])).sum() + (fa[3:] * fb[3:]).sum() / (4 * np.pi)

    geo = col = 0.0
    for view, plane in enumerate(view_planes(merged["cov"])):
        covs = [plane @ c @ plane.T for c in (cov[0], cov[1], merged["cov"])]
        centres = [plane @ m for m in mus]
        for x in range(3):
            for y in range(3):
                o = sign[x] * sign[y] * a[x] * a[y] * gaussian_overlap_2d(centres[x], covs[x], centres[y], covs[y])
                geo += o
                col += o * dot(feats[x], feats[y])
        if view > 0:
            continue
        # face-on, the opacity field of the pair composited, a_i G_i + a_j G_j - a_i a_j G_i G_j: the terms in G_i G_j
        a_i, a_j, a_m = a

        def product(*powers):
            return gaussian_product_2d(powers, centres, covs)

        geo += (-2 * a_i * a_i * a_j * product(2, 1, 0) - 2 * a_i * a_j * a_j * product(1, 2, 0)
                + (a_i * a_j) ** 2 * product(2, 2, 0) + 2 * a_m * a_i * a_j * product(1, 1, 1))  # fmt: skip
    contrast = 0.0 if lambda_contrast == 0.0 else lambda_contrast * (reference_energy(s) if energy is None else energy) * base_colour_change(s, i, j)
    return lambda_geo * max(geo, 0.0) + lambda_app * max(col, 0.0) + contrast


def quadrature_overlap_2d(mu_a, a, mu_b, b, points: int = 801) -> float:
    """int G_a G_b dA by brute-force quadrature on a grid around both (for checking the closed form)."""
    reach = 7.0 * np.sqrt(max(np.linalg.eigvalsh(a).max(), np.linalg.eigvalsh(b).max()))
    centre = 0.5 * (mu_a + mu_b)
    t = np.linspace(-reach, reach, points) + 0.0
    gx, gy = np.meshgrid(t + centre[0], t + centre[1], indexing="ij")
    pts = np.stack([gx, gy], -1)
    total = np.ones(gx.shape)
    for mu, c in ((mu_a, a), (mu_b, b)):
        d = pts - mu
        total = total * np.exp(-0.5 * np.einsum("...i,ij,...j->...", d, np.linalg.inv(c), d))
    return float(total.sum() * (t[1] - t[0]) ** 2)
