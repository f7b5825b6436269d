"""Meshes: triangulation, primvars, orientation, visibility and purpose, transforms."""

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, Vt

from conftest import add_cube_mesh, add_quad, world_points
from usdml.stage import StageDelegate


def _geometric_normals(mesh):
    p = mesh.points.astype(np.float64)
    t = mesh.triangles
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_ngons_are_fan_triangulated(new_stage):
    stage = new_stage()
    mesh = UsdGeom.Mesh.Define(stage, "/m")
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (3, 0, 0), (3.5, 1, 0), (2.5, 2, 0), (2, 1, 0)]
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr([4, 5])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5, 6, 7, 8])
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    (m,) = snap.meshes
    assert m.triangles.shape == (2 + 3, 3)
    assert m.face_index.tolist() == [0, 0, 1, 1, 1]
    assert m.triangles[:2].tolist() == [[0, 1, 2], [0, 2, 3]]
    # the triangles cover the polygons' area exactly (both polygons are convex)
    area = 0.5 * np.linalg.norm(np.cross(*(m.points[m.triangles[:, k]] - m.points[m.triangles[:, 0]] for k in (1, 2))), axis=1)
    assert area[:2].sum() == pytest.approx(1.0)
    assert np.allclose(_geometric_normals(m), [0, 0, 1])


def test_bad_faces_are_dropped_with_a_warning_naming_the_prim(new_stage, warnings_log):
    stage = new_stage()
    mesh = UsdGeom.Mesh.Define(stage, "/bad")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3, 3, 2, 3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 0, 2, 3, 0, 1, 0, 1, 9])
    mesh.CreateHoleIndicesAttr([1])
    stage.Save()
    (m,) = StageDelegate(stage.GetRootLayer().realPath).snapshot(0).meshes
    assert m.face_index.tolist() == [0]
    text = warnings_log.text
    assert "/bad" in text and "hole" in text and "outside the 4 points" in text and "fewer than 3" in text


def test_inconsistent_topology_skips_the_mesh(new_stage, warnings_log):
    stage = new_stage()
    add_cube_mesh(stage, "/good")
    mesh = UsdGeom.Mesh.Define(stage, "/broken")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    assert [m.path for m in snap.meshes] == ["/good"]
    assert "/broken" in warnings_log.text


def test_attributes_authored_with_the_wrong_type_are_ignored_with_a_warning(tmp_path, warnings_log):
    """As usd-wg's schemaTests (pointsTypes.usda, normalsTypes.usda) author them: ``int normals = 7``,
    ``float3 points = (0, 0, 1)``. They used to end the render with a traceback."""
    cube = ("point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]\n"
            "        int[] faceVertexIndices = [0, 1, 2, 3]\n")
    path = tmp_path / "types.usda"
    path.write_text(f"""#usda 1.0
def Mesh "normals_int" {{
        {cube}        int[] faceVertexCounts = [4]
        int normals = 7
        uniform token subdivisionScheme = "none"
}}
def Mesh "points_float3" {{
        float3 points = (0, 0, 1)
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 0, 0]
}}
def Mesh "counts_float" {{
        {cube}        float faceVertexCounts = 4
}}
""")
    snap = StageDelegate(str(path)).snapshot(0)
    (m,) = snap.meshes
    assert m.path == "/normals_int" and m.triangle_count == 2     # smooth normals computed instead
    assert np.isfinite(m.normals).all()
    text = warnings_log.text
    assert "/normals_int.normals: authored as int, not an array of 3-vectors; ignored" in text
    assert "/points_float3.points: authored as Vec3f" in text and "/points_float3: mesh has no points" in text
    assert "/counts_float.faceVertexCounts: authored as float, not an array of numbers" in text


def test_left_handed_meshes_are_rewound_and_mirrors_keep_outward_normals(new_stage):
    stage = new_stage()
    a = add_quad(stage, "/right")
    b = add_quad(stage, "/left")
    b.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    c = add_quad(stage, "/mirrored")
    UsdGeom.Xformable(c).AddScaleOp().Set((1, 1, -1))
    stage.Save()
    snap = StageDelegate(stage.GetRootLayer().realPath).snapshot(0)
    by = {m.path: m for m in snap.meshes}
    # the quad is counter-clockwise seen from +Y: right-handed normal +Y, left-handed -Y
    assert np.allclose(_geometric_normals(by["/right"]), [0, 1, 0])
    assert np.allclose(_geometric_normals(by["/left"]), [0, -1, 0])
    assert by["/left"].orientation == "leftHanded"
    # a mirror keeps the inverse-transpose normal: diag(1, 1, -1) maps +Y to +Y
    assert np.allclose(_geometric_normals(by["/mirrored"]), [0, 1, 0])
    for m in snap.meshes:   # computed shading normals agree with the geometric ones
        assert np.allclose(m.normals, _geometric_normals(m)[:, None], atol=1e-6)


@pytest.mark.parametrize("interp,values,expected", [
    ("constant", [(1, 0, 0)], [[1, 0, 0]] * 9),
    ("uniform", [(1, 0, 0), (0, 1, 0)], [[1, 0, 0]] * 6 + [[0, 1, 0]] * 3),
    ("vertex", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), (0, 0, 0)], None),
    ("faceVarying", [(i / 10, 0, 0) for i in range(7)], None),
])
def test_display_color_interpolations(new_stage, interp, values, expected):
    stage = new_stage()
    mesh = UsdGeom.Mesh.Define(stage, "/m")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0)])
    mesh.CreateFaceVertexCountsAttr([4, 3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 2])
    mesh.CreateDisplayColorPrimvar(interp).Set(values)
    stage.Save()
    (m,) = StageDelegate(stage.GetRootLayer().realPath).snapshot(0).meshes
    got = m.albedo.reshape(-1, 3)
    if interp == "vertex":
        expected = np.asarray(values)[m.triangles.reshape(-1)]
    if interp == "faceVarying":
        corners = [0, 1, 2, 0, 2, 3, 4, 5, 6]   # fan corners of face 0, then face 1
        expected = np.asarray(values)[corners]
    assert np.allclose(got, np.asarray(expected, np.float32))


def test_indexed_display_color_and_default_albedo(new_stage):
    stage = new_stage()
    m1 = add_quad(stage, "/indexed")
    pv = m1.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
    pv.Set([(1, 0, 0), (0, 0, 1)])
    pv.SetIndices(Vt.IntArray([0, 1, 1, 0]))
    add_quad(stage, "/plain", y=1)
    stage.Save()
    by = {m.path: m for m in StageDelegate(stage.GetRootLayer().realPath).snapshot(0).meshes}
    assert np.allclose(by["/indexed"].albedo[0], [(1, 0, 0), (0, 0, 1), (0, 0, 1)])
    assert np.allclose(by["/plain"].albedo, 0.18)


def test_authored_normals_vertex_and_face_varying_follow_the_transform(new_stage):
    stage = new_stage()
    a = add_quad(stage, "/vertex")
    a.CreateNormalsAttr([(0, 1, 0)] * 4)
    a.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    UsdGeom.Xformable(a).AddRotateZOp().Set(90)
    b = add_quad(stage, "/fv")
    UsdGeom.PrimvarsAPI(b).CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray,
                                         UsdGeom.Tokens.faceVarying).Set([(0, 1, 0), (1, 0, 0), (0, 0, 1), (0, 1, 0)])
    UsdGeom.Xformable(b).AddScaleOp().Set((1, 2, 1))
    for m in (a, b):
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    stage.Save()
    by = {m.path: m for m in StageDelegate(stage.GetRootLayer().realPath).snapshot(0).meshes}
    assert np.allclose(by["/vertex"].normals, [-1, 0, 0], atol=1e-6)
    assert np.allclose(by["/fv"].normals[0], [(0, 1, 0), (1, 0, 0), (0, 0, 1)], atol=1e-6)
    assert np.allclose(np.linalg.norm(by["/fv"].normals, axis=-1), 1)


@pytest.mark.parametrize("scheme", [None, "catmullClark", "loop", "bilinear"])
def test_subdivision_meshes_ignore_authored_normals_as_usdimaging(new_stage, scheme):
    """usdImaging's mesh adapter reads normals only when subdivisionScheme is "none" (the schema default
    is catmullClark): a subdivision quad with bogus authored normals shades with its geometric normal."""
    stage = new_stage()
    m = add_quad(stage, "/quad")
    m.CreateNormalsAttr([(1, 0, 0)] * 4)
    if scheme is not None:
        m.CreateSubdivisionSchemeAttr(scheme)
    stage.Save()
    (mesh,) = StageDelegate(stage.GetRootLayer().realPath).snapshot(0).meshes
    np.testing.assert_allclose(mesh.normals.reshape(-1, 3), [[0, 1, 0]] * 6, atol=1e-6)


def test_visibility_activation_and_purpose(new_stage):
    stage = new_stage()
    add_quad(stage, "/kept")
    add_quad(stage, "/render").GetPurposeAttr().Set(UsdGeom.Tokens.render)
    add_quad(stage, "/guide").GetPurposeAttr().Set(UsdGeom.Tokens.guide)
    add_quad(stage, "/proxy").GetPurposeAttr().Set(UsdGeom.Tokens.proxy)
    UsdGeom.Xform.Define(stage, "/hidden").MakeInvisible()
    add_quad(stage, "/hidden/child")
    add_quad(stage, "/inactive").GetPrim().SetActive(False)
    g = UsdGeom.Xform.Define(stage, "/guides")
    g.GetPurposeAttr().Set(UsdGeom.Tokens.guide)
    add_quad(stage, "/guides/inherits_guide")
    anim = add_quad(stage, "/blinking")
    anim.GetVisibilityAttr().Set(UsdGeom.Tokens.invisible, 2)
    anim.GetVisibilityAttr().Set(UsdGeom.Tokens.inherited, 1)
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    assert sorted(m.path for m in d.snapshot(1).meshes) == ["/blinking", "/kept", "/render"]
    assert sorted(m.path for m in d.snapshot(2).meshes) == ["/kept", "/render"]


def test_time_sampled_transforms_make_a_rigid_prototype(new_stage):
    stage = new_stage(start=1, end=3)
    xf = UsdGeom.Xform.Define(stage, "/mover")
    op = xf.AddTranslateOp()
    for t in (1, 2, 3):
        op.Set((t * 2.0, 0, 0), t)
    xf.AddRotateYOp().Set(30)
    add_cube_mesh(stage, "/mover/box")
    add_quad(stage, "/ground", size=10)
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    for t in (1, 2.5, 3):
        snap = d.snapshot(t)
        assert [m.path for m in snap.meshes] == ["/ground"] and not snap.meshes[0].deforming
        (p,) = snap.prototypes
        assert p.kind == "rigid" and p.animated and p.instance_count == 1
        got = p.meshes[0].points @ p.xforms[0, :3, :3].T + p.xforms[0, :3, 3]
        assert np.allclose(got, world_points(stage, "/mover/box", t), atol=1e-5)


def test_time_sampled_points_are_deforming(new_stage):
    stage = new_stage(start=1, end=2)
    m = add_quad(stage, "/wave")
    m.GetPointsAttr().Set([(0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0)], 1)
    m.GetPointsAttr().Set([(0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 0)], 2)
    stage.Save()
    d = StageDelegate(stage.GetRootLayer().realPath)
    a, b = d.snapshot(1).meshes[0], d.snapshot(1.5).meshes[0]
    assert a.deforming and b.deforming
    assert np.allclose(b.points[0], [0, 0.5, 0])


def test_purposes_override_and_unsupported_prims(new_stage, warnings_log, capsys):
    import json
    from usdml.cli import main

    stage = new_stage()
    add_quad(stage, "/kept")
    add_quad(stage, "/proxy").GetPurposeAttr().Set(UsdGeom.Tokens.proxy)
    add_quad(stage, "/render").GetPurposeAttr().Set(UsdGeom.Tokens.render)
    curves = UsdGeom.BasisCurves.Define(stage, "/hair")
    curves.CreatePointsAttr([(0, 0, 0), (0, 1, 0), (0, 2, 0), (0, 3, 0)])
    curves.CreateCurveVertexCountsAttr([4])
    UsdGeom.Points.Define(stage, "/dust1")
    UsdGeom.Points.Define(stage, "/dust2")
    stage.Save()
    path = stage.GetRootLayer().realPath
    assert sorted(m.path for m in StageDelegate(path, purposes=["proxy"]).snapshot(0).meshes) == ["/kept", "/proxy"]
    assert main(["info", path, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["unsupported"] == {"BasisCurves": 1, "Points": 2} and info["meshes"] == 2
    assert sum("Points prims are not rendered" in w for w in info["warnings"]) == 1   # once per type


def test_implicit_detail_is_settable(new_stage):
    stage = new_stage()
    UsdGeom.Sphere.Define(stage, "/ball")
    stage.Save()
    path = stage.GetRootLayer().realPath
    coarse = StageDelegate(path).snapshot(0).meshes[0].triangle_count
    fine = StageDelegate(path, implicit_detail=40).snapshot(0).meshes[0].triangle_count
    assert coarse == 10 * 5 * 2 - 2 * 10 and fine > 10 * coarse
