"""The compiled voxel kernel's refinement (``vq_query_refine``, ``VoxelBackend._native_refine``): each
shadow answer and whether it is certain by the thick-ray rule. Five rays per query, the query's own and
the rows ``thick`` voxels to either side of it along its direction bin's grid axes u and v, looked up
for each of the query's pieces over the same voxels (outside the grid: free); each blocked when any
array blocks it; uncertain when they do not all agree.

Checked here: the blocked bit is :meth:`occluded`'s answer bit for bit with every instruction set;
``thick`` 0 flags nothing and a wider ``thick`` flags (nearly) a superset; the flags agree with a NumPy
evaluation of the rule written from the same tables (the scalar C's arithmetic, every instance visited
rather than those the BVH finds); and against geometry: rays along a grid axis through a box are
certain far from its silhouette's edges and uncertain within half a voxel of them.
"""

from __future__ import annotations

import numpy as np
import pytest

from usdml.scene import diff
from usdml.settings import UsdmlSettings
from usdml.visibility import make_backend
from usdml.visibility.voxel import native as voxel_native
from usdml.visibility.voxel.native import NativeScene

from backend_scenes import lights, queries, scene_frames, surface_points
from test_voxel_native import volume_queries

pytestmark = pytest.mark.skipif(voxel_native.library() is None, reason="the compiled voxel kernel was not built")

SETTINGS = UsdmlSettings(voxel_resolution=32, direction_step=10.0)
QUIET = {"report": lambda line: None}
#: the compiled kernel's instruction sets this CPU runs (auto: the widest)
ISAS = ["auto"] + (["avx2"] if voxel_native.isa_width("avx2") == 8 and voxel_native.isa_width() > 8 else []) \
    + ["scalar"]
F = np.float32


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path / "cache"))


@pytest.fixture
def instance_table(monkeypatch):
    """The instance maps and arrays each NativeScene is built with (the last one's)."""
    seen = {}
    build = NativeScene.__init__

    def spy(self, words, arrays, layout, bins, world, inst_inv, inst_array, *rest, **kw):
        seen.update(inv=np.asarray(inst_inv, F).reshape(-1, 4, 4)[:, :3, :].reshape(-1, 12), ids=np.asarray(inst_array))
        build(self, words, arrays, layout, bins, world, inst_inv, inst_array, *rest, **kw)
    monkeypatch.setattr(NativeScene, "__init__", spy)
    return seen


def native(isa: str, settings=SETTINGS):
    b = make_backend("voxel", settings, "cpu", voxel_cpu_kernel="native", native_isa=isa, **QUIET)
    assert b.kernel_name.startswith("native-")
    return b


def mixed_queries(rng, lit, n_points: int = 500, n_volume: int = 4000):
    """Facing pairs from ground points to the lights and segments through the scene's volume, some
    without a normal, some distant (tests/test_voxel_native.py's): more than 10,000 queries."""
    pts, nrm = surface_points(rng, n_points)
    (o1, t1, kw1), (o2, t2, kw2) = queries(pts, nrm, lit), volume_queries(rng, n_volume)
    return (np.concatenate([o1, o2]), np.concatenate([t1, t2]), np.concatenate([kw1["normals"], kw2["normals"]]),
            np.concatenate([kw1["distant"], kw2["distant"]]))


# ---------------------------------------------------------------- the rule in NumPy (float32, scalar C's order)

def _len3(v):
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _affine(m, p):
    """(n, 3) points through one 3 x 4 map (12 floats) or one per point ((n, 12))."""
    m = np.broadcast_to(m, (len(p), 12))
    return np.stack([m[:, 4 * i] * p[:, 0] + m[:, 4 * i + 1] * p[:, 1] + m[:, 4 * i + 2] * p[:, 2] + m[:, 4 * i + 3]
                     for i in range(3)], axis=1)


def _atan2(y, x):
    ax, ay = np.abs(x), np.abs(y)
    mx = np.maximum(ax, ay)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(mx == 0, F(0), np.minimum(ax, ay) / np.where(mx == 0, F(1), mx))
    s = a * a
    r = a * (F(0.99997726) + s * (F(-0.33262347) + s * (F(0.19354346) + s * (F(-0.11643287) + s * (
        F(0.05265332) - F(0.01172120) * s)))))
    r = np.where(ay > ax, F(1.57079637) - r, r)
    r = np.where(x < 0, F(3.14159274) - r, r)
    return np.where(mx == 0, F(0), np.where(y < 0, -r, r))


def _bin(bins, d):
    d = np.where(d[:, 2:3] < 0, -d, d)
    deg = F(57.29577951308232)
    theta = _atan2(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]), d[:, 2]) * deg
    ring = np.clip((theta / F(bins.d_theta) + F(0.5)).astype(np.int64), 0, len(bins.ring_count) - 1)
    phi = _atan2(d[:, 1], d[:, 0]) * deg
    phi = np.where(phi < 0, phi + F(360), phi)
    cnt = np.asarray(bins.ring_count, np.int64)[ring]
    col = (phi * cnt.astype(F) * (F(1) / F(360)) + F(0.5)).astype(np.int64)
    col = np.where(col >= cnt, col - cnt, col)
    return np.asarray(bins.ring_start, np.int64)[ring] + col


def _ray_setup(rule: dict, p, tg, nm, distant):
    dist = distant[:, None]
    dirv = np.where(dist, tg, tg - p)
    nn, ln = _len3(nm), _len3(dirv)
    with np.errstate(divide="ignore", invalid="ignore"):
        nrm = nm / np.where(nn > 0, nn, F(1))[:, None]
    sg = np.where((nrm[:, 0] * dirv[:, 0] + nrm[:, 1] * dirv[:, 1] + nrm[:, 2] * dirv[:, 2]) < 0, F(-1), F(1))
    o = np.where((nn > 0)[:, None], p + nrm * sg[:, None] * F(rule["offset"]), p)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = (_len3(o - np.asarray(rule["far_center"], F)) + F(rule["far"])) / _len3(tg)
    e = np.where(dist, o + tg * reach[:, None], tg)
    skip1 = np.where(distant, F(0), F(rule["end_skip"]))
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_b = np.abs(nm[:, 0] * dirv[:, 0] + nm[:, 1] * dirv[:, 1] + nm[:, 2] * dirv[:, 2]) / (nn * ln)
        k = np.minimum(F(rule["slab"]) / np.maximum(sin_b, F(1e-6)), F(rule["max_skip"]))
    use = (nn > 0) & (ln > 0) & (rule["slab"] > 0)
    skip0 = np.where(use, np.maximum(k, F(rule["skip"])), F(rule["skip"]))
    return o, e, skip0.astype(F), skip1.astype(F)


class _Tables:
    """What the kernel reads for one backend, from the backend's own fields."""

    def __init__(self, b):
        arrays = b.arrays
        self.bins, self.seg, self.words = b.bins, b.segment, b.host_words
        self.wpd = int(b.layout.words)
        w0, nw = np.asarray(b.layout.w0, np.int64), np.asarray(b.layout.nw, np.int64)
        self.row_start = np.asarray(b.layout.offset, np.int64) - w0
        self.w0, self.w1 = w0, w0 + nw
        self.base = np.concatenate([[0], np.cumsum([a.words.size for a in arrays])[:-1]]).astype(np.int64)
        self.n = [a.resolution for a in arrays]
        self.inv_h = [F(a.resolution) / (F(2.0) * F(a.half)) for a in arrays]
        frames = np.asarray(b.bins.frames, np.float64)
        self.fold = [NativeScene._fold(frames, float(ih), np.asarray(a.center, np.float64), float(a.half)).astype(F)
                     for a, ih in zip(arrays, self.inv_h)]
        _, self.world, _ = b._array_order()
        self.world_fold = [NativeScene._fold(frames, float(self.inv_h[i]), np.asarray(arrays[i].center, np.float64),
                                             float(arrays[i].half), np.asarray(arrays[i].to_array, np.float64)).astype(F)
                           for i in self.world]
        self.world_inv = [np.asarray(arrays[i].to_array, F)[:3, :].ravel() for i in self.world]

    def array_refine(self, a, tab, xa, xb, da, skip0, skip1, thick):
        """array_refine of voxelq.c for every ray: (n, 5) blocked flags."""
        n, seg, fn = self.n[a], self.seg, F(self.n[a])
        m = len(xa)
        got = np.zeros((m, 5), bool)
        length = _len3(da) * self.inv_h[a]
        live = ~((length <= skip0 + skip1) | (length <= 0))
        with np.errstate(all="ignore"):
            d = _bin(self.bins, np.where(live[:, None], da, F(1)))
            Fm = tab[d]
            qa, qb = _affine(Fm, xa), _affine(Fm, xb)
            dq = qb - qa
            t0, t1 = skip0 / length, F(1) - skip1 / length
            for ax in range(3):
                both = (qa[:, ax] >= 0) & (qa[:, ax] < fn) & (qb[:, ax] >= 0) & (qb[:, ax] < fn)
                flat = np.abs(dq[:, ax]) < F(1e-12)
                live &= both | ~flat
                inv = F(1) / dq[:, ax]
                ta, tb = (F(0) - qa[:, ax]) * inv, (fn - qa[:, ax]) * inv
                t0 = np.where(both, t0, np.maximum(t0, np.minimum(ta, tb)))
                t1 = np.where(both, t1, np.minimum(t1, np.maximum(ta, tb)))
            live &= ~(t0 > t1)
            wa, wb = qa[:, 2] + dq[:, 2] * t0, qa[:, 2] + dq[:, 2] * t1
            lo = np.clip(np.trunc(np.minimum(wa, wb)), -1, n).astype(np.int64).clip(0, n - 1)
            hi = np.clip(np.trunc(np.maximum(wa, wb)), -1, n).astype(np.int64).clip(0, n - 1)
            fwd = dq[:, 2] >= 0
            inv_dw = np.where(np.abs(dq[:, 2]) > F(1e-12), F(1) / dq[:, 2], F(0))
        dir_base = self.base[a] + d * self.wpd
        npieces = np.where(live, hi // seg - lo // seg + 1, 0)
        shifts = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
        for p in range(int(npieces.max(initial=0))):
            on = npieces > p
            ps = np.where(fwd, (lo // seg + p) * seg, (hi // seg - p) * seg)
            st, en = np.maximum(ps, lo), np.minimum(ps + seg - 1, hi)
            t = ((F(0.5) * (st + en + 1).astype(F)) - qa[:, 2]) * inv_dw
            t = np.where(t < t0, t0, np.where(t > t1, t1, t))
            fu, fv = qa[:, 0] + dq[:, 0] * t, qa[:, 1] + dq[:, 1] * t
            mask = ((np.uint64(0xFFFFFFFF) >> (31 - (en & 31)).astype(np.uint64)) &
                    (np.uint64(0xFFFFFFFF) << (st & 31).astype(np.uint64)) & np.uint64(0xFFFFFFFF))
            for j, (su, sv) in enumerate(shifts):
                u = fu + F(su) * F(thick) if j else fu
                v = fv + F(sv) * F(thick) if j else fv
                ok = on & (u >= 0) & (u < fn) & (v >= 0) & (v < fn)
                r = np.where(ok, u.astype(np.int64) * n + v.astype(np.int64), 0)
                w = st >> 5
                ok &= (w >= self.w0[r]) & (w < self.w1[r])
                word = self.words[np.where(ok, dir_base + self.row_start[r] + w, 0)].astype(np.uint64)
                got[:, j] |= ok & ((word & mask) != 0)
        return got

    def refine(self, rule, o, t, nm, distant, thick, inst=None):
        """(blocked, uncertain) of the rule, every world-space array and every instance visited."""
        o, t, nm = (np.asarray(x, F) for x in (o, t, nm))
        o, e, s0, s1 = _ray_setup(rule, o, t, nm, np.asarray(distant, bool))
        got = np.zeros((len(o), 5), bool)
        for w, a in enumerate(self.world):
            da = _affine(self.world_inv[w], e) - _affine(self.world_inv[w], o)
            got |= self.array_refine(a, self.world_fold[w], o, e, da, s0, s1, thick)
        for m, a in zip(*(inst or ((), ()))):
            pa, pb = _affine(m, o), _affine(m, e)
            got |= self.array_refine(int(a), self.fold[int(a)], pa, pb, pb - pa, s0, s1, thick)
        return got[:, 0], got.any(1) & ~got.all(1)


# ---------------------------------------------------------------- the tests

@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances", "deforming", "many_instances"])
def test_blocked_bit_is_occluded_and_the_flags_follow_thick(scene, isa):
    rng = np.random.default_rng(17)
    b = native(isa)
    try:
        for snap, prev in zip(scene_frames(scene), [None] + scene_frames(scene)):
            b.update(snap, diff(prev, snap))
            o, t, nm, di = mixed_queries(rng, lights(rng))
            assert len(o) >= 10_000
            want = b.occluded(o, t, normals=nm, distant=di)
            flags = {}
            for thick in (0.0, 0.5, 1.0, 2.0):
                blocked, flags[thick] = b._native_refine(o, t, nm, di, thick)
                assert np.array_equal(blocked, want), f"thick {thick}: {(blocked != want).sum()} answers differ"
            assert not flags[0.0].any()
            assert 0.005 < flags[1.0].mean() < 0.5
            # a superset but for rounding at voxel borders (measured <= 0.1 %); among the 121 thin planes
            # wider rows also step over gaps onto other planes, all five blocked again (0.6-0.7 %)
            lost = 0.01 if scene == "many_instances" else 0.005
            for narrow, wide in ((0.5, 1.0), (1.0, 2.0)):
                assert flags[wide].mean() > flags[narrow].mean()
                assert (flags[narrow] & ~flags[wide]).mean() <= lost
    finally:
        b.close()


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "deforming", "instances", "many_instances"])
def test_flags_are_the_row_shift_rule_evaluated_in_numpy(scene, isa, instance_table):
    """Against the rule written again in NumPy from the backend's tables (float32, the scalar C's
    order of operations): the scalar kernel's arithmetic, the SIMD kernels' differing by the rounding of
    fused multiply-adds; every instance visited (the kernel visits those whose boxes the segment meets,
    grown for the shifted rows)."""
    rng = np.random.default_rng(23)
    b = native(isa)
    try:
        snap = scene_frames(scene)[0]
        b.update(snap, diff(None, snap))
        o, t, nm, di = mixed_queries(rng, lights(rng), 200, 2000)
        tables = _Tables(b)
        inst = (instance_table["inv"], instance_table["ids"]) if len(instance_table.get("ids", ())) else None
        for thick in (1.0, 1.5):
            blocked, uncertain = b._native_refine(o, t, nm, di, thick)
            ref_b, ref_u = tables.refine(b._rule_values(), o, t, nm, di, thick, inst)
            assert 0.01 < ref_u.mean() < 0.5
            limit = 0.0 if isa == "scalar" else 0.002
            assert (blocked != ref_b).mean() <= limit and (uncertain != ref_u).mean() <= limit, \
                f"{(blocked != ref_b).sum()} / {(uncertain != ref_u).sum()} of {len(o)} differ"
    finally:
        b.close()


@pytest.mark.parametrize("isa", ISAS)
def test_rays_through_a_box_are_uncertain_only_near_its_edges(isa):
    """A box floating above the plane z = 0, rays straight up (the grid of direction bin 0: u = -y,
    v = x). At thick 1, a ray farther than 3 voxels from the box's silhouette edges is certain (blocked
    inside, free outside), one within 0.45 voxel of an edge (away from the corners) uncertain: its
    rows one voxel to either side across the edge fall on either side of the voxelized edge."""
    from plain_scenes import snapshot, soup
    from voxel_reference import box

    b = native(isa, UsdmlSettings(voxel_resolution=64, direction_step=5.0))
    try:
        b.update(snapshot([soup("/box", box((-2.0, -2.0, 1.0), (2.0, 2.0, 5.0)))]))
        a = b.arrays[0]
        vox = 2.0 * a.half / a.resolution / abs(a.to_array[0, 0])      # world units, the same on every axis
        rng = np.random.default_rng(4)
        n = 20000
        xy = rng.uniform(-3.0, 3.0, (n, 2))
        xy[: n // 4, 0] = np.sign(xy[: n // 4, 0]) * (2.0 + rng.uniform(-0.45, 0.45, n // 4) * vox)   # near x = ±2
        o = np.c_[xy, np.zeros(n)]
        t = o + [0.0, 0.0, 8.0]
        blocked, uncertain = b._native_refine(o, t, np.tile([0.0, 0.0, 1.0], (n, 1)), None, 1.0)
        r = np.abs(xy).max(axis=1)
        inside, outside = r < 2.0 - 3 * vox, r > 2.0 + 3 * vox
        edge_x = (np.abs(np.abs(xy[:, 0]) - 2.0) < 0.45 * vox) & (np.abs(xy[:, 1]) < 2.0 - 3 * vox)
        edge_y = (np.abs(np.abs(xy[:, 1]) - 2.0) < 0.45 * vox) & (np.abs(xy[:, 0]) < 2.0 - 3 * vox)
        near = edge_x | edge_y
        assert inside.sum() > 3000 and outside.sum() > 3000 and near.sum() > 3000
        assert blocked[inside].all() and not blocked[outside].any()
        assert not uncertain[inside | outside].any()
        assert uncertain[near].all()
        assert not b._native_refine(o, t, np.tile([0.0, 0.0, 1.0], (n, 1)), None, 0.0)[1].any()
    finally:
        b.close()


def test_query_refine_checks_its_output_and_reads_any_first_ray():
    """``NativeScene.query_refine`` writes ``out[first:first + count]`` only, uint8 only."""
    rng = np.random.default_rng(2)
    b = native("auto")
    try:
        snap = scene_frames("occluder")[0]
        b.update(snap, diff(None, snap))
        o, t, nm, di = mixed_queries(rng, lights(rng), 100, 1000)
        o, nm = np.ascontiguousarray(o, F), np.ascontiguousarray(nm, F)        # float32 and float64 inputs
        t, di = np.ascontiguousarray(t), np.ascontiguousarray(di.astype(np.int32))   # int32 flags
        rule = b._native_rule()
        whole = np.zeros(len(o), np.uint8)
        b._native.query_refine(rule, 0, len(o), o, t, nm, di, 1.0, whole)
        parts = np.full(len(o), 255, np.uint8)
        for first, count in ((0, 7), (7, 100), (107, len(o) - 107)):
            b._native.query_refine(rule, first, count, o, t, nm, di, 1.0, parts)
        assert np.array_equal(parts, whole) and whole.max() <= 3 and (whole >= 2).any()
        assert np.array_equal(whole & 1, b.occluded(o, t, normals=nm, distant=di.astype(bool)))
        with pytest.raises(TypeError, match="uint8"):
            b._native.query_refine(rule, 0, 4, o, t, nm, di, 1.0, np.zeros(4, bool))
        empty = b._native_refine(np.zeros((0, 3)), np.zeros((0, 3)), None, None, 1.0)
        assert empty[0].shape == (0,) and empty[1].dtype == bool
    finally:
        b.close()


@pytest.mark.parametrize("isa", ISAS)
def test_several_widths_in_one_pass_flag_their_union(isa):
    """``thick`` as several widths (a level's, ``occluded_uncertain``): one pass of the kernel flags what each
    width's own pass flags, together, with the same answers; more than four widths is an error."""
    from usdml.visibility.voxel.backend import THICK, widened

    rng = np.random.default_rng(31)
    b = native(isa)
    try:
        for scene in ("occluder", "instances"):
            snap = scene_frames(scene)[0]
            b.update(snap, diff(None, snap))
            o, t, nm, di = mixed_queries(rng, lights(rng), 200, 2000)
            for level in range(1, len(THICK) + 1):
                blocked, uncertain = b.occluded_uncertain(o, t, normals=nm, distant=di, level=level)
                ref_b, ref_u = widened(lambda w: b._native_refine(o, t, nm, di, w), level)
                assert np.array_equal(blocked, ref_b) and np.array_equal(uncertain, ref_u), (scene, level)
            assert 0.01 < uncertain.mean() < 0.9
        with pytest.raises(ValueError, match="1 to 4 widths"):
            b._native.query_refine(b._native_rule(), 0, 4, o, t, nm, di, [1.0] * 5, np.zeros(len(o), np.uint8))
    finally:
        b.close()
