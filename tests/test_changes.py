"""What changed between two timecodes: per prototype, the static part, deforming meshes, lights."""

import numpy as np
from pxr import UsdGeom, UsdLux

from conftest import add_cube_mesh, add_quad
from usdml.scene import diff
from usdml.stage import StageDelegate


def _scene(new_stage):
    stage = new_stage(start=1, end=3)
    add_quad(stage, "/World/ground", size=20)
    # static instances
    still = UsdGeom.PointInstancer.Define(stage, "/World/rocks")
    add_cube_mesh(stage, "/World/rocks/protos/rock")
    still.CreatePrototypesRel().SetTargets(["/World/rocks/protos/rock"])
    still.CreatePositionsAttr([(0, 0, 0), (3, 0, 0)])
    still.CreateProtoIndicesAttr([0, 0])
    # moving instances
    cars = UsdGeom.PointInstancer.Define(stage, "/World/cars")
    add_cube_mesh(stage, "/World/cars/protos/car")
    cars.CreatePrototypesRel().SetTargets(["/World/cars/protos/car"])
    cars.CreateProtoIndicesAttr([0, 0])
    for t in (1, 2, 3):
        cars.GetPositionsAttr().Set([(t, 0, 5), (-t, 0, 5)], t)
    # deforming mesh
    flag = add_quad(stage, "/World/flag")
    for t in (1, 2, 3):
        flag.GetPointsAttr().Set([(0, 0, 0), (0, 0, 1), (1, 0.1 * t, 1), (1, 0, 0)], t)
    return stage


def test_static_scene_changes_nothing_on_its_second_frame(new_stage):
    stage = new_stage(start=1, end=3)
    add_quad(stage, "/ground", size=20)
    UsdLux.SphereLight.Define(stage, "/lamp")
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    a, b = d.snapshot(1), d.snapshot(2)
    changes = diff(a, b)
    assert not changes.anything
    assert b.meshes[0] is a.meshes[0]            # read once, reused
    first = diff(None, a)
    assert first.static and first.lights and first.camera


def test_moving_instances_change_transforms_only_and_deforming_mesh_its_points(new_stage):
    stage = _scene(new_stage)
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    a, b = d.snapshot(1), d.snapshot(2)
    protos = {p.path: p for p in b.prototypes}
    assert protos["/World/cars/protos/car"].animated and not protos["/World/rocks/protos/rock"].animated
    changes = diff(a, b)
    assert changes.prototypes == {"/World/rocks/protos/rock": set(), "/World/cars/protos/car": {"transforms"}}
    assert changes.deforming == ["/World/flag"]
    assert not changes.static and not changes.lights


def test_moving_lights_change_only_the_lights(new_stage):
    stage = new_stage(start=1, end=2)
    add_quad(stage, "/ground")
    lamp = UsdLux.SphereLight.Define(stage, "/lamp")
    op = lamp.AddTranslateOp()
    op.Set((0, 1, 0), 1)
    op.Set((0, 2, 0), 2)
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    changes = diff(d.snapshot(1), d.snapshot(2))
    assert changes.lights and not changes.static and not changes.deforming and not changes.prototypes


def test_prototype_points_change_inside_a_prototype(new_stage):
    stage = new_stage(start=1, end=2)
    add_quad(stage, "/ground")
    pi = UsdGeom.PointInstancer.Define(stage, "/pi")
    blob = add_quad(stage, "/pi/protos/blob")
    blob.GetPointsAttr().Set([(0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0)], 1)
    blob.GetPointsAttr().Set([(0, 0, 0), (0, 0, 1), (1, 1, 1), (1, 0, 0)], 2)
    pi.CreatePrototypesRel().SetTargets(["/pi/protos/blob"])
    pi.CreatePositionsAttr([(0, 0, 0), (5, 0, 0)])
    pi.CreateProtoIndicesAttr([0, 0])
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    a, b = d.snapshot(1), d.snapshot(2)
    assert b.prototypes[0].deforming
    assert diff(a, b).prototypes == {"/pi/protos/blob": {"points"}}
    assert np.allclose(b.prototypes[0].meshes[0].points[2], [1, 1, 1])
