"""UsdLux radiometry: every unit rule of the README's "Light units" section."""

import math

import numpy as np
import pytest
from pxr import Sdf, UsdGeom, UsdLux

from conftest import add_cube_mesh
from usdml.errors import UsdmlError
from usdml.scene.light_table import LightFlag, LightTable
from usdml.scene import LightType
from usdml.stage import StageDelegate


def _lights(stage):
    add_cube_mesh(stage, "/ground")
    stage.Save()
    return StageDelegate(stage.GetRootLayer().realPath).snapshot(0).lights


def test_sphere_light_radiance_intensity_and_normalize(new_stage):
    stage = new_stage()
    a = UsdLux.SphereLight.Define(stage, "/a")
    a.CreateIntensityAttr(10)
    a.CreateExposureAttr(2)
    a.CreateColorAttr((1, 0.5, 0.25))
    a.CreateRadiusAttr(0.5)
    b = UsdLux.SphereLight.Define(stage, "/b")
    b.CreateIntensityAttr(10)
    b.CreateRadiusAttr(0.5)
    b.CreateNormalizeAttr(True)
    b.AddScaleOp().Set((2, 2, 2))          # world radius 1
    lights = _lights(stage)
    assert lights.type.tolist() == [LightType.SPHERE, LightType.SPHERE]
    L = 10 * 4 * np.array([1, 0.5, 0.25])
    assert np.allclose(lights.radiance[0], L)
    assert np.allclose(lights.intensity[0], L * math.pi * 0.25)
    assert lights.radius[1] == pytest.approx(1.0)
    assert np.allclose(lights.radiance[1], 10 / (4 * math.pi))
    assert np.allclose(lights.intensity[1], 10 / 4)           # normalize: I = intensity / 4


def test_point_lights_treat_as_point_and_zero_radius(new_stage, warnings_log):
    stage = new_stage()
    a = UsdLux.SphereLight.Define(stage, "/treat")
    a.CreateTreatAsPointAttr(True)
    a.CreateRadiusAttr(0.2)
    a.CreateIntensityAttr(50)
    b = UsdLux.SphereLight.Define(stage, "/zero_norm")
    b.CreateRadiusAttr(0)
    b.CreateIntensityAttr(8)
    b.CreateNormalizeAttr(True)
    c = UsdLux.SphereLight.Define(stage, "/zero_plain")
    c.CreateRadiusAttr(0)
    lights = _lights(stage)
    assert (lights.type == LightType.POINT).all()
    assert np.allclose(lights.intensity[0], 50 * math.pi * 0.04, rtol=1e-6)
    assert np.allclose(lights.intensity[1], 2.0)
    assert np.allclose(lights.intensity[2], 0.0)
    assert "/zero_plain" in warnings_log.text and "emits nothing" in warnings_log.text


def test_disk_rect_and_scale_dependent_area(new_stage):
    stage = new_stage()
    d = UsdLux.DiskLight.Define(stage, "/disk")
    d.CreateRadiusAttr(0.5)
    d.CreateIntensityAttr(3)
    d.CreateNormalizeAttr(True)
    d.AddScaleOp().Set((2, 3, 7))      # area scales with x*y only
    r = UsdLux.RectLight.Define(stage, "/rect")
    r.CreateWidthAttr(2)
    r.CreateHeightAttr(0.5)
    r.CreateIntensityAttr(4)
    r.AddRotateXOp().Set(-90)          # turns its -Z emission axis to -Y (pointing down)
    lights = _lights(stage)
    disk_area = math.pi * 0.25 * 6
    assert np.allclose(lights.radiance[0], 3 / disk_area)
    assert np.allclose(lights.intensity[0], 3)                # normalized: L * area = intensity
    assert lights.width[1] == 2 and lights.height[1] == 0.5
    assert np.allclose(lights.intensity[1], 4 * 1.0)
    assert np.allclose(lights.axis[0], [0, 0, -1])
    assert np.allclose(lights.axis[1], [0, -1, 0], atol=1e-9)  # -Z rotated by -90 about X


def test_distant_light_illuminance(new_stage):
    stage = new_stage()
    a = UsdLux.DistantLight.Define(stage, "/sun")            # fallback intensity 50000, angle 0.53
    b = UsdLux.DistantLight.Define(stage, "/sun_norm")
    b.CreateNormalizeAttr(True)
    b.CreateIntensityAttr(1000)
    b.CreateExposureAttr(-1)
    lights = _lights(stage)
    half = math.radians(0.53) / 2
    assert np.allclose(lights.intensity[0], 50000 * math.pi * math.sin(half) ** 2, rtol=1e-5)
    assert np.allclose(lights.intensity[1], 500)
    assert (lights.type == LightType.DISTANT).all()


def test_color_temperature_and_diffuse(new_stage):
    stage = new_stage()
    a = UsdLux.SphereLight.Define(stage, "/warm")
    a.CreateEnableColorTemperatureAttr(True)
    a.CreateColorTemperatureAttr(3000)
    a.CreateColorAttr((1, 1, 0.5))
    b = UsdLux.SphereLight.Define(stage, "/half_diffuse")
    b.CreateDiffuseAttr(0.5)
    lights = _lights(stage)
    rgb = np.array(UsdLux.BlackbodyTemperatureAsRgb(3000))
    assert rgb[0] > rgb[2]                                    # warm
    assert np.allclose(lights.radiance[0], rgb * [1, 1, 0.5], rtol=1e-6)
    assert np.allclose(lights.radiance[1], 0.5)


def test_shaping_api(new_stage):
    stage = new_stage()
    spot = UsdLux.SphereLight.Define(stage, "/spot")
    shaping = UsdLux.ShapingAPI.Apply(spot.GetPrim())
    shaping.CreateShapingConeAngleAttr(30)
    shaping.CreateShapingConeSoftnessAttr(0.25)
    shaping.CreateShapingFocusAttr(2)
    shaping.CreateShapingFocusTintAttr((0.1, 0.2, 0.3))
    UsdLux.SphereLight.Define(stage, "/plain")
    default_cone = UsdLux.SphereLight.Define(stage, "/default_cone")
    UsdLux.ShapingAPI.Apply(default_cone.GetPrim())
    lights = _lights(stage)
    assert lights.cone_angle.tolist() == [30, 180, 90]
    assert lights.cone_softness[0] == 0.25 and lights.focus[0] == 2
    assert np.allclose(lights.focus_tint[0], [0.1, 0.2, 0.3])


def test_animated_light(new_stage):
    stage = new_stage(start=1, end=3)
    light = UsdLux.SphereLight.Define(stage, "/moving")
    op = light.AddTranslateOp()
    op.Set((0, 0, 0), 1)
    op.Set((0, 4, 0), 3)
    light.CreateIntensityAttr().Set(1, 1)
    light.GetIntensityAttr().Set(3, 3)
    add_cube_mesh(stage, "/ground")
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(2)
    assert np.allclose(snap.lights.position[0], [0, 2, 0])
    assert np.allclose(snap.lights.radiance[0], 2)


@pytest.mark.parametrize("attr,value,message", [
    ("inputs:intensity", float("nan"), "not finite"),
    ("inputs:intensity", float("-inf"), "not finite"),
    ("inputs:exposure", float("inf"), "not finite"),
    ("inputs:shaping:cone:angle", -30.0, "negative value -30; use 0 to 180 degrees"),
    ("inputs:shaping:cone:softness", -0.5, "negative value"),
    ("inputs:shaping:focus", -2.0, "negative value"),
])
def test_bad_light_values_are_errors_naming_the_attribute(new_stage, attr, value, message):
    stage = new_stage()
    light = UsdLux.SphereLight.Define(stage, "/World/bad")
    if "shaping" in attr:
        UsdLux.ShapingAPI.Apply(light.GetPrim())
    light.GetPrim().CreateAttribute(attr, Sdf.ValueTypeNames.Float).Set(value)
    with pytest.raises(UsdmlError, match=f"/World/bad.{attr}.*{message}"):
        _lights(stage)


def test_unsupported_light_types_warn(new_stage, warnings_log):
    stage = new_stage()
    UsdLux.PortalLight.Define(stage, "/portal")
    UsdLux.DomeLight.Define(stage, "/dome")            # supported: a dome, sampled per frame
    assert len(_lights(stage)) == 0
    assert "/portal: PortalLight is not supported" in warnings_log.text
    assert "DomeLight" not in warnings_log.text
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    assert [d.path for d in snap.domes] == ["/dome"]


def test_light_table_flags(new_stage):
    stage = new_stage()
    for schema, path in ((UsdLux.DiskLight, "/spot"), (UsdLux.DistantLight, "/sun"), (UsdLux.RectLight, "/rect"),
                         (UsdLux.CylinderLight, "/tube"), (UsdLux.SphereLight, "/bulb")):
        schema.Define(stage, path)
    UsdLux.ShapingAPI.Apply(stage.GetPrimAtPath("/spot")).CreateShapingConeAngleAttr(30)
    UsdLux.ShapingAPI(stage.GetPrimAtPath("/spot")).CreateShapingFocusAttr(2)
    UsdLux.ShadowAPI.Apply(stage.GetPrimAtPath("/sun")).CreateShadowEnableAttr(False)
    lights = _lights(stage)
    table = LightTable(lights)
    F = LightFlag
    assert table.flags.dtype == np.int32
    assert table.flags.tolist() == [F.ONE_SIDED | F.SHAPED | F.FOCUSED | F.CASTS_SHADOWS, F.DISTANT,
                                    F.ONE_SIDED | F.CASTS_SHADOWS, F.CYLINDER | F.CASTS_SHADOWS, F.CASTS_SHADOWS]
    # the Warp kernels test these numbers (usdml.kernels.voxel.query.light_term)
    assert [int(f) for f in F] == [1, 2, 4, 8, 16, 32]


def test_light_flags_are_the_bits_the_shading_kernel_reads():
    """One set of light flags: ``LightFlag`` composes them (``LightTable.flags``), the Warp kernel names the
    same bits as constants."""
    from usdml.kernels.voxel import shading as direct_shading

    for flag in LightFlag:
        assert int(getattr(direct_shading, flag.name)) == int(flag), flag.name
