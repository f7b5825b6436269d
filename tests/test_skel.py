"""UsdSkel: posed points and normals match UsdSkel.BakeSkinning, on real OpenUSD test stages and a built one."""

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

from conftest import add_cube_mesh
from usdml.render.frame import FrameRenderer
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate


def _baked_world_points(path: str, times: list[float]) -> dict[str, list[np.ndarray]]:
    """Reference: bake skinning into a session layer of a fresh stage and read points back."""
    stage = Usd.Stage.Open(path)
    stage.SetEditTarget(stage.GetSessionLayer())
    assert UsdSkel.BakeSkinning(stage.Traverse())
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            pts = []
            for t in times:
                m = np.array(UsdGeom.XformCache(t).GetLocalToWorldTransform(prim))
                p = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(t), np.float64)
                pts.append(p @ m[:3, :3] + m[3, :3])
            out[str(prim.GetPath())] = pts
    return out


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


def test_built_skinned_mesh_with_blend_shape_matches_bake_skinning(new_stage):
    stage = new_stage(start=1, end=10)
    root = UsdSkel.Root.Define(stage, "/Char")
    UsdGeom.Xformable(root).AddTranslateOp().Set((5, 0, 0))
    skel = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
    joints = ["hip", "hip/knee"]
    skel.CreateJointsAttr(joints)
    rest = Vt.Matrix4dArray([Gf.Matrix4d(1), Gf.Matrix4d().SetTranslate((0, 1, 0))])
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1), Gf.Matrix4d().SetTranslate((0, 1, 0))]))
    skel.CreateRestTransformsAttr(rest)
    anim = UsdSkel.Animation.Define(stage, "/Char/Skel/Anim")
    anim.CreateJointsAttr(joints)
    anim.CreateTranslationsAttr().Set(Vt.Vec3fArray([(0, 0, 0), (0, 1, 0)]))
    anim.CreateScalesAttr().Set(Vt.Vec3hArray([(1, 1, 1), (1, 1, 1)]))
    rot = anim.CreateRotationsAttr()
    for t in (1, 10):
        angle = 0 if t == 1 else 60
        q = Gf.Rotation(Gf.Vec3d(0, 0, 1), angle).GetQuat()
        rot.Set(Vt.QuatfArray([Gf.Quatf(1), Gf.Quatf(q)]), t)
    anim.CreateBlendShapesAttr(["bulge"])
    weights = anim.CreateBlendShapeWeightsAttr()
    weights.Set(Vt.FloatArray([0.0]), 1)
    weights.Set(Vt.FloatArray([1.0]), 10)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    mesh = add_cube_mesh(stage, "/Char/Body", size=0.5)
    mesh.GetPointsAttr().Set([(x, y + 1.5, z) for x, y, z in mesh.GetPointsAttr().Get()])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 2).Set([0, 1] * 8)
    binding.CreateJointWeightsPrimvar(False, 2).Set([0.3, 0.7] * 8)
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    shape = UsdSkel.BlendShape.Define(stage, "/Char/Body/bulge")
    shape.CreateOffsetsAttr([(0.2, 0, 0)] * 2)
    shape.CreatePointIndicesAttr([0, 1])
    binding.CreateBlendShapesAttr(["bulge"])
    binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
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


def _colour(path: Path, time: float, width: int = 64) -> np.ndarray:
    d = StageDelegate(str(path))
    r = FrameRenderer(d, UsdmlSettings())
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
