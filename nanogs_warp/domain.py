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
