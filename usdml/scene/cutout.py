"""Cutouts and partly opaque surfaces as the approximate visibility backends see them: kept geometry.

The exact backend passes rays through a cutout's holes hit by hit (:meth:`usdml.visibility.exact.ExactBackend.
intersect`). The approximate backends (voxel arrays, the SVO, shadow maps) are built from triangles, not rays,
so they get the surface as triangles: each triangle of a mesh with a cutout or partial opacity is split into
``m²`` sub-triangles small enough to follow its opacity image (``m`` from the triangle's extent in texels of
that image, at most :data:`MAX_SPLIT`), and only the sub-triangles kept at their centre
(:meth:`usdml.scene.shading.MeshShading.kept`) are built. A partly opaque surface keeps a sub-triangle with
probability ``opacity`` (its random number hashed from the triangle and the sub-triangle: the same every frame),
a screen door whose coverage is the opacity. :func:`kept_snapshot` hands those backends the snapshot with such
meshes replaced; camera rays and the shading keep the original.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from usdml.scene import Mesh, Snapshot
from usdml.scene.hashing import GOLDEN, mix, unit

__all__ = ["MAX_SPLIT", "PARTIAL_SPLIT", "has_see_through", "kept_mesh", "kept_snapshot", "see_through"]

#: most sub-triangles along a triangle's edge (m; m² sub-triangles)
MAX_SPLIT = 32
#: the split of a partly opaque triangle with no opacity image (a screen door of PARTIAL_SPLIT² cells)
PARTIAL_SPLIT = 8


def _splits(mesh: Mesh) -> np.ndarray:
    """(T,) int m per triangle: its longest edge in texels of the opacity images feeding it (1 with none)."""
    shading = mesh.shading
    m = np.ones(mesh.triangle_count, np.int64)
    opacity = shading.fields["opacity"]
    if np.any(opacity.corners < 1) or opacity.textures:
        m[:] = PARTIAL_SPLIT if not opacity.textures else 1
    for mask, lookup, st in opacity.textures:
        h, w = lookup.texture.pixels.shape[:2]
        texels = st * np.array([w, h], np.float64)
        edges = np.stack([texels[:, 1] - texels[:, 0], texels[:, 2] - texels[:, 1], texels[:, 0] - texels[:, 2]], 1)
        longest = np.sqrt((edges ** 2).sum(-1)).max(1)
        want = np.clip(np.ceil(longest * 2.0), 1, MAX_SPLIT).astype(np.int64)   # two samples a texel
        rows = slice(None) if mask is None else mask
        m[rows] = np.maximum(m[rows], want[rows] if mask is None else want[mask])
    return m


def _lattice(m: int) -> tuple[np.ndarray, np.ndarray]:
    """``(corners (m², 3, 3), centres (m², 3))`` barycentric coordinates of a triangle's m² sub-triangles."""
    tris = []
    for i in range(m):
        for j in range(m - i):
            a, b, c = (i, j), (i + 1, j), (i, j + 1)
            tris.append((a, b, c))
            if j < m - i - 1:
                tris.append((b, (i + 1, j + 1), c))
    uv = np.asarray(tris, np.float64) / m                          # (m², 3, 2): (u, v) of corners 1 and 2
    corners = np.concatenate([1.0 - uv.sum(-1, keepdims=True), uv], axis=-1)
    return corners, corners.mean(1)


def _uniform(tri: np.ndarray, sub: np.ndarray) -> np.ndarray:
    """A deterministic uniform number per (triangle, sub-triangle)."""
    with np.errstate(over="ignore"):
        return unit(mix(tri.astype(np.uint64) * GOLDEN + sub.astype(np.uint64) * np.uint64(0xBF58476D1CE4E5B9)))


def kept_mesh(mesh: Mesh) -> Mesh | None:
    """``mesh`` as the triangles that stop light (module doc): every sub-triangle kept at its centre; None when
    none is."""
    m_of = _splits(mesh)
    points, tris, normals, albedo, faces = [], [], [], [], []
    corner_p = mesh.points[mesh.triangles].astype(np.float64)         # (T, 3, 3)
    count = 0
    for m in np.unique(m_of):
        rows = np.flatnonzero(m_of == m)
        corners, centres = _lattice(int(m))
        k = len(centres)
        tri = np.repeat(rows, k)
        sub = np.tile(np.arange(k), len(rows))
        w = np.tile(centres, (len(rows), 1))[:, :, None]
        keep = mesh.shading.kept(tri, w, _uniform(tri, sub))
        if not keep.any():
            continue
        tri, sub = tri[keep], sub[keep]
        bary = corners[sub]                                          # (K, 3 corners, 3 weights)
        p = np.einsum("kcw,kwd->kcd", bary, corner_p[tri])
        points.append(p.reshape(-1, 3))
        tris.append(np.arange(count, count + 3 * len(tri)).reshape(-1, 3))
        normals.append(np.einsum("kcw,kwd->kcd", bary, mesh.normals[tri].astype(np.float64)))
        albedo.append(np.einsum("kcw,kwd->kcd", bary, mesh.albedo[tri].astype(np.float64)))
        faces.append(mesh.face_index[tri])
        count += 3 * len(tri)
    if not tris:
        return None
    return replace(mesh, points=np.concatenate(points).astype(np.float32),
                   triangles=np.concatenate(tris).astype(np.int32),
                   normals=np.concatenate(normals).astype(np.float32), albedo=np.concatenate(albedo).astype(np.float32),
                   face_index=np.concatenate(faces).astype(np.int32), shading=None)


def see_through(mesh: Mesh) -> bool:
    """Rays can pass through some of ``mesh``: a cutout or partial opacity (``MeshShading.cutout``)."""
    return mesh.shading is not None and mesh.shading.cutout


def has_see_through(snapshot: Snapshot) -> bool:
    """Some mesh of ``snapshot``, plain or a prototype's, is :func:`see_through`."""
    return any(see_through(m) for m in snapshot.meshes) or \
        any(see_through(m) for p in snapshot.prototypes for m in p.meshes)


def kept_snapshot(snapshot: Snapshot, cache: dict | None = None) -> Snapshot:
    """``snapshot`` with every mesh that has a cutout or partial opacity replaced by :func:`kept_mesh` (itself when
    none has); ``cache`` (path, geometry hash) -> kept mesh, kept by the caller across frames."""
    cache = {} if cache is None else cache

    def kept(meshes: list[Mesh]) -> list[Mesh]:
        out = []
        for mesh in meshes:
            if see_through(mesh):
                key = (mesh.path, mesh.geometry_hash())
                if key not in cache:
                    cache[key] = kept_mesh(mesh)
                mesh = cache[key]
            if mesh is not None:            # a mesh that is all holes stops no light: left out
                out.append(mesh)
        return out

    if not has_see_through(snapshot):
        return snapshot
    prototypes = [replace(p, meshes=kept(p.meshes)) for p in snapshot.prototypes]
    return replace(snapshot, meshes=kept(snapshot.meshes), prototypes=[p for p in prototypes if p.meshes])
