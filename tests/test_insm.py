"""The insm backend (paper 001): Alg. 2's triangulation on analytic depth images, the per-light maps'
rasterizer against Embree, the compiled maps against the Warp kernels, which queries the maps answer,
and its error against exact on the dragon stage (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from usdml.lighting.direct import shade_with
from usdml.scene import LightType, diff
from usdml.visibility import ExactBackend
from usdml.visibility.insm import mesh as insm_mesh
from usdml.visibility.insm.backend import InsmBackend, kernels, light_views, take_lights
from usdml.visibility.insm.mesh import View, clusters, connected_edges, insm_views, reference_viewpoints, triangulate

from backend_scenes import lights, scene_frames, surface_points

pytest.importorskip("embreex")

W = 32
#: a view at the origin looking down +z, pixels spanning x / z and y / z in [-0.5, 0.5]
VIEW = View(np.zeros(3), np.eye(3), np.array([W, W / 2, W, W / 2], float))


def analytic_image(depth_of):
    """Depth image, points and normals of a surface given as ``depth_of(x/z, y/z) -> (z, normal)``."""
    dirs = VIEW.ray_directions(W)
    z, n = depth_of(dirs[:, 0], dirs[:, 1])
    pts = dirs * z[:, None]
    return (z.reshape(W, W).astype(np.float32), pts.reshape(W, W, 3).astype(np.float32),
            n.reshape(W, W, 3).astype(np.float32))


def tilted_plane(sx, sy):
    # plane z = 5 + 0.8 x through the rays (x, y, 1) t: t = 5 / (1 - 0.8 sx)
    z = 5.0 / (1.0 - 0.8 * sx)
    n = np.tile(np.array([0.8, 0.0, -1.0]) / np.hypot(0.8, 1.0), (len(sx), 1))
    return z, n


def step(sx, sy):
    # two planes facing the view, 5 and 8 away, meeting at x / z = 0
    z = np.where(sx < 0, 5.0, 8.0)
    return z, np.tile([0.0, 0.0, -1.0], (len(sx), 1))


def crease(sx, sy):
    # a floor y = -1 (rays going down) meeting a wall z = 6 (rays above the floor's horizon there)
    t_floor = np.where(sy < 0, -1.0 / np.minimum(sy, -1e-9), np.inf)
    floor = t_floor < 6.0
    z = np.where(floor, t_floor, 6.0)
    n = np.where(floor[:, None], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0])
    return z, n


def test_a_plane_is_reconstructed_whole_and_on_the_plane():
    z, p, n = analytic_image(tilted_plane)
    tris = triangulate(z[None], p[None], [VIEW], 2.0, n[None]).reshape(-1, 3, 3)
    assert len(tris) == 2 * (W - 1) ** 2          # every cell, both triangles: Δ²(1/z) = 0 on a plane
    # on the plane z = 5 + 0.8 x
    np.testing.assert_allclose(tris[..., 2], 5 + 0.8 * tris[..., 0], rtol=1e-5)
    # the same with the paper's rule alone
    assert len(triangulate(z[None], p[None], [VIEW], 2.0)) // 3 == 2 * (W - 1) ** 2


def test_no_triangle_spans_a_step():
    z, p, n = analytic_image(step)
    tris = triangulate(z[None], p[None], [VIEW], 2.0, n[None]).reshape(-1, 3, 3)
    depth = tris[..., 2]
    assert np.all((depth.max(1) < 5.5) | (depth.min(1) > 7.5)), "a triangle joins the two planes"
    # both planes are there, eroded by at most a column of cells each side of the step
    near, far = (depth.max(1) < 5.5).sum(), (depth.min(1) > 7.5).sum()
    assert near >= 2 * (W - 1) * (W // 2 - 3) and far >= 2 * (W - 1) * (W // 2 - 3)


def test_a_crease_is_connected_only_by_the_crease_rule(monkeypatch):
    z, p, n = analytic_image(crease)
    edges = connected_edges(z, W, 2.0, p, n)[(1, 0)]       # down the image: floor rows, then the wall
    floor = np.isfinite(z) & (z < 5.999)
    across = floor[:-1] != floor[1:]                       # row pairs where the floor meets the wall
    rows = np.nonzero(across.any(1))[0]
    assert len(rows) and edges[rows][across[rows]].all()
    monkeypatch.setattr(insm_mesh, "CREASE", 0.0)
    paper = connected_edges(z, W, 2.0, p, n)[(1, 0)]
    assert not paper[rows][across[rows]].any()            # the second differences alone cut it


def test_viewpoints_are_the_papers_ten_first():
    lo, hi = np.array([-2.0, 0.0, -1.0]), np.array([2.0, 1.0, 1.0])
    pts = reference_viewpoints(lo, hi, 10)
    centre = 0.5 * (lo + hi)
    local = (pts - centre) / (insm_mesh.MARGIN * 0.5 * (hi - lo))
    # eight non-vertical edges (y = ±1, one of x, z zero) and the two side faces (x = ±1, y = z = 0)
    edges = [tuple(v) for v in np.round(local).astype(int) if abs(v[1]) == 1]
    sides = [tuple(v) for v in np.round(local).astype(int) if v[1] == 0]
    assert len(edges) == 8 and all((x == 0) != (z == 0) for x, _, z in edges)
    assert sorted(sides) == [(-1, 0, 0), (1, 0, 0)]
    assert len(set(map(tuple, reference_viewpoints(lo, hi, insm_mesh.MAX_COUNT)))) == insm_mesh.MAX_COUNT
    # each view's image holds the whole box
    for view in insm_views(lo, hi, 10, 64):
        corners = insm_mesh.box_corners(lo, hi)
        q = (corners - view.origin) @ view.rot.T
        px = view.proj[0] * q[:, 0] / q[:, 2] + view.proj[1]
        py = view.proj[2] * q[:, 1] / q[:, 2] + view.proj[3]
        assert q[:, 2].min() > 0 and px.min() >= -1e-6 and px.max() <= 64 + 1e-6 and py.min() >= -1e-6


def _raster(tris, lv, size, cube: bool):
    import warp as wp
    k = kernels()
    tiles = -(-size // 16)
    nv = lv.views
    depth = wp.full(nv * size * size, -1.0e30, dtype=float, device="cpu")
    tile_z = wp.full(nv * tiles * tiles, 1.0e30, dtype=float, device="cpu")    # every tile wanted
    view_z = wp.full(nv, 1.0e30, dtype=float, device="cpu")
    t = wp.array(tris, dtype=wp.vec3, device="cpu")
    rot, proj = wp.array(lv.rot, dtype=wp.mat33), wp.array(lv.proj, dtype=wp.vec4)
    near = wp.array(lv.near, dtype=float)
    if cube:
        wp.launch(k.raster_cube, dim=len(tris) // 3, inputs=[t, wp.vec3(*lv.position[0]), rot, proj, near, 0, size,
                                                             0, depth, tiles, tile_z, view_z])
    else:
        wp.launch(k.raster_views, dim=(nv, len(tris) // 3),
                  inputs=[t, wp.array(lv.origin, dtype=wp.vec3), rot, proj, wp.array(lv.kind, dtype=wp.int32), near,
                          0, size, 0, depth, tiles, tile_z, view_z])
    key = depth.numpy().reshape(nv, size * size)
    return np.where(key > -1e29, np.where(lv.kind[:, None] == 0, 1.0 / np.where(key > -1e29, key, 1.0), -key), np.inf)


@pytest.mark.parametrize("kind", ["cube", "spot", "distant"])
def test_the_rasterizer_matches_embree_on_small_maps(kind):
    """Each texel of a light's map holds the depth Embree finds along the ray through its centre."""
    snap = scene_frames("occluder")[0]
    with ExactBackend() as ex:
        ex.update(snap)
        from usdml.scene import world_geometry
        from usdml.visibility.base import all_members
        members = all_members(snap)
        pts, tri = world_geometry(snap, members)
        tris = np.ascontiguousarray(pts[tri].reshape(-1, 3), np.float32)
        size = 48
        pos, axis = np.array([[1.0, 6.0, 0.5]]), np.array([[0.2, -1.0, 0.1]])
        axis /= np.linalg.norm(axis)
        lv = light_views(pos, axis, np.array([kind == "distant"]), np.array([40.0 if kind == "spot" else 180.0]),
                         np.zeros(3), 15.0, size)
        got = _raster(tris, lv, size, cube=False)
        if kind == "cube":
            np.testing.assert_array_equal(_raster(tris, lv, size, cube=True), got)   # the cube kernel: the same
        seen = 0
        for v in range(lv.views):
            view = View(lv.origin[v].astype(float), lv.rot[v].astype(float), lv.proj[v].astype(float))
            if lv.kind[v] == 0:
                dirs = view.ray_directions(size)
                origins = np.repeat(view.origin[None], len(dirs), 0)
            else:
                ax, bx, ay, by = view.proj
                c = np.arange(size) + 0.5
                xx, yy = np.meshgrid((c - bx) / ax, (c - by) / ay)
                origins = view.origin + np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1) @ view.rot
                dirs = np.tile(view.rot[2], (len(origins), 1))
            t = ex.intersect(origins, dirs)["t"]
            both = np.isfinite(t) & np.isfinite(got[v])
            assert np.array_equal(np.isfinite(t), np.isfinite(got[v])) or \
                (np.isfinite(t) != np.isfinite(got[v])).mean() < 0.01          # edge texels may differ
            seen += both.sum()
            np.testing.assert_allclose(got[v][both], t[both], rtol=2e-4)
        assert seen > size * size // 4


def _snapshot_and_points(scene="occluder"):
    snap = scene_frames(scene)[0]
    pts, nrm = surface_points(np.random.default_rng(5), 400)
    return snap, pts, nrm


def test_compiled_maps_answer_as_the_warp_kernels():
    from usdml.visibility.insm import native as insm_native
    if insm_native.library() is None:
        pytest.skip(insm_native.describe())
    snap, pts, nrm = _snapshot_and_points()
    lit = lights(np.random.default_rng(4))
    got = {}
    for k in ("native", "warp"):
        b = InsmBackend(insm_cpu_kernel=k, insm_light_resolution=128)
        b.update(snap, diff(None, snap))
        got[k] = b.blocked_lights(lit, pts, nrm)
        assert b.describe()["cpu_kernel"] == k
        b.close()
    assert 0.05 < got["warp"].mean() < 0.95
    assert (got["native"] != got["warp"]).mean() < 1e-4


def test_the_frames_lights_are_mapped_and_other_targets_go_to_exact():
    snap, pts, nrm = _snapshot_and_points()
    lit = lights(np.random.default_rng(6))
    b = InsmBackend(insm_light_resolution=128)
    b.update(snap, diff(None, snap))
    albedo = np.full((len(pts), 3), 0.5, np.float32)
    shade_with(b, pts, nrm, albedo, lit)             # the frame's lights, point and distant, become known
    b._reset_stats()
    matrix = b.occluded_matrix(pts, nrm, lit.position, lit.type == LightType.DISTANT, lit.axis)
    point = np.flatnonzero(lit.type != LightType.DISTANT)
    targets = np.repeat(lit.position[point[:4]], len(pts), 0)
    origins = np.tile(pts, (4, 1))
    normals = np.tile(nrm, (4, 1))
    got = b.occluded(origins, targets, normals=normals)
    np.testing.assert_array_equal(got, matrix[:, point[:4]].T.ravel())
    assert b.stats["exact_queries"] == 0
    # a VPL-like target that is not a light: exact's answer, counted
    other = targets + np.array([0.01, 0.0, 0.0])
    with ExactBackend() as ex:
        ex.update(snap)
        np.testing.assert_array_equal(b.occluded(origins, other, normals=normals),
                                      ex.occluded(origins, other, normals=normals))
    assert b.stats["exact_queries"] == len(other)
    b.close()


def test_depth_images_are_cast_again_only_when_geometry_moves():
    frames = scene_frames("instances")
    b = InsmBackend(insm_light_resolution=64)
    b.update(frames[0], diff(None, frames[0]))
    first = b._tris
    b.update(frames[0], diff(frames[0], frames[0]))
    assert b._tris is first and b.stats["depth_seconds"] == 0.0
    b.update(frames[1], diff(frames[0], frames[1]))
    assert b._tris is not first and b.stats["depth_seconds"] > 0.0
    assert not np.array_equal(b._tris, first)
    b.close()


def test_clusters_hold_every_triangle_in_their_boxes():
    snap, _, _ = _snapshot_and_points("instances")
    b = InsmBackend(insm_light_resolution=64)
    b.update(snap, diff(None, snap))
    first, boxes = clusters(b._tris)
    t = b._tris.reshape(-1, 3, 3)
    assert first[0] == 0 and first[-1] == len(t) and np.all(np.diff(first) > 0)
    owner = np.repeat(np.arange(len(boxes)), np.diff(first))
    assert np.all(t.min(1) >= boxes[owner, :3]) and np.all(t.max(1) <= boxes[owner, 3:])
    b.close()


def test_take_lights_cuts_every_field():
    lit = lights(np.random.default_rng(1))
    part = take_lights(lit, np.array([2, 5]))
    assert len(part) == 2 and part.paths == [lit.paths[2], lit.paths[5]]
    np.testing.assert_array_equal(part.cone_angle, lit.cone_angle[[2, 5]])


@pytest.mark.slow
def test_dragon_stage_within_its_bound_of_exact():
    """Paper 001's dragon with 1,024 lights, at the paper's settings: measured ε_s 2.4 % at 128 px
    (docs/insm.md: the paper's 0.1 % is not reached); bound 1.5x above at 64 px."""
    from conftest import STAGES
    from usdml.compare import compare_visibility
    from usdml.stage import StageDelegate

    r = compare_visibility(StageDelegate(str(STAGES / "dragon.usda")), "insm", image_width=64)
    assert r["eps_s"] < 0.04 and r["eps_v"] < 0.06, r
    assert r["reconstructed_triangles"] > 10_000 and r["exact_queries"] == 0


def test_a_frame_builds_each_lights_map_once_whatever_the_pixel_samples(new_stage):
    """Every pass's points are shaded in one call (FrameRenderer, LIGHT_MAJOR), so four primary rays per
    pixel cost one set of maps, and the image equals exact's where nothing is in the way."""
    from conftest import ground_stage
    from pxr import UsdLux
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    def bulb(s):        # a point light: its map answers its rays (a light with area sends its rays to exact)
        light = UsdLux.SphereLight.Define(s, "/World/bulb")
        light.AddTranslateOp().Set((1, 4, 0))
        light.CreateTreatAsPointAttr(True)

    path = ground_stage(new_stage, bulb)
    images = {}
    for name in ("insm", "exact"):
        d = StageDelegate(path)
        r = FrameRenderer(d, UsdmlSettings(pixel_samples=4, visibility=name))
        try:
            images[name] = r.render(d.start_time, 16, 16, {"direct"}).buffers["direct"]
            if name == "insm":
                # one map for the frame's shading, one more for its error estimate's sampled pairs
                # (usdml.render.estimate: one occluded call)
                assert r.backends.shadow.stats["maps"] == 2 and r.backends.shadow.stats["exact_queries"] == 0
        finally:
            r.close()
    np.testing.assert_allclose(images["insm"], images["exact"], rtol=1e-5, atol=1e-7)


def test_usdml_bench_times_the_insm_frame_phases(new_stage, capsys):
    """``usdml bench --visibility insm``: the per-frame build (depth images, triangulation) and the last
    pass's receiver tiles, maps and lookups, in the JSON and on the line."""
    import json

    from conftest import ground_stage
    from pxr import UsdGeom, UsdLux
    from usdml.bench import format_bench
    from usdml.cli import main

    def scene(stage):
        UsdGeom.Cube.Define(stage, "/World/box").AddTranslateOp().Set((0, 1, 0))
        UsdLux.SphereLight.Define(stage, "/World/bulb").AddTranslateOp().Set((2, 5, 1))
    path = ground_stage(new_stage, scene)
    assert main(["bench", path, "--visibility", "insm", "--insm-light-resolution", "64", "--imageWidth", "16",
                 "--json"]) == 0
    row = json.loads(capsys.readouterr().out)[0]
    assert row["backend"] == "insm" and 0 < row["blocked_fraction"] < 1
    assert row["depth_image_seconds"] > 0 and row["reconstructed_triangles"] > 100 and row["last_maps"] == 1
    assert row["exact_queries"] == 0 and row["disagreement_vs_exact"] < 0.05
    assert "per frame: depth images" in format_bench([row])


def test_a_plate_shadow_and_the_inverse_square_law_analytically(new_stage):
    """Against no usdml method: a point light over the ground and a 4 x 4 plate 1 unit above it. Where
    the segment to the light crosses the plate (0.6 inside its edge: a depth-image pixel) the ground is
    dark; where it passes 0.1 clear of it, ``direct`` is albedo / π · I cos θ / d² (I = intensity · π r²,
    treatAsPoint)."""
    import math

    from conftest import ALBEDO, add_quad, ground_stage
    from pxr import UsdLux
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    light = np.array([8.0, 4.0, 0.3])          # to the side: the shadow falls beside the plate, in view

    def scene(stage):
        add_quad(stage, "/World/plate", size=4, y=1)
        s = UsdLux.SphereLight.Define(stage, "/World/bulb")
        s.CreateTreatAsPointAttr(True)
        s.CreateRadiusAttr(0.1)
        s.CreateIntensityAttr(5000)
        s.AddTranslateOp().Set(tuple(light))

    d = StageDelegate(ground_stage(new_stage, scene))
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, visibility="insm"))
    try:
        b = r.render(d.start_time, 160, 160, {"direct", "P"}).buffers
    finally:
        r.close()
    p = b["P"].astype(np.float64).reshape(-1, 3)
    got = b["direct"][..., 0].astype(np.float64).ravel()
    ground = np.abs(p[:, 1]) < 1e-4
    to = light - p
    d2 = (to ** 2).sum(-1)
    lit = ALBEDO / math.pi * 5000 * math.pi * 0.01 * (to[:, 1] / np.sqrt(d2)) / d2
    x = p + to * (1.0 / light[1])                 # where the segment crosses y = 1
    edge = 2.0 - np.maximum(np.abs(x[:, 0]), np.abs(x[:, 2]))     # > 0: inside the plate
    # the reconstructed plate's edge erodes by up to a depth-image pixel (paper 001's "half a pixel"): the
    # 40-unit scene over 128 pixels from 1.5x out is about 0.5 units (measured: leaks up to 0.32 in)
    shadowed, clear = ground & (edge > 0.6), ground & (edge < -0.1)
    assert shadowed.sum() > 100 and clear.sum() > 100
    assert np.all(got[shadowed] == 0.0)
    np.testing.assert_allclose(got[clear], lit[clear], rtol=2e-3)
