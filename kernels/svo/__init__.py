"""Kernels of the svo method (paper 003): Warp (``octree``) and C (``svoq.c``, built as ``_svoq``)."""
