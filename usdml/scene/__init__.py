"""The render index: a plain-NumPy snapshot of a USD stage at one timecode (no ``pxr`` here).

Conventions used by every array below:

* Matrices are ``(4, 4) float64`` in the *column-vector* convention, ``p_world = M @ [p, 1]``
  (the transpose of USD's row-vector ``GfMatrix4d``).
* Positions are in scene units (``Snapshot.meters_per_unit`` converts to metres), directions are unit
  vectors, angles are degrees where USD authors degrees (cone angle, distant-light angle).
* Triangles are wound right-handed (counter-clockwise seen from the side the geometric normal points to);
  meshes authored ``leftHanded`` are re-wound by the scene delegate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
import hashlib

import numpy as np

from usdml.errors import UsdmlError
from usdml.scene.dome import Dome, latlong_directions, latlong_texel

__all__ = [
    "Mesh", "Prototype", "LightType", "Lights", "Camera", "RenderVar", "RenderProduct",
    "RenderSettings", "Snapshot", "Changes", "diff", "content_hash", "instance_points", "world_geometry",
    "Dome", "latlong_directions", "latlong_texel",
]


def content_hash(*arrays: np.ndarray) -> str:
    """Hex digest of the bytes, shapes and dtypes of ``arrays`` (stable across runs and machines)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


@dataclass(eq=False)
class Mesh:
    """One triangulated mesh.

    ``points`` are in world space for meshes of ``Snapshot.meshes`` and in prototype space for the
    meshes of a :class:`Prototype`.
    """

    path: str                   #: USD prim path of the source ``Mesh``
    id: int                     #: primId: index of this mesh in ``Snapshot.mesh_paths``
    points: np.ndarray          #: (V, 3) float32 vertex positions
    triangles: np.ndarray       #: (T, 3) int32 vertex indices, right-handed winding
    normals: np.ndarray         #: (T, 3, 3) float32 unit shading normal per triangle corner
    albedo: np.ndarray          #: (T, 3, 3) float32 linear RGB per triangle corner (displayColor)
    face_index: np.ndarray      #: (T,) int32 authored face each triangle came from
    double_sided: bool = False
    orientation: str = "rightHanded"   #: as authored (triangles are already re-wound)
    deforming: bool = False     #: points vary over the shot (time samples or UsdSkel)
    #: the faces' bound surfaces (:class:`usdml.scene.shading.MeshShading`: every UsdPreviewSurface input, images
    #: sampled again at each hit), or None: Lambertian ``albedo`` (displayColor), Storm's fallback surface
    shading: object | None = None
    #: the ``MeshLightAPI`` applied to it (:class:`usdml.scene.mesh_light.MeshLight`: its triangles are lights,
    #: :func:`usdml.scene.mesh_light.triangle_lights`), or None
    light: object | None = None

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def geometry_hash(self) -> str:
        return content_hash(self.points, self.triangles)


@dataclass(eq=False)
class Prototype:
    """Geometry shared by N instances, in its own space, never flattened into world copies.

    Sources: a ``PointInstancer`` prototype, a native instanceable prim's prototype, or a single
    non-instanced mesh whose transform is animated (one instance).
    """

    path: str                   #: USD path of the prototype root (``/__Prototype_N/...`` for native ones)
    name: str                   #: readable source: PointInstancer prototype path or first instance path
    kind: str                   #: "pointInstancer", "native" or "rigid"
    meshes: list[Mesh]
    xforms: np.ndarray          #: (N, 4, 4) float64 prototype-to-world
    instance_ids: np.ndarray    #: (N,) int64 PointInstancer ``ids`` (or index); ordinal for native ones
    instancers: list[str]       #: (N,) path of the PointInstancer / instance prim of each instance
    animated: bool = False      #: instance transforms vary over the shot
    deforming: bool = False     #: prototype points vary over the shot

    @property
    def instance_count(self) -> int:
        return int(self.xforms.shape[0])

    @property
    def triangle_count(self) -> int:
        return sum(m.triangle_count for m in self.meshes)

    def merged(self) -> tuple[np.ndarray, np.ndarray]:
        """All meshes as one soup in prototype space: ``(V, 3) float32`` points, ``(T, 3) int32`` triangles
        (the prototype-space counterpart of :func:`world_geometry`)."""
        return _soup([(m.points, m.triangles) for m in self.meshes])

    def geometry_hash(self) -> str:
        return content_hash(*self.merged())


class LightType(IntEnum):
    POINT = 0     #: SphereLight with treatAsPoint or radius 0
    SPHERE = 1
    DISK = 2
    RECT = 3
    DISTANT = 4
    CYLINDER = 5  #: emits from its side, around its axis (the light's X)
    TRIANGLE = 6  #: one triangle of a MeshLightAPI mesh: xform columns edge1, edge2, unit normal, vertex 0


@dataclass(eq=False)
class Lights:
    """All lights of a snapshot, PointInstancer-instanced ones expanded to one entry per instance.

    Radiometry (UsdLux): ``radiance`` L = intensity · 2^exposure · color (· blackbody) (· diffuse),
    divided by the world-space emitting area in m² when ``normalize`` is on. ``intensity`` is what a
    point-like evaluation needs: radiant intensity along the axis in nit·m² (sphere/point: L·π·r²,
    disk: L·π·r², rect: L·w·h, a mesh light's triangle: L·area, lengths in metres), to be divided by the
    squared distance in metres; for cylinders the intensity perpendicular to their axis, L·2r·length (the side's
    projected area); or, for distant lights, the irradiance at normal incidence. Both are negative for a light
    of negative intensity (:meth:`negative`).
    """

    type: np.ndarray            #: (N,) int8 :class:`LightType`
    position: np.ndarray        #: (N, 3) float64 world position
    axis: np.ndarray            #: (N, 3) float64 unit emission direction (the light's -Z in world)
    xform: np.ndarray           #: (N, 4, 4) float64 light-to-world
    radiance: np.ndarray        #: (N, 3) float32 L, nits per channel
    intensity: np.ndarray       #: (N, 3) float32 see class doc
    radius: np.ndarray          #: (N,) float64 world radius (sphere, point, disk, cylinder)
    width: np.ndarray           #: (N,) float64 world width (rect), world length (cylinder)
    height: np.ndarray          #: (N,) float64 world height (rect)
    angle: np.ndarray           #: (N,) float64 angular diameter in degrees (distant)
    cone_angle: np.ndarray      #: (N,) float64 shaping cone half-angle in degrees, 180 = no shaping
    cone_softness: np.ndarray   #: (N,) float64
    focus: np.ndarray           #: (N,) float64
    focus_tint: np.ndarray      #: (N, 3) float32
    shadow: np.ndarray          #: (N,) bool casts shadows (ShadowAPI)
    paths: list[str]            #: (N,) source light prim path
    instance_ids: np.ndarray    #: (N,) int64 PointInstancer instance id, -1 when not instanced
    #: (N,) int32 the light's ``collection:lightLink`` in the frame's :class:`usdml.scene.linking.LinkSets`,
    #: -1: every prim (UsdLux's default); set from :attr:`paths` by :meth:`LinkSets.label`
    light_link: np.ndarray | None = None
    shadow_link: np.ndarray | None = None   #: (N,) int32 its ``collection:shadowLink`` likewise
    group: list[str] | None = None          #: (N,) ``usdml:lightGroup``, "" for none
    #: (N,) float32 ``inputs:diffuse`` and ``inputs:specular`` as factors of the stored radiance and intensity,
    #: which carry ``emission · m`` with ``m = diffuse`` (``specular`` where diffuse is 0): (1, 1) for a light
    #: whose two lobes are scaled alike
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None
    #: (N,) float32 that factor ``m`` itself (1 where it is 0): the camera sees ``radiance / scale``, the light's own
    scale: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.type)
        for name in ("light_link", "shadow_link"):
            if getattr(self, name) is None:
                setattr(self, name, np.full(n, -1, np.int32))
        for name in ("diffuse", "specular", "scale"):
            if getattr(self, name) is None:
                setattr(self, name, np.ones(n, np.float32))
        if self.group is None:
            self.group = [""] * n

    def __len__(self) -> int:
        return int(self.type.shape[0])

    @staticmethod
    def empty() -> "Lights":
        return Lights.concat([])

    @staticmethod
    def concat(parts: list["Lights"]) -> "Lights":
        shapes = {
            "type": ((), np.int8), "position": ((3,), np.float64), "axis": ((3,), np.float64),
            "xform": ((4, 4), np.float64), "radiance": ((3,), np.float32), "intensity": ((3,), np.float32),
            "radius": ((), np.float64), "width": ((), np.float64), "height": ((), np.float64),
            "angle": ((), np.float64), "cone_angle": ((), np.float64), "cone_softness": ((), np.float64),
            "focus": ((), np.float64), "focus_tint": ((3,), np.float32), "shadow": ((), bool),
            "instance_ids": ((), np.int64), "light_link": ((), np.int32), "shadow_link": ((), np.int32),
            "diffuse": ((), np.float32), "specular": ((), np.float32), "scale": ((), np.float32),
        }
        kw = {}
        for name, (shape, dtype) in shapes.items():
            arrs = [getattr(p, name) for p in parts]
            kw[name] = (np.concatenate(arrs).astype(dtype) if arrs else np.zeros((0,) + shape, dtype))
        kw["paths"] = [s for p in parts for s in p.paths]
        kw["group"] = [s for p in parts for s in p.group]
        return Lights(**kw)

    def subset(self, index: np.ndarray) -> "Lights":
        """The lights at ``index`` (an integer array or a boolean mask), in that order."""
        from dataclasses import fields, replace

        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, np.int64)
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            kw[f.name] = [v[i] for i in idx] if isinstance(v, list) else np.asarray(v)[idx]
        return replace(self, **kw)

    def negative(self) -> np.ndarray:
        """``(N,) bool``: the lights of negative intensity, which take light away (UsdLux allows it; colours
        are >= 0, so every channel has the intensity's sign)."""
        return (np.asarray(self.intensity).reshape(-1, 3) < 0).any(axis=1)

    def cylinder_axis(self) -> np.ndarray:
        """(N, 3) float64 unit world direction of each light's local X (a cylinder light's axis)."""
        x = np.asarray(self.xform, np.float64)[:, :3, 0]
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        return np.where(norm > 0, x / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0])

    def type_counts(self) -> dict[str, int]:
        names, counts = np.unique(self.type, return_counts=True)
        return {LightType(int(n)).name.lower(): int(c) for n, c in zip(names, counts)}

    def state_hash(self) -> str:
        return content_hash(self.type, self.xform, self.radiance, self.radius, self.width, self.height,
                            self.angle, self.cone_angle, self.cone_softness, self.focus, self.focus_tint,
                            self.shadow)


@dataclass(eq=False)
class Camera:
    """A ``UsdGeom.Camera`` at one timecode. Apertures and focal length share USD's unit (tenths of a scene unit, "mm")."""

    path: str                   #: prim path, or "" for a synthesized framing camera
    xform: np.ndarray           #: (4, 4) float64 camera-to-world (camera looks down its -Z, +Y up)
    focal_length: float
    horizontal_aperture: float
    vertical_aperture: float
    horizontal_aperture_offset: float = 0.0
    vertical_aperture_offset: float = 0.0
    clipping_range: tuple[float, float] = (1.0, 1000000.0)
    projection: str = "perspective"     #: "perspective" or "orthographic"
    f_stop: float = 0.0                 #: the lens's f-number; 0: a pinhole (no depth of field)
    focus_distance: float = 0.0         #: scene units from the camera to the plane in focus
    #: (open, close) of the shutter in timecodes around the frame's time; open == close: no motion blur
    shutter: tuple[float, float] = (0.0, 0.0)

    @property
    def lens_radius(self) -> float:
        """The thin lens's radius in scene units: ``focalLength / fStop / 2`` with the focal length in tenths of
        a scene unit (USD's lens unit, GfCamera's ``FOCAL_LENGTH_UNIT``); 0 where there is no depth of field (fStop
        or focusDistance 0, an orthographic camera)."""
        if self.projection != "perspective" or self.f_stop <= 0 or self.focus_distance <= 0:
            return 0.0
        return self.focal_length * 0.1 / self.f_stop / 2.0

    @property
    def aspect(self) -> float:
        """Width / height of the film back."""
        return self.horizontal_aperture / self.vertical_aperture

    def resolution(self, width: int) -> tuple[int, int]:
        """Image size for ``width`` pixels, height from the aperture aspect (as usdrecord does)."""
        return int(width), max(1, int(round(width / self.aspect)))

    def projection_matrix(self) -> np.ndarray:
        """(4, 4) camera-to-clip in OpenGL NDC (x, y, z in [-1, 1], z = -1 at the near plane)."""
        n, f = self.clipping_range
        if self.projection == "orthographic":
            # USD: orthographic apertures are in tenths of a scene unit.
            hw, hh = self.horizontal_aperture / 20.0, self.vertical_aperture / 20.0
            ox, oy = self.horizontal_aperture_offset / 10.0, self.vertical_aperture_offset / 10.0
            m = np.eye(4)
            m[0, 0], m[0, 3] = 1 / hw, -ox / hw
            m[1, 1], m[1, 3] = 1 / hh, -oy / hh
            m[2, 2], m[2, 3] = -2 / (f - n), -(f + n) / (f - n)
            return m
        sx = 2 * self.focal_length / self.horizontal_aperture
        sy = 2 * self.focal_length / self.vertical_aperture
        cx = 2 * self.horizontal_aperture_offset / self.horizontal_aperture
        cy = 2 * self.vertical_aperture_offset / self.vertical_aperture
        return np.array([
            [sx, 0, cx, 0],
            [0, sy, cy, 0],
            [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0, 0, -1, 0],
        ], np.float64)


@dataclass
class RenderVar:
    path: str
    name: str           #: the RenderVar prim's name (AOV name in the product)
    source_name: str
    source_type: str    #: "raw", "primvar", "lpe" or "intrinsic"
    data_type: str      #: e.g. "color3f", "float"


@dataclass
class RenderProduct:
    path: str
    product_name: str           #: resolved at the snapshot's timecode
    product_type: str           #: "raster" by default
    vars: list[RenderVar]
    camera: str | None = None   #: override of the settings' camera
    resolution: tuple[int, int] | None = None
    name_time_varying: bool = False


@dataclass
class RenderSettings:
    """``UsdRender.Settings`` with its products and ordered vars, as plain data."""

    path: str
    camera: str | None
    resolution: tuple[int, int]
    pixel_aspect_ratio: float
    products: list[RenderProduct]
    included_purposes: list[str] = field(default_factory=lambda: ["default", "render"])
    disable_motion_blur: bool = False       #: UsdRender's ``disableMotionBlur``
    disable_depth_of_field: bool = False    #: UsdRender's ``disableDepthOfField``


@dataclass(eq=False)
class Snapshot:
    """Everything a render pass may read for one timecode."""

    time: float
    stage_path: str
    meshes: list[Mesh]              #: non-instanced meshes in world space (static or deforming)
    prototypes: list[Prototype]     #: instanced and rigidly animated geometry
    lights: Lights
    camera: Camera | None
    render_settings: RenderSettings | None
    mesh_paths: list[str]           #: primId -> mesh path, for every mesh of the snapshot
    start_time: float = 1.0
    end_time: float = 1.0
    time_codes_per_second: float = 24.0
    meters_per_unit: float = 0.01
    up_axis: str = "Y"
    #: dome lights, turned into distant lights per frame (:func:`usdml.lighting.dome.dome_to_distant_lights`)
    domes: list[Dome] = field(default_factory=list)
    #: light and shadow linking and light groups (:class:`usdml.scene.linking.LinkSets`), None: none read
    links: object | None = None

    @property
    def static_meshes(self) -> list[Mesh]:
        return [m for m in self.meshes if not m.deforming]

    @property
    def deforming_meshes(self) -> list[Mesh]:
        return [m for m in self.meshes if m.deforming]

    def triangle_count(self) -> int:
        """Triangles as rendered: prototype triangles count once per instance."""
        return (sum(m.triangle_count for m in self.meshes)
                + sum(p.triangle_count * p.instance_count for p in self.prototypes))

    def unique_triangle_count(self) -> int:
        return sum(m.triangle_count for m in self.meshes) + sum(p.triangle_count for p in self.prototypes)

    def world_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Axis-aligned (min, max) of all geometry in world space, or None when there is none."""
        lo, hi = [], []
        for m in self.meshes:
            if len(m.points):
                lo.append(m.points.min(0))
                hi.append(m.points.max(0))
        for p in self.prototypes:
            pts, _ = p.merged()
            if not len(pts) or not p.instance_count:
                continue
            a, b = pts.min(0).astype(np.float64), pts.max(0).astype(np.float64)
            corners = np.array([[x, y, z, 1.0] for x in (a[0], b[0]) for y in (a[1], b[1]) for z in (a[2], b[2])])
            w = np.einsum("nij,kj->nki", p.xforms, corners)[..., :3].reshape(-1, 3)
            lo.append(w.min(0))
            hi.append(w.max(0))
        if not lo:
            return None
        return np.min(lo, 0), np.max(hi, 0)


def _soup(pieces: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One triangle soup from ``(points (V, 3), triangles (T, 3))`` pieces, each piece's triangles
    indexing its own points: ``(ΣV, 3)`` points (their dtype), ``(ΣT, 3) int32`` triangles."""
    if not pieces:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    sizes = [p.shape[0] for p, _ in pieces]
    if sum(sizes) >= 2 ** 31:
        raise UsdmlError(f"{sum(sizes)} flattened vertices exceed 32-bit triangle indices; render with an "
                         "approximate backend (--visibility voxel) or fewer static instances")
    offsets = np.cumsum([0] + sizes[:-1])
    pts = np.concatenate([p for p, _ in pieces])
    tris = np.concatenate([t + o for (_, t), o in zip(pieces, offsets)]).astype(np.int32)
    return pts, tris


def instance_points(xforms: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N, V, 3) float64`` world positions of prototype-space ``points (V, 3)`` under each of
    ``xforms (N, 4, 4)`` (prototype-to-world, column convention), transformed in float64."""
    xf = np.asarray(xforms, np.float64).reshape(-1, 4, 4)
    v = np.asarray(points, np.float64).reshape(-1, 3)
    return np.einsum("nij,vj->nvi", xf[:, :3, :3], v) + xf[:, None, :3, 3]


def world_geometry(snapshot: "Snapshot", members) -> tuple[np.ndarray, np.ndarray]:
    """World-space ``(V, 3) float32`` points and ``(T, 3) int32`` triangles of ``members``, prototype
    instances flattened into world copies.

    ``members`` is a sequence of ``("mesh", path)`` (a mesh of ``snapshot.meshes``, already in world
    space) and ``("proto", path)`` (every instance of a prototype of ``snapshot.prototypes``). The
    triangles come in that order; a prototype's mesh-major: for each of its meshes, every instance
    (the order of :class:`usdml.visibility.exact.SourceTable`). Raises :class:`UsdmlError` past
    2³¹ vertices.
    """
    meshes = {m.path: m for m in snapshot.meshes}
    protos = {p.path: p for p in snapshot.prototypes}
    pieces: list[tuple[np.ndarray, np.ndarray]] = []
    for kind, path in members:
        if kind == "mesh":
            m = meshes[path]
            pieces.append((np.asarray(m.points, np.float32).reshape(-1, 3),
                           np.asarray(m.triangles, np.int64).reshape(-1, 3)))
            continue
        p = protos[path]
        for m in p.meshes:
            world = instance_points(p.xforms, m.points)                 # (n, V, 3)
            n, nv = world.shape[:2]
            t = np.asarray(m.triangles, np.int64).reshape(-1, 3)
            tris = (t[None] + (nv * np.arange(n, dtype=np.int64))[:, None, None]).reshape(-1, 3)
            pieces.append((world.reshape(-1, 3).astype(np.float32), tris))
    return _soup(pieces)


@dataclass
class Changes:
    """What changed between two snapshots, so passes rebuild only that.

    ``prototypes`` maps a prototype path to a set drawn from {"added", "removed", "transforms", "points"};
    an empty set means nothing changed.
    """

    static: bool                                #: any non-deforming world-space mesh changed
    deforming: list[str]                        #: paths of world-space meshes whose points changed
    prototypes: dict[str, set[str]]
    lights: bool
    camera: bool

    @property
    def geometry(self) -> bool:
        """Any mesh or instance moved, deformed, appeared or went."""
        return self.static or bool(self.deforming) or any(self.prototypes.values())

    @property
    def anything(self) -> bool:
        return self.geometry or self.lights or self.camera


def _mesh_changed(a: Mesh, b: Mesh) -> bool:
    # the delegate hands out the same Mesh object while nothing changed: skip hashing then
    return a is not b and content_hash(a.points, a.triangles) != content_hash(b.points, b.triangles)


def diff(prev: Snapshot | None, cur: Snapshot) -> Changes:
    """Compare two snapshots of the same stage; ``prev=None`` means everything is new."""
    if prev is None:
        return Changes(static=True, deforming=[m.path for m in cur.deforming_meshes],
                       prototypes={p.path: {"added"} for p in cur.prototypes}, lights=True, camera=True)
    before = {m.path: m for m in prev.meshes}
    static = ({m.path for m in prev.static_meshes} != {m.path for m in cur.static_meshes}
              or any(_mesh_changed(m, before[m.path]) for m in cur.static_meshes if m.path in before))
    deforming = [m.path for m in cur.deforming_meshes
                 if m.path not in before or _mesh_changed(m, before[m.path])]
    protos: dict[str, set[str]] = {}
    old = {p.path: p for p in prev.prototypes}
    for p in cur.prototypes:
        q = old.pop(p.path, None)
        if q is None:
            protos[p.path] = {"added"}
            continue
        what = set()
        if p.xforms.shape != q.xforms.shape or not np.array_equal(p.xforms, q.xforms) \
                or not np.array_equal(p.instance_ids, q.instance_ids):
            what.add("transforms")
        same_meshes = len(p.meshes) == len(q.meshes) and all(a is b for a, b in zip(p.meshes, q.meshes))
        if not same_meshes and p.geometry_hash() != q.geometry_hash():
            what.add("points")
        protos[p.path] = what
    for path in old:
        protos[path] = {"removed"}
    cam = (prev.camera is None) != (cur.camera is None) or (
        cur.camera is not None and (not np.array_equal(prev.camera.xform, cur.camera.xform)
                                    or prev.camera.focal_length != cur.camera.focal_length))
    return Changes(static=static, deforming=deforming, prototypes=protos,
                   lights=prev.lights.state_hash() != cur.lights.state_hash(), camera=bool(cam))
