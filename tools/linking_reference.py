#!/usr/bin/env python
"""An independent reference for light linking, shadow linking and light groups (issue 52, items 1 and 2).

Two parts, neither importing usdml:

* **Stage families** written with pxr (seeded): a ground quad and axis-aligned boxes as ``UsdGeom.Mesh``
  (``displayColor`` albedo, polygonal), a perspective camera </World/main_cam> and ``SphereLight``\\ s with
  ``treatAsPoint`` whose ``collection:lightLink`` / ``collection:shadowLink`` use includes, excludes,
  ``includeRoot = false``, nested prims (a box two Xforms below an included or excluded one) and native
  instances; :func:`four_light_stage`, :func:`instanced_stage` (lights instanced by a PointInstancer from two
  prototype lights with different collections, and boxes instanced by a PointInstancer) and
  :func:`collection_stage` (one light, one rule). ``linked=False`` writes the same stage without the
  collections. Lights carry ``usdml:lightGroup`` strings.
* **A renderer** (:func:`read_scene`, :func:`render`): it reads any such stage back with pxr alone (world
  transforms, ``PointInstancer.ComputeInstanceTransformsAtTime``, instance proxies, ``Gf.Camera``) and casts
  one camera ray per pixel centre in NumPy: the ray-AABB slab test against every box (the ground is the box of
  zero height, where the slab test is the ray-quad test), Lambertian shading

      L_o = albedo / π · Σ_lights I · cos θ / d²      (d in metres)

  with UsdLux's point-light intensity written out below, a shadow ray from the hit toward each light tested
  only against the boxes that light's ``shadowLink`` holds, and a light counted only on the geometry its
  ``lightLink`` holds. Membership is USD's own: ``Usd.CollectionAPI.ComputeMembershipQuery().IsPathIncluded``
  asked for the path Hydra gives the geometry (a mesh's path; a native instance's instance-proxy path, so an
  instance is in a collection by its own path or an ancestor's; a PointInstancer's prototype mesh's path);
  an instanced light uses its prototype light's collections and group.

UsdLux point lights (the UsdLux spec, not usdml's code): a ``SphereLight`` of radiance
``L = intensity · 2^exposure · color`` and world radius r (metres) treated as a point emits the radiant
intensity of the sphere seen from afar, ``I = L · π r²``; with ``normalize`` L is divided by the sphere's area
4πr², so ``I = intensity · 2^exposure · color / 4``. A light with no ``usdml:lightGroup`` is in group
``default``.

Usage (a look at one stage)::

    .venv/bin/python tools/linking_reference.py --stage four --seed 1 --width 96 --out /tmp/ref
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, Vt

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from stage_build import new_stage  # noqa: E402  (the generated stages' metadata: metersPerUnit 1, upAxis Y)

GROUP_ATTRIBUTE = "usdml:lightGroup"
DEFAULT_GROUP = "default"
#: the camera's film back: 3 : 2, so widths divisible by 3 give whole heights
APERTURE = (36.0, 24.0)

# -- writing the stages ----------------------------------------------------------------------------------------

_CUBE = [(-.5, -.5, -.5), (.5, -.5, -.5), (.5, .5, -.5), (-.5, .5, -.5),
         (-.5, -.5, .5), (.5, -.5, .5), (.5, .5, .5), (-.5, .5, .5)]
_CUBE_FACES = [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 2, 3, 7, 6, 1, 2, 6, 5, 0, 4, 7, 3]


def _color(mesh: UsdGeom.Mesh, rgb) -> None:
    mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, rgb))]))


def _unit_cube(stage: Usd.Stage, path: str, rgb) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in _CUBE])
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr(_CUBE_FACES)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    _color(mesh, rgb)
    return mesh


def _box(stage: Usd.Stage, path: str, center, size, rgb) -> UsdGeom.Mesh:
    """A box of ``size`` (w, h, d) at ``center``: the unit cube moved by translate and scale ops."""
    mesh = _unit_cube(stage, path, rgb)
    mesh.AddTranslateOp().Set(Gf.Vec3d(*map(float, center)))
    mesh.AddScaleOp().Set(Gf.Vec3f(*map(float, size)))
    return mesh


def _ground(stage: Usd.Stage, half: float, rgb=(0.6, 0.6, 0.6)) -> None:
    mesh = UsdGeom.Mesh.Define(stage, "/World/ground")
    mesh.CreatePointsAttr([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    _color(mesh, rgb)


def _camera(stage: Usd.Stage, eye=(0.0, 7.5, 9.0), pitch: float = -40.0) -> None:
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(28.0)
    cam.CreateHorizontalApertureAttr(APERTURE[0])
    cam.CreateVerticalApertureAttr(APERTURE[1])
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(*eye))
    cam.AddRotateXOp().Set(pitch)


def _point_light(stage: Usd.Stage, path: str, rgb, power: float, normalize: bool, group: str | None,
                 position=None) -> UsdLux.SphereLight:
    """A point light (``treatAsPoint``) of radiant intensity ``power · rgb`` written as UsdLux would have it:
    ``normalize`` on, intensity 4·power; off, radius 0.1 and intensity power / (π · 0.1²)."""
    light = UsdLux.SphereLight.Define(stage, path)
    light.CreateTreatAsPointAttr(True)
    light.CreateColorAttr(Gf.Vec3f(*map(float, rgb)))
    if normalize:
        light.CreateNormalizeAttr(True)
        light.CreateRadiusAttr(0.05)
        light.CreateIntensityAttr(float(4.0 * power))
    else:
        light.CreateRadiusAttr(0.1)
        light.CreateIntensityAttr(float(power / (math.pi * 0.01)))
    if group is not None:
        light.GetPrim().CreateAttribute(GROUP_ATTRIBUTE, Sdf.ValueTypeNames.String).Set(group)
    if position is not None:
        light.AddTranslateOp().Set(Gf.Vec3d(*map(float, position)))
    return light


def link(light: Usd.Prim, which: str, includes=(), excludes=(), include_root: bool | None = None,
         rule: str | None = None) -> None:
    """Author ``collection:<which>`` (``lightLink`` or ``shadowLink``) on ``light``."""
    api = Usd.CollectionAPI(light, which)
    if include_root is not None:
        api.CreateIncludeRootAttr(include_root)
    if rule is not None:
        api.CreateExpansionRuleAttr(rule)
    for p in includes:
        api.CreateIncludesRel().AddTarget(Sdf.Path(p))
    for p in excludes:
        api.CreateExcludesRel().AddTarget(Sdf.Path(p))


def _place_boxes(rng: np.random.Generator, n: int, reach: float, sizes=((0.8, 2.0), (0.8, 2.6), (0.8, 2.0))):
    """``n`` (center, size) boxes standing on the ground in [-reach, reach]², apart from each other."""
    out: list[tuple[np.ndarray, np.ndarray]] = []
    while len(out) < n:
        size = np.array([rng.uniform(*s) for s in sizes])
        c = np.array([rng.uniform(-reach, reach), size[1] / 2, rng.uniform(-reach, reach)])
        if all(abs(c[0] - o[0]) > (size[0] + s[0]) / 2 + 0.4 or abs(c[2] - o[2]) > (size[2] + s[2]) / 2 + 0.4
               for o, s in out):
            out.append((c, size))
    return out


def _albedo(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(0.25, 0.9, 3)


def four_light_stage(path, seed: int, linked: bool = True) -> str:
    """Four point lights over a ground and six boxes, each light with its own linking rules (module doc).

    Boxes: </World/boxes/b0..b2>, </World/group/inner/b3> (nested two Xforms deep, the group moved by its own
    op) and two native instances </World/crates/c0>, </World/crates/c1> of the class prototype
    </Prototypes/crate>. The seed places the boxes and lights and picks which box each rule names:

    * ``key`` (group ``key``, normalize): lightLink includeRoot false, includes one box, </World/group> and the
      instance </World/crates/c0>: it lights those and nothing else;
    * ``fill`` (group ``fill``): lightLink excludes </World/ground>; shadowLink includeRoot false, includes one
      box: only that box casts its shadows;
    * ``rim`` (group ``key``): lightLink excludes one box; shadowLink excludes </World/group/inner> (the nested
      box casts no shadow from it);
    * ``top`` (no group: ``default``): shadowLink includeRoot false, nothing included: no shadows at all.
    """
    rng = np.random.default_rng([seed, 52])
    stage = new_stage(str(path), 1, 1)
    _ground(stage, 9.0)
    places = _place_boxes(rng, 6, 4.0)
    for k in range(3):
        _box(stage, f"/World/boxes/b{k}", *places[k], _albedo(rng))
    group = UsdGeom.Xform.Define(stage, "/World/group")
    c, s = places[3]
    group.AddTranslateOp().Set(Gf.Vec3d(float(c[0]), 0.0, float(c[2])))
    UsdGeom.Xform.Define(stage, "/World/group/inner")
    _box(stage, "/World/group/inner/b3", (0.0, c[1], 0.0), s, _albedo(rng))
    proto = stage.CreateClassPrim("/Prototypes")
    UsdGeom.Xform.Define(stage, "/Prototypes/crate")
    _box(stage, "/Prototypes/crate/box", (0.0, 0.5, 0.0), (1.2, 1.0, 1.2), _albedo(rng))
    assert proto
    for k in range(2):
        c, _ = places[4 + k]
        inst = UsdGeom.Xform.Define(stage, f"/World/crates/c{k}")
        inst.GetPrim().GetReferences().AddInternalReference("/Prototypes/crate")
        inst.GetPrim().SetInstanceable(True)
        inst.AddTranslateOp().Set(Gf.Vec3d(float(c[0]), 0.0, float(c[2])))
    boxes = [f"/World/boxes/b{k}" for k in range(3)]
    pick = rng.permutation(3)
    spots = [np.array([rng.uniform(-5, 5), rng.uniform(4.0, 6.5), rng.uniform(-5, 5)]) for _ in range(4)]
    key = _point_light(stage, "/World/lights/key", (1.0, 0.92, 0.8), 30.0, True, "key", spots[0])
    fill = _point_light(stage, "/World/lights/fill", (0.75, 0.85, 1.0), 20.0, False, "fill", spots[1])
    rim = _point_light(stage, "/World/lights/rim", (1.0, 0.8, 0.9), 20.0, False, "key", spots[2])
    top = _point_light(stage, "/World/lights/top", (1.0, 1.0, 1.0), 12.0, True, None, spots[3])
    if linked:
        link(key.GetPrim(), "lightLink", includes=[boxes[pick[0]], "/World/group", "/World/crates/c0"],
             include_root=False)
        link(fill.GetPrim(), "lightLink", excludes=["/World/ground"])
        link(fill.GetPrim(), "shadowLink", includes=[boxes[pick[1]]], include_root=False)
        link(rim.GetPrim(), "lightLink", excludes=[boxes[pick[2]]])
        link(rim.GetPrim(), "shadowLink", excludes=["/World/group/inner"])
        link(top.GetPrim(), "shadowLink", include_root=False)
    _camera(stage)
    stage.Save()
    return str(path)


#: :func:`instanced_stage`'s rules: prototype light -> collection -> link() arguments
INSTANCED_RULES = {
    "scene": {"warm": {"lightLink": {"includes": ["/World/scatter", "/World/boxes/b0"], "include_root": False}},
              "cool": {"lightLink": {"excludes": ["/World/scatter/protos/crate"]},
                       "shadowLink": {"excludes": ["/World/boxes/b1"]}}},
    "one box": {"warm": {"lightLink": {"excludes": ["/World/boxes/b0"]}},
                "cool": {"lightLink": {"excludes": ["/World/boxes/b1"]},
                         "shadowLink": {"excludes": ["/World/boxes/b2"]}}},
    "two sets": {"warm": {"lightLink": {"excludes": ["/World/boxes/b0"]}},
                 "cool": {"lightLink": {"excludes": ["/World/boxes/b1"]}}},
}


def instanced_stage(path, seed: int, lights: int = 1000, linked: bool = True, boxes: int = 4,
                    scattered: int = 8, frames: int = 1, rules: str = "scene") -> str:
    """``lights`` point lights instanced by the PointInstancer </World/lights> from two prototype lights
    </World/lights/protos/warm> and </World/lights/protos/cool> (groups ``warm`` and ``cool``), over a ground,
    ``boxes`` boxes </World/boxes/b*> and ``scattered`` boxes instanced by the PointInstancer </World/scatter>
    (prototype </World/scatter/protos/crate>). The two prototypes link differently (:data:`INSTANCED_RULES`):

    * ``scene``: ``warm``'s lightLink includeRoot false, includes </World/scatter> and </World/boxes/b0>;
      ``cool``'s lightLink excludes the prototype </World/scatter/protos/crate>, its shadowLink </World/boxes/b1>;
    * ``one box`` (a frame with nearly the same pairs as without links, for the machinery's cost): each prototype
      light's lightLink excludes one box, ``cool``'s shadowLink a third one;
    * ``two sets``: the light links of ``one box`` alone (two light-link sets, no shadow set).

    The total intensity is the same for any ``lights`` (each light 1/``lights`` of it). ``frames`` > 1: the
    lights drift (up to 0.2 a frame) over frames 1..``frames`` (a sequence whose every frame is new).
    """
    rng = np.random.default_rng([seed, 520])
    stage = new_stage(str(path), 1, 1)
    reach = 4.5 + 0.1 * max(boxes + scattered - 12, 0) ** 0.5
    _ground(stage, 2 * reach + 1)
    places = _place_boxes(rng, boxes + scattered, reach)
    for k in range(boxes):
        _box(stage, f"/World/boxes/b{k}", *places[k], _albedo(rng))
    scatter = UsdGeom.PointInstancer.Define(stage, "/World/scatter")
    _unit_cube(stage, "/World/scatter/protos/crate", _albedo(rng))
    scatter.CreatePrototypesRel().AddTarget("/World/scatter/protos/crate")
    rest = places[boxes:]
    scatter.CreateProtoIndicesAttr([0] * len(rest))
    scatter.CreatePositionsAttr([Gf.Vec3f(*map(float, c)) for c, _ in rest])
    scatter.CreateScalesAttr([Gf.Vec3f(*map(float, s)) for _, s in rest])
    inst = UsdGeom.PointInstancer.Define(stage, "/World/lights")
    each = 80.0 / lights
    warm = _point_light(stage, "/World/lights/protos/warm", (1.0, 0.78, 0.52), each, False, "warm")
    cool = _point_light(stage, "/World/lights/protos/cool", (0.7, 0.82, 1.0), each, True, "cool")
    for proto in (warm, cool):
        inst.CreatePrototypesRel().AddTarget(proto.GetPath())
    inst.CreateProtoIndicesAttr(rng.integers(0, 2, lights).tolist())
    spread = reach + 2.0
    pos = np.c_[rng.uniform(-spread, spread, lights), rng.uniform(3.0, 6.5, lights),
                rng.uniform(-spread, spread, lights)]
    positions = inst.CreatePositionsAttr()
    if frames == 1:
        positions.Set(Vt.Vec3fArray.FromNumpy(pos.astype(np.float32)))
    drift = rng.uniform(-0.2, 0.2, (lights, 3))
    for f in range(frames if frames > 1 else 0):
        positions.Set(Vt.Vec3fArray.FromNumpy((pos + f * drift).astype(np.float32)), 1 + f)
    stage.SetEndTimeCode(frames)
    if linked:
        for proto in (warm, cool):
            for which, kwargs in INSTANCED_RULES[rules][proto.GetPrim().GetName()].items():
                link(proto.GetPrim(), which, **kwargs)
    _camera(stage, eye=(0.0, 1.6 * reach + 1.0, 2.0 * reach + 1.0))
    stage.Save()
    return str(path)


#: :func:`collection_stage`'s rules: (collection, its arguments to :func:`link`, the boxes it lights or shadows)
CASES = {
    "includes": ("lightLink", {"includes": ["/World/boxes/b0", "/World/boxes/b2"], "include_root": False},
                 {"/World/boxes/b0", "/World/boxes/b2"}),
    "excludes": ("lightLink", {"excludes": ["/World/boxes/b1", "/World/ground"]},
                 {"/World/boxes/b0", "/World/boxes/b2", "/World/nest/inner/b3"}),
    "includeRoot false": ("lightLink", {"include_root": False}, set()),
    "nested include": ("lightLink", {"includes": ["/World/nest"], "include_root": False}, {"/World/nest/inner/b3"}),
    "nested exclude": ("lightLink", {"excludes": ["/World/nest/inner"]},
                       {"/World/ground", "/World/boxes/b0", "/World/boxes/b1", "/World/boxes/b2"}),
    "exclude under include": ("lightLink", {"includes": ["/World/boxes"], "excludes": ["/World/boxes/b1"],
                                            "include_root": False}, {"/World/boxes/b0", "/World/boxes/b2"}),
    "explicitOnly": ("lightLink", {"includes": ["/World/nest", "/World/boxes/b1"], "include_root": False,
                                   "rule": "explicitOnly"}, {"/World/boxes/b1"}),
    "shadow includes": ("shadowLink", {"includes": ["/World/boxes/b1"], "include_root": False}, {"/World/boxes/b1"}),
}


def collection_stage(path, case: str) -> str:
    """One point light over a ground and four boxes (</World/boxes/b0..b2>, </World/nest/inner/b3>) with the
    collection rule :data:`CASES` ``[case]``; a fixed layout, every box seen and casting a shadow on the ground."""
    which, kwargs, _ = CASES[case]
    stage = new_stage(str(path), 1, 1)
    _ground(stage, 9.0)
    spots = [((-3.0, 0.9, -1.0), (1.4, 1.8, 1.4)), ((0.0, 1.2, -2.0), (1.2, 2.4, 1.2)),
             ((3.0, 0.7, -0.5), (1.6, 1.4, 1.0))]
    for k, (c, s) in enumerate(spots):
        _box(stage, f"/World/boxes/b{k}", c, s, (0.8, 0.5 + 0.1 * k, 0.4))
    nest = UsdGeom.Xform.Define(stage, "/World/nest")
    nest.AddTranslateOp().Set(Gf.Vec3d(0.5, 0.0, 2.0))
    UsdGeom.Xform.Define(stage, "/World/nest/inner")
    _box(stage, "/World/nest/inner/b3", (0.0, 0.6, 0.0), (1.2, 1.2, 1.2), (0.4, 0.6, 0.9))
    light = _point_light(stage, "/World/lights/one", (1.0, 1.0, 1.0), 40.0, True, None, (-1.0, 6.0, 4.0))
    link(light.GetPrim(), which, **kwargs)
    _camera(stage)
    stage.Save()
    return str(path)


# -- reading a stage back ---------------------------------------------------------------------------------------

@dataclass
class Scene:
    """What the reference renders: boxes as world AABBs, point lights, the camera; float64, world units."""

    lo: np.ndarray                  #: (M, 3) box minimum corners
    hi: np.ndarray                  #: (M, 3) box maximum corners
    albedo: np.ndarray              #: (M, 3) displayColor
    paths: list[str]                #: (M,) the path each box is in a collection by
    light_pos: np.ndarray           #: (L, 3) positions
    light_I: np.ndarray             #: (L, 3) radiant intensity (nit·m²)
    light_group: list[str]          #: (L,) light group
    light_link: np.ndarray          #: (L, M) bool: the light shines on box m
    shadow_link: np.ndarray         #: (L, M) bool: box m casts the light's shadows
    eye: np.ndarray                 #: (3,) camera position
    cam_to_world: np.ndarray        #: (3, 3) camera rotation, columns the camera's x, y, z in the world
    focal: float
    aperture: tuple[float, float, float, float] = (APERTURE[0], APERTURE[1], 0.0, 0.0)  # h, v, h offset, v offset
    meters_per_unit: float = 1.0
    groups: list[str] = field(default_factory=list)     #: the groups present, sorted

    def height(self, width: int) -> int:
        return max(1, round(width * self.aperture[1] / self.aperture[0]))


def _matrix(m: Gf.Matrix4d) -> np.ndarray:
    return np.array(m, np.float64)             # Gf: row vectors, p_world = [p, 1] · M


def _mesh_box(prim: Usd.Prim, world: np.ndarray, time) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(time), np.float64)
    p = np.c_[points, np.ones(len(points))] @ world
    p = p[:, :3] / p[:, 3:]
    lo, hi = p.min(0), p.max(0)
    on_face = np.isclose(p, lo, atol=1e-6 * (1 + np.abs(lo))) | np.isclose(p, hi, atol=1e-6 * (1 + np.abs(hi)))
    if not on_face.all():
        raise ValueError(f"{prim.GetPath()}: not an axis-aligned box; the reference renders boxes and quads only")
    color = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor").Get(time)
    return lo, hi, np.array(color[0] if color else (0.5, 0.5, 0.5), np.float64)


def _point_intensity(prim: Usd.Prim, world: np.ndarray, time, mpu: float) -> np.ndarray:
    light = UsdLux.SphereLight(prim)
    if not light.GetTreatAsPointAttr().Get(time):
        raise ValueError(f"{prim.GetPath()}: the reference renders point lights (treatAsPoint) only")
    rgb = (light.GetIntensityAttr().Get(time) * 2.0 ** light.GetExposureAttr().Get(time)
           * np.array(light.GetColorAttr().Get(time), np.float64))
    if light.GetNormalizeAttr().Get(time):
        return rgb / 4.0
    r = light.GetRadiusAttr().Get(time) * abs(np.linalg.det(world[:3, :3])) ** (1 / 3) * mpu
    return rgb * math.pi * r * r


def read_scene(path: str, camera: str = "/World/main_cam") -> Scene:
    """Read a stage of :func:`four_light_stage`'s family at its start time with pxr alone (module doc)."""
    stage = Usd.Stage.Open(str(path))
    time = Usd.TimeCode(stage.GetStartTimeCode())
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    boxes: list[tuple] = []                     # (lo, hi, albedo, path)
    lights: list[tuple] = []                    # (position, I, source light prim)

    def world_of(prim):
        return _matrix(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time))

    def add(prim, world, member_path, source):
        if prim.IsA(UsdGeom.Mesh):
            boxes.append((*_mesh_box(prim, world, time), member_path))
        elif prim.IsA(UsdLux.SphereLight):
            lights.append((world[3, :3].copy(), _point_intensity(prim, world, time, mpu), source))

    walk = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in walk:
        if prim.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(prim).ComputeVisibility(time) == UsdGeom.Tokens.invisible:
            walk.PruneChildren()
            continue
        if prim.IsA(UsdGeom.PointInstancer):
            walk.PruneChildren()            # its prototypes are seen only as its instances
            pi = UsdGeom.PointInstancer(prim)
            xforms = [_matrix(m) for m in pi.ComputeInstanceTransformsAtTime(time, time)]
            indices = list(pi.GetProtoIndicesAttr().Get(time))
            pi_world = world_of(prim)
            for k, root_path in enumerate(pi.GetPrototypesRel().GetTargets()):
                root = stage.GetPrimAtPath(root_path)
                root_inv = np.linalg.inv(world_of(root))
                for sub in Usd.PrimRange(root):
                    rel = world_of(sub) @ root_inv      # below the prototype root (its own op is in xforms)
                    for i in (i for i, j in enumerate(indices) if j == k):
                        add(sub, rel @ xforms[i] @ pi_world, str(sub.GetPath()), sub)
            continue
        add(prim, world_of(prim), str(prim.GetPath()), prim)

    paths = [b[3] for b in boxes]
    queries: dict[tuple[str, str], np.ndarray] = {}

    def membership(light: Usd.Prim, which: str) -> np.ndarray:
        key = (str(light.GetPath()), which)
        if key not in queries:
            q = Usd.CollectionAPI(light, which).ComputeMembershipQuery()
            queries[key] = np.array([q.IsPathIncluded(Sdf.Path(p)) for p in paths], bool)
        return queries[key]

    def group(light: Usd.Prim) -> str:
        attr = light.GetAttribute(GROUP_ATTRIBUTE)
        value = attr.Get(time) if attr else None
        return value or DEFAULT_GROUP

    cam_prim = stage.GetPrimAtPath(camera)
    gf = UsdGeom.Camera(cam_prim).GetCamera(time)
    cam = _matrix(gf.transform)
    rot = cam[:3, :3].T                      # columns: the camera's axes in the world
    rot = rot / np.linalg.norm(rot, axis=0)
    return Scene(
        lo=np.array([b[0] for b in boxes]), hi=np.array([b[1] for b in boxes]),
        albedo=np.array([b[2] for b in boxes]), paths=paths,
        light_pos=np.array([x[0] for x in lights]).reshape(-1, 3),
        light_I=np.array([x[1] for x in lights]).reshape(-1, 3),
        light_group=[group(x[2]) for x in lights],
        light_link=np.array([membership(x[2], "lightLink") for x in lights]).reshape(len(lights), len(boxes)),
        shadow_link=np.array([membership(x[2], "shadowLink") for x in lights]).reshape(len(lights), len(boxes)),
        eye=cam[3, :3].copy(), cam_to_world=rot, focal=gf.focalLength,
        aperture=(gf.horizontalAperture, gf.verticalAperture, gf.horizontalApertureOffset,
                  gf.verticalApertureOffset),
        meters_per_unit=mpu, groups=sorted({group(x[2]) for x in lights}))


# -- rendering ----------------------------------------------------------------------------------------------------

def slab(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Ray-AABB slab test of ``(N, 3)`` rays against ``(M, 3)`` boxes: ``(t_near, t_far, entry axis)``, each
    ``(N, M)``; a ray meets box m where ``t_near <= t_far``. A box of zero size along an axis is a quad."""
    near = far = entry = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            inv = 1.0 / direction[:, k, None]
            t0 = (lo[None, :, k] - origin[:, k, None]) * inv
            t1 = (hi[None, :, k] - origin[:, k, None]) * inv
            enter, leave = np.minimum(t0, t1), np.maximum(t0, t1)
            if near is None:
                near, far, entry = enter, leave, np.zeros(enter.shape, np.int8)
            else:
                entry = np.where(enter > near, np.int8(k), entry)
                near, far = np.maximum(near, enter), np.minimum(far, leave)
    return near, far, entry


@dataclass
class Image:
    """A reference frame: ``(H, W, 3)`` radiance, per group, and what each pixel sees."""

    color: np.ndarray
    groups: dict[str, np.ndarray]
    box: np.ndarray                 #: (H, W) int: the box each pixel sees, -1 for none


def camera_rays(scene: Scene, width: int) -> tuple[np.ndarray, int]:
    """Unit world directions ``(H·W, 3)`` through the pixel centres, row 0 at the top; and H."""
    height = scene.height(width)
    h_ap, v_ap, h_off, v_off = scene.aperture
    col, row = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = ((col.ravel() / width * 2 - 1) * h_ap / 2 + h_off) / scene.focal
    y = ((1 - row.ravel() / height * 2) * v_ap / 2 + v_off) / scene.focal
    d = np.c_[x, y, -np.ones_like(x)] @ scene.cam_to_world.T
    return d / np.linalg.norm(d, axis=1, keepdims=True), height


def render(scene: Scene, width: int, linked: bool = True, chunk: int = 32) -> Image:
    """Render ``scene`` at ``width`` pixels, one ray per pixel centre; ``linked=False`` ignores the
    collections (every light on and shadowed by every box)."""
    dirs, height = camera_rays(scene, width)
    n = len(dirs)
    origin = np.broadcast_to(scene.eye, dirs.shape)
    t_near, t_far, axis = slab(origin, dirs, scene.lo, scene.hi)
    t = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
    box = t.argmin(1)
    hit = np.isfinite(t[np.arange(n), box])
    box = np.where(hit, box, -1)
    rows = np.flatnonzero(hit)
    b = box[rows]
    p = scene.eye + dirs[rows] * t[rows, b][:, None]
    ax = axis[rows, b]
    normal = np.zeros_like(p)
    normal[np.arange(len(rows)), ax] = -np.sign(dirs[rows, ax])   # the face the camera sees
    start = p + 1e-5 * normal
    albedo = scene.albedo[b] / math.pi
    groups = scene.groups
    which = np.array([groups.index(g) for g in scene.light_group], np.int64)
    out = np.zeros((len(rows), len(groups), 3))
    light_link = scene.light_link if linked else np.ones_like(scene.light_link)
    shadow_link = scene.shadow_link if linked else np.ones_like(scene.shadow_link)
    for a in range(0, len(scene.light_pos), chunk):
        pos, inten = scene.light_pos[a:a + chunk], scene.light_I[a:a + chunk]
        to = pos[None] - start[:, None]                          # (P, C, 3)
        dist = np.linalg.norm(to, axis=2)
        l = to / dist[..., None]
        cos = np.einsum("pc,pkc->pk", normal, l)
        lit = (cos > 0) & light_link[a:a + chunk][:, b].T          # (P, C)
        pk = np.nonzero(lit)                                       # the shadow rays: (pixel, light) pairs
        near, far, _ = slab(start[pk[0]], l[pk], scene.lo, scene.hi)
        blocked = (near <= far) & (far > 0) & (near < dist[pk][:, None]) & shadow_link[a + pk[1]]
        lit[pk[0][blocked.any(1)], pk[1][blocked.any(1)]] = False
        e = np.where(lit, cos / (dist * scene.meters_per_unit) ** 2, 0.0)     # (P, C)
        contrib = e[..., None] * inten[None]                                   # (P, C, 3)
        onehot = np.zeros((len(pos), len(groups)))
        onehot[np.arange(len(pos)), which[a:a + chunk]] = 1.0
        out += np.einsum("pkc,kg->pgc", contrib, onehot)
    out *= albedo[:, None]
    per_group = {}
    for g, name in enumerate(groups):
        img = np.zeros((n, 3))
        img[rows] = out[:, g]
        per_group[name] = img.reshape(height, width, 3)
    color = sum(per_group.values()) if per_group else np.zeros((height, width, 3))
    return Image(color=color, groups=per_group, box=box.reshape(height, width))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--stage", choices=("four", "instanced"), default="four")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--lights", type=int, default=1000, help="instanced stage: lights (default: %(default)s)")
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--out", required=True, help="folder for the stage and the reference's .npy images")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stage = out / f"{args.stage}_{args.seed}.usda"
    if args.stage == "four":
        four_light_stage(stage, args.seed)
    else:
        instanced_stage(stage, args.seed, args.lights)
    scene = read_scene(str(stage))
    image = render(scene, args.width)
    np.save(out / f"{stage.stem}_color.npy", image.color)
    for name, img in image.groups.items():
        np.save(out / f"{stage.stem}_{name}.npy", img)
    print(f"{stage}: {len(scene.paths)} boxes, {len(scene.light_pos)} lights, groups {', '.join(scene.groups)}; "
          f"mean radiance {image.color.mean():.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
