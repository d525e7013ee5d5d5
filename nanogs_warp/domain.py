"""The numeric domain of the input: the values every stage of the simplification keeps finite.

Worked out from the arithmetic the stages do:

- Positions: any finite float32. The kNN ranks by float32 squared distances, measured in the
  scene's points scaled by a power of two when its extent is far from 1 (exact, so the neighbours
  stay the same; ``nanogs_warp.topology.measured_points``); only far outliers' distances may then
  overflow to +inf, and such candidates rank by index (``nanogs_warp.kernels.knn``). Costs and
  merges work in float64, where squares and products of float32 coordinates (up to ~1e77) stay
  finite, and merged splats may be as small as the input's log-scales allow.
- Log-scales: within [-LOG_SCALE_LIMIT, LOG_SCALE_LIMIT]. Variances are exp(2 log-scale) in float64
  and the costs take determinants (products of three variances, plus the spread of the means):
  e^(6 x 100) ~ 1e260 and e^(-600) ~ 1e-261 stay within float64's range, while exp(2 x 355)
  already overflows. Trained scenes hold log-scales of about -20 to 10.
- Opacity logits, SH coefficients and quaternion components: any finite float32 (quaternions not
  all zero). Sigmoids saturate; appearance distances are float64 sums of at most 48 squares.

Values outside it are invalid input, refused with the counts per property or dropped on request;
they are never clamped.
"""

LOG_SCALE_LIMIT = 100.0


# The rules of the domain, shared by the file readers' checks (``nanogs_warp.io.ply.check_values``)
# and ``SplatSet.from_numpy``'s; numpy arrays in, boolean arrays out (numpy is imported here only when
# a check runs: the command line's start reads LOG_SCALE_LIMIT alone).


def not_finite(values, opacity: bool = False):
    """Where ``values`` are outside the domain as numbers: NaN or infinite; for opacity logits NaN
    only (+-Inf are alpha 1 and 0, valid)."""
    import numpy as np

    return np.isnan(values) if opacity else ~np.isfinite(values)


def zero_quaternions(quaternions):
    """Which rows of (N, 4) quaternions are all zero: their norm in float64, exact for float32
    components (NaNs cast and compare quietly, as not zero)."""
    import numpy as np

    with np.errstate(all="ignore"):
        q = np.asarray(quaternions, dtype=np.float64)
        return np.einsum("ij,ij->i", q, q) == 0


def outside_log_scales(log_scales):
    """Where finite log-scales lie beyond +-LOG_SCALE_LIMIT (NaN compares false)."""
    import numpy as np

    return np.abs(log_scales) > LOG_SCALE_LIMIT


def saturate_opacity_logits(logits):
    """Opacity logits with +Inf / -Inf (alpha exactly 1 / 0) replaced by +/- the largest float32.

    The activated opacity is the same (sigmoid gives exactly 1 and 0 in float32), but the merge and
    cost kernels' log-sigmoid arithmetic stays finite: two -Inf logits would make the pair's mass
    weights 0/0. Finite logits are returned bit for bit unchanged.
    """
    import numpy as np

    infinite = np.isinf(logits)
    if not infinite.any():
        return logits
    out = np.array(logits, dtype=np.float32, copy=True)
    out[infinite] = np.copysign(np.finfo(np.float32).max, out[infinite])
    return out
