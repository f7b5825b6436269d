"""Direct light from the stage's own lights through a lighting grid hierarchy (``--direct lgh``, paper 004).

Paper 004 built its hierarchy for explosions authored as up to a million point lights (§1, Fig. 1);
usdml builds the same hierarchy (:func:`usdml.lighting.lgh.build.build_lgh`) over the frame's UsdLux lights
and shades it with the code ``--gi lgh`` uses for VPLs (:func:`usdml.lighting.lgh.shading.lgh_indirect`):
one LGH, two light sources. Per frame:

1. **Split** (:func:`grid_mask`). Lights the grid represents faithfully become grid lights:

   * sphere and point lights, isotropic: radiant intensity ``I`` in every direction;
   * disk and rect lights and mesh lights' triangles, one-sided cosine emitters ``I · max(0, cos θ_l)`` about
     their axis: an isotropic-equivalent intensity ``I / 4`` with the axis as emission normal, the LGH's cosine lobe
     (:func:`usdml.kernels.lgh.shading.lobe_factor`: ``4 · max(0, cos)``), which is exact for one
     light and for grid lights over lights that face the same way, and tends to isotropic where they
     do not; mixed with isotropic lights the lobe is exact too (the factor is linear in the mean normal).

   Sphere, disk and rect lights with area: a few (their samples' rays per point, lights × ``usdml:light:samples``,
   up to :data:`MAX_SAMPLES`: :func:`area_every_light`) are shaded every-light, exactly as ``--direct all`` does;
   more are grid lights like points at their centres (their unshadowed light is the point's, the far field of
   their shapes: too bright or too dark within a few sizes of a large one), and a shadow ray aimed at one goes
   to a point sampled on it (:class:`usdml.lighting.area.targets.AreaTargets`): soft shadows.

   Everything else is shaded every-light through the visibility backend, exactly as ``--direct all``
   does: distant lights (and the distant lights a dome is sampled into), cylinder lights, lights with
   a shaping cone or focus (their profile is not a cosine lobe), lights with ``shadow:enable`` off,
   lights of zero luminance (they light nothing and would only stand in the grid's counts) and lights of
   negative intensity (they take light away: the hierarchy sums intensities into grid lights and draws its
   shadow rays by luminance, neither of which holds a negative light), so ``--direct lgh`` shades those exactly
   as ``--direct all`` does.
2. **Build** the hierarchy over the grid lights, levels by the paper's rule (``usdml:lgh:levels``
   0) unless set.
3. **Shade**: every pixel gathers the lights themselves within ``alpha h_1`` (level S0: the near field
   is exact, so one light, or two, is reproduced exactly) and the grid lights of S1 and up beyond,
   blended (§3.2); ``usdml:direct:shadowSamples`` shadow rays per pixel (0: chosen per frame,
   :func:`choose_shadow_samples`) are importance-sampled while
   gathering (Appendix A, stratified), each to a light the chosen grid light stands for and weighed
   by the grid light's irradiance (:data:`SHADOW_TARGETS`); each light the samples chose counts once,
   by its inclusion probability (:func:`usdml.lighting.lgh.shading.shadow_fraction`'s ``inclusion``),
   and the shadow ratio scales the unshadowed LGH irradiance. Where it costs less (``usdml:direct:gather``
   auto, :func:`choose_gather`), every pixel sums every grid light instead (the hierarchy's limit,
   :mod:`usdml.lighting.lgh.each`), its rays drawn among the lights by each one's own light at the pixel.
   The ratio is filtered (à-trous, §3.3)
   only when ``usdml:shadow:filterIterations`` asks (> 0): on the city at night, 100,000 lamps at
   256 px, alpha 3, 32 samples, one iteration took the relative RMSE of ``direct`` from 13.0 to
   25.7 % and the automatic two to 32.9 % (shadows of buildings on streets a few pixels wide).

AOVs: ``direct`` is the sum of both parts; ``lightCount`` is the lights that face the pixel: the
every-light part's count plus the LGH's ``Σ B_l · (lights each grid light stands for)`` over the grid
lights that reach it (fractional); ``shadow`` is the fraction of those lights that are blocked, as
with ``--direct all``: the every-light part counts its blocked lights, the LGH part estimates its
blocked lights from the samples (each chosen light's count over its inclusion probability, as a
fraction of the chosen lights' counts), the two weighed by the lights each stands for. The estimate
is noisy per pixel (the far lights, most of a pixel's lights by number, are rarely chosen, as they
bring little light): city at night, 100,000 lamps, 256 px, mean 0.756 against 0.775, 0.063 off per
pixel on average.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import numpy as np

from usdml.lighting.area.params import LIGHT_SAMPLES
from usdml.lighting.area.sampling import sampled
from usdml.lighting.area.targets import AreaTargets
from usdml.lighting.direct import DirectResult
from usdml.scene import Lights, LightType

LUMA = np.array([0.2126, 0.7152, 0.0722])

#: where a grid light's shadow ray goes and how it counts (``usdml:shadow:targets``'s values): a light it
#: stands for, drawn by luminance, the sample weighed by the grid light's irradiance. City at night, 100,000 lamps,
#: 64 px, alpha 2, unfiltered, relative RMSE of direct at 32 / 128 samples: cluster 15.5 / 8.9 %, member
#: (weighed by the light's own irradiance, the VPLs' default) 17.4 / 11.3 %, jitter 22.9 / 18.0 %
SHADOW_TARGETS = "cluster"

#: isotropic-equivalent intensity of a one-sided cosine emitter: I cos = (I / 4) · 4 cos (the LGH lobe)
COSINE_SHARE = 0.25

#: what a grid light's term in the sum over every light (``usdml:direct:gather`` each, ``kernels/lgh/lghq.c``
#: ``lghq_each``) costs in visits of the hierarchy's gather at usdml:direct:alpha, up to :data:`EACH_COST_LIGHTS`
#: lights, by the lanes the sum runs on (:func:`usdml.lighting.lgh.native.each_lanes`; 0: a platform without the
#: function clones, taken as AVX2). AVX-512: the sum's seconds over the hierarchy's per visit on the suite's six
#: tuning stages at 100,000 lights, 128 px, both with their own shadow rays (64-121 per pixel): 0.025-0.039
#: (docs/lgh-direct.md); AVX2 and SSE scaled as ``--gi lgh``'s VPL sums measured (1.6-1.7 and 3.2 times
#: AVX-512's per light)
EACH_VISIT_COSTS = {16: 0.034, 8: 0.055, 4: 0.11, 0: 0.055}
#: above this many lights a light's term costs less in the hierarchy's visits, as (lights / this) ** -EACH_COST_FALL:
#: the hierarchy's tables outgrow the caches while the sum streams its lights in chunks. On the tuning stages at
#: 1,000,000 lights (256 px) a term cost 0.012-0.018 visits, against 0.025-0.039 at 100,000
EACH_COST_LIGHTS = 100_000
EACH_COST_FALL = 0.32


#: with the preview surface, a light's term in the sum over every light (``lghq_each_brdf``, one light at a time with
#: its BRDF) costs this many times the Lambertian one, counted in visits of the hierarchy's gather with the BRDF
#: (``lghq_gather_brdf``): on the city (1,024 lights, 128 px, glossy against diffuse, each run both ways) the sum's
#: lighting took 5.2 times its Lambertian seconds and the hierarchy's 1.23 times
EACH_BRDF_COST = 4.2


def each_visits(lights: int, lanes: int) -> float:
    """What a point's sum over ``lights`` grid lights costs, in visits of the hierarchy's gather, on ``lanes``
    (:data:`EACH_VISIT_COSTS`, falling above :data:`EACH_COST_LIGHTS` lights)."""
    cost = EACH_VISIT_COSTS.get(lanes, EACH_VISIT_COSTS[0])
    if lights > EACH_COST_LIGHTS:
        cost *= (lights / EACH_COST_LIGHTS) ** -EACH_COST_FALL
    return cost * lights

#: the automatic shadow samples (``usdml:direct:shadowSamples`` 0, :func:`choose_shadow_samples`): a pilot of
#: PILOT_SAMPLES rays per point on PILOT_POINTS of the frame's first pass, twice with other seeds
PILOT_POINTS = 512
PILOT_SAMPLES = 64
#: the fewest shadow rays per pixel the automatic choice takes (the fixed default of earlier versions: fewer
#: would leave the ``shadow`` AOV, the blocked fraction of the lights by number, noisier than it was, and the
#: direct light of an easy stage gains little), and the most
MIN_SAMPLES = 64
MAX_SAMPLES = 1024
#: the automatic choice sends at most one ray per this many grid lights per pixel (the speed headroom: the
#: rays stay this many times fewer than every-light shading's); below MIN_SAMPLES · LIGHTS_PER_RAY grid lights
#: it takes MIN_SAMPLES without a pilot
LIGHTS_PER_RAY = 100


def clamp_distance(direct: "DirectField") -> float:
    """The geometry term's clamp for the stage's own lights: a millionth of the S1 spacing (a light is a light,
    not a VPL standing for a patch of surface: next to none)."""
    return 1e-6 * float(direct.lgh.h1)


def grid_mask(lights: Lights) -> np.ndarray:
    """``(N,) bool``: the lights a grid light represents faithfully (see the module doc)."""
    t = np.asarray(lights.type)
    kind = np.isin(t, (LightType.POINT, LightType.SPHERE, LightType.DISK, LightType.RECT, LightType.TRIANGLE))
    plain = (np.asarray(lights.cone_angle) >= 180.0) & (np.asarray(lights.focus) <= 0.0)
    lum = np.asarray(lights.intensity, np.float64).reshape(-1, 3) @ LUMA
    return kind & plain & np.asarray(lights.shadow, bool) & (lum > 0.0)


def area_every_light(lights: Lights, grid: np.ndarray, light_samples: int) -> np.ndarray:
    """``(N,) bool``: the lights with area among the ``grid`` ones when they are few enough to be shaded every-light,
    exactly as ``--direct all`` does (their samples' rays per point, lights × ``light_samples``, no more than
    :data:`MAX_SAMPLES`, the most shadow rays the hierarchy's automatic choice sends per pixel); none otherwise."""
    area = sampled(lights) & grid
    return area if int(area.sum()) * max(int(light_samples), 1) <= MAX_SAMPLES else np.zeros_like(area)


def grid_sources(lights: Lights) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(positions (N, 3), isotropic-equivalent intensities (N, 3), emission normals (N, 3) or None)``
    of grid lights: ``I`` for isotropic lights, ``I / 4`` about the axis for disk, rect and triangle lights."""
    one_sided = np.isin(np.asarray(lights.type), (LightType.DISK, LightType.RECT, LightType.TRIANGLE))
    intensity = np.asarray(lights.intensity, np.float32).reshape(-1, 3).copy()
    if not one_sided.any():
        return np.asarray(lights.position, np.float64), intensity, None
    intensity[one_sided] *= np.float32(COSINE_SHARE)
    normals = np.zeros_like(intensity)
    normals[one_sided] = np.asarray(lights.axis, np.float32)[one_sided]
    return np.asarray(lights.position, np.float64), intensity, normals


@dataclass
class DirectField:
    """One frame's lights as ``--direct lgh`` shades them: the hierarchy and the every-light rest."""

    grid: Lights                    #: the lights in the hierarchy
    rest: Lights                    #: the lights shaded every-light
    lgh: object | None              #: :class:`usdml.lighting.lgh.build.LGH` over ``grid`` (None without grid lights)
    sources: tuple | None           #: ``grid_sources(grid)``: S0 and the shadow rays' targets
    stats: dict = field(default_factory=dict)
    sampler: object | None = None   #: the shadow rays' :class:`ClusterSampler`, made by the frame's first pass
    samples: int | None = None      #: shadow rays per pixel chosen by the frame's first pass (shadowSamples 0)
    #: every grid light its own light (:class:`usdml.lighting.lgh.each.EachLight`) where the frame's first pass
    #: chose it (:func:`choose_gather`), else None: the hierarchy
    each: object | None = None
    chosen: bool = False            #: whether :func:`choose_gather` has chosen for the frame
    #: the grid's lights with area, where shadow rays aimed at them go (None: none has area)
    area: AreaTargets | None = None

    @property
    def source(self):
        """What the frame's pixels gather from: :attr:`each` where chosen, else the hierarchy."""
        return self.lgh if self.each is None else self.each


def prepare_direct(lights: Lights, levels: int = 0, device: str = "cpu", seed: int = 0,
                   meters_per_unit: float = 1.0, light_samples: int = LIGHT_SAMPLES) -> DirectField:
    """Split the frame's ``lights`` and build the hierarchy over the grid lights (once per frame,
    however many primary rays per pixel gather from it); ``levels`` as ``usdml:lgh:levels``; ``seed`` places the
    shadow rays' points on the grid's lights with area, ``light_samples`` (``usdml:light:samples``) decides whether
    there are few enough of them to shade every-light (:func:`area_every_light`)."""
    from usdml.lighting.lgh.build import build_lgh

    t0 = _time.perf_counter()
    mask = grid_mask(lights)
    mask &= ~area_every_light(lights, mask, light_samples)
    grid, rest = lights.subset(mask), lights.subset(~mask)
    stats = {"grid_lights": len(grid), "every_light": len(rest)}
    if len(grid) == 0:
        stats["lgh_seconds"] = _time.perf_counter() - t0
        return DirectField(grid, rest, None, None, stats)
    sources = grid_sources(grid)
    lgh = build_lgh(sources[0], sources[1], levels=levels, device=device, normal=sources[2])
    stats["lgh_seconds"] = _time.perf_counter() - t0
    stats["lgh_levels"] = lgh.depth
    stats["lgh_h1"] = float(lgh.h1)
    stats["grid_light_count"] = int(len(lgh.position))
    return DirectField(grid, rest, lgh, sources, stats, area=AreaTargets.of(grid, seed, meters_per_unit))


def choose_gather(points: np.ndarray, direct: DirectField, settings, device: str = "cpu",
                  material: bool = False) -> dict:
    """Once per frame (its first pass's ``points``): whether its pixels gather from the hierarchy or from every
    grid light (``usdml:direct:gather``); sets ``direct.each`` and returns the choice's stats.

    ``auto`` takes every light on a CPU with the compiled sum (:func:`usdml.lighting.lgh.native.each_lanes`)
    where a point's sum over the N grid lights (:func:`each_visits`: ``N ·`` :data:`EACH_VISIT_COSTS` visits up to
    :data:`EACH_COST_LIGHTS` lights, fewer per light above) costs no more than the
    hierarchy's gather at ``usdml:direct:alpha`` (:func:`usdml.lighting.lgh.shading.lights_visited`: the grid
    lights and S0 lights a point visits, counted on a few of the points, drawn by the seed).

    With ``material`` (the frame's surfaces carry preview-surface rows) both gathers evaluate the BRDF per light,
    which costs the sum far more of its term than the hierarchy of its visit: the sum's cost is scaled by
    :data:`EACH_BRDF_COST`; and as the rows are gathered compiled on the CPU whatever the device
    (:func:`usdml.lighting.lgh.shading.lgh_indirect`), the device and ``--lgh-cpu-kernel`` do not decide."""
    from usdml.lighting.lgh import native as lgh_native
    from usdml.lighting.lgh.each import EachLight
    from usdml.lighting.lgh.shading import lights_visited

    direct.chosen = True
    mode = settings.direct_gather
    stats: dict = {}
    if mode == "auto":
        lanes = lgh_native.each_lanes() if lgh_native.library() is not None else None
        elsewhere = (device != "cpu" or settings.lgh_cpu_kernel == "warp") and not material
        if elsewhere or lanes is None or len(points) == 0:
            mode = "hierarchy"
        else:
            visits = float(lights_visited(direct.lgh, points, [settings.direct_alpha], s0_positions=direct.sources[0],
                                          seed=int(settings.seed))[0])
            cost = each_visits(len(direct.grid), lanes) * (EACH_BRDF_COST if material else 1.0)
            stats.update({"hierarchy_visits": visits, "each_visits": cost})
            mode = "each" if cost <= visits else "hierarchy"
    direct.each = EachLight(direct.sources) if mode == "each" else None
    stats["gather"] = mode
    return stats


def rays_per_pass(settings, samples: int | None = None) -> int:
    """Shadow rays per primary ray: ``usdml:direct:shadowSamples`` (or ``samples``, the frame's automatic
    choice) is per pixel, shared by its ``usdml:pixelSamples`` primary rays (whose results the pixel
    filter averages)."""
    k = int(settings.direct_shadow_samples) if samples is None else int(samples)
    return max(1, -(-k // max(int(settings.pixel_samples), 1)))


def samples_cap(grid_lights: int) -> int:
    """The most shadow rays per pixel the automatic choice takes over ``grid_lights`` lights: one per
    :data:`LIGHTS_PER_RAY` lights, at least :data:`MIN_SAMPLES`, at most :data:`MAX_SAMPLES`."""
    return int(min(MAX_SAMPLES, max(MIN_SAMPLES, int(grid_lights) // LIGHTS_PER_RAY)))


def samples_for_noise(noise: float, target: float, pilot: int = PILOT_SAMPLES, cap: int = MAX_SAMPLES) -> int:
    """Shadow rays per pixel that bring a relative noise ``noise`` measured at ``pilot`` rays to ``target``:
    the noise falls as 1/sqrt(k) (measured on the suite's tuning stages: 16 -> 64 rays halved it, 64 -> 256
    more than halved it as bright lights become certain picks), so k = pilot (noise / target)^2, within
    [:data:`MIN_SAMPLES`, ``cap``]."""
    if not np.isfinite(noise) or noise <= 0.0:
        return MIN_SAMPLES
    return int(min(max(MIN_SAMPLES, math.ceil(pilot * (noise / float(target)) ** 2)), max(cap, MIN_SAMPLES)))


def choose_shadow_samples(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, direct: DirectField,
                          occluded, settings, *, meters_per_unit: float = 1.0, geometric: np.ndarray | None = None,
                          device: str = "cpu", material: np.ndarray | None = None) -> tuple[int, dict]:
    """Shadow rays per pixel for ``usdml:direct:shadowSamples`` 0: ``(k, stats)``.

    The error of ``--direct lgh`` is mostly the stochastic shadows' noise (on the suite's tuning stages,
    100,000 lights at 128 px: 2.3-4.4 % relative RMSE at 64 rays, 0.6-1.2 % at 1,024, where the hierarchy's
    own error is left), and how much noise a number of rays leaves depends on the stage (how much is in
    shadow, how the light is spread over the lights): 64 rays left 2.3 % on one stage and 8 % on another.
    So the frame measures it: :data:`PILOT_POINTS` of its first pass's ``points`` (drawn by the seed) are
    shaded twice with :data:`PILOT_SAMPLES` rays and two other seeds; half the mean squared difference of
    the two is the noise's variance at that count, its root over the two's mean light the relative noise,
    and :func:`samples_for_noise` gives the rays that bring it to ``usdml:direct:shadowNoise``, capped by
    :func:`samples_cap` (the speed headroom). Arguments as :func:`shade_lgh_direct`.
    """
    from usdml.lighting.lgh.shading import lgh_indirect

    t0 = _time.perf_counter()
    n = len(points)
    cap = samples_cap(len(direct.grid))
    if cap <= MIN_SAMPLES or n == 0:        # nothing to choose
        return MIN_SAMPLES, {"shadow_samples": MIN_SAMPLES, "samples_cap": cap}
    m = min(n, PILOT_POINTS)
    pick = np.sort(np.random.default_rng([int(settings.seed), 37]).choice(n, m, replace=False))
    geo = normals if geometric is None else geometric
    runs = [lgh_indirect(points[pick], normals[pick], albedo[pick], direct.source, occluded, alpha=settings.direct_alpha,
                         samples=PILOT_SAMPLES, seed=int(settings.seed) + 1 + i, meters_per_unit=meters_per_unit,
                         clamp_distance=clamp_distance(direct), filter_iterations=0, device=device,
                         sources=direct.sources, start_level=0, shadow_targets=SHADOW_TARGETS, geometric=geo[pick],
                         sampler=direct.sampler, inclusion=True, cpu_kernel=settings.lgh_cpu_kernel,
                         material=None if material is None else material[pick]).radiance
            for i in range(2)]
    a, b = (r.astype(np.float64) for r in runs)
    mean = 0.5 * float((a + b).mean())
    noise = math.sqrt(0.5 * float(np.mean((a - b) ** 2))) / mean if mean > 0 else 0.0
    k = samples_for_noise(noise, settings.direct_shadow_noise, PILOT_SAMPLES, cap)
    return k, {"shadow_samples": k, "pilot_noise": noise, "pilot_points": m, "samples_cap": cap,
               "pilot_seconds": _time.perf_counter() - t0}


def shade_lgh_direct(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, direct: DirectField,
                     occluded, shade_rest, settings, *, meters_per_unit: float = 1.0,
                     image: tuple | None = None, geometric: np.ndarray | None = None,
                     device: str = "cpu", material: np.ndarray | None = None) -> tuple[DirectResult, dict]:
    """Direct light at ``P`` points from ``direct`` (:func:`prepare_direct`): ``(DirectResult, stats)``.

    ``occluded`` is the visibility backend's shadow query; ``shade_rest(points, normals, albedo,
    lights, geometric=)`` shades the every-light rest (the backend's ``shade_direct``). ``settings``:
    ``direct_shadow_samples`` (0: :func:`choose_shadow_samples`, once per ``direct``, with
    ``direct_shadow_noise``), ``direct_alpha``, ``shadow_filter_iterations``, ``seed``, ``lgh_cpu_kernel``. ``image =
    (hit, positions)`` lets the shadow ratio be filtered; ``geometric`` normals, when given, are where
    shadow rays leave from (and, for the rest, which lights face a point). ``material`` (P, WIDTH) rows
    (``kernels/brdf``; None: Lambertian): the preview surface, ``albedo`` being the diffuse reflectance ρ; each grid
    light adds ``E·(ρ/π·kd + ks)`` toward its illumination centre and draws the shadow rays by it
    (:func:`usdml.lighting.lgh.shading.lgh_indirect`), ``shade_rest`` gets ``material=`` too, and the result's
    ``specular`` is both parts' ``Σ E·ks``.
    """
    from usdml.lighting.lgh.shading import ClusterSampler, lgh_indirect

    n = len(points)
    stats: dict = {}
    t0 = _time.perf_counter()
    if direct.area is not None and occluded is not None:
        occluded = direct.area.wrap(occluded)          # shadow rays to points on the lights with area
    brdf = {} if material is None else {"material": material}
    rest = shade_rest(points, normals, albedo, direct.rest, geometric=geometric, **brdf) if len(direct.rest) else \
        DirectResult(np.zeros((n, 3), np.float32), np.zeros(n, np.float32), np.zeros(n, np.int32), 0,
                     None if material is None else np.zeros((n, 3), np.float32))
    stats["every_light_seconds"] = _time.perf_counter() - t0
    if direct.lgh is None or n == 0:
        return rest, stats
    t1 = _time.perf_counter()
    clamp = clamp_distance(direct)
    if not direct.chosen:
        stats.update(choose_gather(points, direct, settings, device, material is not None))
        stats["choice_seconds"] = _time.perf_counter() - t1
    if direct.sampler is None and direct.each is None:
        direct.sampler = ClusterSampler(direct.lgh, *direct.sources, reweight=SHADOW_TARGETS == "member",
                                        meters_per_unit=meters_per_unit, clamp_distance=clamp,
                                        cpu_kernel=settings.lgh_cpu_kernel)
        stats["sampler_seconds"] = _time.perf_counter() - t1
    samples = None
    if int(settings.direct_shadow_samples) <= 0 and occluded is not None:     # automatic: once per frame
        if direct.samples is None:
            direct.samples, chosen = choose_shadow_samples(points, normals, albedo, direct, occluded, settings,
                                                           meters_per_unit=meters_per_unit, geometric=geometric,
                                                           device=device, material=material)
            stats.update(chosen)
        samples = direct.samples
    r = lgh_indirect(points, normals, albedo, direct.source, occluded, alpha=settings.direct_alpha,
                     samples=rays_per_pass(settings, samples), seed=settings.seed, meters_per_unit=meters_per_unit,
                     clamp_distance=clamp, image=image,
                     filter_iterations=max(settings.shadow_filter_iterations, 0), device=device,
                     sources=direct.sources,
                     start_level=0, shadow_targets=SHADOW_TARGETS, geometric=geometric, sampler=direct.sampler,
                     inclusion=True, cpu_kernel=settings.lgh_cpu_kernel, material=material)
    stats.update({f"lgh_{k}": v for k, v in r.stats.items()})
    stats["lgh_shading_seconds"] = _time.perf_counter() - t1
    count = np.asarray(r.count if r.count is not None else np.zeros(n), np.float32)
    blocked = 1.0 - r.visible.astype(np.float64)       # of the lights the samples stand for
    facing = rest.facing.astype(np.float64) + count
    blocked_lights = rest.shadow.astype(np.float64) * rest.facing + blocked * count
    shadow = np.where(facing > 0, blocked_lights / np.maximum(facing, 1e-30), 0.0)
    radiance = (rest.radiance + r.radiance).astype(np.float32)
    queries = rest.queries + int(r.stats.get("shadow_rays", 0))
    specular = None
    if material is not None:
        specular = (r.specular if rest.specular is None else rest.specular + r.specular).astype(np.float32)
    return DirectResult(radiance, shadow.astype(np.float32), facing.astype(np.float32), queries, specular), stats
