"""UsdLux lights: read a light prim's parameters once, expand them over any number of world transforms.

Radiometry (UsdLux, README "Light units"):

* radiance ``L = intensity · 2^exposure · color (· blackbody(colorTemperature)) · diffuse``;
  ``normalize`` divides L by the world-space emitting area (sphere 4πr², disk πr², rect w·h,
  cylinder side 2πr·length);
* sphere and point lights: radiant intensity ``I = L · π · r²`` (r world radius), so a normalized one
  has ``I = intensity · 2^exposure · color / 4``; disk ``I = L · π · r²``, rect ``I = L · w · h`` on axis;
* cylinder lights: ``I⊥ = L · 2r · length`` perpendicular to their axis (the side's projected area; at
  angle θ to the axis it is ``I⊥ · sin θ``), so a normalized one has ``I⊥ = intensity · 2^exposure · color / π``;
* distant lights: irradiance at normal incidence ``E = L · π · sin²(angle / 2)``, or with ``normalize``
  ``E = intensity · 2^exposure · color`` (lux); an unnormalized zero-angle distant light uses ``E = L``.

``inputs:diffuse`` is folded into L (``inputs:specular`` where diffuse is 0), and each lobe's factor of it is
the light's label (:func:`lobe_scale`, :attr:`usdml.scene.Lights.diffuse`). A negative
``inputs:intensity`` is a light that takes light away (UsdLux allows it; Karma renders it): its L, I and E
are negative, every channel (colours stay >= 0), and the shading sums it like any other light
(docs/usd.md, "Negative lights").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from pxr import Usd, UsdLux

from usdml.errors import UsdmlError
from usdml.scene import Lights, LightType

SUPPORTED = {"SphereLight", "DiskLight", "RectLight", "DistantLight", "CylinderLight"}


@dataclass
class LightParams:
    """A light's parameters in its own space, before any transform."""

    path: str
    type: LightType
    base_radiance: np.ndarray   # (3,) L before normalize
    normalize: bool
    radius: float
    width: float                # rect width; cylinder length
    height: float
    angle: float
    cone_angle: float
    cone_softness: float
    focus: float
    focus_tint: np.ndarray
    shadow: bool
    line: bool = False          # a cylinder light with treatAsLine: sampled along its axis


def attribute_value(prim: Usd.Prim, name: str, time: Usd.TimeCode, fallback):
    """``name``'s value at ``time``, or ``fallback`` when the attribute is missing or has no value."""
    attr = prim.GetAttribute(name)
    value = attr.Get(time) if attr else None
    return fallback if value is None else value


def _finite(path: str, name: str, value, what: str = "") -> float | np.ndarray:
    a = np.asarray(value, np.float64)
    if not np.isfinite(a).all():
        raise UsdmlError(f"{path}.{name}: value {value} is not finite; set a finite {what or 'value'}")
    return a


def emitted_radiance(prim: Usd.Prim, time: Usd.TimeCode, default_intensity: float = 1.0,
                     with_diffuse: bool = True) -> np.ndarray:
    """UsdLux radiance before ``normalize``: intensity · 2^exposure · color (· blackbody) (· diffuse), (3,).

    Negative where ``inputs:intensity`` is (a light that takes light away). Raises :class:`UsdmlError`
    naming the attribute for NaN/inf, a negative colour, or an exposure that overflows.
    """
    path = str(prim.GetPath())

    def value(name: str, fallback):
        return _finite(path, name, attribute_value(prim, name, time, fallback))

    intensity = float(value("inputs:intensity", default_intensity))
    exposure = float(value("inputs:exposure", 0.0))
    color = value("inputs:color", (1.0, 1.0, 1.0))
    if (color < 0).any():
        raise UsdmlError(f"{path}.inputs:color: negative color {tuple(color)}; use components >= 0")
    if exposure > 64:
        raise UsdmlError(f"{path}.inputs:exposure: {exposure} stops overflows; use a smaller exposure")
    radiance = intensity * 2.0 ** exposure * color * (lobe_scale(prim, time)[0] if with_diffuse else 1.0)
    if bool(attribute_value(prim, "inputs:enableColorTemperature", time, False)):
        temp = float(value("inputs:colorTemperature", 6500.0))
        radiance = radiance * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(temp), np.float64)
    return np.asarray(radiance, np.float64)


def lobe_scale(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[float, float, float]:
    """``(m, diffuse / m, specular / m)``: the factor the stored radiance carries (``inputs:diffuse``, or
    ``inputs:specular`` where diffuse is 0) and each lobe's factor of it (negative factors count as 0)."""
    path = str(prim.GetPath())
    diffuse = max(float(_finite(path, "inputs:diffuse", attribute_value(prim, "inputs:diffuse", time, 1.0))), 0.0)
    specular = max(float(_finite(path, "inputs:specular", attribute_value(prim, "inputs:specular", time, 1.0))), 0.0)
    m = diffuse if diffuse > 0 else specular
    return (m, diffuse / m, specular / m) if m > 0 else (0.0, 1.0, 1.0)


def read_light(prim: Usd.Prim, time: Usd.TimeCode, warn: Callable[[str], None]) -> LightParams | None:
    """Parameters of a supported UsdLux light, None (with a warning) for other light types."""
    path = str(prim.GetPath())
    kind = prim.GetTypeName()
    if kind not in SUPPORTED:
        warn(f"{path}: {kind or 'untyped light'} is not supported yet; ignored")
        return None
    api = UsdLux.LightAPI(prim)

    def value(name: str, fallback, what: str = ""):
        return _finite(path, name, attribute_value(prim, name, time, fallback), what)

    radiance = emitted_radiance(prim, time, 50000.0 if kind == "DistantLight" else 1.0)
    normalize = bool(api.GetNormalizeAttr().Get(time))

    radius = width = height = angle = 0.0
    ltype = {"SphereLight": LightType.SPHERE, "DiskLight": LightType.DISK, "RectLight": LightType.RECT,
             "DistantLight": LightType.DISTANT, "CylinderLight": LightType.CYLINDER}[kind]
    if ltype in (LightType.SPHERE, LightType.DISK):
        radius = float(value("inputs:radius", 0.5))
        if radius < 0:
            raise UsdmlError(f"{path}.inputs:radius: negative radius {radius}; use a radius >= 0")
        if ltype == LightType.SPHERE and (radius == 0 or bool(attribute_value(prim, "treatAsPoint", time, False))):
            ltype = LightType.POINT
        if ltype == LightType.POINT and radius == 0 and not normalize:
            warn(f"{path}: point light with radius 0 and normalize off emits nothing (I = L·π·r²); "
                 "set inputs:normalize = true or a radius > 0")
    elif ltype == LightType.RECT:
        width, height = float(value("inputs:width", 1.0)), float(value("inputs:height", 1.0))
        if width < 0 or height < 0:
            raise UsdmlError(f"{path}.inputs:width/height: negative size; use sizes >= 0")
        if prim.GetAttribute("inputs:texture:file") and prim.GetAttribute("inputs:texture:file").Get(time):
            warn(f"{path}: RectLight texture is not supported; using its color")
    elif ltype == LightType.CYLINDER:
        # treatAsLine: shadow rays go to points along the axis (a line), while the radius still sets the
        # emitting area (expand keeps it for the intensity and stores the line's world radius as 0)
        radius, width = float(value("inputs:radius", 0.5)), float(value("inputs:length", 1.0))
        line = bool(attribute_value(prim, "treatAsLine", time, False))
        for name, v in (("radius", radius), ("length", width)):
            if v < 0:
                raise UsdmlError(f"{path}.inputs:{name}: negative {name} {v:g}; use a {name} >= 0")
        if (radius == 0 or width == 0) and not normalize:
            warn(f"{path}: cylinder light with radius or length 0 and normalize off emits nothing "
                 "(I = L·2r·length); set inputs:normalize = true or a radius and length > 0")
    else:
        angle = float(value("inputs:angle", 0.53))

    cone_angle, softness, focus, tint = 180.0, 0.0, 0.0, np.zeros(3)
    if prim.HasAPI(UsdLux.ShapingAPI):
        cone_angle = float(value("inputs:shaping:cone:angle", 90.0))
        softness = float(value("inputs:shaping:cone:softness", 0.0))
        focus = float(value("inputs:shaping:focus", 0.0))
        tint = value("inputs:shaping:focusTint", (0.0, 0.0, 0.0))
        for name, v, rule in (("cone:angle", cone_angle, "use 0 to 180 degrees"),
                              ("cone:softness", softness, "use 0 to 1"), ("focus", focus, "use a focus >= 0")):
            if v < 0:
                raise UsdmlError(f"{path}.inputs:shaping:{name}: negative value {v:g}; {rule}")
        if attribute_value(prim, "inputs:shaping:ies:file", time, None):
            warn(f"{path}: IES profiles are not supported; using the cone only")
    shadow = bool(attribute_value(prim, "inputs:shadow:enable", time, True))
    return LightParams(path, ltype, radiance, normalize, radius, width, height, angle,
                       cone_angle, softness, focus, np.asarray(tint, np.float64), shadow,
                       ltype == LightType.CYLINDER and line)


def expand(params: LightParams, xforms: np.ndarray, instance_ids: np.ndarray | None = None,
           meters_per_unit: float = 1.0) -> Lights:
    """One light per ``(N, 4, 4)`` light-to-world matrix (column convention), vectorized.

    Areas are measured in square metres (``meters_per_unit`` converts scene units), since UsdLux
    radiance is in nits (per square metre): ``intensity`` comes out in nit·m², and a renderer divides
    it by the squared distance in metres.
    """
    n = len(xforms)
    m = np.asarray(xforms, np.float64)
    if not np.isfinite(m).all():
        raise UsdmlError(f"{params.path}: non-finite (NaN/inf) transform; fix its xformOps or its "
                         "PointInstancer positions/orientations/scales")
    ax, ay, az = m[:, :3, 0], m[:, :3, 1], m[:, :3, 2]
    sx, sy, sz = (np.linalg.norm(a, axis=1) for a in (ax, ay, az))
    xy_area = np.linalg.norm(np.cross(ax, ay), axis=1)       # area scale of the light's XY plane
    radius = params.radius * np.cbrt(sx * sy * sz)
    base = np.broadcast_to(params.base_radiance, (n, 3))
    t = params.type
    m2 = meters_per_unit ** 2
    if t in (LightType.SPHERE, LightType.POINT):
        area = 4 * np.pi * radius ** 2 * m2
        proj = np.pi * radius ** 2 * m2
    elif t == LightType.DISK:
        radius = params.radius * np.sqrt(sx * sy)
        area = proj = np.pi * params.radius ** 2 * xy_area * m2
    elif t == LightType.RECT:
        area = proj = params.width * params.height * xy_area * m2
    elif t == LightType.CYLINDER:
        # an elliptic section (Y and Z scaled apart) has Ramanujan's perimeter (OpenUSD hdEmbree's UsdLux area);
        # its mean width over directions is perimeter / π (Cauchy), so the radius perimeter / 2π keeps
        # the power of I⊥·sinθ at π·L·area for any scale
        a, b = params.radius * sy, params.radius * sz
        perimeter = np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b)))
        radius = perimeter / (2 * np.pi)
        area = perimeter * params.width * sx * m2
        proj = area / np.pi
    else:
        half = np.radians(params.angle) / 2
        area = proj = np.full(n, np.pi * np.sin(half) ** 2 if params.angle > 0 else 1.0)
    if params.normalize:
        safe = np.where(area > 0, area, 1.0)
        radiance = np.where((area > 0)[:, None], base / safe[:, None], 0.0)
        # at zero area, the limit of proj / area as the size goes to 0
        limit = {LightType.SPHERE: 0.25, LightType.POINT: 0.25, LightType.CYLINDER: 1 / np.pi}.get(t, 1.0)
        intensity = base * np.where(area > 0, proj / safe, limit)[:, None]
        if t == LightType.DISTANT:
            intensity = base.copy()
    else:
        radiance = base
        intensity = base * proj[:, None]
    axis = -az
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.where(norm > 0, axis / np.where(norm > 0, norm, 1), [0.0, 0.0, -1.0])
    ids = np.full(n, -1, np.int64) if instance_ids is None else np.asarray(instance_ids, np.int64)
    return Lights(
        type=np.full(n, int(t), np.int8), position=m[:, :3, 3].copy(), axis=axis, xform=m.copy(),
        radiance=radiance.astype(np.float32), intensity=intensity.astype(np.float32),
        radius=radius if t in (LightType.SPHERE, LightType.POINT, LightType.DISK) or (
            t == LightType.CYLINDER and not params.line) else np.zeros(n),
        width=params.width * sx if t in (LightType.RECT, LightType.CYLINDER) else np.zeros(n),
        height=params.height * sy if t == LightType.RECT else np.zeros(n),
        angle=np.full(n, params.angle), cone_angle=np.full(n, params.cone_angle),
        cone_softness=np.full(n, params.cone_softness), focus=np.full(n, params.focus),
        focus_tint=np.broadcast_to(params.focus_tint, (n, 3)).astype(np.float32),
        shadow=np.full(n, params.shadow), paths=[params.path] * n, instance_ids=ids)
