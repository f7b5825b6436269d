"""Read a ``UsdGeom.Mesh`` into a triangulated :class:`usdml.scene.Mesh`.

Polygons are fan-triangulated (as Hydra's mesh util does); faces that are hole faces, have fewer than
three vertices or index outside ``points`` are dropped with a warning naming the prim. Subdivision
meshes render as their control cage.

Normals: authored ones are read on polygonal meshes (``subdivisionScheme = "none"``) only, as
usdImaging's mesh adapter. Without them, usdml follows the final-frame renderers (RenderMan, Arnold,
Omniverse RTX): a polygonal mesh is faceted, each triangle shaded with its own geometric normal; a
subdivision mesh, drawn as its cage, gets area-weighted smooth normals of its points, closer to its
limit surface.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from pxr import Usd, UsdGeom

from usdml.errors import UsdmlError
from usdml.scene import Mesh
from usdml.stage.implicit import IMPLICIT_TYPES, tessellate
from usdml.stage.mesh_light import read_mesh_light

#: segments around an implicit surface's axis: usdImaging's (its sphere and cylinder adapters use 10)
DEFAULT_IMPLICIT_DETAIL = 10

#: attributes whose time samples make a gprim's points vary
_SHAPE_ATTRS = ("points", "size", "radius", "height", "radiusTop", "radiusBottom", "width", "length", "axis")

#: albedo of meshes without displayColor: UsdPreviewSurface's diffuseColor fallback
DEFAULT_ALBEDO = (0.18, 0.18, 0.18)


class Topology:
    """Fan triangulation of one mesh's faces, shared by every per-corner primvar expansion."""

    def __init__(self, counts: np.ndarray, indices: np.ndarray, n_points: int, holes: np.ndarray,
                 left_handed: bool, path: str, warn: Callable[[str], None]):
        counts = counts.astype(np.int64)
        indices = indices.astype(np.int64)
        if counts.sum() != len(indices) or (counts < 0).any():
            raise ValueError(f"faceVertexCounts sum to {int(counts.clip(0).sum())} but there are "
                             f"{len(indices)} faceVertexIndices")
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, np.int64)
        keep = counts >= 3
        if (~keep).any():
            warn(f"{path}: {int((~keep).sum())} face(s) with fewer than 3 vertices dropped")
        bad_index = (indices < 0) | (indices >= n_points)
        if bad_index.any():
            face_of_corner = np.repeat(np.arange(len(counts)), counts)
            bad_faces = np.zeros(len(counts), bool)
            bad_faces[face_of_corner[bad_index]] = True
            warn(f"{path}: {int(bad_faces.sum())} face(s) index outside the {n_points} points; dropped "
                 "(check faceVertexIndices)")
            keep &= ~bad_faces
        if len(holes):
            valid = holes[(holes >= 0) & (holes < len(counts))]
            if len(valid):
                warn(f"{path}: {len(np.unique(valid))} hole face(s) (holeIndices) not rendered")
                keep[valid] = False
        faces = np.nonzero(keep)[0]
        ntri = counts[faces] - 2
        self.face = np.repeat(faces, ntri)                                   # (T,)
        first = np.repeat(offsets[faces], ntri)
        k = np.arange(len(self.face)) - np.repeat(np.cumsum(ntri) - ntri, ntri)
        corner = np.stack([first, first + k + 1, first + k + 2], axis=1)     # (T, 3) face-varying index
        if left_handed:
            corner = corner[:, [0, 2, 1]]
        self.corner = corner
        self.vertex = indices[corner] if len(corner) else np.zeros((0, 3), np.int64)

    def expand(self, values: np.ndarray, interpolation: str, n_points: int) -> np.ndarray | None:
        """Per-corner ``(T, 3, C)`` values for a primvar of the given interpolation, None on size mismatch."""
        values = np.asarray(values)
        if interpolation == "constant":
            return np.broadcast_to(values[:1][None], (len(self.face), 3, values.shape[-1])) if len(values) else None
        if interpolation == "uniform":
            if len(values) <= (self.face.max(initial=-1)):
                return None
            return np.repeat(values[self.face][:, None], 3, axis=1)
        if interpolation in ("vertex", "varying"):
            if len(values) < n_points:
                return None
            return values[self.vertex]
        if interpolation == "faceVarying":
            if len(values) <= self.corner.max(initial=-1):
                return None
            return values[self.corner]
        return None


def _array(value, dtype, width=None, where: str = "", warn: Callable[[str], None] | None = None) -> np.ndarray:
    """An authored array attribute as ``(N,)`` or ``(N, width)`` ``dtype``; empty when unauthored.

    A value of the wrong shape (``int normals = 7``, a single ``float3``, an ``int[]`` where 3-vectors
    belong: attributes authored with another type than the schema's, as USD test stages do) is
    treated as unauthored, with a warning naming ``where`` (``/prim.attribute``)."""
    empty = np.zeros((0,) if width is None else (0, width), dtype)
    if value is None:
        return empty
    a = np.asarray(value)
    if a.size == 0:
        return empty
    if a.dtype.kind not in "biuf" or a.ndim != (1 if width is None else 2) or (width and a.shape[1] != width):
        if warn is not None:
            want = "numbers" if width is None else f"{width}-vectors"
            warn(f"{where}: authored as {type(value).__name__}, not an array of {want}; ignored")
        return empty
    return a.astype(dtype, copy=False)


def transform_points(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points through a (4, 4) column-convention matrix (affine)."""
    return p @ m[:3, :3].T + m[:3, 3]


def _face_cross(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points as float64 and each triangle's ``(v1 - v0) × (v2 - v0)`` (twice its area, unnormalised)."""
    p = points.astype(np.float64)
    return p, np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])


def smooth_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, per corner ``(T, 3, 3)`` float32."""
    p, fn = _face_cross(points, tris)
    # each vertex's sum of its triangles' normals, corner 0 of every triangle first, then 1, then 2:
    # bincount adds in that order as np.add.at did, to the same bits, 2-3x faster (254k triangles)
    corners = tris.T.reshape(-1)
    vn = np.empty_like(p)
    for k in range(3):
        vn[:, k] = np.bincount(corners, weights=np.tile(fn[:, k], 3), minlength=len(p))
    # vertices used only by zero-area triangles fall back to +Y rather than NaN
    length = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(length > 0, vn / np.where(length > 0, length, 1), [0.0, 1.0, 0.0])
    return vn.astype(np.float32)[tris]


def faceted_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Each triangle's own unit geometric normal at its three corners, ``(T, 3, 3)`` float32
    (zero-area triangles get +Y, as :func:`smooth_normals` gives their unused vertices)."""
    _, fn = _face_cross(points, tris)
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    fn = np.where(length > 0, fn / np.where(length > 0, length, 1), [0.0, 1.0, 0.0])
    return np.repeat(fn[:, None, :], 3, axis=1).astype(np.float32)


def is_gprim(prim: Usd.Prim) -> bool:
    """A gprim usdml draws: a Mesh or an implicit surface it tessellates."""
    return prim.IsA(UsdGeom.Mesh) or prim.GetTypeName() in IMPLICIT_TYPES


def moves_by_velocity(prim: Usd.Prim, time: Usd.TimeCode,
                      names: tuple[str, ...] = ("velocities", "accelerations")) -> bool:
    """Whether ``prim`` authors a non-zero one of ``names`` at ``time``: USD then extrapolates its points (or
    instances) from their time sample, so they move even with a single sample."""
    for name in names:
        value = prim.GetAttribute(name).Get(time) if prim.HasAttribute(name) else None
        if value is not None and len(value) and np.any(np.asarray(value)):
            return True
    return False


def points_vary(prim: Usd.Prim) -> bool:
    """Whether the gprim's shape (points, or an implicit surface's sizes) might change over time: time samples, or
    points that move by their ``velocities`` (:func:`moves_by_velocity`)."""
    return (any(prim.GetAttribute(a).ValueMightBeTimeVarying() for a in _SHAPE_ATTRS if prim.HasAttribute(a))
            or (prim.IsA(UsdGeom.PointBased) and moves_by_velocity(prim, Usd.TimeCode.EarliestTime())))


def read_gprim(prim: Usd.Prim, time: Usd.TimeCode, to_space: np.ndarray | None, mesh_id: int,
               warn: Callable[[str], None], deforming: bool = False,
               detail: int = DEFAULT_IMPLICIT_DETAIL, materials=None) -> Mesh | None:
    """A Mesh (:func:`read_mesh`) or an implicit gprim tessellated by :mod:`usdml.stage.implicit`
    with ``detail`` segments around its axis; ``materials`` resolves bound materials to albedo."""
    if prim.IsA(UsdGeom.Mesh):
        return read_mesh(prim, time, to_space, mesh_id, warn, deforming=deforming, materials=materials)
    try:
        poly = tessellate(prim, time, detail)
    except ValueError as e:
        raise UsdmlError(f"{prim.GetPath()}: {e}; fix the {prim.GetTypeName()}'s attribute") from None
    if poly is None:
        return None
    sided = UsdGeom.Gprim(prim).GetDoubleSidedAttr().Get(time)
    return build_mesh(prim, time, mesh_id, poly.points, poly.counts, poly.indices, np.zeros(0, np.int64),
                      False, to_space, (poly.normals, "faceVarying"), bool(sided), deforming, warn, materials)


def read_mesh(prim: Usd.Prim, time: Usd.TimeCode, to_space: np.ndarray | None, mesh_id: int,
              warn: Callable[[str], None], points: np.ndarray | None = None,
              deforming: bool = False, authored_normals: bool = True, materials=None) -> Mesh | None:
    """Triangulate the ``UsdGeom.Mesh`` ``prim`` at ``time``; ``to_space`` maps its local space to the target space.

    ``points`` overrides the authored points (posed UsdSkel points, already in the target space when
    ``to_space`` is None); ``authored_normals=False`` ignores authored normals (they do not follow a pose).
    Authored normals are read only for polygonal meshes (``subdivisionScheme = "none"``): usdImaging's
    mesh adapter drops them on subdivision surfaces (catmullClark, the schema default, loop, bilinear),
    whose normals come from the surface. Without normals, polygonal meshes shade faceted, subdivision
    meshes smooth; so does a polygonal mesh whose authored normals are ignored (``authored_normals``
    False: skinned), since it authored them smooth.
    Points with ``velocities`` (and ``accelerations``) are USD's at ``time``: extrapolated from the sample at or
    before it (``UsdGeomPointBased.ComputePointsAtTime``).
    Returns None (after a warning) for a mesh with nothing renderable.
    """
    mesh = UsdGeom.Mesh(prim)
    if points is None:
        # with velocities USD defines the points between (and past) samples by them: UsdGeomPointBased's rule
        value = mesh.ComputePointsAtTime(time, time) if moves_by_velocity(prim, time) else \
            mesh.GetPointsAttr().Get(time)
        points = _array(value, np.float64, 3, f"{prim.GetPath()}.points", warn)
    normals = None
    polygonal = mesh.GetSubdivisionSchemeAttr().Get(time) == UsdGeom.Tokens.none
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    primvar = bool(pv and pv.HasAuthoredValue())
    if authored_normals and polygonal:
        normals = (pv.ComputeFlattened(time), pv.GetInterpolation()) if primvar else \
            (mesh.GetNormalsAttr().Get(time), mesh.GetNormalsInterpolation())
    # authored normals that do not follow the pose (a skinned mesh) still say the surface is smooth:
    # a skinned character exported polygonal (glTF, FBX) shades smooth from its posed points
    smooth_intent = not authored_normals and (primvar or mesh.GetNormalsAttr().HasAuthoredValue())
    return build_mesh(
        prim, time, mesh_id, points,
        *(_array(a.Get(time), np.int64, None, f"{prim.GetPath()}.{a.GetName()}", warn)
          for a in (mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr(), mesh.GetHoleIndicesAttr())),
        mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded, to_space, normals,
        bool(mesh.GetDoubleSidedAttr().Get(time)), deforming, warn, materials,
        faceted=polygonal and not smooth_intent)


def build_mesh(prim: Usd.Prim, time: Usd.TimeCode, mesh_id: int, points: np.ndarray, counts: np.ndarray,
               indices: np.ndarray, holes: np.ndarray, left: bool, to_space: np.ndarray | None,
               normals: tuple | None, double_sided: bool, deforming: bool,
               warn: Callable[[str], None], materials=None, faceted: bool = False) -> Mesh | None:
    """Triangulate polygon arrays of ``prim`` (a Mesh or a tessellated implicit gprim).

    ``normals`` is ``(values, interpolation)`` or None to compute them: per-triangle geometric
    normals when ``faceted``, else area-weighted smooth ones. ``materials`` (a
    :class:`usdml.stage.materials.MaterialResolver`) gives the faces' bound surfaces (``Mesh.shading``) and their
    diffuse reflectance as the albedo; faces with none take ``primvars:displayColor``. A ``MeshLightAPI`` on
    ``prim`` is read into ``Mesh.light``.
    """
    path = str(prim.GetPath())
    if len(points) == 0:
        warn(f"{path}: mesh has no points; skipped")
        return None
    if not np.isfinite(points).all():
        raise UsdmlError(f"{path}.points: non-finite (NaN/inf) point values at time {time.GetValue()}; "
                         "fix the mesh points")
    m = np.eye(4) if to_space is None else to_space
    flipped = np.linalg.det(m[:3, :3]) < 0
    try:
        topo = Topology(counts, indices, len(points), holes, left != flipped, path, warn)
    except ValueError as e:
        warn(f"{path}: {e}; mesh skipped")
        return None
    if len(topo.face) == 0:
        warn(f"{path}: mesh has no renderable faces; skipped")
        return None

    world = transform_points(m, points) if to_space is not None else points
    tris = topo.vertex.astype(np.int32)

    corner_normals = None
    raw, interp = normals if normals is not None else (None, "vertex")
    raw = _array(raw, np.float64, 3, f"{path}.normals", warn)
    if len(raw):
        n = topo.expand(raw, interp, len(points))
        if n is None:
            warn(f"{path}: {len(raw)} normals do not match interpolation {interp!r}; computing normals")
        else:
            n = n @ np.linalg.inv(m[:3, :3])   # inverse-transpose applied to row vectors
            length = np.linalg.norm(n, axis=-1, keepdims=True)
            corner_normals = np.where(length > 0, n / np.where(length > 0, length, 1), 0).astype(np.float32)
    if corner_normals is None:
        corner_normals = (faceted_normals if faceted else smooth_normals)(world, tris)

    shading = materials.shading(prim, time, topo, len(points)) if materials is not None else None
    albedo = None
    if shading is None or shading.lambert is not None:      # displayColor: the whole mesh, or faces with no surface
        dc = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
        if dc and dc.HasValue():
            raw = _array(dc.ComputeFlattened(time), np.float32, 3, f"{path}.primvars:displayColor", warn)
            if len(raw):
                albedo = topo.expand(raw, dc.GetInterpolation(), len(points))
                if albedo is None:
                    warn(f"{path}: {len(raw)} displayColor values do not match interpolation "
                         f"{dc.GetInterpolation()!r}; using the default albedo")
        if albedo is None:
            albedo = np.broadcast_to(np.float32(DEFAULT_ALBEDO), (len(tris), 3, 3))
    if shading is not None:
        surface = shading.albedo_corners()
        if shading.lambert is not None:
            surface[shading.lambert] = albedo[shading.lambert]
        albedo = surface

    return Mesh(
        path=path, id=mesh_id, points=np.ascontiguousarray(world, np.float32), triangles=tris,
        normals=np.ascontiguousarray(corner_normals, np.float32), albedo=np.ascontiguousarray(albedo, np.float32),
        face_index=topo.face.astype(np.int32), double_sided=double_sided,
        orientation="leftHanded" if left else "rightHanded", deforming=deforming, shading=shading,
        light=read_mesh_light(prim, time, warn))
