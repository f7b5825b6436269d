"""Camera selection as usdrecord does it, camera parameters, RenderSettings and usdml's schema."""

import math
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender

from conftest import add_cube_mesh, add_quad
from usdml.errors import UsdmlError
from usdml.stage import StageDelegate


def _stage_with_cameras(new_stage, names):
    stage = new_stage()
    add_cube_mesh(stage, "/World/box")
    for n in names:
        cam = UsdGeom.Camera.Define(stage, f"/World/cams/{n}")
        cam.AddTranslateOp().Set((0, 0, 10))
    stage.Save()
    return stage.GetRootLayer().realPath


def test_camera_selection_rules(new_stage):
    path = _stage_with_cameras(new_stage, ["a", "main_cam", "b"])
    assert StageDelegate(path).snapshot(0).camera.path == "/World/cams/main_cam"
    assert StageDelegate(path, camera="b").snapshot(0).camera.path == "/World/cams/b"
    assert StageDelegate(path, camera="/World/cams/a").snapshot(0).camera.path == "/World/cams/a"
    with pytest.raises(UsdmlError, match="no camera named 'zz'.*cameras: /World/cams/a"):
        StageDelegate(path, camera="zz").snapshot(0)
    with pytest.raises(UsdmlError, match="camera '/World/box' not found"):
        StageDelegate(path, camera="/World/box").snapshot(0)


def test_first_camera_then_framing_camera(new_stage, tmp_path):
    path = _stage_with_cameras(new_stage, ["x", "y"])
    assert StageDelegate(path).snapshot(0).camera.path == "/World/cams/x"
    stage = Usd.Stage.CreateNew(str(tmp_path / "nocam.usda"))
    box = add_cube_mesh(stage, "/box", size=4)
    box.AddTranslateOp().Set((100, 0, 0))
    stage.Save()
    cam = StageDelegate(str(tmp_path / "nocam.usda")).snapshot(0).camera
    assert cam.path == ""
    # every corner of the box projects inside the image and in front of the camera
    corners = np.array([[100 + x, y, z, 1] for x in (-2, 2) for y in (-2, 2) for z in (-2, 2)])
    clip = (cam.projection_matrix() @ np.linalg.inv(cam.xform) @ corners.T).T
    ndc = clip[:, :3] / clip[:, 3:]
    assert (clip[:, 3] > 0).all() and (np.abs(ndc) <= 1).all()


#: usdrecord's framing of a cube (UsdAppUtils' FrameRecorder): its face toward the camera, whose half diagonal
#: fills half the width (1/√2 of it), and that times the film back's aspect 20.955 / 15.2908 of the height
CUBE_WIDTH = 1 / math.sqrt(2)
CUBE_HEIGHT = CUBE_WIDTH * 20.955 / 15.2908


@pytest.mark.parametrize("up", ["Y", "Z"])
def test_framing_camera_centres_a_cube_and_fills_the_frame(tmp_path, up):
    """A unit cube at (3, -2, 7) with no camera: its projected bounds are centred and fill CUBE_WIDTH of the
    image's width and CUBE_HEIGHT of its height, by the camera's projection and in the rendered pixels."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings

    stage = Usd.Stage.CreateNew(str(tmp_path / "cube.usda"))
    UsdGeom.SetStageUpAxis(stage, up)
    add_cube_mesh(stage, "/cube").AddTranslateOp().Set((3, -2, 7))
    stage.Save()
    d = StageDelegate(str(tmp_path / "cube.usda"))
    cam = d.snapshot(0).camera
    assert cam.path == "" and cam.focal_length == 50
    world_up = [0, 0, 1] if up == "Z" else [0, 1, 0]
    assert np.allclose(cam.xform[:3, 1], world_up)      # the stage's up is up in the image
    corners = np.array([[3 + x, -2 + y, 7 + z, 1] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    clip = (cam.projection_matrix() @ np.linalg.inv(cam.xform) @ corners.T).T
    ndc = clip[:, :2] / clip[:, 3:]
    np.testing.assert_allclose(ndc.min(axis=0), [-CUBE_WIDTH, -CUBE_HEIGHT], rtol=1e-9)
    np.testing.assert_allclose(ndc.max(axis=0), [CUBE_WIDTH, CUBE_HEIGHT], rtol=1e-9)

    width, height = cam.resolution(48)
    assert (width, height) == (48, 35)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1))
    try:
        depth = r.render(0, width, height, {"depth"}).buffers["depth"]
    finally:
        r.close()
    rows, cols = np.nonzero(np.isfinite(depth.reshape(height, width)))
    assert abs((cols.min() + cols.max() + 1) / 2 - width / 2) <= 1
    assert abs((rows.min() + rows.max() + 1) / 2 - height / 2) <= 1
    assert abs((cols.max() - cols.min() + 1) / width - CUBE_WIDTH) <= 1.5 / width
    assert abs((rows.max() - rows.min() + 1) / height - CUBE_HEIGHT) <= 1.5 / height


def test_no_camera_warns_once_and_quiet_hides_it(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "nocam.usda"))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(3)
    add_cube_mesh(stage, "/box")
    stage.Save()
    argv = [sys.executable, "-m", "usdml.cli", "render", str(tmp_path / "nocam.usda"), str(tmp_path / "o.####.exr"),
            "--frames", "1:3", "--imageWidth", "16", "--pixel-samples", "1"]
    loud = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert loud.returncode == 0, loud.stderr
    lines = [line for line in loud.stderr.splitlines() if "no camera" in line]
    assert lines == [f"usdml: warning: {tmp_path / 'nocam.usda'}: no camera; framing the scene with usdml's own camera "
                     "(usdrecord's: a 50 mm lens looking -Z at the centre of its bounds); add a UsdGeom.Camera "
                     "(named main_cam, or chosen with --camera)"]
    quiet = subprocess.run(argv + ["-q"], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0 and "no camera" not in quiet.stderr


def test_camera_parameters(new_stage):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    cam = UsdGeom.Camera.Define(stage, "/cam")
    cam.CreateFocalLengthAttr(50)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(24)
    cam.CreateHorizontalApertureOffsetAttr(2)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.5, 200))
    cam.AddTranslateOp().Set((1, 2, 3))
    stage.Save()
    c = StageDelegate(stage.GetRootLayer().realPath).snapshot(0).camera
    assert (c.focal_length, c.horizontal_aperture, c.vertical_aperture) == (50, 36, 24)
    assert c.horizontal_aperture_offset == 2 and c.clipping_range == pytest.approx((0.5, 200))
    assert np.allclose(c.xform[:3, 3], [1, 2, 3])
    assert c.resolution(600) == (600, 400)
    # the projection agrees with Gf.Frustum's
    gf = UsdGeom.Camera(stage.GetPrimAtPath("/cam")).GetCamera(0).frustum.ComputeProjectionMatrix()
    assert np.allclose(c.projection_matrix(), np.array(gf).T, atol=1e-6)


def _render_settings_stage(new_stage):
    stage = new_stage(start=1, end=3)
    add_cube_mesh(stage, "/World/box")
    UsdGeom.Camera.Define(stage, "/World/main_cam")
    UsdGeom.Camera.Define(stage, "/World/shot_cam")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets(["/World/shot_cam"])
    settings.CreateResolutionAttr(Gf.Vec2i(320, 180))
    product = UsdRender.Product.Define(stage, "/Render/Product")
    name = product.CreateProductNameAttr()
    for t in (1, 2, 3):
        name.Set(f"beauty.{t:04d}.exr", t)
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    for var_name, source, dtype in [("color", "color", "color4f"), ("depth", "depth", "float"),
                                    ("N", "normal", "normal3f")]:
        v = UsdRender.Var.Define(stage, f"/Render/Vars/{var_name}")
        v.CreateSourceNameAttr(source)
        v.CreateDataTypeAttr(dtype)
        product.CreateOrderedVarsRel().AddTarget(v.GetPath())
    prim = settings.GetPrim()
    prim.ApplyAPI("UsdmlRenderSettingsAPI")
    prim.GetAttribute("usdml:voxel:resolution").Set(64)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    return stage.GetRootLayer().realPath


def test_render_settings_products_vars_and_camera(new_stage):
    path = _render_settings_stage(new_stage)
    d = StageDelegate(path)
    snap = d.snapshot(2)
    rs = snap.render_settings
    assert rs.path == "/Render/Settings" and rs.resolution == (320, 180) and rs.camera == "/World/shot_cam"
    (product,) = rs.products
    assert product.product_name == "beauty.0002.exr" and product.name_time_varying
    assert [(v.name, v.source_name, v.data_type) for v in product.vars] == [
        ("color", "color", "color4f"), ("depth", "depth", "float"), ("N", "normal", "normal3f")]
    assert [v.source_type for v in product.vars] == ["raw"] * 3
    # the delegate hands out the same plain data at any timecode, without a snapshot
    assert d.render_settings(3).products[0].product_name == "beauty.0003.exr"
    assert d.render_settings(2) == rs
    assert snap.camera.path == "/World/shot_cam"              # RenderSettings decide the camera
    assert StageDelegate(path, camera="main_cam").snapshot(2).camera.path == "/World/main_cam"
    # the schema's fallbacks plus the authored value
    s = d.usdml_settings
    assert s.voxel_resolution == 64 and s.direction_step == 2.0 and s.visibility == "exact"


def test_explicit_and_missing_render_settings_paths(new_stage):
    path = _render_settings_stage(new_stage)
    with pytest.raises(UsdmlError, match="no RenderSettings prim at /Render/Nope.*/Render/Settings"):
        StageDelegate(path, render_settings_path="/Render/Nope")
    with pytest.raises(UsdmlError, match="not an absolute prim path"):
        StageDelegate(path, render_settings_path="Render")
    assert StageDelegate(path, render_settings_path="/Render/Settings").settings_prim


def test_openusd_render_settings_stages(assets):
    stage = str(assets / "openusd/testUsdviewRenderSettingsEdits/test.usda")
    opened = Usd.Stage.Open(stage)
    found = [str(p.GetPath()) for p in opened.Traverse() if p.IsA(UsdRender.Settings)]
    d = StageDelegate(stage, render_settings_path=found[0])
    rs = d.snapshot(0).render_settings
    assert rs.path == found[0]
    assert sum(len(p.vars) for p in rs.products) == 2
    blur = str(assets / "openusd/MotionBlurTest/motionBlur.usda")
    opened = Usd.Stage.Open(blur)
    rs_paths = [str(p.GetPath()) for p in opened.Traverse() if p.IsA(UsdRender.Settings)]
    assert rs_paths
    for p in rs_paths:
        rs = StageDelegate(blur, render_settings_path=p).snapshot(1).render_settings
        assert rs.products and all(prod.vars for prod in rs.products)


def test_bad_usdml_attribute_value_is_a_clear_error(new_stage):
    path = _render_settings_stage(new_stage)
    stage = Usd.Stage.Open(path)
    stage.GetPrimAtPath("/Render/Settings").GetAttribute("usdml:visibility").Set("raytraced")
    stage.Save()
    with pytest.raises(UsdmlError, match="/Render/Settings.*unknown visibility backend 'raytraced'"):
        StageDelegate(path)


def test_no_render_settings_is_none(new_stage):
    stage = new_stage("plain.usda")
    add_quad(stage, "/ground")
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    assert d.render_settings(0) is None and d.snapshot(0).render_settings is None
