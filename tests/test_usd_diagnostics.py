"""USD's own warnings reach stderr as usdml warnings (``-q`` hides them); Tf errors stay errors."""

import pytest
from pxr import Tf, UsdGeom, UsdLux

from conftest import add_quad
from usdml.cli import main
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
