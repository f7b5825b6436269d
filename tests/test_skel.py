"""UsdSkel: posed points and normals match UsdSkel.BakeSkinning, on real OpenUSD test stages and a built one."""

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdSkel, Vt

from conftest import add_cube_mesh, ground_stage, instance_world_points, world_points
from usdml.render.frame import FrameRenderer
from usdml.scene import diff
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate


#: prims below an ``over`` too (PointInstancer prototypes), as usdml's delegate walks them
_ALL_DEFINED = Usd.PrimIsActive & Usd.PrimIsLoaded & ~Usd.PrimIsAbstract


def _bake_deinstanced(path: str) -> Usd.Stage:
    """Reference: the stage with every instance made uninstanceable and every ``over`` a ``def`` (in its
    session layer: UsdSkel bakes neither instanced SkelRoots nor undefined ones), then
    ``UsdSkel.BakeSkinning``."""
    stage = Usd.Stage.Open(path)
    stage.SetEditTarget(stage.GetSessionLayer())
    for prim in Usd.PrimRange.Stage(stage, _ALL_DEFINED):
        if prim.GetSpecifier() == Sdf.SpecifierOver:
            prim.SetSpecifier(Sdf.SpecifierDef)
    while instances := [p for p in Usd.PrimRange.Stage(stage, _ALL_DEFINED) if p.IsInstance()]:
        for prim in instances:
            prim.SetInstanceable(False)
    assert UsdSkel.BakeSkinning(stage.Traverse())
    return stage


def _baked_world_points(path: str, times: list[float]) -> dict[str, list[np.ndarray]]:
    """Reference: every mesh's world points at ``times`` in :func:`_bake_deinstanced`'s bake."""
    stage = _bake_deinstanced(path)
    return {str(prim.GetPath()): [world_points(stage, str(prim.GetPath()), t) for t in times]
            for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)}


def _check_against_bake(path: str, times: list[float]) -> None:
    reference = _baked_world_points(path, times)
    d = StageDelegate(path)
    moved = False
    for k, t in enumerate(times):
        snap = d.snapshot(t)
        meshes = {m.path: m for m in snap.meshes}
        for mesh_path, ref in reference.items():
            mesh = meshes[mesh_path]
            assert mesh.deforming
            assert np.allclose(mesh.points, ref[k], atol=1e-3 * max(1.0, np.abs(ref[k]).max()))
        moved |= k > 0 and not np.allclose(snap.meshes[0].points, d.snapshot(times[0]).meshes[0].points)
    assert moved, "the skinned mesh should move over these frames"


def test_openusd_lbs_stage_matches_bake_skinning(assets):
    _check_against_bake(str(assets / "openusd/testUsdImagingGLSkelSkinning/test_lbs.usda"), [1, 30, 60.5, 120])


def _animation(stage: Usd.Stage, path: str, angle: float) -> UsdSkel.Animation:
    """A SkelAnimation of :func:`_rig`'s joints: the knee bends ``angle`` degrees about Z from frame 1
    to 10 and the blend shape ``bulge`` swells from 0 to 1."""
    anim = UsdSkel.Animation.Define(stage, path)
    anim.CreateJointsAttr(["hip", "hip/knee"])
    anim.CreateTranslationsAttr().Set(Vt.Vec3fArray([(0, 0, 0), (0, 1, 0)]))
    anim.CreateScalesAttr().Set(Vt.Vec3hArray([(1, 1, 1), (1, 1, 1)]))
    rot = anim.CreateRotationsAttr()
    for t, a in ((1, 0), (10, angle)):
        rot.Set(Vt.QuatfArray([Gf.Quatf(1), Gf.Quatf(Gf.Rotation(Gf.Vec3d(0, 0, 1), a).GetQuat())]), t)
    anim.CreateBlendShapesAttr(["bulge"])
    weights = anim.CreateBlendShapeWeightsAttr()
    weights.Set(Vt.FloatArray([0.0]), 1)
    weights.Set(Vt.FloatArray([1.0]), 10)
    return anim


def _rig(stage: Usd.Stage, root: str, animated: bool = True) -> UsdSkel.Root:
    """A SkelRoot at ``root``: a two-joint Skeleton ``Skel`` skinning a cube ``Body`` (30 % hip, 70 %
    knee) with a blend shape; ``animated`` binds :func:`_animation` (60°) at ``Skel/Anim``."""
    skel_root = UsdSkel.Root.Define(stage, root)
    skel = UsdSkel.Skeleton.Define(stage, f"{root}/Skel")
    skel.CreateJointsAttr(["hip", "hip/knee"])
    rest = Vt.Matrix4dArray([Gf.Matrix4d(1), Gf.Matrix4d().SetTranslate((0, 1, 0))])
    skel.CreateBindTransformsAttr(rest)
    skel.CreateRestTransformsAttr(rest)
    if animated:
        anim = _animation(stage, f"{root}/Skel/Anim", 60)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    mesh = add_cube_mesh(stage, f"{root}/Body", size=0.5)
    mesh.GetPointsAttr().Set([(x, y + 1.5, z) for x, y, z in mesh.GetPointsAttr().Get()])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 2).Set([0, 1] * 8)
    binding.CreateJointWeightsPrimvar(False, 2).Set([0.3, 0.7] * 8)
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    shape = UsdSkel.BlendShape.Define(stage, f"{root}/Body/bulge")
    shape.CreateOffsetsAttr([(0.2, 0, 0)] * 2)
    shape.CreatePointIndicesAttr([0, 1])
    binding.CreateBlendShapesAttr(["bulge"])
    binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
    return skel_root


def test_built_skinned_mesh_with_blend_shape_matches_bake_skinning(new_stage):
    stage = new_stage(start=1, end=10)
    UsdGeom.Xformable(_rig(stage, "/Char")).AddTranslateOp().Set((5, 0, 0))
    add_cube_mesh(stage, "/ground")
    stage.Save()
    path = stage.GetRootLayer().realPath
    reference = _baked_world_points(path, [1, 5, 10])["/Char/Body"]
    d = StageDelegate(path)
    for k, t in enumerate([1, 5, 10]):
        body = next(m for m in d.snapshot(t).meshes if m.path == "/Char/Body")
        assert body.deforming
        assert np.allclose(body.points, reference[k], atol=1e-5)
    assert not np.allclose(reference[0], reference[2])


def test_usdz_rigged_figure_loads_skinned(assets):
    d = StageDelegate(str(assets / "usd-wg/USDZ/RiggedFigure/RiggedFigure.usdz"))
    a, b = d.snapshot(0), d.snapshot(15)
    assert a.meshes and all(m.deforming for m in a.meshes)
    assert not np.allclose(a.meshes[0].points, b.meshes[0].points)


def test_skinned_polygonal_mesh_with_authored_normals_shades_smooth(assets):
    """RiggedFigure (a glTF export: subdivisionScheme none, primvars:normals, skinned): its normals
    come from the posed points, smooth (one per point), not faceted as a normal-less polygon mesh."""
    d = StageDelegate(str(assets / "usd-wg/USDZ/RiggedFigure/RiggedFigure.usdz"))
    mesh = d.snapshot(10).meshes[0]
    p = mesh.points.astype(np.float64)[mesh.triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    keep = np.linalg.norm(face, axis=1) > 0
    face = face[keep] / np.linalg.norm(face[keep], axis=1, keepdims=True)
    along = np.einsum("tcj,tj->tc", mesh.normals[keep].astype(np.float64), face)
    assert (along < 0.9999).mean() > 0.5            # most corners lean off their triangle's plane
    by_point: dict[int, list] = {}
    for v, n in zip(mesh.triangles.ravel(), mesh.normals.reshape(-1, 3)):
        by_point.setdefault(int(v), []).append(n)
    assert all(np.allclose(ns, ns[0], atol=1e-5) for ns in by_point.values())


#: OpenUSD's testUsdImagingGLUsdSkel arm (bogus authored normals) and usdview's bake of it (tests/data/README.md)
ARM = Path(__file__).parent / "data/openusd/arm.usda"
ARM_BAKED = Path(__file__).parent / "data/openusd/arm_baked.usda"


def _colour(path: Path, time: float, width: int = 64, settings: UsdmlSettings | None = None) -> np.ndarray:
    d = StageDelegate(str(path))
    r = FrameRenderer(d, settings or UsdmlSettings())
    try:
        return r.render(time, width, width, {"color"}).buffers["color"][..., :3].astype(np.float64)
    finally:
        r.close()


@pytest.mark.parametrize("time", [1, 7, 10])
def test_skinned_arm_renders_as_its_bake(time):
    """Both stages carry normals (0, 0, 1) that usdImaging ignores: the arm's because it is skinned, the
    bake's because its mesh is a subdivision surface (catmullClark by default). The bake rendered with
    them and differed from the skinned arm by 0.60-0.77 in colour."""
    skinned, baked = _colour(ARM, time), _colour(ARM_BAKED, time)
    assert (baked.sum(-1) > 0).mean() > 0.05            # the arm covers part of the frame
    assert np.abs(skinned - baked).sum() / np.abs(baked).sum() < 1e-3


def _reference_normals(points: np.ndarray, counts, indices) -> np.ndarray:
    """(V, 3) area-weighted vertex normals of fan-triangulated polygons, written out loop by loop."""
    acc = np.zeros_like(points)
    start = 0
    for n in counts:
        face = indices[start:start + n]
        start += n
        for k in range(1, n - 1):
            a, b, c = points[face[0]], points[face[k]], points[face[k + 1]]
            cross = np.cross(b - a, c - a)
            for v in (face[0], face[k], face[k + 1]):
                acc[v] += cross
    return acc / np.linalg.norm(acc, axis=1, keepdims=True)


def test_skinned_arm_normals_follow_the_pose_not_the_authored_ones(tmp_path):
    """Normals of the posed arm equal those of UsdSkel.BakeSkinning's points on a copy of the stage."""
    copy = tmp_path / "arm.usda"
    copy.write_text(ARM.read_text())
    stage = Usd.Stage.Open(str(copy))
    assert UsdSkel.BakeSkinning(stage.Traverse())
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Model/Arm"))
    counts, indices = mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get()
    d = StageDelegate(str(ARM))
    rest = None
    for time in (1, 5, 10):
        baked = np.asarray(mesh.GetPointsAttr().Get(time), np.float64)     # the stage has no transforms
        (posed,) = d.snapshot(time).meshes
        want = _reference_normals(baked, counts, indices)[posed.triangles]
        np.testing.assert_allclose(posed.normals, want, atol=1e-4)
        assert np.abs(posed.normals[..., 2]).min() < 0.9   # not the authored (0, 0, 1)
        rest = want if rest is None else rest
    assert np.abs(want - rest).max() > 0.5               # the pose moved the normals


# ---- skinned meshes inside instance prototypes ---------------------------------------------------

def _instanced_shot(stage: Usd.Stage, tmp_path, instances: dict[str, str | None],
                    animations: dict[str, float] | None = None) -> str:
    """Saves ``stage`` (frames 1 to 10) referencing :func:`_rig` (``asset.usda``'s default prim) on
    one instanceable SkelRoot per ``instances`` key, each placed apart. A value names an animation of
    ``animations`` (path: knee angle) bound as that instance's ``skel:animationSource`` (UsdSkel's
    "bind state" instancing: then the asset has no animation of its own)."""
    asset = Usd.Stage.CreateNew(str(tmp_path / "asset.usda"))
    asset.SetDefaultPrim(_rig(asset, "/Char", animated=not animations).GetPrim())
    asset.Save()
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(10)
    for anim, angle in (animations or {}).items():
        _animation(stage, anim, angle)
    for k, (name, anim) in enumerate(instances.items()):
        prim = stage.DefinePrim(f"/World/{name}")            # typed by the reference: a SkelRoot
        xf = UsdGeom.Xformable(prim)
        xf.AddTranslateOp().Set((3.0 * k, 0.5 * k, -k))
        xf.AddRotateYOp().Set(40.0 * k)
        xf.AddScaleOp().Set((1 + 0.5 * k,) * 3)
        prim.GetReferences().AddReference("asset.usda")
        prim.SetInstanceable(True)
        if anim is not None:
            UsdSkel.BindingAPI.Apply(prim).CreateAnimationSourceRel().SetTargets([anim])
    stage.Save()
    return stage.GetRootLayer().realPath


def _assert_instances_match_bake(path: str, times=(1, 5, 10)) -> list:
    """Every instance's world points of every skinned prototype equal the de-instanced bake's to 1e-5;
    returns the skinned prototypes of each time."""
    reference = _bake_deinstanced(path)
    d = StageDelegate(path)
    out = []
    for t in times:
        skinned = [p for p in d.snapshot(t).prototypes if any(m.path.endswith("/Body") for m in p.meshes)]
        assert skinned
        for p in skinned:
            assert p.deforming and all(m.deforming for m in p.meshes)
            world = instance_world_points(p)
            for i, instance in enumerate(p.instancers):
                np.testing.assert_allclose(world[i], world_points(reference, f"{instance}/Body", t), atol=1e-5)
        out.append(skinned)
    return out


def test_instanced_skinned_mesh_is_one_posed_prototype_matching_bake_skinning(new_stage, tmp_path):
    path = _instanced_shot(new_stage(), tmp_path, {"A": None, "B": None, "C": None})
    frames = _assert_instances_match_bake(path)
    for (proto,) in frames:                    # shared: one prototype, three instances, not flattened
        assert proto.kind == "native" and proto.instance_count == 3 and len(proto.meshes) == 1
        assert sorted(proto.instancers) == ["/World/A", "/World/B", "/World/C"]
    rest, bent = frames[0][0].meshes[0].points, frames[-1][0].meshes[0].points
    assert np.abs(bent - rest).max() > 0.5     # posed, not at rest
    d = StageDelegate(path)
    a, b = d.snapshot(1), d.snapshot(10)
    assert diff(a, b).prototypes[a.prototypes[0].path] == {"points"}


def test_instances_with_their_own_animation_source_share_a_pose_per_animation(new_stage, tmp_path):
    """UsdSkel's bind-state instancing: the instanced asset has no animation; each instance binds its
    own. Instances binding the same animation share one posed prototype."""
    path = _instanced_shot(new_stage(), tmp_path, {"A": "/Anims/Bend", "B": "/Anims/Bend", "C": "/Anims/Wave"},
                           {"/Anims/Bend": 60, "/Anims/Wave": -45})
    *_, bent = _assert_instances_match_bake(path)
    by_instances = {tuple(sorted(p.instancers)): p.meshes[0].points for p in bent}
    assert set(by_instances) == {("/World/A", "/World/B"), ("/World/C",)}
    assert np.abs(by_instances[("/World/A", "/World/B")] - by_instances[("/World/C",)]).max() > 0.5


def test_point_instancer_prototype_skelroot_is_posed_and_shared(new_stage):
    """A PointInstancer prototype that is a SkelRoot, defined under an ``over`` (hidden from the
    plain traversal): posed once in the prototype's space, its instances placed by the instancer."""
    stage = new_stage(start=1, end=10)
    UsdGeom.Xformable(_rig(stage, "/Prototypes/Char")).AddTranslateOp().Set((0.5, 0, 0))
    stage.GetPrimAtPath("/Prototypes").SetSpecifier(Sdf.SpecifierOver)
    pi = UsdGeom.PointInstancer.Define(stage, "/World/crowd")
    pi.AddTranslateOp().Set((0, 0, 2))
    pi.CreatePrototypesRel().SetTargets(["/Prototypes/Char"])
    pi.CreatePositionsAttr().Set([(0, 0, 0), (4, 0, 0), (0, 0, 4)])
    pi.CreateOrientationsAttr().Set([Gf.Quath(1), Gf.Quath(0.7071, 0, 0.7071, 0), Gf.Quath(0, 0, 0, 1)])
    pi.CreateProtoIndicesAttr().Set([0, 0, 0])
    add_cube_mesh(stage, "/World/ground")
    stage.Save()
    path = stage.GetRootLayer().realPath
    reference = _bake_deinstanced(path)
    ref_pi = UsdGeom.PointInstancer(reference.GetPrimAtPath("/World/crowd"))
    body, char = reference.GetPrimAtPath("/Prototypes/Char/Body"), reference.GetPrimAtPath("/Prototypes/Char")
    d = StageDelegate(path)
    for t in (1, 5, 10):
        (proto,) = d.snapshot(t).prototypes
        assert proto.kind == "pointInstancer" and proto.instance_count == 3 and proto.deforming
        xf = UsdGeom.XformCache(t)
        local = np.asarray(UsdGeom.Mesh(body).GetPointsAttr().Get(t), np.float64)
        to_root = np.array(xf.ComputeRelativeTransform(body, char)[0])
        pi_world = np.array(xf.GetLocalToWorldTransform(ref_pi.GetPrim()))
        for i, inst in enumerate(ref_pi.ComputeInstanceTransformsAtTime(t, t)):
            m = to_root @ np.array(inst) @ pi_world
            np.testing.assert_allclose(instance_world_points(proto)[i], local @ m[:3, :3] + m[3, :3], atol=1e-5)
    rest, bent = (d.snapshot(t).prototypes[0].meshes[0].points for t in (1, 10))
    assert np.abs(bent - rest).max() > 0.5


@pytest.mark.parametrize("visibility", ["exact", "voxel"])
def test_instanced_skinned_rigs_render_as_their_bake(new_stage, tmp_path, visibility):
    """The instanced rigs render as the de-instanced stage baked by UsdSkel (flattened to a file of
    time-sampled meshes) does, and bent, not at rest."""
    lit = ground_stage(
        new_stage, lambda s: UsdLux.SphereLight.Define(s, "/World/bulb").AddTranslateOp().Set((2, 6, 1)))
    path = _instanced_shot(Usd.Stage.Open(lit), tmp_path, {"A": None, "B": None, "C": None})
    baked = tmp_path / "baked.usda"
    assert _bake_deinstanced(path).Export(str(baked))
    # the bulb unseen: the rigs' colour is compared, and the bulb's own pixels (L = 1) would outweigh it
    settings = UsdmlSettings(visibility=visibility, voxel_resolution=64, direction_step=5.0, pixel_samples=1,
                             visible_lights=False)
    bent, bent_baked, rest = (_colour(p, t, 48, settings) for p, t in ((path, 10), (baked, 10), (path, 1)))
    assert np.abs(bent - bent_baked).sum() / np.abs(bent_baked).sum() < 1e-3
    assert np.abs(bent - rest).sum() / np.abs(rest).sum() > 0.01
