"""The insm backend's REFINE rule (issue 36 item 1): its answers are :meth:`occluded`'s, its levels nest, and
on a floating square over a ground (a closed-form shadow, no code shared with the backend) the answers it
calls certain are right and those it gets wrong are flagged. Both CPU paths: the compiled maps' rule and the
Warp kernels' simpler one (usdml.visibility.insm.backend, "Refinement")."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from usdml.scene import Lights, LightType, diff
from usdml.visibility.insm import native as insm_native
from usdml.visibility.insm.backend import InsmBackend

from plain_scenes import snapshot, soup

pytest.importorskip("embreex")

#: the square: half-size and height over a 20 x 20 ground; point lights over it
HALF, HEIGHT = 2.0, 3.0
LIGHTS = np.array([[0.3, 8.0, 0.2], [-3.0, 7.0, 1.5], [2.5, 9.0, -2.0], [1.0, 6.0, 3.5]])
#: a coarse reconstruction (64 px depth images, 256 px maps): it errs along the shadow's edges
COARSE = dict(insm_resolution=64, insm_light_resolution=256)

native_only = pytest.mark.skipif(insm_native.library() is None, reason="compiled maps not built")
KERNELS = [pytest.param("native", marks=native_only), "warp"]


def _quad(y: float, half: float) -> np.ndarray:
    """Two triangles of a square in the plane ``y``, facing +Y."""
    return np.array([[(-half, y, -half), (-half, y, half), (half, y, half)],
                     [(-half, y, -half), (half, y, half), (half, y, -half)]])


def _lights(pos: np.ndarray) -> Lights:
    n = len(pos)
    return Lights(type=np.full(n, LightType.POINT, np.int8), position=pos, axis=np.tile([0.0, -1.0, 0.0], (n, 1)),
                  xform=np.tile(np.eye(4), (n, 1, 1)), radiance=np.ones((n, 3), np.float32),
                  intensity=np.ones((n, 3), np.float32), radius=np.zeros(n), width=np.zeros(n), height=np.zeros(n),
                  angle=np.zeros(n), cone_angle=np.full(n, 180.0), cone_softness=np.zeros(n), focus=np.zeros(n),
                  focus_tint=np.ones((n, 3), np.float32), shadow=np.ones(n, bool), paths=[f"/l{i}" for i in range(n)],
                  instance_ids=np.full(n, -1, np.int64))


def _scene(kernel: str):
    """The backend on the square, and every ground point's pairs with the lights: origins, targets, normals,
    the closed form's answers, the distance in the square's plane from each crossing to the square's outline,
    and how near the pair lies to a seam of its light's cube map (the ratio of the point's two largest offsets
    from the light: 1 on a seam, where a lookup may leave its face, outside every view, and a footprint reaches
    past the face's side: uncertain by rule)."""
    snap = replace(snapshot([soup("/ground", _quad(0.0, 10.0), id=1), soup("/square", _quad(HEIGHT, HALF), id=2)]),
                   lights=_lights(LIGHTS))
    backend = InsmBackend(None, insm_cpu_kernel=kernel, **COARSE)
    backend.update(snap, diff(None, snap))
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-9, 9, 6000), np.zeros(6000), rng.uniform(-9, 9, 6000)]
    o = np.repeat(p, len(LIGHTS), 0)
    t = np.tile(LIGHTS, (len(p), 1))
    n = np.tile([0.0, 1.0, 0.0], (len(o), 1))
    s = (HEIGHT - o[:, 1]) / (t[:, 1] - o[:, 1])
    c = np.abs((o + s[:, None] * (t - o))[:, [0, 2]])
    truth = (c[:, 0] < HALF) & (c[:, 1] < HALF)
    outside = np.linalg.norm(np.maximum(c - HALF, 0.0), axis=1)
    edge = np.where(outside > 0, outside, np.min(HALF - c, axis=1))
    a = np.sort(np.abs(o - t), axis=1)
    return backend, o, t, n, truth, edge, a[:, 1] / a[:, 2]


@pytest.mark.parametrize("kernel", KERNELS)
def test_answers_are_occluded_and_levels_nest(kernel):
    """``blocked`` is :meth:`occluded`'s booleans at every level; each level flags a superset of the one below;
    the widest flags part of the pairs, not all; levels outside 1 .. refine_levels are refused."""
    backend, o, t, n, *_ = _scene(kernel)
    assert backend.supports("refine") and backend.refine_levels == 5
    plain = backend.occluded(o, t, normals=n)
    below = np.zeros(len(o), bool)
    for level in range(1, backend.refine_levels + 1):
        blocked, uncertain = backend.occluded_uncertain(o, t, normals=n, level=level)
        np.testing.assert_array_equal(blocked, plain)
        assert not (below & ~uncertain).any(), f"level {level} drops a flag of level {level - 1}"
        below = uncertain
    assert 0 < below.mean() < 0.5
    for level in (0, backend.refine_levels + 1):
        with pytest.raises(ValueError, match="level"):
            backend.occluded_uncertain(o[:4], t[:4], normals=n[:4], level=level)
    backend.close()


@native_only
def test_the_square_closed_form():
    """The compiled rule on the square: the coarse reconstruction errs (3 % of the pairs, along the shadow's
    edge); every wrong answer is flagged from level 3 (six in ten at level 1, nine in ten at level 2), so every
    certain answer there is right; pairs off the cube maps' seams farther than 1.0 from the outline (the square's
    sample spacings are 0.18 - 1.2 here; level k reaches c_k = 0.1 .. 1.0 of them) are right and certain at
    levels 1 - 2, and farther than 2.0 at every level."""
    backend, o, t, n, truth, edge, seam = _scene("native")
    got = backend.occluded(o, t, normals=n)
    wrong = got != truth
    assert 0.01 < wrong.mean() < 0.1
    assert edge[wrong].max() < 1.6
    caught = []
    for level in range(1, backend.refine_levels + 1):
        _, uncertain = backend.occluded_uncertain(o, t, normals=n, level=level)
        caught.append(uncertain[wrong].mean())
        far = (edge > (1.0 if level <= 2 else 2.0)) & (seam < 0.99)
        np.testing.assert_array_equal(got[far], truth[far])
        assert not uncertain[far].any(), f"level {level} flags pairs far from the outline"
        if level >= 3:
            assert uncertain[wrong].all(), f"level {level} misses {np.sum(wrong & ~uncertain)} wrong answers"
        assert uncertain.mean() < 0.35
    assert caught[0] > 0.55 and caught[1] > 0.9
    backend.close()


def test_the_square_warp_rule():
    """The Warp kernels' simpler rule (a fixed footprint, not widened with the occluder's distance to the light)
    on the same square: it flags fewer of the wrong answers at each level (one in ten at level 1) but nine in ten
    at the widest, and pairs farther than 1.0 from the outline and off the seams by more than the widest
    footprint (8 texels: about 0.4 at the square's depth) are right and certain at every level."""
    backend, o, t, n, truth, edge, seam = _scene("warp")
    got = backend.occluded(o, t, normals=n)
    wrong = got != truth
    far = (edge > 1.0) & (seam < 0.9)
    np.testing.assert_array_equal(got[far], truth[far])
    for level in range(1, backend.refine_levels + 1):
        _, uncertain = backend.occluded_uncertain(o, t, normals=n, level=level)
        assert not uncertain[far].any(), f"level {level} flags pairs far from the outline"
    assert uncertain[wrong].mean() > 0.9 and uncertain.mean() < 0.3
    backend.close()


@pytest.mark.parametrize("kernel", KERNELS)
def test_rows_the_exact_backend_answers_are_certain(kernel):
    """Targets that are none of the frame's lights (a VPL, a sample on an area light) go to the exact backend:
    their answers are exact and certain at every level, the map rows' flags unchanged beside them."""
    backend, o, t, n, *_ = _scene(kernel)
    rows = slice(0, 4000)
    other = t[rows] + np.array([0.37, -0.5, 0.21])           # no light of the frame
    mixed_t = np.concatenate([t[rows], other])
    mixed_o = np.concatenate([o[rows], o[rows]])
    mixed_n = np.concatenate([n[rows], n[rows]])
    before = backend.stats["exact_queries"]
    exact = backend.exact.occluded(o[rows], other, normals=n[rows])
    got = {level: backend.occluded_uncertain(mixed_o, mixed_t, normals=mixed_n, level=level)
           for level in (1, backend.refine_levels)}
    assert backend.stats["exact_queries"] - before == 4000       # one graded pass, kept for the other level
    for level, (blocked, uncertain) in got.items():
        _, alone = backend.occluded_uncertain(o[rows], t[rows], normals=n[rows], level=level)
        np.testing.assert_array_equal(blocked[4000:], exact)
        assert not uncertain[4000:].any()
        np.testing.assert_array_equal(uncertain[:4000], alone)
    backend.close()


@native_only
def test_fused_refined_shading_hands_back_the_uncertain_pairs():
    """:meth:`shade_refined` (the compiled shading, graded): answering the handed-back pairs by the maps' own
    answers gives :meth:`shade_direct`'s pixels; answering them exactly gives the closed form's shadow on the
    ground at level 3 (every wrong answer there is uncertain) but on one point in 6,000, where the maps alone
    miss it on 11 % of the points; each handed-back pair is a facing pair of the frame's lights, counted."""
    backend, o, t, n, truth, *_ = _scene("native")
    backend.workers = 1                                  # one thread: the same sums in the same order
    lights = _lights(LIGHTS)
    p, nrm = o[::len(LIGHTS)], n[::len(LIGHTS)]
    albedo = np.full((len(p), 3), 0.5, np.float32)
    maps = backend.blocked_lights(lights, p, nrm)        # (L, P) the maps' answers
    handed = []

    def own(point, light, kind):
        assert not kind.any()
        handed.append((point.copy(), light.copy()))
        return maps[light, point] == 0

    plain = backend.shade_direct(p, nrm, albedo, lights, plain=None)
    got, counts = backend.shade_refined(p, nrm, albedo, lights, level=3, near=None, resolve=own)
    np.testing.assert_allclose(got.radiance, plain.radiance, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(got.shadow, plain.shadow)
    np.testing.assert_array_equal(got.facing, plain.facing)
    point = np.concatenate([h[0] for h in handed])
    assert counts["uncertain"] == len(point) > 0 and counts["queries"] == plain.queries
    assert np.all(got.facing[point] > 0)

    def exact(point, light, kind):
        return ~backend.exact.occluded(p[point], LIGHTS[light], normals=nrm[point])

    refined, _ = backend.shade_refined(p, nrm, albedo, lights, level=3, near=None, resolve=exact)
    closed = truth.reshape(len(p), len(LIGHTS)).mean(1)  # every light faces the ground
    assert np.all(plain.facing == len(LIGHTS))
    assert (np.abs(plain.shadow - closed) > 1e-6).mean() > 0.05
    assert (np.abs(refined.shadow - closed) > 1e-6).mean() < 0.002
    backend.close()


@native_only
def test_compiled_shading_gives_the_same_pixels_on_any_number_of_threads():
    """The compiled maps' Alg. 3 sums a fixed set of light blocks, each in light order, added in block order:
    bit for bit the same on 1, 2 and 3 threads (per-thread sums had been added in whatever order the threads
    took the lights, a float32 step apart from run to run)."""
    backend, o, t, n, *_ = _scene("native")
    rng = np.random.default_rng(5)
    many = LIGHTS[rng.integers(0, len(LIGHTS), 48)] + rng.uniform(-1.0, 1.0, (48, 3))   # 48 lights about the four
    lights = _lights(many)
    p, nrm = o[::len(LIGHTS)], n[::len(LIGHTS)]
    albedo = np.full((len(p), 3), 0.5, np.float32)
    runs = []
    for workers in (1, 2, 3, 2):
        backend.workers = workers
        runs.append(backend.shade_direct(p, nrm, albedo, lights, plain=None))
    for r in runs[1:]:
        assert r.radiance.tobytes() == runs[0].radiance.tobytes()
        np.testing.assert_array_equal(r.shadow, runs[0].shadow)
        np.testing.assert_array_equal(r.facing, runs[0].facing)
    backend.close()
