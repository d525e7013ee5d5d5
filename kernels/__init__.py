"""Warp kernels, one module per pipeline stage (installed as ``nanogs_warp.kernels``)."""
