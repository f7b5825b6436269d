"""The fused shading with refinement (``vq_shade_refine``, ``VoxelBackend.shade_refined``): Alg. 3 with each
shadow query answered by the thick-ray rule, the certain ones shaded in the kernel and the uncertain ones (and
the certain free ones of near points) listed for the caller's ``resolve``.

Checked here, with every instruction set, on a single occluder and on moving instances (the instance walk of
the refinement): with ``resolve`` answering the uncertain entries by the backend's own ``occluded`` and the
near ones free, the result is :meth:`shade_direct`'s (light sums within float32 rounding, blocked and facing
counts exact); the uncertain entries are exactly the facing pairs :meth:`occluded_uncertain` flags at the
level (its pairs built with the geometric normals, which the kernel offsets its rays along), the near entries
exactly the certain free pairs; a list too small for more than a tile or two at a time (many resumes) gives the
same result; without the compiled kernel the method says it cannot.
"""

from __future__ import annotations

import numpy as np
import pytest

from usdml.lighting.direct import facing_pairs, shade_direct
from usdml.scene import diff
from usdml.scene.light_table import LightTable
from usdml.visibility import make_backend
from usdml.visibility.voxel import native as voxel_native
from usdml.visibility.voxel.backend import SHADE_TILE

from backend_scenes import lights, scene_frames, surface_points
# the settings, instruction sets and private cache of the refinement's kernel tests
from test_voxel_refine_native import F, ISAS, QUIET, SETTINGS, private_cache  # noqa: F401 (an autouse fixture)

pytestmark = pytest.mark.skipif(voxel_native.library() is None, reason="the compiled voxel kernel was not built")


def shading_job(seed: int, n_points: int = 700, n_lights: int = 40) -> dict:
    """Ground points with tilted shading normals (their geometric normals +Y), albedo and lights."""
    rng = np.random.default_rng(seed)
    lit = lights(rng, n_lights)
    pts, geo = surface_points(rng, n_points)
    nrm = geo + rng.normal(scale=0.15, size=geo.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    albedo = rng.uniform(0.2, 0.9, (n_points, 3)).astype(F)
    return dict(points=pts, normals=nrm, albedo=albedo, lights=lit, geometric=geo)


def backend(scene: str, kernel: str = "native", isa: str = "auto"):
    """A voxel backend updated on ``scene``'s first frame."""
    b = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel=kernel, native_isa=isa, **QUIET)
    snap = scene_frames(scene)[0]
    b.update(snap, diff(None, snap))
    return b


def frame(scene: str, isa: str, seed: int = 5, n_points: int = 700):
    """A compiled-kernel backend on ``scene`` and a shading job."""
    b = backend(scene, "native", isa)
    assert b.kernel_name.startswith("native-")
    return b, shading_job(seed, n_points)


def own_answers(b, job, calls=None):
    """A ``resolve`` answering the uncertain entries by the backend's own ``occluded`` (the kernel's float32
    points, geometric normals and targets: light positions, or the direction against a distant light's
    axis) and the near ones free; each call's arguments appended to ``calls``."""
    lit = job["lights"]
    distant = LightTable(lit).distant
    pos, axis = np.asarray(lit.position, F), np.asarray(lit.axis, F)
    pts, geo = np.asarray(job["points"], F), np.asarray(job["geometric"], F)

    def resolve(pi, li, kind):
        if calls is not None:
            calls.append((pi.copy(), li.copy(), kind.copy()))
        free = np.ones(len(pi), bool)
        ask = np.flatnonzero(kind == 0)
        if len(ask):
            d = distant[li[ask]]
            tg = np.where(d[:, None], -axis[li[ask]], pos[li[ask]])
            free[ask] = ~b.occluded(pts[pi[ask]], tg, normals=geo[pi[ask]], distant=d)
        return free
    return resolve


def entries(calls, kind: int) -> set:
    return {(int(p), int(li)) for pi, li, k in calls for p, li in zip(pi[k == kind], li[k == kind])}


def assert_same(got, want):
    assert np.array_equal(got.facing, want.facing)
    assert np.array_equal(got.shadow, want.shadow)
    assert got.queries == want.queries
    np.testing.assert_allclose(got.radiance, want.radiance, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances"])
def test_resolved_by_its_own_answers_it_shades_as_shade_direct(scene, isa):
    b, job = frame(scene, isa)
    try:
        want = b.shade_direct(**job, plain=shade_direct)
        assert 0.05 < want.shadow.mean() < 0.95
        near = np.random.default_rng(1).random(len(job["points"])) < 0.3
        for level, flags in ((1, None), (2, near)):
            calls = []
            got, stats = b.shade_refined(**job, level=level, near=flags, resolve=own_answers(b, job, calls))
            assert_same(got, want)
            assert stats["queries"] == want.queries
            assert stats["uncertain"] == len(entries(calls, 0)) > 0
            assert stats["near"] == len(entries(calls, 1))
            assert (stats["near"] > 0) == (flags is not None)
    finally:
        b.close()


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances"])
@pytest.mark.parametrize("level", [1, 2])
def test_the_listed_pairs_are_those_the_rule_flags(scene, isa, level):
    b, job = frame(scene, isa, seed=7)
    try:
        blocks = list(facing_pairs(job["points"], job["normals"], job["lights"], job["geometric"]))
        o, t, n, d, pi, li = (np.concatenate([blk[k] for blk in blocks]) for k in range(6))
        blocked, uncertain = b.occluded_uncertain(o, t, normals=n, distant=d.astype(bool), level=level)
        calls = []
        n_p = len(job["points"])
        _, stats = b.shade_refined(**job, level=level, near=np.ones(n_p, bool),
                                   resolve=lambda p, lt, k: calls.append((p, lt, k)) or np.ones(len(p), bool))
        pairs = list(zip(pi.tolist(), li.tolist()))
        assert entries(calls, 0) == {pq for pq, u in zip(pairs, uncertain) if u}
        assert entries(calls, 1) == {pq for pq, u, x in zip(pairs, uncertain, blocked) if not u and not x}
        assert stats["queries"] == len(pairs)
        assert stats["uncertain"] + stats["near"] == sum(len(c[0]) for c in calls)
    finally:
        b.close()


@pytest.mark.parametrize("isa", ISAS)
def test_a_small_list_resumes_to_the_same_result(isa, monkeypatch):
    b, job = frame("instances", isa, seed=9, n_points=2000)     # several tiles a band
    try:
        near = np.random.default_rng(2).random(len(job["points"])) < 0.5
        resolve = own_answers(b, job)
        full, full_stats = b.shade_refined(**job, level=2, near=near, resolve=resolve)
        # room for one tile's pairs and a little: every call of the kernel stops after a tile or two
        small = voxel_native.ShadeList
        resumes = []

        def tiny(capacity):
            resumes.append(capacity)
            return small(SHADE_TILE * len(job["lights"]) + 100)
        monkeypatch.setattr(voxel_native, "ShadeList", tiny)
        calls = []
        got, stats = b.shade_refined(**job, level=2, near=near, resolve=own_answers(b, job, calls))
        assert resumes and len(calls) > len(resumes)
        assert stats == full_stats
        assert_same(got, full)
    finally:
        b.close()


def test_the_kernel_resumes_where_the_list_is_full():
    """``NativeScene.shade_refine`` straight: a list of one tile's pairs is filled tile by tile; the entries
    and sums of the calls from each resume are those of one call with room for all."""
    b, job = frame("occluder", "auto", seed=3, n_points=300)
    try:
        lt, _ = b._light_struct(job["lights"], 1.0, 0.0)
        p = np.ascontiguousarray(job["points"], F)
        nm = np.ascontiguousarray(job["normals"], F)
        g = np.ascontiguousarray(job["geometric"], F)
        near = (np.arange(len(p)) % 3 == 0).astype(np.uint8)
        rule, n_tiles, pairs = b._native_rule(), -(-len(p) // SHADE_TILE), SHADE_TILE * len(job["lights"])
        widths = np.array([1.0, 2.5], F)

        def run(capacity):
            out = [np.zeros((len(p), 3), F), np.zeros(len(p), np.int32), np.zeros(len(p), np.int32)]
            listing, got, t, starts = voxel_native.ShadeList(capacity), [], 0, []
            while t < n_tiles:
                listing.count = 0
                starts.append(t)
                t = b._native.shade_refine(rule, lt, p, nm, g, t, n_tiles - t, SHADE_TILE, widths, near, *out, listing)
                got.append([a.copy() for a in listing.entries()])
            return out, [np.concatenate(x) for x in zip(*got)], starts, listing.queries
        whole, all_entries, starts, queries = run(pairs * n_tiles)
        parts, part_entries, part_starts, part_queries = run(pairs)
        assert starts == [0] and len(part_starts) > 2 and part_queries == queries
        for a, c in zip(whole + all_entries, parts + part_entries):
            assert np.array_equal(a, c)
        assert set(all_entries[3].tolist()) == {0, 1}
        # the kinds: kind 1 only at near points
        assert near[all_entries[0][all_entries[3] == 1]].all()
    finally:
        b.close()


def test_without_the_compiled_kernel_it_is_not_implemented():
    b = backend("occluder", "warp")
    job = shading_job(5, n_points=10)
    try:
        with pytest.raises(NotImplementedError):
            b.shade_refined(**job, level=1, near=None, resolve=lambda *a: None)
    finally:
        b.close()


def test_list_apply_adds_the_free_and_counts_the_rest():
    """``NativeScene.list_apply``: against NumPy's sums over the same entries, repeated points included; a wrong
    count of answers is an error."""
    from usdml.visibility.voxel.native import ShadeList

    b = backend("occluder")
    try:
        rng = np.random.default_rng(3)
        listing = ShadeList(5000)
        listing.count = 4000
        listing.point[:4000] = rng.integers(0, 300, 4000)
        listing.rgb[:4000] = rng.random((4000, 3))
        free = rng.random(4000) < 0.6
        rad = rng.random((300, 3)).astype(F)
        blocked = rng.integers(0, 5, 300).astype(np.int32)
        want_rad, want_blocked = rad.astype(np.float64), blocked.copy()
        p = listing.point[:4000]
        np.add.at(want_rad, p[free], listing.rgb[:4000][free])
        np.add.at(want_blocked, p[~free], 1)
        b._native.list_apply(listing, free, rad, blocked)
        np.testing.assert_allclose(rad, want_rad, rtol=1e-5)
        assert np.array_equal(blocked, want_blocked)
        with pytest.raises(ValueError, match="answers"):
            b._native.list_apply(listing, free[:10], rad, blocked)
    finally:
        b.close()
