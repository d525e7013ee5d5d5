"""Time of the portable float64 exp and log (kernels/portable_math.py) against Warp's own (the
device's math library), per call.

    python tools/math_bench.py --device cpu [--count 4000000] [--repeat 7]

One kernel per function over --count arguments in [0.01, 3) (log: of x + 2), the best of --repeat
launches, less the time of a kernel that only copies (the memory traffic).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from nanogs_warp.device import init_warp, resolve_device
from nanogs_warp.kernels.portable_math import exp64, log64


@wp.kernel
def _copy(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    t = wp.tid()
    out[t] = x[t] + wp.float64(1.0)


@wp.kernel
def _exp_library(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    t = wp.tid()
    out[t] = wp.exp(x[t])


@wp.kernel
def _exp_portable(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    t = wp.tid()
    out[t] = exp64(x[t])


@wp.kernel
def _log_library(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    t = wp.tid()
    out[t] = wp.log(x[t] + wp.float64(2.0))


@wp.kernel
def _log_portable(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    t = wp.tid()
    out[t] = log64(x[t] + wp.float64(2.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--count", type=int, default=4_000_000)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    init_warp()
    device = resolve_device(args.device)
    x = wp.array(np.random.default_rng(0).uniform(0.01, 3.0, args.count), dtype=wp.float64, device=device)
    out = wp.empty_like(x)
    kernels = (_copy, _exp_library, _exp_portable, _log_library, _log_portable)
    best = {}
    for kernel in kernels:
        wp.launch(kernel, args.count, inputs=[x], outputs=[out], device=device)
    for _ in range(args.repeat):
        for kernel in kernels:
            wp.synchronize_device(device)
            t = time.perf_counter()
            wp.launch(kernel, args.count, inputs=[x], outputs=[out], device=device)
            wp.synchronize_device(device)
            best[kernel.key] = min(best.get(kernel.key, np.inf), time.perf_counter() - t)
    base = best["_copy"]
    for name in ("_exp_library", "_exp_portable", "_log_library", "_log_portable"):
        print(f"{name[1:]:>13}: {(best[name] - base) / args.count * 1e9:6.1f} ns per call on {device}")


if __name__ == "__main__":
    main()
