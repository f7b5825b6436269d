"""``--gi svo`` (paper 003): interleaved VPL subsets, the clamped geometry term, the tile filter, the
light-path VPLs as an RSM, and the pass end to end against ``vpl-bruteforce``."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from conftest import STAGES
from usdml.aov.exr import read_exr
from usdml.cli import main
from usdml.compare import compare_gi
from usdml.lighting import interleaved as il
from usdml.lighting.atrous import tile_index
from usdml.lighting.direct import shade_direct
from usdml.lighting.vpl import LUMA, VPLs, generate_vpls
from usdml.render.frame import FrameRenderer
from usdml.scene import diff
from usdml.scene.light_table import smoothstep_cone
from usdml.scene.surface import surface_at_hits
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate
from usdml.visibility import ExactBackend


def _random_vpls(rng, n):
    pos = rng.uniform(-1.0, 1.0, (n, 3)) + np.array([0.0, 0.0, 2.0])
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = -np.abs(nrm[:, 2]) - 0.2              # facing down, toward the receivers at z = 0
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flux = rng.uniform(0.5, 2.0, (n, 3)).astype(np.float32)
    return VPLs(pos, nrm.astype(np.float32), flux, np.ones(n, np.int8), n)


def test_each_pixel_gathers_its_tile_subset_times_sixteen():
    """Pixel (x, y) gathers the VPLs j with j mod 16 = (x mod 4) + 4 (y mod 4), weighted 16."""
    assert tile_index(4, 4, 4)[1, 2] == 2 + 4 * 1
    subsets = il.vpl_subsets(37)
    assert sorted(np.concatenate(subsets).tolist()) == list(range(37))       # a partition
    assert all((s % 16 == t).all() for t, s in enumerate(subsets))
    rng = np.random.default_rng(3)
    vpls = _random_vpls(rng, 53)
    intensity = (vpls.flux / np.pi).astype(np.float32)
    # 16 pixels at the same point, one per tile: each sees exactly its subset, and their mean is the full sum
    p = np.zeros((16, 3))
    n = np.tile([0.0, 0.0, 1.0], (16, 1))
    got = il.gather_interleaved(p, n, np.arange(16), vpls.position, vpls.normal, intensity, None, 1e-4).irradiance
    for t, s in enumerate(il.vpl_subsets(53)):
        g = il.clamped_geometry(p[:1], n[:1], vpls.position[s], vpls.normal[s], 1e-4)
        np.testing.assert_allclose(got[t], 16.0 * (g @ intensity[s])[0], rtol=1e-5)
    # the same VPL model as vpl-bruteforce: one-sided disk lights of Φ/π through direct shading
    full = shade_direct(p[:1], n[:1], np.full((1, 3), np.pi, np.float32), vpls.as_lights(isotropic=False), None,
                        min_distance=1e-2).radiance[0]
    np.testing.assert_allclose(got.mean(axis=0), full, rtol=1e-4)
    assert not np.allclose(got.mean(axis=0) / 16.0, full, rtol=0.5)           # without the 16x it is far off


def test_targets_are_lifted_off_their_surface_by_the_backends_voxels():
    """The rays go to each VPL moved target_lift along its normal; target_lift is one of the backend's
    voxels (describe()["voxel_size"]), none for exact."""
    rng = np.random.default_rng(5)
    vpls = _random_vpls(rng, 32)
    asked = []

    def occluded(origins, targets, normals=None, distant=None):
        asked.append((origins, targets, normals))
        return np.zeros(len(origins), bool)

    p, n = np.zeros((16, 3)), np.tile([0.0, 0.0, 1.0], (16, 1))
    il.gather_interleaved(p, n, np.arange(16), vpls.position, vpls.normal, vpls.flux, occluded, 1e-4,
                          target_lift=0.25)
    targets = np.concatenate([t for _, t, _ in asked])
    lifted = vpls.position + 0.25 * vpls.normal
    assert 24 <= len(targets) <= 32           # one ray per VPL with G > 0
    assert all(np.isclose(lifted, t).all(axis=1).any() for t in targets)
    assert (np.concatenate([nn for _, _, nn in asked]) == [0.0, 0.0, 1.0]).all()   # the pixels' normals

    class Voxels:
        def describe(self):
            return {"voxel_size": 0.04}

    assert il.target_lift(Voxels()) == pytest.approx(0.04 * il.TARGET_LIFT_VOXELS)
    assert il.target_lift(ExactBackend()) == 0.0


def test_clamped_geometry_term_by_hand():
    """Eq. 2-4 at p = 0, n = +z, VPL at (1, 0, 1) facing -z: cos θ_i = cos θ_o = 1/√2, d² = 2."""
    p, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    q = np.array([[1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 0.0, -1.0]])
    m = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # facing p, facing away, below p
    np.testing.assert_allclose(il.clamped_geometry(p, n, q, m, 0.5), [[0.25, 0.0, 0.0]], rtol=1e-6)
    np.testing.assert_allclose(il.clamped_geometry(p, n, q[:1], m[:1], 4.0), [[0.125]], rtol=1e-6)   # clamped: /B
    # d in metres: a centimetre stage's G is 10^4 larger per square metre... of scene units
    np.testing.assert_allclose(il.clamped_geometry(p, n, q[:1], m[:1], 0.5, meters_per_unit=0.01), [[2500.0]],
                               rtol=1e-6)
    # a VPL in front of the shading normal but behind the geometric one gives nothing
    tilted = il.clamped_geometry(p, n, q[:1], m[:1], 0.5, geometric=np.array([[-1.0, 0.0, 0.0]]))
    assert tilted[0, 0] == 0.0


def _crease(h=16, w=16):
    """A floor (normal +y, x < 8) meeting a wall (normal +x, x >= 8) at a 90° crease; the floor's
    irradiance is 1 with a 4x4 interleaving pattern of mean 1 on it, the wall's 0.2."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    floor = x < w // 2
    pos = np.where(floor[..., None], np.stack([x, np.zeros_like(x), y], -1),
                   np.stack([np.full_like(x, w // 2), x - w // 2 + 0.5, y], -1))
    nrm = np.where(floor[..., None], np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    pattern = (np.arange(16) % 5 + 1.0)[tile_index(h, w, 4)]
    pattern /= pattern[:4, :4].mean()
    value = np.where(floor, pattern, 0.2)[..., None].repeat(3, -1)
    return value.astype(np.float32), nrm, pos, np.ones((h, w), bool), floor


def test_tile_filter_removes_the_pattern_and_keeps_the_crease():
    value, nrm, pos, valid, floor = _crease()
    out = il.tile_filter(value, nrm, pos, valid)
    inner = floor.copy()
    inner[:2], inner[-2:], inner[:, :2], inner[:, 6:] = False, False, False, False
    np.testing.assert_allclose(out[inner], 1.0, rtol=1e-5)          # every tile weighed the same: the mean
    np.testing.assert_allclose(out[~floor], 0.2, rtol=1e-6)         # nothing of the floor on the wall
    assert abs(out[floor & (np.arange(16)[None, :] == 7)].mean() - value[floor].mean()) < 0.35
    # without edge stops the same taps bleed the floor onto the wall: the test above can fail
    blurred = il.tile_filter(value, nrm, pos, valid, sigma_normal=0.0, sigma_position=0.0)
    assert blurred[~floor].max() > 0.4                                 # measured 0.50


def test_tile_filter_keeps_a_depth_edge():
    """Two parallel planes (same normal) 50 footprints apart do not mix."""
    value, nrm, pos, valid, _ = _crease()
    nrm = np.broadcast_to(np.array([0.0, 0.0, 1.0]), pos.shape).copy()
    y, x = np.mgrid[0:16, 0:16].astype(np.float64)
    near = x < 8
    pos = np.stack([x, y, np.where(near, 0.0, -50.0)], -1)
    value = np.where(near, 1.0, 0.1)[..., None].repeat(3, -1).astype(np.float32)
    out = il.tile_filter(value, nrm, pos, valid)
    np.testing.assert_allclose(out, value, rtol=1e-6)


def _rsm(direction_lights, snap, ex, texels: int, shaped: bool):
    """A reflective shadow map of every light: an equal-solid-angle grid of texels over its cone, each
    texel's flux I · profile · Ω · albedo at the surface its centre ray sees (``shaped=False``: the
    cone's profile left out, a wrong RSM the comparison must tell apart)."""
    pos, flux = [], []
    L = direction_lights
    for i in range(len(L)):
        a = math.radians(min(float(L.cone_angle[i]), 180.0))
        u = (np.arange(texels) + 0.5) / texels
        c, phi = np.meshgrid(1.0 - u * (1.0 - math.cos(a)), 2.0 * np.pi * u, indexing="ij")
        c, phi = c.ravel(), phi.ravel()
        axis = L.axis[i] / np.linalg.norm(L.axis[i])
        t = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        t /= np.linalg.norm(t)
        b = np.cross(axis, t)
        s = np.sqrt(1.0 - c * c)
        d = (t * (s * np.cos(phi))[:, None] + b * (s * np.sin(phi))[:, None] + axis * c[:, None])
        omega = 2.0 * np.pi * (1.0 - math.cos(a)) / len(c)
        profile = np.ones((len(c), 3))
        if shaped:
            cone = smoothstep_cone(c, np.full(len(c), L.cone_angle[i]), np.full(len(c), L.cone_softness[i]))
            profile *= cone[:, None]
            if L.focus[i] > 0:
                tint = L.focus_tint[i].astype(np.float64)
                profile *= tint + (1.0 - tint) * np.clip(c, 0, 1)[:, None] ** L.focus[i]
        h = surface_at_hits(snap, ex, L.position[i] + d * 1e-4, d)
        pos.append(h.position[h.hit])
        flux.append((L.intensity[i].astype(np.float64) * omega * profile * h.albedo.astype(np.float64))[h.hit])
    return np.concatenate(pos), np.concatenate(flux)


def _binned(pos, flux, lo, hi, cells=6):
    idx = np.clip(((pos - lo) / (hi - lo) * cells).astype(int), 0, cells - 1)
    key = (idx[:, 0] * cells + idx[:, 1]) * cells + idx[:, 2]
    return np.bincount(key, weights=flux @ LUMA, minlength=cells ** 3)


def test_first_bounce_light_path_vpls_are_rsm_texels_sampled_by_emission():
    """Paper 003 samples first-bounce VPLs from a reflective shadow map; usdml's light-path VPLs of one
    bounce deposit the same flux on the same surfaces (6³ cells over the room, luminance: measured 1.7 %
    L1 apart at 200k VPLs and 256² texels per light, as far apart as two seeds of the VPLs are, 1.8 %;
    total flux 0.999 of the RSM's; the RSM without the lights' cone profile: 20 % apart)."""
    d = StageDelegate(STAGES / "cornell.usda")
    snap = d.snapshot(1)
    ex = ExactBackend()
    ex.update(snap, diff(None, snap))
    vpls = generate_vpls(snap, ex, snap.lights, 200_000, 1, seed=1)
    lo, hi = (np.asarray(b, np.float64) for b in snap.world_bounds())
    lo, hi = lo - 1e-3, hi + 1e-3
    got = _binned(vpls.position, vpls.flux.astype(np.float64), lo, hi)
    rsm = _binned(*_rsm(snap.lights, snap, ex, 256, True), lo, hi)
    wrong = _binned(*_rsm(snap.lights, snap, ex, 256, False), lo, hi)
    ex.close()
    assert abs(got.sum() / rsm.sum() - 1.0) < 0.01
    l1 = np.abs(got - rsm).sum() / rsm.sum()
    assert l1 < 0.04
    assert np.abs(got - wrong).sum() / wrong.sum() > 3 * 0.04


@pytest.fixture(scope="module")
def cornell_compare():
    return compare_gi(StageDelegate(STAGES / "cornell.usda"), "svo", "vpl-bruteforce", image_width=64,
                      overrides={"vpl_count": 1024, "vpl_bounces": 1})


def test_svo_against_vpl_bruteforce(cornell_compare):
    r = cornell_compare
    assert r["vpls"] == 1024 and r["breakdown"]["svo"]["tiles"] == 16
    # a sixteenth of brute force's shadow rays (fewer: only pairs with G > 0 cast one)
    assert r["breakdown"]["svo"]["shadow_rays"] < r["breakdown"]["vpl-bruteforce"]["shadow_rays"] / 14
    assert r["rel_rmse"] < 0.40     # measured 0.272 (64 px, 1,024 first-bounce VPLs; exact rays 0.269)


def test_no_tile_pattern_left_in_indirect(monkeypatch):
    """Within each 4x4 block of pixels (one pixel per tile), the spread of indirect over the reference's:
    unfiltered each pixel has its own VPL subset, filtered they agree (median over blocks, measured
    128 px, 512 first-bounce VPLs, one ray per pixel: 0.326 unfiltered, 0.037 filtered; exact rays 0.323,
    0.039)."""
    d = StageDelegate(STAGES / "cornell.usda")
    settings = d.usdml_settings.updated(vpl_count=512, vpl_bounces=1, pixel_samples=1)

    def indirect(gi):
        r = FrameRenderer(d, settings.updated(gi=gi))
        try:
            return r.render(1, 128, 72, {"indirect", "depth"}).buffers
        finally:
            r.close()

    ref = indirect("vpl-bruteforce")
    hit = np.isfinite(ref["depth"]) & (ref["indirect"].sum(-1) > 0)
    blocks = hit.reshape(18, 4, 32, 4).all(axis=(1, 3))

    def spread(img):
        ratio = (img.sum(-1) / np.where(hit, ref["indirect"].sum(-1), 1.0)).reshape(18, 4, 32, 4)
        ratio = ratio.transpose(0, 2, 1, 3).reshape(18, 32, 16)[blocks]
        return float(np.median(ratio.std(axis=1) / ratio.mean(axis=1)))

    filtered = spread(indirect("svo")["indirect"])
    monkeypatch.setattr(il, "merge_and_filter", lambda irr, *a: irr)
    raw = spread(indirect("svo")["indirect"])
    assert filtered < 0.06 and raw > 4 * filtered


def test_render_gi_svo_writes_indirect(tmp_path):
    out = tmp_path / "c.exr"
    assert main(["render", str(STAGES / "cornell.usda"), str(out), "--gi", "svo", "--vpls", "256",
                 "--vpl-bounces", "1", "--imageWidth", "32", "--aovs", "color,direct,indirect,depth"]) == 0
    aovs, _ = read_exr(out)
    ind, direct = aovs["indirect"].astype(np.float64), aovs["direct"].astype(np.float64)
    hit = np.isfinite(aovs["depth"])
    assert (ind[aovs["color"][..., 3] == 0] == 0).all()        # no geometry, no indirect light
    # every wall, floor and ceiling pixel gets indirect light (the ceiling has no direct light at all)
    lit = (ind[hit].sum(-1) > 0).mean()
    assert lit > 0.95
    assert 0.05 < ind[hit].mean() / direct[hit].mean() < 2.0
    np.testing.assert_allclose(aovs["color"][..., :3], direct + ind, rtol=2e-3, atol=2e-3)


def test_frame_renderer_owns_the_gi_backend(monkeypatch):
    """--gi svo builds its own visibility backend (updated per frame, closed with the renderer) unless
    one of the renderer's backends is that backend already; a backend in two roles is updated and
    closed once."""
    d = StageDelegate(STAGES / "cornell.usda")
    settings = UsdmlSettings(gi="svo", vpl_count=64, vpl_bounces=1)
    r = FrameRenderer(d, settings)
    b = r.backends
    assert b.gi.name == il.GI_VISIBILITY == "svo" and b.gi is not b.shadow and b.shadow is b.primary
    assert [role for role, _ in b.owners()] == ["primary", "gi"]
    r.close()
    r = FrameRenderer(d, settings.updated(visibility="svo"))       # --visibility svo: one backend for both
    assert r.backends.gi is r.backends.shadow and [role for role, _ in r.backends.owners()] == ["primary", "shadow"]
    r.close()
    closed, updated = [], []
    own = ExactBackend()
    monkeypatch.setattr(own, "close", lambda: closed.append(True))
    real_update = own.update
    monkeypatch.setattr(own, "update", lambda snap, ch: (updated.append(snap.time), real_update(snap, ch)))
    monkeypatch.setattr(il, "gi_visibility_backend", lambda s, dev, name=None: own)
    r = FrameRenderer(d, settings, gi_visibility="own")
    assert r.backends.gi is own
    stats = r.render(1, 16, 9, {"indirect"}).stats
    r.close()
    assert updated == [1] and closed == [True] and stats.gi_update_seconds is not None
    r2 = FrameRenderer(d, replace(settings, gi="lgh"))
    assert r2.backends.gi is None
    r2.close()
    # --gi svo through the shadow backend: updated once a frame, closed once, no update of its own counted
    r3 = FrameRenderer(d, settings, gi_visibility="exact")
    exact = r3.backends.primary
    assert r3.backends.gi is r3.backends.shadow is exact
    calls = []
    monkeypatch.setattr(exact, "update", lambda snap, ch, real=exact.update: (calls.append("update"), real(snap, ch)))
    monkeypatch.setattr(exact, "close", lambda real=exact.close: (calls.append("close"), real()))
    stats = r3.render(1, 16, 9, {"indirect"}).stats
    r3.close()
    assert calls == ["update", "close"] and stats.gi_update_seconds is None
    assert "gi_update_seconds" not in stats.as_dict() and {"gi", "gi_seconds", "update_seconds"} <= set(stats.as_dict())


def test_svo_gi_table_tool_and_its_table(capsys):
    import sys

    from conftest import ROOT

    sys.path.insert(0, str(ROOT / "tools"))
    import bench_tables
    import svo_gi_table

    assert svo_gi_table.main([str(STAGES / "cornell.usda"), "--vpls", "64", "--imageWidth", "16",
                              "--stage-width", "16", "--ray-backends", "exact", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    row = out["rows"][0]
    assert row["vpls"] == 64 and row["rays"]["exact"]["shadow_rays"] > 0 and row["stages"]["gather"] > 0
    lines = bench_tables.gi_svo({"runs": [{"command": "c", "source": "s", "output": out}]})
    assert any("| 64 | 16×9 | `exact` |" in line for line in lines) and any("16 / 33 / 69" in line for line in lines)


def test_faint_pairs_cast_no_ray_and_are_seen_as_the_traced_light_is():
    """Paper 003 skips the V term of faint VPLs: pairs under ``skip_below`` x the pixel's mean light
    cast no ray; their light counts in the proportion the pixel's traced light is seen."""
    rng = np.random.default_rng(11)
    vpls = _random_vpls(rng, 160)
    intensity = (vpls.flux / np.pi).astype(np.float32)
    intensity[::3] *= 0.01                                       # a third of them faint
    p = np.c_[rng.uniform(-1, 1, (64, 2)), np.zeros(64)]
    n = np.tile([0.0, 0.0, 1.0], (64, 1))
    tiles = np.arange(64) % 16
    g = il.clamped_geometry(p[:1], n[:1], vpls.position, vpls.normal, 1e-4)
    lum = intensity @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    test, small = il.fruitful_pairs(g, lum, 0.5)
    assert small is not None and small.any() and test.any() and not (test & small).any()
    assert np.array_equal(test | small, g > 0)
    assert np.array_equal(il.fruitful_pairs(g, lum, 0.0)[0], g > 0)
    calls = {}

    def record(hidden, key=None):
        def occluded(o, t, **kw):
            # rays per gather (a gather may ask in several blocks, on threads)
            calls[key] = calls.get(key, 0) + len(o)
            return np.full(len(o), hidden)
        return occluded

    def gather(skip, occluded):
        return il.gather_interleaved(p, n, tiles, vpls.position, vpls.normal, intensity, occluded, 1e-4,
                                     skip_below=skip)
    free_all, free_skip = gather(0.0, record(False, "all")), gather(0.5, record(False, "skip"))
    assert calls["skip"] < calls["all"], "faint pairs cast no ray"
    # nothing hidden: the skipped light counts whole, the same irradiance as tracing every pair
    np.testing.assert_allclose(free_skip.irradiance, free_all.irradiance, rtol=1e-5)
    # everything hidden: the skipped light is hidden too (seen as the traced light is: not at all)
    dark = gather(0.5, record(True))
    assert np.abs(dark.irradiance).max() == 0.0
    assert free_skip.stats["shadow_rays"] < free_all.stats["shadow_rays"]
