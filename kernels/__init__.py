"""Warp kernels (installed as usdml.kernels): pure compute over arrays, runnable on cpu and cuda."""
