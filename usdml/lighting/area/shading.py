"""Direct light of the lights with area (:func:`usdml.lighting.area.sampling.sampled`): each light's K samples are
point evaluations at points on it (:mod:`usdml.lighting.area.sampling`), each with its own shadow ray.

At a surface point with shading normal n, a sample toward unit direction ω adds ``emit · max(0, n·ω) · S(θ_l) · V``
times the light's RGB intensity (``S``: UsdLux shaping about the light's axis, θ_l measured from the sample: the
cone and focus of :class:`usdml.scene.light_table.LightTable`; 1 for distant lights, as for points), and nothing
where the light is behind the geometric normal. The ``shadow`` AOV counts a light as facing when any of its
samples does and as blocked by the fraction of its facing samples that are blocked.

The estimate's noise: per point, the sample variance of each light's K terms (treated as independent, which the
stratification makes conservative) times K, summed over the lights, is the variance of the point's direct light
(its luminance, Lambertian part): :attr:`AreaResult.variance`, from which the frame's noise estimate is made
(:func:`noise_estimate`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from usdml.lighting.area.sampling import sample_lights
from usdml.lighting.brdf_sums import brdf_sums
from usdml.parallel import cpu_workers, iter_parallel
from usdml.scene import Lights
from usdml.scene.light_table import LightTable, smoothstep_cone
from usdml.visibility.emitter_ends import off_emitters

__all__ = ["AreaEstimate", "AreaResult", "SAMPLES_PER_CHUNK", "noise_estimate", "shade_area"]

#: (point, light, sample) triples evaluated per block (small enough for the blocks to share the cores)
SAMPLES_PER_CHUNK = 1 << 16
#: Rec. 709 luminance weights
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class AreaResult:
    """What :func:`shade_area` returns beside :class:`usdml.visibility.base.DirectResult`'s fields."""

    radiance: np.ndarray        #: (P, 3) float32 outgoing radiance (diffuse ρ/π·ΣE, plus specular with material rows)
    specular: np.ndarray | None  #: (P, 3) float32 ΣE·ks with material rows, else None
    facing: np.ndarray          #: (P,) int32 lights with a facing sample
    blocked: np.ndarray         #: (P,) float64 Σ over facing lights of their blocked share of facing samples
    queries: int                #: shadow rays
    variance: np.ndarray        #: (P,) float32 variance of the luminance of ``radiance`` from the sampling


@dataclass
class _Columns:
    """A light table's RGB rows repeated for each of K samples (what :func:`brdf_sums` reads)."""

    base: np.ndarray
    focus_rgb: np.ndarray


def shade_area(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
               occluded: Callable[..., np.ndarray] | None, samples: int, seed: int, meters_per_unit: float = 1.0,
               min_distance: float = 0.0, geometric: np.ndarray | None = None,
               material: np.ndarray | None = None) -> AreaResult:
    """Direct light at ``P`` points from ``lights``, each sampled ``samples`` times (module doc).

    Arguments as :func:`usdml.lighting.direct.shade_direct` (``occluded(origins, targets, normals=, distant=)``:
    segments to world points, or unit directions where ``distant``; None: unshadowed); ``seed`` keys the samples.
    """
    n_p, n_l, k = len(points), len(lights), max(int(samples), 1)
    radiance = np.zeros((n_p, 3), np.float32)
    specular = np.zeros((n_p, 3), np.float32) if material is not None else None
    facing = np.zeros(n_p, np.int32)
    blocked = np.zeros(n_p, np.float64)
    variance = np.zeros(n_p, np.float32)
    if n_p == 0 or n_l == 0:
        return AreaResult(radiance, specular, facing, blocked, 0, variance)
    table = LightTable(lights, meters_per_unit, min_distance)
    columns = _Columns(np.repeat(table.base, k, axis=0), np.repeat(table.focus_rgb, k, axis=0))
    luma_base, luma_focus = table.base @ LUMA, table.focus_rgb @ LUMA
    offset = normals if geometric is None else geometric
    step = max(1, SAMPLES_PER_CHUNK // (n_l * k))

    def block(lo: int) -> int:
        hi = min(n_p, lo + step)
        asked = 0
        s = sample_lights(points[lo:hi], lights, k, seed, meters_per_unit, min_distance)
        w = s.directions.astype(np.float32)
        n = normals[lo:hi].astype(np.float32)
        g = np.maximum(np.einsum("plki,pi->plk", w, n), 0.0) * s.emit.astype(np.float32)
        if geometric is not None:
            g[np.einsum("plki,pi->plk", w, geometric[lo:hi].astype(np.float32)) <= 0.0] = 0.0
        f = None
        if table.shaped.any() or table.focused.any():
            cos_l = np.where(table.distant[None, :, None], 1.0,
                             -np.einsum("plki,il->plk", w, table.axis)).astype(np.float32)
            g *= smoothstep_cone(cos_l, table.cone[None, :, None], table.softness[None, :, None])
            if table.focused.any():
                f = np.clip(cos_l, 0.0, 1.0) ** table.focus[None, :, None]
        live = g > 0
        facing_samples = live.sum(axis=2)
        facing[lo:hi] = (facing_samples > 0).sum(axis=1)
        if occluded is not None:
            pi, li, ki = np.nonzero(live & table.casts[None, :, None])
            if len(pi):
                # a point on a mesh light's triangle ends off the surface the backend holds
                targets = off_emitters(s.targets[pi, li, ki], lights, li, occluded)
                hit = np.asarray(occluded(points[lo + pi], targets, normals=offset[lo + pi],
                                          distant=s.distant[li]), bool)
                asked = len(pi)
                g[pi[hit], li[hit], ki[hit]] = 0.0
                hidden = np.bincount(pi[hit] * n_l + li[hit], minlength=(hi - lo) * n_l).reshape(hi - lo, n_l)
                blocked[lo:hi] = (hidden / np.maximum(facing_samples, 1)).sum(axis=1)
        y = g * luma_base[None, :, None] + (0.0 if f is None else g * f * luma_focus[None, :, None])
        variance[lo:hi] = (y.var(axis=2, ddof=1) * k).sum(axis=1) if k > 1 else 0.0
        g2 = g.reshape(hi - lo, n_l * k)
        f2 = None if f is None else f.reshape(hi - lo, n_l * k)
        if material is not None:
            wx, wy, wz = (np.ascontiguousarray(w[..., c].reshape(hi - lo, n_l * k)) for c in range(3))
            radiance[lo:hi], specular[lo:hi] = brdf_sums(g2, f2, (wx, wy, wz), columns, material[lo:hi], n)
        else:
            radiance[lo:hi] = g2 @ columns.base
            if f2 is not None:
                radiance[lo:hi] += (g2 * f2) @ columns.focus_rgb
        return asked

    # blocks write disjoint rows: NumPy's work on one overlaps the shadow rays of another (both release the GIL)
    queries = sum(iter_parallel(block, range(0, n_p, step), cpu_workers()))
    rho = albedo.astype(np.float32) / np.float32(np.pi)
    radiance *= rho
    variance *= (rho @ LUMA) ** 2
    if specular is not None:
        radiance += specular
    return AreaResult(radiance, specular, facing, blocked, queries, variance)


@dataclass
class AreaEstimate:
    """A frame's estimate of the noise its lights with area leave in ``direct`` (:func:`noise_estimate`)."""

    rel_rmse: float         #: relative RMSE of ``direct`` from the sampling
    light_samples: int      #: samples per light and shading point

    def as_dict(self) -> dict:
        return asdict(self)


def noise_estimate(variance: np.ndarray, direct: np.ndarray, passes: int = 1) -> float:
    """The frame's relative RMSE (RMS over pixels over the mean luminance of ``direct``) that the area lights'
    sampling leaves, from the per-point ``variance`` (P,) of :func:`shade_area` over ``passes`` primary rays per
    pixel (a pixel's value is their mean): ``sqrt(mean variance / passes) / mean luminance``; 0 without light."""
    mean = float(np.mean(np.asarray(direct, np.float64).reshape(-1, 3) @ LUMA)) if len(direct) else 0.0
    if mean <= 0 or not len(variance):
        return 0.0
    return float(np.sqrt(np.mean(variance) / max(passes, 1)) / mean)
