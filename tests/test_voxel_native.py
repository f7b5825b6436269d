"""The compiled CPU voxel kernel (``kernels/voxel/voxelq.c``, ``usdml.visibility.voxel.native``) answers as
the Warp kernels do, with every instruction set it has, and a machine without it gets Warp.

The two share the rule, not the code path: the compiled one folds the world -> array -> bin maps into
one per (array, bin), multiplies by reciprocals and finds instances by its own BVH, so answers may
differ where a ray passes within float rounding of a voxel border. Measured here (about 12,000 rays
per scene) and on the 7.35 M city bench rays: no occluded answer differs; hit distances differ by up
to one voxel on 7e-6 of the city's rays (1 of 5,947 here). The answers' bound (1e-4) is the issue's
"≥ 99.99 %"; distances may differ on 0.1 %, by at most 1.5 voxels. Where a ray meets several moving instances the
hit distance is that of the first instance each kernel's BVH visits (``hit_distances``), so distances
are compared on the scenes with one array per ray.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from usdml.errors import UsdmlError
from usdml.lighting.direct import shade_with
from usdml.scene import diff
from usdml.settings import UsdmlSettings
from usdml.visibility import make_backend
from usdml.visibility.voxel import native as voxel_native
from usdml.visibility.voxel.backend import VoxelBackend

from backend_scenes import lights, queries, scene_frames, surface_points

#: CI sets USDML_REQUIRE_NATIVE=1 so that a failed build fails these tests instead of skipping them
if voxel_native.library() is None and os.environ.get("USDML_REQUIRE_NATIVE") == "1":
    raise RuntimeError(f"USDML_REQUIRE_NATIVE=1 but the compiled voxel kernel is {voxel_native.describe()}")
pytestmark = pytest.mark.skipif(voxel_native.library() is None, reason="the compiled voxel kernel was not built")

SETTINGS = UsdmlSettings(voxel_resolution=32, direction_step=10.0)
QUIET = {"report": lambda line: None}
#: the compiled kernel's instruction sets this CPU runs (auto: the widest)
ISAS = ["auto"] + (["avx2"] if voxel_native.isa_width("avx2") == 8 and voxel_native.isa_width() > 8 else []) \
    + ["scalar"]


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path / "cache"))


def volume_queries(rng, n: int = 3000):
    """Segments between random points in and around the scenes, some without a normal, some distant."""
    o = rng.uniform([-11, -1, -11], [11, 8, 11], (n, 3))
    t = rng.uniform([-11, -1, -11], [11, 10, 11], (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm[::5] = 0.0
    distant = rng.random(n) < 0.2
    t[distant] = rng.normal(size=(int(distant.sum()), 3))
    return o, t, dict(normals=nrm, distant=distant)


def backends(isa: str):
    warp = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="warp", **QUIET)
    native = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="native", native_isa=isa, **QUIET)
    assert warp.kernel_name == "warp" and native.kernel_name.startswith("native-")
    return warp, native


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances", "deforming", "many_instances"])
def test_native_kernel_answers_as_the_warp_kernel(scene, isa):
    rng = np.random.default_rng(11)
    lit = lights(rng)
    warp, native = backends(isa)
    previous = None
    answers, distances = [], []
    try:
        for snap in scene_frames(scene):
            for b in (warp, native):
                b.update(snap, diff(previous, snap))
            previous = snap
            pts, nrm = surface_points(rng, 800)
            for o, t, kw in (queries(pts, nrm, lit), volume_queries(rng)):
                want = warp.hit_distances(o, t, **kw)
                got = native.hit_distances(o, t, **kw)
                assert np.array_equal(native.occluded(o, t, **kw), got >= 0)
                assert 0.02 < (want >= 0).mean() < 0.98       # the scenes block some rays, not all
                answers.append((got >= 0) != (want >= 0))
                both = (got >= 0) & (want >= 0)
                distances.append(np.abs(got - want)[both])
    finally:
        warp.close()
        native.close()
    answers = np.concatenate(answers)
    assert answers.mean() <= 1e-4, f"{answers.sum()} of {answers.size} answers differ"
    if scene in ("occluder", "deforming"):
        # (with several instances hit, each kernel reports the first instance its BVH visits)
        d = np.concatenate(distances)
        assert (d > 1e-3).mean() <= 1e-3 and d.max() <= 1.5, f"{(d > 1e-3).sum()} of {d.size}; max {d.max()}"




def _segment_meets_box(o, t, lo, hi):
    """Whether each segment o -> t meets the box [lo, hi] (the slab test, in float64)."""
    d = t - o
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - o) / d, (hi - o) / d
    near = np.nanmax(np.where(d == 0, np.where((o >= lo) & (o <= hi), -np.inf, np.inf), np.minimum(a, b)), axis=1)
    far = np.nanmin(np.where(d == 0, np.where((o >= lo) & (o <= hi), np.inf, -np.inf), np.maximum(a, b)), axis=1)
    return (near <= far) & (far >= 0) & (near <= 1)


@pytest.mark.parametrize("isa", ISAS)
def test_native_kernel_answers_a_floating_box_as_the_slab_test_does(isa):
    """Against geometry, not another usdml method: one box floating above ground points, lights above
    it. Every segment that misses the box grown by 3 voxels is free, every one that crosses the box
    shrunk by 3 voxels is blocked (between the two, voxels and bins may go either way)."""
    from plain_scenes import snapshot, soup
    from voxel_reference import box

    lo, hi = np.array([-2.0, 1.0, -2.0]), np.array([2.0, 3.0, 2.0])
    native = make_backend("voxel", UsdmlSettings(voxel_resolution=64, direction_step=5.0), "cpu",
                          voxel_cpu_kernel="native", native_isa=isa, **QUIET)
    try:
        native.update(snapshot([soup("/box", box(lo, hi))]))
        rng = np.random.default_rng(8)
        n = 20000
        o = np.c_[rng.uniform(-6, 6, n), np.zeros(n), rng.uniform(-6, 6, n)]
        t = np.c_[rng.uniform(-6, 6, n), rng.uniform(5, 9, n), rng.uniform(-6, 6, n)]
        got = native.occluded(o, t, normals=np.tile([0.0, 1.0, 0.0], (n, 1)))
        arr = native.arrays[0]
        margin = 3 * 2.0 * arr.half / arr.resolution / arr.to_array[0, 0]      # 3 voxels, world units
        free = ~_segment_meets_box(o, t, lo - margin, hi + margin)
        blocked = _segment_meets_box(o, t, lo + margin, hi - margin)
        assert free.mean() > 0.3 and blocked.mean() > 0.1 and (free | blocked).mean() > 0.7    # measured 0.77
        assert not got[free].any() and got[blocked].all()
    finally:
        native.close()

@pytest.mark.parametrize("isa", ISAS)
def test_blocked_flags_are_the_distances_answers_across_chunks(isa):
    """``query`` into a bool array (what ``occluded`` asks: the kernel writes bytes, answering 8,192 rays
    at a time) gives the float path's answers, from any first ray and across chunk edges."""
    rng = np.random.default_rng(3)
    _, native = backends(isa)
    try:
        native.update(scene_frames("occluder")[0], diff(None, scene_frames("occluder")[0]))
        o, t, kw = volume_queries(rng, 30000)
        o, t = np.ascontiguousarray(o, np.float32), np.ascontiguousarray(t)        # float32 and float64 inputs
        nrm, di = np.ascontiguousarray(kw["normals"], np.float32), np.ascontiguousarray(kw["distant"])
        rule = native._native_rule()
        dist = np.full(len(o), 7.0, np.float32)
        flags = np.zeros(len(o), bool)
        for first, count in ((0, 5), (5, 8192 * 2 + 3), (16392, len(o) - 16392)):
            native._native.query(rule, first, count, o, t, nrm, di, False, dist)
            native._native.query(rule, first, count, o, t, nrm, di, False, flags)
        assert np.array_equal(flags, dist >= 0) and 0.05 < flags.mean() < 0.95
        with pytest.raises(TypeError, match="float32 or bool"):
            native._native.query(rule, 0, 4, o, t, nrm, di, False, np.zeros(4, np.float64))
    finally:
        native.close()

@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances"])
def test_native_shading_equals_the_warp_shading_kernel(scene, isa):
    """Alg. 3 (``vq_shade``) against ``kernels.voxel.shading.shade_tiles``: the same light sums."""
    rng = np.random.default_rng(5)
    lit = lights(rng, 40)
    warp, native = backends(isa)
    try:
        for snap in scene_frames(scene)[:1]:
            for b in (warp, native):
                b.update(snap, diff(None, snap))
            pts, nrm = surface_points(rng, 700)
            albedo = rng.uniform(0.2, 0.9, (len(pts), 3)).astype(np.float32)
            want = shade_with(warp, pts, nrm, albedo, lit)
            got = shade_with(native, pts, nrm, albedo, lit)
            assert np.array_equal(got.facing, want.facing) and got.queries == want.queries
            assert np.allclose(got.shadow, want.shadow)
            assert np.allclose(got.radiance, want.radiance, rtol=1e-5, atol=1e-7)
            assert 0.05 < got.shadow.mean() < 0.95
    finally:
        warp.close()
        native.close()


def test_a_machine_without_the_compiled_kernel_gets_warp(monkeypatch):
    monkeypatch.setattr(voxel_native.EXTENSION, "load", lambda: (None, "not built (no C compiler)"))
    b = VoxelBackend(voxel_resolution=32, direction_step=10.0, cache=False)
    assert not b.native and b.kernel_name == "warp"
    assert "Warp kernels" in voxel_native.describe() and "C compiler" in voxel_native.describe()
    with pytest.raises(UsdmlError, match="voxel-cpu-kernel"):
        VoxelBackend(voxel_resolution=32, direction_step=10.0, cache=False, voxel_cpu_kernel="native")


def test_a_gpu_device_never_takes_the_compiled_path():
    assert not VoxelBackend(voxel_resolution=32, direction_step=10.0, cache=False, device="cuda:0").native


def test_describe_names_the_instruction_set():
    line = voxel_native.describe()
    assert line.startswith("compiled kernel") and str(voxel_native.simd_width()) in line or "scalar" in line



def test_widths_and_names_follow_the_instruction_set():
    """Two registers per vector: 2 x the register's lanes at a time; names by the instruction set."""
    for isa in ISAS:
        lanes, register = voxel_native.simd_width(isa), voxel_native.isa_width(isa)
        assert lanes == (2 * register if register > 1 else 1)
        b = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="native", native_isa=isa, **QUIET)
        want = {16: "native-avx512", 8: "native-avx2", 1: "native-scalar"}[register]
        assert b.kernel_name == want
        b.close()

def test_native_alg5_rotation_sets_the_same_bits_as_warp():
    """Alg. 5's point mapping by the compiled kernel (``rotate_point``): the same integer rule, the same words."""
    from usdml.visibility.voxel.rotate import rotate_array

    from voxel_reference import box

    tris = np.concatenate([box((-2, 0.5, -1), (1, 2, 1.5)), box((0, 0, 0), (0.4, 3, 0.4))])
    pts, idx = tris.reshape(-1, 3), np.arange(len(tris) * 3).reshape(-1, 3)
    warp = rotate_array(pts, idx, 32, 10.0, native=False)
    native = rotate_array(pts, idx, 32, 10.0, native=True)
    assert native.occupied == warp.occupied > 100
    assert np.array_equal(native.words, warp.words) and native.words.any()
