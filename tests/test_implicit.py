"""Tessellation of implicit gprims (usdml.stage.implicit): shape, winding, normals and bounds."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from usdml.stage.implicit import IMPLICIT_TYPES, PolyMesh, tessellate

T = Usd.TimeCode.Default()
_STAGES: list[Usd.Stage] = []
SCHEMA = {name: getattr(UsdGeom, name) for name in IMPLICIT_TYPES}


def define(kind: str, **attrs) -> Usd.Prim:
    stage = Usd.Stage.CreateInMemory()
    _STAGES.append(stage)                        # a prim expires with its stage
    prim = SCHEMA[kind].Define(stage, f"/{kind}").GetPrim()
    for name, value in attrs.items():
        prim.GetAttribute(name).Set(value)
    return prim


def triangles(mesh: PolyMesh) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate: (T, 3, 3) corner points and (T, 3, 3) corner normals."""
    start = np.concatenate([[0], np.cumsum(mesh.counts)[:-1]])
    corners = [(s, s + k, s + k + 1) for s, c in zip(start, mesh.counts) for k in range(1, c - 1)]
    corners = np.array(corners, np.int64).reshape(-1, 3)
    return mesh.points[mesh.indices[corners]], mesh.normals[corners]


def area(mesh: PolyMesh) -> float:
    p, _ = triangles(mesh)
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def volume(mesh: PolyMesh) -> float:
    """Divergence theorem: positive only if faces wind outward."""
    p, _ = triangles(mesh)
    return np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0


def check_structure(mesh: PolyMesh, closed: bool) -> None:
    assert mesh.points.dtype == np.float64 and mesh.points.shape[1] == 3
    assert mesh.counts.dtype == np.int64 and mesh.indices.dtype == np.int64
    assert mesh.counts.sum() == len(mesh.indices) == len(mesh.normals)
    assert (mesh.counts >= 3).all()
    assert mesh.indices.min() >= 0 and mesh.indices.max() < len(mesh.points)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-12)
    # geometric normal of every (non-degenerate) triangle agrees with all three corner normals
    p, n = triangles(mesh)
    g = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    big = np.linalg.norm(g, axis=1) > 1e-12
    assert big.any()
    assert (np.einsum("ij,ikj->ik", g[big], n[big]) > 0).all()
    if closed:
        # watertight with consistent winding: every directed edge has exactly one reverse twin
        start = np.concatenate([[0], np.cumsum(mesh.counts)[:-1]])
        edges = Counter()
        for s, c in zip(start, mesh.counts):
            f = mesh.indices[s:s + c]
            for a, b in zip(f, np.roll(f, -1)):
                edges[(a, b)] += 1
        assert all(v == 1 for v in edges.values())
        assert all(edges[(b, a)] == 1 for a, b in edges)


def extent(prim: Usd.Prim) -> np.ndarray:
    return np.array(UsdGeom.Boundable.ComputeExtentFromPlugins(UsdGeom.Boundable(prim), T), np.float64)


def bbox(mesh: PolyMesh) -> np.ndarray:
    return np.stack([mesh.points.min(0), mesh.points.max(0)])


def capsule_1_exact(rt, rb, h):
    """Frustum of length h between rb and rt with spherical caps tangent to it at its ends."""
    a = math.atan((rb - rt) / h)
    big_t, big_b = rt / math.cos(a), rb / math.cos(a)
    cap_t, cap_b = big_t * (1 - math.sin(a)), big_b * (1 + math.sin(a))   # cap heights (sagitta)
    slant = math.hypot(h, rb - rt)
    a_ = math.pi * (rt + rb) * slant + 2 * math.pi * (big_t * cap_t + big_b * cap_b)
    v = (math.pi * h / 3 * (rt * rt + rt * rb + rb * rb)
         + math.pi * cap_t ** 2 * (3 * big_t - cap_t) / 3 + math.pi * cap_b ** 2 * (3 * big_b - cap_b) / 3)
    return a_, v


pi = math.pi
# kind, attrs, analytic area, analytic volume (None: open surface)
CASES = [
    ("Sphere", {"radius": 1.5}, 4 * pi * 1.5**2, 4 / 3 * pi * 1.5**3),
    ("Cube", {"size": 3.0}, 6 * 9.0, 27.0),
    ("Cylinder", {"radius": 0.5, "height": 3.0}, 2 * pi * 0.5 * 3 + 2 * pi * 0.25, pi * 0.25 * 3),
    ("Cone", {"radius": 1.0, "height": 2.0}, pi * (1 + math.sqrt(5)), pi * 2 / 3),
    ("Capsule", {"radius": 0.5, "height": 2.0}, 4 * pi * 0.25 + 2 * pi * 0.5 * 2,
     4 / 3 * pi * 0.125 + pi * 0.25 * 2),
    ("Plane", {"width": 3.0, "length": 5.0}, 15.0, None),
    ("Cylinder_1", {"radiusTop": 0.5, "radiusBottom": 1.0, "height": 2.0},
     pi * 1.5 * math.hypot(2, 0.5) + pi * (0.25 + 1), pi * 2 / 3 * (0.25 + 0.5 + 1)),
    ("Capsule_1", {"radiusTop": 1.0, "radiusBottom": 0.5, "height": 2.0}, *capsule_1_exact(1.0, 0.5, 2.0)),
    ("Capsule_1", {"radiusTop": 0.25, "radiusBottom": 0.5, "height": 1.0}, *capsule_1_exact(0.25, 0.5, 1.0)),
]


@pytest.mark.parametrize("kind, attrs, want_area, want_volume", CASES)
def test_area_volume_and_winding(kind, attrs, want_area, want_volume):
    mesh = tessellate(define(kind, **attrs), T, detail=64)
    check_structure(mesh, closed=want_volume is not None)
    assert area(mesh) == pytest.approx(want_area, rel=0.02)
    if want_volume is not None:
        assert volume(mesh) == pytest.approx(want_volume, rel=0.02)


@pytest.mark.parametrize("kind, attrs", [(k, a) for k, a, _, _ in CASES])
@pytest.mark.parametrize("axis", ["X", "Y", "Z"])
def test_bounds_match_usd_extent(kind, attrs, axis):
    prim = define(kind, **attrs)
    if prim.GetAttribute("axis"):
        prim.GetAttribute("axis").Set(axis)
    mesh = tessellate(prim, T, detail=64)
    want = extent(prim)
    np.testing.assert_allclose(bbox(mesh), want, atol=0.01 * np.abs(want).max())
    check_structure(mesh, closed=kind != "Plane")


def test_fallback_values_come_from_the_schema():
    for kind in IMPLICIT_TYPES:
        prim = define(kind)
        np.testing.assert_allclose(bbox(tessellate(prim, T)), extent(prim), atol=1e-6, err_msg=kind)
    # the Capsule's fallbacks differ from the other shapes: radius 0.5, height 1
    np.testing.assert_allclose(bbox(tessellate(define("Capsule"), T)), [[-.5, -.5, -1], [.5, .5, 1]])


def test_axis_orients_the_spine():
    mesh = tessellate(define("Cylinder", radius=0.25, height=3.0, axis="X"), T)
    np.testing.assert_allclose(bbox(mesh), [[-1.5, -0.25, -0.25], [1.5, 0.25, 0.25]], atol=1e-12)
    # the cone's apex is the one point at +height/2 along the axis
    for axis, a in zip("XYZ", range(3)):
        mesh = tessellate(define("Cone", radius=1.0, height=4.0, axis=axis), T)
        top = mesh.points[np.isclose(mesh.points[:, a], 2.0)]
        assert len(top) == 1 and np.linalg.norm(np.delete(top[0], a)) == 0
        assert mesh.points[:, a].min() == pytest.approx(-2.0)
    # Cylinder_1 / Capsule_1: radiusTop on the positive side of the axis
    mesh = tessellate(define("Cylinder_1", radiusTop=0.0, radiusBottom=1.0, axis="Y"), T)
    assert np.isclose(mesh.points[:, 1], 1.0).sum() == 1
    mesh = tessellate(define("Capsule_1", radiusTop=1.0, radiusBottom=0.25, height=1.0, axis="X"), T)
    assert mesh.points[:, 0].max() > -mesh.points[:, 0].min()


@pytest.mark.parametrize("axis, width_axis, length_axis", [("X", 2, 1), ("Y", 0, 2), ("Z", 0, 1)])
def test_plane_width_length_and_facing(axis, width_axis, length_axis):
    mesh = tessellate(define("Plane", width=3.0, length=5.0, axis=axis), T)
    size = np.ptp(mesh.points, axis=0)
    assert size[width_axis] == 3.0 and size[length_axis] == 5.0
    assert list(mesh.counts) == [4]
    normal = np.zeros(3)
    normal["XYZ".index(axis)] = 1.0
    np.testing.assert_array_equal(mesh.normals, np.tile(normal, (4, 1)))
    p = mesh.points[mesh.indices]
    assert np.cross(p[1] - p[0], p[2] - p[0]) @ normal > 0


def test_sphere_topology():
    mesh = tessellate(define("Sphere"), T, detail=16)
    # 16 segments, 8 bands: triangle fans at both poles, quads between
    assert Counter(mesh.counts.tolist()) == {3: 32, 4: 16 * 6}
    assert len(mesh.points) == 16 * 7 + 2
    np.testing.assert_allclose(np.linalg.norm(mesh.points, axis=1), 1.0)
    # smooth: each corner's normal is the radial direction of its point
    np.testing.assert_allclose(mesh.normals, mesh.points[mesh.indices], atol=1e-12)


def test_flat_caps_and_smooth_sides():
    mesh = tessellate(define("Cylinder"), T, detail=8)
    assert Counter(mesh.counts.tolist()) == {4: 8, 8: 2}
    caps = np.repeat(mesh.counts == 8, mesh.counts)
    assert (np.abs(mesh.normals[caps][:, 2]) == 1).all()
    np.testing.assert_allclose(mesh.normals[~caps][:, 2], 0, atol=1e-15)
    cube = tessellate(define("Cube"), T)
    assert list(cube.counts) == [4] * 6 and len(cube.points) == 8
    assert volume(cube) == pytest.approx(8.0)


def test_capsule_is_c1_where_caps_meet_the_side():
    mesh = tessellate(define("Capsule_1", radiusTop=1.0, radiusBottom=0.25, height=1.0), T, detail=32)
    # every point shared by several faces gets the same normal from all of them
    by_point = {}
    for i, n in zip(mesh.indices, mesh.normals):
        by_point.setdefault(int(i), []).append(n)
    poles = {i for i, ns in by_point.items() if np.linalg.norm(mesh.points[i][:2]) == 0}
    for i, ns in by_point.items():
        if i not in poles:
            np.testing.assert_allclose(ns, np.broadcast_to(ns[0], np.shape(ns)), atol=1e-12)


def test_equal_radii_and_zero_height_degenerate_cleanly():
    a = tessellate(define("Capsule_1", radiusTop=0.5, radiusBottom=0.5, height=1.0), T)
    b = tessellate(define("Capsule"), T)
    np.testing.assert_allclose(a.points, b.points)
    np.testing.assert_array_equal(a.indices, b.indices)
    sphere = tessellate(define("Capsule", height=0.0, radius=1.0), T, detail=64)
    check_structure(sphere, closed=True)
    assert volume(sphere) == pytest.approx(4 / 3 * pi, rel=0.02)
    prim = define("Capsule_1", radiusTop=1.0, radiusBottom=0.5, height=0.0)
    mesh = tessellate(prim, T, detail=64)
    check_structure(mesh, closed=True)
    np.testing.assert_allclose(bbox(mesh), extent(prim), atol=0.01)
    assert len(tessellate(define("Sphere", radius=0.0), T).counts) == 0


def test_time_samples():
    prim = define("Sphere")
    prim.GetAttribute("radius").Set(1.0, Usd.TimeCode(1))
    prim.GetAttribute("radius").Set(3.0, Usd.TimeCode(3))
    mesh = tessellate(prim, Usd.TimeCode(2))
    assert mesh.points[:, 2].max() == pytest.approx(2.0)


@pytest.mark.parametrize("kind, name, value, message", [
    ("Sphere", "radius", -1.0, "radius -1 must be >= 0"),
    ("Cube", "size", -2.0, "size -2 must be >= 0"),
    ("Cylinder", "height", float("nan"), "height nan must be"),
    ("Capsule_1", "radiusTop", float("inf"), "radiusTop inf must be"),
    ("Plane", "width", -0.5, "width -0.5 must be >= 0"),
    ("Cone", "axis", "W", "axis 'W'"),
])
def test_invalid_sizes_raise(kind, name, value, message):
    with pytest.raises(ValueError, match=message):
        tessellate(define(kind, **{name: value}), T)


def test_not_implicit_returns_none():
    stage = Usd.Stage.CreateInMemory()
    assert tessellate(UsdGeom.Mesh.Define(stage, "/m").GetPrim(), T) is None
    assert tessellate(UsdGeom.Xform.Define(stage, "/x").GetPrim(), T) is None
    assert tessellate(stage.DefinePrim("/untyped"), T) is None
