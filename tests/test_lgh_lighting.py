"""LGH lighting (paper 004 §3.2–3.3): blending functions, streaming shadow-sample selection."""

from types import SimpleNamespace

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from usdml.kernels.lgh.shading import blend  # noqa: E402
from usdml.lighting.lgh.shading import LUMA, lgh_lighting  # noqa: E402


@wp.kernel
def _blend_sum(d: wp.array(dtype=float), levels: int, alpha: float, h1: float, out: wp.array(dtype=float)):
    i = wp.tid()
    total = float(0.0)
    for l in range(levels):
        total = total + blend(l, levels - 1, d[i], alpha * h1 * wp.pow(2.0, float(l)))
    out[i] = total


@pytest.mark.parametrize("levels,alpha", [(1, 1.0), (2, 1.0), (4, 1.0), (6, 2.0), (5, 0.5)])
def test_blending_functions_are_a_partition_of_unity(levels, alpha, device):
    wp.init()
    d = np.concatenate([np.linspace(0, 200, 4001), [1e-6, 1e6]]).astype(np.float32)
    out = wp.zeros(len(d), dtype=float, device=device)
    wp.launch(_blend_sum, dim=len(d), inputs=[wp.array(d, dtype=float, device=device), levels, alpha, 1.0, out],
              device=device)
    np.testing.assert_allclose(out.numpy(), 1.0, atol=1e-5)


def _one_level(positions, intensities, spacing=100.0):
    """A single-level hierarchy (blend == 1 everywhere) holding the given lights, one per vertex."""
    m = len(positions)
    return SimpleNamespace(h1=spacing, levels=[SimpleNamespace(
        level=1, spacing=spacing, origin=np.zeros(3), dims=np.array([m, 1, 1]),
        position=np.asarray(positions, np.float32), intensity=np.asarray(intensities, np.float32),
        variance=np.zeros(m, np.float32), vertex=np.arange(m))])


@pytest.mark.parametrize("samples,stratified", [(2, False), (16, False), (2, True), (16, True)])
def test_sampler_picks_lights_in_proportion_to_their_contribution(samples, stratified, device):
    """Appendix A's streaming picks and the stratified second sweep draw light i with probability f_i / F."""
    rng = np.random.default_rng(1)
    lights = np.array([[0, 5, 0], [3, 4, 1], [-2, 6, 2], [1, 2, -3], [4, 9, 0]], np.float32)
    inten = rng.uniform(0.2, 3.0, (5, 3)).astype(np.float32)
    n = 40000 // samples
    points = np.zeros((n, 3), np.float32)
    normals = np.tile(np.float32([0, 1, 0]), (n, 1))
    lgh = _one_level(lights, inten)
    out = lgh_lighting(points, normals, lgh, device=device, alpha=1.0, samples=samples, seed=3, clamp_distance=1e-3,
                       stratified=stratified)
    # analytic contributions f_i = lum(I_i) cos / d²
    d2 = (lights ** 2).sum(1)
    f = (inten @ LUMA) * (lights[:, 1] / np.sqrt(d2)) / d2
    expected_e = (inten * ((lights[:, 1] / np.sqrt(d2)) / d2)[:, None]).sum(0)
    np.testing.assert_allclose(out.irradiance[0], expected_e, rtol=1e-5)
    assert out.sample_ok.all()
    picks = out.sample_pos.reshape(-1, 3)
    idx = np.argmin(((picks[:, None, :] - lights[None]) ** 2).sum(-1), axis=1)
    counts = np.bincount(idx, minlength=5)
    exp = f / f.sum() * len(idx)
    chi2 = ((counts - exp) ** 2 / exp).sum()
    assert chi2 < 18.5            # chi-square, 4 degrees of freedom, p = 0.001
    # deterministic for a seed
    again = lgh_lighting(points[:100], normals[:100], lgh, device=device, samples=samples, seed=3, clamp_distance=1e-3,
                         stratified=stratified)
    assert np.array_equal(again.sample_pos, out.sample_pos[:100])
    if stratified:    # every pixel's k samples hold light i floor(k p_i) or ceil(k p_i) times
        per_pixel = idx.reshape(n, samples)
        for i in range(5):
            got = (per_pixel == i).sum(axis=1)
            share = samples * f[i] / f.sum()
            assert got.min() >= np.floor(share) and got.max() <= np.ceil(share)


def test_member_weights_leave_out_vpls_that_face_away(device):
    """Two VPLs of one grid light above a floor point, one facing it and one facing up (it sends nothing
    down) behind an occluder: weighing by luminance alone sees half the cluster blocked; weighing each
    sample by its own VPL's irradiance (``reweight``) sees the light unshadowed and casts no ray to the
    VPL facing away."""
    from usdml.lighting.lgh.shading import ClusterSampler, shadow_fraction

    vpl = np.array([[-0.5, 5, 0], [0.5, 5, 0]], np.float32)
    inten = np.ones((2, 3), np.float32)
    emit = np.array([[0, -1, 0], [0, 1, 0]], np.float32)
    lgh = _one_level([[0, 5, 0]], [[2, 2, 2]])
    n = 500
    pts = np.zeros((n, 3), np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (n, 1))
    shading = lgh_lighting(pts, nrm, lgh, device=device, samples=8, seed=2, clamp_distance=1e-3, jitter=False)
    cast = []

    def occluded(origins, targets, normals=None):
        cast.append(len(targets))
        return np.asarray(targets)[:, 0] > 0             # the VPL facing away is behind a wall

    plain = ClusterSampler(lgh, vpl, inten, emit, clamp_distance=1e-3)
    _, shadowed, rays = shadow_fraction(pts, nrm, shading, occluded, plain, seed=1)
    assert rays == 8 * n and 0.3 < (shadowed / shading.irradiance).mean() < 0.7
    own = ClusterSampler(lgh, vpl, inten, emit, reweight=True, clamp_distance=1e-3)
    _, shadowed, rays = shadow_fraction(pts, nrm, shading, occluded, own, seed=1)
    np.testing.assert_allclose(shadowed, shading.irradiance, rtol=1e-6)
    assert rays == cast[-1] < 0.7 * 8 * n                # about half the samples drew the other VPL


def test_lights_behind_the_surface_are_not_sampled(device):
    lgh = _one_level([[0, -5, 0], [0, 5, 0]], [[1, 1, 1], [1, 1, 1]])
    out = lgh_lighting(np.zeros((50, 3)), np.tile([0.0, 1.0, 0.0], (50, 1)), lgh, device=device, samples=1,
                       clamp_distance=1e-3)
    assert np.allclose(out.sample_pos[:, 0], [0, 5, 0])
    np.testing.assert_allclose(out.irradiance[:, 1], 1 / 25, rtol=1e-5)


def test_interleaved_sampling_is_unbiased_over_a_tile(device):
    """Each pixel of an n x n tile gathers 1/n² of the lights × n²: the tile average equals the full sum."""
    rng = np.random.default_rng(4)
    lights = rng.uniform([-5, 1, -5], [5, 6, 5], (37, 3)).astype(np.float32)
    inten = rng.uniform(0.1, 1.0, (37, 3)).astype(np.float32)
    lgh = _one_level(lights, inten)
    pts = np.zeros((16, 3), np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (16, 1))
    full = lgh_lighting(pts[:1], nrm[:1], lgh, device=device, samples=0, clamp_distance=1e-3).irradiance[0]
    tiled = lgh_lighting(pts, nrm, lgh, device=device, samples=0, clamp_distance=1e-3, tile=np.arange(16),
                         tiles=16).irradiance
    np.testing.assert_allclose(tiled.mean(0), full, rtol=1e-5)
    assert not np.allclose(tiled[0], full)


def _random_lights(seed: int, lights: int, points: int):
    """Lights in a 4 x 2 x 4 box over points on a floor facing up, and a 3-level LGH over the lights."""
    from usdml.lighting.lgh.build import build_lgh

    rng = np.random.default_rng(seed)
    pos = rng.uniform([-2, 1, -2], [2, 3, 2], (lights, 3)).astype(np.float32)
    inten = rng.uniform(0.1, 1.0, (lights, 3)).astype(np.float32)
    pts = rng.uniform([-2, 0, -2], [2, 0.5, 2], (points, 3)).astype(np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (points, 1))
    return pos, inten, build_lgh(pos, inten, levels=3), pts, nrm


def test_s0_start_is_exact_when_every_light_is_in_its_reach(device):
    """With S0 the input lights are the finest level: once r_0 = alpha h_1 / 2 covers every light, the
    blending leaves all the weight on S0 and the LGH sum is the brute-force sum, light by light."""
    lights, inten, lgh, pts, nrm = _random_lights(7, 300, 64)
    clamp = 0.05
    alpha = 2 * 20.0 / lgh.h1               # r_0 = 20: far beyond the 4 x 2 x 4 box
    w = lights[None].astype(np.float64) - pts[:, None]
    d2 = (w ** 2).sum(-1)
    g = np.maximum(w[..., 1], 0) / np.sqrt(d2) / np.maximum(d2, clamp ** 2)
    exact = (g[..., None] * inten[None]).sum(1)
    s0 = lgh_lighting(pts, nrm, lgh, device=device, alpha=alpha, samples=0, clamp_distance=clamp, s0=(lights,
                      inten)).irradiance
    np.testing.assert_allclose(s0, exact, rtol=1e-4)
    s1 = lgh_lighting(pts, nrm, lgh, device=device, alpha=1.0, samples=0, clamp_distance=clamp).irradiance
    assert np.abs(s1 - exact).max() / exact.max() > 1e-2     # S1 alone is an approximation


def test_s0_samples_point_at_the_input_lights(device):
    """A shadow sample drawn on an S0 light carries index M + i and the light's own position."""
    from usdml.lighting.lgh.shading import ClusterSampler

    lights, inten, lgh, pts, nrm = _random_lights(8, 200, 400)
    out = lgh_lighting(pts, nrm, lgh, device=device, alpha=2.0, samples=4, clamp_distance=0.05, s0=(lights, inten))
    grid = sum(len(lv.position) for lv in lgh.levels)
    picked = out.sample_light[out.sample_ok]
    own = picked >= grid
    assert own.any() and (~own).any()
    np.testing.assert_allclose(out.sample_pos[out.sample_ok][own], lights[picked[own] - grid])
    sampler = ClusterSampler(lgh, lights, inten)
    targets = sampler.targets(picked, out.sample_pos[out.sample_ok], seed=0)
    np.testing.assert_allclose(targets[own], lights[picked[own] - grid])


def test_shadowed_estimate_is_unbiased_per_colour_channel(device):
    """A red light that is blocked and a green one that is not: the shadowed estimate F · mean(V e / f)
    averages to the green light's irradiance alone; a luminance visibility fraction would tint it."""
    from usdml.lighting.lgh.shading import shadow_fraction

    lights = np.array([[-1, 4, 0], [1, 4, 0]], np.float32)
    inten = np.array([[4, 0, 0], [0, 1, 0]], np.float32)
    n = 20000
    pts = np.zeros((n, 3), np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (n, 1))
    shading = lgh_lighting(pts, nrm, _one_level(lights, inten), device=device, samples=4, seed=5, clamp_distance=1e-3)

    def occluded(origins, targets, normals=None):
        return np.asarray(targets)[:, 0] < 0          # the red light (x = -1) is behind a wall

    visible, shadowed, rays = shadow_fraction(pts, nrm, shading, occluded)
    assert rays == 4 * n
    g = 4 / 17 ** 1.5                                   # cos / d² for both lights
    np.testing.assert_allclose(shadowed.mean(0), [0, g, 0], atol=0.015 * g)   # ~4 sigma over 80k samples
    assert shadowed[:, 0].max() == 0


def test_filter_iterations_follow_the_samples():
    from usdml.lighting.lgh.shading import filter_iterations_for

    assert [filter_iterations_for(k) for k in (1, 4, 8, 16, 32, 64, 1024)] == [4, 3, 3, 2, 2, 1, 0]


def _blend_np(level, top, d, r):
    """NumPy copy of kernels.lgh_lighting.blend."""
    if level == top and level == 0:
        return np.ones_like(d)
    w = np.ones_like(d)
    if level > 0:
        x = np.clip((d - 0.5 * r) / (0.5 * r), 0, 1)
        w = x * x * (3 - 2 * x)
    if level < top:
        y = np.clip((d - r) / r, 0, 1)
        w = w * (1 - y * y * (3 - 2 * y))
    return w


@pytest.mark.parametrize("alpha,start", [(1.0, 1), (2.0, 1), (1.5, 0)])
def test_gather_visits_every_grid_light_that_counts(alpha, start, device):
    """The kernel visits only the vertices near a point; the sum must equal the blended sum over every
    grid light of every level (and every input light as S0), computed without any window."""
    from usdml.lighting.lgh.build import build_lgh

    rng = np.random.default_rng(11)
    lights = rng.uniform([-3, 0, -3], [3, 2, 3], (2000, 3)).astype(np.float32)
    inten = rng.uniform(0.1, 1.0, (2000, 3)).astype(np.float32)
    lgh = build_lgh(lights, inten, levels=4)
    pts = rng.uniform([-3.5, -0.5, -3.5], [3.5, 2.5, 3.5], (300, 3)).astype(np.float32)
    nrm = rng.normal(size=(300, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    clamp = 0.05
    s0 = (lights, inten) if start == 0 else None
    got = lgh_lighting(pts, nrm, lgh, device=device, alpha=alpha, samples=0, clamp_distance=clamp, s0=s0).irradiance
    layers = ([(lights, inten, 0.5 * lgh.h1)] if start == 0 else []) + \
        [(lv.position, lv.intensity, lv.spacing) for lv in lgh.levels]
    top = len(layers) - 1
    want = np.zeros((300, 3))
    for index, (pos, inte, h) in enumerate(layers):
        w = pos[None].astype(np.float64) - pts[:, None]
        d2 = (w ** 2).sum(-1)
        d = np.sqrt(d2)
        cos = np.maximum((w * nrm[:, None]).sum(-1) / d, 0)
        g = _blend_np(index, top, d, alpha * h) * cos / np.maximum(d2, clamp ** 2)
        want += (g[..., None] * inte[None]).sum(1)
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-6 * want.max())


@pytest.mark.parametrize("start", [1, 0])
def test_one_cosine_emitter_is_lambertian_at_every_distance(start, device):
    """A VPL with a normal is the Lambertian emitter Φ·cos θ_l / π (I = Φ/4π, lobe 4·max(0, cos θ_l)) on
    every level: its grid lights share its position and normal, and the blending weights sum to one.
    Analytic reference: E = Φ cos θ_l cos θ_s / (π d²)."""
    from usdml.lighting.lgh.build import build_lgh

    q = np.array([[0.3, 0.2, -0.1]], np.float32)
    n_l = np.array([[0.0, 0.6, 0.8]], np.float32)
    flux = np.array([[2.0, 1.0, 0.5]], np.float32)
    inten = flux / np.float32(4 * np.pi)
    lgh = build_lgh(q, inten, levels=3, normal=n_l)
    rng = np.random.default_rng(8)
    pts = (q + rng.normal(size=(400, 3)) * [0.3, 3, 3]).astype(np.float32)
    w = q - pts
    d = np.linalg.norm(w, axis=1, keepdims=True)
    nrm = (w / d).astype(np.float32)                               # receivers face the light
    s0 = (q, inten, n_l) if start == 0 else None
    got = lgh_lighting(pts, nrm, lgh, device=device, alpha=1.0, samples=0, clamp_distance=1e-4, s0=s0).irradiance
    cos_l = np.maximum(-(w / d) @ n_l[0], 0.0)
    want = flux * (cos_l / (np.pi * d[:, 0] ** 2))[:, None]
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-7)
    assert (got[cos_l == 0] == 0).all() and (cos_l == 0).sum() > 100     # nothing behind its surface


def test_sample_runs_and_guide_table():
    """sample_runs numbers a point's consecutive samples on one light; the guide table's cut points
    lead a forward step to the row a binary search over the group finds, for any draw."""
    from usdml.lighting.lgh.shading import _guide_table, sample_runs

    rank, length = sample_runs(np.array([5, 5, 7, 7, 7, 5, 5, 2]), 4)      # two points of 4 samples
    np.testing.assert_array_equal(rank, [0, 1, 0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(length, [2, 2, 2, 2, 1, 2, 2, 1])
    rng = np.random.default_rng(4)
    w = rng.random(300) ** 4
    w[rng.random(300) < 0.1] = 0.0                                           # zero-luminance members too
    cum = np.concatenate([[0.0], np.cumsum(w)])
    start, stop = np.array([0, 7, 7, 150]), np.array([7, 7, 150, 300])       # an empty group among them
    guide = _guide_table(cum, start, stop)
    # kernels/lgh/lghq.c's table (where built) is NumPy's, cut point for cut point
    np.testing.assert_array_equal(guide, _guide_table(cum, start, stop, compiled=False))
    for lo, hi in zip(start, stop):
        if hi <= lo:
            continue
        for x in cum[lo] + rng.random(500) * (cum[hi] - cum[lo]):
            want = lo + np.searchsorted(cum[lo:hi], x, side="right") - 1          # last row with cum <= x
            share = min(max(int((x - cum[lo]) / (cum[hi] - cum[lo]) * (hi - lo)), 0), hi - lo - 1)
            a = guide[lo + share]
            assert cum[a] <= x
            while a + 1 < hi and cum[a + 1] <= x:
                a += 1
            assert a == want


def test_light_runs_counts_each_chosen_samples_light():
    """light_runs (sorted rows by runs, others sorted first) against counting every pair of a point's samples."""
    from usdml.lighting.lgh.shading import light_runs

    rng = np.random.default_rng(3)
    for trial in range(60):
        n, k = int(rng.integers(1, 12)), int(rng.integers(1, 30))
        light = rng.integers(-1, int(rng.integers(1, 9)), (n, k))
        if trial % 2:                   # every light its own light: the systematic draws come in order
            light = np.sort(light, axis=1)
        ok = (light >= 0) & (rng.random((n, k)) < 0.85)
        pairs = ((light[:, :, None] == light[:, None, :]) & ok[:, None, :]).sum(axis=2)
        got = light_runs(light, ok)
        assert np.array_equal(got[ok], pairs[ok])
        assert (got[~ok] == 1).all()
