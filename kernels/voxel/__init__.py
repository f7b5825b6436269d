"""Kernels of the voxel method (paper 000): Warp (``query``, ``shading``, ``rotate``, ``codec``) and C
(``voxelq.c``, ``voxcodec.c``, built as ``_voxelq`` and ``_voxcodec``)."""
