"""The direct and the indirect light of a frame, each integrator chosen once per renderer from the settings.

Direct (:func:`direct_integrator`), per pass a G-buffer and its :class:`usdml.lighting.direct.DirectResult`:

* :class:`EveryLight` (``--direct all``): every light with the shadow backend's shadows, per pass
  (:func:`usdml.lighting.direct.shade_with`: a ``SHADE_DIRECT`` backend in one kernel);
* :class:`EveryLightFused`: the same over a ``LIGHT_MAJOR`` backend with several primary rays per pixel:
  every pass's points shaded by one call, so the backend's per-light structures (paper 001's maps) are
  built once per frame, not once per pass;
* :class:`LghDirect` (``--direct lgh``): one hierarchy over the frame's lights
  (:mod:`usdml.lighting.lgh.direct`), gathered in every pass.

Indirect (:func:`gi_integrator`): :class:`NoGI` (``--gi none``), or :class:`VplGI`: the frame's VPLs (and
their LGH) made once, gathered in every pass by ``--gi``'s method (:func:`usdml.lighting.gi.indirect_gather`).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, replace
from typing import Callable, Iterator

import numpy as np

from usdml.errors import log
from usdml.lighting.area.params import LIGHT_SAMPLES
from usdml.lighting.direct import DirectResult, shade_with
from usdml.render.backends import Backends
from usdml.render.frame_stats import FrameStats
from usdml.render.gbuffer import GBuffer, PixelPass, build_gbuffer
from usdml.render.light_classes import LightClass, LinkedShadows, light_classes, shade_classes, shading_units
from usdml.scene import Lights, LightType, Snapshot
from usdml.scene.shading import lambert_rows
from usdml.settings import UsdmlSettings
from usdml.visibility.base import LIGHT_MAJOR

Progress = Callable[[float], None] | None


@dataclass
class FrameInputs:
    """What every pass of one frame reads: the snapshot (camera conformed to the image), its lights, the size."""

    snap: Snapshot
    lights: Lights
    width: int
    height: int


@dataclass
class Surface:
    """One pass's hit pixels (G-buffer order) as ``(P, 3)`` arrays: what direct and indirect light shade."""

    hit: np.ndarray             #: (H·W,) bool, the pixels whose ray hit
    position: np.ndarray        #: (P, 3) world units
    normal: np.ndarray          #: (P, 3) shading normals
    albedo: np.ndarray          #: (P, 3) diffuse reflectance ρ
    geometric: np.ndarray       #: (P, 3) geometric normals
    material: np.ndarray | None = None   #: (P, WIDTH) BRDF rows (``kernels/brdf``), None: every point Lambertian
    emission: np.ndarray | None = None   #: (P, 3) emitted radiance, or None
    prim_id: np.ndarray | None = None    #: (P,) the G-buffer's primId (light linking's geometry)
    instance_id: np.ndarray | None = None   #: (P,) its instanceId

    def restricted(self, sel: np.ndarray) -> "Surface":
        """The surface of the points ``sel`` (a boolean mask over its points) only: the other pixels count as missed."""
        hit = np.zeros_like(self.hit)
        hit[np.flatnonzero(self.hit)[sel]] = True
        return Surface(hit, *(None if getattr(self, f) is None else getattr(self, f)[sel]
                              for f in ("position", "normal", "albedo", "geometric", "material", "emission",
                                        "prim_id", "instance_id")))

    @classmethod
    def of(cls, gb: GBuffer) -> "Surface":
        hit = gb.hit.ravel()
        material = None if gb.material is None else gb.material[hit]
        emission = None if gb.emission is None else gb.emission.reshape(-1, 3)[hit]
        return cls(hit, *(getattr(gb, name).reshape(-1, 3)[hit]
                          for name in ("position", "normal", "albedo", "geometric")), material, emission,
                   gb.prim_id.ravel()[hit], gb.instance_id.ravel()[hit])


def dome_columns(lights: Lights, domes: list) -> np.ndarray | None:
    """(L,) bool: the frame's lights that stand for a dome (its distant samples, usdml.lighting.dome), or None."""
    if not domes or not len(lights):
        return None
    paths = {d.path for d in domes}
    mask = np.fromiter((p in paths for p in lights.paths), bool, len(lights)) & (lights.type == int(LightType.DISTANT))
    return mask if mask.any() else None


def shade_surface(backend, frame: FrameInputs, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                  geometric: np.ndarray, material: np.ndarray | None, seed: int, progress: Progress,
                  light_samples: int = LIGHT_SAMPLES) -> DirectResult:
    """Every light of ``frame`` at the points (:func:`usdml.lighting.direct.shade_with`, ``light_samples`` points on
    each light with area, placed by ``seed``); with material rows a dome's distant samples light the diffuse lobe and
    its specular lobes are sampled from the BRDF (:func:`usdml.lighting.dome_specular.dome_specular`)."""
    domes = frame.snap.domes if material is not None else []
    if domes:       # the domes among the lights shaded (a class of a linked frame holds some only)
        present = set(frame.lights.paths)
        domes = [d for d in domes if d.path in present]
    mask = dome_columns(frame.lights, domes)
    direct = shade_with(backend, points, normals, albedo, frame.lights, progress,
                        meters_per_unit=frame.snap.meters_per_unit, geometric=geometric, material=material,
                        diffuse_only=mask, light_samples=light_samples, seed=seed)
    if mask is not None:
        from usdml.lighting.dome_specular import dome_specular

        spec = dome_specular(points, normals, geometric, material, domes, backend.occluded, seed)
        direct.radiance += spec
        direct.specular = spec if direct.specular is None else direct.specular + spec
    return direct


def _gbuffer(frame: FrameInputs, backends: Backends, rays: PixelPass, stats: FrameStats,
             visible_lights: bool) -> GBuffer:
    t0 = _time.perf_counter()
    gb = build_gbuffer(frame.snap, backends.primary, frame.width, frame.height, rays.offsets, visible_lights,
                       rays.lens)
    stats.gbuffer_seconds += _time.perf_counter() - t0
    return gb


class EveryLight:
    """``--direct all``, a pass at a time (module doc)."""

    def __init__(self, backends: Backends, settings: UsdmlSettings, device: str, where: str):
        self.backends, self.settings, self.device, self.where = backends, settings, device, where
        #: called with ``(frame, surface, stats)`` on each frame's first pass before it is shaded (``--error-budget``
        #: chooses the frame's refinement there: usdml.render.budget)
        self.before_shading: Callable[[FrameInputs, "Surface", FrameStats], None] | None = None
        #: split the direct light by light group (``lightgroup:`` AOVs asked for): set by the frame renderer
        self.groups = False
        #: the shadow backends of shadow-link sets (usdml.render.light_classes), made by the frame renderer
        self.linked: LinkedShadows | None = None
        self.classes: list[LightClass] = []

    def prepare(self, frame: FrameInputs, stats: FrameStats) -> None:
        """Once per frame, before its passes: the frame's light classes (usdml.render.light_classes)."""
        self.classes = light_classes(frame.lights, self.groups)

    def by_class(self, frame: FrameInputs, prim_id: np.ndarray, instance_id: np.ndarray, progress: Progress,
                 shade: Callable[..., DirectResult]) -> DirectResult:
        """The direct light at points (``prim_id``, ``instance_id`` each) as :func:`usdml.render.light_classes.
        shade_classes` sums it: ``shade(ks, backends, frame of the lights of classes ks, points, progress)`` for each
        shading unit (``ks``: indices in :attr:`classes`), with the backends of its shadow set; one call over every
        point (``ks`` None) when the frame is one plain class."""
        if self.single():
            return shade(None, self.backends, frame, slice(None), progress)
        total = len(frame.lights)

        def members(link: int) -> np.ndarray:
            return self._members(frame, prim_id, instance_id, link)

        def one(ks: tuple[int, ...], sel: np.ndarray) -> DirectResult:
            index = np.concatenate([self.classes[k].index for k in ks])
            share = None if progress is None else (lambda done, f=len(index) / total: progress(done * f))
            shadow_link = self.classes[ks[0]].shadow_link
            backends = self.backends if self.linked is None else self.linked.backends(shadow_link, self.backends)
            return shade(ks, backends, replace(frame, lights=frame.lights.subset(index)), sel, share)

        return shade_classes(self.classes, len(prim_id), members, one, self.groups)

    @staticmethod
    def _members(frame: FrameInputs, prim_id: np.ndarray, instance_id: np.ndarray, link: int) -> np.ndarray:
        """``(P,) bool``: the points (the G-buffer's ``prim_id``, ``instance_id`` of each) light-link set ``link``
        reaches."""
        links = frame.snap.links
        return np.ones(len(prim_id), bool) if links is None else links.members(link, prim_id, instance_id)

    def single(self) -> bool:
        """Whether the frame is shaded in one call: no lights, or one plain class and no groups asked."""
        return not self.classes or (len(self.classes) == 1 and self.classes[0].plain and not self.groups)

    def _before_shading(self, frame: FrameInputs, surface: "Surface", stats: FrameStats, first: bool) -> None:
        if first and self.before_shading is not None:
            self.before_shading(frame, surface, stats)

    def passes(self, frame: FrameInputs, passes: list[PixelPass], stats: FrameStats,
               progress: Progress) -> Iterator[tuple[GBuffer, Surface, DirectResult]]:
        """``(G-buffer, its surface, direct light)`` of each pass of ``passes`` (its sub-pixel offsets and lens
        points, :class:`usdml.render.gbuffer.PixelPass`), one at a time: the caller finishes a pass before the
        next is traced."""
        for i, rays in enumerate(passes):
            gb = _gbuffer(frame, self.backends, rays, stats, self.settings.visible_lights)
            surface = Surface.of(gb)
            self._before_shading(frame, surface, stats, i == 0)
            t0 = _time.perf_counter()
            direct = self.shade(frame, gb, surface, stats, progress)
            stats.shading_seconds += _time.perf_counter() - t0
            yield gb, surface, direct

    def shade(self, frame: FrameInputs, gb: GBuffer, surface: Surface, stats: FrameStats,
              progress: Progress) -> DirectResult:
        s = surface

        def shade(_, backends: Backends, fr: FrameInputs, sel, share: Progress) -> DirectResult:
            return shade_surface(backends.shadow, fr, s.position[sel], s.normal[sel], s.albedo[sel], s.geometric[sel],
                                 None if s.material is None else s.material[sel], self.settings.seed, share,
                                 self.settings.light_samples)
        return self.by_class(frame, s.prim_id, s.instance_id, progress, shade)


class EveryLightFused(EveryLight):
    """``--direct all`` over a ``LIGHT_MAJOR`` backend, every pass shaded by one call (module doc)."""

    def passes(self, frame: FrameInputs, passes: list[PixelPass], stats: FrameStats,
               progress: Progress) -> Iterator[tuple[GBuffer, Surface, DirectResult]]:
        gbs = [_gbuffer(frame, self.backends, rays, stats, self.settings.visible_lights) for rays in passes]
        surfaces = [Surface.of(gb) for gb in gbs]
        self._before_shading(frame, surfaces[0], stats, True)
        t0 = _time.perf_counter()

        def stacked(name: str) -> np.ndarray:
            return np.concatenate([getattr(s, name) for s in surfaces])
        material = None
        if any(s.material is not None for s in surfaces):
            material = np.concatenate([s.material if s.material is not None else lambert_rows(len(s.position))
                                       for s in surfaces])
        points, normals, albedo, geometric = (stacked(name) for name in ("position", "normal", "albedo", "geometric"))

        def shade(_, backends: Backends, fr: FrameInputs, sel, share: Progress) -> DirectResult:
            return shade_surface(backends.shadow, fr, points[sel], normals[sel], albedo[sel], geometric[sel],
                                 None if material is None else material[sel], self.settings.seed, share,
                                 self.settings.light_samples)
        direct = self.by_class(frame, stacked("prim_id"), stacked("instance_id"), progress, shade)
        stats.shading_seconds += _time.perf_counter() - t0
        lo = 0
        for i, (gb, surface) in enumerate(zip(gbs, surfaces)):
            hi = lo + len(surface.position)
            yield gb, surface, DirectResult(direct.radiance[lo:hi], direct.shadow[lo:hi], direct.facing[lo:hi],
                                            direct.queries if i == 0 else 0,
                                            None if direct.specular is None else direct.specular[lo:hi],
                                            variance=None if direct.variance is None else direct.variance[lo:hi],
                                            groups=None if direct.groups is None else
                                            {k: v[lo:hi] for k, v in direct.groups.items()})
            lo = hi


class LghDirect(EveryLight):
    """``--direct lgh``: a hierarchy over the frame's lights, gathered in every pass (module doc); with linking or
    light groups, a hierarchy per shading unit's lights (:func:`usdml.render.light_classes.shading_units`), made
    the first time the frame shades that unit."""

    def __init__(self, backends: Backends, settings: UsdmlSettings, device: str, where: str):
        super().__init__(backends, settings, device, where)
        self.fields: dict = {}                  # class indices of a unit (None: every light) -> its hierarchy
        self.estimate = None                    # the frame's error estimate (usdml.render.lighting_estimate)
        self._measured = None                   # the unit the estimate measures: the frame's first pass's largest
        self._part = None                       # (points, radiance) of that unit in the pass being shaded
        self._frame = None
        self._told_no_grid = False

    @property
    def field(self):
        """The hierarchy over every light of the frame (a plain frame's only one), or None."""
        return self.fields.get(None)

    def prepare(self, frame: FrameInputs, stats: FrameStats) -> None:
        super().prepare(frame, stats)
        self.fields, self.estimate, self._measured, self._frame = {}, None, None, frame
        stats.direct_lgh = {}
        if self.single():
            self._field(None, frame, frame.lights, stats)
            self._measure(None, self.backends.shadow, frame.lights, stats)

    def _field(self, ks, frame: FrameInputs, lights: Lights, stats: FrameStats):
        from usdml.lighting.lgh.direct import prepare_direct

        if ks not in self.fields:
            field = self.fields[ks] = prepare_direct(lights, self.settings.lgh_levels, device=self.device,
                                                     seed=self.settings.seed, meters_per_unit=frame.snap.meters_per_unit,
                                                     light_samples=self.settings.light_samples)
            for k, v in field.stats.items():
                stats.direct_lgh[k] = stats.direct_lgh.get(k, 0) + v if isinstance(v, (int, float)) else v
            if field.lgh is None and len(field.rest) and not self._told_no_grid:
                log.warning(f"{self.where}: --direct lgh: none of its {len(field.rest)} light(s) at time "
                            f"{frame.snap.time:g} can go in the hierarchy (distant, dome or cylinder lights, shaping "
                            "cones or focus, shadows off, black or negative): all are shaded every-light, as --direct all")
                self._told_no_grid = True
        return self.fields[ks]

    def _measure(self, ks, shadow, lights: Lights, stats: FrameStats) -> None:
        """The frame's estimate measures unit ``ks`` (its hierarchy against every light of it)."""
        from usdml.render.lighting_estimate import direct_estimator

        self._measured = ks
        self.estimate = direct_estimator(self.fields[ks], replace(self._frame, lights=lights), shadow, self.settings)

    def passes(self, frame: FrameInputs, passes: list[PixelPass], stats: FrameStats,
               progress: Progress) -> Iterator[tuple[GBuffer, Surface, DirectResult]]:
        for gb, surface, direct in super().passes(frame, passes, stats, progress):
            if self.estimate is not None:       # after the frame's last pass, its estimate
                measured, radiance = surface, direct.radiance
                if self._part is not None:      # a linked frame: the measured unit on the points it reaches
                    sel, radiance = self._part
                    measured = surface.restricted(sel)
                stats.estimate_direct = (self.estimate.add_surface(measured, radiance, measured.material)
                                         or stats.estimate_direct)
            yield gb, surface, direct

    def shade(self, frame: FrameInputs, gb: GBuffer, surface: Surface, stats: FrameStats,
              progress: Progress) -> DirectResult:
        from usdml.lighting.lgh.direct import shade_lgh_direct

        mpu, sf = frame.snap.meters_per_unit, surface
        self._part = None
        if self._measured is None and not self.single() and len(sf.position):
            units = shading_units(self.classes, lambda link: self._members(frame, sf.prim_id, sf.instance_id, link))
            ks, _ = max(units, key=lambda u: sum(len(self.classes[k].index) for k in u[0]) * int(u[1].sum()))
            index = np.concatenate([self.classes[k].index for k in ks])
            lights = frame.lights.subset(index)
            self._field(ks, frame, lights, stats)
            backends = self.backends if self.linked is None else \
                self.linked.backends(self.classes[ks[0]].shadow_link, self.backends)
            self._measure(ks, backends.shadow, lights, stats)

        seed, samples = self.settings.seed, self.settings.light_samples

        def shade(ks, backends: Backends, fr: FrameInputs, sel, share: Progress) -> DirectResult:
            shadow = backends.shadow
            field = self._field(ks, fr, fr.lights, stats)

            def shade_rest(p, n, a, rest, geometric=None, material=None):
                if material is None:
                    return shade_with(shadow, p, n, a, rest, None, meters_per_unit=mpu, geometric=geometric,
                                      light_samples=samples, seed=seed)
                # the every-light rest as --direct all shades it with material rows (a dome's specular sampled)
                return shade_surface(shadow, replace(fr, lights=rest), p, n, a, geometric, material, seed, None,
                                     samples)

            hit = gb.hit
            if ks is not None:      # the unit's points laid out in the image
                hit = np.zeros(gb.hit.size, bool)
                hit[np.flatnonzero(gb.hit.ravel())[sel]] = True
                hit = hit.reshape(gb.hit.shape)
            direct, s = shade_lgh_direct(sf.position[sel], sf.normal[sel], sf.albedo[sel], field, shadow.occluded,
                                         shade_rest, self.settings, meters_per_unit=mpu, image=(hit, gb.position),
                                         geometric=sf.geometric[sel], device=self.device,
                                         material=None if sf.material is None else sf.material[sel])
            for key, v in s.items():
                stats.direct_lgh[key] = stats.direct_lgh.get(key, 0) + v if isinstance(v, (int, float)) else v
            if ks is not None and ks == self._measured:
                self._part = (sel, direct.radiance)
            return direct

        direct = self.by_class(frame, sf.prim_id, sf.instance_id, None, shade)
        if progress is not None:
            progress(int(surface.hit.sum()))
        return direct


def direct_integrator(backends: Backends, settings: UsdmlSettings, device: str, where: str) -> EveryLight:
    """The frame's direct light for ``settings`` (module doc); ``where`` starts its warnings (the stage)."""
    if settings.direct == "lgh":
        return LghDirect(backends, settings, device, where)
    if settings.pixel_samples > 1 and backends.shadow.supports(LIGHT_MAJOR):
        return EveryLightFused(backends, settings, device, where)
    return EveryLight(backends, settings, device, where)


class NoGI:
    """``--gi none``: no indirect light."""

    def prepare(self, frame: FrameInputs, stats: FrameStats) -> None:
        """Once per frame, before its passes."""

    def gather(self, frame: FrameInputs, gb: GBuffer, surface: Surface, stats: FrameStats) -> np.ndarray:
        """``(P, 3)`` float32 indirect radiance at the pass's surface."""
        return np.zeros((len(surface.position), 3), np.float32)


class VplGI(NoGI):
    """``--gi lgh | svo | vpl-bruteforce``: the frame's VPLs made once, gathered in every pass (module doc)."""

    def __init__(self, backends: Backends, settings: UsdmlSettings, device: str, where: str):
        from usdml.lighting.gi import indirect_gather

        self.backends, self.settings, self.device, self.where = backends, settings, device, where
        self.indirect = indirect_gather(settings.gi)
        # --gi svo casts its rays with a backend of its own; the others with the shadow backend
        self.rays = backends.gi or backends.shadow
        self.field = None
        self.estimate = None                    # --gi lgh: the frame's error estimate (usdml.render.lighting_estimate)
        self.target_lift = 0.0
        self._told_no_vpls = False
        self._told_negative = False
        self._told_glossy = False

    def prepare(self, frame: FrameInputs, stats: FrameStats) -> None:
        from usdml.lighting.gi import prepare_vpls
        from usdml.lighting.interleaved import target_lift
        from usdml.render.lighting_estimate import gi_estimator

        self.field = prepare_vpls(frame.snap, self.backends.primary, frame.lights, self.settings, device=self.device)
        self.estimate = gi_estimator(self.field, frame, self.rays.occluded, self.settings)
        stats.gi_seconds = self.field.stats["vpl_seconds"] + self.field.stats.get("lgh_seconds", 0.0)
        self.target_lift = target_lift(self.backends.gi) if self.backends.gi is not None else 0.0
        negative = int(frame.lights.negative().sum())
        if negative and not self._told_negative:
            log.warning(f"{self.where}: --gi {self.settings.gi}: {negative} light(s) of negative intensity at time "
                        f"{frame.snap.time:g} emit no VPLs: they take away direct light only, not indirect")
            self._told_negative = True

    def gather(self, frame: FrameInputs, gb: GBuffer, surface: Surface, stats: FrameStats) -> np.ndarray:
        t0 = _time.perf_counter()
        albedo = surface.albedo
        if surface.material is not None:
            from usdml.lighting.specular_albedo import indirect_albedo

            albedo = indirect_albedo(albedo, surface.material, surface.normal)
            if not self._told_glossy:
                log.warning(f"{self.where}: --gi {self.settings.gi}: glossy surfaces bounce indirect light with the "
                            "energy their lobes reflect but spread as diffuse light: no reflections of the scene in "
                            "indirect light (docs/materials.md)")
                self._told_glossy = True
        gi = self.indirect(self.field, frame.snap, self.rays.occluded, surface.position, surface.normal,
                           albedo, self.settings, image=(gb.hit, gb.position), device=self.device,
                           geometric=surface.geometric, target_lift=self.target_lift)
        stats.gi = gi.stats                     # the last pass's
        if gi.stats.get("vpls") == 0 and not self._told_no_vpls:
            n = len(frame.lights)
            why = ("the stage has no lights (a camera light adds no indirect light)" if n == 0
                   else f"its {n} light(s) have negative intensity" if frame.lights.negative().all()
                   else f"no light path from its {n} light(s) reached the geometry")
            log.warning(f"{self.where}: --gi {self.settings.gi}: no VPLs at time {frame.snap.time:g}: {why}; "
                        "indirect is 0")
            self._told_no_vpls = True
        stats.gi_seconds += _time.perf_counter() - t0
        if self.estimate is not None:           # after the frame's last pass, its estimate
            stats.estimate_gi = self.estimate.add_surface(surface, gi.radiance) or stats.estimate_gi
        return gi.radiance


def gi_integrator(backends: Backends, settings: UsdmlSettings, device: str, where: str) -> NoGI:
    """The frame's indirect light for ``settings`` (module doc); ``where`` starts its warnings (the stage)."""
    return NoGI() if settings.gi == "none" else VplGI(backends, settings, device, where)
