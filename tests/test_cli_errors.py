"""Bad input: one clear line naming the file / prim / attribute, exit status 2, no traceback."""

import os
import subprocess
import sys

import pytest
from pxr import Sdf, UsdGeom, UsdLux

from conftest import add_cube_mesh
from usdml.cli import main


def _run(capsys, *argv):
    code = main(["info", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def _errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("usdml: error:")]


def _assert_one_error(capsys, argv, pattern):
    code, out, err = _run(capsys, *argv)
    assert code == 2
    (line,) = _errors(err)
    assert "Traceback" not in err
    import re
    assert re.search(pattern, line), line


def test_missing_file(capsys, tmp_path):
    _assert_one_error(capsys, [tmp_path / "nope.usda"], r"nope\.usda: no such file")


def test_syntax_error_names_file_and_line(capsys, tmp_path):
    bad = tmp_path / "broken.usda"
    bad.write_text('#usda 1.0\ndef Xform "a" {\n  float x = \n}\n')
    _assert_one_error(capsys, [bad], r"broken\.usda: cannot open stage: .*broken\.usda:3")


def test_not_a_usd_file(capsys, tmp_path):
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    _assert_one_error(capsys, [txt], r"notes\.txt: .txt is not a USD file format")
    garbage = tmp_path / "garbage.usdc"
    garbage.write_bytes(b"\x00\x01garbage" * 10)
    _assert_one_error(capsys, [garbage], r"garbage\.usdc: cannot open stage")


def test_directory_instead_of_a_file(capsys, tmp_path):
    _assert_one_error(capsys, [tmp_path], r"is a directory")


def test_unreadable_file(capsys, tmp_path):
    import os
    if os.geteuid() == 0:
        pytest.skip("root can read any file")
    f = tmp_path / "locked.usda"
    f.write_text("#usda 1.0\n")
    f.chmod(0)
    _assert_one_error(capsys, [f], r"not readable")


def test_no_renderable_geometry(capsys, new_stage):
    stage = new_stage()
    UsdGeom.Xform.Define(stage, "/empty")
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], r"no renderable geometry")


def test_time_outside_the_stage_is_a_warning_and_a_time_that_is_not_finite_an_error(capsys, new_stage):
    stage = new_stage(start=1, end=24)
    add_cube_mesh(stage, "/box")
    stage.Save()
    path = stage.GetRootLayer().realPath
    code, out, err = _run(capsys, path, "--time", "30")        # USD holds the last samples there (issue 55)
    # the stage has no camera: the framing camera's warning aside (issue 55 item 6)
    assert code == 0 and [line for line in err.splitlines() if ": no camera;" not in line] == [
        f"usdml: warning: {path}: time 30 is outside the stage's range [1, 24] (startTimeCode/endTimeCode); rendered "
        "with the values USD holds there (each attribute's first or last time sample)"]
    _assert_one_error(capsys, [path, "--time", "nan"], r"time nan is not a finite timecode")


def test_swapped_time_range_is_used_the_right_way_round(capsys, new_stage):
    import json
    stage = new_stage(start=100, end=0)      # as usd-wg's start_end_timeCodes_swapped.usda
    add_cube_mesh(stage, "/box")
    stage.Save()
    assert main(["info", stage.GetRootLayer().realPath, "--time", "50", "--json"]) == 0
    out, err = capsys.readouterr()
    info = json.loads(out)
    assert (info["startTimeCode"], info["endTimeCode"]) == (0, 100)
    assert "startTimeCode 100 is after endTimeCode 0; using the range [0, 100]" in err


def test_nan_transform_names_the_prim(capsys, new_stage):
    stage = new_stage()
    box = add_cube_mesh(stage, "/World/box")
    box.AddTranslateOp().Set((float("nan"), 0, 0))
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], r"/World/box.*non-finite")


def test_nan_light_intensity_names_the_attribute(capsys, new_stage):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    UsdLux.SphereLight.Define(stage, "/key").CreateIntensityAttr(float("nan"))
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], r"/key\.inputs:intensity: value nan is not finite")


def test_nan_point_instancer_positions(capsys, new_stage):
    stage = new_stage()
    pi = UsdGeom.PointInstancer.Define(stage, "/pi")
    add_cube_mesh(stage, "/pi/protos/box")
    pi.CreatePrototypesRel().SetTargets(["/pi/protos/box"])
    pi.CreatePositionsAttr([(0, 0, 0), (float("nan"), 0, 0)])
    pi.CreateProtoIndicesAttr([0, 0])
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], r"/pi: non-finite")


def test_zero_scale_camera_names_the_camera(capsys, new_stage):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    cam = UsdGeom.Camera.Define(stage, "/cam")
    cam.AddTranslateOp().Set((0, 0, 10))
    cam.AddScaleOp().Set((0, 0, 0))
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], r"/cam: camera transform is singular at time")


@pytest.mark.parametrize("mpu", [0.0, -1.0])
def test_meters_per_unit_must_be_positive(capsys, new_stage, mpu):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath], rf"metersPerUnit {mpu:g} must be positive")


def test_missing_camera(capsys, new_stage):
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    stage.Save()
    _assert_one_error(capsys, [stage.GetRootLayer().realPath, "--camera", "hero"], r"no camera named 'hero'")


def test_console_script_exit_status_and_single_line(tmp_path):
    """The installed entry point, as a user runs it."""
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "info", str(tmp_path / "x.usda")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"usdml: error: {tmp_path / 'x.usda'}: no such file; check the stage path"]


def _lit_box(new_stage) -> str:
    stage = new_stage(start=1, end=2)
    add_cube_mesh(stage, "/box")
    UsdLux.DistantLight.Define(stage, "/sun")
    stage.Save()
    return stage.GetRootLayer().realPath


@pytest.mark.parametrize("below", ["x.#.exr", "sub/x.#.exr"])
def test_output_folder_under_a_file(new_stage, tmp_path, below):
    """``usdml render good.usda good.usda/x.#.exr``: the output folder's parent is a file. It ended in a
    FileExistsError (NotADirectoryError one level deeper) traceback."""
    stage = _lit_box(new_stage)
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", stage, f"{stage}/{below}", "--frames", "1:2",
                        "--imageWidth", "8"], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = _errors(r.stderr)         # beside the warning that the stage has no camera
    assert f"({stage} is a file, not a folder); choose another" in line


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc (a folder no one can create files in)")
def test_output_folder_that_takes_no_file(new_stage, capsys):
    """Root may write anywhere else: /proc refuses new files to everyone. OpenEXR's RuntimeError was a traceback."""
    assert main(["render", _lit_box(new_stage), "/proc/x.#.exr", "--frames", "1", "--imageWidth", "8"]) == 2
    (line,) = _errors(capsys.readouterr().err)
    assert line.startswith("usdml: error: /proc/x.1.exr: cannot write the file (") and "writable output folder" in line


def test_workers_and_scheduler_are_refused_before_the_stage_is_read(tmp_path):
    """Issue 55, item 4: ``--workers 2 --scheduler tcp://...`` waited ten seconds for the scheduler before
    failing; two ways of running the frames is one line at once, before the stage (here none) is read."""
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(tmp_path / "nope.usda"), "out.####.exr",
                        "--workers", "2", "--scheduler", "tcp://127.0.0.1:9"], capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        "usdml: error: --workers 2 and --scheduler tcp://127.0.0.1:9: two ways of running the frames; give "
        "--workers N (a local cluster) or --scheduler ADDRESS (a running one), not both"]


def test_a_missing_render_settings_prim_lists_the_stage_s(tmp_path):
    """Issue 55, item 5: ``--renderSettingsPrimPath`` naming no RenderSettings says which there are, as
    ``--camera`` lists cameras, and how to give one."""
    boxes = os.path.join(os.path.dirname(__file__), "..", "stages", "boxes.usda")
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "info", boxes, "--renderSettingsPrimPath", "/Render/Nope"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        "usdml: error: --renderSettingsPrimPath: no RenderSettings prim at /Render/Nope; RenderSettings on the "
        "stage: /Render/Settings (give one with --renderSettingsPrimPath)"]


def test_every_missing_thing_says_what_to_do(capsys, new_stage, tmp_path):
    """Issue 55, item 5: each "no X at Y" error ends in "; what to do"."""
    stage = new_stage()
    add_cube_mesh(stage, "/box")
    stage.DefinePrim("/Render", "Scope")
    stage.Save()
    path = stage.GetRootLayer().realPath
    _assert_one_error(capsys, [path, "--renderSettingsPrimPath", "/Render/Nope"],
                      r"no RenderSettings prim at /Render/Nope; the stage has no RenderSettings prim \(omit "
                      r"--renderSettingsPrimPath\)$")
    _assert_one_error(capsys, [path, "--renderSettingsPrimPath", "/Render"],
                      r"/Render is a prim of type Scope, not RenderSettings; the stage has no RenderSettings prim")
    _assert_one_error(capsys, [path, "--renderSettingsPrimPath", "Render"],
                      r"'Render' is not an absolute prim path; the stage has no RenderSettings prim")
    _assert_one_error(capsys, [path, "--camera", "/not a path"], r"is not a valid prim path; the stage has no camera")
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Gone")
    stage.Save()
    _assert_one_error(capsys, [path], r"the stage's renderSettingsPrimPath metadata: no RenderSettings prim at "
                                      r"/Render/Gone; .* \(fix or remove its renderSettingsPrimPath metadata\)$")
    from usdml.aov.exr import read_exr
    from usdml.aov.naming import frame_spec
    from usdml.errors import UsdmlError

    with pytest.raises(UsdmlError, match=r"no such EXR file; check the path$"):
        read_exr(tmp_path / "nope.exr")
    with pytest.raises(UsdmlError, match=r"no start timecode; give --frames \(e\.g\. --frames 1\) or author"):
        frame_spec(None, None, None)
