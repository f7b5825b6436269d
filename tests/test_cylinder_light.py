"""UsdLux CylinderLight: units, the point-at-its-centre profile I⊥·sin θ against the true cylinder side,
direct shading against the closed form, the voxel kernel against exact, VPL power and emission profile,
bad attributes through the CLI."""

import math

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux

from conftest import ALBEDO, add_cube_mesh, ground_stage, render_aovs
from usdml.cli import main
from usdml.lighting.direct import shade_direct, shade_with
from usdml.scene import Lights, LightType
from usdml.stage import StageDelegate

pytest.importorskip("embreex")


def _cylinder(stage, path="/World/tube", radius=0.5, length=1.0, intensity=1.0, normalize=False):
    c = UsdLux.CylinderLight.Define(stage, path)
    c.CreateRadiusAttr(radius)
    c.CreateLengthAttr(length)
    c.CreateIntensityAttr(intensity)
    c.CreateNormalizeAttr(normalize)
    return c


def _lights(stage) -> Lights:
    add_cube_mesh(stage, "/ground")
    stage.Save()
    return StageDelegate(stage.GetRootLayer().realPath).snapshot(0).lights


def _side_irradiance(L, radius, length, centre, axis, points, normals, n_phi=360, n_x=120):
    """Irradiance (P,) at ``points`` from the true Lambertian side of a cylinder of radiance ``L``,
    by a midpoint rule over its surface (each element visible where it faces the point): the
    reference the point model is checked against."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    x = ((np.arange(n_x) + 0.5) / n_x - 0.5) * length
    n = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v                       # (F, 3)
    pos = centre + (radius * n)[:, None, :] + x[None, :, None] * axis             # (F, X, 3)
    pos, n = pos.reshape(-1, 3), np.repeat(n, n_x, axis=0)
    dA = 2 * np.pi * radius / n_phi * length / n_x
    out = []
    for p, nr in zip(points, normals):
        w = p - pos
        d2 = (w * w).sum(1)
        w /= np.sqrt(d2)[:, None]
        out.append(L * dA * (np.maximum((n * w).sum(1), 0) * np.maximum(-(w @ nr), 0) / d2).sum())
    return np.array(out)


# ---------------------------------------------------------------------------------------------- units

def test_cylinder_light_units_and_scale(new_stage, warnings_log):
    stage = new_stage()
    _cylinder(stage, "/plain", radius=0.25, length=3.0, intensity=10.0)
    n = _cylinder(stage, "/norm", radius=0.25, length=3.0, intensity=10.0, normalize=True)
    n.AddScaleOp().Set((2, 3, 3))                 # length 6, radius 0.75
    e = _cylinder(stage, "/ellipse", radius=1.0, length=1.0, intensity=1.0)
    e.AddScaleOp().Set((1, 1, 3))                 # elliptic section, semi-axes 1 and 3
    line = _cylinder(stage, "/line", radius=0.0, length=2.0, intensity=4.0, normalize=True)
    line.CreateTreatAsLineAttr(True)
    _cylinder(stage, "/dark", radius=0.0, length=2.0)
    lights = _lights(stage)
    assert lights.type.tolist() == [LightType.CYLINDER] * 5
    # I⊥ = L · 2r · length; normalize: L / (2πr · length), so I⊥ = intensity / π at any size
    assert np.allclose(lights.intensity[0], 10 * 2 * 0.25 * 3)
    assert lights.radius[1] == pytest.approx(0.75) and lights.width[1] == pytest.approx(6.0)
    assert np.allclose(lights.radiance[1], 10 / (2 * math.pi * 0.75 * 6), rtol=1e-6)
    assert np.allclose(lights.intensity[1], 10 / math.pi, rtol=1e-6)
    # elliptic section: Ramanujan's perimeter, radius = perimeter / 2π
    perimeter = math.pi * (3 * 4 - math.sqrt((3 + 3) * (1 + 9)))
    assert lights.radius[2] == pytest.approx(perimeter / (2 * math.pi))
    assert np.allclose(lights.intensity[2], perimeter / math.pi, rtol=1e-6)
    assert np.allclose(lights.intensity[3], 4 / math.pi, rtol=1e-6)   # a normalized line light
    assert np.allclose(lights.intensity[4], 0.0)
    assert "/dark: cylinder light with radius or length 0" in warnings_log.text
    assert "/line" not in warnings_log.text
    assert np.allclose(lights.axis, [0, 0, -1])                        # shaping axis, as every light
    assert np.allclose(lights.cylinder_axis(), [1, 0, 0])
    assert "CylinderLight is not supported" not in warnings_log.text


def test_cylinder_light_in_centimetres(new_stage):
    stage = new_stage()
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    _cylinder(stage, radius=5.0, length=100.0, intensity=2.0)
    lights = _lights(stage)
    assert np.allclose(lights.intensity[0], 2 * 2 * 0.05 * 1.0, rtol=1e-6)   # m²


def test_info_lists_cylinder_lights(new_stage, capsys):
    import json
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    _cylinder(stage)
    UsdLux.SphereLight.Define(stage, "/bulb")
    stage.Save()
    assert main(["info", stage.GetRootLayer().realPath, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["lightTypes"] == {"sphere": 1, "cylinder": 1}
    assert not any("Cylinder" in w for w in info["warnings"])


@pytest.mark.parametrize("attr, value, message", [
    ("inputs:radius", -0.5, "negative radius -0.5; use a radius >= 0"),
    ("inputs:length", -2.0, "negative length -2; use a length >= 0"),
    ("inputs:radius", float("nan"), "value nan is not finite"),
    ("inputs:length", float("inf"), "value inf is not finite"),
])
def test_bad_cylinder_attributes_end_the_render_with_one_line(new_stage, tmp_path, capsys, attr, value, message):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    _cylinder(stage, "/World/tube").GetPrim().GetAttribute(attr).Set(value)
    stage.Save()
    code = main(["render", stage.GetRootLayer().realPath, str(tmp_path / "x.exr"), "--imageWidth", "8"])
    err = capsys.readouterr().err
    (line,) = [s for s in err.splitlines() if s.startswith("usdml: error:")]
    assert code == 2 and "Traceback" not in err
    assert f"/World/tube.{attr}: {message}" in line
    assert not (tmp_path / "x.exr").exists()


# ---------------------------------------------------------------------------------------------- the profile

def test_sampled_side_is_the_true_cylinder_side_and_the_point_model_its_far_field(new_stage):
    """Shadow rays to points sampled on the side (usdml.lighting.area) give the true cylinder's irradiance
    (integrated over its surface) at any distance, where the point at the centre, I(ω) = L·2r·length·sin θ
    (the projected area of the side), is off by an error of first order in size / distance (the visible half
    of the side is nearer than the centre; a sphere has none)."""
    stage = new_stage()
    c = _cylinder(stage, radius=0.3, length=1.2, intensity=7.0)
    c.AddTranslateOp().Set((1.0, 2.0, 3.0))
    c.AddRotateZOp().Set(35.0)
    lights = _lights(stage)
    axis = np.array([math.cos(math.radians(35)), math.sin(math.radians(35)), 0.0])
    assert np.allclose(lights.cylinder_axis()[0], axis)
    rng = np.random.default_rng(3)
    w = rng.normal(size=(30, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    sin = np.sqrt(1 - (w @ axis) ** 2)
    w = w[sin > 0.3]
    assert sin.max() > 0.99 and (sin < 0.5).any()      # across the axis and nearer to it
    errors, sampled = [], []
    point = Lights.concat([lights])
    point.radius[:], point.width[:] = 0.0, 0.0          # no size: the point at the centre
    for d in (3.0, 100.0, 200.0):
        points = np.array([1.0, 2.0, 3.0]) + d * w
        albedo = np.full((len(w), 3), math.pi, np.float32)
        want = _side_irradiance(7.0, 0.3, 1.2, np.array([1.0, 2.0, 3.0]), axis, points, -w)
        got = shade_direct(points, -w, albedo, lights, None, light_samples=16).radiance[:, 0]
        sampled.append(np.abs(got / want - 1).max())
        if d > 50:
            at_centre = shade_direct(points, -w, albedo, point, None).radiance[:, 0]
            errors.append(np.abs(at_centre / want - 1).max())
    # the sampling's noise (16 points, by the angle along the length): measured 0.028 at 3, 0.005 and 0.003 at 100
    # and 200
    assert sampled[0] < 0.06 and max(sampled[1:]) < 0.01, sampled
    assert errors[0] < 0.01 and errors[1] < 0.005, errors
    assert 0.4 < errors[1] / errors[0] < 0.6, errors        # first order: halves with twice the distance
    # and the power of I⊥·sin θ over the sphere is a Lambertian area's π·L·A
    theta = (np.arange(2000) + 0.5) / 2000 * math.pi
    power = (7.0 * 2 * 0.3 * 1.2 * np.sin(theta) * 2 * math.pi * np.sin(theta)).sum() * math.pi / 2000
    assert power == pytest.approx(math.pi * 7.0 * 2 * math.pi * 0.3 * 1.2, rel=1e-6)


def test_cylinder_light_above_a_plane_matches_the_closed_form(new_stage):
    centre = np.array([2.0, 3.0, -1.0])

    def light(stage):
        c = _cylinder(stage, radius=0.2, length=4.0, intensity=400.0)
        c.AddTranslateOp().Set(Gf.Vec3d(*centre))
        c.AddRotateYOp().Set(30.0)
        c.AddRotateZOp().Set(-50.0)

    path = ground_stage(new_stage, light)
    stage = Usd.Stage.Open(path)
    xf = UsdGeom.Xformable(stage.GetPrimAtPath("/World/tube")).ComputeLocalToWorldTransform(1)
    axis = np.array(xf.TransformDir(Gf.Vec3d(1, 0, 0)))
    axis /= np.linalg.norm(axis)
    b = render_aovs(path)
    p = b["P"].astype(np.float64)
    to = centre - p
    d2 = (to ** 2).sum(-1)
    w = to / np.sqrt(d2)[..., None]
    sin_c = np.sqrt(np.maximum(1 - (w @ axis) ** 2, 0))
    # the true side's irradiance (the point model, 400·2·0.2·4·sin θ_c·cos θ / d², is its far field only)
    got = b["direct"][..., 0].astype(np.float64)
    assert (sin_c > 0).all()
    pick = np.random.default_rng(1).choice(p.shape[0] * p.shape[1], 200, replace=False)
    pts = p.reshape(-1, 3)[pick]
    side = _side_irradiance(400.0, 0.2, 4.0, centre, axis, pts, np.tile([0.0, 1.0, 0.0], (200, 1)))
    lit = side > 1e-3 * side.max()
    rel = np.abs(got.reshape(-1)[pick][lit] / (ALBEDO / math.pi * side[lit]) - 1)
    # 16 points on a tube 4 long: noise, unbiased (measured median 0.013, max 0.049 a pixel; the mean 0.6 %)
    assert np.median(rel) < 0.03 and rel.max() < 0.1, (np.median(rel), rel.max())
    mean = got.reshape(-1)[pick][lit].mean() / (ALBEDO / math.pi * side[lit]).mean()
    assert abs(mean - 1) < 0.01, mean
    assert b["shadow"].max() == 0


# ---------------------------------------------------------------------------------------------- voxel

def test_voxel_kernel_shades_cylinder_lights_as_the_numpy_path(small_city):
    """The Warp kernel's cylinder profile (with cone and focus about -Z) against
    :func:`usdml.lighting.direct.shade_direct` asking the same backend: equal to float32."""
    from usdml.visibility import VoxelBackend

    snap, o, t, nrm, ref = small_city
    rng = np.random.default_rng(8)
    n = 24
    xf = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        x = rng.normal(size=3)
        x /= np.linalg.norm(x)
        y = np.cross(x, [0.3, 0.1, 1.0])
        y /= np.linalg.norm(y)
        xf[i, :3, 0], xf[i, :3, 1], xf[i, :3, 2] = x, y, np.cross(x, y)
    xf[:, :3, 3] = np.c_[rng.uniform(-9, 9, n), rng.uniform(2, 9, n), rng.uniform(-9, 9, n)]
    lights = Lights(
        type=np.where(np.arange(n) % 4 == 0, LightType.SPHERE, LightType.CYLINDER).astype(np.int8),
        position=xf[:, :3, 3].copy(), axis=-xf[:, :3, 2], xform=xf, radiance=np.ones((n, 3), np.float32),
        intensity=rng.uniform(1, 5, (n, 3)).astype(np.float32), radius=np.full(n, 0.1), width=np.ones(n),
        height=np.zeros(n), angle=np.zeros(n), cone_angle=np.where(np.arange(n) % 3 == 0, 60.0, 180.0),
        cone_softness=np.full(n, 0.2), focus=np.where(np.arange(n) % 5 == 0, 1.5, 0.0),
        focus_tint=np.zeros((n, 3), np.float32), shadow=np.ones(n, bool), paths=[f"/c{i}" for i in range(n)],
        instance_ids=np.full(n, -1))
    pts, normals = o[:600], nrm[:600]
    albedo = np.full((600, 3), 0.5, np.float32)
    voxel = VoxelBackend(voxel_resolution=32, direction_step=10.0, cache=False, report=lambda line: None)
    voxel.update(snap)
    fused = shade_with(voxel, pts, normals, albedo, lights)
    pairs = shade_direct(pts, normals, albedo, lights, voxel.occluded)
    assert np.array_equal(fused.facing, pairs.facing)
    assert fused.shadow.max() > 0
    np.testing.assert_allclose(fused.radiance, pairs.radiance, rtol=1e-4, atol=1e-6)
    # the profile matters here: the same lights shaded as spheres differ by far more than float32
    as_spheres = Lights.concat([lights])
    as_spheres.type[:] = LightType.SPHERE
    off = shade_with(voxel, pts, normals, albedo, as_spheres).radiance
    assert np.abs(off - fused.radiance).sum() / fused.radiance.sum() > 0.1


def test_voxel_render_of_a_cylinder_light_against_exact(new_stage):
    """The same small stage (a tube light over a ground, a box casting a shadow) rendered with the
    voxel backend and with exact: the direct images agree within the voxel visibility error."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings

    def light(stage):
        c = _cylinder(stage, radius=0.1, length=6.0, intensity=300.0)
        c.AddTranslateOp().Set((0.0, 4.5, 0.0))
        c.AddRotateYOp().Set(20.0)
        box = add_cube_mesh(stage, "/World/box", size=3)
        box.AddTranslateOp().Set((1.0, 1.5, 2.0))

    path = ground_stage(new_stage, light)
    images = {}
    for backend in ("exact", "voxel"):
        d = StageDelegate(path)
        r = FrameRenderer(d, UsdmlSettings(visibility=backend, voxel_resolution=64, direction_step=5.0,
                                           pixel_samples=1))
        try:
            images[backend] = r.render(d.start_time, 48, 48, {"direct", "shadow"}).buffers
        finally:
            r.close()
    exact, voxel = images["exact"], images["voxel"]
    shadowed = exact["shadow"] > 0.5
    assert 0.05 < shadowed.mean() < 0.5            # the box's shadow is in view
    e, v = exact["direct"][..., 0].astype(np.float64), voxel["direct"][..., 0].astype(np.float64)
    err = np.abs(v - e).sum() / e.sum()
    assert err < 0.03, err
    assert np.abs(voxel["shadow"] - exact["shadow"]).mean() < 0.03


# ---------------------------------------------------------------------------------------------- VPLs

def _cylinder_light(**kw) -> Lights:
    from vpl_scenes import light
    return light(LightType.CYLINDER, **kw)     # identity frame: the tube along +X


def _face_fraction(half: float, n: int = 400) -> float:
    """Fraction of a sin θ_x emitter's power at the centre of a cube (half-size ``half``) that lands on
    its two ±X faces: midpoint rule over a face, ∫ sin θ · cos / d² dA over Φ/I = π²."""
    g = ((np.arange(n) + 0.5) / n * 2 - 1) * half
    y, z = np.meshgrid(g, g)
    d2 = half * half + y * y + z * z
    per_face = (np.sqrt(y * y + z * z) / np.sqrt(d2) * half / np.sqrt(d2) / d2).sum() * (2 * half / n) ** 2
    return 2 * per_face / math.pi ** 2


def test_cylinder_light_power_is_pi_L_area(new_stage):
    from usdml.lighting.vpl import light_power

    stage = new_stage()
    c = _cylinder(stage, radius=0.25, length=2.0, intensity=3.0)
    c.AddScaleOp().Set((1.5, 2, 2))               # world radius 0.5, length 3
    add_cube_mesh(stage, "/ground")
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    phi = light_power(snap, snap.lights)[0]
    np.testing.assert_allclose(phi, math.pi * 3.0 * (2 * math.pi * 0.5 * 3.0), rtol=1e-6)


def test_cylinder_vpls_follow_the_side_profile_in_a_closed_box():
    """Closed cube around the tube: every bounce carries ρ^b·Φ, and the first bounce's share on the
    faces the tube points at is the profile's (0.220), not an isotropic light's (1/3)."""
    from vpl_scenes import backend_for, box, snapshot
    from usdml.lighting.vpl import generate_vpls, light_power

    rho = np.array([0.9, 0.6, 0.3])
    snap = snapshot([box((-1, -1, -1), (1, 1, 1), rho)])
    intensity = np.array([1.0, 2.0, 4.0])
    lights = _cylinder_light(intensity=intensity)
    phi = math.pi ** 2 * intensity
    np.testing.assert_allclose(light_power(snap, lights)[0], phi, rtol=1e-6)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=2, paths=40_000, seed=4)
    assert len(v) == 2 * 40_000
    for b in (1, 2):
        np.testing.assert_allclose(v.total_flux(b), phi * rho ** b, rtol=1e-4)
    first = v.bounce == 1
    on_x = first & (np.abs(v.position[:, 0]) > 1 - 1e-4)
    share = v.flux[on_x, 0].sum() / v.flux[first, 0].sum()
    expected = _face_fraction(1.0)
    assert 0.21 < expected < 0.23
    assert share == pytest.approx(expected, abs=0.006)      # ~3.5 standard errors of 40k paths
    # azimuth about the tube: the ±Y and ±Z faces share the rest equally
    on_y = first & (np.abs(v.position[:, 1]) > 1 - 1e-4)
    assert v.flux[on_y, 0].sum() / v.flux[first, 0].sum() == pytest.approx((1 - expected) / 2, abs=0.01)


def test_shaped_cylinder_light_power_and_vpl_flux():
    """A cone about the light's -Z on a tube: power by the 2-D midpoint rule against a fine spherical
    quadrature, and VPL flux (profile-sampled paths weighted by the cone) against that power."""
    from vpl_scenes import backend_for, box, snapshot
    from usdml.lighting.vpl import generate_vpls, light_power

    snap = snapshot([box((-1, -1, -1), (1, 1, 1), (1.0, 1.0, 1.0))])
    one = np.ones(3)
    # a 90° cone keeps the half of the tube's emission on its -Z side
    half = light_power(snap, _cylinder_light(intensity=one, axis=(0.0, 0.0, -1.0), cone=90.0))[0]
    np.testing.assert_allclose(half, math.pi ** 2 / 2, rtol=1e-3)
    # a 40° cone: ∫ over the cap about -Z of sin θ_x dω, on a fine (θ, φ) grid
    m = 2000
    t = (np.arange(m) + 0.5) / m * math.radians(40)
    p = (np.arange(m) + 0.5) / m * 2 * math.pi
    tt, pp = np.meshgrid(t, p)
    x = np.sin(tt) * np.cos(pp)                     # the tube axis component of the direction
    cap = (np.sqrt(1 - x * x) * np.sin(tt)).sum() * (math.radians(40) / m) * (2 * math.pi / m)
    lights = _cylinder_light(intensity=one, axis=(0.0, 0.0, -1.0), cone=40.0)
    got = light_power(snap, lights)[0]
    np.testing.assert_allclose(got, cap, rtol=0.004)             # measured 0.0015
    v = generate_vpls(snap, backend_for(snap), lights, bounces=1, paths=40_000, seed=5)
    np.testing.assert_allclose(v.total_flux(1), got, rtol=0.02)
    # everything lands on the -Z face, inside the cone's footprint
    assert np.allclose(v.position[:, 2], -1.0, atol=1e-4)
    assert (np.hypot(v.position[:, 0], v.position[:, 1]) <= math.tan(math.radians(40)) + 1e-3).all()
