"""Transcendental functions that give the same bits on every device.

The pipeline's kernels must give the CPU and a CUDA GPU the same output, byte for byte. IEEE 754
rounds + - x / and sqrt correctly, so those agree everywhere once no compiler fuses a multiply and
an add into one FMA (every pipeline module sets ``fuse_fp: False``: LLVM's strict FP-op fusion on
the CPU, NVRTC's ``--fmad=false`` on CUDA). ``exp``, ``log``, ``pow``, ``cos`` are not correctly
rounded: the CPU's libm and CUDA's libdevice may differ in the last bit, and one flipped bit of a
cost can reorder two merges and with them every later pass. So the pipeline uses these instead:
float64 functions built only from correctly rounded operations, integer and bit operations on the
float's representation, and exact scaling by powers of two, evaluated in a fixed order.

The algorithms are FDLIBM's (Sun Microsystems, 1993; also the basis of Java's StrictMath and
of musl), which need no FMA: ``exp64`` and ``log64`` err by less than 1 ulp over the whole float64
range; ``cos_two_pi`` (for random normals) by about 1 ulp. ``tests/portable_math_reference.py``
re-implements them in numpy, operation for operation.
"""

import warp as wp

from .options import PORTABLE

wp.set_module_options(PORTABLE)

# exp: FDLIBM e_exp.c
EXP_OVERFLOW = wp.constant(wp.float64(7.09782712893383973096e02))  # above: +inf
EXP_UNDERFLOW = wp.constant(wp.float64(-7.45133219101941108420e02))  # below: 0
LN2_HI = wp.constant(wp.float64(6.93147180369123816490e-01))  # 32 significant bits: k LN2_HI is exact for |k| < 2^11
LN2_LO = wp.constant(wp.float64(1.90821492927058770002e-10))
INV_LN2 = wp.constant(wp.float64(1.44269504088896338700e00))
HALF_LN2 = wp.constant(wp.float64(0.34657359027997264))  # |x| up to this: no reduction
THREE_HALVES_LN2 = wp.constant(wp.float64(1.0397207708399179))  # |x| up to this: k = +-1
TINY_EXP = wp.constant(wp.float64(3.725290298461914e-09))  # 2^-28: exp(x) = 1 + x
EXP_P1 = wp.constant(wp.float64(1.66666666666666019037e-01))
EXP_P2 = wp.constant(wp.float64(-2.77777777770155933842e-03))
EXP_P3 = wp.constant(wp.float64(6.61375632143793436117e-05))
EXP_P4 = wp.constant(wp.float64(-1.65339022054652515390e-06))
EXP_P5 = wp.constant(wp.float64(4.13813679705723846039e-08))
TWO_M1000 = wp.constant(wp.float64(9.33263618503218878990e-302))  # 2^-1000
EXPONENT_ONE = wp.constant(wp.int64(1 << 52))  # one unit of the float64 exponent field

# log: FDLIBM e_log.c
TWO_54 = wp.constant(wp.float64(1.80143985094819840000e16))
SMALLEST_NORMAL = wp.constant(wp.float64(2.2250738585072014e-308))
LOG_LG1 = wp.constant(wp.float64(6.666666666666735130e-01))
LOG_LG2 = wp.constant(wp.float64(3.999999999940941908e-01))
LOG_LG3 = wp.constant(wp.float64(2.857142874366239149e-01))
LOG_LG4 = wp.constant(wp.float64(2.222219843214978396e-01))
LOG_LG5 = wp.constant(wp.float64(1.818357216161805012e-01))
LOG_LG6 = wp.constant(wp.float64(1.531383769920937332e-01))
LOG_LG7 = wp.constant(wp.float64(1.479819860511658591e-01))
LOW_WORD = wp.constant(wp.int64(0xFFFFFFFF))

# sin and cos on [-pi/4, pi/4]: FDLIBM k_sin.c, k_cos.c
SIN_S1 = wp.constant(wp.float64(-1.66666666666666324348e-01))
SIN_S2 = wp.constant(wp.float64(8.33333333332248946124e-03))
SIN_S3 = wp.constant(wp.float64(-1.98412698298579493134e-04))
SIN_S4 = wp.constant(wp.float64(2.75573137070700676789e-06))
SIN_S5 = wp.constant(wp.float64(-2.50507602534068634195e-08))
SIN_S6 = wp.constant(wp.float64(1.58969099521155010221e-10))
COS_C1 = wp.constant(wp.float64(4.16666666666666019037e-02))
COS_C2 = wp.constant(wp.float64(-1.38888888888741095749e-03))
COS_C3 = wp.constant(wp.float64(2.48015872894767294178e-05))
COS_C4 = wp.constant(wp.float64(-2.75573143513906633035e-07))
COS_C5 = wp.constant(wp.float64(2.08757232129817482790e-09))
COS_C6 = wp.constant(wp.float64(-1.13596475577881948265e-11))
TWO_PI64 = wp.constant(wp.float64(6.283185307179586))
RANDN_OFFSET = wp.constant(wp.float64(2.9802322387695312e-08))  # 2^-25: log's argument stays in (0, 1)

# expf in float32: FDLIBM's reduction with float32 constants (FreeBSD msun's e_expf.c), Cephes' polynomial
EXP32_OVERFLOW = wp.constant(wp.float32(88.7216796875))  # above: +inf
EXP32_UNDERFLOW = wp.constant(wp.float32(-103.97208404541016))  # below: 0
LN2_HI32 = wp.constant(wp.float32(0.693145751953125))  # 15 significant bits: k LN2_HI32 is exact for |k| < 2^9
LN2_LO32 = wp.constant(wp.float32(1.428606765330187e-06))
INV_LN2_32 = wp.constant(wp.float32(1.4426950216293335))
EXP32_P0 = wp.constant(wp.float32(1.9875691500e-4))
EXP32_P1 = wp.constant(wp.float32(1.3981999507e-3))
EXP32_P2 = wp.constant(wp.float32(8.3333337680e-3))
EXP32_P3 = wp.constant(wp.float32(4.1665795894e-2))
EXP32_P4 = wp.constant(wp.float32(1.6666665459e-1))
EXP32_P5 = wp.constant(wp.float32(5.0000001201e-1))
TWO_M100_32 = wp.constant(wp.float32(7.888609052210118e-31))  # 2^-100


@wp.func
def scale_by_power_of_two(y: wp.float64, k: int):
    """y 2^k for y in [0.5, 2) and k in [-1075, 1024], exact unless the result is subnormal (then
    one rounding): k added to the exponent field."""
    if k >= -1021:
        return wp.cast(wp.cast(y, wp.int64) + wp.int64(k) * EXPONENT_ONE, wp.float64)
    return wp.cast(wp.cast(y, wp.int64) + wp.int64(k + 1000) * EXPONENT_ONE, wp.float64) * TWO_M1000


@wp.func
def exp64(x: wp.float64):
    """e^x, less than 1 ulp from the exact value; +inf above 709.78, 0 below -745.13, NaN for NaN."""
    one = wp.float64(1.0)
    if not (x == x):
        return x
    if x > EXP_OVERFLOW:
        return wp.float64(wp.inf)
    if x < EXP_UNDERFLOW:
        return wp.float64(0.0)
    ax = wp.abs(x)
    if ax < TINY_EXP:
        return one + x
    # x = k ln2 + r, |r| <= ln2 / 2, r carried as hi - lo
    k = int(0)
    hi = x
    lo = wp.float64(0.0)
    if ax > HALF_LN2:
        if ax < THREE_HALVES_LN2:
            if x > wp.float64(0.0):
                k = 1
                hi = x - LN2_HI
                lo = LN2_LO
            else:
                k = -1
                hi = x + LN2_HI
                lo = -LN2_LO
        else:
            half = wp.float64(0.5)
            if x < wp.float64(0.0):
                half = wp.float64(-0.5)
            k = int(INV_LN2 * x + half)  # truncation: round to nearest
            t = wp.float64(k)
            hi = x - t * LN2_HI  # t LN2_HI is exact
            lo = t * LN2_LO
        r = hi - lo
    else:
        r = x
    # e^r = 1 + 2r / (R(r) - r), R a minimax rational on [-ln2/2, ln2/2]
    t = r * r
    c = r - t * (EXP_P1 + t * (EXP_P2 + t * (EXP_P3 + t * (EXP_P4 + t * EXP_P5))))
    if k == 0:
        return one - ((r * c) / (c - wp.float64(2.0)) - r)
    y = one - ((lo - (r * c) / (wp.float64(2.0) - c)) - hi)
    return scale_by_power_of_two(y, k)


@wp.func
def log64(x: wp.float64):
    """Natural log, less than 1 ulp from the exact value; -inf at 0, NaN below 0 or for NaN, +inf
    at +inf."""
    if not (x == x):
        return x
    if x < wp.float64(0.0):
        return wp.float64(wp.nan)
    if x == wp.float64(0.0):
        return wp.float64(-wp.inf)
    if x == wp.float64(wp.inf):
        return x
    k = int(0)
    if x < SMALLEST_NORMAL:
        k = -54
        x = x * TWO_54  # subnormal: scale up, exactly
    bits = wp.cast(x, wp.int64)
    hx = int(bits >> wp.int64(32))
    k += (hx >> 20) - 1023
    hx = hx & 0x000FFFFF
    i = (hx + 0x95F64) & 0x100000
    # x scaled by a power of two into [sqrt(2)/2, sqrt(2)): exponent 0x3ff, or 0x3fe where i is set
    x = wp.cast((wp.int64(hx | (i ^ 0x3FF00000)) << wp.int64(32)) | (bits & LOW_WORD), wp.float64)
    k += i >> 20
    f = x - wp.float64(1.0)
    dk = wp.float64(k)
    if (0x000FFFFF & (2 + hx)) < 3:  # |f| < 2^-20
        if f == wp.float64(0.0):
            if k == 0:
                return wp.float64(0.0)
            return dk * LN2_HI + dk * LN2_LO
        r = f * f * (wp.float64(0.5) - wp.float64(0.33333333333333333) * f)
        if k == 0:
            return f - r
        return dk * LN2_HI - ((r - dk * LN2_LO) - f)
    s = f / (wp.float64(2.0) + f)
    z = s * s
    w = z * z
    t1 = w * (LOG_LG2 + w * (LOG_LG4 + w * LOG_LG6))
    t2 = z * (LOG_LG1 + w * (LOG_LG3 + w * (LOG_LG5 + w * LOG_LG7)))
    r = t2 + t1
    if ((hx - 0x6147A) | (0x6B851 - hx)) > 0:
        hfsq = wp.float64(0.5) * f * f
        if k == 0:
            return f - (hfsq - s * (hfsq + r))
        return dk * LN2_HI - ((hfsq - (s * (hfsq + r) + dk * LN2_LO)) - f)
    if k == 0:
        return f - s * (f - r)
    return dk * LN2_HI - ((s * (f - r) - dk * LN2_LO) - f)


@wp.func
def pow64(x: wp.float64, y: wp.float64):
    """x^y for x >= 0 (the callers' domain): two square roots for y = 1/4, one for y = 1/2 (correctly
    rounded steps), else exp64(y log64(x)), within (|y log x| + 2) ulp; 0 for x = 0 and y > 0."""
    if y == wp.float64(0.25):
        return wp.sqrt(wp.sqrt(x))
    if y == wp.float64(0.5):
        return wp.sqrt(x)
    if x == wp.float64(0.0) and y > wp.float64(0.0):
        return wp.float64(0.0)
    return exp64(y * log64(x))


@wp.func
def sigmoid64(x: wp.float64):
    """1 / (1 + e^-x)."""
    return wp.float64(1.0) / (wp.float64(1.0) + exp64(-x))


@wp.func
def exp32(x: float):
    """e^x in float32, less than 1 ulp from the exact value; +inf above 88.72, 0 below -103.97, NaN
    for NaN: x = k ln2 + r, |r| <= ln2 / 2 (``exp64``'s reduction in float32), e^r by a degree-7
    polynomial (Cephes' expf, no division), then k added to the exponent field. The renderer's
    per-pixel exponential: the same bits on every device without paying for float64."""
    if not (x == x):
        return x
    if x > EXP32_OVERFLOW:
        return float(wp.inf)
    if x < EXP32_UNDERFLOW:
        return float(0.0)
    half = float(0.5)
    if x < float(0.0):
        half = float(-0.5)
    k = int(INV_LN2_32 * x + half)  # truncation: round to nearest
    t = float(k)
    r = (x - t * LN2_HI32) - t * LN2_LO32  # t LN2_HI32 is exact
    p = EXP32_P0 * r + EXP32_P1
    p = p * r + EXP32_P2
    p = p * r + EXP32_P3
    p = p * r + EXP32_P4
    p = p * r + EXP32_P5
    y = (p * (r * r) + r) + float(1.0)  # in [0.70, 1.42]
    if k >= -125:
        return wp.cast(wp.cast(y, wp.int32) + (k << 23), float)
    return wp.cast(wp.cast(y, wp.int32) + ((k + 100) << 23), float) * TWO_M100_32  # subnormal: one rounding


@wp.func
def log32(x: float):
    """Natural log in float32: ``log64`` rounded to float32 (the renderer takes a few per splat, not
    per pixel)."""
    return float(log64(wp.float64(x)))


@wp.func
def sigmoid32(x: float):
    """1 / (1 + e^-x) in float32."""
    return float(1.0) / (float(1.0) + exp32(-x))


@wp.func
def _sin_kernel(x: wp.float64):
    # sin x for |x| <= pi/4
    z = x * x
    v = z * x
    r = SIN_S2 + z * (SIN_S3 + z * (SIN_S4 + z * (SIN_S5 + z * SIN_S6)))
    return x + v * (SIN_S1 + z * r)


@wp.func
def _cos_kernel(x: wp.float64):
    # cos x for |x| <= pi/4
    one = wp.float64(1.0)
    z = x * x
    r = z * (COS_C1 + z * (COS_C2 + z * (COS_C3 + z * (COS_C4 + z * (COS_C5 + z * COS_C6)))))
    if wp.abs(x) < wp.float64(0.3):
        return one - (wp.float64(0.5) * z - z * r)
    qx = wp.float64(0.28125)
    if wp.abs(x) <= wp.float64(0.78125):
        # x / 4 with its low word cleared: one - qx and 0.5 z - qx are exact
        hx = int(wp.cast(wp.abs(x), wp.int64) >> wp.int64(32)) - 0x00200000
        qx = wp.cast(wp.int64(hx) << wp.int64(32), wp.float64)
    hz = wp.float64(0.5) * z - qx
    a = one - qx
    return a - (hz - z * r)


@wp.func
def cos_two_pi(u: wp.float64):
    """cos(2 pi u) for u in [0, 1], reduced exactly by the symmetries of cos (u a multiple of 2^-26
    or coarser, as random floats are), then FDLIBM's kernels on [0, pi/4]."""
    v = u
    if v > wp.float64(0.5):
        v = wp.float64(1.0) - v
    sign = wp.float64(1.0)
    if v > wp.float64(0.25):
        v = wp.float64(0.5) - v
        sign = wp.float64(-1.0)
    # v in [0, 1/4]: cos(2 pi v) = sin(2 pi (1/4 - v))
    if v > wp.float64(0.125):
        return sign * _sin_kernel(TWO_PI64 * (wp.float64(0.25) - v))
    return sign * _cos_kernel(TWO_PI64 * v)


@wp.func
def normal_from_uniforms(u1: float, u2: float):
    """A standard normal from two uniforms in [0, 1) (randf's multiples of 2^-24) by Box-Muller:
    sqrt(-2 log u) cos(2 pi u2), u = u1 + 2^-25 in (0, 1); float64 throughout."""
    u = wp.float64(u1) + RANDN_OFFSET
    return wp.sqrt(wp.float64(-2.0) * log64(u)) * cos_two_pi(wp.float64(u2))


@wp.kernel
def evaluate(function: int, x: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    """out = f(x) (or f(x, y)) for f numbered 0 exp64, 1 log64, 2 pow64, 3 sigmoid64, 4 cos_two_pi,
    5 normal_from_uniforms (x, y read as float32), 6 exp32, 7 log32, 8 sigmoid32 (x read as float32):
    tests and tools call the functions through this."""
    t = wp.tid()
    v = x[t]
    r = wp.float64(0.0)
    if function == 0:
        r = exp64(v)
    elif function == 1:
        r = log64(v)
    elif function == 2:
        r = pow64(v, y[t])
    elif function == 3:
        r = sigmoid64(v)
    elif function == 4:
        r = cos_two_pi(v)
    elif function == 6:
        r = wp.float64(exp32(wp.float32(v)))
    elif function == 7:
        r = wp.float64(log32(wp.float32(v)))
    elif function == 8:
        r = wp.float64(sigmoid32(wp.float32(v)))
    else:
        r = normal_from_uniforms(wp.float32(v), wp.float32(y[t]))
    out[t] = r
