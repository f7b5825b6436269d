"""Motion blur over the camera's shutter (usdml.render.shutter): every way a stage moves, against the coverage a
moving box has by its own kinematics, computed here from the sweep and sharing no usdml code.

The stages are metres, 24 timecodes per second, frames 1–3; a quad 1 m wide, 10 m in front of a camera at the
origin looking down -Z, whose centre moves 8 m per frame along X (so over a 180° shutter, -0.25 to 0.25 around
frame 2, it sweeps from -2 to 2 m). A pixel column's coverage is the fraction of the shutter the quad covers it,
averaged over the pixel.
"""

import re
import subprocess
import sys

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux, UsdRender, UsdSkel, Vt

from usdml.render.frame import FrameRenderer
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate

DEPTH, APERTURE, FOCAL, SPEED = 10.0, 20.0, 25.0, 8.0
WIDTH = 96
QUAD = [(-0.5, -0.5, -DEPTH), (0.5, -0.5, -DEPTH), (0.5, 0.5, -DEPTH), (-0.5, 0.5, -DEPTH)]


def new(path, shutter=(-0.25, 0.25), camera_speed=0.0):
    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(s, 1.0)
    s.SetTimeCodesPerSecond(24)
    s.SetStartTimeCode(1)
    s.SetEndTimeCode(3)
    cam = UsdGeom.Camera.Define(s, "/cam")
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(APERTURE)
    cam.CreateVerticalApertureAttr(APERTURE / 2)
    cam.CreateShutterOpenAttr(shutter[0])
    cam.CreateShutterCloseAttr(shutter[1])
    if camera_speed:
        op = cam.AddTranslateOp()
        for t in (1, 2, 3):
            op.Set(Gf.Vec3d(camera_speed * (t - 2), 0, 0), t)
    UsdLux.DistantLight.Define(s, "/sun")
    return s


def quad(s, path, points=QUAD):
    m = UsdGeom.Mesh.Define(s, path)
    m.CreatePointsAttr(points)
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return m


def moving_box(s):
    """The quad under an Xform ``/box`` translated SPEED m per frame along X (module doc)."""
    quad(s, "/box/quad")
    op = UsdGeom.Xform.Define(s, "/box").AddTranslateOp()
    for t in (1, 2, 3):
        op.Set(Gf.Vec3d(SPEED * (t - 2), 0, 0), t)


def ground_from_above(path, shutter):
    """A Y-up stage: a 40 m ground (both sides) and :func:`new`'s camera 10 m above it looking straight down, so
    image X is world X."""
    s = new(path, shutter)
    UsdGeom.SetStageUpAxis(s, "Y")
    s.RemovePrim("/sun")
    cam = UsdGeom.Camera(s.GetPrimAtPath("/cam"))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 10, 0))
    cam.AddRotateXOp().Set(-90.0)
    quad(s, "/ground", [(-20, 0, 20), (20, 0, 20), (20, 0, -20), (-20, 0, -20)]).CreateDoubleSidedAttr(True)
    return s


def swept(sweep=(-2.0, 2.0), width=WIDTH):
    """Each pixel column's coverage: the fraction of 512 shutter times at which the quad covers each of 64 points
    across the pixel (the view at depth DEPTH spans ±DEPTH·APERTURE/2/FOCAL)."""
    half = DEPTH * APERTURE / 2 / FOCAL
    centre = sweep[0] + (sweep[1] - sweep[0]) * (np.arange(512) + 0.5) / 512
    across = (np.arange(64) + 0.5) / 64
    return np.array([np.mean(np.abs(-half + (x + across[:, None]) / width * 2 * half - centre[None]) < 0.5)
                     for x in range(width)])


def render(path, samples=64, time=2.0, aovs=("color",), **settings):
    d = StageDelegate(str(path))
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=samples, **settings))
    try:
        return r.render(time, WIDTH, WIDTH // 2, set(aovs))
    finally:
        r.close()


def coverage_error(path, sweep=(-2.0, 2.0), **settings) -> float:
    """Mean |coverage − swept| over the pixels the sweep or the render touches (the issue's measure)."""
    alpha = render(path, **settings).buffers["color"][..., 3].astype(np.float64)
    want = np.broadcast_to(swept(sweep), alpha.shape)
    rows = np.abs(np.arange(alpha.shape[0]) - alpha.shape[0] / 2 + 0.5) < alpha.shape[0] * 0.1   # inside the quad
    touched = (want > 0) | (alpha > 0)
    return float(np.abs(alpha - want)[touched & rows[:, None]].mean())


def test_transform_blur_covers_each_pixel_for_its_share_of_the_shutter(tmp_path):
    s = new(tmp_path / "xform.usda")
    moving_box(s)
    s.Save()
    assert coverage_error(tmp_path / "xform.usda") <= 0.03
    sharp = render(tmp_path / "xform.usda", motion_blur=False).buffers["color"][..., 3]
    assert coverage_error(tmp_path / "xform.usda", motion_blur=False) > 0.2      # what the issue found: sharp
    assert set(np.unique(sharp)) == {0.0, 1.0}


def test_a_shutter_after_the_frame_blurs_forward(tmp_path):
    s = new(tmp_path / "open.usda", shutter=(0.0, 0.5))
    moving_box(s)
    s.Save()
    assert coverage_error(tmp_path / "open.usda", sweep=(0.0, 4.0)) <= 0.03


def test_deformation_blur_from_points_time_samples(tmp_path):
    s = new(tmp_path / "points.usda")
    m = quad(s, "/quad")
    for t in (1, 2, 3):
        m.GetPointsAttr().Set([(x + SPEED * (t - 2), y, z) for x, y, z in QUAD], t)
    s.Save()
    assert coverage_error(tmp_path / "points.usda") <= 0.03


def test_deformation_blur_from_velocities_of_one_sample(tmp_path):
    """USD moves points by their velocities (units per second) from the sample at or before the time."""
    s = new(tmp_path / "vel.usda")
    m = quad(s, "/quad")
    m.GetPointsAttr().Set([(x - 2.0, y, z) for x, y, z in QUAD], 1.75)
    m.CreateVelocitiesAttr().Set([(SPEED * 24, 0, 0)] * 4, 1.75)
    s.Save()
    assert coverage_error(tmp_path / "vel.usda") <= 0.03


def test_point_instancer_blur_from_positions_and_velocities(tmp_path):
    s = new(tmp_path / "pi.usda")
    pi = UsdGeom.PointInstancer.Define(s, "/pi")
    quad(s, "/pi/protos/quad", [(x, y, 0.0) for x, y, _ in QUAD])
    pi.CreatePrototypesRel().SetTargets(["/pi/protos/quad"])
    pi.CreateProtoIndicesAttr([0])
    pi.CreatePositionsAttr().Set([(-2.0, 0, -DEPTH)], 1.75)
    pi.CreateVelocitiesAttr().Set([(SPEED * 24, 0, 0)], 1.75)
    s.Save()
    assert coverage_error(tmp_path / "pi.usda") <= 0.03


def test_skinned_blur(tmp_path):
    """A quad skinned to one joint whose translation moves it: UsdSkel posed at each pass's time."""
    s = new(tmp_path / "skel.usda")
    UsdSkel.Root.Define(s, "/rig")
    skel = UsdSkel.Skeleton.Define(s, "/rig/skel")
    skel.CreateJointsAttr(["root"])
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    anim = UsdSkel.Animation.Define(s, "/rig/skel/anim")
    anim.CreateJointsAttr(["root"])
    anim.CreateRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1)]))
    anim.CreateScalesAttr().Set(Vt.Vec3hArray([(1, 1, 1)]))
    for t in (1, 2, 3):
        anim.CreateTranslationsAttr().Set(Vt.Vec3fArray([(SPEED * (t - 2), 0, 0)]), t)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    m = quad(s, "/rig/quad")
    binding = UsdSkel.BindingAPI.Apply(m.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set([0])
    binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    s.Save()
    assert coverage_error(tmp_path / "skel.usda") <= 0.03


def test_camera_motion_blurs_a_still_quad(tmp_path):
    """The camera moving -8 m per frame sees the still quad sweep as the moving quad does."""
    s = new(tmp_path / "cam.usda", camera_speed=-SPEED)
    quad(s, "/quad")
    s.Save()
    assert coverage_error(tmp_path / "cam.usda") <= 0.03


def test_shadows_are_traced_at_each_pass_time(tmp_path):
    """A plate 2 m above the ground moving 2 m per frame under a light 45° from vertical: the ground beside its
    path (the plate's own pixels excluded) is shadowed the fraction of the shutter the plate's shadow covers it."""
    s = ground_from_above(tmp_path / "shadow.usda", (-0.25, 0.25))
    plate = quad(s, "/plate/quad", [(-0.5, 2, 0.5), (0.5, 2, 0.5), (0.5, 2, -0.5), (-0.5, 2, -0.5)])
    plate.CreateDoubleSidedAttr(True)
    op = UsdGeom.Xform.Define(s, "/plate").AddTranslateOp()
    for t in (1, 2, 3):
        op.Set(Gf.Vec3d(2.0 * (t - 2), 0, 0), t)
    sun = UsdLux.DistantLight.Define(s, "/sun")
    sun.AddRotateZOp().Set(45.0)                  # its -Z turned down, then toward +X: shadows 2 m to +X
    sun.AddRotateXOp().Set(-90.0)
    s.Save()
    shadow = render(tmp_path / "shadow.usda", aovs=("shadow", "color")).buffers["shadow"].astype(np.float64)
    half = 10 * APERTURE / 2 / FOCAL               # the ground 10 m below spans ±half across the image
    across = (np.arange(64) + 0.5) / 64
    centre = 2.0 + -0.5 + (np.arange(512) + 0.5) / 512          # the shadow's centre over the shutter: 1.5 .. 2.5
    want = np.array([np.mean(np.abs(-half + (x + across[:, None]) / WIDTH * 2 * half - centre[None]) < 0.5)
                     for x in range(WIDTH)])
    row = shadow[shadow.shape[0] // 2]
    beside = (np.abs(-half + (np.arange(WIDTH) + 0.5) / WIDTH * 2 * half) > 1.6)     # off the plate's own sweep
    assert want[beside].max() > 0.9
    assert np.abs(row[beside] - want[beside]).mean() <= 0.03


def test_a_moving_light_is_averaged_over_the_shutter(tmp_path):
    """A point light 1 m above the ground moving 2 m per frame: the ground's direct light is its irradiance
    I·cos/d² averaged over the shutter (by quadrature here), relative to the unblurred frame's."""
    s = ground_from_above(tmp_path / "light.usda", (-0.5, 0.5))
    light = UsdLux.SphereLight.Define(s, "/lamp")
    light.CreateTreatAsPointAttr(True)
    op = light.AddTranslateOp()
    for t in (1, 2, 3):
        op.Set(Gf.Vec3d(2.0 * (t - 2), 1.0, 0), t)
    s.Save()
    blurred = render(tmp_path / "light.usda", 16, aovs=("direct",)).buffers["direct"][..., 0].astype(np.float64)
    still = render(tmp_path / "light.usda", 16, aovs=("direct",), motion_blur=False).buffers["direct"][..., 0]
    half = 10 * APERTURE / 2 / FOCAL
    x = -half + (np.arange(WIDTH) + 0.5) / WIDTH * 2 * half
    lamp = -1.0 + 2.0 * (np.arange(4096) + 0.5) / 4096                  # the lamp's X over the shutter

    def irradiance(dx):
        return 1.0 / (dx ** 2 + 1.0) ** 1.5                             # cos/d² at 1 m height
    want = irradiance(x[:, None] - lamp[None]).mean(1) / irradiance(x)
    row = blurred[blurred.shape[0] // 2] / still[still.shape[0] // 2]
    near = np.abs(x) < 3.0
    assert np.abs(row[near] / want[near] - 1).max() < 0.03, row


def test_render_settings_disable_motion_blur_and_determinism(tmp_path):
    s = new(tmp_path / "rs.usda")
    moving_box(s)
    rs = UsdRender.Settings.Define(s, "/Render/settings")
    s.SetMetadata("renderSettingsPrimPath", "/Render/settings")
    s.Save()
    a, b = (render(tmp_path / "rs.usda", 16).buffers["color"] for _ in range(2))
    np.testing.assert_array_equal(a, b)                 # same stage, settings and seed: the same pixels
    assert len(render(tmp_path / "rs.usda", 16).stats.shutter_times) == 16
    rs.CreateDisableMotionBlurAttr(True)
    s.Save()
    result = render(tmp_path / "rs.usda", 16)
    assert result.stats.shutter_times is None
    assert set(np.unique(result.buffers["color"][..., 3])) == {0.0, 1.0}


def test_a_shutter_closing_before_it_opens_is_one_line(tmp_path):
    s = new(tmp_path / "bad.usda", shutter=(0.25, -0.25))
    quad(s, "/quad")
    s.Save()
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(tmp_path / "bad.usda"),
                          str(tmp_path / "out.exr"), "--imageWidth", "16"], capture_output=True, text=True)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    (line,) = [line for line in run.stderr.splitlines() if line.startswith("usdml: error:")]
    assert re.search(r"/cam: shutter:close \(-0\.25\) is before shutter:open \(0\.25\)", line), line


def test_the_exr_says_what_was_blurred(tmp_path):
    import OpenImageIO as oiio

    s = new(tmp_path / "cli.usda")
    moving_box(s)
    cam = UsdGeom.Camera(s.GetPrimAtPath("/cam"))
    cam.CreateFStopAttr(2.0)
    cam.CreateFocusDistanceAttr(10.0)
    s.Save()
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(tmp_path / "cli.usda"),
                          str(tmp_path / "out.####.exr"),
                          "--frames", "2", "--imageWidth", "32", "--pixel-samples", "4"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    spec = oiio.ImageInput.open(str(tmp_path / "out.0002.exr")).spec()
    assert spec.getattribute("usdml:shutter:open") == -0.25 and spec.getattribute("usdml:shutter:close") == 0.25
    assert spec.getattribute("usdml:shutter:slices") == 4
    assert spec.getattribute("usdml:lens:fStop") == 2.0
    assert abs(spec.getattribute("usdml:lens:radius") - FOCAL * 0.1 / 2.0 / 2) < 1e-6
    info = subprocess.run([sys.executable, "-m", "usdml.cli", "info", str(tmp_path / "cli.usda")],
                          capture_output=True, text=True)
    assert "shutter -0.25..0.25; f/2 focused at 10" in info.stdout, info.stdout
