"""The compiled CPU voxel queries (kernels/voxelq.c) as an optional extension: everything else is in
pyproject.toml. Without a C compiler the install goes on and usdml answers voxel queries with its
Warp kernels instead (``usdml info`` says which path a machine has)."""

from setuptools import Extension, setup

setup(ext_modules=[Extension(
    "usdml.kernels._voxelq", sources=["kernels/voxelq.c"], depends=["kernels/voxelq_simd.h"],
    # portable code: the AVX2 functions carry their own target attribute and are picked at run time
    extra_compile_args=["-O3", "-fno-math-errno", "-fno-strict-aliasing"],
    optional=True)])
