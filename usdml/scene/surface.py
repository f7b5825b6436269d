"""What a ray hits: the surface of a snapshot at the closest hits of a batch of rays.

The rays are traced by a visibility backend's ``intersect`` (the exact backend); what this module adds
is the render index's side: which mesh each hit belongs to and its attributes there, the shading
normal interpolated from the mesh's per-corner normals (instanced ones through the inverse transpose
of their instance transform), the albedo (textures sampled at the hit, not per corner) and, where a mesh has
bound surfaces (``Mesh.shading``), each hit's BRDF row (``kernels/brdf``, seen from the ray's origin) and
emission, plus the radiance of an emitting mesh (``Mesh.light``) toward the ray. Used by the
G-buffer (:mod:`usdml.render.gbuffer`) and by VPL light paths (:mod:`usdml.lighting.vpl`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdml.scene import Snapshot
from usdml.scene.mesh_light import emitted_at_hits
from usdml.scene.shading import lambert_rows

__all__ = ["Hits", "surface_at_hits", "tangent_space_normal"]


@dataclass
class Hits:
    """Surface attributes where rays hit (rays that missed have ``hit`` False and zeros)."""

    hit: np.ndarray         #: (N,) bool
    position: np.ndarray    #: (N, 3) float64 world position
    normal: np.ndarray      #: (N, 3) float64 unit world shading normal (as authored, not flipped)
    geometric: np.ndarray   #: (N, 3) float64 unit world geometric normal (of the triangle's winding)
    albedo: np.ndarray      #: (N, 3) float32 linear RGB (textures sampled at the hit)
    geom: np.ndarray        #: (N,) int32 backend geometry source, -1 on a miss
    triangle: np.ndarray    #: (N,) int32 triangle of that source's mesh, -1 on a miss
    t: np.ndarray           #: (N,) float32 ray parameter, inf on a miss
    #: (N, WIDTH) float32 BRDF rows (``kernels/brdf``; Lambertian rows where a mesh has no surface), or None when
    #: no hit mesh has one (every hit Lambertian); ``albedo`` is then the diffuse reflectance times occlusion
    material: np.ndarray | None = None
    #: (N, 3) float32 emitted radiance (emissiveColor, a mesh light's L on its front), or None
    emission: np.ndarray | None = None


def surface_at_hits(snapshot: Snapshot, backend, origins: np.ndarray, dirs: np.ndarray,
                    tmax: np.ndarray | float | None = None) -> Hits:
    """Closest hits of rays ``origins + t·dirs`` with ``backend.intersect`` (the exact backend), and
    the surface there: interpolated shading normal and albedo (per-pixel texture lookups included).

    ``origins``, ``dirs`` : (N, 3) float64 world positions and unit directions; ``tmax`` : (N,) or
    scalar ray length (None: unbounded). ``backend`` is anything with ``intersect(origins, dirs, tmax)``
    and ``source(geom)`` as :class:`usdml.visibility.exact.ExactBackend`.
    """
    r = backend.intersect(origins, dirs, tmax)
    n = len(origins)
    hit = r["geom"] >= 0
    position = np.zeros((n, 3), np.float64)
    position[hit] = origins[hit] + dirs[hit] * r["t"][hit].astype(np.float64)[:, None]
    normal = np.zeros((n, 3), np.float64)
    albedo = np.zeros((n, 3), np.float32)
    geoms = r["geom"][hit]
    rows = np.flatnonzero(hit)
    material = emission = None
    order = np.argsort(geoms, kind="stable")
    bounds = np.flatnonzero(np.diff(geoms[order])) + 1
    for group in np.split(order, bounds):
        if not len(group):
            continue
        src = backend.source(int(geoms[group[0]]))
        mesh = src.mesh_of(snapshot)
        px = rows[group]
        tri = r["prim"][px]
        u, v = r["u"][px].astype(np.float64), r["v"][px].astype(np.float64)
        w = np.stack([1.0 - u - v, u, v], axis=1)[:, :, None]
        nrm = _blend(mesh.normals[tri], w)
        to_world = snapshot.prototypes[src.prototype].xforms[src.instance][:3, :3] if src.prototype >= 0 else None
        if to_world is not None:
            nrm = nrm @ np.linalg.inv(to_world)      # inverse transpose, row vectors
        normal[px] = nrm
        if emission is None and (mesh.shading is not None or mesh.light is not None):
            emission = np.zeros((n, 3), np.float32)
        if mesh.light is not None:
            emission[px] = emitted_at_hits(mesh, tri, dirs[px], to_world, snapshot.meters_per_unit)
        if mesh.shading is None:
            albedo[px] = _blend(mesh.albedo[tri], w)
            continue
        if material is None:
            material = lambert_rows(n, -dirs)
        eye = -np.asarray(dirs[px], np.float64)
        lambert = _blend(mesh.albedo[tri], w) if mesh.shading.lambert is not None else None
        at = mesh.shading.at(tri, w, eye, lambert)
        mapped = mesh.shading.normal_map(tri) if at.normal is not None else None
        if mapped is not None:
            k, st = mapped
            normal[px[k]] = tangent_space_normal(mesh.points[mesh.triangles[tri[k]]], st, _unit(normal[px[k]]),
                                                 at.normal[k], to_world)
        albedo[px] = at.reflectance
        material[px] = at.rows
        emission[px] += at.emission
    return Hits(hit=hit, position=position, normal=_unit(normal), geometric=_unit(r["ng"].astype(np.float64)),
                albedo=albedo, geom=r["geom"], triangle=r["prim"], t=r["t"], material=material, emission=emission)


def _blend(corners: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(K, C) ``(corners * w).sum(1)`` of (K, 3, C) per-corner values and (K, 3, 1) barycentric weights,
    corner by corner: the same sums in the same order, without the (K, 3, C) product."""
    return corners[:, 0] * w[:, 0] + corners[:, 1] * w[:, 1] + corners[:, 2] * w[:, 2]


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit length; zero rows stay zero."""
    # column by column: the same lengths as np.linalg.norm(axis=1), several times sooner on (N, 3) rows
    length = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])[:, None]
    return np.where(length > 0, v / np.where(length > 0, length, 1.0), 0.0)


def tangent_space_normal(corners: np.ndarray, st: np.ndarray, n: np.ndarray, value: np.ndarray,
                         to_world: np.ndarray | None = None) -> np.ndarray:
    """Shading normals ``n`` (K, 3) (unit, world) perturbed by a normal map's tangent-space ``value`` (K, 3) (the
    UsdPreviewSurface ``normal`` input after its texture's scale and bias): ``normalize(x·T + y·B + z·n)`` with the
    tangent T along increasing s and the bitangent B along increasing t of the triangle's texture coordinates ``st``
    (K, 3, 2) over its ``corners`` (K, 3, 3) (mesh space; ``to_world`` (3, 3) the instance's linear part), T made
    orthogonal to n and B = ±n × T keeping the texture's handedness (MikkTSpace's per-triangle frame, as Storm
    derives it from derivatives). Triangles whose st is degenerate keep ``n``."""
    corners = np.asarray(corners, np.float64)
    st = np.asarray(st, np.float64)
    dp1, dp2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    d1, d2 = st[:, 1] - st[:, 0], st[:, 2] - st[:, 0]
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(r) > 1e-20
    r = np.where(ok, r, 1.0)[:, None]
    t = (dp1 * d2[:, 1:2] - dp2 * d1[:, 1:2]) / r
    b = (dp2 * d1[:, 0:1] - dp1 * d2[:, 0:1]) / r
    if to_world is not None:
        t, b = t @ to_world.T, b @ to_world.T
    t = t - n * (t * n).sum(1, keepdims=True)
    tl = np.linalg.norm(t, axis=1, keepdims=True)
    ok &= tl[:, 0] > 1e-20
    t = t / np.where(tl > 1e-20, tl, 1.0)
    side = np.where((np.cross(n, t) * b).sum(1) < 0, -1.0, 1.0)[:, None]
    bt = side * np.cross(n, t)
    v = np.asarray(value, np.float64)
    out = _unit(v[:, 0:1] * t + v[:, 1:2] * bt + v[:, 2:3] * n)
    bad = ~ok | ~(np.linalg.norm(out, axis=1) > 0)
    out[bad] = n[bad]
    return out
