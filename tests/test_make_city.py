"""tools/make_city.py: the seeded "unseen city" generator (issue 36), at a small budget."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from pxr import Usd, UsdGeom
from usdml.stage.delegate import StageDelegate

TRIANGLES = 20_000
SEED = 3


def make(seed, out, triangles=TRIANGLES):
    """The CLI, as a person runs it: returns the stage path it wrote."""
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "make_city.py"), "--seed", str(seed), "--out", str(out),
                          "--triangles", str(triangles)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    path = out / f"unseen_city_{seed}.usda"
    assert f"{path}:" in run.stdout and "triangles=" in run.stdout
    return path


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    return make(SEED, tmp_path_factory.mktemp("city"))


def stage_triangles(stage):
    """Triangles as rendered: every mesh, instance proxies included (so instanced props count per instance)."""
    total = 0
    for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdGeom.Mesh):
            total += int(np.sum(np.asarray(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get()) - 2))
    return total


def test_same_seed_same_bytes_other_seed_differs(city, tmp_path):
    again = make(SEED, tmp_path / "again")
    assert again.read_bytes() == city.read_bytes()
    other = make(SEED + 1, tmp_path / "other")
    assert other.read_bytes() != city.read_bytes()


def test_stage_contents(city):
    stage = Usd.Stage.Open(str(city))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 24 and (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1, 24)
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert stage.GetMetadata("renderSettingsPrimPath") == "/Render/Settings"

    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/main_cam"))
    assert cam and cam.GetFocalLengthAttr().Get() == 35.0
    eye1 = cam.ComputeLocalToWorldTransform(1).ExtractTranslation()
    eye24 = cam.ComputeLocalToWorldTransform(24).ExtractTranslation()
    assert 1.5 < eye1[1] < 2.5 and 0.5 < (eye24 - eye1).GetLength() < 6.0      # street level, a slight dolly

    lights = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Lights"))
    assert len(lights.GetProtoIndicesAttr().Get()) == 1024
    p1, p24 = (np.asarray(lights.GetPositionsAttr().Get(t)) for t in (1, 24))
    assert p1.shape == p24.shape == (1024, 3)
    assert np.all(p1[:, 1] >= 2.0) and np.any(np.linalg.norm(p24 - p1, axis=1) > 0.5)    # above ground, moving
    for target in lights.GetPrototypesRel().GetTargets():
        bulb = stage.GetPrimAtPath(target)
        assert bulb.GetTypeName() == "SphereLight" and bulb.GetAttribute("treatAsPoint").Get() is True
        assert bulb.GetAttribute("inputs:normalize").Get() is False

    tris = stage_triangles(stage)
    assert abs(tris - TRIANGLES) <= 0.15 * TRIANGLES, tris
    instances = [p for p in stage.Traverse() if p.IsInstance()]
    assert instances, "the seed's instanced props"
    buildings = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "/World/City/" in str(p.GetPath())
                 and p.GetName().split("_")[0] in ("box", "tower", "gable")]
    assert buildings and not any(p.IsInstanceProxy() or p.IsInstance() for p in buildings)


def test_delegate_reads_it(city):
    snap = StageDelegate(str(city)).snapshot(1.0)
    assert len(snap.lights) == 1024
    assert snap.camera is not None
    assert abs(snap.triangle_count() - TRIANGLES) <= 0.15 * TRIANGLES
    assert any(p.instance_count > 1 for p in snap.prototypes)
