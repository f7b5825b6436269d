"""The compiled CPU voxel queries (kernels/voxelq.c), SVO traversal (kernels/svoq.c), INSM maps
(kernels/insmr.c), LGH gather (kernels/lghq.c) and the cache's voxel-array coding (kernels/voxcodec.c) as optional
extensions: everything else is in pyproject.toml. Without a C compiler the install goes on and usdml
answers those queries with its Warp kernels instead (``usdml info`` says which path a machine has)."""

from setuptools import Extension, setup

setup(ext_modules=[Extension(
    "usdml.kernels._voxelq", sources=["kernels/voxelq.c"], depends=["kernels/voxelq_simd.h", "kernels/light_term.h", "kernels/simd_avx2.h", "kernels/simd_avx512.h", "kernels/simd_x2.h", "kernels/simd_undef.h", "kernels/simd_undef_ops.h", "kernels/simd_pick.h"],
    # portable code: the AVX2 functions carry their own target attribute and are picked at run time
    extra_compile_args=["-O3", "-fno-math-errno", "-fno-strict-aliasing"],
    optional=True), Extension(
    "usdml.kernels._svoq", sources=["kernels/svoq.c"],
    depends=["kernels/svoq_simd.h", "kernels/simd_avx2.h", "kernels/simd_avx512.h", "kernels/simd_undef.h", "kernels/simd_undef_ops.h", "kernels/simd_pick.h"],
    # no a * b + c contracted into one rounding: the SIMD walk must round as the scalar one does
    extra_compile_args=["-O3", "-fno-math-errno", "-fno-strict-aliasing", "-ffp-contract=off"], optional=True),
    Extension("usdml.kernels._insmr", sources=["kernels/insmr.c"], depends=["kernels/light_term.h"],
              # no contraction: the maps round as the Warp kernels' do
              extra_compile_args=["-O3", "-fno-math-errno", "-fno-strict-aliasing", "-ffp-contract=off"],
              optional=True),
    Extension("usdml.kernels._lghq", sources=["kernels/lghq.c"],
              # no contraction: the gather rounds as the Warp kernel's does (the same picks)
              extra_compile_args=["-O3", "-fno-math-errno", "-fno-strict-aliasing", "-ffp-contract=off"],
              optional=True),
    # the cache's depth coding of voxel arrays (integers only: any compiler flags give the same bytes)
    Extension("usdml.kernels._voxcodec", sources=["kernels/voxcodec.c"], extra_compile_args=["-O3"], optional=True)])
