"""Adam on flat float32 parameter arrays, and the constraints that keep refined splats valid.

Adam (Kingma & Ba), one thread per parameter, with the bias corrections in the host's scalars
c1 = 1 - beta1^t and c2 = 1 - beta2^t, and a learning rate per column of the parameter's rows
(lr = scale * rates[i mod columns], e.g. SH dc and rest apart):

    m = beta1 m + (1 - beta1) g,  v = beta2 v + (1 - beta2) g^2,
    p -= lr (m / c1) / (sqrt(v / c2) + eps).
"""

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)  # the same bits on every device: portable_math.py


@wp.kernel
def adam_step(
    first: int,
    grad: wp.array(dtype=float),
    rates: wp.array(dtype=float),
    columns: int,
    scale: float,
    beta1: float,
    beta2: float,
    eps: float,
    c1: float,
    c2: float,
    m: wp.array(dtype=float),
    v: wp.array(dtype=float),
    param: wp.array(dtype=float),
):
    i = first + wp.tid()
    g = grad[i]
    mi = beta1 * m[i] + (1.0 - beta1) * g
    vi = beta2 * v[i] + (1.0 - beta2) * g * g
    m[i] = mi
    v[i] = vi
    lr = scale * rates[i - (i / columns) * columns]
    param[i] = param[i] - lr * (mi / c1) / (wp.sqrt(vi / c2) + eps)


@wp.kernel
def constrain_splats(
    first: int,
    log_scale_min: float,
    log_scale_max: float,
    logit_min: float,
    logit_max: float,
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
):
    """Unit quaternions (the identity for a zero one), log-scales and opacity logits clamped to their
    ranges."""
    i = first + wp.tid()
    q = rotations[i]
    n = wp.length(q)
    if n > 0.0:
        rotations[i] = q / n
    else:
        rotations[i] = wp.quat(0.0, 0.0, 0.0, 1.0)
    s = log_scales[i]
    log_scales[i] = wp.vec3(
        wp.clamp(s[0], log_scale_min, log_scale_max),
        wp.clamp(s[1], log_scale_min, log_scale_max),
        wp.clamp(s[2], log_scale_min, log_scale_max),
    )
    opacities[i] = wp.clamp(opacities[i], logit_min, logit_max)
