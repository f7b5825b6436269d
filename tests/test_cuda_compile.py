"""The CUDA side of every Warp kernel module compiles, on a machine without a GPU.

Warp ships NVRTC, so the kernels' CUDA code (the GPU branches: atomic bit writes, one launch per
batch) is generated and compiled to PTX here as it would be on a GPU's first launch. This does not
run it; it catches code that only the CUDA backend rejects. The PTX goes to Warp's kernel cache,
so only a cold cache pays the compile (about 5 s).
"""

import importlib
import importlib.util
import pkgutil

import pytest

wp = pytest.importorskip("warp")

import usdml.kernels

#: oldest architecture Warp's NVRTC targets (Turing); PTX for it JIT-compiles on every newer GPU
ARCH = 75


def _kernel_modules() -> list[str]:
    """The Warp kernel modules, in the folder of each method and beside them (not the packages, nor the
    compiled C extensions such as ``voxel._voxelq``, which are CPU code, nor the NumPy references such as
    ``brdf``, which define no Warp kernel)."""
    found = pkgutil.walk_packages(usdml.kernels.__path__, "usdml.kernels.")
    names = []
    for m in found:
        if m.ispkg or m.name.rpartition(".")[2].startswith("_"):
            continue
        spec = importlib.util.find_spec(m.name)
        if spec is None or spec.origin is None or "@wp.kernel" not in open(spec.origin).read():
            continue
        names.append(m.name.removeprefix("usdml.kernels."))
    return sorted(names)


def test_every_kernel_module_is_checked():
    assert {"voxel.query", "voxel.rotate", "voxel.shading", "voxel.codec", "lgh.build", "lgh.shading", "atrous",
            "svo.octree", "insm.maps", "shadow_rays"} <= set(_kernel_modules())


@pytest.mark.parametrize("name", _kernel_modules())
def test_kernel_module_compiles_for_cuda(name):
    if not hasattr(wp, "compile_aot_module"):
        pytest.skip("this Warp has no ahead-of-time compilation")
    wp.init()
    if ARCH not in (wp.get_cuda_supported_archs() or []):
        pytest.skip(f"this Warp build cannot compile CUDA for sm_{ARCH} (no NVRTC)")
    module = importlib.import_module(f"usdml.kernels.{name}")
    paths = wp.compile_aot_module(module, arch=ARCH, use_ptx=True)
    assert paths and all(p.exists() and p.stat().st_size > 0 for p in paths)
    ptx = paths[0].read_text(errors="replace")
    assert ".entry" in ptx      # at least one kernel entry point was generated
