"""Shading and geometric normals: polygonal meshes shade faceted, and whatever the shading normal,
only lights in front of the surface light it (issue 18, item 1).

References are closed forms of the stage's own numbers: face normals from the authored points, and
``E = I · max(0, n_s·ω) / d²`` with the authored (tilted) normal, written here without usdml's code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from conftest import add_cube_mesh, add_quad
from usdml.render.frame import FrameRenderer
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate

ALBEDO = 0.5


@pytest.mark.parametrize("scheme, faceted", [("none", True), ("catmullClark", False), (None, False)])
def test_polygonal_meshes_shade_faceted_and_subdivision_meshes_smooth(new_stage, scheme, faceted):
    stage = new_stage(start=1, end=1)
    box = add_cube_mesh(stage, "/World/box", size=2)
    if scheme is not None:
        box.CreateSubdivisionSchemeAttr(scheme)
    stage.Save()
    mesh = StageDelegate(stage.GetRootLayer().realPath).snapshot(1).meshes[0]
    p = mesh.points.astype(np.float64)[mesh.triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    along_face = np.einsum("tcj,tj->tc", mesh.normals.astype(np.float64), face)
    if faceted:
        assert np.allclose(along_face, 1.0, atol=1e-6)
    else:       # one normal per point, shared by every face around it, leaning off each face
        by_point = {}
        for v, n in zip(mesh.triangles.ravel(), mesh.normals.reshape(-1, 3)):
            by_point.setdefault(int(v), []).append(n)
        assert all(np.allclose(ns, ns[0], atol=1e-6) for ns in by_point.values())
        assert (along_face > 0.4).all() and (along_face < 0.82).all()


def _tilted_ground(new_stage, lights):
    """A 40 × 40 ground at y = 0 whose authored normals lean 81° from its face toward +X, seen from
    straight above, lit by ``lights``: ``{name: (position, intensity)}`` treatAsPoint sphere lights."""
    stage = new_stage(start=1, end=1)
    ground = add_quad(stage, "/World/ground", size=40)
    ground.CreateSubdivisionSchemeAttr("none")
    tilt = np.array([1.0, 0.15, 0.0]) / math.hypot(1.0, 0.15)
    ground.CreateNormalsAttr([Gf.Vec3f(*tilt)] * 4)
    ground.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    ground.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(18)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(36)
    cam.AddTranslateOp().Set((0, 15, 0))
    cam.AddRotateXOp().Set(-90)
    for name, (pos, intensity) in lights.items():
        s = UsdLux.SphereLight.Define(stage, f"/World/{name}")
        s.CreateTreatAsPointAttr(True)
        s.CreateIntensityAttr(intensity)
        s.AddTranslateOp().Set(Gf.Vec3d(*pos))
    stage.Save()
    return stage.GetRootLayer().realPath, tilt


def _render(path, visibility):
    d = StageDelegate(path)
    settings = UsdmlSettings(visibility=visibility, voxel_resolution=32, direction_step=6.0, pixel_samples=1)
    r = FrameRenderer(d, settings)
    try:
        return r.render(d.start_time, 48, 48, {"direct", "P", "shadow", "lightCount", "normal"}).buffers
    finally:
        r.close()


@pytest.mark.parametrize("visibility", ["exact", "voxel"])
def test_a_light_behind_the_surface_never_lights_it_through_a_tilted_normal(new_stage, visibility):
    # below the ground, but in front of the tilted shading normal wherever x < 5 - 3·0.15/0.989
    path, _ = _tilted_ground(new_stage, {"below": ((5.0, -3.0, 0.0), 1000.0)})
    b = _render(path, visibility)
    on_ground = np.abs(b["P"][..., 1]) < 1e-4
    assert on_ground.mean() > 0.9
    assert (b["lightCount"][on_ground] == 0).all()
    assert (b["shadow"][on_ground] == 0).all()
    assert (b["direct"][on_ground] == 0).all()


@pytest.mark.parametrize("visibility", ["exact", "voxel"])
def test_shading_follows_the_tilted_normal_for_lights_in_front(new_stage, visibility):
    light = np.array([6.0, 3.0, 0.0])
    path, tilt = _tilted_ground(new_stage, {"above": (light, 1000.0)})
    b = _render(path, visibility)
    p = b["P"].astype(np.float64)
    on_ground = np.abs(p[..., 1]) < 1e-4
    to_light = light - p
    d2 = (to_light ** 2).sum(-1)
    cos_s = to_light @ tilt / np.sqrt(d2)
    intensity = 1000.0 * math.pi * 0.5 ** 2     # treatAsPoint: I = L·π·r², default radius 0.5
    want = ALBEDO / math.pi * intensity * np.maximum(cos_s, 0.0) / d2
    lit = on_ground & (want > 1e-3 * want.max())
    assert lit.mean() > 0.3 and (on_ground & (cos_s < 0)).sum() > 50
    got = b["direct"][..., 0].astype(np.float64)
    assert np.abs(got[lit] - want[lit]).max() <= 2e-3 * want[lit].max()
    # behind the shading normal but in front of the face: faces nothing, adds nothing, is not shadowed
    dark = on_ground & (cos_s < 0)
    assert (got[dark] == 0).all() and (b["lightCount"][dark] == 0).all() and (b["shadow"][on_ground] == 0).all()
    # the normal AOV is the shading normal on the camera's side of the face
    assert np.allclose(b["normal"][on_ground], tilt, atol=1e-5)
