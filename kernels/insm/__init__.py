"""Kernels of the insm method (paper 001): Warp (``maps``) and C (``insmr.c``, built as ``_insmr``)."""
