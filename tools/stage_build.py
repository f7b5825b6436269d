"""The conventions and building blocks every generated stage shares: the stage metadata (metersPerUnit 1,
upAxis Y, 24 fps, defaultPrim </World>), the 35 mm camera, </Render/Settings> with its six AOVs, the bulb
colours, ``MeshBuilder`` and the point-light instancer, and ``settled``: every computed value rounded
before it is written, so the files are the same bytes on any machine.

Imported by ``make_stages.py`` (the sample stages), ``stage_suite.py`` (the seeded suite) and
``make_city.py`` (the unseen cities); it imports none of them.
"""
import math
import os

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, Vt

FPS = 24
RESOLUTION = (960, 540)
UP = np.array([0.0, 1.0, 0.0])

# (name, sourceName, dataType) of the RenderVars every product writes.
RENDER_VARS = [
    ("color", "color", "color4f"),
    ("depth", "depth", "float"),
    ("normal", "normal", "normal3f"),
    ("direct", "direct", "color3f"),
    ("shadow", "shadow", "float"),
    ("primId", "primId", "int"),
]

# Bulb colours used as light prototypes (PointInstancers cannot vary a
# light's colour per instance, so colour variety comes from prototypes).
BULBS = {
    "warm": (1.0, 0.78, 0.52),
    "cool": (0.70, 0.82, 1.0),
    "white": (1.0, 1.0, 1.0),
    "pink": (1.0, 0.55, 0.75),
}


# --------------------------------------------------------------------------
# Small math helpers
# --------------------------------------------------------------------------

def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def frame_times(start, end):
    """Frame numbers (time codes) and matching seconds from the first one."""
    frames = np.arange(start, end + 1, dtype=float)
    return frames, (frames - start) / FPS


def yaw_quats(yaw):
    """Quaternions (x, y, z, w) rotating about +Y by ``yaw`` radians.

    Rotating +Z by yaw gives (sin yaw, 0, cos yaw): prototypes face +Z.
    """
    yaw = np.asarray(yaw, dtype=float)
    z = np.zeros_like(yaw)
    return np.stack([z, np.sin(yaw / 2), z, np.cos(yaw / 2)], axis=-1)


def axis_angle_quat(axis, angle):
    """Quaternion (w, x, y, z) tuple for a rotation of ``angle`` radians."""
    axis = unit(axis)
    s = math.sin(angle / 2)
    return (math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s)


def quat_mul(a, b):
    """Hamilton product of (w, x, y, z) tuples."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def basis_quat(x_axis, y_axis, z_axis):
    """Quaternion (x, y, z, w) mapping local X/Y/Z onto the given unit axes."""
    m = Gf.Matrix3d(*[float(c) for c in (*x_axis, *y_axis, *z_axis)])
    q = m.ExtractRotation().GetQuat()
    i = q.GetImaginary()
    return (i[0], i[1], i[2], q.GetReal())


def look_at(eye, target, up=UP):
    """Camera-to-world matrix: USD cameras look down local -Z with +Y up."""
    eye = np.asarray(eye, dtype=float)
    fwd = unit(np.asarray(target, dtype=float) - eye)
    right = unit(np.cross(fwd, up))
    cam_up = np.cross(right, fwd)
    rows = [(*right, 0.0), (*cam_up, 0.0), (*(-fwd), 0.0), (*eye, 1.0)]
    return Gf.Matrix4d(*[float(c) for c in settled(rows, 9).ravel()])


def settled(values, decimals):
    """``values`` rounded to ``decimals`` (float64 array), with -0.0 written as 0.0: what the
    stages store, so an ulp of difference in how numpy computed them never changes a byte."""
    return np.round(np.asarray(values, dtype=np.float64), decimals) + 0.0


def settled_points(points):
    """``(n, 3)`` points or positions as the Vec3fArray a stage stores: settled to 1e-5 scene units."""
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(settled(points, 5), dtype=np.float32))


def round_sig(x, digits=2):
    return float(f"{x:.{digits}g}")


# --------------------------------------------------------------------------
# Mesh building
# --------------------------------------------------------------------------

class MeshBuilder:
    """Accumulates polygons with per-face colours.

    Vertices are welded on a 10 micron grid so boxes and facade grids come
    out watertight.  Every ``add_*`` takes an outward hint and flips the
    polygon if needed, so winding is consistently counter-clockwise seen from
    outside (USD's rightHanded orientation) without hand-checking each face.
    """

    def __init__(self):
        self.points = []
        self.lookup = {}
        self.counts = []
        self.indices = []
        self.colors = []

    def _vertex(self, p):
        key = (round(float(p[0]), 5), round(float(p[1]), 5), round(float(p[2]), 5))
        idx = self.lookup.get(key)
        if idx is None:
            idx = self.lookup[key] = len(self.points)
            self.points.append(key)
        return idx

    def add_poly(self, pts, color, outward):
        pts = [np.asarray(p, dtype=float) for p in pts]
        # Newell's method: robust normal for any planar-ish polygon.
        normal = np.zeros(3)
        for a, b in zip(pts, pts[1:] + pts[:1]):
            normal += np.cross(a, b)
        if np.dot(normal, outward) < 0:
            pts = pts[::-1]
        self.counts.append(len(pts))
        self.indices.extend(self._vertex(p) for p in pts)
        self.colors.append(tuple(color))

    def add_prism(self, poly2d, origin, u, v, w0, w1, color, cap_color=None):
        """Extrude a convex polygon given in the (u, v) plane along u x v."""
        origin, u, v = (np.asarray(a, dtype=float) for a in (origin, u, v))
        w = np.cross(u, v)
        base = [origin + u * a + v * b for a, b in poly2d]
        bottom = [p + w * w0 for p in base]
        top = [p + w * w1 for p in base]
        center = sum(base) / len(base) + w * (w0 + w1) / 2
        cap = cap_color or color
        self.add_poly(top, cap, w)
        self.add_poly(bottom, cap, -w)
        n = len(base)
        for i in range(n):
            j = (i + 1) % n
            quad = [bottom[i], bottom[j], top[j], top[i]]
            self.add_poly(quad, color, sum(quad) / 4 - center)

    def add_box(self, lo, hi, color, cap_color=None):
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        rect = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
        # u = +X, v = +Z -> extrusion axis u x v = -Y, hence the negated heights.
        self.add_prism(rect, (0, 0, 0), (1, 0, 0), (0, 0, 1), -y1, -y0, color, cap_color)

    def add_cylinder(self, center, radius, y0, y1, sides, color, cap_color=None, phase=0.0):
        """Vertical n-gon prism: small n (5-8) gives the n-gon caps we want."""
        poly = regular_polygon(sides, radius, phase)
        cx, cz = center[0], center[-1]
        poly = [(cx + a, cz + b) for a, b in poly]
        self.add_prism(poly, (0, 0, 0), (1, 0, 0), (0, 0, 1), -y1, -y0, color, cap_color)

    def add_beam(self, p0, p1, width, height, color, up_hint=(0, 1, 0)):
        """Rectangular bar from p0 to p1 (width along the side axis)."""
        p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
        axis = p1 - p0
        length = np.linalg.norm(axis)
        w = axis / length
        side = np.cross(np.asarray(up_hint, dtype=float), w)
        if np.linalg.norm(side) < 1e-6:
            side = np.cross((1.0, 0.0, 0.0), w)
        u = unit(side)
        v = np.cross(w, u)  # u x v = w
        hw, hh = width / 2, height / 2
        rect = [(-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh)]
        self.add_prism(rect, p0, u, v, 0.0, length, color)

    def add_pyramid(self, base_center, radius, y0, height, sides, color, phase=0.0):
        """n-gon base + triangle fan: a spire/cap (base is an n-gon face)."""
        cx, cz = base_center
        ring = [np.array((cx + a, y0, cz + b)) for a, b in regular_polygon(sides, radius, phase)]
        apex = np.array((cx, y0 + height, cz))
        self.add_poly(ring, color, (0, -1, 0))
        for i in range(sides):
            tri = [ring[i], ring[(i + 1) % sides], apex]
            self.add_poly(tri, color, sum(tri) / 3 - np.array((cx, y0 + height / 3, cz)))

    def add_uv_sphere(self, center, radius, segments, rings, color):
        c = np.asarray(center, dtype=float)

        def at(i, j):
            th = math.pi * i / rings
            ph = 2 * math.pi * j / segments
            return c + radius * np.array((math.sin(th) * math.cos(ph), math.cos(th),
                                          math.sin(th) * math.sin(ph)))

        for i in range(rings):
            for j in range(segments):
                quad = [at(i, j), at(i, j + 1), at(i + 1, j + 1), at(i + 1, j)]
                if i == 0:
                    quad = [quad[0], quad[2], quad[3]]  # pole: triangle
                elif i == rings - 1:
                    quad = quad[:3]
                self.add_poly(quad, color, sum(quad) / len(quad) - c)

    @property
    def triangle_count(self):
        return int(sum(n - 2 for n in self.counts))


def regular_polygon(sides, radius, phase=0.0):
    return [(radius * math.cos(phase + 2 * math.pi * k / sides),
             radius * math.sin(phase + 2 * math.pi * k / sides)) for k in range(sides)]


def define_mesh(stage, path, mb):
    """Author a UsdGeom.Mesh from a MeshBuilder (flat, no subdivision)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    points = settled_points(mb.points)
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray(mb.counts))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(mb.indices))
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    set_display_color(mesh, mb.colors)
    return mesh


def set_display_color(gprim, face_colors):
    """Constant colour when all faces agree, else one colour per face."""
    unique = sorted(set(face_colors))
    if len(unique) == 1:
        pv = gprim.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant)
        pv.Set(Vt.Vec3fArray([Gf.Vec3f(*unique[0])]))
    else:
        pv = gprim.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform)
        pv.Set(Vt.Vec3fArray([Gf.Vec3f(*c) for c in face_colors]))


# --------------------------------------------------------------------------
# Stage plumbing: creation, cameras, render settings, lights
# --------------------------------------------------------------------------

def remove(path):
    if os.path.exists(path):
        os.remove(path)


def new_stage(path, start, end, default_prim="World"):
    """Fresh layer with the shared stage metadata and an Xform default prim."""
    remove(path)
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(end)
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetFramesPerSecond(FPS)
    root = UsdGeom.Xform.Define(stage, "/" + default_prim)
    stage.SetDefaultPrim(root.GetPrim())
    # Assembly root keeps the model hierarchy valid above component assets.
    Usd.ModelAPI(root).SetKind("assembly")
    return stage


def add_anim_layer(stage, out_dir, name):
    """Create ``anim/<name>.usdc`` as the weakest sublayer of ``stage``.

    Per-frame PointInstancer data for thousands of instances is megabytes as
    text; binary crate keeps the .usda readable and the repo small.  Callers
    author into it with ``Usd.EditContext(stage, layer)``.
    """
    rel = f"./anim/{name}.usdc"
    path = os.path.join(out_dir, "anim", f"{name}.usdc")
    remove(path)
    layer = Sdf.Layer.CreateNew(path)
    # Same rate as the root layer, so no implicit time scaling on sublayering.
    layer.timeCodesPerSecond = FPS
    layer.framesPerSecond = FPS
    stage.GetRootLayer().subLayerPaths.append(rel)
    return layer


def define_ground(stage, half, albedo=None, path="/World/ground"):
    """A square ground ``2 half`` wide at y = 0, one quad facing up (+Y); grey ``albedo`` as its displayColor."""
    ground = UsdGeom.Mesh.Define(stage, path)
    ground.CreatePointsAttr([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    if albedo is not None:
        ground.CreateDisplayColorPrimvar().Set([(albedo, albedo, albedo)])
    return ground


def define_camera(stage, eyes, targets, clip, frames=None, path="/World/main_cam"):
    """35 mm lens on a 16:9 back; ``eyes``/``targets`` per frame if animated."""
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    cam.CreateFocalLengthAttr(35.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(20.25)
    cam.CreateClippingRangeAttr(Gf.Vec2f(*clip))
    set_camera_xform(cam, eyes, targets, frames)
    return cam


def set_camera_xform(cam, eyes, targets, frames=None):
    op = cam.MakeMatrixXform()
    if frames is None:
        op.Set(look_at(eyes, targets))
    else:
        for f, eye, target in zip(frames, eyes, targets):
            op.Set(look_at(eye, target), Usd.TimeCode(float(f)))


def define_render_settings(stage, product_name, camera_path="/World/main_cam"):
    """</Render/Settings> -> one product -> the six standard AOVs."""
    UsdGeom.Scope.Define(stage, "/Render")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(*RESOLUTION))
    settings.CreateCameraRel().SetTargets([Sdf.Path(camera_path)])
    # Codeless schema registered by usdml; we only author the apiSchemas op.
    settings.GetPrim().AddAppliedSchema("UsdmlRenderSettingsAPI")

    product = UsdRender.Product.Define(stage, "/Render/Product")
    product.CreateProductNameAttr(product_name)
    var_paths = []
    for name, source, dtype in RENDER_VARS:
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateSourceNameAttr(source)
        var.CreateDataTypeAttr(dtype)
        var.CreateSourceTypeAttr(UsdRender.Tokens.raw)
        var_paths.append(var.GetPath())
    product.CreateOrderedVarsRel().SetTargets(var_paths)
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return settings


def calibrate_intensity(light_pos, radius, samples, normals, target=0.3, albedo=0.5):
    """Bulb radiance giving ``target`` mean unshadowed exitant radiance.

    A treat-as-point sphere light of radius r and radiance L has radiant
    intensity I = L*pi*r^2; a Lambertian point receives E = sum I cos/d^2 and
    reflects albedo*E/pi.  Shadows only lower the real value.
    """
    to_light = light_pos[None, :, :] - samples[:, None, :]
    d2 = np.maximum(np.sum(to_light ** 2, axis=-1), 0.25)  # clamp near-field
    cos = np.clip(np.einsum("mnk,mk->mn", to_light, normals) / np.sqrt(d2), 0, None)
    irradiance_per_l = np.sum(math.pi * radius ** 2 * cos / d2, axis=1)
    exitant_per_l = albedo / math.pi * irradiance_per_l
    return round_sig(target / float(np.mean(exitant_per_l)))


def define_light_instancer(stage, anim_layer, path, protos, radius, intensity,
                           proto_indices, positions, frames):
    """PointInstancer of point-like SphereLights with per-frame positions.

    ``protos`` are BULBS keys; ``positions`` is (frames, lights, 3), time-sampled in
    ``anim_layer``, or (lights, 3) with ``frames`` None: a static set, its one value authored
    in the stage's root layer (``anim_layer`` unused).
    """
    pi = UsdGeom.PointInstancer.Define(stage, path)
    UsdGeom.Scope.Define(stage, f"{path}/Prototypes")
    proto_paths = []
    for name in protos:
        light = UsdLux.SphereLight.Define(stage, f"{path}/Prototypes/bulb_{name}")
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(radius)
        light.CreateNormalizeAttr(False)
        light.CreateIntensityAttr(intensity)
        light.CreateColorAttr(Gf.Vec3f(*BULBS[name]))
        proto_paths.append(light.GetPath())
    pi.CreatePrototypesRel().SetTargets(proto_paths)
    pi.CreateProtoIndicesAttr(Vt.IntArray([int(i) for i in proto_indices]))
    pi.CreateIdsAttr(Vt.Int64Array(list(range(len(proto_indices)))))
    if frames is None:
        pi.CreatePositionsAttr().Set(settled_points(positions))
        return pi
    with Usd.EditContext(stage, anim_layer):
        attr = pi.CreatePositionsAttr()
        for f, pos in zip(frames, positions):
            attr.Set(settled_points(pos), Usd.TimeCode(float(f)))
    return pi


def set_instancer_xforms(stage, anim_layer, pi, frames, positions, orientations):
    """Time-sampled positions (F, N, 3) and quath orientations (F, N, x y z w)."""
    with Usd.EditContext(stage, anim_layer):
        pos_attr = pi.CreatePositionsAttr()
        ori_attr = pi.CreateOrientationsAttr()
        for f, pos, ori in zip(frames, positions, orientations):
            t = Usd.TimeCode(float(f))
            pos_attr.Set(settled_points(pos), t)
            ori_attr.Set(Vt.QuathArray.FromNumpy(np.ascontiguousarray(ori, dtype=np.float16)), t)


def write_asset(path, name, meshes, root_type="Xform"):
    """Binary asset layer: default prim ``name`` holding named Mesh prims."""
    remove(path)
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = stage.DefinePrim(f"/{name}", root_type)
    stage.SetDefaultPrim(root)
    Usd.ModelAPI(root).SetKind("component")
    for mesh_name, mb in meshes.items():
        define_mesh(stage, f"/{name}/{mesh_name}", mb)
    stage.Save()
    return stage
