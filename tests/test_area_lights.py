"""Lights with area (issue 52 item 3, usdml.lighting.area): a rect light's unshadowed irradiance against Lambert's
formula for a polygon, soft shadows against Mitsuba 3's area emitters, far-field equality with today's point
evaluation, points that stay points, and samples that do not depend on how the frame is cut."""

import math
import os
import sys
from dataclasses import replace

import numpy as np
import pytest

from usdml.lighting.area.sampling import sampled
from usdml.lighting.direct import shade_direct
from usdml.scene import LightType
from usdml.stage.lights import LightParams, expand

TOOLS = os.path.join(os.path.dirname(__file__), "..", "tools")


def _light(kind: LightType, position, radius=0.0, width=0.0, height=0.0, angle=0.0, radiance=1.0, rotate=True):
    """One light facing down (-Y) at ``position``: its -Z turned to -Y (rotated -90 degrees about X)."""
    params = LightParams("/World/light", kind, np.full(3, radiance), False, radius, width, height, angle, 180.0, 0.0,
                         0.0, np.zeros(3), True)
    m = np.eye(4)
    m[:3, 3] = position
    if rotate:
        m[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    return expand(params, m[None])


def lambert_polygon(point, normal, vertices, radiance):
    """Irradiance at ``point`` (unit ``normal``) from a Lambertian polygon of uniform ``radiance`` wholly above its
    horizon (Lambert 1760): ``E = L/2 · |Σ_i γ_i n·(r_i × r_i+1)/|r_i × r_i+1||``, γ_i the angle between the unit
    directions r_i, r_i+1 to consecutive vertices."""
    r = np.asarray(vertices, float) - point
    r /= np.linalg.norm(r, axis=1)[:, None]
    total = 0.0
    for a, b in zip(r, np.roll(r, -1, axis=0)):
        c = np.cross(a, b)
        total += math.acos(np.clip(a @ b, -1, 1)) * (normal @ c) / np.linalg.norm(c)
    return radiance / 2 * abs(total)


def test_rect_light_irradiance_is_lamberts_polygon_formula():
    """A 2 x 1 rect light 1.5 above a ground: at points under it, beside it and far off, the sampled irradiance
    (16 samples, by solid angle) is Lambert's closed form within the sampling noise, unbiased over many points."""
    light = _light(LightType.RECT, (0.5, 1.5, -0.25), width=2.0, height=1.0, radiance=7.0)
    corners = [(-0.5, 1.5, -0.75), (1.5, 1.5, -0.75), (1.5, 1.5, 0.25), (-0.5, 1.5, 0.25)]
    rng = np.random.default_rng(4)
    points = np.c_[rng.uniform(-4, 5, 300), np.zeros(300), rng.uniform(-4, 4, 300)]
    normal = np.array([0.0, 1.0, 0.0])
    want = np.array([lambert_polygon(p, normal, corners, 7.0) for p in points])
    got = shade_direct(points, np.tile(normal, (300, 1)), np.full((300, 3), np.pi), light, None,
                       light_samples=16).radiance[:, 0]
    rel = got / want - 1
    assert np.abs(rel).max() < 0.05, np.abs(rel).max()          # measured 0.027
    assert np.median(np.abs(rel)) < 0.01                        # measured 0.004
    assert abs(got.sum() / want.sum() - 1) < 0.002              # unbiased
    # tilted receivers, at the points whose horizon leaves the whole rect above it (the formula's condition)
    tilted = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
    above = points[((np.asarray(corners)[None] - points[:, None]) @ tilted > 0).all(axis=1)][:50]
    want_t = np.array([lambert_polygon(p, tilted, corners, 7.0) for p in above])
    got_t = shade_direct(above, np.tile(tilted, (len(above), 1)), np.full((len(above), 3), np.pi), light, None,
                         light_samples=64).radiance[:, 0]
    assert len(above) >= 30 and np.abs(got_t / want_t - 1).max() < 0.03


@pytest.mark.parametrize("kind,size", [
    (LightType.RECT, dict(width=0.2, height=0.1)), (LightType.DISK, dict(radius=0.1)),
    (LightType.SPHERE, dict(radius=0.1)), (LightType.CYLINDER, dict(radius=0.05, width=0.2)),
    (LightType.DISTANT, dict(angle=2.0))])
def test_far_from_a_light_its_samples_are_the_point_evaluation(kind, size):
    """Thirty light sizes away, the area light's mean equals the same light of size 0 (today's point), and the
    sampled kinds are exactly the sized ones."""
    light = _light(kind, (0.0, 6.0, 0.0), **size)
    point = replace(light, radius=light.radius * 0, width=light.width * 0, height=light.height * 0,
                    angle=light.angle * 0)
    assert sampled(light).all() and not sampled(point).any()
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(-4, 4, 40), np.zeros(40), rng.uniform(-4, 4, 40)]
    n = np.tile([0.0, 1.0, 0.0], (40, 1))
    a = shade_direct(pts, n, np.ones((40, 3)), light, None, light_samples=16, seed=5).radiance
    p = shade_direct(pts, n, np.ones((40, 3)), point, None).radiance
    rel = np.abs(a / p - 1)
    if kind == LightType.CYLINDER:
        # the visible half of the side is nearer than the centre, and its ends are seen at other angles from
        # points near its axis: the point model is off by first order in size / distance (docs/area-lights.md)
        assert rel.max() < 0.08 and rel.mean() < 0.02, (rel.max(), rel.mean())
    else:
        assert rel.max() < 0.005, rel.max()


def test_a_sphere_light_does_not_blow_up_at_close_range():
    """Irradiance right above a sphere light's surface is its solid angle's, L·π·sin²θ_max (θ_max the half-angle it
    covers, normal incidence), where a point at its centre would give L·π·r² / d² (17 times more at 0.05 r)."""
    r, L = 0.5, 3.0
    light = _light(LightType.SPHERE, (0.0, 0.0, 0.0), radius=r, radiance=L, rotate=False)
    d = np.array([0.525, 0.6, 1.0, 2.0])                    # distance of the receiver to the centre
    pts = np.c_[np.zeros(4), -d, np.zeros(4)]
    n = np.tile([0.0, 1.0, 0.0], (4, 1))
    got = shade_direct(pts, n, np.full((4, 3), np.pi), light, None, light_samples=64).radiance[:, 0]
    want = L * math.pi * (r / d) ** 2                       # sin²θ_max = (r/d)²: the disc the sphere covers
    np.testing.assert_allclose(got, want, rtol=0.01)


def test_points_stay_points_and_samples_do_not_depend_on_the_blocks():
    """treatAsPoint spheres are POINT lights (one ray, to the centre); an area light's result for a point is the
    same whatever other points it is shaded with (samples keyed by the point and the light, not by order)."""
    light = _light(LightType.RECT, (0.0, 2.0, 0.0), width=1.0, height=1.0)
    assert not sampled(_light(LightType.POINT, (0, 2, 0), radius=0.5)).any()
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-2, 2, 64), np.zeros(64), rng.uniform(-2, 2, 64)]
    n = np.tile([0.0, 1.0, 0.0], (64, 1))

    def occluded(origins, targets, normals=None, distant=None):     # a half-plane wall x > 0.3 at heights 0.5-1
        t = (0.75 - origins[:, 1]) / np.maximum(targets[:, 1] - origins[:, 1], 1e-9)
        x = origins[:, 0] + t * (targets[:, 0] - origins[:, 0])
        return x > 0.3

    whole = shade_direct(pts, n, np.ones((64, 3)), light, occluded, light_samples=8, seed=3)
    parts = [shade_direct(pts[i::4], n[i::4], np.ones((16, 3)), light, occluded, light_samples=8, seed=3)
             for i in range(4)]
    for i, part in enumerate(parts):
        np.testing.assert_array_equal(part.radiance, whole.radiance[i::4])
    assert ((whole.shadow > 0) & (whole.shadow < 1)).any()         # a penumbra: partly blocked points
    assert whole.queries == 64 * 8
    other = shade_direct(pts, n, np.ones((64, 3)), light, occluded, light_samples=8, seed=4)
    assert not np.array_equal(other.radiance, whole.radiance)         # the seed places the samples


def test_soft_shadows_against_mitsuba(tmp_path):
    """tools/area_lights.py at 32 px: usdml's exact penumbrae against Mitsuba 3's rectangle and sphere area emitters
    (scalar_rgb, 2 x 256 spp; its own noise 1.5 % and 0.6 % RMS there). Bounds: the issue's 6 % median over the
    penumbra and 4 % frame relative RMSE, with the reference's noise on top at this resolution (measured: rect
    1.75 % and 2.13 %, sphere 2.06 % and 2.36 %, means within 0.1 %)."""
    pytest.importorskip("mitsuba")
    pytest.importorskip("embreex")
    sys.path.insert(0, TOOLS)
    try:
        import area_lights
    finally:
        sys.path.remove(TOOLS)
    for shape in ("rect", "sphere"):
        row = area_lights.compare(shape, 32, 256, ["exact"], str(tmp_path))
        exact = row["backends"]["exact"]
        assert row["penumbra_pixels"] > 20
        assert exact["penumbra_median"] < 0.06, (shape, exact)
        assert exact["rel_rmse"] < 0.04 + 2 * row["mitsuba_noise_rel_rmse"], (shape, exact, row)
        assert abs(exact["mean_ratio"] - 1) < 0.01, (shape, exact)


def test_material_rows_and_the_lgh_s_shadow_rays_sample_area_lights():
    """Lambertian material rows (kernels/brdf) give the Lambertian result with each sample's own direction, and
    ``--direct lgh`` keeps lights with area in its hierarchy, its shadow rays going to points sampled on them."""
    from usdml.lighting.lgh.direct import grid_mask
    from usdml.scene import Lights
    from usdml.scene.shading import lambert_rows

    lights = Lights.concat([_light(LightType.RECT, (0.0, 2.0, 0.0), width=1.5, height=0.5),
                            _light(LightType.SPHERE, (1.0, 1.0, 0.5), radius=0.3, rotate=False),
                            _light(LightType.POINT, (-1.0, 1.0, 0.5), radius=0.3, rotate=False)])
    rng = np.random.default_rng(6)
    pts = np.c_[rng.uniform(-2, 2, 50), np.zeros(50), rng.uniform(-2, 2, 50)]
    n = np.tile([0.0, 1.0, 0.0], (50, 1))
    albedo = np.full((50, 3), 0.5)
    plain = shade_direct(pts, n, albedo, lights, None, seed=2)
    rows = shade_direct(pts, n, albedo, lights, None, seed=2, material=lambert_rows(50, np.tile([0, 1.0, 0], (50, 1))))
    np.testing.assert_allclose(rows.radiance, plain.radiance, rtol=2e-5, atol=1e-7)
    assert plain.variance is not None and (plain.variance > 0).any()
    assert grid_mask(lights).tolist() == [True, True, True]
    # --direct lgh: rays aimed at the rect's or the sphere's centre go to points on them, the point's stay
    from usdml.lighting.area.targets import AreaTargets

    area = AreaTargets.of(lights, seed=2)
    origins = np.repeat(pts[:4], 3, axis=0)
    aimed = np.tile(lights.position, (4, 1))
    moved = area.retarget(origins, aimed)
    np.testing.assert_array_equal(moved[2::3], aimed[2::3])
    assert np.allclose(moved[0::3, 1], 2.0) and (np.abs(moved[0::3, 0]) <= 0.75).all()     # on the rect
    assert np.allclose(np.linalg.norm(moved[1::3] - lights.position[1], axis=1), 0.3)       # on the sphere
    assert not np.allclose(moved[0::3], aimed[0::3])
    twice = area.retarget(np.repeat(origins[:1], 2, axis=0), np.repeat(aimed[:1], 2, axis=0))
    assert not np.allclose(twice[0], twice[1])          # a point's two rays to one light: two strata
    # a few lights with area go every-light (exactly --direct all's light), many into the hierarchy
    from usdml.lighting.lgh.direct import prepare_direct

    few = prepare_direct(lights, light_samples=16)
    assert len(few.grid) == 1 and len(few.rest) == 2 and few.area is None
    many = Lights.concat([lights] * 40)                 # 80 lights with area x 16 samples > 1,024 rays a point
    field = prepare_direct(many, light_samples=16)
    assert len(field.grid) == 120 and len(field.rest) == 0 and len(field.area.lights) == 80


def test_a_render_states_its_area_lights_noise(new_stage, tmp_path, capsys):
    """The frame's estimate of its area lights' sampling noise is in the EXR header and the command's summary."""
    pytest.importorskip("embreex")
    from pxr import UsdLux

    from conftest import ground_stage
    from usdml.aov.exr import read_exr
    from usdml.cli import main

    def rect(stage):        # a 3 x 1 panel 2 above the ground, facing it
        light = UsdLux.RectLight.Define(stage, "/World/panel")
        for name, value in (("inputs:width", 3.0), ("inputs:intensity", 50.0)):
            light.GetPrim().GetAttribute(name).Set(value)
        for op, value in ((light.AddTranslateOp(), (0, 2, 0)), (light.AddRotateXOp(), -90)):
            op.Set(value)

    path = ground_stage(new_stage, rect)
    out = tmp_path / "f.exr"
    assert main(["render", path, str(out), "--imageWidth", "16", "--light-samples", "4"]) == 0
    summary = capsys.readouterr().out
    assert "lights with area: estimated rel. RMSE of their sampling" in summary and "(4 samples a light)" in summary
    header = read_exr(out)[1]
    assert header["usdml:estimate:area:light_samples"] == 4
    assert 0 < header["usdml:estimate:area:rel_rmse"] < 0.5


def test_a_triangle_light_is_lamberts_polygon():
    """A TRIANGLE light as the mesh-light convention builds it (xform columns edge1, edge2, unit normal, vertex 0;
    position the centroid, axis the normal, intensity L · area): its sampled irradiance is Lambert's formula for
    the triangle, and it emits on its normal's side only."""
    from usdml.scene import Lights

    v = np.array([[-1.0, 2.0, -0.5], [1.5, 2.2, -0.2], [0.0, 1.8, 1.2]])
    e1, e2 = v[1] - v[0], v[2] - v[0]
    normal = np.cross(e1, e2)
    area = np.linalg.norm(normal) / 2
    normal /= -np.linalg.norm(normal) if normal[1] > 0 else np.linalg.norm(normal)       # facing down
    xform = np.eye(4)
    xform[:3, 0], xform[:3, 1], xform[:3, 2], xform[:3, 3] = e1, e2, normal, v[0]
    L = 4.0
    light = Lights(type=np.array([LightType.TRIANGLE], np.int8), position=v.mean(0)[None], axis=normal[None],
                   xform=xform[None], radiance=np.full((1, 3), L, np.float32),
                   intensity=np.full((1, 3), L * area, np.float32), radius=np.zeros(1), width=np.zeros(1),
                   height=np.zeros(1), angle=np.zeros(1), cone_angle=np.full(1, 180.0), cone_softness=np.zeros(1),
                   focus=np.zeros(1), focus_tint=np.zeros((1, 3), np.float32), shadow=np.ones(1, bool),
                   paths=["/World/panel"], instance_ids=np.full(1, -1))
    assert sampled(light).all()
    rng = np.random.default_rng(9)
    pts = np.c_[rng.uniform(-3, 3, 60), np.zeros(60), rng.uniform(-3, 3, 60)]
    up = np.array([0.0, 1.0, 0.0])
    want = np.array([lambert_polygon(p, up, v, L) for p in pts])
    got = shade_direct(pts, np.tile(up, (60, 1)), np.full((60, 3), np.pi), light, None, light_samples=64).radiance[:, 0]
    rel = np.abs(got / want - 1)                      # by area, 64 samples: measured median 0.006, sum 1.0003
    assert np.median(rel) < 0.01 and abs(got.sum() / want.sum() - 1) < 0.005, (np.median(rel), got.sum() / want.sum())
    above = shade_direct(pts + [0, 4, 0], np.tile(-up, (60, 1)), np.ones((60, 3)), light, None).radiance
    assert (above == 0).all()                           # behind its emitting side
