"""The committed sample stages: what `usdml info` reports, and that the generator reproduces them."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, STAGES
from usdml.cli import main
from usdml.scene import diff
from usdml.stage import StageDelegate

#: stage -> expected info (counted by hand from tools/make_stages.py; triangles after instancing)
EXPECTED = {
    "city": dict(meshes=864, uniqueMeshes=18, triangles=1_043_204, prototypes=5, instances=292,
                 animatedPrototypes=0, deforming=0, lights=1024),
    "planes": dict(meshes=866, uniqueMeshes=19, triangles=1_048_108, prototypes=6, instances=294,
                   animatedPrototypes=1, deforming=0, lights=1024),
    "creature": dict(meshes=2, uniqueMeshes=2, triangles=257_152, prototypes=0, instances=0,
                     animatedPrototypes=0, deforming=1, lights=1024),
    "cornell": dict(meshes=9, uniqueMeshes=9, triangles=1034, prototypes=0, instances=0,
                    animatedPrototypes=0, deforming=0, lights=2),
    "park": dict(meshes=118, uniqueMeshes=9, triangles=17_562, prototypes=5, instances=114,
                 animatedPrototypes=5, deforming=0, lights=7088),
    "dragon": dict(meshes=2, uniqueMeshes=2, triangles=48_082, prototypes=0, instances=0,
                   animatedPrototypes=0, deforming=0, lights=1024),
}
#: the stages of one frame (the others run 1-48)
STILLS = {"cornell", "dragon"}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_sample_stage_info(capsys, name):
    assert main(["info", str(STAGES / f"{name}.usda"), "--json"]) == 0
    out, err = capsys.readouterr()
    info = json.loads(out)
    assert {k: info[k] for k in EXPECTED[name]} == EXPECTED[name]
    assert info["camera"] == "/World/main_cam" and info["warnings"] == []
    assert info["renderSettings"]["path"] == "/Render/Settings"
    assert [v["name"] for v in info["renderSettings"]["products"][0]["vars"]] == [
        "color", "depth", "normal", "direct", "shadow", "primId"]
    assert info["endTimeCode"] == (1 if name in STILLS else 48)
    assert "usdml: warning" not in err


def test_city_is_a_layout_of_instanced_assets_with_instanced_lights():
    d = StageDelegate(STAGES / "city.usda")
    a, b = d.snapshot(1), d.snapshot(2)
    assert all(p.kind == "native" and not p.animated for p in a.prototypes)
    assert a.triangle_count() >= 500_000
    assert (a.lights.instance_ids >= 0).all()                  # every light comes from the PointInstancer
    changes = diff(a, b)
    assert changes.lights and not changes.static and not any(changes.prototypes.values())
    assert not np.allclose(a.lights.position, b.lights.position)


def test_park_is_fully_dynamic_with_moving_rides():
    d = StageDelegate(STAGES / "park.usda")
    assert d.usdml_settings.fully_dynamic
    snap = d.snapshot(10)
    assert sum(p.instance_count for p in snap.prototypes if p.kind == "pointInstancer") >= 100
    assert len({p.path for p in snap.prototypes if p.kind == "pointInstancer"}) >= 3
    assert len(snap.lights) == 7088


def test_planes_move_and_creature_deforms():
    planes = StageDelegate(STAGES / "planes.usda")
    changes = diff(planes.snapshot(1), planes.snapshot(5))
    moving = [p for p, what in changes.prototypes.items() if what]
    assert len(moving) == 1 and changes.prototypes[moving[0]] == {"transforms"}
    creature = StageDelegate(STAGES / "creature.usda")
    changes = diff(creature.snapshot(1), creature.snapshot(5))
    assert len(changes.deforming) == 1 and not changes.static


def test_dragon_stands_on_the_ground_under_a_dome_of_lights():
    snap = StageDelegate(STAGES / "dragon.usda").snapshot(1)
    dragon = next(m for m in snap.meshes if m.path == "/World/Dragon/body")
    lo, hi = dragon.points.min(0), dragon.points.max(0)
    assert hi[0] - lo[0] == pytest.approx(2.0, abs=1e-4) and lo[1] == pytest.approx(0.0, abs=1e-5)
    assert np.all(dragon.normals == dragon.normals[:, :1])        # no authored normals: faceted
    pos = snap.lights.position                                    # the dome is centred on the origin
    distance = np.linalg.norm(pos, axis=1)
    elevation = np.degrees(np.arcsin(pos[:, 1] / distance))
    assert len(pos) == 1024 and 3.0 <= distance.min() and distance.max() <= 5.0
    assert 10.0 <= elevation.min() and elevation.max() <= 70.0


@pytest.mark.slow      # 6 s: regenerates every sample stage
def test_generator_reproduces_the_committed_stages():
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "make_stages.py"), "--check", "--out", str(STAGES)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr


def test_the_stage_check_tolerates_a_last_digit_and_catches_a_moved_point(tmp_path):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from make_stages import CHECK_TOLERANCE, layer_differences
    finally:
        sys.path.pop(0)
    from pxr import Sdf, Vt

    original = STAGES / "boxes.usda"
    layer = Sdf.Layer.FindOrOpen(str(original))
    mesh = next(p for p in _specs(layer) if p.IsPrimPath() and layer.GetPrimAtPath(p).typeName == "Mesh")
    points = layer.GetAttributeAtPath(mesh.AppendProperty("points"))
    base = np.asarray(points.default, np.float64)
    for shift, expected in ((0.5 * CHECK_TOLERANCE, []), (10 * CHECK_TOLERANCE, [f"<{points.path}>.default differs"])):
        copy = Sdf.Layer.CreateAnonymous(".usda")
        copy.TransferContent(layer)
        moved = base.copy()
        moved[0, 0] += shift
        copy.GetAttributeAtPath(points.path).default = Vt.Vec3fArray.FromNumpy(moved.astype(np.float32))
        out = tmp_path / f"boxes_{shift:g}.usda"
        copy.Export(str(out))
        assert layer_differences(str(original), str(out)) == expected


def _specs(layer):
    found = []
    layer.Traverse("/", found.append)
    return found
