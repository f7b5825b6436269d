"""Indirect light with virtual point lights: ``lgh`` (paper 004), ``svo`` (paper 003,
:mod:`usdml.lighting.interleaved`) or the ``vpl-bruteforce`` reference.

All three use the same VPLs (same seed) and the same lighting model: each VPL is a Lambertian emitter of
its flux Φ, ``Φ·cos θ / π`` about its normal (an isotropic point of Φ/4π sent half its power into its
own surface: 0.44 of path tracing's indirect energy on a closed box, 0.49 in the furnace), a clamped
geometry term ``1 / max(d², d_c²)`` with ``d_c`` half the S1 grid spacing, and Lambertian receivers.
Brute force gathers them as one-sided cosine lights; ``svo`` gathers a sixteenth of them per pixel
(interleaved 4×4 tiles, × 16) with the same emission and clamp; the LGH aggregates their normals into each grid
light's lobe (:func:`usdml.kernels.lgh.shading.lobe_factor`). So the difference between the two is the
hierarchy's approximation and its stochastic, filtered shadows, which is what
``usdml compare --gi lgh --against vpl-bruteforce`` measures."""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from usdml.lighting.direct import shade_direct
from usdml.lighting.lgh.build import build_lgh, build_lgh_split, s1_spacing
from usdml.lighting.lgh.choice import choose as choose_hierarchy
from usdml.lighting.lgh.shading import (AUTO_VPLS_PER_RAY, EACH_VPLS_PER_RAY, auto_shadow_samples, cluster_sampler,
                                         lgh_indirect)
from usdml.lighting.vpl import generate_vpls
from usdml.scene import Lights, Snapshot
from usdml.settings import UsdmlSettings


@dataclass
class GIResult:
    radiance: np.ndarray            #: (P, 3) float32 indirect outgoing radiance at the points
    stats: dict = field(default_factory=dict)


def warm_up(device: str = "cpu") -> float:
    """Load the Warp kernels of the LGH path on ``device`` (done once per process on the first frame
    otherwise: ~0.2 s here, more than a whole cornell frame's indirect pass). Returns the seconds."""
    t0 = _time.perf_counter()
    from usdml.kernels import atrous, warp
    from usdml.kernels.lgh import build as lgh
    from usdml.kernels.lgh import shading as lgh_lighting

    wp = warp()
    for module in (lgh, lgh_lighting, atrous):
        wp.load_module(module, device=device)
    build_lgh(np.zeros((2, 3), np.float32), np.ones((2, 3), np.float32), device=device)  # Warp's scan, too
    return _time.perf_counter() - t0


@dataclass
class VPLField:
    """What every pass of a frame gathers indirect light from: the frame's VPLs and their LGH."""

    vpls: object                    #: :class:`usdml.lighting.vpl.VPLs`
    lgh: object | None              #: the lighting grid hierarchy over them (None without VPLs, or for svo)
    intensity: np.ndarray | None    #: (V, 3) float32 isotropic-equivalent intensity Φ/4π
    stats: dict = field(default_factory=dict)
    clamp: float = 0.0              #: geometry-term clamp distance d_c, scene units: half the S1 spacing
    #: ``--gi lgh``, made by the frame's first pass for the rest (with the settings they were made for): the
    #: hierarchy and ``--lgh-alpha`` chosen (:func:`usdml.lighting.lgh.choice.choose`), the candidates it
    #: weighed, the shadow rays' ``ClusterSampler`` and the passes' gathers
    frame_choices: dict = field(default_factory=dict)
    #: makes the hierarchy split by VPL normal over the same VPLs (``--lgh-split``; the frame's choice calls
    #: it at most once, through :meth:`split_lgh`)
    build_split: Callable[[], object] | None = field(default=None, repr=False)
    _split: object | None = field(default=None, repr=False)

    def split_lgh(self):
        """The hierarchy split by VPL normal (:func:`usdml.lighting.lgh.build.build_lgh_split`), made on first use."""
        if self._split is None:
            self._split = self.build_split()
        return self._split


def prepare_vpls(snap: Snapshot, exact, lights: Lights, settings: UsdmlSettings, device: str = "cpu") -> VPLField:
    """Trace the frame's light paths into VPLs (``exact``: closest hits) and build their LGH, once
    per frame however many primary rays per pixel gather from them (``svo`` needs only the LGH's S1
    spacing, for the clamp, and builds no hierarchy)."""
    stats: dict = {}
    t0 = _time.perf_counter()
    vpls = generate_vpls(snap, exact, lights, settings.vpl_count, settings.vpl_bounces, settings.seed)
    stats["vpl_seconds"] = _time.perf_counter() - t0
    stats["vpls"] = len(vpls)
    if len(vpls) == 0:
        return VPLField(vpls, None, None, stats)
    # the LGH takes isotropic-equivalent intensity Φ/4π plus each VPL's normal (cosine emission);
    # brute force gathers the same VPLs as one-sided cosine emitters (Φ/π on the normal)
    intensity = (vpls.flux / np.float32(4.0 * np.pi)).astype(np.float32)
    t1 = _time.perf_counter()
    if settings.gi == "svo":
        clamp = 0.5 * s1_spacing(vpls.position, intensity, levels=settings.lgh_levels, device=device)
        stats["lgh_seconds"] = _time.perf_counter() - t1
        return VPLField(vpls, None, intensity, stats, clamp)
    # --lgh-split normal: the split hierarchy; none and auto: the single one (auto makes the split one only
    # if the frame's choice needs it, usdml.lighting.lgh.choice)
    split = settings.lgh_split == "normal"
    lgh = (build_lgh_split(vpls.position, intensity, vpls.normal, levels=settings.lgh_levels, device=device) if split
           else build_lgh(vpls.position, intensity, levels=settings.lgh_levels, device=device, normal=vpls.normal))
    stats["lgh_seconds"] = _time.perf_counter() - t1
    stats["lgh_levels"] = lgh.depth
    field = VPLField(vpls, lgh, intensity, stats, 0.5 * float(lgh.h1))
    # the split one on the single one's level count (what --lgh-levels 0 finds for these VPLs: not found again)
    field.build_split = (lambda: lgh) if split else \
        (lambda: build_lgh_split(vpls.position, intensity, vpls.normal, levels=settings.lgh_levels or lgh.depth,
                                 device=device))
    return field


def indirect_lighting(snap: Snapshot, exact, occluded, lights: Lights, points: np.ndarray, normals: np.ndarray,
                      albedo: np.ndarray, settings: UsdmlSettings, image: tuple | None = None,
                      device: str = "cpu", vpl_field: VPLField | None = None,
                      geometric: np.ndarray | None = None, target_lift: float = 0.0) -> GIResult:
    """Indirect radiance at ``points`` by ``settings.gi`` ("lgh", "svo" or "vpl-bruteforce").

    ``exact`` traces the light paths that place the VPLs (closest hits) unless ``vpl_field``
    (:func:`prepare_vpls`) already holds them; the rest as :func:`indirect_gather`'s gather.
    """
    if vpl_field is None:
        vpl_field = prepare_vpls(snap, exact, lights, settings, device)
    return indirect_gather(settings.gi)(vpl_field, snap, occluded, points, normals, albedo, settings, image=image,
                                        device=device, geometric=geometric, target_lift=target_lift)


def indirect_gather(method: str) -> Callable[..., GIResult]:
    """``--gi method``'s gather ("lgh", "svo" or "vpl-bruteforce"), chosen once for every frame:
    ``gather(vpl_field, snap, occluded, points, normals, albedo, settings, *, image, device, geometric,
    target_lift) -> GIResult``, indirect radiance at ``P`` points from a frame's :class:`VPLField`.

    ``occluded`` is the chosen visibility backend's shadow query (for ``svo``: that of the backend the
    frame renderer owns for it); ``image = (hit, positions)`` lets the LGH shadow ratio be filtered in
    screen space (``svo``: required, its tiles and filter are the image's); ``geometric`` normals, when
    given, decide which VPLs face a point and where shadow rays start
    (:func:`usdml.lighting.direct.shade_direct`); ``target_lift`` moves ``svo``'s VPL targets off their
    surface (:func:`usdml.lighting.interleaved.target_lift`).
    """
    try:
        gather = _GATHERS[method]
    except KeyError:
        raise ValueError(f"no VPL gather for --gi {method!r}; one of {', '.join(_GATHERS)}") from None

    def indirect(vpl_field: VPLField, snap: Snapshot, occluded, points: np.ndarray, normals: np.ndarray,
                 albedo: np.ndarray, settings: UsdmlSettings, **where) -> GIResult:
        stats = dict(vpl_field.stats)
        if len(vpl_field.vpls) == 0:
            return GIResult(np.zeros((len(points), 3), np.float32), stats)
        radiance, s = gather(vpl_field, snap, occluded, points, normals, albedo, settings, **where)
        stats.update(s)
        return GIResult(radiance, stats)
    return indirect


def _gather_svo(field: VPLField, snap: Snapshot, occluded, points, normals, albedo, settings, *, image, device,
                geometric, target_lift) -> tuple[np.ndarray, dict]:
    """A sixteenth of the VPLs per pixel, interleaved over the image's 4x4 tiles (paper 003)."""
    from usdml.lighting.interleaved import svo_indirect

    if image is None:
        raise ValueError("--gi svo gathers over the image's 4x4 tiles: pass image=(hit, positions)")
    return svo_indirect(points, normals, albedo, field.vpls, occluded, field.clamp, image,
                        meters_per_unit=snap.meters_per_unit, geometric=geometric,
                        target_lift=target_lift, skip_below=settings.gi_svo_skip)


def _gather_lgh(field: VPLField, snap: Snapshot, occluded, points, normals, albedo, settings, *, image, device,
                geometric, target_lift) -> tuple[np.ndarray, dict]:
    """The lighting grid hierarchy over the VPLs, stochastic filtered shadows (paper 004)."""
    t0 = _time.perf_counter()
    sources = (field.vpls.position, field.intensity, field.vpls.normal)
    s0 = settings.lgh_start_level == 0
    key = (settings.lgh_alpha, s0, settings.shadow_targets, settings.lgh_cpu_kernel, settings.lgh_split)
    if field.frame_choices.get("key") != key:           # the frame's first pass (or other settings)
        choice = choose_hierarchy(
            field.lgh if settings.lgh_split != "normal" else None, field.split_lgh, points, normals, sources,
            alpha=settings.lgh_alpha, split=settings.lgh_split, s0=s0, clamp_distance=field.clamp,
            meters_per_unit=snap.meters_per_unit, seed=settings.seed, device=device,
            # every VPL its own light, where it is cheaper: compiled on a CPU, from S0, with shadow rays to the VPLs
            each=(device == "cpu" and s0 and settings.interleave == 1 and settings.lgh_cpu_kernel != "warp"
                  and settings.shadow_targets in ("member", "cluster")))
        sampler = None if choice.split == "each" else cluster_sampler(
            choice.lgh, sources, settings.shadow_targets, snap.meters_per_unit, field.clamp, settings.lgh_cpu_kernel)
        field.frame_choices = {"key": key, "alpha": choice.alpha, "sampler": sampler, "lgh": choice.lgh,
                               "split": choice.split, "candidates": choice.candidates}
    choices_s = _time.perf_counter() - t0
    each = field.frame_choices["split"] == "each"
    samples = settings.shadow_samples if settings.shadow_samples > 0 else \
        auto_shadow_samples(len(field.vpls), EACH_VPLS_PER_RAY if each else AUTO_VPLS_PER_RAY)
    r = lgh_indirect(points, normals, albedo, field.frame_choices["lgh"], occluded, alpha=field.frame_choices["alpha"],
                     samples=samples, seed=settings.seed,
                     meters_per_unit=snap.meters_per_unit, clamp_distance=field.clamp, image=image,
                     interleave=settings.interleave, device=device, sources=sources,
                     start_level=settings.lgh_start_level, filter_iterations=settings.shadow_filter_iterations,
                     shadow_targets=settings.shadow_targets, geometric=geometric,
                     sampler=field.frame_choices["sampler"], cpu_kernel=settings.lgh_cpu_kernel,
                     gathers=field.frame_choices.setdefault("gathers", {}))
    r.stats["choice_seconds"] = choices_s
    # each: every VPL, no α (null in JSON)
    r.stats["lgh_alpha"] = None if each else field.frame_choices["alpha"]
    r.stats["lgh_split"] = field.frame_choices["split"]
    r.stats["lgh_split_candidates"] = field.frame_choices["candidates"]
    r.stats["shadow_samples"] = samples
    return r.radiance, r.stats


def _gather_bruteforce(field: VPLField, snap: Snapshot, occluded, points, normals, albedo, settings, *, image,
                       device, geometric, target_lift) -> tuple[np.ndarray, dict]:
    """Every VPL as a one-sided cosine light with a shadow ray: the reference."""
    t2 = _time.perf_counter()
    r = shade_direct(points, normals, albedo, field.vpls.as_lights(isotropic=False), occluded,
                     meters_per_unit=snap.meters_per_unit, min_distance=field.clamp, geometric=geometric)
    return r.radiance, {"lighting_seconds": _time.perf_counter() - t2, "shadow_rays": r.queries}


#: --gi method -> its gather over a frame's VPLs
_GATHERS = {"lgh": _gather_lgh, "svo": _gather_svo, "vpl-bruteforce": _gather_bruteforce}
