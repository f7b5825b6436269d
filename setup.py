"""The compiled CPU voxel queries (kernels/voxel/voxelq.c), SVO traversal (kernels/svo/svoq.c), INSM maps
(kernels/insm/insmr.c), LGH gather (kernels/lgh/lghq.c), the preview surface's BRDF sums (kernels/brdf/brdfsum.c)
and the cache's voxel-array coding (kernels/voxel/voxcodec.c) as optional extensions, each under its method's
folder (``usdml.kernels.voxel._voxelq``); the headers they share (instruction sets, the light term, the BRDF) are
in kernels/include. Everything else is in pyproject.toml. Without a C compiler the install goes on and usdml answers
those queries with its Warp kernels instead (``usdml info`` says which path a machine has; the BRDF sums fall back
to NumPy)."""

from setuptools import Extension, setup

INCLUDE = "kernels/include"
SIMD = [f"{INCLUDE}/{h}" for h in ("simd_avx2.h", "simd_avx512.h", "simd_undef.h", "simd_undef_ops.h", "simd_pick.h")]
BRDF = [f"{INCLUDE}/brdf.h", f"{INCLUDE}/brdf_lobes.h"]
# portable code: the AVX2 functions carry their own target attribute and are picked at run time
FLAGS = ["-O3", "-fno-math-errno", "-fno-strict-aliasing"]
# no a * b + c contracted into one rounding: the SIMD walk, the maps and the gather round as their scalar and
# Warp counterparts do
NO_CONTRACT = [*FLAGS, "-ffp-contract=off"]


def kernel(method: str, name: str, depends=(), flags=FLAGS) -> Extension:
    """The optional extension ``usdml.kernels.<method>._<name>`` from ``kernels/<method>/<name>.c``."""
    return Extension(f"usdml.kernels.{method}._{name}", sources=[f"kernels/{method}/{name}.c"],
                     include_dirs=[INCLUDE], depends=list(depends), extra_compile_args=list(flags), optional=True)


setup(ext_modules=[
    kernel("voxel", "voxelq", ["kernels/voxel/voxelq_simd.h", f"{INCLUDE}/light_term.h", f"{INCLUDE}/simd_x2.h",
                               *BRDF, *SIMD]),
    kernel("svo", "svoq", ["kernels/svo/svoq_simd.h", *SIMD], NO_CONTRACT),
    kernel("insm", "insmr", [f"{INCLUDE}/light_term.h"], NO_CONTRACT),
    kernel("lgh", "lghq", BRDF, NO_CONTRACT),
    # rounded as the NumPy reference rounds (usdml.lighting.brdf_sums)
    kernel("brdf", "brdfsum", [*BRDF, f"{INCLUDE}/simd_undef.h", f"{INCLUDE}/simd_undef_ops.h"], NO_CONTRACT),
    # the cache's depth coding of voxel arrays (integers only: any compiler flags give the same bytes)
    kernel("voxel", "voxcodec", flags=["-O3"])])
