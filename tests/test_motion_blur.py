"""Motion blur over the camera's shutter (usdml.render.shutter): every way a stage moves, against the coverage a
moving quad has by its own kinematics (``tools/final_frames_accuracy.py``: its stages and its ``swept``
reference, sharing no usdml code), and shadows and lights against their own geometry computed here.

The stages are metres, 24 timecodes per second, frames 1–3; a quad 1 m wide, 10 m in front of a camera at the
origin looking down -Z, whose centre moves 8 m per frame along X (so over a 180° shutter, -0.25 to 0.25 around
frame 2, it sweeps from -2 to 2 m). A pixel column's coverage is the fraction of the shutter the quad covers it,
averaged over the pixel.
"""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux, UsdRender, Vt

from usdml.render.frame import FrameRenderer
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
from final_frames_accuracy import APERTURE, FOCAL, KINDS, blur_stage, quad, swept  # noqa: E402

SPEED, WIDTH, SHUTTER = 8.0, 96, (-0.25, 0.25)


def ground_from_above(path, shutter):
    """A Y-up stage: a 40 m ground (both sides) and a camera 10 m above it looking straight down, so image X is
    world X (the tool's camera and lens, its quad and light removed)."""
    s = Usd.Stage.Open(blur_stage(path, "camera", 0.0, 1.0, shutter))
    UsdGeom.SetStageUpAxis(s, "Y")
    s.RemovePrim("/sun")
    s.RemovePrim("/quad")
    cam = UsdGeom.Camera(s.GetPrimAtPath("/cam"))
    where = cam.GetPrim().GetAttribute("xformOp:translate")
    where.Clear()                               # the tool's still camera has samples; this one stays put
    where.Set(Gf.Vec3d(0, 10, 0))
    cam.AddRotateXOp().Set(-90.0)
    quad(s, "/ground", [(-20, 0, 20), (20, 0, 20), (20, 0, -20), (-20, 0, -20)]).CreateDoubleSidedAttr(True)
    return s


def render(path, samples=64, time=2.0, aovs=("color",), **settings):
    d = StageDelegate(str(path))
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=samples, **settings))
    try:
        return r.render(time, WIDTH, WIDTH // 2, set(aovs))
    finally:
        r.close()


def coverage_error(path, shutter=SHUTTER, **settings) -> float:
    """Mean |coverage − swept| over the pixels the sweep or the render touches (the issue's measure)."""
    alpha = render(path, **settings).buffers["color"][..., 3].astype(np.float64)
    want = np.broadcast_to(swept(WIDTH, SPEED, 1.0, shutter), alpha.shape)
    rows = np.abs(np.arange(alpha.shape[0]) - alpha.shape[0] / 2 + 0.5) < alpha.shape[0] * 0.1   # inside the quad
    touched = (want > 0) | (alpha > 0)
    return float(np.abs(alpha - want)[touched & rows[:, None]].mean())


@pytest.mark.parametrize("kind", KINDS)
def test_each_way_of_moving_covers_each_pixel_for_its_share_of_the_shutter(tmp_path, kind):
    """Transform, points time samples, velocities of one sample, a PointInstancer's velocity, a skinned joint and
    the camera moving past a still quad: each blurs as the sweep's kinematics say."""
    path = blur_stage(tmp_path / f"{kind}.usda", kind, SPEED, 1.0, SHUTTER)
    assert coverage_error(path) <= 0.03


def test_without_motion_blur_the_frame_is_sharp(tmp_path):
    path = blur_stage(tmp_path / "xform.usda", "xform", SPEED, 1.0, SHUTTER)
    assert coverage_error(path, motion_blur=False) > 0.2      # what the issue found: sharp at the frame's time
    assert set(np.unique(render(path, motion_blur=False).buffers["color"][..., 3])) == {0.0, 1.0}


def test_a_shutter_after_the_frame_blurs_forward(tmp_path):
    path = blur_stage(tmp_path / "open.usda", "xform", SPEED, 1.0, (0.0, 0.5))
    assert coverage_error(path, (0.0, 0.5)) <= 0.03


def test_shadows_are_traced_at_each_pass_time(tmp_path):
    """A plate 2 m above the ground moving 2 m per frame under a light 45° from vertical: the ground beside its
    path (the plate's own pixels excluded) is shadowed the fraction of the shutter the plate's shadow covers it."""
    s = ground_from_above(tmp_path / "shadow.usda", SHUTTER)
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


@pytest.mark.parametrize("integrators", [{}, {"direct": "lgh"}, {"gi": "lgh", "vpl_count": 2000}],
                         ids=["all", "direct-lgh", "gi-lgh"])
def test_a_moving_light_is_averaged_over_the_shutter(tmp_path, integrators):
    """A point light 1 m above the ground moving 2 m per frame: the ground's direct light is its irradiance
    I·cos/d² averaged over the shutter (by quadrature here), relative to the unblurred frame's; through every
    direct integrator, and with VPLs prepared per slice."""
    s = ground_from_above(tmp_path / "light.usda", (-0.5, 0.5))
    light = UsdLux.SphereLight.Define(s, "/lamp")
    light.CreateTreatAsPointAttr(True)
    op = light.AddTranslateOp()
    for t in (1, 2, 3):
        op.Set(Gf.Vec3d(2.0 * (t - 2), 1.0, 0), t)
    s.Save()
    blurred = render(tmp_path / "light.usda", 16, aovs=("direct",), **integrators).buffers["direct"][..., 0]
    still = render(tmp_path / "light.usda", 16, aovs=("direct",), motion_blur=False, **integrators).buffers["direct"]
    blurred, still = blurred.astype(np.float64), still[..., 0]
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
    s = Usd.Stage.Open(blur_stage(tmp_path / "rs.usda", "xform", SPEED, 1.0, SHUTTER))
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
    blur_stage(tmp_path / "bad.usda", "xform", SPEED, 1.0, (0.25, -0.25))
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(tmp_path / "bad.usda"),
                          str(tmp_path / "out.exr"), "--imageWidth", "16"], capture_output=True, text=True)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    (line,) = [line for line in run.stderr.splitlines() if line.startswith("usdml: error:")]
    assert re.search(r"/cam: shutter:close \(-0\.25\) is before shutter:open \(0\.25\)", line), line


def test_the_exr_says_what_was_blurred(tmp_path):
    import OpenImageIO as oiio

    s = Usd.Stage.Open(blur_stage(tmp_path / "cli.usda", "xform", SPEED, 1.0, SHUTTER))
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


def _coverage(path, inside, samples=64) -> float:
    """Mean |alpha − the fraction of the shutter each pixel is ``inside(x, y, τ)``| (x, y: metres on the plane 10 m
    in front of the camera, τ: seconds from frame 2) over the pixels either touches; 4 × 4 points per pixel and
    256 times of the shutter -0.25..0.25."""
    alpha = render(path, samples).buffers["color"][..., 3].astype(np.float64)
    h, w = alpha.shape
    half = 10 * APERTURE / 2 / FOCAL
    sub = (np.arange(4) + 0.5) / 4
    xs = -half + (np.arange(w)[:, None] + sub[None]).ravel() / w * 2 * half
    ys = half * h / w - (np.arange(h)[:, None] + sub[None]).ravel() / h * 2 * half * h / w
    taus = (-0.25 + 0.5 * (np.arange(256) + 0.5) / 256) / 24
    x, y = np.meshgrid(xs, ys)
    frac = np.mean([inside(x, y, tau) for tau in taus], axis=0).reshape(h, 4, w, 4).mean(axis=(1, 3))
    touched = (frac > 0) | (alpha > 0)
    assert frac.max() > 0.5 and touched.mean() > 0.05
    return float(np.abs(alpha - frac)[touched].mean())


def _still_view(path):
    """blur_stage's camera and light, and nothing in view."""
    s = Usd.Stage.Open(blur_stage(path, "camera", 0.0, 1.0, SHUTTER))
    s.RemovePrim("/quad")
    return s


def test_point_instancer_angular_velocity_turns_instances_over_the_shutter(tmp_path):
    """USD's angularVelocities (degrees per second) turn an instance from its sample's orientation: a 2 m square
    turning 90° over the shutter covers each point for the fraction of the shutter it is inside the turned square."""
    s = _still_view(tmp_path / "spin.usda")
    pi = UsdGeom.PointInstancer.Define(s, "/pi")
    quad(s, "/pi/protos/square", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    pi.CreatePrototypesRel().SetTargets(["/pi/protos/square"])
    pi.CreateProtoIndicesAttr([0])
    pi.CreatePositionsAttr().Set([(0, 0, -10)], 2)
    pi.CreateOrientationsAttr().Set(Vt.QuathArray([Gf.Quath(1)]), 2)
    omega = 90.0 / (0.5 / 24)                                   # degrees per second: 90° over the shutter
    pi.CreateAngularVelocitiesAttr().Set([(0, 0, omega)], 2)
    s.Save()

    def inside(x, y, tau):
        a = -np.radians(omega * tau)                            # the point in the square's own frame
        return (np.abs(x * np.cos(a) - y * np.sin(a)) < 1) & (np.abs(x * np.sin(a) + y * np.cos(a)) < 1)
    assert _coverage(tmp_path / "spin.usda", inside) <= 0.03


def test_accelerations_move_points_over_the_shutter(tmp_path):
    """USD's accelerations: points at τ seconds from their sample are p + v·τ + ½·a·τ²; a quad at rest at frame 2
    accelerating along X is 2 m away at either end of the shutter."""
    s = _still_view(tmp_path / "accel.usda")
    m = UsdGeom.Mesh.Define(s, "/quad")
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    m.CreatePointsAttr().Set([(x, y, -10.0) for x, y in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))], 2)
    m.CreateVelocitiesAttr().Set([(0, 0, 0)] * 4, 2)
    accel = 2 * 2.0 * 96 ** 2                                   # ½·a·(1/96 s)² = 2 m
    m.CreateAccelerationsAttr().Set([(accel, 0, 0)] * 4, 2)
    s.Save()

    def inside(x, y, tau):
        return (np.abs(x - 0.5 * accel * tau ** 2) < 0.5) & (np.abs(y) < 0.5)
    assert _coverage(tmp_path / "accel.usda", inside) <= 0.03
