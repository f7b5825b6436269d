"""PointInstancer and native instancing: one prototype, N transforms, never flattened."""

from dataclasses import replace

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from conftest import add_cube_mesh, instance_world_points
from plain_scenes import mesh
from usdml.scene import Lights, LightType, Prototype, Snapshot, instance_points, world_geometry
from usdml.stage import StageDelegate


def _m(gf) -> np.ndarray:
    return np.array(gf, np.float64).T


def _trs(p, q, s) -> np.ndarray:
    """Column-convention T @ R(q) @ S from a position, a (w, x, y, z) quaternion and a scale."""
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(s)[None, :]
    m[:3, 3] = p
    return m


def _point_instancer_stage(new_stage, orientation_attr="orientations"):
    stage = new_stage(start=1, end=2)
    pi = UsdGeom.PointInstancer.Define(stage, "/World/pi")
    UsdGeom.Xformable(pi).AddTranslateOp().Set((0, 0, 5))
    root = UsdGeom.Xform.Define(stage, "/World/pi/protos/arrow")
    root.AddTranslateOp().Set((0, 1, 0))                       # prototype root xform: applied per instance
    inner = UsdGeom.Xform.Define(stage, "/World/pi/protos/arrow/inner")
    inner.AddScaleOp().Set((2, 2, 2))
    box = add_cube_mesh(stage, "/World/pi/protos/arrow/inner/box")
    box.AddTranslateOp().Set((1, 0, 0))
    add_cube_mesh(stage, "/World/pi/protos/other")
    pi.CreatePrototypesRel().SetTargets(["/World/pi/protos/arrow", "/World/pi/protos/other"])
    pos = [(0, 0, 0), (10, 0, 0), (0, 10, 0), (5, 5, 5)]
    quats = [(1, 0, 0, 0), (0.7071, 0, 0.7071, 0), (0.5, 0.5, 0.5, 0.5), (0, 0, 0, 1)]
    pi.CreatePositionsAttr().Set(pos, 1)
    pi.CreateVelocitiesAttr().Set([(24, 0, 0), (0, 48, 0), (0, 0, 0), (0, 0, -24)], 1)
    if orientation_attr == "orientations":
        pi.CreateOrientationsAttr().Set([Gf.Quath(*q) for q in quats])
    else:
        pi.CreateOrientationsfAttr().Set([Gf.Quatf(*q) for q in quats])
    pi.CreateScalesAttr().Set([(1, 1, 1), (0.5, 0.5, 0.5), (1, 2, 3), (1, 1, 1)])
    pi.CreateProtoIndicesAttr().Set([0, 0, 1, 0])
    pi.CreateIdsAttr().Set([10, 11, 12, 13])
    pi.CreateInvisibleIdsAttr().Set([13])
    stage.Save()
    return stage, pos, quats


@pytest.mark.parametrize("orientation_attr", ["orientations", "orientationsf"])
def test_point_instancer_transforms_velocities_and_invisible_ids(new_stage, orientation_attr):
    stage, pos, quats = _point_instancer_stage(new_stage, orientation_attr)
    d = StageDelegate(stage.GetRootLayer().realPath)
    snap = d.snapshot(1.5)
    assert snap.meshes == []
    by = {p.path: p for p in snap.prototypes}
    arrow, other = by["/World/pi/protos/arrow"], by["/World/pi/protos/other"]
    assert arrow.kind == "pointInstancer" and arrow.animated
    assert arrow.instance_ids.tolist() == [10, 11]            # 13 is invisible, 12 uses the other prototype
    assert other.instance_ids.tolist() == [12]
    assert arrow.instancers == ["/World/pi", "/World/pi"]
    # the prototype keeps its nested xforms, in prototype space (relative to the prototype root)
    local = arrow.meshes[0].points
    assert np.allclose(local.min(0), [1, -1, -1]) and np.allclose(local.max(0), [3, 1, 1])
    dt = 0.5 / 24.0                                            # velocities are per second
    scales = [(1, 1, 1), (0.5, 0.5, 0.5)]
    vel = [(24, 0, 0), (0, 48, 0)]
    for i in range(2):
        p = np.asarray(pos[i]) + np.asarray(vel[i]) * dt
        expected = (np.array(_m(Gf.Matrix4d().SetTranslate((0, 0, 5)))) @ _trs(p, np.array(quats[i]), scales[i])
                    @ _m(Gf.Matrix4d().SetTranslate((0, 1, 0))))
        assert np.allclose(arrow.xforms[i], expected, atol=2e-3)   # quath has ~3 decimal digits
    world = instance_world_points(arrow)
    assert world.shape == (2, 8, 3)


def test_angular_velocities_and_accelerations(new_stage):
    stage = new_stage(start=1, end=2)
    pi = UsdGeom.PointInstancer.Define(stage, "/pi")
    add_cube_mesh(stage, "/pi/protos/box")
    pi.CreatePrototypesRel().SetTargets(["/pi/protos/box"])
    pi.CreatePositionsAttr().Set([(0, 0, 0)], 1)
    pi.CreateVelocitiesAttr().Set([(0, 0, 0)], 1)                   # USD applies accelerations with velocities
    pi.CreateAccelerationsAttr().Set([(0, -9.8 * 24 * 24, 0)], 1)   # scene units per second squared
    pi.CreateOrientationsAttr().Set([Gf.Quath(1, 0, 0, 0)], 1)       # USD spins authored orientations only
    pi.CreateAngularVelocitiesAttr().Set([(0, 2160, 0)], 1)         # degrees per second
    pi.CreateProtoIndicesAttr([0])
    stage.Save()
    (proto,) = StageDelegate(stage.GetRootLayer().realPath).snapshot(1.5).prototypes
    dt = 0.5 / 24
    assert proto.animated
    assert np.allclose(proto.xforms[0, :3, 3], [0, -0.5 * 9.8 * 24 * 24 * dt * dt, 0], atol=1e-9)
    c = np.cos(np.radians(45))
    assert np.allclose(proto.xforms[0, :3, :3], [[c, 0, c], [0, 1, 0], [-c, 0, c]], atol=1e-3)


def test_native_instances_share_one_prototype(new_stage, tmp_path):
    asset = Usd.Stage.CreateNew(str(tmp_path / "asset.usda"))
    root = UsdGeom.Xform.Define(asset, "/Asset")
    asset.SetDefaultPrim(root.GetPrim())
    add_cube_mesh(asset, "/Asset/geo").AddTranslateOp().Set((0, 0.5, 0))
    asset.Save()
    stage = new_stage()
    for i in range(3):
        prim = stage.DefinePrim(f"/World/inst{i}", "Xform")
        prim.GetReferences().AddReference("./asset.usda")
        prim.SetInstanceable(True)
        UsdGeom.Xformable(prim).AddTranslateOp().Set((3.0 * i, 0, 0))
    flat = stage.DefinePrim("/World/unique", "Xform")
    flat.GetReferences().AddReference("./asset.usda")
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    assert [m.path for m in snap.meshes] == ["/World/unique/geo"]
    (proto,) = snap.prototypes
    assert proto.kind == "native" and not proto.animated and proto.instance_count == 3
    assert proto.instancers == ["/World/inst0", "/World/inst1", "/World/inst2"]
    assert snap.triangle_count() == 4 * 12 and snap.unique_triangle_count() == 2 * 12
    # same world geometry as USD's instance proxies
    xf = UsdGeom.XformCache(0)
    for i, world in enumerate(instance_world_points(proto)):
        proxy = stage.GetPrimAtPath(f"/World/inst{i}/geo")
        assert proxy.IsInstanceProxy()
        m = np.array(xf.GetLocalToWorldTransform(proxy))
        p = np.asarray(UsdGeom.Mesh(proxy).GetPointsAttr().Get(), np.float64) @ m[:3, :3] + m[3, :3]
        assert np.allclose(np.sort(world, 0), np.sort(p, 0), atol=1e-6)


def test_nested_instancing_composes_transforms(new_stage, tmp_path):
    """A PointInstancer whose prototype is an instanceable prim, inside an instanceable asset."""
    asset = Usd.Stage.CreateNew(str(tmp_path / "tree.usda"))
    asset.SetDefaultPrim(UsdGeom.Xform.Define(asset, "/Tree").GetPrim())
    add_cube_mesh(asset, "/Tree/trunk")
    asset.Save()
    forest = Usd.Stage.CreateNew(str(tmp_path / "forest.usda"))
    forest.SetDefaultPrim(UsdGeom.Xform.Define(forest, "/Forest").GetPrim())
    pi = UsdGeom.PointInstancer.Define(forest, "/Forest/pi")
    tree = forest.DefinePrim("/Forest/pi/protos/tree", "Xform")
    tree.GetReferences().AddReference("./tree.usda")
    tree.SetInstanceable(True)
    pi.CreatePrototypesRel().SetTargets([tree.GetPath()])
    pi.CreatePositionsAttr([(0, 0, 0), (10, 0, 0)])
    pi.CreateProtoIndicesAttr([0, 0])
    forest.Save()
    stage = new_stage()
    for i in range(2):
        prim = stage.DefinePrim(f"/World/forest{i}", "Xform")
        prim.GetReferences().AddReference("./forest.usda")
        prim.SetInstanceable(True)
        UsdGeom.Xformable(prim).AddTranslateOp().Set((0, 0, 100.0 * i))
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    (proto,) = snap.prototypes          # the tree: 2 forests x 2 trees, geometry stored once
    assert proto.instance_count == 4 and proto.triangle_count == 12
    centers = sorted(map(tuple, np.round(instance_world_points(proto).mean(1), 6)))
    assert centers == [(0, 0, 0), (0, 0, 100), (10, 0, 0), (10, 0, 100)]


def test_lights_instanced_by_a_point_instancer(new_stage):
    stage = new_stage()
    pi = UsdGeom.PointInstancer.Define(stage, "/World/lights")
    UsdGeom.Xformable(pi).AddTranslateOp().Set((0, 10, 0))
    bulb = UsdLux.SphereLight.Define(stage, "/World/lights/protos/bulb")
    bulb.CreateRadiusAttr(0.1)
    bulb.CreateTreatAsPointAttr(True)
    bulb.CreateIntensityAttr(100)
    pi.CreatePrototypesRel().SetTargets([bulb.GetPath()])
    n = 1000
    rng = np.random.default_rng(1)
    pos = rng.uniform(-50, 50, (n, 3))
    pi.CreatePositionsAttr(pos.tolist())
    pi.CreateProtoIndicesAttr([0] * n)
    pi.CreateInvisibleIdsAttr([3])
    add_cube_mesh(stage, "/World/ground")
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    lights = snap.lights
    assert len(lights) == n - 1 and snap.prototypes == []
    assert (lights.type == LightType.POINT).all()
    keep = np.arange(n) != 3
    assert np.allclose(lights.position, pos[keep] + [0, 10, 0], atol=1e-4)   # point3f positions
    assert lights.instance_ids.tolist() == np.arange(n)[keep].tolist()
    assert np.allclose(lights.intensity, 100 * np.pi * 0.01)


def test_light_inside_a_native_prototype_is_one_light_per_instance(new_stage, tmp_path):
    asset = Usd.Stage.CreateNew(str(tmp_path / "lamp.usda"))
    asset.SetDefaultPrim(UsdGeom.Xform.Define(asset, "/Lamp").GetPrim())
    add_cube_mesh(asset, "/Lamp/post", size=0.2)
    UsdLux.SphereLight.Define(asset, "/Lamp/bulb").AddTranslateOp().Set((0, 2, 0))
    asset.Save()
    stage = new_stage()
    for i in range(4):
        prim = stage.DefinePrim(f"/World/lamp{i}", "Xform")
        prim.GetReferences().AddReference("./lamp.usda")
        prim.SetInstanceable(True)
        UsdGeom.Xformable(prim).AddTranslateOp().Set((i, 0, 0))
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    assert len(snap.lights) == 4
    assert sorted(snap.lights.position[:, 0]) == [0, 1, 2, 3] and np.allclose(snap.lights.position[:, 1], 2)


def test_prototypes_defined_under_an_over_are_drawn_only_as_instances(new_stage):
    """The usdImaging pattern: PointInstancer prototypes as `def`s under an `over`, hidden from traversal."""
    stage = new_stage()
    pi = UsdGeom.PointInstancer.Define(stage, "/World/pi")
    add_cube_mesh(stage, "/World/pi/hidden/box")
    add_cube_mesh(stage, "/World/pi/hidden/box/extra/ghost")
    for over in ("/World/pi/hidden", "/World/pi/hidden/box/extra"):   # Define made them defs
        stage.GetPrimAtPath(over).SetSpecifier(Sdf.SpecifierOver)
    assert not stage.GetPrimAtPath("/World/pi/hidden/box").IsDefined()
    pi.CreatePrototypesRel().SetTargets(["/World/pi/hidden/box"])
    pi.CreatePositionsAttr([(0, 0, 0), (3, 0, 0), (6, 0, 0)])
    pi.CreateProtoIndicesAttr([0, 0, 0])
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    assert snap.meshes == []
    (proto,) = snap.prototypes
    assert proto.instance_count == 3 and [m.path for m in proto.meshes] == ["/World/pi/hidden/box"]


def test_world_geometry_flattens_instances_mesh_major():
    tri = mesh("/tri", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)], 0)
    quad = mesh("/quad", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [(0, 1, 2), (0, 2, 3)], 1)
    ground = mesh("/ground", [(-5, 0, -5), (5, 0, -5), (0, 0, 5)], [(0, 2, 1)], 2)
    xforms = np.stack([_trs(p, np.array(q), s) for p, q, s in (
        ((0, 0, 0), (1, 0, 0, 0), (1, 1, 1)), ((3, 0, 0), (0.7071, 0, 0.7071, 0), (2, 2, 2)),
        ((0, 4, 1), (0.5, 0.5, 0.5, 0.5), (1, 2, 3)))])
    proto = Prototype(path="/protos/p", name="/pi", kind="pointInstancer", meshes=[tri, quad], xforms=xforms,
                      instance_ids=np.arange(3, dtype=np.int64), instancers=["/pi"] * 3)
    snap = Snapshot(time=1.0, stage_path="", meshes=[ground], prototypes=[proto], lights=Lights.empty(),
                    camera=None, render_settings=None, mesh_paths=["/tri", "/quad", "/ground"])

    points, triangles = world_geometry(snap, (("mesh", "/ground"), ("proto", "/protos/p")))
    assert points.dtype == np.float32 and triangles.dtype == np.int32
    assert points.shape == (3 + 3 * 3 + 3 * 4, 3) and triangles.shape == (1 + 3 * 1 + 3 * 2, 3)
    expected = [ground.points[ground.triangles[0]]]
    for m in (tri, quad):                       # mesh-major: every instance of one mesh, then the next mesh
        for xf in xforms:
            h = np.c_[m.points.astype(np.float64), np.ones(len(m.points))] @ xf.T
            expected += list(h[:, :3][m.triangles])
    assert np.allclose(points[triangles], np.array(expected), atol=1e-5)
    assert np.allclose(instance_points(xforms, quad.points), instance_world_points(proto, 1))

    local = world_geometry(replace(snap, prototypes=[replace(proto, xforms=np.eye(4)[None])]),
                           (("proto", "/protos/p"),))
    assert all(np.array_equal(a, b) for a, b in zip(local, proto.merged()))
    empty = world_geometry(snap, ())
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)


def test_primids_of_native_instances_are_the_same_in_every_process():
    """USD names native prototypes (/__Prototype_N) in an order that changes between processes; the
    primIds must not (a farm's frames, or a re-render, would disagree). Measured on the city before the
    fix: four processes, four different primId maps."""
    import subprocess
    import sys

    from conftest import STAGES

    script = ("import sys\n"
              "from usdml.stage import StageDelegate\n"
              "d = StageDelegate(sys.argv[1])\n"
              "first = {str(p.GetPath()): min(str(i.GetPath()) for i in p.GetInstances()) "
              "for p in d.stage.GetPrototypes()}\n"
              "snap = d.snapshot(d.start_time)\n"
              "for proto in snap.prototypes:\n"
              "    for m in proto.meshes:\n"
              "        root = '/' + m.path.split('/')[1]\n"
              "        print(m.id, first.get(root, root) + m.path[len(root):])\n")
    maps = {subprocess.run([sys.executable, "-c", script, str(STAGES / "city.usda")], capture_output=True,
                           text=True, check=True).stdout for _ in range(3)}
    assert len(maps) == 1 and len(next(iter(maps)).splitlines()) > 5
