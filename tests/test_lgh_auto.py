"""``--lgh-alpha`` and ``--shadow-samples`` 0 (automatic per frame) and the S0 start (issue 37): the count of
the lights a gather visits against a plain loop, the choices' growth with the VPL count, and the error
against every VPL on a suite stage, below a bound that the paper's alpha 1 from S1 misses."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, gi_frame
from usdml.lighting.direct import shade_direct
from usdml.lighting.lgh.build import build_lgh, build_lgh_split
from usdml.lighting.lgh.choice import PILOT_ALPHAS, choose
from usdml.lighting.lgh.shading import AUTO_SHADOW_SAMPLES, auto_shadow_samples, lgh_indirect, lights_visited


def _planes(n, rng):
    """``n`` VPL-like points on the floor and two walls of a 10 m room, with their normals."""
    side = rng.integers(0, 3, n)
    p = rng.uniform(0, 10, (n, 3))
    p[side == 0, 1] = 0.0
    p[side == 1, 0] = 0.0
    p[side == 2, 2] = 0.0
    normal = np.zeros((n, 3))
    normal[np.arange(n), np.array([1, 0, 2])[side]] = 1.0
    return p.astype(np.float32), normal.astype(np.float32)


def _plain_count(lgh, points, alpha, s0):
    """The lights the compiled gather walks (``kernels/lgh/lghq.c``, ``collect``), one point and light at a time."""
    total = 0
    top = max(lv.level for lv in lgh.levels)     # a split hierarchy lists each level once per normal class
    for q in points:
        for lv in lgh.levels:
            for vertex in lv.vertex:
                ijk = np.array(np.unravel_index(int(vertex), tuple(int(d) for d in lv.dims)), float)
                rel = (q - np.asarray(lv.origin)) / lv.spacing
                total += lv.level == top or np.linalg.norm(ijk - rel) <= 2 * alpha + 1.7321
        s1 = lgh.levels[0]
        cell = np.floor((q - np.asarray(s1.origin)) / s1.spacing)
        for v in s0:
            total += np.abs(np.floor((v - np.asarray(s1.origin)) / s1.spacing) - cell).max() <= np.ceil(alpha)
    return total / len(points)


@pytest.mark.parametrize("split", [False, True])
def test_lights_visited_counts_the_gathers_walk(split):
    rng = np.random.default_rng(3)
    pos, nrm = _planes(600, rng)
    lgh = (build_lgh_split(pos, np.ones((len(pos), 3), np.float32), nrm) if split else
           build_lgh(pos, np.ones((len(pos), 3), np.float32), normal=nrm))
    points, _ = _planes(5, rng)
    got = lights_visited(lgh, points, (1.0, 2.5), s0_positions=pos, sample=5)
    want = [_plain_count(lgh, points.astype(np.float64), a, pos.astype(np.float64)) for a in (1.0, 2.5)]
    np.testing.assert_allclose(got, want)
    assert got[0] < got[1]


def test_auto_alpha_grows_with_the_vpl_count():
    """The largest alpha the visit budget leaves ``--lgh-alpha auto`` (the last the pilot may try: with a target
    nothing meets, it tries every alpha within the budget) grows with the VPL count."""
    rng = np.random.default_rng(0)
    points, point_normals = _planes(256, rng)
    chosen = []
    for n in (2_000, 20_000, 200_000):
        pos, nrm = _planes(n, rng)
        inten = np.ones((n, 3), np.float32)
        lgh = build_lgh(pos, inten, normal=nrm)
        c = choose(lgh, None, points, point_normals, (pos, inten, nrm), split="none", clamp_distance=0.5 * lgh.h1,
                   target=0.0)
        tried = c.candidates["none"].get("pilot")
        chosen.append(max(t["alpha"] for t in tried) if tried else c.alpha)
    assert chosen == sorted(chosen) and chosen[0] == PILOT_ALPHAS[0] and chosen[-1] > 2.0, chosen


def test_auto_shadow_samples_grow_with_the_vpl_count():
    chosen = [auto_shadow_samples(n) for n in (100, 10_000, 20_000, 100_000, 10_000_000)]
    assert chosen == [4, 4, 16, 64, 64] and set(chosen) <= set(AUTO_SHADOW_SAMPLES)


@pytest.fixture(scope="module")
def interior(tmp_path_factory):
    """A suite stage of a held-back kind (interior, 64 lights, tuning seed 0) at 24 px: ``(snapshot, hit
    points, normals, albedo, 100,000 VPLs)``."""
    out = tmp_path_factory.mktemp("suite")
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "make_stages.py"), "--suite", "--out", str(out),
                          "--seeds", "0", "--lights", "64", "--kinds", "interior"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    snap, _, _, pts, nrm, alb, vpls = gi_frame(out / "suite_interior_64_s0.usda", 24, 100_000)
    return snap, pts, nrm, alb, vpls


def test_auto_alpha_from_s0_within_bound_of_every_vpl_where_the_paper_default_is_not(interior):
    """Unshadowed, so the hierarchy alone against every VPL as a cosine emitter (brute force's model)."""
    snap, pts, nrm, alb, vpls = interior
    intensity = vpls.flux / np.float32(4 * np.pi)
    lgh = build_lgh(vpls.position, intensity, normal=vpls.normal)
    clamp = 0.5 * lgh.h1
    reference = shade_direct(pts, nrm, alb, vpls.as_lights(isotropic=False), None,
                             meters_per_unit=snap.meters_per_unit, min_distance=clamp).radiance.astype(np.float64)

    def error(alpha, start):
        got = lgh_indirect(pts, nrm, alb, lgh, None, alpha=alpha, meters_per_unit=snap.meters_per_unit,
                           clamp_distance=clamp, sources=(vpls.position, intensity, vpls.normal),
                           start_level=start).radiance
        return np.sqrt(((got - reference) ** 2).mean()) / reference.mean()

    sources = (vpls.position, intensity, vpls.normal)
    alpha = choose(lgh, None, pts, nrm, sources, split="none", clamp_distance=clamp,
                   meters_per_unit=snap.meters_per_unit).alpha
    assert alpha > 1.0
    # measured 0.088 (the single hierarchy's pilot-chosen alpha 2 from S0) against 0.193 (alpha 1 from S1)
    assert error(alpha, 0) < 0.12 < error(1.0, 1)


def test_auto_choice_holds_its_pilot_target_over_every_vpl(interior):
    """``--lgh-split auto`` on a held-back kind at 100,000 VPLs: the split hierarchy (it fits the budget) at the
    smallest α whose pilot error is within target; over the whole image, against every VPL by brute force's own
    code (unshadowed, no code shared with the pilot's sum), within 1.6 times the target, and the α before it on
    the pilot's grid (tried and refused) errs more there."""
    from usdml.lighting.lgh.choice import PILOT_TARGET

    snap, pts, nrm, alb, vpls = interior
    intensity = vpls.flux / np.float32(4 * np.pi)
    sources = (vpls.position, intensity, vpls.normal)
    one = build_lgh(vpls.position, intensity, normal=vpls.normal)
    clamp = 0.5 * one.h1
    reference = shade_direct(pts, nrm, alb, vpls.as_lights(isotropic=False), None,
                             meters_per_unit=snap.meters_per_unit, min_distance=clamp).radiance.astype(np.float64)
    built = []

    def build_split():
        built.append(build_lgh_split(*sources))
        return built[-1]

    choice = choose(one, build_split, pts, nrm, sources, clamp_distance=clamp, meters_per_unit=snap.meters_per_unit)
    assert len(built) == 1 and choice.split == "normal" and choice.lgh is built[0], choice.candidates
    tried = choice.candidates["normal"]["pilot"]
    assert [t["alpha"] for t in tried] == sorted(t["alpha"] for t in tried) and tried[-1]["alpha"] == choice.alpha
    assert tried[-1]["rel_rmse"] <= PILOT_TARGET < min(t["rel_rmse"] for t in tried[:-1]), tried
    assert tried[-1]["visits"] <= 0.06 * len(vpls)

    def error(alpha):
        got = lgh_indirect(pts, nrm, alb, choice.lgh, None, alpha=alpha, meters_per_unit=snap.meters_per_unit,
                           clamp_distance=clamp, sources=sources, start_level=0).radiance
        return np.sqrt(((got - reference) ** 2).mean()) / reference.mean()

    # measured: alpha 1.75 (pilot 4.6 %), 4.6 % over the image; alpha 1.5 (pilot 9.2 %) 9.6 %
    assert error(choice.alpha) < 1.6 * PILOT_TARGET
    assert len(tried) < 2 or error(tried[-2]["alpha"]) > error(choice.alpha)
