"""The portable transcendental functions (kernels/portable_math.py) that make the pipeline give the
same bits on the CPU and on CUDA:

- accuracy against numpy's float64 exp and log (and mpmath's exact values on a sample) over the
  whole float64 range, with the special values the callers rely on;
- bit for bit against ``portable_math_reference``, a numpy re-implementation in the same operation
  order: any fused multiply-add, reordering or library call in the device's build of the kernels
  changes bits here (on the CPU always, on the GPU where there is one);
- the float32 ``exp32`` (the renderer's per-pixel exponential) within 1 ulp of float32 over its
  whole range, and bit for bit against its numpy re-implementation;
- the common random samples of the idiv cost, bit for bit against a numpy re-implementation of
  Warp's PCG generator and the portable Box-Muller transform.
"""

import mpmath
import numpy as np
import portable_math_reference as ref
import pytest
import warp as wp

from nanogs_warp.kernels import cost as cost_kernels
from nanogs_warp.kernels import portable_math as pm

EXP, LOG, POW, SIGMOID, COS_TWO_PI, NORMAL, EXP32, LOG32, SIGMOID32 = range(9)


def evaluate(function, x, y=None, device="cpu"):
    x = np.ascontiguousarray(x, np.float64)
    y = np.zeros_like(x) if y is None else np.ascontiguousarray(np.broadcast_to(y, x.shape), np.float64)
    out = wp.full(len(x), np.nan, dtype=wp.float64, device=device)  # poisoned: every slot is written
    wp.launch(
        pm.evaluate, len(x),
        inputs=[function, wp.array(x, dtype=wp.float64, device=device), wp.array(y, dtype=wp.float64, device=device)],
        outputs=[out], device=device,
    )  # fmt: skip
    return out.numpy()


def ulps(a, b):
    """Distance in units in the last place between float64 arrays (equal infinities: 0)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ai, bi = a.view(np.int64).astype(object), b.view(np.int64).astype(object)
    lo = -(2**63)
    ai = np.array([lo - v if v < 0 else v for v in ai], dtype=object)
    bi = np.array([lo - v if v < 0 else v for v in bi], dtype=object)
    return np.abs(ai - bi).astype(np.float64)


def same_bits(a, b):
    return np.array_equal(np.asarray(a, np.float64).view(np.int64), np.asarray(b, np.float64).view(np.int64))


def exp_inputs(rng, n):
    return np.concatenate([
        rng.uniform(-745.13, 709.78, n),  # the whole finite range, subnormal results included
        rng.uniform(-1.5, 1.5, n),  # the reduction's branches: k = 0, k = +-1
        rng.normal(scale=1e-6, size=n // 4),
        rng.uniform(-745.14, -708.0, n // 4),  # subnormal and tiny results
        rng.uniform(700.0, 709.78, n // 4),
        rng.uniform(-40.0, 40.0, n),  # the range the pipeline uses most
    ])  # fmt: skip


def log_inputs(rng, n):
    bits = rng.integers(1, 0x7FF0000000000000, size=n, dtype=np.int64)  # every positive finite float64
    return np.concatenate([
        bits.view(np.float64),
        rng.uniform(0.5, 2.0, n),  # around 1: the small-|f| branch and both normalisations
        1.0 + rng.normal(scale=1e-7, size=n // 4),
        rng.uniform(1e-300, 1e300, n // 4),
        np.exp(rng.uniform(-700, 700, n)),
    ])  # fmt: skip


def test_exp64_within_one_ulp_of_numpy(rng):
    x = exp_inputs(rng, 200_000)
    got = evaluate(EXP, x)
    assert np.all(np.isfinite(got))
    assert ulps(got[:5000], np.exp(x[:5000])).max() <= 2
    rel = np.abs(got - np.exp(x)) / np.maximum(np.abs(np.exp(x)), np.finfo(np.float64).tiny)
    normal = np.exp(x) >= np.finfo(np.float64).tiny
    assert rel[normal].max() <= 2 * np.finfo(np.float64).eps  # 2 ulp, relative, where normal
    sub = ~normal  # subnormal results: absolute error within 2 of the smallest subnormal
    assert np.all(np.abs(got[sub] - np.exp(x[sub])) <= 2 * 5e-324)


def test_log64_within_one_ulp_of_numpy(rng):
    x = log_inputs(rng, 200_000)
    got = evaluate(LOG, x)
    want = np.log(x)
    assert np.all(np.isfinite(got))
    assert ulps(got[:5000], want[:5000]).max() <= 2
    exact_zero = want == 0.0
    assert np.all(got[exact_zero] == 0.0)
    rel = np.abs(got - want)[~exact_zero] / np.abs(want[~exact_zero])
    assert rel.max() <= 2 * np.finfo(np.float64).eps


def test_exp64_log64_against_exact_values(rng):
    """Against mpmath's exact values rounded once: at most 1 ulp (FDLIBM's bound)."""
    mpmath.mp.prec = 120
    x = np.concatenate([rng.uniform(-745.0, 709.7, 300), rng.uniform(-2, 2, 300)])
    exact = np.array([float(mpmath.exp(mpmath.mpf(float(v)))) for v in x])
    assert ulps(evaluate(EXP, x), exact).max() <= 1
    y = np.concatenate([log_inputs(rng, 200)[:600]])
    exact = np.array([float(mpmath.log(mpmath.mpf(float(v)))) for v in y])
    assert ulps(evaluate(LOG, y), exact).max() <= 1


def test_special_values():
    inf, nan = np.inf, np.nan
    tiny = 5e-324
    x = np.array([0.0, -0.0, 1.0, -1.0, inf, -inf, nan, 709.78, 709.79, -745.13, -745.14, 1e-300, -1e-300, 3.725290298461914e-09])
    got = evaluate(EXP, x)
    assert got[0] == 1.0 and got[1] == 1.0 and got[13] == 1.0 + x[13]
    assert ulps(got[2:4], np.exp([1.0, -1.0])).max() <= 1
    assert got[4] == inf and got[5] == 0.0 and np.isnan(got[6])
    assert np.isfinite(got[7]) and got[7] > 1.7e308 and got[8] == inf
    assert got[9] == tiny and got[10] == 0.0
    assert got[11] == 1.0 and got[12] == 1.0
    y = np.array([0.0, -0.0, -1.0, inf, nan, 1.0, tiny, np.finfo(np.float64).max, 2.0, 0.5, np.e])
    got = evaluate(LOG, y)
    assert got[0] == -inf and got[1] == -inf
    assert np.isnan(got[2]) and got[3] == inf and np.isnan(got[4])
    assert got[5] == 0.0 and not np.signbit(got[5])
    assert ulps(got[6:], np.log(y[6:])).max() <= 1
    # pow64: the callers' domain x >= 0; y = 1/4 and 1/2 by square roots
    got = evaluate(POW, np.array([0.0, 16.0, 16.0, 8.0, 1e300, 2.0]), np.array([0.25, 0.25, 0.5, 1.0 / 3.0, 0.25, 0.0]))
    assert got[0] == 0.0 and got[1] == 2.0 and got[2] == 4.0 and got[5] == 1.0
    assert abs(got[3] - 2.0) <= 4e-16 and got[4] == np.sqrt(np.sqrt(1e300))
    # sigmoid at the extremes of a float32 logit
    got = evaluate(SIGMOID, np.array([0.0, 3.0e38, -3.0e38, 800.0, -800.0, 40.0]))
    assert got[0] == 0.5 and got[1] == 1.0 and got[2] == 0.0 and got[3] == 1.0 and got[4] == 0.0
    assert ulps(got[5:], [1.0 / (1.0 + np.exp(-40.0))]).max() <= 1


def test_pow_sigmoid_and_cos_accuracy(rng):
    x = np.exp(rng.uniform(-30, 30, 20_000))
    y = rng.uniform(-3, 3, 20_000)
    got = evaluate(POW, x, y)
    want = np.power(x, y)
    # exp(y log x): log's rounding is scaled by y log x, so a few ulp where |y log x| is small (the
    # coverage operator's growth: y <= 1, x a coverage ratio), (|y log x| + 2) ulp in general
    bound = (np.abs(y * np.log(x)) + 2.0) * np.finfo(np.float64).eps
    assert np.all(np.abs(got - want) / want <= bound)
    s = rng.uniform(-50, 50, 20_000)
    got = evaluate(SIGMOID, s)
    assert np.max(np.abs(got - 1 / (1 + np.exp(-s))) / (1 / (1 + np.exp(-s)))) <= 4 * np.finfo(np.float64).eps
    u = np.r_[rng.integers(0, 2**24, 20_000) / 2**24, np.arange(17) / 16]  # randf's lattice, octant ends
    got = evaluate(COS_TWO_PI, u)
    mpmath.mp.prec = 120
    exact = np.array([float(mpmath.cos(2 * mpmath.pi * mpmath.mpf(float(v)))) for v in u[:2000]])
    assert np.max(np.abs(got[:2000] - exact)) <= 2 * np.finfo(np.float64).eps  # absolute: cos is 0 at 1/4, 3/4
    assert np.max(np.abs(got - np.cos(2 * np.pi * u))) <= 4 * np.finfo(np.float64).eps
    assert got[-17] == 1.0 and got[-1] == 1.0 and got[-9] == -1.0  # u = 0, 1, 1/2


def test_bit_for_bit_as_the_numpy_reference(device, rng):
    """The kernels do exactly what their source says, in its order: the same bits as numpy's
    correctly rounded, unfused operations. A contracted multiply-add, a reordering or a library
    function in the build changes bits here."""
    x = exp_inputs(rng, 50_000)
    assert same_bits(evaluate(EXP, x, device=device), ref.exp64(x))
    y = log_inputs(rng, 50_000)
    assert same_bits(evaluate(LOG, y, device=device), ref.log64(y))
    b = np.exp(rng.uniform(-20, 20, 50_000))
    e = np.where(rng.random(50_000) < 0.2, 0.25, rng.uniform(-2, 2, 50_000))
    assert same_bits(evaluate(POW, b, e, device=device), ref.pow64(b, e))
    s = rng.uniform(-60, 60, 50_000)
    assert same_bits(evaluate(SIGMOID, s, device=device), ref.sigmoid64(s))
    u = rng.integers(0, 2**24, 50_000) / 2**24
    assert same_bits(evaluate(COS_TWO_PI, u, device=device), ref.cos_two_pi(u))
    u1, u2 = rng.integers(0, 2**24, (2, 50_000)) / 2**24
    assert same_bits(evaluate(NORMAL, u1, u2, device=device), ref.normal_from_uniforms(u1, u2))


def exp32_inputs(rng, n):
    every = rng.integers(0, 2**32, size=n, dtype=np.uint64).astype(np.uint32).view(np.float32)  # any float32
    return np.concatenate([
        every[np.isfinite(every)],
        rng.uniform(-104.0, 88.73, n),  # the whole finite range, subnormal results included
        rng.uniform(-1.1, 1.1, n),  # the reduction's branches: k = 0, k = +-1
        rng.normal(scale=1e-4, size=n // 4),
        rng.uniform(-104.0, -87.0, n // 4),
        rng.uniform(-12.0, 0.0, n),  # the renderer's powers
        rng.uniform(-20.0, 5.0, n),  # log-scales
    ]).astype(np.float32)  # fmt: skip


def ulps32(a, b):
    """Distance in float32 units in the last place (equal infinities: 0)."""
    ai = np.asarray(a, np.float32).view(np.int32).astype(np.int64)
    bi = np.asarray(b, np.float32).view(np.int32).astype(np.int64)
    ai = np.where(ai < 0, -(2**31) - ai, ai)
    bi = np.where(bi < 0, -(2**31) - bi, bi)
    return np.abs(ai - bi)


def test_exp32_within_one_ulp(rng):
    x = exp32_inputs(rng, 100_000)
    got = evaluate(EXP32, x).astype(np.float32)
    with np.errstate(over="ignore"):
        exact = np.exp(x.astype(np.float64))  # float64: the exact value to far below a float32 ulp
        rounded = exact.astype(np.float32)
    finite = np.isfinite(rounded) & (x <= 88.7216796875)
    assert finite.sum() > 300_000
    assert np.max(ulps32(got[finite], rounded[finite])) <= 1
    assert np.all(np.abs(got[finite].astype(np.float64) - exact[finite]) <= np.spacing(rounded[finite]).astype(np.float64))


def test_exp32_special_values():
    x = np.array([0.0, -0.0, 1e-30, -1e-30, 88.7216796875, 88.7217, 89.0, np.inf, -103.97, -104.0, -np.inf, np.nan, 1.0, -1.0, 0.5])
    got = evaluate(EXP32, x).astype(np.float32)
    assert got[0] == 1.0 and got[1] == 1.0 and got[2] == 1.0 and got[3] == 1.0
    assert np.isfinite(got[4]) and ulps32(got[4], np.float32(3.3988806e38)) <= 1  # the largest finite result
    assert got[5] == np.inf and got[6] == np.inf and got[7] == np.inf
    assert got[8] <= 1.5e-45 and got[9] == 0.0 and got[10] == 0.0  # e^-103.97 = 7e-46: half the least subnormal
    assert np.isnan(got[11])
    assert ulps32(got[12:], np.exp(x[12:]).astype(np.float32)).max() <= 1


def test_float32_functions_bit_for_bit_as_the_numpy_reference(device, rng):
    """``exp32`` (the renderer's per-pixel exponential), ``log32`` and ``sigmoid32``: the same bits
    as their numpy re-implementation in float32, on every device."""
    x = exp32_inputs(rng, 50_000)
    assert same_bits(evaluate(EXP32, x, device=device), ref.exp32(x).astype(np.float64))
    y = np.abs(exp32_inputs(rng, 20_000))
    y = y[y > 0]
    assert same_bits(evaluate(LOG32, y, device=device), ref.log32(y).astype(np.float64))
    s = rng.uniform(-40, 40, 50_000).astype(np.float32)
    assert same_bits(evaluate(SIGMOID32, s, device=device), ref.sigmoid32(s).astype(np.float64))


def _pcg(state):
    state = (state * np.uint32(747796405) + np.uint32(2891336453)).astype(np.uint32)
    word = (((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)).astype(np.uint32)
    return ((word >> np.uint32(22)) ^ word).astype(np.uint32)


def common_samples_reference(seed, pass_index, count):
    """kernels.cost.draw_common_samples in numpy: Warp's rand_init and randf (PCG hash), three
    portable Box-Muller normals per sample (two uniforms each, in order)."""
    with np.errstate(over="ignore"):
        offsets = (pass_index * count + np.arange(count)).astype(np.uint32)
        state = _pcg((np.uint32(seed) + _pcg(offsets)).astype(np.uint32))
        uniforms = []
        for _ in range(6):
            state = _pcg(state)
            uniforms.append((state >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0))
    z = [ref.normal_from_uniforms(uniforms[2 * c], uniforms[2 * c + 1]).astype(np.float32) for c in range(3)]
    return np.stack(z, axis=1)


@pytest.mark.parametrize("seed, pass_index", [(0, 0), (7, 3), (123456, 41)])
def test_common_samples_bit_for_bit(device, seed, pass_index):
    count = 4096
    out = wp.full(count, np.nan, dtype=wp.vec3, device=device)
    wp.launch(cost_kernels.draw_common_samples, count, inputs=[seed, pass_index], outputs=[out], device=device)
    got = out.numpy()
    want = common_samples_reference(seed, pass_index, count)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    # and they are standard normals
    z = got.ravel()
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1) < 0.05
