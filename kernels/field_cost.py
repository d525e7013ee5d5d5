"""Field cost: how much the emitted field changes when a pair becomes the merged splat that the merge
operator actually produces (``mpmm_merged`` / ``coverage_merged``: one device function for the cost
and the merge, so the cost always scores the merge that happens).

A splat k emits a_k c_k(d) G_k(x): opacity a_k, SH colour c_k in view direction d and a peak-one
Gaussian G_k. Seen along an axis of the merged splat, each G_k is the peak-one 2D Gaussian of its
covariance projected onto the plane of the other two axes, as a rasteriser draws it
(``kernels/field.py``). The cost is the squared L2 change of that projected field, for the opacity
and for the colour averaged over view directions, summed over the three views along the merged
splat's axes (face-on and two edge-on: a strand merged into a flat patch is invisible face-on and
plain edge-on):

    C = lambda_geo  sum_v int (T_v - a_m G_m)^2 dA
      + lambda_app  sum_v int mean_d |a_i c_i G_i + a_j c_j G_j - a_m c_m G_m|^2 dA,

from the closed-form overlaps int G_a G_b dA = 2 pi sqrt(det A det B / det(A + B)) exp(-d^T (A + B)^-1 d / 2)
and, for the term in G_i G_j below, the same for products of three or four Gaussians (G_i G_j is
itself a scaled Gaussian: ``view_overlaps``). It weighs a merge by the area and opacity it disturbs
(in scene units squared), unlike the scale-free divergences.

T_v is the pair's opacity field. Face-on (the view along the merged splat's minor axis) it is the
pair as a renderer composites it, 1 - (1 - a_i G_i)(1 - a_j G_j) = a_i G_i + a_j G_j - a_i a_j G_i G_j:
two opaque splats that overlap side by side cover their union, so merging them is cheap, where
the sum would count their overlap twice and make such merges look dear. In the two edge-on views
it stays the sum a_i G_i + a_j G_j (composited there too, the twelve-scene leave-one-scene-out of
docs/quality.md came out slightly worse in its worst scene, and the cost took longer). The colour
field keeps the sum: what a renderer shows of two overlapping colours depends on which is in front.

Both field terms vanish with the splats' area and opacity, so small or faint splats would merge
colour-blind and fine texture wash out. A colour contrast term keeps a colour change costly at
every scale:

    + lambda_c E_ref |b_i - b_j|^2,

b the base colour (0.5 + C0 f_dc per channel) clamped to [0, 1] as a rendered colour is (a raw
trainer's f_dc far beyond that range changes nothing visible), and E_ref the geometric mean over
the current splats of a^2 s_a s_b (opacity squared times the two largest scales: a splat's face-on
field energy up to pi), so the term is in the field's units and the balance does not depend on the
scene's units or on how far the merging has gone.
"""

import warp as wp

from .cost import UNMERGEABLE, finite_cost
from .field import pair_view_overlaps
from .merge import coverage_moments, coverage_shaped, coverage_terms, mpmm_merged
from .options import PORTABLE
from .portable_math import SMALLEST_NORMAL, exp64, log64, scale_by_power_of_two, sigmoid64
from .splat_math import Splats, covariance, jacobi_sweeps, jacobi_sweeps_in_lanes, sorted_frame, to_vec3d

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py

SH_C0 = wp.constant(0.28209479177387814)

# Merge operators the field cost can score (``FieldCost.operator``).
MPMM = wp.constant(0)
COVERAGE = wp.constant(1)


@wp.func
def merged_moments(
    operator_id: int, i: int, j: int, src: Splats, cov_i: wp.mat33d, cov_j: wp.mat33d, log_w_i: wp.float64, log_w_j: wp.float64
):
    """The operator's pair weight pi, merged mean and covariance (``mpmm_merged``, ``coverage_moments``)
    and, for MPMM, its opacity logit; ``log_w_i``, ``log_w_j``: the logs of the pair's coverage weights
    (``splat_terms``)."""
    if operator_id == MPMM:
        pi, mu_m, cov_m, logit_m = mpmm_merged(i, j, src)
        return pi, mu_m, cov_m, logit_m
    pi, mu_i, mu_j, mu_m, cov_m = coverage_moments(i, j, src, cov_i, cov_j, log_w_i, log_w_j)
    return pi, mu_m, cov_m, float(0.0)


@wp.func
def merged_shape(
    operator_id: int, i: int, j: int, src: Splats, values: wp.vec3d, frame: wp.mat33d, mu_m: wp.vec3d, logit_m: float,
    cov_i: wp.mat33d, cov_j: wp.mat33d, a_i: wp.float64, a_j: wp.float64, growth: float,
):  # fmt: skip
    """The operator's merged splat given its covariance's eigenvalues and frame: (eigenvalues, alpha_m)
    and the overlap sums (own, cross, comp) of the pair and the merged splat over the three views along
    its axes (``view_overlaps``); ``a_i``, ``a_j``: the pair's opacities."""
    mu_i = to_vec3d(src.means[i])
    mu_j = to_vec3d(src.means[j])
    if operator_id == MPMM:
        own, cross, comp = pair_view_overlaps(frame, values, mu_i, mu_j, mu_m, cov_i, cov_j)
        return values, sigmoid64(wp.float64(logit_m)), own, cross, comp
    return coverage_shaped(values, frame, mu_i, mu_j, mu_m, cov_i, cov_j, a_i, a_j, growth)


@wp.func
def colour_dot(features: wp.array2d(dtype=float), a: int, b: int):
    """mean_d c_a(d) . c_b(d) for SH colours c(d) = 0.5 + sum_lm f_lm Y_lm(d): the real SH basis is
    orthonormal, so the DC terms give (0.5 + C0 f_a)(0.5 + C0 f_b) and every other coefficient
    C0^2 f_a f_b (C0^2 = 1 / 4 pi)."""
    dot = wp.float64(0.0)
    for ch in range(3):
        dot += (wp.float64(0.5) + wp.float64(SH_C0) * wp.float64(features[a, ch])) * (
            wp.float64(0.5) + wp.float64(SH_C0) * wp.float64(features[b, ch])
        )
    rest = wp.float64(0.0)
    for c in range(3, features.shape[1]):
        rest += wp.float64(features[a, c]) * wp.float64(features[b, c])
    return dot + wp.float64(SH_C0) * wp.float64(SH_C0) * rest


@wp.kernel
def splat_terms(
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    features: wp.array2d(dtype=float),
    covariances: wp.array(dtype=wp.mat33d),
    colour_norms: wp.array(dtype=wp.float64),
    alphas: wp.array(dtype=wp.float64),
    log_weights: wp.array(dtype=wp.float64),
):
    """Per splat, once per pass (every edge reads two): Sigma, mean_d |c(d)|^2 (``colour_dot`` of
    the splat with itself) and ``coverage_terms`` (the opacity and the log of the coverage weight,
    as the merge computes them): the same operations an edge would do, once."""
    i = wp.tid()
    covariances[i] = covariance(rotations[i], log_scales[i])
    colour_norms[i] = colour_dot(features, i, i)
    alpha, log_weight = coverage_terms(opacities[i], log_scales[i])
    alphas[i] = alpha
    log_weights[i] = log_weight


@wp.func
def log_face_energy(logit: float, log_scale: wp.vec3):
    """log(a^2 s_a s_b), s_a s_b the two largest scales: the log of a splat's face-on field energy
    (int (a G)^2 dA = pi a^2 s_a s_b) up to log pi; opacities below 1e-300 count as 1e-300."""
    a = wp.max(sigmoid64(wp.float64(logit)), wp.float64(1e-300))
    smallest = wp.min(wp.min(log_scale[0], log_scale[1]), log_scale[2])
    two_largest = wp.float64(log_scale[0]) + wp.float64(log_scale[1]) + wp.float64(log_scale[2]) - wp.float64(smallest)
    return wp.float64(2.0) * log64(a) + two_largest


@wp.kernel
def log_energy_partials(
    first: int,
    opacities: wp.array(dtype=float),
    log_scales: wp.array(dtype=wp.vec3),
    chunk: int,
    partials: wp.array(dtype=wp.float64),
):
    """partials[c] = the sum of ``log_face_energy`` over splats [c chunk, (c + 1) chunk), in order
    (thread t handles chunk first + t): a fixed summation order, so every device gets the same bits."""
    c = first + wp.tid()
    start = c * chunk
    stop = wp.min(start + chunk, opacities.shape[0])
    total = wp.float64(0.0)
    for i in range(start, stop):
        total += log_face_energy(opacities[i], log_scales[i])
    partials[c] = total


@wp.func
def cost_unit(energy: wp.float64):
    """2^-e for the binary exponent e of ``energy`` (energy in [2^e, 2^(e+1))); 1 for an energy that
    is 0, subnormal or not finite. The field costs are reported in this unit: near 1 in a scene of
    any units, so that their float32 values neither vanish (a scene in tiny units) nor overflow (in
    huge ones), and scaled by a power of two, exactly, so that they order as the float64 costs do."""
    if not (energy >= SMALLEST_NORMAL and energy < wp.float64(wp.inf)):
        return wp.float64(1.0)
    e = wp.int32((wp.cast(energy, wp.int64) >> wp.int64(52)) & wp.int64(0x7FF)) - 1023
    return scale_by_power_of_two(wp.float64(1.0), -e)


@wp.kernel
def reference_energy(partials: wp.array(dtype=wp.float64), count: int, energy: wp.array(dtype=wp.float64)):
    """energy[0] = E_ref, the geometric mean of the splats' face-on energies: exp of the mean of the
    partial sums' total (one thread, summed in order); energy[1] = its ``cost_unit``."""
    total = wp.float64(0.0)
    for c in range(partials.shape[0]):
        total += partials[c]
    energy[0] = exp64(total / wp.float64(count))
    energy[1] = cost_unit(energy[0])


@wp.func
def base_colour_change(features: wp.array2d(dtype=float), i: int, j: int):
    """|b_i - b_j|^2 for the base colours b = clamp(0.5 + C0 f_dc, 0, 1), the colour a renderer shows
    face-on without the view-dependent terms."""
    total = wp.float64(0.0)
    for ch in range(3):
        b_i = wp.clamp(wp.float64(0.5) + wp.float64(SH_C0) * wp.float64(features[i, ch]), wp.float64(0.0), wp.float64(1.0))
        b_j = wp.clamp(wp.float64(0.5) + wp.float64(SH_C0) * wp.float64(features[j, ch]), wp.float64(0.0), wp.float64(1.0))
        total += (b_i - b_j) * (b_i - b_j)
    return total


@wp.func
def squared_change(
    a_i: wp.float64, a_j: wp.float64, a_m: wp.float64, own: wp.vec3d, cross: wp.vec3d, w_own: wp.vec3d, w_cross: wp.vec3d
):
    """sum_v int (a_i G_i + a_j G_j - a_m G_m)^2 dA expanded into the overlap sums (``view_overlaps``),
    each term weighted by w (1 for the opacity field; the colour products c_x . c_y for the colour
    field): own = (ii, jj, mm), cross = (ij, im, jm)."""
    two = wp.float64(2.0)
    return (
        a_i * a_i * w_own[0] * own[0] + a_j * a_j * w_own[1] * own[1] + a_m * a_m * w_own[2] * own[2]
        + two * (a_i * a_j * w_cross[0] * cross[0] - a_i * a_m * w_cross[1] * cross[1] - a_j * a_m * w_cross[2] * cross[2])
    )  # fmt: skip


@wp.func
def composited_terms(a_i: wp.float64, a_j: wp.float64, a_m: wp.float64, t: wp.vec4d):
    """What the composited pair changes in the squared opacity change: with the pair's field
    T = a_i G_i + a_j G_j - a_i a_j G_i G_j, int (T - a_m G_m)^2 minus the same for the sum of the
    two, from t = (int G_i^2 G_j, int G_i G_j^2, int G_i^2 G_j^2, int G_i G_j G_m) face-on:
    -2 a_i^2 a_j t0 - 2 a_i a_j^2 t1 + a_i^2 a_j^2 t2 + 2 a_m a_i a_j t3."""
    two = wp.float64(2.0)
    a_ij = a_i * a_j
    return -two * a_ij * a_i * t[0] - two * a_ij * a_j * t[1] + a_ij * a_ij * t[2] + two * a_m * a_ij * t[3]


@wp.func
def edge_moments(
    e: int, edge_i: wp.array(dtype=wp.int32), edge_j: wp.array(dtype=wp.int32), src: Splats,
    covariances: wp.array(dtype=wp.mat33d), log_weights: wp.array(dtype=wp.float64), operator_id: int,
):  # fmt: skip
    """``merged_moments`` of edge e."""
    i = int(edge_i[e])
    j = int(edge_j[e])
    return merged_moments(operator_id, i, j, src, covariances[i], covariances[j], log_weights[i], log_weights[j])


@wp.func
def edge_cost(
    e: int, diagonal: wp.vec3d, rotation: wp.mat33d, pi: wp.float64, mu_m: wp.vec3d, logit_m: float,
    edge_i: wp.array(dtype=wp.int32), edge_j: wp.array(dtype=wp.int32), src: Splats,
    covariances: wp.array(dtype=wp.mat33d), colour_norms: wp.array(dtype=wp.float64), alphas: wp.array(dtype=wp.float64),
    operator_id: int, growth: float, lambda_geo: float, lambda_app: float, lambda_contrast: float,
    energy: wp.array(dtype=wp.float64),
):  # fmt: skip
    """The field cost of edge e (module docstring) in the unit ``energy[1]`` (``cost_unit`` of
    E_ref = ``energy[0]``, from ``reference_energy``), given its merged covariance's Jacobi sweeps
    (``jacobi_sweeps``: diagonal and rotation) and ``edge_moments``; the merged colour
    c_m = pi c_i + (1 - pi) c_j is linear in the features, so every colour product follows from
    c_i.c_i, c_i.c_j, c_j.c_j."""
    i = int(edge_i[e])
    j = int(edge_j[e])
    a_i = alphas[i]
    a_j = alphas[j]
    values, frame = sorted_frame(diagonal, rotation)
    values, alpha_m, own, cross, comp = merged_shape(
        operator_id, i, j, src, values, frame, mu_m, logit_m, covariances[i], covariances[j], a_i, a_j, growth
    )
    if not (wp.isfinite(alpha_m) and wp.isfinite(values[0] * values[1] * values[2])):
        return wp.float32(UNMERGEABLE)
    one = wp.vec3d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    geo = squared_change(a_i, a_j, alpha_m, own, cross, one, one)
    geo += composited_terms(a_i, a_j, alpha_m, comp)
    # colour: the same with the direction-averaged colour products c_x . c_y (c_m = pi c_i + (1 - pi) c_j)
    pj = wp.float64(1.0) - pi
    d_ii = colour_norms[i]
    d_jj = colour_norms[j]
    d_ij = colour_dot(src.features, i, j)
    d_im = pi * d_ii + pj * d_ij
    d_jm = pi * d_ij + pj * d_jj
    d_mm = pi * d_im + pj * d_jm
    col = squared_change(a_i, a_j, alpha_m, own, cross, wp.vec3d(d_ii, d_jj, d_mm), wp.vec3d(d_ij, d_im, d_jm))
    total = wp.float64(lambda_geo) * wp.max(geo, wp.float64(0.0)) + wp.float64(lambda_app) * wp.max(col, wp.float64(0.0))
    total += wp.float64(lambda_contrast) * energy[0] * base_colour_change(src.features, i, j)
    return finite_cost(total * energy[1])


@wp.kernel
def field_costs(
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    src: Splats,
    covariances: wp.array(dtype=wp.mat33d),
    colour_norms: wp.array(dtype=wp.float64),
    alphas: wp.array(dtype=wp.float64),
    log_weights: wp.array(dtype=wp.float64),
    operator_id: int,
    growth: float,
    lambda_geo: float,
    lambda_app: float,
    lambda_contrast: float,
    energy: wp.array(dtype=wp.float64),
    costs: wp.array(dtype=float),
):
    """``edge_cost`` of each edge (a GPU's kernel: one edge a thread)."""
    e = wp.tid()
    pi, mu_m, cov_m, logit_m = edge_moments(e, edge_i, edge_j, src, covariances, log_weights, operator_id)
    diagonal, rotation = jacobi_sweeps(cov_m)
    costs[e] = edge_cost(
        e, diagonal, rotation, pi, mu_m, logit_m, edge_i, edge_j, src, covariances, colour_norms, alphas,
        operator_id, growth, lambda_geo, lambda_app, lambda_contrast, energy,
    )  # fmt: skip


@wp.kernel
def field_costs_in_lanes(
    first: int,
    count: int,
    edge_i: wp.array(dtype=wp.int32),
    edge_j: wp.array(dtype=wp.int32),
    src: Splats,
    covariances: wp.array(dtype=wp.mat33d),
    colour_norms: wp.array(dtype=wp.float64),
    alphas: wp.array(dtype=wp.float64),
    log_weights: wp.array(dtype=wp.float64),
    operator_id: int,
    growth: float,
    lambda_geo: float,
    lambda_app: float,
    lambda_contrast: float,
    energy: wp.array(dtype=wp.float64),
    costs: wp.array(dtype=float),
):
    """``field_costs`` for the CPU: thread t scores edges 4 (first + t) to 4 (first + t) + 3 (of
    ``count``), their Jacobi sweeps side by side (``jacobi_sweeps_in_lanes``), which a CPU core
    overlaps; each edge's cost has the same bits as in ``field_costs``."""
    e0 = 4 * (first + wp.tid())
    e1 = wp.min(e0 + 1, count - 1)  # past the end: the last edge again, not written
    e2 = wp.min(e0 + 2, count - 1)
    e3 = wp.min(e0 + 3, count - 1)
    pi0, mu0, cov0, logit0 = edge_moments(e0, edge_i, edge_j, src, covariances, log_weights, operator_id)
    pi1, mu1, cov1, logit1 = edge_moments(e1, edge_i, edge_j, src, covariances, log_weights, operator_id)
    pi2, mu2, cov2, logit2 = edge_moments(e2, edge_i, edge_j, src, covariances, log_weights, operator_id)
    pi3, mu3, cov3, logit3 = edge_moments(e3, edge_i, edge_j, src, covariances, log_weights, operator_id)
    d0, r0, d1, r1, d2, r2, d3, r3 = jacobi_sweeps_in_lanes(cov0, cov1, cov2, cov3)
    costs[e0] = edge_cost(
        e0, d0, r0, pi0, mu0, logit0, edge_i, edge_j, src, covariances, colour_norms, alphas,
        operator_id, growth, lambda_geo, lambda_app, lambda_contrast, energy,
    )  # fmt: skip
    if e0 + 1 < count:
        costs[e1] = edge_cost(
            e1, d1, r1, pi1, mu1, logit1, edge_i, edge_j, src, covariances, colour_norms, alphas,
            operator_id, growth, lambda_geo, lambda_app, lambda_contrast, energy,
        )  # fmt: skip
    if e0 + 2 < count:
        costs[e2] = edge_cost(
            e2, d2, r2, pi2, mu2, logit2, edge_i, edge_j, src, covariances, colour_norms, alphas,
            operator_id, growth, lambda_geo, lambda_app, lambda_contrast, energy,
        )  # fmt: skip
    if e0 + 3 < count:
        costs[e3] = edge_cost(
            e3, d3, r3, pi3, mu3, logit3, edge_i, edge_j, src, covariances, colour_norms, alphas,
            operator_id, growth, lambda_geo, lambda_app, lambda_contrast, energy,
        )  # fmt: skip
