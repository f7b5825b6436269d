"""`usdml render`: analytic one-light images, shadows, EXR products, RenderSettings, resume, determinism."""

import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux

import usdml
from conftest import ALBEDO, add_cube_mesh, add_quad, add_top_camera, assert_direct, ground_stage, render_aovs
from usdml.aov.exr import is_complete_exr, read_exr, write_exr
from usdml.cli import main
from usdml.errors import UsdmlError
from usdml.render.frame import FrameRenderer
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate


def test_point_light_inverse_square_and_cosine(new_stage):
    def light(stage):
        s = UsdLux.SphereLight.Define(stage, "/World/bulb")
        s.CreateTreatAsPointAttr(True)
        s.CreateRadiusAttr(0.1)
        s.CreateIntensityAttr(5000)
        s.AddTranslateOp().Set((3, 4, -2))

    b = render_aovs(ground_stage(new_stage, light))
    p = b["P"].astype(np.float64)
    to = np.array([3, 4, -2]) - p
    d2 = (to ** 2).sum(-1)
    cos = to[..., 1] / np.sqrt(d2)
    assert_direct(b, 5000 * math.pi * 0.01 * cos / d2)
    assert np.allclose(b["normal"][..., 1], 1)
    assert b["shadow"].max() == 0


@pytest.mark.parametrize("softness", [0.0, 0.5])
def test_spot_cone_and_softness(new_stage, softness):
    def light(stage):
        s = UsdLux.SphereLight.Define(stage, "/World/spot")
        s.CreateTreatAsPointAttr(True)
        s.CreateRadiusAttr(0.1)
        s.CreateIntensityAttr(8000)
        s.CreateNormalizeAttr(True)
        s.AddTranslateOp().Set((0, 5, 0))
        s.AddRotateXOp().Set(-90)             # emit along -Y
        shaping = UsdLux.ShapingAPI.Apply(s.GetPrim())
        shaping.CreateShapingConeAngleAttr(30)
        shaping.CreateShapingConeSoftnessAttr(softness)

    b = render_aovs(ground_stage(new_stage, light), width=96)
    p = b["P"].astype(np.float64)
    to = np.array([0, 5, 0]) - p
    d = np.sqrt((to ** 2).sum(-1))
    cos = to[..., 1] / d                      # = cosine off the spot axis too
    outer, inner = math.cos(math.radians(30)), math.cos(math.radians(30 * (1 - softness)))
    if softness == 0:
        cone = (cos >= outer).astype(float)
    else:
        x = np.clip((cos - outer) / (inner - outer), 0, 1)
        cone = x * x * (3 - 2 * x)
    expected = 8000 / 4 * cos / d ** 2 * cone
    if softness == 0:                         # skip pixels straddling the hard edge
        edge = np.abs(np.degrees(np.arccos(np.clip(cos, -1, 1))) - 30) < 1.0
        b["direct"][edge] = 0
        expected[edge] = 0
    assert_direct(b, expected, min_lit=0.02)            # the cone lights ~3 % of the view
    assert (b["direct"][..., 0][cos < outer - 0.01] == 0).all()


def test_distant_light(new_stage):
    def light(stage):
        s = UsdLux.DistantLight.Define(stage, "/World/sun")
        s.CreateIntensityAttr(3)
        s.CreateNormalizeAttr(True)
        s.AddRotateXOp().Set(-60)             # -Z tilted 60 deg toward -Y: 30 deg above the horizon

    b = render_aovs(ground_stage(new_stage, light))
    cos = math.sin(math.radians(60))
    assert_direct(b, np.full(b["direct"].shape[:2], 3 * cos))


def test_shadow_under_a_box(new_stage):
    def light(stage):
        s = UsdLux.SphereLight.Define(stage, "/World/bulb")
        s.CreateTreatAsPointAttr(True)
        s.CreateIntensityAttr(1000)
        s.AddTranslateOp().Set((10, 10, 0))     # the shadow falls toward the camera's axis, in view
        box = add_cube_mesh(stage, "/World/box", size=2)
        box.AddTranslateOp().Set((5, 2, 0))

    b = render_aovs(ground_stage(new_stage, light), width=96)
    p = b["P"].astype(np.float64)
    on_ground = np.abs(p[..., 1]) < 1e-4

    def crosses_box(half):
        """Slab test: does the segment ground point -> light pass through the box grown by ``half - 1``?"""
        d = np.array([10.0, 10.0, 0.0]) - p
        lo, hi = np.array([5 - half, 2 - half, -half]), np.array([5 + half, 2 + half, half])
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (lo - p) / d, (hi - p) / d
        near = np.nanmax(np.minimum(t0, t1), axis=-1)
        far = np.nanmin(np.maximum(t0, t1), axis=-1)
        return (near <= far) & (far > 0) & (near < 1)

    inside = on_ground & crosses_box(0.9)
    clear = on_ground & ~crosses_box(1.1)
    assert inside.sum() > 20 and clear.sum() > 1000
    assert (b["shadow"][inside] == 1).all() and (b["direct"][inside] == 0).all()
    assert (b["shadow"][clear] == 0).all()


def test_render_writes_every_aov_and_the_header(new_stage, tmp_path, capsys):
    path = ground_stage(new_stage, lambda s: UsdLux.SphereLight.Define(s, "/World/b").AddTranslateOp().Set((0, 3, 0)))
    out = tmp_path / "out" / "img.####.exr"
    assert main(["render", path, str(out), "--frames", "1", "--imageWidth", "32", "--preview"]) == 0
    exr = tmp_path / "out" / "img.0001.exr"
    aovs, meta = read_exr(exr)
    assert set(aovs) == {"color", "direct", "indirect", "shadow", "depth", "normal", "P", "albedo", "primId", "instanceId"}
    assert aovs["color"].shape == (32, 32, 4) and aovs["color"].dtype == np.float16
    # the sphere light (radius 0.5, 3 above the ground) is seen in the middle, no surface there (visible lights)
    bulb = aovs["primId"] == -1
    assert 0 < bulb.sum() < 0.05 * bulb.size and bulb[15:17, 15:17].any() and np.isinf(aovs["depth"][bulb]).all()
    assert (aovs["primId"][~bulb] == 0).all() and (aovs["instanceId"] == -1).all()
    assert np.allclose(aovs["depth"][~bulb], 15, atol=1e-3)  # camera 15 above the ground, looking down
    assert meta["usdml:timeCode"] == 1.0 and meta["usdml:stage"] == os.path.abspath(path)
    assert np.asarray(meta["worldToCamera"]).shape == (4, 4)
    assert (tmp_path / "out" / "img.0001.png").exists()
    assert "img.0001.exr" in capsys.readouterr().out


def test_render_is_deterministic(new_stage, tmp_path):
    path = ground_stage(new_stage, lambda s: UsdLux.SphereLight.Define(s, "/World/b").AddTranslateOp().Set((1, 3, 0)))
    a = render_aovs(path, aovs=("color", "shadow"))
    b = render_aovs(path, aovs=("color", "shadow"))
    for k in a:
        assert np.array_equal(a[k], b[k])


def _sequence_stage(new_stage):
    stage = new_stage(start=1, end=4)
    add_quad(stage, "/World/ground", size=10)
    add_top_camera(stage, 5.0)          # usdml's framing camera would see the ground edge-on (usdrecord's)
    lamp = UsdLux.SphereLight.Define(stage, "/World/lamp")
    op = lamp.AddTranslateOp()
    for t in range(1, 5):
        op.Set((t - 2.0, 3, 0), t)
    stage.Save()
    return stage.GetRootLayer().realPath


def test_resume_after_an_interrupted_sequence(new_stage, tmp_path, monkeypatch, capsys):
    path = _sequence_stage(new_stage)
    tmp_path = tmp_path / "out"
    out = str(tmp_path / "seq.####.exr")
    real = FrameRenderer.render

    def interrupted(self, time, *a, **k):
        if time == 3:
            raise KeyboardInterrupt
        return real(self, time, *a, **k)

    monkeypatch.setattr(FrameRenderer, "render", interrupted)
    assert main(["render", path, out, "--frames", "1:4", "--imageWidth", "16"]) == 130
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["seq.0001.exr", "seq.0002.exr"]           # nothing partial, no temp files
    monkeypatch.setattr(FrameRenderer, "render", real)
    before = {n: os.stat(tmp_path / n).st_mtime_ns for n in files}
    Path(tmp_path / "seq.0002.exr").write_bytes(Path(tmp_path / "seq.0002.exr").read_bytes()[:500])  # corrupt
    capsys.readouterr()
    assert main(["render", path, out, "--frames", "1:4", "--imageWidth", "16", "--resume"]) == 0
    assert "1 frame(s) already complete" in capsys.readouterr().out
    assert os.stat(tmp_path / "seq.0001.exr").st_mtime_ns == before["seq.0001.exr"]
    assert all(is_complete_exr(tmp_path / f"seq.000{i}.exr") for i in range(1, 5))


def _json_render(capsys, argv) -> dict:
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_resume_renders_again_frames_made_with_other_settings(new_stage, tmp_path, capsys):
    """Issue 38: frames made at another width, with another seed, from an edited stage or by a usdml that
    wrote no settings digest are stale: rendered again, and the summary says how many."""
    path = _sequence_stage(new_stage)
    out = tmp_path / "seq.####.exr"
    render = ["render", path, str(out), "--pixel-samples", "1", "--frames"]
    assert main(render + ["1:3", "--imageWidth", "16"]) == 0
    write_exr(tmp_path / "seq.0004.exr", {"color": np.zeros((24, 24, 4), np.float32)})   # no usdml:settings
    capsys.readouterr()
    assert main(render + ["1:4", "--imageWidth", "24", "--resume"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("rendered 4 frame(s) at 24x24") and "4 stale (other settings), rendered again" in text
    assert "already complete" not in text
    aovs, meta = read_exr(tmp_path / "seq.0001.exr")
    assert aovs["color"].shape == (24, 24, 4)
    written = json.loads(meta["usdml:settings"])
    assert written["resolution"] == [24, 24] and written["params"]["pixel_samples"] == 1
    assert written["stage"]["path"] == path and written["camera"] == "/World/main_cam"
    assert meta["usdml:settingsDigest"] == "sha256:" + hashlib.sha256(meta["usdml:settings"].encode()).hexdigest()

    same = _json_render(capsys, render + ["1:4", "--imageWidth", "24", "--resume"])
    assert same["skipped"] == [1.0, 2.0, 3.0, 4.0] and same["frames"] == [] and same["stale"] == []
    seed = _json_render(capsys, render + ["1:2", "--imageWidth", "24", "--seed", "7", "--resume"])
    assert seed["stale"] == [1.0, 2.0] and seed["frames"] == [1.0, 2.0] and seed["skipped"] == []
    stage = Usd.Stage.Open(path)
    UsdLux.SphereLight(stage.GetPrimAtPath("/World/lamp")).CreateIntensityAttr(3.0)
    stage.Save()
    edited = _json_render(capsys, render + ["1:2", "--imageWidth", "24", "--seed", "7", "--resume"])
    assert edited["stale"] == [1.0, 2.0] and edited["frames"] == [1.0, 2.0]


def test_preview_pngs_are_in_the_summary(new_stage, tmp_path, capsys):
    path = _sequence_stage(new_stage)
    out = tmp_path / "p.####.exr"
    capsys.readouterr()
    assert main(["render", path, str(out), "--frames", "1:2", "--imageWidth", "8", "--preview"]) == 0
    # after the first line, each frame's estimates (its sphere light has area: "frame 1: lights with area ..."), then
    # the files
    listed = [line.strip() for line in capsys.readouterr().out.splitlines()[1:] if not line.startswith("frame ")]
    assert listed == [str(tmp_path / "p.0001.exr"), str(tmp_path / "p.0002.exr"),
                      str(tmp_path / "p.0001.png"), str(tmp_path / "p.0002.png")]
    summary = _json_render(capsys, ["render", path, str(out), "--frames", "1:3", "--imageWidth", "8", "--preview",
                                    "--resume"])
    assert summary["outputs"] == [str(tmp_path / "p.0003.exr")]
    assert summary["previews"] == [str(tmp_path / "p.0003.png")]
    assert summary["skippedOutputs"] == [str(tmp_path / "p.0001.exr"), str(tmp_path / "p.0002.exr")]


def test_an_output_path_takes_the_render_settings_resolution(new_stage, tmp_path):
    """Issue 38: with OUTPUT, the RenderSettings in force (flag or stage metadata) give the resolution;
    --imageWidth wins for the width and keeps the RenderSettings' aspect."""
    from pxr import UsdRender

    path = ground_stage(new_stage, lambda s: UsdLux.SphereLight.Define(s, "/World/b").AddTranslateOp().Set((0, 3, 0)))
    stage = Usd.Stage.Open(path)
    UsdRender.Settings.Define(stage, "/Render/Settings").CreateResolutionAttr(Gf.Vec2i(40, 20))
    stage.Save()

    def size(*argv) -> tuple:
        out = tmp_path / f"r{len(list(tmp_path.glob('r*.exr')))}.exr"
        assert main(["render", path, str(out), "--aovs", "color", "--pixel-samples", "1", *argv]) == 0
        return read_exr(out)[0]["color"].shape[:2]

    assert size("--imageWidth", "16") == (16, 16)                              # no RenderSettings: the camera's
    flag = ("--renderSettingsPrimPath", "/Render/Settings")
    assert size("--imageWidth", "16", *flag) == (8, 16)                        # --imageWidth wins, the RS aspect
    assert size(*flag) == (20, 40)                                             # the RenderSettings resolution
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    assert size() == (20, 40)                                                  # by the stage's metadata too
    assert usdml.Recorder(pixel_samples=1, aovs=["color"]).record(path, 1, str(tmp_path / "api.exr")).resolution \
        == [40, 20]


def test_render_settings_drive_products_on_openusd_stages(assets, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    blur = assets / "openusd/MotionBlurTest/motionBlur.usda"
    assert main(["render", str(blur), "--renderSettingsPrimPath", "/Render/Settings", "--imageWidth", "48"]) == 0
    aovs, meta = read_exr(tmp_path / "test.exr")               # the product's productName
    assert set(aovs) == {"Ci"} and aovs["Ci"].shape == (25, 48, 4)   # 2048x1080 fallback, scaled
    assert meta["usdml:camera"] == "/first_cam"
    usdview = assets / "openusd/testUsdviewRenderSettingsEdits/test.usda"
    assert main(["render", str(usdview), "--renderSettingsPrimPath", "/Render/Settings", "--imageWidth", "32"]) == 0
    aovs, _ = read_exr(tmp_path / "primary.exr")
    assert set(aovs) == {"Ci"} and aovs["Ci"].shape == (32, 32, 4)    # resolution (512, 512)
    assert "/Render/Vars/a: sourceName 'a'" in capsys.readouterr().err


def _with_product(path: str, set_name) -> None:
    """Give the stage at ``path`` RenderSettings (its renderSettingsPrimPath) with one RenderProduct,
    whose productName ``set_name(attribute)`` authors."""
    from pxr import Usd, UsdRender
    stage = Usd.Stage.Open(path)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    product = UsdRender.Product.Define(stage, "/Render/Product")
    set_name(product.CreateProductNameAttr())
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()


def test_time_sampled_product_name(new_stage, tmp_path, monkeypatch):
    path = _sequence_stage(new_stage)
    _with_product(path, lambda name: [name.Set(f"shot_{t * 10}.exr", t) for t in range(1, 5)])
    (tmp_path / "out").mkdir()
    monkeypatch.chdir(tmp_path / "out")
    assert main(["render", path, "--frames", "2:3", "--imageWidth", "16"]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["shot_20.exr", "shot_30.exr"]


@pytest.mark.parametrize("argv,message", [
    (["--frames", "1:x"], "FrameSpec"),
    (["--imageWidth", "0"], "--imageWidth 0"),
    (["--visibility", "octree"], "unknown visibility backend 'octree'"),
    (["--aovs", "beauty"], "beauty"),
    (["--gi", "lgh", "--lgh-alpha", "nan"], "LGH alpha must be finite"),
    (["--seed", "-1"], "seed must be >= 0"),
    (["--purposes", "render,bogus"], "--purposes: unknown purpose(s) bogus"),
    (["--implicit-detail", "5000"], "--implicit-detail 5000: give an integer from 3 to 1024"),
])
def test_render_errors(new_stage, tmp_path, capsys, argv, message):
    path = _sequence_stage(new_stage)
    code = main(["render", path, str(tmp_path / "out" / "x.####.exr"), *argv])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_frames_outside_the_stage_range_render_as_usdrecord_renders_them(new_stage, tmp_path):
    """Issue 55: frames 1:2 of a stage whose range is 1 to 1 were refused; USD holds the values outside the
    range and usdrecord renders them. Outside an animated stage's range they are one warning."""
    import subprocess
    import sys

    still = new_stage("still.usda", start=1, end=1)
    add_quad(still, "/World/ground", size=10)
    add_top_camera(still, 5.0)
    UsdLux.SphereLight.Define(still, "/World/lamp").AddTranslateOp().Set((0, 3, 0))
    still.Save()
    result = usdml.Recorder(image_width=8, pixel_samples=1).record_sequence(
        still.GetRootLayer().realPath, "1:2", str(tmp_path / "still.####.exr"))
    assert result.frames == [1.0, 2.0] and not result.warnings
    assert [os.path.basename(f) for f in result.files] == ["still.0001.exr", "still.0002.exr"]
    path = _sequence_stage(new_stage)                  # frames 1 to 4, the lamp moving
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", path, str(tmp_path / "o.####.exr"), "--frames",
                        "3:6", "--imageWidth", "8", "--pixel-samples", "1"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("rendered 4 frame(s)")
    assert r.stderr.splitlines() == [
        f"usdml: warning: {path}: 2 frames (5 ... 6) are outside the stage's range [1, 4] (startTimeCode/endTimeCode); "
        "rendered with the values USD holds there (each attribute's first or last time sample)"]
    color = {f: read_exr(tmp_path / f"o.000{f}.exr")[0]["color"] for f in (4, 6)}
    assert np.array_equal(color[4], color[6])                   # the last samples held


def test_output_must_be_exr_and_a_product_name_becomes_one(new_stage, tmp_path, capsys, monkeypatch):
    path = _sequence_stage(new_stage)
    assert main(["render", path, str(tmp_path / "x.png"), "--imageWidth", "8"]) == 2
    assert "usdml writes multi-channel OpenEXR; give a .exr path" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
    _with_product(path, lambda name: name.Set("still.png"))
    monkeypatch.chdir(tmp_path)
    assert main(["render", path, "--imageWidth", "8"]) == 0
    assert "/Render/Product.productName: 'still.png' is not OpenEXR" in capsys.readouterr().err
    assert is_complete_exr(tmp_path / "still.exr") and not (tmp_path / "still.png").exists()


@pytest.mark.parametrize("command", ["bench", "compare"])
def test_bench_and_compare_check_the_width_and_need_lights(new_stage, capsys, command):
    path = _sequence_stage(new_stage)
    extra = ["--visibility", "voxel"] if command == "compare" else []
    assert main([command, path, "--imageWidth", "0", *extra]) == 2
    err = capsys.readouterr().err
    assert "--imageWidth 0: give an integer from 1 to 16384 (pixels)" in err and "Traceback" not in err
    dark = ground_stage(new_stage, lambda stage: None)
    assert main([command, dark, "--imageWidth", "8", *extra]) == 2
    assert f"no lights at time 1, so no shadow rays to {command}" in capsys.readouterr().err


def test_render_of_a_stage_without_geometry(new_stage, tmp_path, capsys):
    stage = new_stage()
    UsdGeom.Camera.Define(stage, "/cam")
    stage.Save()
    assert main(["render", stage.GetRootLayer().realPath, str(tmp_path / "out" / "x.exr")]) == 2
    assert "no renderable geometry" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_render_needs_an_output_or_render_settings(new_stage, capsys):
    path = _sequence_stage(new_stage)
    assert main(["render", path]) == 2
    assert "give an OUTPUT path" in capsys.readouterr().err


@pytest.mark.parametrize("normalize", [False, True])
def test_centimetre_stage_renders_like_the_metre_stage(new_stage, tmp_path, normalize):
    """metersPerUnit: a scene authored in cm x100 gives the same radiance as in metres."""
    images = []
    for unit, scale in ((1.0, 1.0), (0.01, 100.0)):
        stage = new_stage(name=f"s{scale:g}.usda", start=1, end=1)
        UsdGeom.SetStageMetersPerUnit(stage, unit)
        ground = add_quad(stage, "/World/ground", size=40 * scale)
        ground.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
        cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
        cam.CreateClippingRangeAttr(Gf.Vec2f(0.1 * scale, 1000 * scale))
        cam.AddTranslateOp().Set((0, 15 * scale, 0))
        cam.AddRotateXOp().Set(-90)
        bulb = UsdLux.SphereLight.Define(stage, "/World/bulb")
        bulb.CreateRadiusAttr(0.2 * scale)
        bulb.CreateIntensityAttr(300)
        bulb.CreateNormalizeAttr(normalize)
        bulb.AddTranslateOp().Set((1 * scale, 3 * scale, 0))
        disk = UsdLux.DiskLight.Define(stage, "/World/disk")
        disk.CreateRadiusAttr(0.3 * scale)
        disk.CreateIntensityAttr(200)
        disk.CreateNormalizeAttr(normalize)
        disk.AddTranslateOp().Set((-2 * scale, 4 * scale, 0))
        disk.AddRotateXOp().Set(-90)
        stage.Save()
        images.append(render_aovs(stage.GetRootLayer().realPath, width=32, aovs=("direct",))["direct"])
    assert images[0].max() > 0
    # the sphere and the disk have area: their samples are keyed by the points' float32 bits, which the two
    # stages do not share, so the pixels agree within the sampling's noise and the images' means closely
    np.testing.assert_allclose(images[1].mean(), images[0].mean(), rtol=2e-3)
    np.testing.assert_allclose(images[1], images[0], rtol=0.05, atol=1e-4)


def test_camera_light_only_when_the_stage_has_no_lights(new_stage, tmp_path, capsys):
    dark = ground_stage(new_stage, lambda stage: None)
    b = render_aovs(dark, aovs=("direct", "normal", "P"))
    # usdrecord's camera light: albedo · cos(angle to the eye), no falloff, no shadow
    to_eye = np.array([0, 15, 0]) - b["P"].astype(np.float64)
    cos = to_eye[..., 1] / np.linalg.norm(to_eye, axis=-1)
    np.testing.assert_allclose(b["direct"][..., 0], ALBEDO * cos, rtol=1e-4)
    capsys.readouterr()
    assert main(["render", dark, str(tmp_path / "a.exr"), "--imageWidth", "8", "--disableCameraLight"]) == 0
    assert read_exr(tmp_path / "a.exr")[0]["direct"].max() == 0
    assert "camera light" not in capsys.readouterr().err
    assert main(["render", dark, str(tmp_path / "b.exr"), "--imageWidth", "8"]) == 0
    assert "no lights at time 1; lit by a camera light" in capsys.readouterr().err
    # GI asked for with nothing to emit VPLs: said once, not a silent black indirect
    assert main(["render", dark, str(tmp_path / "c.exr"), "--imageWidth", "8", "--gi", "lgh", "--vpls", "100"]) == 0
    err = capsys.readouterr().err
    assert "--gi lgh: no VPLs at time 1: the stage has no lights" in err and err.count("no VPLs") == 1
    assert read_exr(tmp_path / "c.exr")[0]["indirect"].max() == 0
    lit = ground_stage(new_stage, lambda s: UsdLux.DistantLight.Define(s, "/World/sun"))
    d = StageDelegate(lit)
    r = FrameRenderer(d, UsdmlSettings())
    assert not r.render(1, 8, 8, {"color"}).stats.camera_light


def test_a_black_or_empty_frame_says_so_and_what_to_check(new_stage, tmp_path, capsys):
    """A line per frame whose color is 0 everywhere, naming the frame and the likely cause (issue 55)."""
    def blank(path, *flags) -> list[str]:
        capsys.readouterr()
        assert main(["render", path, str(tmp_path / "o.exr"), "--imageWidth", "8", "--pixel-samples", "1", *flags]) == 0
        return [line for line in capsys.readouterr().err.splitlines() if "frame 1 is" in line]

    dark = ground_stage(new_stage, lambda stage: None)
    assert blank(dark) == []                                        # the camera light
    (line,) = blank(dark, "--disableCameraLight")
    assert line == (f"usdml: warning: {dark}: frame 1 is black (color 0 everywhere): the stage has no lights here and "
                    "--disableCameraLight turned usdrecord's light at the eye off; add a UsdLux light")

    def sun(name: str, rotate_x: float) -> str:
        return ground_stage(new_stage,
                            lambda s: UsdLux.DistantLight.Define(s, "/World/sun").AddRotateXOp().Set(rotate_x), name)

    below = sun("below.usda", 90)
    assert "no light reaches what the camera sees; check the lights" in blank(below)[0]     # lit from below
    above = sun("above.usda", -90)
    assert blank(above) == []
    stage = Usd.Stage.Open(above)
    stage.GetPrimAtPath("/World/main_cam").GetAttribute("xformOp:rotateX").Set(90.0)     # looking at the sky
    stage.Save()
    assert blank(above) == [f"usdml: warning: {above}: frame 1 is empty (alpha 0 everywhere): no geometry in the "
                            "camera's view; check the camera (/World/main_cam: where it looks, its clipping range) "
                            "and the geometry's visibility, purpose and activation"]


def test_constant_dome_on_an_unoccluded_upward_plane(new_stage):
    """A dome of radiance L gives irradiance π·L on an open upward plane: direct = albedo · L."""
    def light(stage):
        dome = UsdLux.DomeLight.Define(stage, "/World/sky")
        dome.CreateIntensityAttr(2.0)
        dome.CreateColorAttr((1.0, 0.5, 0.25))

    b = render_aovs(ground_stage(new_stage, light), width=16, aovs=("direct", "shadow"))
    expected = ALBEDO * 2.0 * np.array([1.0, 0.5, 0.25])
    np.testing.assert_allclose(b["direct"].reshape(-1, 3), np.broadcast_to(expected, (256, 3)), rtol=0.01)
    assert b["shadow"].max() == 0


def _cube_on_ground(new_stage) -> str:
    """ground_stage with a 4-unit cube on the ground and three sphere lights above it."""
    def lights(stage):
        cube = add_cube_mesh(stage, "/World/cube", size=4)
        cube.AddTranslateOp().Set((0, 2, 0))
        for i, x in enumerate((-6, 0, 6)):
            light = UsdLux.SphereLight.Define(stage, f"/World/light{i}")
            light.CreateIntensityAttr(100.0)
            light.AddTranslateOp().Set((x, 8, x / 2))

    return ground_stage(new_stage, lights)


def test_bench_times_bare_embree_on_the_exact_backends_rays(new_stage, tmp_path, monkeypatch, capsys):
    """usdml bench's bare-embreex peer: on the rays exact traces, the same answers; every row's ratios
    follow from the seconds (no timing asserted)."""
    import json

    from usdml.bench import format_bench

    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path / "cache"))
    assert main(["bench", _cube_on_ground(new_stage), "--visibility", "exact", "--visibility", "voxel",
                 "--voxel-resolution", "16", "--direction-step", "15", "--imageWidth", "24", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["backend"] for r in rows] == ["exact", "voxel"]
    exact = rows[0]
    assert exact["queries"] > 0 and 0 < exact["blocked_fraction"] < 1
    assert exact["bare_embree_seconds"] > 0 and exact["disagreement_vs_bare_embree"] == 0.0
    for r in rows:
        assert r["bare_embree_seconds"] == exact["bare_embree_seconds"]
        assert r["speedup_vs_bare_embree"] == pytest.approx(r["bare_embree_seconds"] / r["seconds"])
        assert r["exact_overhead_vs_bare_embree"] == pytest.approx(exact["seconds"] / exact["bare_embree_seconds"])
        assert r["disagreement_vs_bare_embree"] == pytest.approx(r["disagreement_vs_exact"])
    lines = format_bench(rows).splitlines()
    assert "bare embreex on the same rays" in lines[0] and "x bare embreex" in lines[1]


def test_bench_and_compare_set_up_backends_as_a_render(new_stage, tmp_path, monkeypatch):
    """usdml.render.backends.Backends with QUERY_ROLES (compare --visibility, bench): no --gi svo backend; a
    shared exact backend is updated and closed by its own Backends only; --error-budget on a backend that cannot
    refine warns (a render), says nothing (bench) or is Refined's error (compare)."""
    from usdml.errors import log
    from usdml.render.backends import QUERY_ROLES, Backends
    from usdml.scene import diff
    from usdml.visibility import registry

    (tmp_path / "plain_backend.py").write_text(
        "from usdml.visibility.exact import ExactBackend\n\n\n"
        "class PlainBackend(ExactBackend):\n"
        "    name = 'plain'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    warnings = []
    monkeypatch.setattr(log, "warning", warnings.append)
    snap = StageDelegate(_cube_on_ground(new_stage)).snapshot(1.0)
    first = Backends(UsdmlSettings().updated(gi="svo"), roles=QUERY_ROLES)
    assert first.gi is None and first.shadow is first.primary is first.configured
    registry.register("plain", "plain_backend:PlainBackend")
    try:
        settings = UsdmlSettings().updated(visibility="plain", error_budget=0.01)
        with pytest.raises(UsdmlError, match="plain backend does not say which of its answers are uncertain; leave "
                                             "--error-budget out, or use voxel, svo or insm"):
            Backends(settings, roles=QUERY_ROLES, unrefinable="raise")
        assert not warnings
        Backends(settings, roles=QUERY_ROLES).close()
        assert warnings == ["--error-budget is ignored: the plain backend does not say which of its answers are "
                            "uncertain"]
        other = Backends(settings, roles=QUERY_ROLES, primary=first.primary, unrefinable="ignore")
        assert len(warnings) == 1 and other.refined is None and other.shadow is other.configured
        assert other.primary is first.primary and other.shadow.name == "plain"
        assert set(first.update(snap, diff(None, snap))) == {"primary"}
        calls = []
        monkeypatch.setattr(first.primary, "update", lambda *a: calls.append("update"))
        monkeypatch.setattr(first.primary, "close", lambda: calls.append("close"))
        assert set(other.update(snap, diff(None, snap))) == {"shadow"}
        other.close()
        assert calls == []
    finally:
        registry.unregister("plain")
    first.close()
    assert calls == ["close"]


def test_exact_overhead_tool_agrees_with_bare_embree(new_stage):
    """tools/exact_overhead.py: rounds of exact and bare embreex, same answers, ratios from the seconds."""
    import json
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, str(root / "tools" / "exact_overhead.py"), _cube_on_ground(new_stage),
                           "--imageWidth", "24", "--rounds", "2", "--json"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["queries"] > 0 and r["rounds"] == 2 and r["disagreements"] == 0
    assert r["overhead_cpu"] and r["overhead_wall"] == pytest.approx(
        [a / b for a, b in zip(r["exact_seconds"], r["bare_embree_seconds"])])


def test_a_sequence_reads_each_frame_once(new_stage, tmp_path, monkeypatch):
    """The first frame renders from the snapshot the sequence read to size the image (read once, not twice);
    every other frame reads its own; the pixels are those of a frame that reads its stage itself."""
    path = _sequence_stage(new_stage)
    reads = []
    real = StageDelegate.snapshot

    def counted(self, time):
        reads.append(time)
        return real(self, time)

    monkeypatch.setattr(StageDelegate, "snapshot", counted)
    out = str(tmp_path / "seq.####.exr")
    assert main(["render", path, out, "--frames", "1:3", "--imageWidth", "16", "-q"]) == 0
    assert reads == [1.0, 2.0, 3.0]
    monkeypatch.setattr(StageDelegate, "snapshot", real)
    d = StageDelegate(path)
    alone = FrameRenderer(d, d.usdml_settings).render(1.0, 16, 9, {"color"})
    given = FrameRenderer(d, d.usdml_settings).render(1.0, 16, 9, {"color"}, snapshot=d.snapshot(1.0))
    other = FrameRenderer(d, d.usdml_settings).render(1.0, 16, 9, {"color"}, snapshot=d.snapshot(3.0))
    assert np.array_equal(alone.buffers["color"], given.buffers["color"])
    assert np.array_equal(alone.buffers["color"], other.buffers["color"])      # a snapshot of another time: read
