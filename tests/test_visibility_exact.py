"""The ``exact`` visibility backend (Embree) against brute force, hand-flattened instances and known hits.

Snapshots are built directly from the ``usdml.scene`` dataclasses: no USD stage needed.
"""

from __future__ import annotations

import numpy as np
import pytest

from usdml.errors import UsdmlError
from usdml.scene import Snapshot, diff
from usdml.visibility import ExactBackend, VisibilityBackend, available_backends, make_backend

from plain_scenes import prototype, rot_y, snapshot, soup, translate

pytest.importorskip("embreex")


# ---------------------------------------------------------------------------------------------- scenes

def box_tris(lo, hi) -> np.ndarray:
    """(12, 3, 3) outward-wound triangles of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corner = lambda i: np.where([(i >> k) & 1 for k in range(3)], hi, lo)   # bit k picks hi on axis k
    center = (lo + hi) / 2
    out = []
    for a, b, c, d in [(0, 2, 6, 4), (1, 3, 7, 5), (0, 1, 5, 4), (2, 3, 7, 6), (0, 1, 3, 2), (4, 5, 7, 6)]:
        q = [corner(i) for i in (a, b, c, d)]
        if np.dot(np.cross(q[1] - q[0], q[2] - q[0]), q[0] - center) < 0:
            q = q[::-1]
        out += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    return np.array(out)


def quad_tris(size: float, y: float = 0.0) -> np.ndarray:
    """(2, 3, 3) square in the XZ plane at height ``y``, facing +Y."""
    s = size / 2
    a, b, c, d = [(-s, y, -s), (-s, y, s), (s, y, s), (s, y, -s)]
    return np.array([[a, b, c], [a, c, d]], np.float64)


def backend(snap: Snapshot, **kw) -> ExactBackend:
    b = ExactBackend(**kw)
    b.update(snap, None)
    return b


# ---------------------------------------------------------------------------------------------- brute force

def brute_force(A: np.ndarray, B: np.ndarray, tris: np.ndarray, far: float = 1.0):
    """Möller-Trumbore of every segment ``A + s (B - A), s in (0, far)`` against every triangle, float64.

    Returns ``(S,) bool`` hit and the per-pair data :func:`ambiguous` needs: segment parameter ``s``,
    distance of the plane crossing to the triangle boundary, inside flag, segment length.
    """
    v0, v1, v2 = (tris[None, :, k] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    D = (B - A)[:, None]
    pv = np.cross(D, e2)
    det = np.einsum("stk,stk->st", e1, pv)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tv = A[:, None] - v0
        u = np.einsum("stk,stk->st", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("stk,stk->st", D, qv) * inv
        s = np.einsum("stk,stk->st", e2, qv) * inv
    w = 1 - u - v
    inside = (u >= 0) & (v >= 0) & (w >= 0)
    on_seg = (s > 0) & (s < far)
    hit = (inside & on_seg & np.isfinite(s)).any(axis=1)
    # distance of the plane crossing to the triangle boundary: barycentric × altitude is the distance
    # to that edge's line; inside, the nearest line; outside, the farthest violated line (a lower bound)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    alt = [area2 / np.linalg.norm(e, axis=-1) for e in (v2 - v1, v2 - v0, v1 - v0)]
    scaled = np.stack([w * alt[0], u * alt[1], v * alt[2]])
    edge_dist = np.where(inside, scaled.min(axis=0), np.maximum(-scaled, 0).max(axis=0))
    length = np.linalg.norm(B - A, axis=1)[:, None]
    return hit, (s, edge_dist, inside, length)


def ambiguous(info, margin: float, far: float = 1.0) -> np.ndarray:
    """``(S,) bool``: some plane crossing lies within ``margin`` of a triangle edge or of a segment end,
    where the epsilon-offset float32 answer may legitimately differ from float64 brute force."""
    s, edge_dist, inside, length = info
    near_edge = (edge_dist < margin) & (s > -margin / length) & (s < far + margin / length)
    near_end = inside & ((np.abs(s) * length < margin) | (np.abs(far - s) * length < margin))
    return (near_edge | near_end).any(axis=1)


def random_triangles(rng, n: int = 200) -> np.ndarray:
    centers = rng.uniform(0, 1, (n, 1, 3))
    return centers + rng.normal(0, 0.08, (n, 3, 3))


# ---------------------------------------------------------------------------------------------- tests

def test_registry():
    assert "exact" in available_backends()
    b = make_backend("exact", workers=1)
    assert isinstance(b, VisibilityBackend) and b.name == "exact"
    with pytest.raises(UsdmlError, match="available: .*exact"):
        make_backend("nope")


@pytest.mark.parametrize("with_normals", [False, True])
def test_matches_brute_force(with_normals):
    """(a) 2000 random segments over 200 random triangles agree with float64 Möller-Trumbore."""
    rng = np.random.default_rng(7)
    tris = random_triangles(rng)
    snap = snapshot([soup("/tris", tris)])
    b = backend(snap, workers=2, chunk_rays=256)        # small chunks: exercise the thread pool
    A = rng.uniform(-0.1, 1.1, (2000, 3))
    B = rng.uniform(-0.1, 1.1, (2000, 3))
    normals = rng.normal(size=(2000, 3)) if with_normals else None
    got = b.occluded(A, B, normals=normals)
    want, info = brute_force(A, B, tris)
    # the origin moves up to eps (plus float slack), the far end stops eps short
    skip = ambiguous(info, margin=1.5 * b.epsilon)
    assert b.epsilon == pytest.approx(b.rel_epsilon * np.linalg.norm(np.ptp(tris.reshape(-1, 3), axis=0)), rel=1e-6)
    assert b.rel_epsilon == 1e-5
    assert skip.mean() < 0.05, skip.mean()
    assert want[~skip].mean() > 0.2          # a meaningful mix of blocked and free segments
    np.testing.assert_array_equal(got[~skip], want[~skip])
    # determinism: same inputs, same answers, whatever the chunking
    np.testing.assert_array_equal(b.occluded(A, B, normals=normals), got)
    b1 = backend(snap, workers=1)
    np.testing.assert_array_equal(b1.occluded(A, B, normals=normals), got)


def test_instances_match_hand_flattened():
    """(b) a prototype with a few instances answers like the same triangles written out in world space."""
    rng = np.random.default_rng(3)
    local = random_triangles(rng, 40) - 0.5
    xforms = [translate(0, 0, 0), translate(1.2, 0.3, 0) @ rot_y(40), translate(0, 1.1, 0.8) @ rot_y(-75),
              translate(1.0, 1.0, 1.0) @ np.diag([0.5, 2.0, 1.0, 1.0])]
    proto = prototype("/proto", [soup("/proto/m", local, id=1)], xforms)
    world = np.concatenate([np.einsum("ij,tkj->tki", M[:3, :3], local) + M[:3, 3] for M in xforms])
    a = backend(snapshot([soup("/ground", quad_tris(8, -1.0))], [proto]))
    b = backend(snapshot([soup("/ground", quad_tris(8, -1.0)), soup("/flat", world, id=1)]))
    A = rng.uniform(-1, 2, (1500, 3))
    B = rng.uniform(-1, 2, (1500, 3))
    got = a.occluded(A, B)
    assert 0.05 < got.mean() < 0.9
    np.testing.assert_array_equal(got, b.occluded(A, B))
    assert a.stats["static_triangles"] == 2 + 4 * 40


def test_distant_lights():
    """(c) distant rows are directions toward the light and run to infinity."""
    snap = snapshot([soup("/ground", quad_tris(100)), soup("/box", box_tris((-1, 0, -1), (1, 2, 1)), id=1)])
    b = backend(snap)
    up = np.array([0.0, 1.0, 0.0])
    slanted = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)         # sun low in +x: box shadow falls toward -x
    P = np.array([[-1.5, 0, 0], [-1.5, 0, 0], [3, 0, 0], [0, 2, 0], [-3.5, 0, 0]])
    T = np.array([up, slanted, slanted, slanted, slanted])
    N = np.tile(up, (5, 1))
    got = b.occluded(P, T, normals=N, distant=np.ones(5, bool))
    np.testing.assert_array_equal(got, [False, True, False, False, False])
    # far beyond any point light: a blocker 1e4 away still counts
    snap2 = snapshot([soup("/ground", quad_tris(100)), soup("/roof", quad_tris(10, 1e4), id=1)])
    b2 = backend(snap2)
    assert b2.occluded([[0, 0, 0]], [up], normals=[up], distant=[True])[0]
    # a mixed batch: point rows stop at the light, distant rows do not
    got = b2.occluded([[0, 0, 0], [0, 0, 0]], [[0, 10, 0], up], normals=[up, up], distant=[False, True])
    np.testing.assert_array_equal(got, [False, True])


def test_update_moves_instances_and_keeps_static():
    """(d) moving an animated instance changes answers; the static scene is built once."""
    ground = soup("/ground", quad_tris(20))
    blocker = [soup("/blocker/m", box_tris((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), id=1)]
    f1 = snapshot([ground], [prototype("/blocker", blocker, [translate(0, 3, 0), translate(5, 3, 5)], animated=True)])
    f2 = snapshot([ground], [prototype("/blocker", blocker, [translate(-5, 3, -5), translate(5, 3, 5)], animated=True)],
                  time=2)
    P = np.array([[0, 0, 0], [-5, 0, -5], [5, 0, 5]], np.float64)
    L = P + [0, 10, 0]
    N = np.tile([0.0, 1.0, 0.0], (3, 1))
    b = ExactBackend(workers=1)
    b.update(f1, diff(None, f1))
    np.testing.assert_array_equal(b.occluded(P, L, normals=N), [True, False, True])
    b.update(f2, diff(f1, f2))
    np.testing.assert_array_equal(b.occluded(P, L, normals=N), [False, True, True])
    assert b.stats["static_builds"] == 1 and b.stats["dynamic_builds"] == 2
    # nothing changed: nothing rebuilt
    b.update(f2, diff(f2, f2))
    assert b.stats["static_builds"] == 1 and b.stats["dynamic_builds"] == 2
    # a purely static scene: the second update does not rebuild the static part
    s1 = snapshot([ground, soup("/wall", box_tris((-1, 0, -1), (1, 2, 1)), id=1)])
    s2 = snapshot(s1.meshes, time=2)
    c = ExactBackend(workers=1)
    c.update(s1, diff(None, s1))
    c.update(s2, diff(s1, s2))
    assert c.stats["static_builds"] == 1
    # a static change does rebuild it
    s3 = snapshot([ground], time=3)
    c.update(s3, diff(s2, s3))
    assert c.stats["static_builds"] == 2
    assert not c.occluded([[0, 3, 0]], [[0, 10, 0]])[0] and c.stats["static_triangles"] == 2


def test_intersect_maps_hits_to_sources():
    """(e) closest hit: t, triangle, barycentrics, and geom -> mesh / (prototype, instance, mesh)."""
    ground = soup("/ground", quad_tris(20), id=0)
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float64)     # faces +z
    other = soup("/proto/other", quad_tris(0.1, 50), id=1)
    proto = prototype("/proto", [other, soup("/proto/tri", tri, id=2)],
                      [translate(10, 10, 10), translate(0, 1, 5)], animated=True)
    snap = snapshot([ground], [proto])
    b = backend(snap)
    O = np.array([[0.25, 1.5, 10.0], [3, 5, 3], [50, 50, 50], [0.25, 1.5, 10.0]])
    D = np.array([[0, 0, -1.0], [0, -1.0, 0], [1.0, 0, 0], [0, 0, -1.0]])
    r = b.intersect(O, D, tmax=np.array([np.inf, np.inf, np.inf, 2.0]))
    np.testing.assert_allclose(r["t"], [5.0, 5.0, np.inf, np.inf], rtol=1e-6)
    assert r["geom"][2] == -1 and r["geom"][3] == -1 and r["prim"][2] == -1
    # ray 0 hits instance 1 of the prototype's second mesh, triangle 0, at local (0.25, 0.5)
    s = b.source(int(r["geom"][0]))
    assert (s.mesh, s.prototype, s.instance, s.proto_mesh, s.prim_id, s.instance_id) == (-1, 0, 1, 1, 2, 101)
    assert s.mesh_of(snap) is proto.meshes[1] and r["prim"][0] == 0
    np.testing.assert_allclose([r["u"][0], r["v"][0]], [0.25, 0.5], atol=1e-6)
    np.testing.assert_allclose(r["ng"][0] / np.linalg.norm(r["ng"][0]), [0, 0, 1], atol=1e-6)
    # ray 1 hits the static ground mesh
    s = b.source(int(r["geom"][1]))
    assert (s.mesh, s.prototype, s.prim_id, s.instance_id) == (0, -1, 0, -1)
    assert s.mesh_of(snap) is ground and r["prim"][1] in (0, 1)
    prim, inst = b.ids(r["geom"])
    np.testing.assert_array_equal(prim, [2, 0, -1, -1])
    np.testing.assert_array_equal(inst, [101, -1, -1, -1])
    # the nearer of the static and the dynamic scene wins
    r = b.intersect([[0.25, 1.5, 10.0]], [[0, 0, 1.0]])
    assert r["geom"][0] == -1
    r = b.intersect([[0.25, 10.0, 5.0]], [[0, -1.0, 0]])
    assert b.source(int(r["geom"][0])).mesh == 0 and r["t"][0] == pytest.approx(10.0)


def test_no_self_occlusion_and_contact():
    """(f) points on surfaces with normals see lights above them; contacts behave as documented."""
    rng = np.random.default_rng(11)
    ground = soup("/ground", quad_tris(20))
    box = soup("/box", box_tris((-1, 0, -1), (1, 2, 1)), id=1)
    b = backend(snapshot([ground, box]))
    eps = b.epsilon
    # points on the ground and on the box top, lights straight above them at various heights
    g = np.c_[rng.uniform(-9, 9, 500), np.zeros(500), rng.uniform(-9, 9, 500)]
    g = g[(np.abs(g[:, 0]) > 1.01) | (np.abs(g[:, 2]) > 1.01)]
    top = np.c_[rng.uniform(-1, 1, 200), np.full(200, 2.0), rng.uniform(-1, 1, 200)]
    P = np.concatenate([g, top])
    L = P + np.c_[rng.uniform(-0.2, 0.2, len(P)), rng.uniform(0.01, 20, len(P)), rng.uniform(-0.2, 0.2, len(P))]
    L[:len(g)] += np.sign(P[:len(g)]) * [0.5, 0, 0.5]     # lean away from the box
    N = np.tile([0.0, 1.0, 0.0], (len(P), 1))
    assert not b.occluded(P, L, normals=N).any()
    # the box's side wall, lit from outside at grazing angles, is not self-shadowed either
    side = np.c_[np.full(300, 1.0), rng.uniform(0.001, 1.999, 300), rng.uniform(-1, 1, 300)]
    Ls = side + np.c_[rng.uniform(0.5, 5, 300), rng.uniform(0.0, 5, 300), rng.uniform(-5, 5, 300)]
    assert not b.occluded(side, Ls, normals=np.tile([1.0, 0, 0], (300, 1))).any()
    # contact: a ground point just outside the box wall, light on the other side, low: blocked by the wall
    assert b.occluded([[1.0 + eps / 2, 0, 0]], [[-5, 0.5, 0]], normals=[[0, 1, 0]])[0]
    # a ground point under the box starts inside it: blocked
    assert b.occluded([[0.3, 0, 0.3]], [[0, 50, 0]], normals=[[0, 1, 0]])[0]
    # a light sitting on the box top is not blocked by the top it sits on
    assert not b.occluded([[0, 8, 0], [0.5, 2, 0.5]], [[0, 2, 0], [0, 2, 0]], normals=[[0, 0, 0], [0, 1, 0]]).any()
    # documented miss: a plate hovering closer than eps above the ground casts no shadow right under it
    for h, blocked in ((0.5 * eps, False), (10 * eps, True)):
        c = backend(snapshot([ground, soup("/plate", quad_tris(1.0, h), id=1)]), epsilon=eps)
        assert c.occluded([[0, 0, 0]], [[0, 5, 0]], normals=[[0, 1, 0]])[0] == blocked
    # back-lit: a closed box's wall lit from inside-out starts inside and is blocked by the far wall;
    # an open sheet lit from behind is visible (shading's cosine, not visibility, darkens it)
    assert b.occluded([[1, 1, 0]], [[-5, 1, 0]], normals=[[1, 0, 0]])[0]
    assert not b.occluded([[5, 0, 5]], [[5, -3, 5]], normals=[[0, 1, 0]])[0]


def test_occluded_matrix_equals_flattened_pairs():
    """(g) all points × all lights equals occluded() on the flattened pairs, across row/column chunks."""
    rng = np.random.default_rng(5)
    tris = random_triangles(rng, 150)
    b = backend(snapshot([soup("/tris", tris)]), workers=2, chunk_rays=500)
    b.matrix_chunk_pairs = 700          # forces several row blocks and column blocks
    P = rng.uniform(0, 1, (90, 3))
    N = rng.normal(size=(90, 3))
    L = rng.uniform(-0.5, 1.5, (1000, 3))
    distant = rng.random(1000) < 0.2
    axis = rng.normal(size=(1000, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    m = b.occluded_matrix(P, N, L, distant, axis)
    assert m.shape == (90, 1000) and m.dtype == bool and 0.05 < m.mean() < 0.95
    T = np.where(distant[:, None], -axis, L)
    flat = b.occluded(np.repeat(P, 1000, 0), np.tile(T, (90, 1)), normals=np.repeat(N, 1000, 0),
                      distant=np.tile(distant, 90))
    np.testing.assert_array_equal(m, flat.reshape(90, 1000))
    assert b.occluded_matrix(P, None, np.zeros((0, 3))).shape == (90, 0)


def test_empty_scene_and_degenerate_segments():
    b = backend(snapshot())
    assert not b.occluded([[0, 0, 0]], [[1, 1, 1]]).any()
    assert b.intersect([[0, 0, 0]], [[1, 0, 0]])["geom"][0] == -1
    c = backend(snapshot([soup("/ground", quad_tris(2))]))
    # zero-length and shorter-than-epsilon segments are never blocked
    assert not c.occluded([[0, 0, 0], [0, -1, 0]], [[0, 0, 0], [0, -1 + 1e-9, 0]]).any()
    with pytest.raises(RuntimeError, match="update"):
        ExactBackend().occluded([[0, 0, 0]], [[1, 1, 1]])


# ---------------------------------------------------------------------------------------------- compiled rays

def same_bits(a: np.ndarray, b: np.ndarray) -> None:
    """``a`` and ``b`` equal bit for bit (NaN where the other is NaN, whatever its payload)."""
    nan = np.isnan(a)
    np.testing.assert_array_equal(nan, np.isnan(b))
    np.testing.assert_array_equal(np.where(nan, 0, a).view(np.uint32), np.where(nan, 0, b).view(np.uint32))


@pytest.mark.parametrize("with_normals", [True, False])
@pytest.mark.parametrize("with_distant", [True, False])
@pytest.mark.parametrize("dtype", [np.float64, np.float32, "mixed"])
def test_compiled_rays_are_the_numpy_rule_bit_for_bit(with_normals, with_distant, dtype):
    """occluded's compiled ray set-up (usdml.kernels.shadow_rays) gives exactly ExactBackend.shadow_rays's
    float32 rays, edge cases included: zero and non-unit normals, distant rows, segments of no length or
    shorter than the epsilons, points far from the origin, normals facing away from the light."""
    from usdml.visibility.exact import _RayKernel

    rng = np.random.default_rng(7)
    n = 5000
    P = rng.uniform(-300, 300, (n, 3)) * rng.choice([1e-6, 1.0, 1e3], (n, 1))
    L = P + rng.normal(size=(n, 3)) * rng.choice([0.0, 1e-9, 1e-3, 1.0, 50.0], (n, 1))
    N = rng.normal(size=(n, 3)) * rng.choice([0.0, 1.0, 0.5, 3.0], (n, 1))
    far = rng.random(n) < 0.2
    L[far] = rng.normal(size=(far.sum(), 3))
    L[far] /= np.linalg.norm(L[far], axis=1, keepdims=True)
    # "mixed": float64 points, float32 targets (the LGH's shadow rays: G-buffer points, light targets)
    P, L = (P, L.astype(np.float32)) if dtype == "mixed" else (P.astype(dtype), L.astype(dtype))
    normals = N.astype(np.float32) if with_normals else None
    distant = far if with_distant else None
    b = ExactBackend(epsilon=0.0123)
    want = b.shadow_rays(P, L, normals, distant)
    got = _RayKernel(P, L, normals, distant, b.epsilon)
    from usdml.kernels import shadow_rays as kernels

    # float32 targets are read as float32 (no float64 copy of the batch), float64 as float64
    assert got.kernel is (kernels.shadow_rays if dtype == np.float64 else kernels.shadow_rays_df)
    for lo, hi in ((0, n), (17, 1234), (n - 3, n)):
        for w, g in zip(want, got(lo, hi)):
            same_bits(w[lo:hi], g)
    assert (want[2] == 0).any() and (want[2] > 0).any()


def test_occluded_answers_as_the_numpy_rays_do():
    """occluded (compiled rays, chunked, two scenes) equals Embree run on shadow_rays's rays."""
    rng = np.random.default_rng(3)
    tris = random_triangles(rng, 300)
    anim = prototype("/anim", [soup("/anim/tri", [[[0, 0, 0], [0.3, 0, 0], [0, 0, 0.3]]])],
                     np.stack([translate(*rng.uniform(0, 1, 3)) for _ in range(50)]), animated=True)
    snap = snapshot([soup("/tris", tris)], [anim])
    b = backend(snap, chunk_rays=257)
    P = rng.uniform(-0.5, 1.5, (4000, 3))
    L = rng.uniform(-0.5, 1.5, (4000, 3))
    N = rng.normal(size=(4000, 3)).astype(np.float32)
    o, d, t = b.shadow_rays(P, L, N, None)
    live = t > 0
    want = np.zeros(4000, bool)
    for g in b._groups():
        want[live] |= g.scene.run(o[live], d[live], query="OCCLUDED", dists=t[live]) != -1
    np.testing.assert_array_equal(b.occluded(P, L, normals=N), want)
    assert 0.1 < want.mean() < 0.9 and len(b._groups()) == 2
    b.close()
