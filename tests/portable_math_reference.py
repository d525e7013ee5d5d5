"""numpy re-implementation of ``kernels/portable_math.py``, operation for operation and in the same
order: numpy's float64 + - x / and sqrt round correctly and never fuse, so on a device that does
what the kernels' source says (no contraction) the kernel and this give the same bits."""

from __future__ import annotations

import numpy as np

EXP_OVERFLOW = 7.09782712893383973096e02
EXP_UNDERFLOW = -7.45133219101941108420e02
LN2_HI = 6.93147180369123816490e-01
LN2_LO = 1.90821492927058770002e-10
INV_LN2 = 1.44269504088896338700e00
HALF_LN2 = 0.34657359027997264
THREE_HALVES_LN2 = 1.0397207708399179
TINY_EXP = 3.725290298461914e-09
P1, P2, P3, P4, P5 = (
    1.66666666666666019037e-01,
    -2.77777777770155933842e-03,
    6.61375632143793436117e-05,
    -1.65339022054652515390e-06,
    4.13813679705723846039e-08,
)
TWO_M1000 = 9.33263618503218878990e-302
TWO_54 = 1.80143985094819840000e16
SMALLEST_NORMAL = 2.2250738585072014e-308
LG1, LG2, LG3, LG4, LG5, LG6, LG7 = (
    6.666666666666735130e-01,
    3.999999999940941908e-01,
    2.857142874366239149e-01,
    2.222219843214978396e-01,
    1.818357216161805012e-01,
    1.531383769920937332e-01,
    1.479819860511658591e-01,
)
S1, S2, S3, S4, S5, S6 = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
C1, C2, C3, C4, C5, C6 = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)
TWO_PI = 6.283185307179586
RANDN_OFFSET = 2.0**-25


def _f(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _bits(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.float64).view(np.int64)


def _float(bits: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(bits, dtype=np.int64).view(np.float64)


def scale_by_power_of_two(y: np.ndarray, k: np.ndarray) -> np.ndarray:
    k = k.astype(np.int64)
    normal = k >= -1021
    out = np.empty_like(y)
    out[normal] = _float(_bits(y[normal]) + k[normal] * (1 << 52))
    sub = ~normal
    out[sub] = _float(_bits(y[sub]) + (k[sub] + 1000) * (1 << 52)) * TWO_M1000
    return out


def exp64(x) -> np.ndarray:
    x = _f(x).copy()
    out = np.empty_like(x)
    with np.errstate(all="ignore"):
        nan = np.isnan(x)
        over = x > EXP_OVERFLOW
        under = x < EXP_UNDERFLOW
        ax = np.abs(x)
        tiny = ~nan & ~over & ~under & (ax < TINY_EXP)
        rest = ~nan & ~over & ~under & ~tiny
        out[nan] = x[nan]
        out[over] = np.inf
        out[under] = 0.0
        out[tiny] = 1.0 + x[tiny]
        x, ax = x[rest], ax[rest]
        k = np.zeros(len(x), np.int64)
        hi = x.copy()
        lo = np.zeros_like(x)
        near = (ax > HALF_LN2) & (ax < THREE_HALVES_LN2)
        pos = near & (x > 0.0)
        neg = near & ~(x > 0.0)
        k[pos], hi[pos], lo[pos] = 1, x[pos] - LN2_HI, LN2_LO
        k[neg], hi[neg], lo[neg] = -1, x[neg] + LN2_HI, -LN2_LO
        far = (ax > HALF_LN2) & ~near
        half = np.where(x[far] < 0.0, -0.5, 0.5)
        k[far] = np.trunc(INV_LN2 * x[far] + half).astype(np.int64)
        t = k[far].astype(np.float64)
        hi[far] = x[far] - t * LN2_HI
        lo[far] = t * LN2_LO
        reduced = ax > HALF_LN2
        r = np.where(reduced, hi - lo, x)
        t = r * r
        c = r - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))))
        y = np.where(
            k == 0,
            1.0 - ((r * c) / (c - 2.0) - r),
            1.0 - ((lo - (r * c) / (2.0 - c)) - hi),
        )
        y[k != 0] = scale_by_power_of_two(y[k != 0], k[k != 0])
        out[rest] = y
    return out


def log64(x) -> np.ndarray:
    x = _f(x).copy()
    out = np.empty_like(x)
    with np.errstate(all="ignore"):
        nan = np.isnan(x)
        out[nan] = x[nan]
        negative = x < 0.0
        out[negative] = np.nan
        zero = x == 0.0
        out[zero] = -np.inf
        inf = x == np.inf
        out[inf] = np.inf
        rest = ~(nan | negative | zero | inf)
        x = x[rest]
        k = np.zeros(len(x), np.int64)
        sub = x < SMALLEST_NORMAL
        k[sub] = -54
        x[sub] = x[sub] * TWO_54
        bits = _bits(x)
        hx = (bits >> 32).astype(np.int64)
        k += (hx >> 20) - 1023
        hx = hx & 0x000FFFFF
        i = (hx + 0x95F64) & 0x100000
        x = _float(((hx | (i ^ 0x3FF00000)) << 32) | (bits & 0xFFFFFFFF))
        k += i >> 20
        f = x - 1.0
        dk = k.astype(np.float64)
        y = np.empty_like(x)
        small = (0x000FFFFF & (2 + hx)) < 3
        exact = small & (f == 0.0)
        y[exact] = np.where(k[exact] == 0, 0.0, dk[exact] * LN2_HI + dk[exact] * LN2_LO)
        near = small & ~exact
        fn, dn = f[near], dk[near]
        r = fn * fn * (0.5 - 0.33333333333333333 * fn)
        y[near] = np.where(k[near] == 0, fn - r, dn * LN2_HI - ((r - dn * LN2_LO) - fn))
        m = ~small
        f, dk, k, hx = f[m], dk[m], k[m], hx[m]
        s = f / (2.0 + f)
        z = s * s
        w = z * z
        t1 = w * (LG2 + w * (LG4 + w * LG6))
        t2 = z * (LG1 + w * (LG3 + w * (LG5 + w * LG7)))
        r = t2 + t1
        hfsq = 0.5 * f * f
        wide = ((hx - 0x6147A) | (0x6B851 - hx)) > 0
        y_wide = np.where(k == 0, f - (hfsq - s * (hfsq + r)), dk * LN2_HI - ((hfsq - (s * (hfsq + r) + dk * LN2_LO)) - f))
        y_narrow = np.where(k == 0, f - s * (f - r), dk * LN2_HI - ((s * (f - r) - dk * LN2_LO) - f))
        y[m] = np.where(wide, y_wide, y_narrow)
        out[rest] = y
    return out


def pow64(x, y) -> np.ndarray:
    x, y = np.broadcast_arrays(_f(x), _f(y))
    with np.errstate(all="ignore"):
        general = exp64(y * log64(x))
        general = np.where((x == 0.0) & (y > 0.0), 0.0, general)
        return np.where(y == 0.25, np.sqrt(np.sqrt(x)), np.where(y == 0.5, np.sqrt(x), general))


def sigmoid64(x) -> np.ndarray:
    return 1.0 / (1.0 + exp64(-_f(x)))


EXP32_OVERFLOW = np.float32(88.7216796875)
EXP32_UNDERFLOW = np.float32(-103.97208404541016)
LN2_HI32 = np.float32(0.693145751953125)
LN2_LO32 = np.float32(1.428606765330187e-06)
INV_LN2_32 = np.float32(1.4426950216293335)
EXP32_P = [np.float32(v) for v in (1.9875691500e-4, 1.3981999507e-3, 8.3333337680e-3, 4.1665795894e-2, 1.6666665459e-1, 5.0000001201e-1)]
TWO_M100_32 = np.float32(2.0**-100)


def exp32(x) -> np.ndarray:
    """``exp32``: every operation in float32, as the kernel's."""
    x = np.asarray(x, dtype=np.float32).copy()
    f = np.float32
    out = np.empty_like(x)
    with np.errstate(all="ignore"):
        nan = np.isnan(x)
        over = x > EXP32_OVERFLOW
        under = x < EXP32_UNDERFLOW
        rest = ~nan & ~over & ~under
        out[nan] = x[nan]
        out[over] = np.inf
        out[under] = 0.0
        x = x[rest]
        half = np.where(x < f(0.0), f(-0.5), f(0.5)).astype(np.float32)
        k = np.trunc(INV_LN2_32 * x + half).astype(np.int32)
        t = k.astype(np.float32)
        r = (x - t * LN2_HI32) - t * LN2_LO32
        p = EXP32_P[0] * r + EXP32_P[1]
        for c in EXP32_P[2:]:
            p = p * r + c
        y = ((p * (r * r) + r) + f(1.0)).astype(np.float32)
        bits = y.view(np.int32)
        normal = k >= -125
        y[normal] = (bits[normal] + (k[normal] << 23)).astype(np.int32).view(np.float32)
        sub = ~normal
        y[sub] = (bits[sub] + ((k[sub] + 100) << 23)).astype(np.int32).view(np.float32) * TWO_M100_32
        out[rest] = y
    return out


def log32(x) -> np.ndarray:
    return log64(np.asarray(x, dtype=np.float32).astype(np.float64)).astype(np.float32)


def sigmoid32(x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    with np.errstate(over="ignore"):
        return np.float32(1.0) / (np.float32(1.0) + exp32(-x))


def _sin_kernel(x):
    z = x * x
    v = z * x
    r = S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))
    return x + v * (S1 + z * r)


def _cos_kernel(x):
    z = x * x
    r = z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))))
    small = 1.0 - (0.5 * z - z * r)
    hx = (_bits(np.abs(x)) >> 32) - 0x00200000
    qx = np.where(np.abs(x) <= 0.78125, _float(hx << 32), 0.28125)
    large = (1.0 - qx) - ((0.5 * z - qx) - z * r)
    return np.where(np.abs(x) < 0.3, small, large)


def cos_two_pi(u) -> np.ndarray:
    v = _f(u)
    v = np.where(v > 0.5, 1.0 - v, v)
    sign = np.where(v > 0.25, -1.0, 1.0)
    v = np.where(v > 0.25, 0.5 - v, v)
    return np.where(v > 0.125, sign * _sin_kernel(TWO_PI * (0.25 - v)), sign * _cos_kernel(TWO_PI * v))


def normal_from_uniforms(u1, u2) -> np.ndarray:
    u = np.asarray(u1, np.float32).astype(np.float64) + RANDN_OFFSET
    return np.sqrt(-2.0 * log64(u)) * cos_two_pi(np.asarray(u2, np.float32).astype(np.float64))
