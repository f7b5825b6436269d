"""Virtual point lights (VPLs) from light paths (Keller 1997; paper 004 §4: "light rays up to three diffuse bounces").

Model
-----
Units. Every flux here is RGB power in **nit·m²·sr** ("the units of :attr:`Lights.intensity` × sr"):
a light of radiant intensity ``I`` (nit·m², divided by d² in metres) that emits isotropically has
power ``4π·I``. Positions are scene units; ``Snapshot.meters_per_unit`` enters only where an area is
turned into power (distant lights). A VPL of flux Φ is therefore a point light of intensity ``Φ/4π``
(isotropic) or ``Φ/π`` on its normal (cosine lobe) in exactly the units :mod:`usdml.lighting.direct`
divides by d² in metres: no further unit conversion anywhere.

Emitted power Φ_l of each light (what ``light_power`` returns), with the emission profile of
the light geometry of :mod:`usdml.lighting.direct` (θ the angle from the light's ``axis``, ``c = cos θ``):

* point / sphere: isotropic, ``profile = 1``;  disk / rect: one-sided cosine, ``profile = max(0, c)``;
  cylinder: its side's projected area, ``profile = sin θ_c`` (θ_c from its local X axis, ``Lights.intensity``
  the intensity perpendicular to it), so ``Φ = π²·I`` (= π·L·2πr·length, a Lambertian area's π·L·A);
* UsdLux shaping multiplies both: the cone smoothstep ``S(c)`` (zero outside the cone half-angle,
  smoothstep across ``softness``) and focus ``tint + (1 − tint)·clip(c, 0, 1)^focus`` (RGB);
* ``Φ_l = I · 2π ∫ profile(c) dc``. Unshaped lights use the closed forms ``4π·I`` and ``π·I``; a hard cone
  of half-angle a gives ``2π(1 − cos a)·I`` (isotropic) or ``π sin²a·I`` (cosine). Softness and focus are
  **integrated numerically** (1024-point midpoint rule over the sampling distribution below), not
  ignored, so a soft or focused spot light gets its true power; so is any cone or focus on a cylinder
  light (``CYLINDER_POWER_NODES``² midpoint nodes of its direction sampling);
* distant lights: ``Φ = E · π R² · metersPerUnit²``, with R the radius of the bounding sphere of the
  snapshot's world bounds (``Snapshot.world_bounds``), i.e. the irradiance E times the area of the
  scene's bounding disk perpendicular to the light. (The light's angular diameter is ignored, as
  direct shading ignores it.)

Light paths
-----------
* **Light choice**: probability ``p_l ∝ luminance(Φ_l)`` (Rec. 709 weights), stratified: path i takes
  ``u_i = (i + ξ_i) / n`` through the CDF, then the paths are shuffled (so any prefix of them is an
  unbiased subset, see "count" below). Lights of zero power are never chosen.
* **Emission direction** from the profile's *envelope*: uniform on the spherical cap of the cone
  (whole sphere without a cone) for point / sphere lights; cosine-weighted on the cap (hemisphere
  without a cone, cap clamped at 90°) for disk / rect lights; exactly ∝ ``sin θ_c`` for cylinder lights
  (whose envelope is their profile, ``P_env = π²``; :func:`_cylinder_directions`); ``axis`` for distant lights, whose
  origins are uniform on the bounding disk, placed upstream outside the bounding sphere.
  The path's starting flux is ``I · P_env · profile/envelope(θ) / (p_l · paths)``, with ``P_env`` the
  envelope's power (``2π(1 − cos a)`` or ``π sin²a``): the profile/envelope ratio (cone softness and
  focus, ≤ 1, RGB) weights each path, so VPL flux is unbiased for any shaping, and exactly
  ``Φ_l / (p_l · paths)`` for unshaped lights.
* **Origins**: point, sphere, disk, rect and cylinder lights emit from their *centre* (the point-light model that
  direct shading uses too: sphere radius and area extent are ignored), moved ``eps`` along the ray so
  a light mounted flush on a surface does not hit that surface at t = 0.
* **Bounces**: all live paths are traced together, one :func:`usdml.scene.surface.surface_at_hits`
  call (exact, Embree closest hit) per bounce. Each hit deposits a VPL: ``flux = path flux × albedo``
  (the power the Lambertian surface re-emits), ``normal`` = the interpolated shading normal turned to
  face the incoming ray (the ray's reverse where a mesh has no normals), ``bounce`` = 1 for the first
  surface hit from a light. The path continues with that flux (``path flux ×= albedo``: no Russian
  roulette, a path ends only when it misses everything, reaches ``bounces`` VPLs, or its flux is 0),
  from ``P + eps(P)·n`` in a cosine-weighted direction about ``n`` (Lambertian re-emission). VPLs of
  zero flux (black surfaces) are not stored. ``eps(P) = max(epsilon, |P|_max · 2^-20)`` with the exact
  backend's ``epsilon`` (``1e-5`` × scene diagonal) and float margin (8 float32 ulps).

``count``: VPLs in total (``--vpls N``)
-------------------------------------
A path yields at most ``bounces`` VPLs, fewer when it escapes. ``generate_vpls(count=N)`` traces
``ceil(N / bounces)`` paths; while fewer than N VPLs came back it traces further rounds of paths
(sized from the measured VPLs per path, +5 %, at most ``MAX_ROUNDS`` rounds and ``MAX_PATH_FACTOR``·N
paths per round; after a round in which no path has hit anything yet, the next traces
``MAX_PATH_FACTOR`` times as many, so a small object far from its only light still gets VPLs and only
a scene whose lights reach nothing ends with none); the last round keeps the *prefix* of its
(shuffled) paths whose VPLs fit, plus the first VPLs of the path that straddles N. So a scene that
catches light returns exactly N VPLs, and an open scene (a city under a sun whose paths escape
after one bounce) still gets N by tracing more paths. Flux is normalised by the paths kept (those of every round, plus the straddling one); paths
traced and dropped from the last round are not counted. The only bias is the straddling path's
missing deeper bounces (one path out of ~N/bounces). ``paths=`` fixes the number of light paths
instead (no rounds, no trimming: the energy tests use it). Deterministic for a seed: every random
number comes from ``numpy.random.default_rng(seed)``, consumed in a fixed order.

VPLs as lights (:meth:`VPLs.as_lights`)
--------------------------------------
* ``isotropic=False`` (what :mod:`usdml.lighting.gi` uses): DISK lights of radius 0 with ``axis = normal``
  and ``intensity = flux / π``, so direct shading's one-sided ``max(0, cos θ_l)`` profile makes them the
  exact Lambertian re-emission (no leaks, correct lobe). The LGH takes the same VPLs as ``flux / 4π``
  plus their normals (:func:`usdml.lighting.lgh.build.build_lgh`).
* ``isotropic=True`` (paper 004's grid lights): POINT lights, ``intensity = flux / 4π``. Half of each
  VPL's power then goes into the back hemisphere, into its own surface, and is lost wherever the
  surface is closed: measured against path tracing with the same bounces, isotropic VPLs carried 0.44
  of the indirect energy of a closed box and 0.49 in the furnace sphere (``tools/gi_reference.py``).
  Both conserve the VPL's power (``4π·I = π·I_disk = flux``).
Both are ``shadow = True``, cone 180°, radius 0. Their ``radiance`` (meaningless at radius 0) holds the
intensity so that ``Lights.state_hash`` tracks VPL power changes.

Not modelled: glossy bounces (usdml shades Lambertian surfaces only), emission from the surface of
area lights (centre only), VPL clamping (a renderer's concern: ``min_distance`` in direct shading).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdml.lighting.specular_albedo import indirect_albedo
from usdml.scene import Lights, LightType, Snapshot
from usdml.scene.light_table import smoothstep_cone
from usdml.scene.surface import surface_at_hits

__all__ = ["VPLs", "generate_vpls", "light_power", "LUMA"]

#: Rec. 709 / sRGB luminance weights (as usdml.lighting.dome)
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: relative float32 precision margin: 8 ulps of a coordinate (as usdml.visibility.exact)
FLOAT_MARGIN = 2.0 ** -20
#: ray offset as a fraction of the scene diagonal when the backend has no ``epsilon`` (exact's default)
REL_EPSILON = 1e-5
#: midpoint-rule nodes for the power of shaped (soft cone / focus) lights
POWER_NODES = 1024
#: rounds of light paths ``generate_vpls(count=N)`` traces at most to reach N VPLs
MAX_ROUNDS = 6
#: a round traces at most this many paths per requested VPL
MAX_PATH_FACTOR = 16
#: midpoint nodes per side of the (u1, u2) grid that integrates a shaped cylinder light's power
CYLINDER_POWER_NODES = 64

_KIND_ISO, _KIND_COS, _KIND_DISTANT, _KIND_CYL = 0, 1, 2, 3


# ------------------------------------------------------------------------------------------ the VPLs


@dataclass(eq=False)
class VPLs:
    """Virtual point lights: surface points that re-emit diffusely the light that reached them."""

    position: np.ndarray    #: (N, 3) float64 world position (scene units)
    normal: np.ndarray      #: (N, 3) float32 unit, facing the side the light came from
    flux: np.ndarray        #: (N, 3) float32 RGB power re-emitted, nit·m²·sr (Lights.intensity × sr)
    bounce: np.ndarray      #: (N,) int8, 1 = first surface hit from a light
    paths: int = 0          #: light paths the flux is normalised by (0 for an empty set)

    def __len__(self) -> int:
        return int(self.position.shape[0])

    @staticmethod
    def empty() -> "VPLs":
        return VPLs(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                    np.zeros(0, np.int8), 0)

    def total_flux(self, bounce: int | None = None) -> np.ndarray:
        """(3,) float64 summed flux, of one bounce generation when ``bounce`` is given."""
        f = self.flux if bounce is None else self.flux[self.bounce == bounce]
        return f.astype(np.float64).sum(axis=0)

    def as_lights(self, isotropic: bool = True) -> Lights:
        """The VPLs as :class:`Lights` (see the module doc for the trade-off).

        ``isotropic=True``: POINT lights, ``intensity = flux / 4π``. ``isotropic=False``: one-sided
        cosine emitters, DISK of radius 0 with ``axis = normal``, ``intensity = flux / π``.
        """
        n = len(self)
        normal = self.normal.astype(np.float64)
        scale = 4.0 * np.pi if isotropic else np.pi
        intensity = (self.flux.astype(np.float64) / scale).astype(np.float32)
        # light-to-world frames: the light's -Z is its axis (the normal)
        z = -normal
        t, b = _frame(z)
        xform = np.zeros((n, 4, 4))
        xform[:, :3, 0], xform[:, :3, 1], xform[:, :3, 2] = t, b, z
        xform[:, :3, 3] = self.position
        xform[:, 3, 3] = 1.0
        zeros = np.zeros(n)
        return Lights(
            type=np.full(n, int(LightType.POINT if isotropic else LightType.DISK), np.int8),
            position=np.asarray(self.position, np.float64).copy(), axis=normal, xform=xform,
            radiance=intensity.copy(), intensity=intensity, radius=zeros.copy(), width=zeros.copy(),
            height=zeros.copy(), angle=zeros.copy(), cone_angle=np.full(n, 180.0),
            cone_softness=zeros.copy(), focus=zeros.copy(), focus_tint=np.zeros((n, 3), np.float32),
            shadow=np.ones(n, bool), paths=["/usdml/vpl"] * n, instance_ids=np.arange(n, dtype=np.int64))


# ------------------------------------------------------------------------------------------ sampling helpers


def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``(t, b)`` completing unit ``n`` (N, 3) to a right-handed frame (Duff et al. 2017)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    bt = np.stack([b, sign + y * y * a, -y], axis=1)
    return t, bt


def _around(axis: np.ndarray, cos_t: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions at angle ``acos(cos_t)`` from unit ``axis`` (N, 3), azimuth ``phi``."""
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    t, b = _frame(axis)
    return (t * (sin_t * np.cos(phi))[:, None] + b * (sin_t * np.sin(phi))[:, None]
            + axis * cos_t[:, None])


@dataclass
class _Emitters:
    """Per-light constants of path emission."""

    kind: np.ndarray        #: (L,) _KIND_*
    position: np.ndarray    #: (L, 3)
    axis: np.ndarray        #: (L, 3) unit
    cylinder_axis: np.ndarray   #: (L, 3) unit local X (cylinder lights)
    intensity: np.ndarray   #: (L, 3) float64 I (or E for distant lights)
    cone: np.ndarray        #: (L,) degrees
    softness: np.ndarray
    focus: np.ndarray
    tint: np.ndarray        #: (L, 3)
    span: np.ndarray        #: (L,) envelope sampling span: 1 − cos a (iso) or sin² a (cos)
    p_env: np.ndarray       #: (L,) envelope power per unit intensity (sr), area in m² for distant
    shaped: np.ndarray      #: (L,) bool profile/envelope ratio is not identically 1
    power: np.ndarray       #: (L, 3) float64 Φ_l
    center: np.ndarray      #: (3,) bounding-sphere centre (distant lights)
    radius: float           #: bounding-sphere radius, scene units
    #: (L,) each light's light-link set where some light has one (usdml.scene.linking), else None
    linked: np.ndarray | None = None


def _envelope_cos(kind: np.ndarray, span: np.ndarray, u: np.ndarray) -> np.ndarray:
    """cos θ from the envelope distribution for uniform ``u`` (iso: uniform on the cap; cos: cosine-weighted)."""
    return np.where(kind == _KIND_COS, np.sqrt(np.clip(1.0 - u * span, 0.0, 1.0)), 1.0 - u * span)


def _ratio(c: np.ndarray, cone, softness, focus, tint) -> np.ndarray:
    """(N, 3) profile / envelope at cos θ = ``c``: cone smoothstep × focus (1 inside a hard cone, no focus)."""
    s = smoothstep_cone(c, cone, softness)
    focused = focus > 0
    f = np.where(focused, np.clip(c, 0.0, 1.0) ** np.where(focused, focus, 0.0), 1.0)
    fr = np.where(focused[:, None], tint + (1.0 - tint) * f[:, None], 1.0)
    return s[:, None] * fr


def _emitters(snapshot: Snapshot, lights: Lights) -> _Emitters:
    n = len(lights)
    t = np.asarray(lights.type)
    kind = np.where(t == LightType.DISTANT, _KIND_DISTANT,
                    np.where(np.isin(t, (LightType.DISK, LightType.RECT, LightType.TRIANGLE)), _KIND_COS,
                             np.where(t == LightType.CYLINDER, _KIND_CYL, _KIND_ISO)))
    cone = np.asarray(lights.cone_angle, np.float64)
    softness = np.asarray(lights.cone_softness, np.float64)
    focus = np.asarray(lights.focus, np.float64)
    tint = np.asarray(lights.focus_tint, np.float64).reshape(n, 3)
    # a light of negative intensity emits no VPLs: its paths would carry negative flux (docs/gi.md)
    intensity = np.maximum(np.asarray(lights.intensity, np.float64).reshape(n, 3), 0.0)
    intensity *= np.asarray(lights.diffuse, np.float64)[:, None]     # inputs:diffuse: what surfaces bounce on
    a_iso = np.radians(np.clip(cone, 0.0, 180.0))
    a_cos = np.radians(np.clip(cone, 0.0, 90.0))
    span = np.where(kind == _KIND_COS, np.sin(a_cos) ** 2, 1.0 - np.cos(a_iso))
    p_env = np.where(kind == _KIND_COS, np.pi * span, 2.0 * np.pi * span)
    cyl = kind == _KIND_CYL
    p_env = np.where(cyl, np.pi ** 2, p_env)
    cylinder_axis = lights.cylinder_axis()

    bounds = snapshot.world_bounds()
    if bounds is None:
        center, radius = np.zeros(3), 0.0
    else:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
        center, radius = (lo + hi) / 2.0, float(np.linalg.norm(hi - lo)) / 2.0
    distant = kind == _KIND_DISTANT
    p_env = np.where(distant, np.pi * (radius * snapshot.meters_per_unit) ** 2, p_env)
    soft_edge = (cone < 180.0) & (softness > 0)
    shaped = ~distant & (soft_edge | (focus > 0))
    shaped |= cyl & (cone < 180.0)      # a cylinder's envelope has no cone cap

    factor = np.ones((n, 3))
    rows = np.flatnonzero(shaped & ~cyl)
    if rows.size:
        u = (np.arange(POWER_NODES) + 0.5) / POWER_NODES
        for lo in range(0, rows.size, 4096):
            r = rows[lo:lo + 4096]
            k = len(r)
            rr = np.repeat(r, POWER_NODES)
            c = _envelope_cos(kind[rr], span[rr], np.tile(u, k))
            ratio = _ratio(c, cone[rr], softness[rr], focus[rr], tint[rr])
            factor[r] = ratio.reshape(k, POWER_NODES, 3).mean(axis=1)
    axis = np.asarray(lights.axis, np.float64).reshape(n, 3)
    rows = np.flatnonzero(shaped & cyl)
    if rows.size:
        factor[rows] = _cylinder_power_factor(cylinder_axis[rows], axis[rows], cone[rows], softness[rows],
                                              focus[rows], tint[rows])
    power = intensity * p_env[:, None] * factor
    return _Emitters(kind=kind, position=np.asarray(lights.position, np.float64).reshape(n, 3),
                     axis=axis, cylinder_axis=cylinder_axis, intensity=intensity, cone=cone,
                     softness=softness, focus=focus, tint=tint, span=span, p_env=p_env, shaped=shaped,
                     power=power, center=center, radius=radius,
                     linked=lights.light_link if snapshot.links is not None and (lights.light_link >= 0).any() else None)


def light_power(snapshot: Snapshot, lights: Lights) -> np.ndarray:
    """(L, 3) float64 emitted power Φ_l of each light in nit·m²·sr (module doc, "Model")."""
    return _emitters(snapshot, lights).power


def _epsilon(snapshot: Snapshot, backend) -> float:
    eps = getattr(backend, "epsilon", 0.0) or 0.0
    if eps > 0:
        return float(eps)
    bounds = snapshot.world_bounds()
    if bounds is None:
        return 0.0
    return REL_EPSILON * float(np.linalg.norm(np.asarray(bounds[1], np.float64) - bounds[0]))


def _offset(p: np.ndarray, eps: float) -> np.ndarray:
    """(N,) ``eps(P) = max(eps, |P|_max · 2^-20)``."""
    return np.maximum(eps, _max_abs(p) * FLOAT_MARGIN)


# NumPy reduces an (N, 3) array along its rows element by element (an inner loop of 3); the same
# maximum and comparisons column by column are the same values, several times sooner at 100k rays


def _max_abs(v: np.ndarray) -> np.ndarray:
    """(N,) ``np.abs(v).max(axis=1)`` of (N, 3) ``v`` (NaN where a row has one)."""
    a = np.abs(v)
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _any_positive(v: np.ndarray) -> np.ndarray:
    """(N,) bool ``(v > 0).any(axis=1)`` of (N, 3) ``v``."""
    return (v[:, 0] > 0) | (v[:, 1] > 0) | (v[:, 2] > 0)


# ------------------------------------------------------------------------------------------ cylinder lights


def _cylinder_directions(cylinder_axis: np.ndarray, axis: np.ndarray, u1: np.ndarray, u2: np.ndarray):
    """Unit directions ``(N, 3)`` with density ``sin θ_c / π²`` about the unit ``cylinder_axis`` (N, 3)
    (a cylinder side's radiant intensity) from uniform ``u1, u2`` (N,), and their ``(N,)`` cos to the
    light's shaping ``axis``.

    ``(x, y)`` uniform on the unit disk: ``x`` has the semicircle density ∝ √(1 − x²), i.e. ∝ sin θ_c
    for ``x = cos θ_c`` (dω = d cos θ · dφ), and ``y / √(1 − x²)`` is uniform on [−1, 1] given ``x``:
    it sets the azimuth, so two numbers sample the profile exactly.
    """
    r, a = np.sqrt(u1), 2.0 * np.pi * u2
    x, y = r * np.cos(a), r * np.sin(a)
    s = np.sqrt(np.maximum(1.0 - x * x, 0.0))
    phi = np.pi * (1.0 + np.clip(y / np.maximum(s, 1e-300), -1.0, 1.0))
    d = _around(cylinder_axis, x, phi)
    return d, np.einsum("ij,ij->i", d, axis)


def _cylinder_power_factor(cylinder_axis, axis, cone, softness, focus, tint) -> np.ndarray:
    """(K, 3) mean shaping ratio (cone × focus) over a cylinder light's emission: its power is
    ``π²·I`` times this. Midpoint nodes of :func:`_cylinder_directions`' (u1, u2) square."""
    m = CYLINDER_POWER_NODES
    g = (np.arange(m) + 0.5) / m
    u1, u2 = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    out = np.empty((len(cone), 3))
    for i in range(len(cone)):
        rep = np.full(m * m, i)
        _, c = _cylinder_directions(cylinder_axis[rep], axis[rep], u1, u2)
        out[i] = _ratio(c, cone[rep], softness[rep], focus[rep], tint[rep]).mean(axis=0)
    return out


def _emit_cylinders(em: _Emitters, li, rows, u1, u2, eps: float, origins, dirs, weight) -> None:
    """Paths ``rows`` (of lights ``li[rows]``, cylinder lights) in place: directions ∝ sin θ_c from their
    centre, weights × the shaping ratio where a cone or focus shapes them."""
    lj = li[rows]
    d, c = _cylinder_directions(em.cylinder_axis[lj], em.axis[lj], u1[rows], u2[rows])
    p = em.position[lj]
    dirs[rows] = d
    origins[rows] = p + d * _offset(p, eps)[:, None]
    shaped = em.shaped[lj]
    if shaped.any():
        ls = lj[shaped]
        weight[rows[shaped]] *= _ratio(c[shaped], em.cone[ls], em.softness[ls], em.focus[ls], em.tint[ls])


# ------------------------------------------------------------------------------------------ tracing


@dataclass
class _Round:
    position: np.ndarray
    normal: np.ndarray
    flux: np.ndarray        #: (K, 3) float64, not yet divided by the path count
    bounce: np.ndarray
    path: np.ndarray        #: (K,) int64 path index within the round


def _emit(em: _Emitters, prob: np.ndarray, cdf: np.ndarray, n: int, eps: float, rng: np.random.Generator):
    """``n`` light paths: origins, unit directions, starting flux × n (RGB float64) and each path's light."""
    u = (np.arange(n) + rng.random(n)) / n
    li = np.minimum(np.searchsorted(cdf, u * cdf[-1], side="right"), len(cdf) - 1)
    li = li[rng.permutation(n)]
    kind = em.kind[li]
    u1, u2 = rng.random(n), rng.random(n)
    phi = 2.0 * np.pi * u2
    origins = np.empty((n, 3))
    dirs = np.empty((n, 3))
    weight = em.intensity[li] * (em.p_env[li] / prob[li])[:, None]

    local = (kind != _KIND_DISTANT) & (kind != _KIND_CYL)
    if local.any():
        lj = li[local]
        c = _envelope_cos(kind[local], em.span[lj], u1[local])
        d = _around(em.axis[lj], c, phi[local])
        p = em.position[lj]
        dirs[local] = d
        origins[local] = p + d * _offset(p, eps)[:, None]
        shaped = em.shaped[lj]
        if shaped.any():
            idx = np.flatnonzero(local)[shaped]
            ls = lj[shaped]
            weight[idx] *= _ratio(c[shaped], em.cone[ls], em.softness[ls], em.focus[ls], em.tint[ls])
    cyl = kind == _KIND_CYL
    if cyl.any():
        _emit_cylinders(em, li, np.flatnonzero(cyl), u1, u2, eps, origins, dirs, weight)
    far = kind == _KIND_DISTANT
    if far.any():
        lj = li[far]
        axis = em.axis[lj]
        t, b = _frame(axis)
        r = em.radius * np.sqrt(u1[far])
        start = em.center - axis * (em.radius * 1.01 + eps + abs(em.radius) * 1e-6 + 1e-6)
        origins[far] = start + t * (r * np.cos(phi[far]))[:, None] + b * (r * np.sin(phi[far]))[:, None]
        dirs[far] = axis
    return origins, dirs, weight, li


def _trace(snapshot: Snapshot, backend, em: _Emitters, prob, cdf, n: int, bounces: int, eps: float,
           rng: np.random.Generator) -> _Round:
    origins, dirs, flux, li = _emit(em, prob, cdf, n, eps, rng)
    path = np.arange(n, dtype=np.int64)
    live = _any_positive(flux)
    origins, dirs, flux, path, li = origins[live], dirs[live], flux[live], path[live], li[live]
    out: list[tuple] = []
    for b in range(1, bounces + 1):
        if not len(path):
            break
        h = surface_at_hits(snapshot, backend, origins, dirs)
        hit = h.hit
        if b == 1 and em.linked is not None:     # light linking: a light leaves no VPL on a prim it does not light
            hit = hit & _linked(snapshot, backend, em.linked, li, h.geom)
        d = dirs[hit]
        nrm = h.normal[hit]
        missing = ~(_max_abs(nrm) > 0)
        if missing.any():
            nrm[missing] = -d[missing]
        flip = np.einsum("ij,ij->i", nrm, d) > 0
        nrm[flip] *= -1.0
        albedo = h.albedo[hit].astype(np.float64)
        if h.material is not None:      # a glossy surface sends on what its lobes reflect (indirect_albedo)
            albedo = indirect_albedo(albedo, h.material[hit], nrm).astype(np.float64)
        flux = flux[hit] * albedo
        pos = h.position[hit]
        path = path[hit]
        keep = _any_positive(flux)
        pos, nrm, flux, path = pos[keep], nrm[keep], flux[keep], path[keep]
        out.append((pos, nrm, flux, np.full(len(path), b, np.int8), path))
        if b == bounces or not len(path):
            break
        m = len(path)
        u1, u2 = rng.random(m), rng.random(m)
        dirs = _around(nrm, np.sqrt(1.0 - u1), 2.0 * np.pi * u2)
        origins = pos + nrm * _offset(pos, eps)[:, None]
    if not out:
        z = np.zeros((0, 3))
        return _Round(z, z.copy(), z.copy(), np.zeros(0, np.int8), np.zeros(0, np.int64))
    cat = [np.concatenate(x) for x in zip(*out)]
    return _Round(*cat)


def _linked(snapshot: Snapshot, backend, light_link: np.ndarray, li: np.ndarray, geom: np.ndarray) -> np.ndarray:
    """``(n,) bool``: whether each path's first hit (``geom``, the backend's sources) is in its light's light-link
    set (:class:`usdml.scene.linking.LinkSets`)."""
    out = np.ones(len(li), bool)
    links = light_link[li]
    prim_id, instance_id = backend.ids(geom)
    for link in np.unique(links[links >= 0]):
        sel = np.flatnonzero(links == link)
        out[sel] = snapshot.links.members(int(link), prim_id[sel], instance_id[sel])
    return out


def _take(r: _Round, mask: np.ndarray) -> _Round:
    return _Round(r.position[mask], r.normal[mask], r.flux[mask], r.bounce[mask], r.path[mask])


def _fit(r: _Round, n_paths: int, room: int) -> tuple[_Round, int]:
    """Keep the prefix of paths whose VPLs fit in ``room``, plus the first VPLs of the straddling path.

    Returns the kept VPLs and the number of paths they are normalised by."""
    per_path = np.bincount(r.path, minlength=n_paths)
    cum = np.cumsum(per_path)
    k = int(np.searchsorted(cum, room, side="right"))      # paths 0..k-1 fit whole
    if k >= n_paths:
        return r, n_paths
    left = room - (int(cum[k - 1]) if k else 0)            # VPLs of path k that still fit
    mask = (r.path < k) | ((r.path == k) & (r.bounce <= left))
    return _take(r, mask), k + (1 if left > 0 else 0)


def generate_vpls(snapshot: Snapshot, backend, lights: Lights, count: int = 100_000, bounces: int = 3,
                  seed: int = 0, paths: int | None = None) -> VPLs:
    """VPLs from light paths of ``lights`` traced through ``snapshot`` with ``backend.intersect``.

    Parameters
    ----------
    snapshot : the frame's geometry (and ``meters_per_unit``, world bounds for distant lights).
    backend : an updated :class:`usdml.visibility.exact.ExactBackend` (anything with ``intersect``
        and ``source`` that :func:`usdml.scene.surface.surface_at_hits` accepts).
    lights : the primary lights (usually ``snapshot.lights`` plus dome-derived distant lights).
    count : VPLs wanted in total (``--vpls N``); exactly ``count`` unless too few paths hit anything
        (module doc, "count").
    bounces : VPL generations per path (paper 004: 3).
    seed : everything random comes from ``numpy.random.default_rng(seed)``.
    paths : trace exactly this many light paths instead (``count`` is then ignored, nothing trimmed).
    """
    count, bounces = int(count), int(bounces)
    if count < 0 or bounces < 0 or (paths is not None and int(paths) < 0):
        raise ValueError("count, bounces and paths must be >= 0")
    if len(lights) == 0 or bounces == 0 or (paths is None and count == 0) or paths == 0:
        return VPLs.empty()
    if snapshot.world_bounds() is None:
        return VPLs.empty()
    em = _emitters(snapshot, lights)
    lum = np.maximum(em.power @ LUMA, 0.0)
    if not (lum.sum() > 0) or not np.isfinite(lum.sum()):
        return VPLs.empty()
    prob = lum / lum.sum()
    cdf = np.cumsum(lum)
    eps = _epsilon(snapshot, backend)
    rng = np.random.default_rng(seed)

    rounds: list[_Round] = []
    total_paths = 0
    if paths is not None:
        rounds.append(_trace(snapshot, backend, em, prob, cdf, int(paths), bounces, eps, rng))
        total_paths = int(paths)
    else:
        have = 0
        n = -(-count // bounces)
        for _ in range(MAX_ROUNDS):
            r = _trace(snapshot, backend, em, prob, cdf, n, bounces, eps, rng)
            room = count - have
            if len(r.path) >= room:
                r, used = _fit(r, n, room)
                rounds.append(r)
                total_paths += used
                have += len(r.path)
                break
            rounds.append(r)
            total_paths += n
            have += len(r.path)
            cap = MAX_PATH_FACTOR * max(count, 1)
            if have == 0:
                # no path has hit anything yet (a small object far from its light): the next round
                # traces MAX_PATH_FACTOR times as many; rounds only run out when nothing is lit at all
                n = min(n * MAX_PATH_FACTOR, cap)
                continue
            per_path = have / total_paths
            n = int(min(np.ceil((count - have) / per_path * 1.05) + 1, cap))
    if total_paths == 0 or not sum(len(r.path) for r in rounds):
        return VPLs.empty()
    flux = np.concatenate([r.flux for r in rounds]) / total_paths
    return VPLs(position=np.concatenate([r.position for r in rounds]),
                normal=np.concatenate([r.normal for r in rounds]).astype(np.float32),
                flux=flux.astype(np.float32),
                bounce=np.concatenate([r.bounce for r in rounds]).astype(np.int8),
                paths=total_paths)
