"""Tessellation of UsdGeom implicit gprims (Sphere, Cube, Cylinder, Cone, Capsule, Plane and the
``_1`` variants) into polygon meshes the renderer draws like ``UsdGeom.Mesh``.

Geometry follows the UsdGeom schema (fallback values come from the schema through the schema
classes): every shape is centred at the origin; ``axis`` picks the spine (Cone apex, Cylinder_1 /
Capsule_1 ``radiusTop`` on the positive side); Plane lies across ``axis`` with ``width`` along x
(axis Y, Z) or z (axis X) and ``length`` along y (axis X, Z) or z (axis Y). Implicit prims are
rightHanded, so every face winds counter-clockwise seen from outside: ``cross(p1 - p0, p2 - p0)``
points outward, along the face-varying normals. The Plane faces +axis (it is doubleSided by
default; the renderer reads ``doubleSided`` from the prim as for any gprim).

Round shapes are surfaces of revolution: a profile of rings ``(r, z)`` around the spine, swept by
``detail`` azimuthal segments; rings of radius 0 (poles, the cone apex) are single points, so the
faces next to them are triangles. Points are shared between faces; normals are face-varying, so
cap and cube faces are flat while curved parts are smooth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom

IMPLICIT_TYPES: tuple[str, ...] = ("Sphere", "Cube", "Cylinder", "Cone", "Capsule", "Plane",
                                   "Cylinder_1", "Capsule_1")


@dataclass
class PolyMesh:
    """A polygon mesh in the prim's local space.

    points  (V, 3) float64
    counts  (F,) int64 faceVertexCounts
    indices (sum(counts),) int64 faceVertexIndices, counter-clockwise seen from outside
    normals (sum(counts), 3) float64 face-varying unit normals
    """

    points: np.ndarray
    counts: np.ndarray
    indices: np.ndarray
    normals: np.ndarray


def tessellate(prim: Usd.Prim, time: Usd.TimeCode, detail: int = 32) -> PolyMesh | None:
    """Tessellate an implicit gprim at ``time``; None if ``prim`` is not one.

    ``detail`` is the number of segments around the spine (the Sphere gets ``detail // 2``
    latitudinal bands). Raises ValueError naming the attribute for a negative or non-finite size
    (``radius -1 must be >= 0``) or an unknown axis.
    """
    for schema, build in _BUILDERS:
        if prim.IsA(schema):
            if detail < 3:
                raise ValueError(f"detail {detail} must be >= 3")
            return build(schema(prim), time, int(detail))
    return None


# --- attribute reading ---------------------------------------------------------------------------

def _size(attr: Usd.Attribute, time: Usd.TimeCode) -> float:
    value = _get(attr, time)
    name = attr.GetName()
    if value is None or not math.isfinite(value):
        raise ValueError(f"{name} {value} must be a finite number")
    if value < 0:
        raise ValueError(f"{name} {value:g} must be >= 0")
    return float(value)


def _axis(attr: Usd.Attribute, time: Usd.TimeCode) -> int:
    value = _get(attr, time)
    if value not in ("X", "Y", "Z"):
        raise ValueError(f"axis {value!r} must be X, Y or Z")
    return "XYZ".index(value)


def _get(attr: Usd.Attribute, time: Usd.TimeCode):
    value = attr.Get(time)
    if value is None:
        # a value block hides the schema fallback from Get(); the prim definition still has it
        value = attr.GetPrim().GetPrimDefinition().GetAttributeFallbackValue(attr.GetName())
    return value


# --- surfaces of revolution ----------------------------------------------------------------------

def _lathe(r, z, bands, caps, n: int, axis: int) -> PolyMesh:
    """Sweep the profile rings ``r, z`` (K,) around the spine ``axis`` in ``n`` segments.

    bands: (lo, hi, (nr, nz) at lo, (nr, nz) at hi) per ring pair, lo below hi along the profile;
           a side whose profile is straight passes None to use the profile's own normal.
    caps:  (ring, +1 | -1) flat n-gon closing that ring, facing +spine or -spine.
    """
    r = np.asarray(r, np.float64)
    z = np.asarray(z, np.float64)
    pole = r == 0.0
    size = np.where(pole, 1, n)
    first = np.concatenate([[0], np.cumsum(size)[:-1]])
    theta = 2.0 * np.pi * np.arange(n) / n
    cos, sin = np.cos(theta), np.sin(theta)
    # local (u, v, w): w along the spine; u, v follow azimuth 0 and 90 degrees
    local = np.concatenate([
        [[0.0, 0.0, z[k]]] if pole[k] else np.stack([r[k] * cos, r[k] * sin, np.full(n, z[k])], 1)
        for k in range(len(r))])

    j = np.arange(n)
    mid = theta + np.pi / n                      # azimuth of each face's centre
    faces, normals = [], []

    def ring(k, jj):
        return np.full(n, first[k]) if pole[k] else first[k] + jj % n

    def corner_normal(prof, az):
        nr, nz = prof
        return np.stack([nr * np.cos(az), nr * np.sin(az), np.full(n, float(nz))], 1)

    for lo, hi, n_lo, n_hi in bands:
        if pole[lo] and pole[hi]:
            continue                             # a segment on the spine: no area
        if r[lo] == r[hi] and z[lo] == z[hi]:
            continue                             # coincident rings (e.g. a zero-height cylinder)
        if n_lo is None:
            # straight profile segment: its outward normal is the tangent turned clockwise,
            # which is outward because rings go up the spine and azimuth turns counter-clockwise
            t = np.array([z[hi] - z[lo], r[lo] - r[hi]])
            n_lo = n_hi = t / np.hypot(*t)
        # corners at a pole take the face-centre azimuth so a cone apex stays smooth per face
        az_lo = mid if pole[lo] else theta
        az_lo1 = mid if pole[lo] else theta + 2 * np.pi / n
        az_hi = mid if pole[hi] else theta
        az_hi1 = mid if pole[hi] else theta + 2 * np.pi / n
        quad = [(ring(lo, j), corner_normal(n_lo, az_lo)),
                (ring(lo, j + 1), corner_normal(n_lo, az_lo1)),
                (ring(hi, j + 1), corner_normal(n_hi, az_hi1)),
                (ring(hi, j), corner_normal(n_hi, az_hi))]
        if pole[lo]:
            quad = quad[1:]                      # the two corners on the pole are one point
        elif pole[hi]:
            quad = quad[:3]
        faces.append(np.stack([q[0] for q in quad], 1))
        normals.append(np.stack([q[1] for q in quad], 1))

    for k, sign in caps:
        if pole[k]:
            continue
        order = j if sign > 0 else j[::-1]       # counter-clockwise seen from +spine or -spine
        faces.append((first[k] + order)[None])
        normals.append(np.tile([0.0, 0.0, float(sign)], (1, n, 1)))

    counts = np.concatenate([np.full(len(f), f.shape[1], np.int64) for f in faces]) \
        if faces else np.zeros(0, np.int64)
    indices = np.concatenate([f.ravel() for f in faces]).astype(np.int64) \
        if faces else np.zeros(0, np.int64)
    nrm = np.concatenate([v.reshape(-1, 3) for v in normals]) if normals else np.zeros((0, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return PolyMesh(_to_axis(local, axis), counts, indices, _to_axis(nrm, axis))


def _to_axis(local: np.ndarray, axis: int) -> np.ndarray:
    """Place local (u, v, w) with w on ``axis``; a cyclic permutation, so handedness is kept."""
    out = np.empty_like(local)
    out[:, axis] = local[:, 2]
    out[:, (axis + 1) % 3] = local[:, 0]
    out[:, (axis + 2) % 3] = local[:, 1]
    return out


def _sphere_rings(radius, centre, lat0, lat1, steps):
    """Rings of the sphere (radius, centre on the spine) from latitude lat0 to lat1, with normals."""
    lat = np.linspace(lat0, lat1, steps + 1)
    r = radius * np.cos(lat)
    r[np.abs(lat) == np.pi / 2] = 0.0           # exact poles, so they collapse to one point
    return r, centre + radius * np.sin(lat), list(zip(np.cos(lat), np.sin(lat)))


def _sphere(s: UsdGeom.Sphere, time, n):
    radius = _size(s.GetRadiusAttr(), time)
    m = max(2, n // 2)
    r, z, nrm = _sphere_rings(radius, 0.0, -np.pi / 2, np.pi / 2, m)
    bands = [(k, k + 1, nrm[k], nrm[k + 1]) for k in range(m)]
    return _lathe(r, z, bands, [], n, 2)


def _frustum(r_bottom, r_top, height, axis, n):
    """Side and two flat caps (a cap of radius 0 is dropped by _lathe)."""
    return _lathe([r_bottom, r_top], [-height / 2, height / 2], [(0, 1, None, None)],
                  [(0, -1), (1, +1)], n, axis)


def _cylinder(s: UsdGeom.Cylinder, time, n):
    radius = _size(s.GetRadiusAttr(), time)
    return _frustum(radius, radius, _size(s.GetHeightAttr(), time), _axis(s.GetAxisAttr(), time), n)


def _cylinder_1(s: UsdGeom.Cylinder_1, time, n):
    return _frustum(_size(s.GetRadiusBottomAttr(), time), _size(s.GetRadiusTopAttr(), time),
                    _size(s.GetHeightAttr(), time), _axis(s.GetAxisAttr(), time), n)


def _cone(s: UsdGeom.Cone, time, n):
    # apex towards +axis: the top ring has radius 0, so it is one point and the side is triangles
    return _frustum(_size(s.GetRadiusAttr(), time), 0.0, _size(s.GetHeightAttr(), time),
                    _axis(s.GetAxisAttr(), time), n)


def _capsule(s: UsdGeom.Capsule, time, n):
    radius = _size(s.GetRadiusAttr(), time)
    return _capsule_mesh(radius, radius, _size(s.GetHeightAttr(), time),
                         _axis(s.GetAxisAttr(), time), n)


def _capsule_1(s: UsdGeom.Capsule_1, time, n):
    return _capsule_mesh(_size(s.GetRadiusBottomAttr(), time), _size(s.GetRadiusTopAttr(), time),
                         _size(s.GetHeightAttr(), time), _axis(s.GetAxisAttr(), time), n)


def _capsule_mesh(r_bottom, r_top, height, axis, n):
    """A frustum of length ``height`` between radii r_bottom (at -height/2) and r_top, closed by
    spherical caps tangent to it at its end rings (C1, as the schema asks).

    With unequal radii the cap spheres are larger than the ring radii (r / cos(alpha), alpha the
    frustum's slope) and their centres move along the spine: this is the shape whose bounds USD
    26.x's Capsule_1 ComputeExtent reports. Equal radii give the usual capsule with hemispheres.
    """
    # alpha: latitude of the tangent rings, where the frustum's outward normal (h, rB - rT) points
    tan_a = (r_bottom - r_top) / height if height > 0 else 0.0
    alpha = math.atan(tan_a)
    cos_a = math.cos(alpha)
    # latitudinal steps of both caps together ~ detail / 2, shared by the angle each cap spans
    m = max(2, n // 2)
    m_bottom = min(max(1, round(m * (alpha + np.pi / 2) / np.pi)), m - 1)
    rb, zb, nb = _sphere_rings(r_bottom / cos_a, -height / 2 - r_bottom * tan_a,
                               -np.pi / 2, alpha, m_bottom)
    rt, zt, nt = _sphere_rings(r_top / cos_a, height / 2 - r_top * tan_a, alpha, np.pi / 2,
                               m - m_bottom)
    # the tangent rings are exact: no drift between the caps and the frustum
    rb[-1], zb[-1], rt[0], zt[0] = r_bottom, -height / 2, r_top, height / 2
    frustum = height > 0 or r_bottom != r_top
    if not frustum:
        rt, zt, nt = rt[1:], zt[1:], nt[1:]      # a sphere: the caps share their equator ring
    r, z, nrm = np.concatenate([rb, rt]), np.concatenate([zb, zt]), nb + nt
    bands = [(k, k + 1, nrm[k], nrm[k + 1]) for k in range(len(r) - 1)]
    side = len(rb) - 1
    if frustum:
        # the frustum between the tangent rings; with height 0 and unequal radii it is a flat
        # annulus, whose normal is the profile's own (None), not the tangent-ring normal
        bands[side] = (side, side + 1, None, None)
    return _lathe(r, z, bands, [], n, axis)


# --- boxes ---------------------------------------------------------------------------------------

# corners of a face spanned by the two axes after its normal axis, counter-clockwise about it
_QUAD = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)


def _cube(s: UsdGeom.Cube, time, n):
    half = _size(s.GetSizeAttr(), time) / 2
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    points = half * signs                        # (8, 3); corner index = 4*(x>0) + 2*(y>0) + (z>0)
    weight = np.array([4, 2, 1])
    indices, normals = [], []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3          # cyclic, so cross(b, c) = +a
        for sign in (-1.0, 1.0):
            quad = _QUAD if sign > 0 else _QUAD[::-1]
            corner = np.zeros((4, 3))
            corner[:, a], corner[:, b], corner[:, c] = sign, quad[:, 0], quad[:, 1]
            indices.append(((corner > 0) @ weight).astype(np.int64))
            nrm = np.zeros((4, 3))
            nrm[:, a] = sign
            normals.append(nrm)
    return PolyMesh(points, np.full(6, 4, np.int64), np.concatenate(indices), np.concatenate(normals))


def _plane(s: UsdGeom.Plane, time, n):
    width, length = _size(s.GetWidthAttr(), time), _size(s.GetLengthAttr(), time)
    a = _axis(s.GetAxisAttr(), time)
    half = np.zeros(3)
    # schema table: width along z for axis X, else x; length along z for axis Y, else y
    half[2 if a == 0 else 0] = width / 2
    half[2 if a == 1 else 1] = length / 2
    b, c = (a + 1) % 3, (a + 2) % 3
    points = np.zeros((4, 3))
    points[:, b], points[:, c] = _QUAD[:, 0] * half[b], _QUAD[:, 1] * half[c]
    normals = np.zeros((4, 3))
    normals[:, a] = 1.0
    return PolyMesh(points, np.array([4], np.int64), np.arange(4, dtype=np.int64), normals)


_BUILDERS = ((UsdGeom.Sphere, _sphere), (UsdGeom.Cube, _cube), (UsdGeom.Cylinder, _cylinder),
             (UsdGeom.Cone, _cone), (UsdGeom.Capsule, _capsule), (UsdGeom.Plane, _plane),
             (UsdGeom.Cylinder_1, _cylinder_1), (UsdGeom.Capsule_1, _capsule_1))
