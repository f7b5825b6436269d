"""Direct many-light shading (paper 000, Alg. 3): every pixel against every light, any visibility backend.

For a surface point P with unit normal n and Lambertian albedo ρ, each light contributes
outgoing radiance ``ρ/π · E``, with irradiance

* point lights, and lights whose size is zero (as points at their centre):
  ``E = I · S(θ_l) · max(0, n·ω) / d²`` (d in metres) where ω is the unit direction to the light, d its distance,
  θ_l the angle between the light's axis and −ω, ``I`` the light's radiant intensity
  (:class:`usdml.scene.Lights`); disk and rect lights emit one-sided with a ``max(0, cos θ_l)``
  profile, sphere and point lights isotropically, cylinder lights with the projected area of their
  side, ``sin θ_c`` (θ_c the angle between −ω and the cylinder's axis, its local X);
* distant lights: ``E = E₀ · max(0, n·ω)`` with ω = −axis.

Lights with area (rect, disk, sphere, cylinder, mesh triangles, distant lights with an angle:
:func:`usdml.lighting.area.sampling.sampled`) are the same sum at ``light_samples`` points sampled on each, a shadow
ray to each (:func:`usdml.lighting.area.shading.shade_area`): soft shadows, and no blow-up close to them.

``S`` is UsdLux shaping: zero outside the cone half-angle, a smoothstep from ``cos(angle)`` to
``cos(angle·(1−softness))`` across the cone edge, and focus as ``focusTint + (1 − focusTint)·cos^focus θ_l``
(the per-light constants: :class:`usdml.scene.light_table.LightTable`).

A light *faces* a point when its unshadowed contribution is non-zero; the ``shadow`` AOV is the
fraction of facing lights that are blocked (paper 000's hiddenLightsN / n). With a geometric normal
``n_g`` beside the shading normal ``n``, a light also has to be in front of the surface
(``n_g·ω > 0``) to face it, and shadow rays leave along ``n_g``: a shading normal tilted toward a
light behind the surface must not light the point (the surface itself is in the way).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from usdml.lighting.area.params import LIGHT_SAMPLES
from usdml.lighting.area.sampling import sampled
from usdml.lighting.area.shading import AreaResult, shade_area
from usdml.lighting.brdf_sums import brdf_sums
from usdml.parallel import cpu_workers, iter_parallel
from usdml.scene import Lights
from usdml.scene.light_table import LightTable, smoothstep_cone
from usdml.visibility.base import SHADE_DIRECT, DirectResult

__all__ = ["DirectResult", "PAIRS_PER_CHUNK", "facing_pairs", "shade_direct", "shade_with", "shadow_queries"]

#: (pixel, light) pairs evaluated per block: ~15 float32 arrays of this size are alive at once
PAIRS_PER_CHUNK = 1 << 20


def _geometry(points: np.ndarray, normals: np.ndarray, t: LightTable, geometric: np.ndarray | None = None):
    """Scalar irradiance factor ``g`` and focus factor ``f`` ``(Pc, L)``, plus direction components;
    ``g`` is 0 where the light is behind ``geometric`` (the surface's own normal, when given)."""
    p = points.astype(np.float32)
    n = normals.astype(np.float32)
    dx = t.position[0][None, :] - p[:, 0:1]
    dy = t.position[1][None, :] - p[:, 1:2]
    dz = t.position[2][None, :] - p[:, 2:3]
    if t.distant.any():
        for comp, axis in ((dx, t.axis[0]), (dy, t.axis[1]), (dz, t.axis[2])):
            comp[:, t.distant] = -axis[t.distant]
    d2 = dx * dx + dy * dy + dz * dz
    if t.distant.any():
        d2[:, t.distant] = 1.0
    inv_d = 1.0 / np.sqrt(np.maximum(d2, 1e-30))
    cos_s = (n[:, 0:1] * dx + n[:, 1:2] * dy + n[:, 2:3] * dz) * inv_d
    g = np.maximum(cos_s, 0.0)
    if geometric is not None:
        ng = geometric.astype(np.float32)
        g[ng[:, 0:1] * dx + ng[:, 1:2] * dy + ng[:, 2:3] * dz <= 0.0] = 0.0
    g *= np.where(t.distant[None, :], 1.0, t.inv_m2 / np.maximum(d2, t.min_d2)).astype(np.float32)
    if t.cylinder.any():
        c = t.cylinder
        cos_c = (t.cylinder_axis[0][None, c] * dx[:, c] + t.cylinder_axis[1][None, c] * dy[:, c]
                 + t.cylinder_axis[2][None, c] * dz[:, c]) * inv_d[:, c]
        g[:, c] *= np.sqrt(np.maximum(1.0 - cos_c * cos_c, 0.0))
    f = None
    if t.one_sided.any() or t.shaped.any() or t.focused.any():
        cols = t.one_sided | t.shaped | t.focused
        cos_l = -(t.axis[0][None, cols] * dx[:, cols] + t.axis[1][None, cols] * dy[:, cols]
                  + t.axis[2][None, cols] * dz[:, cols]) * inv_d[:, cols]
        factor = np.where(t.one_sided[cols][None, :], np.maximum(cos_l, 0.0), 1.0)
        factor *= smoothstep_cone(cos_l, t.cone[cols][None, :], t.softness[cols][None, :])
        g[:, cols] *= factor
        if t.focused.any():
            f = np.ones_like(g)
            f[:, cols] = np.clip(cos_l, 0.0, 1.0) ** t.focus[cols][None, :]
    g[d2 <= 0] = 0.0
    return g, f, (dx * inv_d, dy * inv_d, dz * inv_d)


def shadow_queries(live: np.ndarray, directions, table: LightTable, lights: Lights):
    """The shadow rays a block needs: ``(pi, li)`` pair indices of facing, shadow-casting lights,
    their targets (light positions, or unit directions toward distant lights) and distant flags."""
    pi, li = np.nonzero(live & table.casts[None, :])
    dist = table.distant[li]
    targets = lights.position[li].copy()
    if dist.any():
        wx, wy, wz = directions
        targets[dist] = np.stack([wx[pi[dist], li[dist]], wy[pi[dist], li[dist]], wz[pi[dist], li[dist]]], axis=1)
    return pi, li, targets, dist


def facing_pairs(points: np.ndarray, normals: np.ndarray, lights: Lights, geometric: np.ndarray | None = None,
                 among: np.ndarray | None = None):
    """Yield ``(origins, targets, normals, distant, point_index, light_index)`` of every shadow query
    of :func:`shade_direct`, by block (``normals`` of the queries: the geometric ones when given);
    ``among``: (P, L) bool, only those pairs (the same queries in the same order as filtering all of them)."""
    table = LightTable(lights)     # units do not change which pairs face each other
    step = max(1, PAIRS_PER_CHUNK // max(len(lights), 1))
    offset = normals if geometric is None else geometric
    for lo in range(0, len(points), step):
        hi = min(len(points), lo + step)
        g, _, w = _geometry(points[lo:hi], normals[lo:hi], table, None if geometric is None else geometric[lo:hi])
        live = g > 0 if among is None else (g > 0) & among[lo:hi]
        pi, li, targets, dist = shadow_queries(live, w, table, lights)
        yield points[lo + pi], targets, offset[lo + pi], dist, lo + pi, li


def shade_direct(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
                 occluded: Callable[..., np.ndarray] | None,
                 progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
                 min_distance: float = 0.0, geometric: np.ndarray | None = None,
                 answers: np.ndarray | None = None, material: np.ndarray | None = None,
                 diffuse_only: np.ndarray | None = None, light_samples: int = LIGHT_SAMPLES,
                 seed: int = 0) -> DirectResult:
    """Shade ``P`` surface points by every light.

    Parameters
    ----------
    points, normals, albedo : (P, 3) world positions, unit shading normals, linear RGB albedo.
    lights : all lights of the frame.
    occluded : ``occluded(origins, targets, normals=, distant=) -> (K,) bool`` of a visibility
        backend (:meth:`usdml.visibility.VisibilityBackend.occluded`); None shades unshadowed.
    progress : called with the number of points finished after each block.
    meters_per_unit : the stage's; light falloff uses distances in metres.
    min_distance : clamp of the geometry term, ``d² >= min_distance²`` (scene units): VPL gathering
        uses it against the singularity of point lights on nearby surfaces (paper 004 §2).
    geometric : (P, 3) unit geometric normals on the shading normals' side, or None (the shading
        normals serve): which lights face a point, and the shadow rays' offset.
    answers : (P, L) bool or uint8, optional
        Every pair's answer, computed before shading (paper 001 answers light by light from a map per
        light): read for each shadow query instead of calling ``occluded``.
    material : (P, WIDTH) float32, optional
        UsdPreviewSurface rows (``kernels/brdf``): each visible light adds ``E·(ρ/π·kd + ks)``, ``albedo``
        being the effective diffuse reflectance ρ; the result's ``specular`` holds ΣE·ks. None: Lambertian.
    diffuse_only : (L,) bool, optional
        With ``material``: lights that light the diffuse lobe only (a dome's distant samples: its specular is
        :func:`usdml.lighting.dome_specular.dome_specular`'s).
    light_samples, seed : points sampled on each light with area, and the seed that places them
        (:func:`usdml.lighting.area.shading.shade_area`; with ``answers``, which hold one answer per light,
        every light is shaded as a point).

    Loop order (DESIGN, "Performance shape"): a block of pixels against all lights, dense float32
    ``(pixels, lights)`` arrays; the sum over lights is a matrix product.
    """
    area = _area_columns(lights, diffuse_only) if answers is None else None
    if area is not None:
        point = shade_direct(points, normals, albedo, lights.subset(~area), occluded, progress, meters_per_unit,
                             min_distance, geometric, None, material,
                             None if diffuse_only is None else diffuse_only[~area])
        return _plus_area(point, shade_area(points, normals, albedo, lights.subset(area), occluded, light_samples,
                                            seed, meters_per_unit, min_distance, geometric, material))
    n_p, n_l = len(points), len(lights)
    radiance = np.zeros((n_p, 3), np.float32)
    specular = np.zeros((n_p, 3), np.float32) if material is not None else None
    blocked = np.zeros(n_p, np.int64)
    facing = np.zeros(n_p, np.int64)
    queries = 0
    if n_l == 0 or n_p == 0:
        return DirectResult(radiance, np.zeros(n_p, np.float32), facing.astype(np.int32), 0, specular)
    table = LightTable(lights, meters_per_unit, min_distance)
    step = max(1, PAIRS_PER_CHUNK // n_l)
    offset = normals if geometric is None else geometric

    def block(lo: int) -> int:
        hi = min(n_p, lo + step)
        g, f, w = _geometry(points[lo:hi], normals[lo:hi], table, None if geometric is None else geometric[lo:hi])
        live = g > 0
        facing[lo:hi] = live.sum(axis=1)
        asked = 0
        if occluded is not None or answers is not None:
            pi, li, targets, dist = shadow_queries(live, w, table, lights)
            if len(pi):
                if answers is not None:
                    hit = np.asarray(answers[lo + pi, li], bool)
                else:
                    hit = occluded(points[lo + pi], targets, normals=offset[lo + pi], distant=dist)
                asked = len(pi)
                g[pi[hit], li[hit]] = 0.0
                blocked[lo:hi] = np.bincount(pi[hit], minlength=hi - lo)
        if material is not None:
            radiance[lo:hi], specular[lo:hi] = _material_sums(g, f, w, table, material[lo:hi], normals[lo:hi],
                                                              diffuse_only)
            return asked
        radiance[lo:hi] = g @ table.base
        if f is not None:
            radiance[lo:hi] += (g * f) @ table.focus_rgb
        return asked

    # Blocks write disjoint rows, so they can overlap: NumPy's element-wise work on one block runs
    # while Embree traces another (both release the GIL).
    starts = range(0, n_p, step)
    for lo, asked in zip(starts, iter_parallel(block, starts, cpu_workers())):
        queries += asked
        if progress is not None:
            progress(min(n_p, lo + step) - lo)
    radiance *= albedo.astype(np.float32) / np.float32(np.pi)
    if specular is not None:
        radiance += specular
    shadow = np.where(facing > 0, blocked / np.maximum(facing, 1), 0.0)
    return DirectResult(radiance, shadow.astype(np.float32), facing.astype(np.int32), queries, specular)


def _area_columns(lights: Lights, diffuse_only: np.ndarray | None) -> np.ndarray | None:
    """``(L,) bool`` the lights sampled over their area (a dome's samples, ``diffuse_only``, never), or None when
    there are none."""
    area = sampled(lights)
    if diffuse_only is not None:
        area &= ~np.asarray(diffuse_only, bool)
    return area if area.any() else None


def _plus_area(point: DirectResult, area: AreaResult) -> DirectResult:
    """The point lights' result with the area lights' added: light, facing lights, blocked share, rays."""
    facing = point.facing.astype(np.int64) + area.facing
    blocked = point.shadow.astype(np.float64) * point.facing + area.blocked
    shadow = np.where(facing > 0, blocked / np.maximum(facing, 1), 0.0).astype(np.float32)
    specular = None if point.specular is None else point.specular + area.specular
    variance = area.variance if point.variance is None else point.variance + area.variance
    return DirectResult(point.radiance + area.radiance, shadow, facing.astype(np.int32), point.queries + area.queries,
                        specular, variance)


def _material_sums(g: np.ndarray, f: np.ndarray | None, w, table: LightTable, rows: np.ndarray,
                   normals: np.ndarray, diffuse_only: np.ndarray | None):
    """:func:`usdml.lighting.brdf_sums.brdf_sums` of a block; the ``diffuse_only`` lights' pairs add their
    diffuse part only (a second sum over them alone, whose specular part is dropped)."""
    if diffuse_only is None or not diffuse_only.any():
        return brdf_sums(g, f, w, table, rows, normals)
    rest = g.copy()
    rest[:, diffuse_only] = 0.0
    only = np.zeros_like(g)
    only[:, diffuse_only] = g[:, diffuse_only]
    diffuse, specular = brdf_sums(rest, f, w, table, rows, normals)
    diffuse_dome, _ = brdf_sums(only, f, w, table, rows, normals)
    return diffuse + diffuse_dome, specular


def shade_with(backend, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
               progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
               min_distance: float = 0.0, geometric: np.ndarray | None = None,
               material: np.ndarray | None = None, diffuse_only: np.ndarray | None = None,
               light_samples: int = LIGHT_SAMPLES, seed: int = 0) -> DirectResult:
    """:func:`shade_direct` with ``backend``'s shadows (a :class:`usdml.visibility.base.VisibilityBackend`,
    updated): its fused kernel where it declares ``SHADE_DIRECT`` (handed this module's
    :func:`shade_direct` for what it does not fuse), else :func:`shade_direct` over its ``occluded``. With
    ``material`` rows the fused kernel sums both lobes where it can (the voxel backend's compiled one) and hands the
    rest to :func:`shade_direct` over ``occluded`` (the same shadows; ``tools/material_cost.py`` times both).
    Lights with area go to :func:`usdml.lighting.area.shading.shade_area` over ``occluded`` (no fused kernel samples
    them; docs/area-lights.md measures the cost). Arguments and result as :func:`shade_direct`."""
    area = _area_columns(lights, diffuse_only)
    if area is not None:
        point = shade_with(backend, points, normals, albedo, lights.subset(~area), progress, meters_per_unit,
                           min_distance, geometric, material, None if diffuse_only is None else diffuse_only[~area])
        return _plus_area(point, shade_area(points, normals, albedo, lights.subset(area), backend.occluded,
                                            light_samples, seed, meters_per_unit, min_distance, geometric, material))
    options = dict(meters_per_unit=meters_per_unit, min_distance=min_distance, geometric=geometric)
    if material is not None:
        options["material"] = material
        if diffuse_only is not None and diffuse_only.any():
            options["diffuse_only"] = diffuse_only
    # a fused kernel sums both lobes of every light: lights that light one lobe only go through shade_direct
    if backend.supports(SHADE_DIRECT) and "diffuse_only" not in options and len(lights):
        return backend.shade_direct(points, normals, albedo, lights, progress, plain=shade_direct, **options)
    return shade_direct(points, normals, albedo, lights, backend.occluded, progress, **options)
