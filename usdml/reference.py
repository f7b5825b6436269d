"""An independent reference renderer: a stage read with ``pxr`` alone and rendered by Mitsuba 3.

Nothing here imports usdml's renderer (stage delegate, snapshot, backends, shading): the stage is
read again from USD, triangulated, placed and lit by its own code, and Mitsuba's ``scalar_rgb``
variant traces it (the LLVM variants abort on some CPUs). What it understands is what the
comparison stages use: ``UsdGeom.Mesh`` (fan-triangulated, faceted: Mitsuba's ``face_normals``),
constant or uniform ``primvars:displayColor`` as a two-sided diffuse albedo (0.18 otherwise),
``SphereLight`` (authored, or instanced by a ``PointInstancer``) as a point light at its centre with
radiant intensity ``L·π·r²`` (UsdLux's convention as the README states it: ``L = intensity ·
2^exposure · color``, divided by ``4πr²`` with ``normalize``), and one perspective ``UsdGeom.Camera``;
anything else raises ``ValueError``.

* :func:`render` — a pixel-integrated image (box filter, ``spp`` samples per pixel) of direct light
  (``path`` with ``max_depth = 2``) or of ``bounces`` diffuse bounces (``max_depth = bounces + 2``).
* :func:`shadow_fraction` — paper 000's hiddenLightsN / n at every pixel centre by Mitsuba's own
  ray queries: which lights are in front of the surface, and which of them another surface blocks.

Requires ``mitsuba`` (``pip install mitsuba``, in usdml's ``test`` extra).
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

DEFAULT_ALBEDO = 0.18
LUMA = np.array([0.2126, 0.7152, 0.0722])     #: Rec. 709 luminance weights


def mitsuba():
    """The ``mitsuba`` module with the ``scalar_rgb`` variant set."""
    import mitsuba as mi

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


@dataclass
class ReferenceScene:
    definition: dict                #: Mitsuba scene dictionary: sensor and shapes, no emitters
    lights: np.ndarray              #: (L, 3) float64 point-light positions (scene units)
    intensity: np.ndarray           #: (L, 3) float64 radiant intensity per unit of squared scene distance
    width: int
    height: int
    diagonal: float                 #: of the geometry's bounds, scene units

    def scene(self, lights=None, weighted: bool = False):
        """The loaded ``mitsuba.Scene`` with the point lights ``lights`` (indices; default all);
        ``weighted``: a path picks a light in proportion to its intensity's luminance, not uniformly."""
        mi = mitsuba()
        scene = dict(self.definition)
        for i in range(len(self.lights)) if lights is None else lights:
            scene[f"light{i}"] = {"type": "point", "position": self.lights[i].tolist(),
                                  "intensity": {"type": "rgb", "value": self.intensity[i].tolist()}}
            if weighted:
                scene[f"light{i}"]["sampling_weight"] = max(float(self.intensity[i] @ LUMA), 1e-12)
        return mi.load_dict(scene)

    def light_groups(self, count: int) -> list[list[int]]:
        """The lights in at most ``count`` groups of neighbours (recursive halving of the positions
        along their longest axis), for renders made group by group."""
        groups = [np.arange(len(self.lights))]
        while len(groups) < count and max(len(g) for g in groups) > 1:
            g = groups.pop(int(np.argmax([len(g) for g in groups])))
            p = self.lights[g]
            order = g[np.argsort(p[:, int(np.argmax(np.ptp(p, axis=0)))], kind="stable")]
            groups += [order[: len(g) // 2], order[len(g) // 2:]]
        return [sorted(map(int, g)) for g in groups]


def _world(cache: UsdGeom.XformCache, prim: Usd.Prim) -> np.ndarray:
    """USD's row-vector local-to-world matrix of ``prim`` as (4, 4) float64."""
    return np.array(cache.GetLocalToWorldTransform(prim), np.float64)


def _triangles(counts, indices) -> list[tuple[int, int, int, int]]:
    """``(face, a, b, c)`` of every triangle of a fan triangulation."""
    out, start = [], 0
    for face, n in enumerate(counts):
        for k in range(1, n - 1):
            out.append((face, indices[start], indices[start + k], indices[start + k + 1]))
        start += n
    return out


def _face_albedo(mesh: UsdGeom.Mesh, time: Usd.TimeCode, faces: int) -> np.ndarray:
    pv = UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("displayColor")
    value = pv.ComputeFlattened(time) if pv and pv.HasValue() else None
    if value is None or len(value) == 0:
        return np.full((faces, 3), DEFAULT_ALBEDO)
    value = np.asarray(value, np.float64)
    interp = pv.GetInterpolation()
    if interp == UsdGeom.Tokens.constant:
        return np.repeat(value[:1], faces, axis=0)
    if interp == UsdGeom.Tokens.uniform and len(value) == faces:
        return value
    raise ValueError(f"{mesh.GetPath()}: displayColor interpolation {interp!r} is not supported by the reference")


def _light_prims(stage: Usd.Stage, time: Usd.TimeCode, cache: UsdGeom.XformCache):
    """``(prim, (4, 4) world matrix)`` of every light: authored ones, and one per instance of a light a
    ``PointInstancer`` instances (its prototype's transform below the instancer, then the instance's,
    then the instancer's; the prototypes themselves are not lights)."""
    out, prototypes = [], set()
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer):
            pi = UsdGeom.PointInstancer(prim)
            roots = [stage.GetPrimAtPath(p) for p in pi.GetPrototypesRel().GetTargets()]
            prototypes.update(r.GetPath() for r in roots)
            xforms = pi.ComputeInstanceTransformsAtTime(time, time, UsdGeom.PointInstancer.ExcludeProtoXform)
            indices = list(pi.GetProtoIndicesAttr().Get(time) or [])
            world = _world(cache, prim)
            for j, root in enumerate(roots):
                for light in Usd.PrimRange(root):
                    if not light.HasAPI(UsdLux.LightAPI):
                        continue
                    local = np.array(cache.ComputeRelativeTransform(light, root.GetParent())[0], np.float64)
                    out += [(light, local @ np.array(xforms[k], np.float64) @ world)
                            for k, i in enumerate(indices) if i == j]
    for prim in stage.Traverse():
        if any(prim.GetPath().HasPrefix(p) for p in prototypes):
            continue
        if prim.HasAPI(UsdLux.LightAPI) or prim.IsA(UsdLux.BoundableLightBase) \
                or prim.IsA(UsdLux.NonboundableLightBase):
            out.append((prim, _world(cache, prim)))
    return out


def _lights(stage: Usd.Stage, time: Usd.TimeCode, cache: UsdGeom.XformCache, to_metres: float):
    positions, intensities = [], []
    for prim, m in _light_prims(stage, time, cache):
        if not prim.IsA(UsdLux.SphereLight):
            raise ValueError(f"{prim.GetPath()}: only SphereLights are supported by the reference")
        light = UsdLux.SphereLight(prim)
        if prim.HasAPI(UsdLux.ShapingAPI) or light.GetEnableColorTemperatureAttr().Get(time):
            raise ValueError(f"{prim.GetPath()}: shaping and colour temperature are not supported by the reference")
        radiance = (light.GetIntensityAttr().Get(time) * 2.0 ** light.GetExposureAttr().Get(time)
                    * np.asarray(light.GetColorAttr().Get(time), np.float64))
        r = light.GetRadiusAttr().Get(time) * float(np.linalg.norm(m[0, :3])) * to_metres
        if light.GetNormalizeAttr().Get(time):
            radiance = radiance / (4.0 * math.pi * r * r)
        # I in nit·m²; Mitsuba divides by squared scene distances, the README's falloff by metres²
        intensities.append(radiance * math.pi * r * r / to_metres ** 2)
        positions.append(m[3, :3])
    return np.array(positions, np.float64).reshape(-1, 3), np.array(intensities, np.float64).reshape(-1, 3)


def _camera(stage: Usd.Stage, time: Usd.TimeCode, cache: UsdGeom.XformCache, width: int, mi):
    cams = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    named = [p for p in cams if p.GetName() == "main_cam"]
    if not cams:
        raise ValueError("the reference needs a camera on the stage")
    cam = UsdGeom.Camera(named[0] if named else cams[0])
    g = cam.GetCamera(time)
    if g.projection != g.Perspective:
        raise ValueError(f"{cam.GetPath()}: only perspective cameras are supported by the reference")
    hap, vap = g.horizontalAperture, g.verticalAperture
    height = max(1, round(width * vap / hap))
    m = _world(cache, cam.GetPrim())
    eye, forward, up = m[3, :3], -m[2, :3], m[1, :3]
    near, far = g.clippingRange.min, g.clippingRange.max
    sensor = {
        "type": "perspective", "fov_axis": "x", "fov": math.degrees(2.0 * math.atan(hap / (2.0 * g.focalLength))),
        "near_clip": near, "far_clip": far,
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=(eye + forward).tolist(),
                                                   up=up.tolist()),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"},
    }
    return sensor, height


def load(stage_path: str, time: float | None, width: int, folder: str | None = None) -> ReferenceScene:
    """The stage at ``time`` (None: its start time code) as a Mitsuba scene ``width`` pixels wide
    (height from the apertures).

    Meshes are written as OBJ files into ``folder`` (a temporary one by default) for Mitsuba's
    loader; faces are grouped by albedo.
    """
    mi = mitsuba()
    stage = Usd.Stage.Open(str(stage_path))
    t = Usd.TimeCode(stage.GetStartTimeCode() if time is None else time)
    cache = UsdGeom.XformCache(t)
    to_metres = UsdGeom.GetStageMetersPerUnit(stage)
    folder = folder or tempfile.mkdtemp(prefix="usdml-reference-")
    shapes, lo, hi = {}, np.full(3, np.inf), np.full(3, -np.inf)
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        img = UsdGeom.Imageable(prim)
        if img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or \
                img.ComputePurpose() not in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render):
            continue
        mesh = UsdGeom.Mesh(prim)
        counts = list(mesh.GetFaceVertexCountsAttr().Get(t))
        tris = _triangles(counts, list(mesh.GetFaceVertexIndicesAttr().Get(t)))
        m = _world(cache, prim)
        p = np.asarray(mesh.GetPointsAttr().Get(t), np.float64) @ m[:3, :3] + m[3, :3]
        lo, hi = np.minimum(lo, p.min(0)), np.maximum(hi, p.max(0))
        albedo = _face_albedo(mesh, t, len(counts))
        for colour in {tuple(albedo[f]) for f, *_ in tris}:
            faces = [(a, b, c) for f, a, b, c in tris if tuple(albedo[f]) == colour]
            name = f"m{len(shapes)}"
            path = os.path.join(folder, name + ".obj")
            with open(path, "w") as f:
                f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in p)
                f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
            shapes[name] = {"type": "obj", "filename": path, "face_normals": True,
                            "bsdf": {"type": "twosided", "material": {
                                "type": "diffuse", "reflectance": {"type": "rgb", "value": list(colour)}}}}
    if not shapes:
        raise ValueError(f"{stage_path}: no meshes for the reference")
    positions, intensity = _lights(stage, t, cache, to_metres)
    sensor, height = _camera(stage, t, cache, width, mi)
    return ReferenceScene({"type": "scene", "sensor": sensor, **shapes}, positions, intensity, width, height,
                          float(np.linalg.norm(hi - lo)))


def render(ref: ReferenceScene, spp: int, bounces: int = 0, seed: int = 0,
           by_light: bool | None = None, groups: list[list[int]] | None = None) -> np.ndarray:
    """``(H, W, 3)`` float32 linear radiance, box-filtered over each pixel with ``spp`` stratified
    samples: direct light only (``bounces = 0``) or up to ``bounces`` diffuse bounces after it.

    ``by_light`` (default: for direct light only) renders one light at a time and sums, so the only
    noise left in direct light is where in the pixel a sample lands (a path tracer picking one of
    many lights per sample is far noisier); without it, two renders of one seed share their samples,
    so their difference (indirect = all bounces − direct) cancels the direct part sample by sample.
    ``groups`` (lists of light indices, e.g. :meth:`ReferenceScene.light_groups`) renders group by group
    instead, each path picking a light of its group by intensity: far less light-selection noise than
    one render of thousands of lights, in far fewer renders than one per light.
    """
    mi = mitsuba()
    integrator = mi.load_dict({"type": "path", "max_depth": bounces + 2, "hide_emitters": True})
    sampler = {"type": "stratified", "sample_count": spp, "jitter": True}
    ref.definition["sensor"]["sampler"] = sampler
    by_light = bounces == 0 if by_light is None else by_light
    weighted = groups is not None
    if groups is None:
        groups = [[i] for i in range(len(ref.lights))] if by_light else [None]
    image = np.zeros((ref.height, ref.width, 3), np.float64)
    for k, lights in enumerate(groups):
        image += np.array(mi.render(ref.scene(lights, weighted), integrator=integrator, spp=spp, seed=seed + k),
                          np.float64)
    return image.astype(np.float32)


def relative_rmse(got: np.ndarray, reference: np.ndarray) -> float:
    """RMSE of ``got`` over every pixel and channel, divided by the reference image's mean."""
    reference = np.asarray(reference, np.float64)
    return float(np.sqrt(np.mean((np.asarray(got, np.float64) - reference) ** 2)) / np.mean(reference))


def shadow_fraction(ref: ReferenceScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At every pixel centre: ``(shadow (H, W), facing (H, W), direct (H, W, 3))`` from Mitsuba's
    intersector.

    A light faces a hit when it is in front of the triangle (geometric normal turned to the camera);
    it is blocked when a ray from the hit, lifted ``1e-5`` of the scene diagonal along that normal,
    meets a surface before it (stopping as far short of the light); ``direct`` is the unshadowed-where-
    visible Lambertian radiance ``ρ/π · Σ I cosθ / d²`` over the visible lights.
    """
    mi = mitsuba()
    scene = ref.scene([])
    sensor = scene.sensors()[0]
    eps = 1e-5 * ref.diagonal
    shadow = np.zeros((ref.height, ref.width))
    facing = np.zeros((ref.height, ref.width), np.int32)
    direct = np.zeros((ref.height, ref.width, 3))
    for y in range(ref.height):
        for x in range(ref.width):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / ref.width, (y + 0.5) / ref.height),
                                       mi.Point2f(0.5, 0.5))
            si = scene.ray_intersect(ray)
            if not si.is_valid():
                continue
            p, n, d = np.array(si.p), np.array(si.n), np.array(ray.d)
            if n @ d > 0:
                n = -n
            albedo = np.array(si.bsdf().eval_diffuse_reflectance(si))
            origin = p + eps * n
            blocked = 0
            for pos, inten in zip(ref.lights, ref.intensity):
                to_light = pos - p
                dist = float(np.linalg.norm(to_light))
                w = to_light / dist
                if n @ w <= 0.0:
                    continue
                facing[y, x] += 1
                ray = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*w))
                ray.maxt = dist - 2.0 * eps         # (a third constructor argument would be the time)
                if scene.ray_test(ray):
                    blocked += 1
                else:
                    direct[y, x] += albedo / math.pi * inten * (n @ w) / (dist * dist)
            shadow[y, x] = blocked / facing[y, x] if facing[y, x] else 0.0
    return shadow, facing, direct
