"""Kernels of the lighting grid hierarchy (paper 004): Warp (``build``, ``shading``) and C (``lghq.c``, built as
``_lghq``)."""
