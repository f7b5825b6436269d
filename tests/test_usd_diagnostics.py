"""USD's own warnings reach stderr as usdml warnings (``-q`` hides them); Tf errors stay errors; a warning met on
many prims is printed once, with a count, and listed in full in the JSON."""

import json
import logging
import subprocess
import sys

import pytest
from pxr import Tf, UsdGeom, UsdLux, UsdShade

from conftest import add_quad, add_top_camera
from usdml.cli import main
from usdml.errors import Warnings, cause, collect_warnings
from usdml.stage.diagnostics import usd_diagnostics, usd_message


def _instancer_without_prototypes(new_stage) -> str:
    """A PointInstancer with protoIndices but an empty prototypes relationship: UsdGeom TF_WARNs
    ``/World/PI -- no prototypes`` from ComputeInstanceTransformsAtTime."""
    stage = new_stage()
    add_quad(stage, "/World/ground", size=4)
    pi = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    pi.CreateProtoIndicesAttr([0, 0])
    pi.CreatePositionsAttr([(0, 0, 0), (1, 0, 0)])
    pi.CreatePrototypesRel()
    UsdLux.DistantLight.Define(stage, "/World/sun")
    stage.Save()
    return stage.GetRootLayer().realPath


@pytest.mark.parametrize("quiet", [False, True])
def test_point_instancer_without_prototypes_warns_through_usdml(new_stage, tmp_path, capfd, quiet):
    """It printed ``Warning: in _GetPrototypePathsForInstanceTransforms at line 690 of …/pointInstancer.cpp
    -- /World/PI -- no prototypes`` twice, straight from C++ (capfd sees the file descriptor), even with -q."""
    stage = _instancer_without_prototypes(new_stage)
    capfd.readouterr()
    assert main(["-q"] * quiet + ["render", stage, str(tmp_path / "o.exr"), "--imageWidth", "8"]) == 0
    err = capfd.readouterr().err
    assert "Warning: in" not in err and "pointInstancer.cpp" not in err
    assert err.count("usdml: warning: /World/PI: no prototypes") == (0 if quiet else 1)


def test_messages_name_the_prim_or_else_the_stage():
    assert usd_message("/World/PI -- no prototypes", "s.usda") == "/World/PI: no prototypes"
    assert usd_message("Could not load sublayer @x.usda@;\n skipping.", "s.usda") == \
        "s.usda: Could not load sublayer @x.usda@; skipping."


def test_only_inside_the_block_and_errors_still_raise(capfd):
    got = []
    with pytest.raises(Tf.ErrorException):
        with usd_diagnostics(got.append, "s.usda"):
            Tf.Warn("/A/B -- from inside")
            Tf.RaiseRuntimeError("a real error")
    assert got == ["/A/B: from inside"]        # collected before the error left the block
    Tf.Warn("after the block")
    err = capfd.readouterr().err
    assert "from inside" not in err and "after the block" in err     # Tf prints for itself again


def _usdml(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "usdml.cli", *map(str, argv)], capture_output=True, text=True)


def _lit(new_stage, name: str = "s.usda"):
    stage = new_stage(name)
    add_quad(stage, "/World/ground", size=4)
    add_top_camera(stage, 4.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-60)
    return stage


def test_a_missing_layer_referenced_by_many_prims_is_one_line(new_stage, tmp_path):
    """Issue 55: a thousand prims referencing one missing layer printed 573 lines of USD's (two per prim); now
    one line with a count, and the JSON of render and info lists every prim's."""
    stage = _lit(new_stage)
    for i in range(200):
        stage.DefinePrim(f"/World/P{i}").GetReferences().AddReference("missing.usda")
    stage.Save()
    path = stage.GetRootLayer().realPath
    line = (f"usdml: warning: /World/P0: composition error: Could not open asset @missing.usda@ for reference "
            f"introduced by @{path}@</World/P0>. (… and 199 more prims)")
    r = _usdml("render", path, tmp_path / "o.exr", "--imageWidth", 16, "--pixel-samples", 1, "--json")
    assert r.returncode == 0 and r.stderr.splitlines() == [line]
    warnings = json.loads(r.stdout)["warnings"]
    assert len(warnings) == 200 and warnings[199].startswith("/World/P99: composition error: Could not open asset")
    r = _usdml("info", path, "--json")
    assert r.returncode == 0 and r.stderr.splitlines() == [line] and len(json.loads(r.stdout)["warnings"]) == 200


def test_missing_mtlx_files_are_a_line_each_and_their_materials_one(new_stage, tmp_path):
    """Seven missing .mtlx files printed 29 lines: USD's warning and the composition error for each material, and
    the material's own; now a line per missing file and one for the materials left without a surface."""
    stage = _lit(new_stage)
    for i in range(6):
        material = UsdShade.Material.Define(stage, f"/World/Looks/M{i}")
        material.GetPrim().GetReferences().AddReference(f"mat{i % 3}.mtlx", "/MaterialX/M")
        cube = UsdGeom.Cube.Define(stage, f"/World/C{i}")
        cube.AddTranslateOp().Set((i - 3.0, 0.5, 0.0))
        UsdShade.MaterialBindingAPI.Apply(cube.GetPrim()).Bind(material)
    stage.Save()
    path = stage.GetRootLayer().realPath
    r = _usdml("render", path, tmp_path / "o.exr", "--imageWidth", 16, "--pixel-samples", 1, "--json")
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines() == [
        f"usdml: warning: /World/Looks/M{i}: composition error: Could not open asset @mat{i}.mtlx@ for "
        f"reference introduced by @{path}@</World/Looks/M{i}>. (… and 1 more prim)" for i in range(3)] + [
        "usdml: warning: /World/Looks/M0: no UsdPreviewSurface (MaterialX/other only); using displayColor "
        "(… and 5 more prims)"]
    assert len(json.loads(r.stdout)["warnings"]) == 12


def test_a_cause_is_the_message_without_its_prim_paths():
    assert cause("/World/P9: composition error: Could not open asset @a.usda@ for reference introduced by "
                 "@/s.usda@</World/P9>.") == ("<prim>: composition error: Could not open asset @a.usda@ for "
                                               "reference introduced by @/s.usda@<<prim>>.")
    assert cause("/W/Tex.inputs:file @t.png@ does not resolve") == "<prim>.inputs:file @t.png@ does not resolve"
    # a file's path, a ratio and words with a slash stay
    assert cause("/tmp/s.usda: 1/2 and/or x") == "/tmp/s.usda: 1/2 and/or x"


def test_a_cause_logged_once_is_collected_again_but_not_logged(caplog):
    caplog.set_level(logging.WARNING, logger="usdml")
    warn = Warnings()
    with collect_warnings() as collected:
        with warn.grouped():
            warn("/A: no surface")
            warn("/B: no surface")
            warn("/A: no surface")                    # the same message: once
            warn("/A: other")
        warn("/C: no surface")                        # a later frame's: said already
    assert [r.getMessage() for r in caplog.records] == ["/A: no surface (… and 1 more prim)", "/A: other"]
    assert collected == warn.messages == ["/A: no surface", "/B: no surface", "/A: other", "/C: no surface"]
