"""The LGH's compiled CPU kernels (kernels/lgh/lghq.c) against the Warp kernels they stand in for: the same
gather (sums, picks, jittered positions), the same member draws and weights, bit for bit, with the light
terms 8 at a time (AVX2) or one at a time; and the same frame through lgh_indirect."""

import os

import numpy as np
import pytest

pytest.importorskip("warp")

from usdml.lighting.lgh import shading as m  # noqa: E402
from usdml.lighting.lgh import native as lgh_native  # noqa: E402
from usdml.lighting.lgh.build import build_lgh  # noqa: E402

#: CI sets USDML_REQUIRE_NATIVE=1 so that a failed build fails these tests instead of skipping them
if lgh_native.library() is None and os.environ.get("USDML_REQUIRE_NATIVE") == "1":
    raise RuntimeError(f"USDML_REQUIRE_NATIVE=1 but the LGH's CPU path is {lgh_native.describe()}")
pytestmark = pytest.mark.skipif(lgh_native.library() is None, reason="kernels/lgh/lghq.c was not built")


@pytest.fixture(scope="module")
def frame(cornell):
    """conftest's cornell frame and an LGH over its VPLs (cosine emitters)."""
    snap, ex, gb, pts, nrm, alb, vpls = cornell
    intensity = vpls.flux / np.float32(4 * np.pi)
    lgh = build_lgh(vpls.position, intensity, normal=vpls.normal)
    yield snap, ex, gb, pts, nrm, alb, lgh, (vpls.position, intensity, vpls.normal)
    lgh_native.simd(True)


FIELDS = ("irradiance", "count", "sample_pos", "sample_ok", "sample_light", "sample_weight", "sample_blend",
          "sample_lum")


@pytest.mark.parametrize("k,stratified,jitter,s0,tiles", [(16, True, True, True, 4), (8, False, False, False, 1),
                                                          (8, False, True, True, 1), (0, True, False, True, 1)])
def test_compiled_gather_is_the_warp_gather_bit_for_bit(frame, k, stratified, jitter, s0, tiles):
    snap, ex, gb, pts, nrm, alb, lgh, sources = frame
    tile = np.arange(len(pts)) % tiles
    runs = {}
    for kernel, simd in (("warp", True), ("native", True), ("native", False)):
        width = lgh_native.simd(simd)
        assert (width in (1, 8)) and (simd or width == 1)
        g = m.LGHGather(lgh, 2.0, k, 5, snap.meters_per_unit, None, tiles=tiles, s0=sources if s0 else None,
                        jitter=jitter, stratified=stratified, cpu_kernel=kernel)
        runs[kernel, simd] = g(pts[50:], nrm[50:], tile[50:], first=50)   # numbered as rows 50.. of the frame
    lgh_native.simd(True)
    warp = runs["warp", True]
    assert warp.irradiance.max() > 0 and (k == 0 or warp.sample_ok.mean() > 0.9)
    for key in (("native", True), ("native", False)):
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(runs[key], name), getattr(warp, name), err_msg=f"{key} {name}")


def test_compiled_gather_of_a_split_hierarchy_is_the_warp_gather_bit_for_bit(frame):
    """One hierarchy per normal class (--lgh-split normal): each level listed once per class, blended as its
    level, in both kernels."""
    from usdml.lighting.lgh.build import build_lgh_split

    snap, ex, gb, pts, nrm, alb, _, sources = frame
    lgh = build_lgh_split(sources[0], sources[1], sources[2])
    assert len(lgh.levels) > lgh.depth
    runs = {}
    for kernel in ("warp", "native"):
        g = m.LGHGather(lgh, 1.5, 16, 5, snap.meters_per_unit, None, s0=sources, jitter=False, cpu_kernel=kernel)
        runs[kernel] = g(pts, nrm)
    assert runs["warp"].irradiance.max() > 0
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(runs["native"], name), getattr(runs["warp"], name), err_msg=name)


@pytest.mark.parametrize("kernel", ["native", "warp"])
def test_a_gather_at_another_alpha_is_a_gather_made_at_it(frame, kernel):
    """``LGHGather.at_alpha`` (the frame's choice tries several α over one gather's tables) gathers what a gather
    made at that α does, bit for bit, and leaves the gather it came from as it was."""
    snap, ex, gb, pts, nrm, alb, lgh, sources = frame
    base = m.LGHGather(lgh, 1.0, 8, 5, snap.meters_per_unit, None, s0=sources, cpu_kernel=kernel)
    before = base(pts, nrm)
    for alpha in (1.5, 3.0):
        got = base.at_alpha(alpha)(pts, nrm)
        want = m.LGHGather(lgh, alpha, 8, 5, snap.meters_per_unit, None, s0=sources, cpu_kernel=kernel)(pts, nrm)
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=f"{alpha} {name}")
        assert not np.array_equal(got.irradiance, before.irradiance)
    again = base(pts, nrm)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(again, name), getattr(before, name), err_msg=name)


@pytest.mark.parametrize("reweight", [True, False])
def test_compiled_member_draws_are_the_warp_draws_bit_for_bit(frame, reweight):
    snap, ex, gb, pts, nrm, alb, lgh, sources = frame
    k = 16
    shading = m.LGHGather(lgh, 2.0, k, 3, snap.meters_per_unit, None, s0=sources, jitter=False)(pts, nrm)
    light = shading.sample_light.reshape(-1)
    pixel = np.arange(light.size, dtype=np.int32) // k
    got = {}
    for kernel in ("warp", "native"):
        sampler = m.ClusterSampler(lgh, *sources, reweight=reweight, meters_per_unit=snap.meters_per_unit,
                                   stratify=True, cpu_kernel=kernel)
        got[kernel] = sampler.targets(light, shading.sample_pos.reshape(-1, 3), 9, pts, nrm,
                                      shading.sample_blend.reshape(-1), shading.sample_weight.reshape(-1, 3),
                                      pixel=pixel, first=11, runs=m.sample_runs(light, k))
    warp, native = got["warp"], got["native"]
    if reweight:
        np.testing.assert_array_equal(native[0], warp[0])
        np.testing.assert_array_equal(native[1], warp[1])
        assert (warp[1] == 0).all(axis=1).mean() < 0.9          # most samples weigh something
        targets = warp[0]
    else:
        np.testing.assert_array_equal(native, warp)
        targets = warp
    # a target is a member VPL (S0 picks are VPLs too), or the grid light's centre where it has no member
    vpl = {tuple(p) for p in np.asarray(sources[0], np.float32)}
    own = np.array([tuple(t) in vpl for t in targets[:2000]])
    fallback = (targets[:2000] == shading.sample_pos.reshape(-1, 3)[:2000]).all(axis=1)
    assert (own | fallback).all() and own.mean() > 0.8


def test_compiled_frame_matches_the_warp_frame(frame):
    """lgh_indirect with the compiled kernels: the same visibility and, up to the shadow sums' rounding (double
    in C, float32 in NumPy's einsum), the same radiance."""
    snap, ex, gb, pts, nrm, alb, lgh, sources = frame
    out = {}
    for kernel in ("warp", "native"):
        out[kernel] = m.lgh_indirect(pts, nrm, alb, lgh, ex.occluded, alpha=2.0, samples=32, seed=2,
                                     meters_per_unit=snap.meters_per_unit, image=(gb.hit, gb.position),
                                     sources=sources, start_level=0,
                                     sampler=m.ClusterSampler(lgh, *sources, reweight=True,
                                                              meters_per_unit=snap.meters_per_unit,
                                                              stratify=True, cpu_kernel=kernel),
                                     cpu_kernel=kernel)
    np.testing.assert_array_equal(out["native"].visible, out["warp"].visible)
    np.testing.assert_array_equal(out["native"].unshadowed, out["warp"].unshadowed)
    np.testing.assert_allclose(out["native"].radiance, out["warp"].radiance, rtol=2e-5, atol=1e-7)
    assert 0.05 < out["warp"].visible.mean() < 0.95


def test_a_bad_cpu_kernel_is_a_one_line_error(frame):
    from usdml.errors import UsdmlError

    from usdml.settings import UsdmlSettings

    snap, ex, gb, pts, nrm, alb, lgh, sources = frame
    # a user's value is checked once, with the settings; the kernel layer refuses what no setting gives it
    with pytest.raises(UsdmlError, match="lgh-cpu-kernel|lgh:cpuKernel"):
        UsdmlSettings().updated(lgh_cpu_kernel="avx")
    with pytest.raises(ValueError, match="auto, native or warp"):
        m.LGHGather(lgh, 2.0, 4, cpu_kernel="avx")
