"""Mesh lights (UsdLux ``MeshLightAPI``) in the render index: a mesh's emission as plain data, and its triangles
as :attr:`usdml.scene.LightType.TRIANGLE` lights for the many-light paths.

Radiometry (UsdLux, as every light, :mod:`usdml.stage.lights`): the mesh emits radiance
``L = intensity · 2^exposure · color (· blackbody)``, divided by the mesh's world-space area in m² when
``normalize`` is on (each instance's own area, for an instanced mesh). Each triangle of area A is a Lambertian
emitter of radiance L on its front, the side its surface normal points to (the mesh's winding as the scene
delegate resolves it, ``orientation`` and mirroring transforms included): on-axis radiant intensity
``I = L · A`` (nit·m²) with the one-sided ``max(0, cos θ_l)`` profile of a rect light. ``doubleSided`` does not
make it emit from its back (docs/mesh-lights.md). ``inputs:diffuse`` scales the light the triangles shed (their
``radiance`` and ``intensity``), not the radiance the camera sees on the mesh (:func:`emitted_at_hits`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdml.scene import Lights, LightType, Mesh, instance_points

__all__ = ["MeshLight", "emitted_at_hits", "mesh_area", "triangle_lights"]


@dataclass(frozen=True)
class MeshLight:
    """A ``MeshLightAPI`` applied to a mesh, as read at one timecode."""

    radiance: tuple[float, float, float]   #: L before ``normalize`` (nits), without ``inputs:diffuse``
    diffuse: float = 1.0                   #: ``inputs:diffuse``
    normalize: bool = False                #: divide L by the mesh's world area in m²
    shadow: bool = True                    #: ``inputs:shadow:enable``


def _triangles(mesh: Mesh, xforms: np.ndarray | None):
    """``(N, T, 3)`` float64 vertex 0, edges ``v1 − v0`` and ``v2 − v0``, and the surface normal scaled by twice
    the area, of every triangle under each of ``xforms`` (N, 4, 4) (None: ``mesh.points`` are world, N = 1). A
    mirroring transform turns the edges' cross product around; the surface normal keeps its side (the inverse
    transpose's)."""
    if xforms is None:
        world = np.asarray(mesh.points, np.float64)[None]
        sign = np.ones(1)
    else:
        xforms = np.asarray(xforms, np.float64).reshape(-1, 4, 4)
        world = instance_points(xforms, mesh.points)
        sign = np.sign(np.linalg.det(xforms[:, :3, :3]))
    tri = np.asarray(mesh.triangles, np.int64)
    v0 = world[:, tri[:, 0]]
    e1, e2 = world[:, tri[:, 1]] - v0, world[:, tri[:, 2]] - v0
    return v0, e1, e2, np.cross(e1, e2) * sign[:, None, None]


def mesh_area(mesh: Mesh, linear: np.ndarray | None = None, meters_per_unit: float = 1.0) -> float:
    """The mesh's area in m² under the linear part ``linear`` (3, 3) of an instance transform (None: its points
    are world)."""
    xf = None
    if linear is not None:
        xf = np.eye(4)
        xf[:3, :3] = linear
    *_, normal = _triangles(mesh, xf)
    return float(np.linalg.norm(normal, axis=2).sum()) * 0.5 * meters_per_unit ** 2


def triangle_lights(mesh: Mesh, xforms: np.ndarray | None = None, instance_ids: np.ndarray | None = None,
                    meters_per_unit: float = 1.0) -> Lights:
    """One :attr:`~usdml.scene.LightType.TRIANGLE` light per triangle of the emitting ``mesh`` (``mesh.light``
    set) and instance; triangles of no area emit nothing and are left out.

    ``xforms`` (N, 4, 4) prototype-to-world of each instance (None: ``mesh.points`` are world); ``instance_ids``
    (N,) int64 (None: -1). The lights follow the convention of :class:`usdml.scene.LightType`: ``xform`` columns
    edge 1, edge 2, the unit normal on the emitting side and vertex 0 (world, scene units), ``position`` the
    centroid, ``axis`` the normal, ``radiance`` L·diffuse (nits), ``intensity`` that times the triangle's area
    in m²; instance by instance, triangle by triangle, ``paths`` the mesh's.
    """
    light: MeshLight = mesh.light
    v0, e1, e2, normal = _triangles(mesh, xforms)
    twice = np.linalg.norm(normal, axis=2)                                  # (N, T)
    area = 0.5 * twice * meters_per_unit ** 2
    base = np.asarray(light.radiance, np.float64) * max(light.diffuse, 0.0)
    radiance = np.broadcast_to(base, (len(v0), 3))
    if light.normalize:
        total = area.sum(axis=1, keepdims=True)
        radiance = np.where(total > 0, base / np.where(total > 0, total, 1.0), 0.0)
    inst, k = np.nonzero(twice > 0)
    n = len(inst)
    xform = np.zeros((n, 4, 4))
    xform[:, :3, 0], xform[:, :3, 1], xform[:, :3, 3] = e1[inst, k], e2[inst, k], v0[inst, k]
    xform[:, :3, 2] = normal[inst, k] / twice[inst, k][:, None]
    xform[:, 3, 3] = 1.0
    rad = radiance[inst]
    ids = np.full(len(v0), -1, np.int64) if instance_ids is None else np.asarray(instance_ids, np.int64)
    zeros = np.zeros(n)
    return Lights(
        type=np.full(n, int(LightType.TRIANGLE), np.int8),
        position=xform[:, :3, 3] + (xform[:, :3, 0] + xform[:, :3, 1]) / 3.0,
        axis=xform[:, :3, 2].copy(), xform=xform, radiance=rad.astype(np.float32),
        intensity=(rad * area[inst, k][:, None]).astype(np.float32),
        radius=zeros, width=zeros.copy(), height=zeros.copy(), angle=zeros.copy(), cone_angle=np.full(n, 180.0),
        cone_softness=zeros.copy(), focus=zeros.copy(), focus_tint=np.zeros((n, 3), np.float32),
        shadow=np.full(n, bool(light.shadow)), paths=[mesh.path] * n, instance_ids=ids[inst])


def emitted_at_hits(mesh: Mesh, tri: np.ndarray, dirs: np.ndarray, linear: np.ndarray | None = None,
                    meters_per_unit: float = 1.0) -> np.ndarray:
    """``(K, 3) float32`` radiance the emitting ``mesh`` sends back along rays of unit directions ``dirs`` (K, 3)
    that hit its triangles ``tri`` (K,): L where the ray meets a triangle's front, 0 on its back and for a light
    of negative intensity (it takes light away; it does not glow). ``linear`` (3, 3): the
    instance transform's linear part (None: world points)."""
    light: MeshLight = mesh.light
    radiance = np.maximum(np.asarray(light.radiance, np.float64), 0.0)
    if light.normalize:
        area = mesh_area(mesh, linear, meters_per_unit)
        radiance = radiance / area if area > 0 else np.zeros(3)
    out = np.broadcast_to(radiance.astype(np.float32), (len(tri), 3)).copy()
    p = np.asarray(mesh.points, np.float64)[np.asarray(mesh.triangles)[tri]]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if linear is not None:
        normal = normal @ np.linalg.inv(linear)      # inverse transpose (row vectors): the surface's side
    out[(normal * dirs).sum(axis=1) >= 0] = 0.0
    return out
