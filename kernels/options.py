"""The Warp module options that the package's kernel files set.

- ``enable_backward: False``: no kernel is differentiated by Warp (the refinement writes its own
  backward passes), and the forward-only modules compile in half the time.
- ``fuse_fp: False`` (``PORTABLE``): the same bits on every device (``portable_math.py``).
- ``cpu_compiler_flags``: Warp's own CPU flags without ``-march=native``, that is for the generic
  target of the machine's architecture (x86-64, AArch64) instead of the host's instruction set, so
  that a compiled CPU module serves every machine of that architecture and can ship in the package
  (``nanogs_warp/shipped_kernels.py``). The kernels are scalar float64 and float32 code: on the
  2-core x86-64 machine, playbot -> 0.1 took 5.66-5.70 s generic against 5.54-5.75 s native, the
  same within noise (docs/performance.md). The inlining limits are Warp 1.19's defaults.
"""

CPU_FLAGS = "-mllvm=-inline-threshold=9000 -mllvm=-inline-cold-callsite-threshold=3000 -mllvm=-slp-recursion-max-depth=4"

FORWARD_ONLY = {"enable_backward": False, "cpu_compiler_flags": CPU_FLAGS}
PORTABLE = {**FORWARD_ONLY, "fuse_fp": False}
