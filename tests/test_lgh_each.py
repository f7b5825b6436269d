"""Every VPL its own light (``--lgh-split each``, usdml.lighting.lgh.each): the sum against analytic Lambertian
emitters, the shadow draws against the lights' own shares, the shadowed estimate against an analytic occluder
(no code shared with the kernel), the frame's choice, and a frame against brute force."""

import numpy as np
import pytest

from usdml.lighting.lgh.each import EachLight, uniform
from usdml.lighting.lgh.shading import LUMA, shadow_fraction
from usdml.lighting.lgh.native import library

COMPILED = [True, pytest.param(False, id="numpy")]


def _unit(v):
    v = np.asarray(v, np.float64)
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _lights(n: int, seed: int):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 3)).astype(np.float32)
    return q, _unit(rng.normal(size=(n, 3))), rng.uniform(0.2, 2.0, size=(n, 3)).astype(np.float32)


def _analytic(pts, pn, q, n_l, flux, mpu=1.0):
    """E = Σ Φ cos θ_l cos θ_s / (π d²) per point, in float64 (no clamp: every light farther than it)."""
    w = q[None].astype(np.float64) - pts[:, None]
    d = np.linalg.norm(w, axis=2)
    cos_l = np.maximum(-((w / d[..., None]) * n_l[None]).sum(2), 0.0)
    cos_s = np.maximum(((w / d[..., None]) * pn[:, None]).sum(2), 0.0)
    return cos_l * cos_s / (np.pi * d ** 2) / mpu ** 2, flux.astype(np.float64)


def _gather(q, n_l, flux, k, seed, compiled, mpu=1.0, clamp=1e-4):
    if compiled and library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    return EachLight((q, flux / np.float32(4 * np.pi), n_l)).gather(k, seed, mpu, clamp, compiled=compiled)


@pytest.mark.parametrize("compiled", COMPILED)
def test_the_sum_is_every_light_as_a_cosine_emitter(compiled):
    """37 lights: two blocks of sixteen and a padded remainder, against the analytic sum."""
    q, n_l, flux = _lights(37, 4)
    rng = np.random.default_rng(5)
    pts = (rng.normal(size=(200, 3)) * 4).astype(np.float32)
    pts = pts[np.linalg.norm(pts, axis=1) > 4.5]         # every light well away from the points (no clamp)
    pn = _unit(rng.normal(size=(len(pts), 3)))
    got = _gather(q, n_l, flux, 0, 0, compiled, mpu=2.0)(pts, pn).irradiance
    g, phi = _analytic(pts, pn, q, n_l, flux, mpu=2.0)
    np.testing.assert_allclose(got, g @ phi, rtol=2e-5, atol=1e-9)
    assert (got.sum(1) == 0).any() and (got > 0).any()


@pytest.mark.parametrize("compiled", COMPILED)
@pytest.mark.parametrize("kind", ["isotropic", "mixed"])
def test_the_sum_of_point_lights_and_of_a_mix(compiled, kind):
    """The stage's own lights as ``--direct lgh`` gives them (``grid_sources``): 53 point lights, E = Σ I cos θ_s /
    d², or a mix of those with disk-like one-sided emitters (``I / 4`` about a unit normal, ``4 cos θ_l``), against
    the analytic sum; the count is the lights whose term is above 0."""
    q, n_l, inten = _lights(53, 12)
    normals = None
    if kind == "mixed":
        normals = np.where((np.arange(53) % 3 == 0)[:, None], n_l, 0.0).astype(np.float32)
    rng = np.random.default_rng(6)
    pts = (rng.normal(size=(200, 3)) * 4).astype(np.float32)
    pts = pts[np.linalg.norm(pts, axis=1) > 4.5]
    pn = _unit(rng.normal(size=(len(pts), 3)))
    if compiled and library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    s = EachLight((q, inten, normals)).gather(0, 0, 0.5, 1e-4, compiled=compiled)(pts, pn)
    w = q[None].astype(np.float64) - pts[:, None]
    d = np.linalg.norm(w, axis=2)
    cos_s = np.maximum(((w / d[..., None]) * pn[:, None]).sum(2), 0.0)
    lobe = np.ones(len(q))[None, :] * np.ones_like(d)
    if normals is not None:
        cos_l = np.maximum(-((w / d[..., None]) * n_l[None]).sum(2), 0.0)
        lobe = np.where((np.arange(53) % 3 == 0)[None, :], 4.0 * cos_l, 1.0)
    g = cos_s * lobe / d ** 2 / 0.5 ** 2
    np.testing.assert_allclose(s.irradiance, g @ inten.astype(np.float64), rtol=2e-5, atol=1e-9)
    np.testing.assert_array_equal(s.count, (g > 0).sum(1))
    assert ((s.count > 0) & (s.count < len(q))).any()        # some points face some of the lights only


@pytest.mark.parametrize("compiled", COMPILED)
def test_shadow_draws_follow_each_lights_share_of_the_light(compiled):
    """One point, 40 lights, 64 draws per seed over 400 seeds: each light drawn in proportion to its luminance at
    the point (within 5 standard errors of the count), none that sends the point nothing, and each draw's
    weight times its luminance is its RGB light."""
    q, n_l, flux = _lights(40, 7)
    p = np.zeros((1, 3), np.float32)
    pn = _unit([[0.2, 1.0, 0.1]])
    g, phi = _analytic(p, pn, q, n_l, flux)
    e = g[0][:, None] * phi                                 # (L, 3)
    share = (e @ LUMA) / (e @ LUMA).sum()
    counts = np.zeros(len(q))
    for seed in range(400):
        s = _gather(q, n_l, flux, 64, seed, compiled)(p, pn)
        assert s.sample_ok.all()
        np.add.at(counts, s.sample_light[0], 1)
        np.testing.assert_allclose(s.sample_weight[0] * s.sample_lum[0][:, None], e[s.sample_light[0]], rtol=1e-4)
    expect = share * counts.sum()
    assert counts[share == 0].sum() == 0 and (share == 0).any()
    assert np.all(np.abs(counts - expect) <= 5 * np.sqrt(expect) + 1), np.c_[counts, expect]


def test_compiled_and_numpy_draw_the_same_lights():
    """The same uniform per point (Warp's PCG in NumPy): the same draws but where rounding moves a threshold."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    q, n_l, flux = _lights(500, 9)
    rng = np.random.default_rng(1)
    pts = (rng.normal(size=(300, 3)) * 3).astype(np.float32)
    pn = _unit(rng.normal(size=(300, 3)))
    a = _gather(q, n_l, flux, 8, 3, True)(pts, pn, first=100)
    b = _gather(q, n_l, flux, 8, 3, False)(pts, pn, first=100)
    np.testing.assert_allclose(a.irradiance, b.irradiance, rtol=1e-4, atol=1e-9)
    assert (a.sample_ok == b.sample_ok).all()
    assert (a.sample_light == b.sample_light).mean() > 0.99
    assert 0.0 <= uniform(3, np.arange(5)).min() and uniform(3, np.arange(5)).max() < 1.0


def _culled_and_not(sums, pts: np.ndarray, pn: np.ndarray, k: int = 8) -> list[tuple]:
    """``EachLights.gather`` of every point with and without its skips (chunks behind the points, groups of the
    points' own normal), asserted the same bit for bit: the two outputs."""
    n = len(pts)
    outs = []
    for cull in (True, False):
        out = (np.zeros((n, 3), np.float32), np.zeros(n, np.float32), np.zeros((n, k), np.int32),
               np.zeros((n, k, 3), np.float32), np.zeros((n, k), np.float32), np.zeros((n, k), np.uint8))
        sums.gather(pts, pn, 1e-6, 1.0, k, 3, 0, 0, n, out, cull=cull)
        outs.append(out)
    for x, y in zip(*outs):
        np.testing.assert_array_equal(x, y)
    return outs


def test_the_compiled_sum_over_chunks_and_tiles():
    """``lghq_each`` takes its lights in chunks of 4,096 over tiles of 32 points, keeping each point's running sums
    between chunks: 9,000 point lights (three chunks, the last one padded) at 45 points (a tile and a part), against
    the NumPy sum and draws of the same lights and uniforms."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    rng = np.random.default_rng(21)
    q = (rng.normal(size=(9000, 3)) * 6).astype(np.float32)
    inten = rng.uniform(0.01, 1.0, size=(9000, 3)).astype(np.float32)
    pts = (rng.normal(size=(45, 3)) * 2).astype(np.float32)
    pn = _unit(rng.normal(size=(45, 3)))
    lights = EachLight((q, inten, None))
    a = lights.gather(8, 5, 1.0, 1e-3, compiled=True)(pts, pn, first=7)
    b = lights.gather(8, 5, 1.0, 1e-3, compiled=False)(pts, pn, first=7)
    np.testing.assert_allclose(a.irradiance, b.irradiance, rtol=1e-4)
    np.testing.assert_array_equal(a.count, b.count)
    assert (a.count > 1000).all() and a.sample_ok.all()
    assert (a.sample_light == b.sample_light).mean() > 0.99
    # a point skips the chunks of lights behind its tangent plane: the same answers, bit for bit
    from usdml.lighting.lgh.native import EachLights

    q2 = np.column_stack([rng.uniform(-20, 20, 20000), rng.uniform(0, 4, 20000), rng.uniform(-20, 20, 20000)])
    sums = EachLights(*(EachLight((q2, np.ones((20000, 3), np.float32), None)).__dict__[k]
                        for k in ("position", "intensity", "normal")))
    flat = np.column_stack([rng.uniform(-5, 5, 40), np.zeros(40), rng.uniform(-5, 5, 40)]).astype(np.float32)
    facing = np.tile(np.float32([1, 0, 0]), (40, 1))          # half the lights behind each point
    outs = _culled_and_not(sums, flat, facing)
    assert (outs[0][1] < 15000).all() and (outs[0][1] > 5000).all()


def test_a_floors_vpls_are_skipped_by_the_floors_points():
    """VPLs on a floor and on a wall (cosine emitters, two normal classes) and points on the floor: the lights come
    ordered by class, a group whose one normal is both points' normal is skipped (every term there is 0: cos θ_s
    and cos θ_l are one dot product and its negation), with the same answers bit for bit, and the sums and counts
    are NumPy's, where the floor's own VPLs reach no floor point."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    from usdml.lighting.lgh.each import CLASS_LIGHTS
    from usdml.lighting.lgh.native import EachLights

    rng = np.random.default_rng(8)
    nf, nw = 3000, 1100
    floor = np.column_stack([rng.uniform(-4, 4, nf), np.zeros(nf), rng.uniform(-4, 4, nf)])
    wall = np.column_stack([np.full(nw, -4.0), rng.uniform(0, 3, nw), rng.uniform(-4, 4, nw)])
    q = np.concatenate([floor, wall])[rng.permutation(nf + nw)]
    up = (q[:, 1] == 0) & (q[:, 0] > -4.0)
    n_l = np.where(up[:, None], np.float32([0, 1, 0]), np.float32([1, 0, 0])).astype(np.float32)
    flux = rng.uniform(0.1, 1.0, (nf + nw, 3)).astype(np.float32)
    lights = EachLight((q, flux, n_l))
    assert nf >= CLASS_LIGHTS and (lights.normal[:nf] == [0, 1, 0]).all()     # the floor's class first
    pts = np.column_stack([rng.uniform(-3, 3, 50), np.zeros(50), rng.uniform(-3, 3, 50)]).astype(np.float32)
    pn = np.tile(np.float32([0, 1, 0]), (50, 1))
    sums = EachLights(lights.position, lights.intensity, lights.normal)
    assert sums.shared > 0.6
    _culled_and_not(sums, pts, pn)
    a = lights.gather(8, 3, 1.0, 1e-3, compiled=True)(pts, pn)
    b = lights.gather(8, 3, 1.0, 1e-3, compiled=False)(pts, pn)
    np.testing.assert_allclose(a.irradiance, b.irradiance, rtol=1e-4)
    np.testing.assert_array_equal(a.count, b.count)
    assert (a.count <= nw).all() and (a.count > 0.3 * nw).all()                # the wall's VPLs only
    assert not np.isin(a.sample_light[a.sample_ok], np.flatnonzero(up)).any()   # (in the order given)


def _square_occluder(points, targets, normals=None, distant=None):
    """Analytic: a unit square at z = 0.5 (|x|, |y| < 1) blocks a segment that crosses it."""
    p, t = np.asarray(points, np.float64), np.asarray(targets, np.float64)
    dz = t[:, 2] - p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (0.5 - p[:, 2]) / dz
    x = p + s[:, None] * (t - p)
    return (s > 0) & (s < 1) & (np.abs(x[:, 0]) < 1) & (np.abs(x[:, 1]) < 1)


@pytest.mark.parametrize("compiled", COMPILED)
def test_the_shadowed_estimate_is_unbiased_against_an_analytic_occluder(compiled):
    """Lights above a square, points below it: F · mean(V · e / f) over the draws, averaged over 300 seeds, is
    every light's visible sum (each light's visibility from the occluder itself) within 4 standard errors,
    per colour channel; and where a point sees every light its luminance is exact in one draw."""
    rng = np.random.default_rng(11)
    q = np.column_stack([rng.uniform(-2, 2, 60), rng.uniform(-2, 2, 60), rng.uniform(1.0, 2.0, 60)]).astype(np.float32)
    n_l = np.tile(np.float32([0, 0, -1]), (60, 1))
    flux = rng.uniform(0.2, 2.0, size=(60, 3)).astype(np.float32)
    pts = np.column_stack([rng.uniform(-1.5, 1.5, 20), rng.uniform(-1.5, 1.5, 20), np.zeros(20)]).astype(np.float32)
    pts[0] = [30.0, 0.0, 0.0]                          # sees every light past the square's edge
    pn = np.tile(np.float32([0, 0, 1]), (20, 1))
    g, phi = _analytic(pts, pn, q, n_l, flux)
    seen = np.array([~_square_occluder(np.repeat(p[None], 60, 0), q) for p in pts])
    want = (g * seen) @ phi
    runs = []
    for seed in range(300):
        s = _gather(q, n_l, flux, 4, seed, compiled)(pts, pn)
        runs.append(shadow_fraction(pts, pn, s, _square_occluder, None, seed)[1])
    runs = np.array(runs, np.float64)
    mean, err = runs.mean(0), runs.std(0) / np.sqrt(len(runs))
    assert np.all(np.abs(mean - want) <= 4 * err + 1e-6 * want.max()), np.c_[mean[:, 0], want[:, 0]]
    # the point that sees every light: each draw's luminance is the lights' whole luminance (its colours vary)
    assert seen[0].all() and np.allclose(runs[:, 0] @ LUMA, want[0] @ LUMA, rtol=1e-4)
    assert (want < (g @ phi) * 0.9).any()             # the square shadows some points


def test_the_frame_chooses_every_vpl_where_no_alpha_costs_less():
    """``choose(each=True)``: every VPL where no hierarchy's α fits under its cost (no pilot, no split one
    built); the hierarchy's cheapest α within target where one does; ``--lgh-split each`` whatever the rest, and
    an explicit α or split never."""
    from usdml.lighting.lgh.build import build_lgh, build_lgh_split
    from usdml.lighting.lgh.choice import choose
    from test_lgh_split import _ground_and_wall

    pos, inten, nrm, pts, pn = _ground_and_wall(500)
    sources = (pos, inten, nrm)
    one = build_lgh(pos, inten, normal=nrm)
    split = build_lgh_split(pos, inten, nrm)

    def refuse():
        raise AssertionError("the split hierarchy was built")

    cheap = choose(one, refuse, pts, pn, sources, clamp_distance=0.05, each=True, each_cost=1e-3)
    assert cheap.split == "each" and len(cheap.lgh) == len(pos) and "pilot" not in cheap.candidates["none"]
    # every VPL as dear as visiting each: the hierarchy, as without it
    dear = choose(one, lambda: split, pts, pn, sources, clamp_distance=0.05, fraction=10.0, each=True, each_cost=1.0)
    plain = choose(one, lambda: split, pts, pn, sources, clamp_distance=0.05, fraction=10.0)
    assert (dear.split, dear.alpha) == (plain.split, plain.alpha) and dear.split == "normal"
    # some α fit under its cost, none within a target of 0: every VPL, after the pilot tried them
    strict = choose(one, lambda: split, pts, pn, sources, clamp_distance=0.05, fraction=10.0, each=True,
                    each_cost=1.0, target=0.0)
    assert strict.split == "each" and len(strict.candidates["normal"]["pilot"]) == 9
    assert choose(None, refuse, pts, pn, sources, split="each", clamp_distance=0.05).split == "each"
    assert choose(one, refuse, pts, pn, sources, alpha=2.0, split="none", clamp_distance=0.05, each=True,
                  each_cost=1e-3).split == "none"


def test_a_frame_lit_by_every_vpl_against_brute_force():
    """cornell at 48 px, 3,000 VPLs, the defaults: the frame takes every VPL (no α), and its indirect light is
    within 8 % of brute force's and closer than the paper's single hierarchy at α 1 (measured 5.5 % and 14.8 %)."""
    from conftest import STAGES
    from usdml.compare import compare_gi
    from usdml.stage import StageDelegate

    r = compare_gi(StageDelegate(str(STAGES / "cornell.usda")), "lgh", "vpl-bruteforce", frame=1, image_width=48,
                   overrides={"vpl_count": 3000})
    assert r["lgh_split"] == "each" and r["lgh_alpha"] is None, (r["lgh_split"], r["lgh_alpha"])
    assert r["rel_rmse"] < 0.08, r["rel_rmse"]
    forced = compare_gi(StageDelegate(str(STAGES / "cornell.usda")), "lgh", "vpl-bruteforce", frame=1,
                        image_width=48, overrides={"vpl_count": 3000, "lgh_split": "none", "lgh_alpha": 1.0})
    assert forced["rel_rmse"] > r["rel_rmse"], (forced["rel_rmse"], r["rel_rmse"])


def test_the_sums_lanes_are_the_cpus():
    """``lghq_each_lanes`` (which function clone runs) against the CPU's flags where Linux lists them."""
    from pathlib import Path

    from usdml.lighting.lgh.choice import EACH_VISIT_COSTS, each_visit_cost
    from usdml.lighting.lgh.native import each_lanes

    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    info = Path("/proc/cpuinfo")
    lanes = each_lanes()
    assert lanes in EACH_VISIT_COSTS and each_visit_cost() == EACH_VISIT_COSTS[lanes]
    if lanes and info.exists():
        flags = next((line.split(":", 1)[1].split() for line in info.read_text().splitlines()
                      if line.startswith("flags")), [])
        assert lanes == (16 if "avx512f" in flags else 8 if "avx2" in flags else 4)


def test_compare_says_what_the_frame_lit_with():
    """``usdml compare --gi lgh``'s line names every VPL, or the hierarchy and its α."""
    from usdml.compare import format_gi_comparison

    r = {"gi": "lgh", "against": "vpl-bruteforce", "pixels": 312, "vpls": 2000, "rel_rmse": 0.059, "speedup": 6.4,
         "seconds": {"lgh": 0.14, "vpl-bruteforce": 0.89}, "lgh_split": "each", "lgh_alpha": None}
    assert format_gi_comparison(r).startswith("lgh (every VPL its own light) vs vpl-bruteforce on 312 pixels")
    assert "(one hierarchy per normal class, α 2)" in format_gi_comparison(dict(r, lgh_split="normal", lgh_alpha=2.0))
    assert "(one hierarchy, α 1.5)" in format_gi_comparison(dict(r, lgh_split="none", lgh_alpha=1.5))
