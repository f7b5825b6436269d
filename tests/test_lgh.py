"""Lighting grid hierarchy construction (paper 004 §3.1) against a NumPy reference, on every Warp device."""

from __future__ import annotations

import numpy as np
import pytest

from usdml.errors import UsdmlError
from usdml.lighting.lgh.build import MAX_LEVELS, auto_levels, build_lgh, count_s1

wp = pytest.importorskip("warp")
wp.config.quiet = True
wp.init()

LUMA = np.array([0.2126, 0.7152, 0.0722])
CITY = np.array([360.0, 120.0, 360.0])


def random_lights(n: int, box=CITY, seed: int = 0, offset=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    p = rng.random((n, 3)) * np.asarray(box, np.float64) + np.asarray(offset)
    i = (rng.random((n, 3)) * rng.random((n, 1)) * 10).astype(np.float32)
    return p, i


# -- NumPy reference -----------------------------------------------------------------------------

def ref_splat(points, weight_rgb, m0, m1, m2, origin, h, dims):
    """Distribute point clusters over a grid with trilinear weights (float64).

    Each point carries RGB ``weight_rgb``, luminance weight ``m0``, and absolute moments
    ``m1`` = m0·centre, ``m2`` = m0·(variance + |centre|²). Returns the grid's (I, m0, m1, m2).
    """
    dims = np.asarray(dims)
    V = int(dims.prod())
    acc_i, acc0 = np.zeros((V, 3)), np.zeros(V)
    acc1, acc2 = np.zeros((V, 3)), np.zeros(V)
    g = (points - origin) / h
    i0 = np.clip(np.floor(g).astype(np.int64), 0, dims - 2)
    f = np.clip(g - i0, 0.0, 1.0)
    for c in range(8):
        d = np.array([c >> 2, (c >> 1) & 1, c & 1])
        w = np.prod(np.where(d == 1, f, 1.0 - f), axis=1)
        keep = w > 0
        idx = i0[keep] + d
        v = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        wk = w[keep]
        np.add.at(acc_i, v, wk[:, None] * weight_rgb[keep])
        np.add.at(acc0, v, wk * m0[keep])
        np.add.at(acc1, v, wk[:, None] * m1[keep])
        np.add.at(acc2, v, wk * m2[keep])
    return acc_i, acc0, acc1, acc2


def ref_lights(acc):
    """Compacted grid lights (vertex, intensity, position, variance) of reference accumulators."""
    acc_i, acc0, acc1, acc2 = acc
    v = np.flatnonzero(acc0 > 0)
    pos = acc1[v] / acc0[v, None]
    var = np.maximum(acc2[v] / acc0[v] - (pos ** 2).sum(axis=1), 0.0)
    return v, acc_i[v], pos, var


def ref_s1(p, inten, level):
    lum = inten.astype(np.float64) @ LUMA
    return ref_splat(p, inten.astype(np.float64), lum, lum[:, None] * p, lum * (p ** 2).sum(axis=1),
                     level.origin, level.spacing, level.dims)


def ref_gather(s1_lights, level):
    """Level l from the S1 grid lights, each a point cluster at its illumination centre (paper 004 §3.1)."""
    _, i1, pos1, var1 = s1_lights
    m0 = i1 @ LUMA
    return ref_splat(pos1, i1, m0, m0[:, None] * pos1, m0 * (var1 + (pos1 ** 2).sum(axis=1)),
                     level.origin, level.spacing, level.dims)


def compare(level, ref, scale):
    v, i_ref, p_ref, var_ref = ref
    np.testing.assert_array_equal(level.vertex, v)
    np.testing.assert_allclose(level.intensity, i_ref, rtol=1e-4, atol=1e-5 * np.abs(i_ref).max())
    np.testing.assert_allclose(level.position, p_ref, rtol=0, atol=2e-5 * scale)
    np.testing.assert_allclose(level.variance, var_ref, rtol=1e-3, atol=1e-5 * scale ** 2)


# -- tests ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("box", [CITY, (1.0, 1.0, 1.0)], ids=["city", "unit"])
@pytest.mark.parametrize("levels", [0, 3, 6])
def test_every_level_conserves_total_intensity(device, box, levels):
    p, inten = random_lights(3000, box, seed=1)
    lgh = build_lgh(p, inten, levels=levels, device=device)
    total = inten.astype(np.float64).sum(axis=0)
    assert len(lgh.levels) == (levels or lgh.stats["levels"])
    for lv in lgh.levels:
        np.testing.assert_allclose(lv.intensity.astype(np.float64).sum(axis=0), total, rtol=1e-4,
                                   err_msg=f"level {lv.level}")


@pytest.mark.parametrize("box", [CITY, (1.0, 1.0, 1.0)], ids=["city", "unit"])
def test_every_level_keeps_the_illumination_centre(device, box):
    # off the origin, so that a mistake in the grid origin shows
    p, inten = random_lights(4000, box, seed=2, offset=(-50.0, 3.0, 1000.0))
    lum = inten.astype(np.float64) @ LUMA
    centre = (lum[:, None] * p).sum(axis=0) / lum.sum()
    lgh = build_lgh(p, inten, levels=5, device=device)
    for lv in lgh.levels:
        w = lv.intensity.astype(np.float64) @ LUMA
        got = (w[:, None] * lv.position).sum(axis=0) / w.sum()
        np.testing.assert_allclose(got, centre, rtol=0, atol=1e-4 * max(box), err_msg=f"level {lv.level}")


def test_light_on_a_grid_vertex_is_one_s1_light(device):
    # the box corners fix the grid: 3 levels over a unit cube give h1 = 0.25, so (0.25, 0.5, 0.75) is a vertex
    p = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.25, 0.5, 0.75]])
    inten = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]], np.float32)
    lgh = build_lgh(p, inten, levels=3, device=device)
    s1 = lgh.levels[0]
    assert lgh.h1 == pytest.approx(0.25) and s1.spacing == pytest.approx(0.25)
    np.testing.assert_array_equal(s1.dims, [5, 5, 5])
    assert len(s1.position) == 3
    np.testing.assert_array_equal(s1.vertex, [0, (1 * 5 + 2) * 5 + 3, 124])
    order = [0, 2, 1]     # grid lights come in vertex order
    np.testing.assert_allclose(s1.position, p[order], atol=1e-6)
    np.testing.assert_allclose(s1.intensity, inten[order])
    np.testing.assert_allclose(s1.variance, 0.0, atol=1e-10)


def test_single_light(device):
    lgh = build_lgh(np.array([[5.0, -2.0, 7.0]]), np.array([[1.0, 1.0, 1.0]], np.float32), device=device)
    assert lgh.stats["levels"] == 1
    (top,) = lgh.levels
    np.testing.assert_array_equal(top.dims, [2, 2, 2])
    np.testing.assert_allclose(top.position, [[5.0, -2.0, 7.0]])
    np.testing.assert_allclose(top.variance, [0.0])


def test_compaction_keeps_exactly_the_non_empty_vertices(device):
    p, inten = random_lights(1500, seed=3)
    # some lights are dark: they must not light vertices on their own
    inten[::3] = 0.0
    lgh = build_lgh(p, inten, levels=6, device=device)
    s1 = lgh.levels[0]
    acc = ref_s1(p, inten, s1)
    nonzero = np.flatnonzero(acc[1] > 0)
    assert len(s1.position) == len(nonzero) < int(np.prod(s1.dims))
    np.testing.assert_array_equal(s1.vertex, nonzero)
    assert (s1.intensity.max(axis=1) > 0).all()
    assert lgh.stats["lights_per_level"][0] == len(nonzero)


@pytest.mark.parametrize("box", [CITY, (1.0, 1.0, 1.0)], ids=["city", "unit"])
def test_matches_numpy_reference_scatter_and_gather(device, box):
    p, inten = random_lights(2000, box, seed=4, offset=(10.0, -20.0, 30.0))
    lgh = build_lgh(p, inten, levels=5, device=device)
    scale = float(max(box))
    s1 = lgh.levels[0]
    ref1 = ref_lights(ref_s1(p, inten, s1))
    compare(s1, ref1, scale)
    # levels 2 and 3 and the top (one cell) gather from the reference S1 grid lights
    for lv in (lgh.levels[1], lgh.levels[2], lgh.levels[-1]):
        compare(lv, ref_lights(ref_gather(ref1, lv)), scale)
    assert len(lgh.levels[-1].position) == 8


def test_grid_geometry_follows_the_paper():
    p, inten = random_lights(2000, seed=5)
    lgh = build_lgh(p, inten, levels=4)
    lo, hi = lgh.bounds
    longest = float((hi - lo).max())
    assert lgh.h1 == pytest.approx(longest / 2 ** 3)
    for lv in lgh.levels:
        assert lv.spacing == pytest.approx(lgh.h1 * 2 ** (lv.level - 1))
        np.testing.assert_allclose(lv.origin, lo)
        # the grid covers the box, and vertex j of level l is S1 vertex j·2^(l-1)
        assert ((lv.dims - 1) * lv.spacing >= (hi - lo) - 1e-9).all()
        assert (np.diff(lv.vertex) > 0).all()
    np.testing.assert_array_equal(lgh.levels[-1].dims, [2, 2, 2])
    np.testing.assert_array_equal(lgh.levels[0].dims, [9, 4, 9])   # 360 x 120 x 360 in cells of 45
    # merged buffers hold every level in order, the levels' arrays are views of them
    for lv in lgh.levels:
        a, b = lgh.offsets[lv.level - 1], lgh.offsets[lv.level]
        np.testing.assert_array_equal(lgh.position[a:b], lv.position)
        np.testing.assert_array_equal(lgh.intensity[a:b], lv.intensity)


def numpy_count_s1(p, levels):
    """|S1| of an L-level hierarchy over ``p``, by the reference scatter of unit lights."""
    lo, hi = p.min(axis=0), p.max(axis=0)
    h1 = (hi - lo).max() / 2 ** (levels - 1)
    cells = np.maximum(np.ceil((hi - lo) / (hi - lo).max() * 2 ** (levels - 1) - 1e-9), 1).astype(np.int64)

    class Grid:
        origin, spacing, dims = lo, h1, cells + 1

    lum = np.ones(len(p))
    acc = ref_splat(p, np.ones((len(p), 3)), lum, p, lum, Grid.origin, Grid.spacing, Grid.dims)
    return int(np.count_nonzero(acc[1] > 0))


@pytest.mark.parametrize("n", [1000, 5000])
@pytest.mark.parametrize("box", [CITY, (1.0, 1.0, 1.0), (1.0, 1.0, 1e-3)], ids=["city", "unit", "flat"])
def test_auto_levels_follows_the_rule(device, n, box):
    p, inten = random_lights(n, box, seed=6)
    L = auto_levels(n, p, device=device)
    assert 1 <= L <= MAX_LEVELS
    # |S1| < n/2 at L, and not at L + 1 (paper 004 §4.3: the largest such L)
    assert count_s1(p, None, L, device) * 2 < n
    assert numpy_count_s1(p, L) * 2 < n
    assert numpy_count_s1(p, L + 1) * 2 >= n
    lgh = build_lgh(p, inten, device=device)
    assert lgh.stats["levels"] == L == len(lgh.levels)
    assert len(lgh.levels[0].position) * 2 < n


def test_auto_levels_edge_cases():
    assert auto_levels(0) == 1
    assert auto_levels(1, np.zeros((1, 3))) == 1
    # without positions: only the vertex-count bound (a cube)
    assert auto_levels(100_000) == 6   # 33^3 = 35,937 < 50,000 <= 65^3


def test_refuses_absurd_input():
    p, inten = random_lights(100, seed=7)
    with pytest.raises(UsdmlError, match="at most 12"):
        build_lgh(p, inten, levels=13)
    with pytest.raises(UsdmlError, match="vertices"):
        build_lgh(p, inten, levels=12)           # 2049 x 684 x 2049 S1 vertices
    with pytest.raises(UsdmlError, match="shape"):
        build_lgh(p[:, :2], inten)
    with pytest.raises(UsdmlError, match="shape"):
        build_lgh(p, inten[:10])
    with pytest.raises(UsdmlError, match="non-negative"):
        build_lgh(p, -inten)
    with pytest.raises(UsdmlError, match="NaN"):
        build_lgh(np.full((2, 3), np.nan), inten[:2])


def test_no_lights(device):
    lgh = build_lgh(np.zeros((0, 3)), np.zeros((0, 3), np.float32), device=device)
    assert len(lgh.levels) == 1 and len(lgh.levels[0].position) == 0
    assert lgh.levels[0].position.shape == (0, 3)


@pytest.mark.parametrize("on_planes", [False, True])
def test_split_scatter_matches_one_launch(monkeypatch, on_planes):
    # enough lights that the CPU scatter is split over concurrent x-slabs of one grid, then the lights
    # near the slab boundaries; lights exactly on grid planes test the float32 / float64 cell margin
    import usdml.lighting.lgh.build as lgh_module

    p, inten = random_lights(150_000, seed=8)
    if on_planes:
        lo, hi = p.min(0), p.max(0)
        h1 = float((hi - lo).max()) / 32               # levels=6: 32 S1 cells along the longest edge
        p[::2, 0] = lo[0] + np.floor((p[::2, 0] - lo[0]) / h1) * h1
    monkeypatch.setattr(lgh_module, "cpu_workers", lambda device: 3)
    split = build_lgh(p, inten, levels=6)
    assert split.stats["scatter_launches"] == 3   # 150k lights, >= 65,536 per slab: 2 slabs + boundary lights
    monkeypatch.setattr(lgh_module, "cpu_workers", lambda device: 1)
    single = build_lgh(p, inten, levels=6)
    assert single.stats["scatter_launches"] == 1
    for a, b in zip(split.levels, single.levels):
        np.testing.assert_array_equal(a.vertex, b.vertex)
        np.testing.assert_allclose(a.intensity, b.intensity, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(a.position, b.position, atol=1e-3)


def test_lobe_is_the_luminance_weighted_mean_normal(device):
    """Coplanar cosine emitters keep |ν| = 1 on every level; a sheet lit from both sides averages to ν ≈ 0;
    the luminance-weighted mean normal is the same on every level (the moments are conserved)."""
    rng = np.random.default_rng(4)
    p = np.concatenate([rng.random((2000, 3)) * [10, 0, 10], rng.random((2000, 3)) * [0, 10, 10]])
    p[:, 1] += 0.5                                  # off the grid planes
    inten = (rng.random((4000, 3)) + 0.1).astype(np.float32)
    up, side = np.array([0, 1, 0], np.float32), np.array([1, 0, 0], np.float32)
    normal = np.concatenate([np.tile(up, (2000, 1)), np.tile(side, (2000, 1))])
    lgh = build_lgh(p, inten, levels=4, device=device, normal=normal)
    lum = inten.astype(np.float64) @ LUMA
    mean = (lum[:, None] * normal).sum(axis=0) / lum.sum()
    for lv in lgh.levels:
        w = lv.intensity.astype(np.float64) @ LUMA
        np.testing.assert_allclose((w[:, None] * lv.lobe).sum(axis=0) / w.sum(), mean, atol=1e-4)
    floor_only = build_lgh(p[:2000], inten[:2000], levels=4, device=device, normal=normal[:2000])
    for lv in floor_only.levels:
        np.testing.assert_allclose(lv.lobe, np.tile(up, (len(lv.lobe), 1)), atol=1e-5)
    two_sided = build_lgh(p[:2000], inten[:2000], levels=3, device=device,
                          normal=np.where(np.arange(2000)[:, None] % 2 == 0, up, -up))
    top = two_sided.levels[-1]
    assert np.linalg.norm(top.lobe, axis=1).max() < 0.1
    assert build_lgh(p, inten, levels=3, device=device).lobe.max() == 0.0     # no normals: isotropic
    with pytest.raises(UsdmlError, match="normals"):
        build_lgh(p, inten, normal=normal[:10])
