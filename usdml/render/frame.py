"""Render one timecode: snapshot → backend update → G-buffer → direct lighting → AOV buffers.

Passes never reach back into USD: a frame reads its snapshot and the backends' state only. The
renderer's visibility backends are held by role in one :class:`usdml.render.backends.Backends`
(primary rays: exact, Embree; shadow rays: the configured backend, the same object when it is
``exact``; ``--gi svo``'s rays: a backend of its own, :func:`usdml.lighting.interleaved.gi_visibility_backend`),
each made, updated per frame and closed once. The direct and indirect integrators are chosen once per
renderer (:mod:`usdml.render.integrators`); a frame's numbers are a :class:`FrameStats`.
"""

from __future__ import annotations

import itertools
import time as _time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from usdml.aov.cryptomatte import RankFilter, is_cryptomatte
from usdml.aov.names import find_aov, is_light_group, light_group
from usdml.errors import UsdmlError, log
from usdml.kernels.brdf import brdf_terms
from usdml.lighting.area.shading import AreaEstimate, noise_estimate
from usdml.lighting.dome import dome_to_distant_lights
from usdml.render.backends import QUERY_ROLES, Backends
from usdml.render.denoise.oidn import GUIDES, denoise_frame, wanted
from usdml.render.estimate import estimate_visibility, frame_rng
from usdml.render.frame_stats import FrameStats
from usdml.render.gbuffer import GBuffer, PixelPass, build_gbuffer
from usdml.render.lens import lens_points
from usdml.render.sampling import pixel_offsets
from usdml.render.shutter import pass_times
from usdml.render.integrators import FrameInputs, Surface, direct_integrator, gi_integrator
from usdml.render.light_classes import LinkedShadows
from usdml.render.mattes import FrameMattes, MatteIds
from usdml.scene import Camera, Changes, Lights, Snapshot, diff
from usdml.settings import UsdmlSettings
from usdml.stage.delegate import StageDelegate, require_geometry

#: AOVs written when neither --aovs nor RenderSettings choose
DEFAULT_AOVS = ("color", "direct", "indirect", "shadow", "depth", "normal", "P", "albedo", "primId", "instanceId")


def camera_light(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, camera: Camera,
                 material: np.ndarray | None = None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """usdrecord's default camera light: a light at the eye without falloff, unit diffuse intensity.

    Storm's simple lighting gives ``albedo · max(0, n·l)``; as radiance that is ``albedo/π · E`` with
    ``E = π · max(0, n·l)``. It never casts a visible shadow (it sits at the eye). Returns (P, 3) float32; with
    ``material`` rows (``kernels/brdf``) the preview surface's BRDF toward the eye, ``E·(ρ/π·kd + ks)``, and
    ``(radiance, specular E·ks)``.
    """
    eye = camera.xform[:3, 3]
    if camera.projection == "orthographic":
        to_eye = np.broadcast_to(camera.xform[:3, 2], points.shape)
    else:
        to_eye = eye - points
    to_eye = to_eye / np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-30)
    cos = np.maximum(np.einsum("ij,ij->i", normals.astype(np.float64), to_eye), 0.0)
    if material is None:
        return (albedo * cos[:, None]).astype(np.float32)
    kd, ks = brdf_terms(material, normals, to_eye)
    e = (np.pi * cos)[:, None]
    specular = (e * ks).astype(np.float32)
    return (albedo / np.pi * e * kd + specular).astype(np.float32), specular


def conform_camera(camera: Camera, width: int, height: int) -> Camera:
    """Expand the film back to the image aspect (UsdRender's default ``expandAperture`` policy)."""
    aspect = width / height
    if abs(camera.aspect - aspect) < 1e-9:
        return camera
    if aspect > camera.aspect:
        return replace(camera, horizontal_aperture=camera.vertical_aperture * aspect)
    return replace(camera, vertical_aperture=camera.horizontal_aperture / aspect)


def centre_gbuffer(snap: Snapshot, primary, width: int, height: int) -> tuple[Snapshot, GBuffer]:
    """One frame's G-buffer as ``usdml compare`` and ``usdml bench`` ask their queries on it: one primary ray
    through each pixel centre of ``width`` × ``height``, traced by ``primary`` (the exact backend, updated to
    ``snap``). Returns ``(snap with its camera conformed to the image, as a render's, the G-buffer)``."""
    snap = replace(snap, camera=conform_camera(snap.camera, width, height))
    return snap, build_gbuffer(snap, primary, width, height)


def blank_frame(hit: bool, lit: bool, albedo: bool, lights: int, camera: Camera, seen: bool = False) -> str | None:
    """What a frame whose ``color`` is the same everywhere (or shows no geometry) says, and the cause to check:
    empty (no primary ray hit anything: alpha 0 everywhere; ``seen``: some ray saw a visible light or the dome, so
    the frame shows lights only) or black (``lit``: some pixel has light, on a hit or seen; ``albedo``: some hit has
    a non-zero albedo; ``lights``: the frame's lights, the camera light aside); None when some pixel has colour."""
    camera_check = (f"check the camera ({camera.path or 'the framing camera'}: where it looks, its clipping range) "
                    "and the geometry's visibility, purpose and activation")
    if not hit and seen:
        return f"shows no geometry, only lights (the dome or area lights the camera sees); {camera_check}"
    if not hit:
        return f"is empty (alpha 0 everywhere): no geometry in the camera's view; {camera_check}"
    if lit:
        return None
    if not albedo:
        return ("is black (color 0 everywhere): every surface in view has a black albedo; check the materials (a "
                "diffuseColor of 0, a texture that does not load and whose inputs:fallback is the spec's black)")
    if lights == 0:
        return ("is black (color 0 everywhere): the stage has no lights here and --disableCameraLight turned "
                "usdrecord's light at the eye off; add a UsdLux light")
    return ("is black (color 0 everywhere): no light reaches what the camera sees; check the lights (intensity, "
            "exposure, where they point, what shadows them) and whether the camera is inside closed geometry")


@dataclass
class FrameResult:
    time: float
    buffers: dict[str, np.ndarray]      #: AOV name -> (H, W[, C]) array, row 0 at the top
    camera: Camera                      #: the conformed camera the frame was rendered with
    snapshot: Snapshot
    stats: FrameStats = field(default_factory=FrameStats)
    #: Cryptomatte AOV -> {name: id} of the names its written ranks hold (:func:`usdml.aov.cryptomatte.header`)
    manifests: dict[str, dict[str, int]] = field(default_factory=dict)


class FrameRenderer:
    """Renders timecodes of one stage in order, updating the backends with what changed.

    ``backends`` (:class:`usdml.render.backends.Backends`) holds the visibility backends by role; the direct
    and indirect integrators (:mod:`usdml.render.integrators`) are chosen here, once, from ``settings``.
    """

    def __init__(self, delegate: StageDelegate, settings: UsdmlSettings, device: str = "cpu",
                 camera_light: bool = True, backend_options: dict | None = None, gi_visibility: str | None = None):
        self.delegate = delegate
        self.camera_light = camera_light
        self.settings = settings
        self.device = device
        self.backends = Backends(settings, device, backend_options, gi_visibility)
        self.direct = direct_integrator(self.backends, settings, device, delegate.path)
        self.indirect = gi_integrator(self.backends, settings, device, delegate.path)
        if self.backends.refined is not None:
            self.direct.before_shading = self._choose_refinement
        self.direct.linked = LinkedShadows(lambda: Backends(settings, device, backend_options, roles=QUERY_ROLES,
                                                            unrefinable="ignore"))
        self._previous: Snapshot | None = None
        self.changes: Changes | None = None     #: what the last :meth:`advance` found changed
        self._told_camera_light = False
        self._matte_ids = MatteIds(delegate.warn)

    def frame_lights(self, snap: Snapshot) -> Lights:
        """The snapshot's lights plus each dome light importance-sampled into distant lights.

        The dome's samples use the same seed every frame, so a static dome does not flicker.
        """
        if not snap.domes:
            return snap.lights
        domes = [dome_to_distant_lights(d, self.settings.dome_samples, self.settings.seed, snap.meters_per_unit)
                 for d in snap.domes]
        lights = Lights.concat([snap.lights] + domes)
        return lights if snap.links is None else snap.links.label(lights)

    def close(self) -> None:
        self.backends.close()
        self.direct.linked.close()

    def estimates(self, lights: Lights) -> bool:
        """Whether a frame estimates its visibility error (:mod:`usdml.render.estimate`): approximate shadow
        rays answered pair by pair (``--direct all``; ``--direct lgh`` samples its lights), and lights; under
        ``--error-budget`` the estimate is the budget's (:meth:`_choose_refinement`)."""
        return (self.backends.shadow is not self.backends.primary and self.settings.direct == "all"
                and len(lights) > 0 and self.backends.refined is None)

    def _choose_refinement(self, frame: FrameInputs, surface: Surface, stats: FrameStats) -> None:
        """``--error-budget``: the frame's refinement level and estimate (:mod:`usdml.render.budget`), before its
        first pass is shaded."""
        from usdml.render.budget import choose_level

        if self.settings.direct != "all":
            return
        stats.estimate = choose_level(self.backends.refined, surface.position, surface.normal, surface.geometric,
                                      frame.lights, self.settings.error_budget, self.settings.seed, frame.snap.time,
                                      self.delegate.path)
        self.direct.linked.refine_like(self.backends.refined)

    def render(self, time: float, width: int, height: int, aovs: set[str],
               progress: Callable[[int], None] | None = None, snapshot: Snapshot | None = None) -> FrameResult:
        """Render ``aovs`` of timecode ``time`` at ``width`` × ``height``; ``progress(n)`` per shaded pixels.
        ``snapshot``: the stage at ``time`` as the caller has just read it (not read again).

        With motion blur (:func:`usdml.render.shutter.pass_times`) each pass is a time slice: the stage, the
        backends, the lights and the camera are brought to the pass's time before it is traced and shaded; the
        integrators are prepared again (VPLs, hierarchies) only when the geometry or the lights moved."""
        stats = FrameStats()
        t0 = _time.perf_counter()
        samples = self.settings.pixel_samples
        if snapshot is None or snapshot.time != time:
            snapshot = self.delegate.snapshot(time)
            stats.snapshot_seconds += _time.perf_counter() - t0
        times = pass_times(snapshot, self.settings, samples)
        if times is None:
            snap, lights, camera = self.advance(time, width, height, stats, snapshot)
        else:       # the frame's own camera for its metadata; the slices are advanced to below
            snap, camera = snapshot, conform_camera(snapshot.camera, width, height)
            snap = replace(snap, camera=camera)
            stats.shutter_times = times
        pixel_progress = None if progress is None else (lambda n: progress(n / samples))
        self.direct.groups = any(is_light_group(a) for a in aovs)
        crypto = {a for a in aovs if is_cryptomatte(a)}
        mattes = None           # the Cryptomatte ids of the primary backend's geometry, made again when it moves
        image = _PixelFilter(width, height)
        flags = _Seen()
        # --denoise: the AOVs it denoises, and the guides it needs rendered with them (docs/denoising.md)
        denoised = wanted(self.settings.denoise_aovs, sorted(aovs)) if self.settings.denoise else []
        rendered = set(aovs) | set(GUIDES) if denoised else set(aovs)
        lens = camera.lens_radius > 0 and self.settings.depth_of_field and not (
            snap.render_settings is not None and snap.render_settings.disable_depth_of_field)
        if lens:
            stats.lens_radius = camera.lens_radius
        passes = [PixelPass(offsets, points) for offsets, points in zip(
            pixel_offsets(width, height, samples, self.settings.seed, shifted=times is not None),
            lens_points(width, height, samples, self.settings.seed) if lens else itertools.repeat(None))]
        sampled = []            # (variance, direct radiance) of each pass whose lights with area were sampled
        # slices in time order, so the backends move forward through the shutter
        prepared = None         # the lights the integrators were last prepared for (motion blur: per slice)
        slices = [(time, passes)] if times is None else [(t, [passes[k]]) for t, k in sorted(zip(times, range(samples)))]
        for first, (t, group) in enumerate(slices):
            if times is not None:
                slice_snap, lights, slice_camera = self.advance(t, width, height, stats)
            else:
                slice_snap, slice_camera = snap, camera
            frame = FrameInputs(slice_snap, lights, width, height)
            state = None if times is None else lights.state_hash()
            if first == 0 or self.changes.geometry or state != prepared:
                self.indirect.prepare(frame, stats)     # once for every pass of the slice, while anything moves
                self.direct.prepare(frame, stats)
                prepared = state
            if crypto and (mattes is None or self.changes.geometry):
                mattes = self._mattes(slice_snap, crypto)
            for i, (rays, (gb, surface, direct)) in enumerate(
                    zip(group, self.direct.passes(frame, group, stats, pixel_progress))):
                if i == 0 and first == 0 and self.estimates(lights):
                    stats.estimate = estimate_visibility(
                        surface.position, surface.normal, surface.geometric, lights, self.backends.primary,
                        self.backends.shadow, frame_rng(self.settings.seed, time),
                        frame_pairs=len(surface.position) * len(lights) * samples)
                if self.camera_light and len(lights) == 0:
                    t1 = _time.perf_counter()
                    self._light_by_camera(direct, surface, slice_camera, slice_snap.time, stats)
                    stats.shading_seconds += _time.perf_counter() - t1
                indirect = self.indirect.gather(frame, gb, surface, stats)
                if pixel_progress is not None:
                    pixel_progress(int((~surface.hit).sum()))          # background pixels: nothing to shade
                stats.shadow_queries += direct.queries
                if direct.variance is not None:
                    sampled.append((direct.variance, direct.radiance))
                flags.add(gb, surface, direct, indirect)
                buffers = self._buffers(gb, surface, direct, indirect, slice_camera, rendered - crypto)
                buffers.update({a: mattes.pass_ids(gb.geom, gb.triangle, a) for a in crypto})
                image.add(buffers, rays.offsets)
        if sampled:
            variance, radiance = (np.concatenate(a) for a in zip(*sampled))
            stats.estimate_area = AreaEstimate(noise_estimate(variance, radiance, samples),
                                               int(self.settings.light_samples))
        if self.backends.refined is not None and stats.estimate is not None:
            stats.estimate = replace(stats.estimate, **self.backends.refined.fractions())
        blank = blank_frame(flags.hit, flags.lit, flags.albedo, len(lights), camera, flags.seen)
        if blank:
            log.warning(f"{self.delegate.path}: frame {time:g} {blank}")
        buffers = image.result()
        if denoised:
            stats.denoise = denoise_frame(buffers, denoised, self.settings.denoise_prefilter)
        stats.lights = len(lights)
        stats.pixels = width * height
        stats.pixel_samples = samples
        stats.seconds = _time.perf_counter() - t0
        return FrameResult(time=time, buffers=buffers, camera=camera, snapshot=snap, stats=stats,
                           manifests={a: mattes.manifest(a, image.present[a]) for a in crypto})

    def _mattes(self, snap: Snapshot, crypto: set[str]) -> FrameMattes:
        """The frame's Cryptomatte ids of the primary backend's geometry (:mod:`usdml.render.mattes`)."""
        names = self.delegate.mattes(snap)
        if "CryptoAsset" in crypto and not names.assets:
            self.delegate.warn(f"{self.delegate.path}: no geometry is in a prim of kind component (or a kind derived "
                               "from it); CryptoAsset has no ids (author kind = \"component\" on each asset's root)")
        if "CryptoMaterial" in crypto and not names.materials:
            self.delegate.warn(f"{self.delegate.path}: no geometry has a material bound; CryptoMaterial has no ids")
        return FrameMattes(names, self.backends.primary.sources, self._matte_ids)

    def advance(self, time: float, width: int, height: int, stats: FrameStats | None = None,
                snapshot: Snapshot | None = None) -> tuple[Snapshot, Lights, Camera]:
        """Move to timecode ``time``: its snapshot (``snapshot`` where the caller read it at ``time``), the
        backends updated with what changed since the last frame, ``(snapshot with the camera conformed to
        width × height, the frame's lights, that camera)``; seconds of each step into ``stats``."""
        stats = FrameStats() if stats is None else stats
        t0 = _time.perf_counter()
        snap = snapshot if snapshot is not None and snapshot.time == time else self.delegate.snapshot(time)
        require_geometry(self.delegate, snap)
        stats.snapshot_seconds += _time.perf_counter() - t0
        self.changes = diff(self._previous, snap)
        seconds = self.backends.update(snap, self.changes)
        stats.update_seconds += seconds["primary"] + seconds.get("shadow", 0.0)
        if "gi" in seconds:
            stats.gi_update_seconds = (stats.gi_update_seconds or 0.0) + seconds["gi"]
        self._previous = snap
        camera = conform_camera(snap.camera, width, height)
        lights = self.frame_lights(snap)
        if len(lights) and (lights.shadow_link >= 0).any():
            stats.update_seconds += self.direct.linked.update(snap, lights)
        return replace(snap, camera=camera), lights, camera

    def _light_by_camera(self, direct, surface: Surface, camera: Camera, time: float, stats: FrameStats) -> None:
        """usdrecord's camera light in place of ``direct``'s radiance (the frame has no lights)."""
        if surface.material is None:
            direct.radiance[:] = camera_light(surface.position, surface.normal, surface.albedo, camera)
        else:
            direct.radiance[:], direct.specular = camera_light(surface.position, surface.normal, surface.albedo,
                                                               camera, surface.material)
        stats.camera_light = True
        if not self._told_camera_light:
            log.warning(f"{self.delegate.path}: no lights at time {time:g}; lit by a camera light as "
                        "usdrecord does (--disableCameraLight to turn it off)")
            self._told_camera_light = True

    @staticmethod
    def _buffers(gb: GBuffer, surface: Surface, direct, indirect: np.ndarray, camera: Camera,
                 aovs: set[str]) -> dict[str, np.ndarray]:
        h, w = gb.height, gb.width
        hit = surface.hit

        def scatter(values: np.ndarray, channels: int) -> np.ndarray:
            out = np.zeros((h * w, channels) if channels > 1 else (h * w,), np.float32)
            out[hit] = values
            return out.reshape((h, w, channels) if channels > 1 else (h, w))

        radiance = scatter(direct.radiance, 3)
        indirect_img = scatter(indirect, 3)
        beauty = radiance + indirect_img
        # what the ray ends on emits: a surface's emissiveColor, or a visible light (gb.light: no surface there)
        emission = gb.emission if gb.light is None else gb.light if gb.emission is None else gb.emission + gb.light
        for seen in (emission, gb.background):
            if seen is not None:
                beauty = beauty + seen

        def zeros() -> np.ndarray:
            return np.zeros((h, w, 3), np.float32)

        def specular() -> np.ndarray:
            return scatter(direct.specular, 3) if direct.specular is not None else zeros()
        alpha = gb.hit.astype(np.float32)
        opaque = alpha if gb.emitter is None else (gb.hit | gb.emitter).astype(np.float32)
        world_to_eye = np.linalg.inv(camera.xform)
        table = {
            "color": lambda: np.concatenate([beauty * opaque[..., None], opaque[..., None]], axis=2),
            "color_noisy": lambda: table["color"](),        # --denoise replaces color, not this
            "direct": lambda: radiance,
            "indirect": lambda: indirect_img,
            "diffuse": lambda: radiance - specular(),
            "specular": specular,
            "emission": lambda: emission if emission is not None else zeros(),
            "background": lambda: gb.background if gb.background is not None else zeros(),
            "shadow": lambda: scatter(direct.shadow, 1),
            "lightCount": lambda: scatter(direct.facing.astype(np.float32), 1),
            "depth": lambda: gb.depth,
            "normal": lambda: gb.normal,
            "denoiseNormal": lambda: gb.normal,             # the same, box-filtered (AovSpec.filtered)
            "Neye": lambda: (gb.normal.reshape(-1, 3) @ world_to_eye[:3, :3].T).reshape(h, w, 3) * alpha[..., None],
            "P": lambda: gb.position.astype(np.float32),
            "Peye": lambda: ((gb.position.reshape(-1, 3) @ world_to_eye[:3, :3].T + world_to_eye[:3, 3])
                             .reshape(h, w, 3) * alpha[..., None]).astype(np.float32),
            "albedo": lambda: gb.albedo,
            "primId": lambda: gb.prim_id,
            "instanceId": lambda: gb.instance_id,
        }
        for name in aovs:
            if is_light_group(name):
                part = (direct.groups or {}).get(light_group(name))
                table[name] = (lambda p=part: scatter(p, 3) if p is not None else np.zeros((h, w, 3), np.float32))
        unknown = sorted(set(aovs) - set(table))
        if unknown:
            raise UsdmlError(f"unknown AOV(s) {', '.join(unknown)}; usdml writes {', '.join(table)}")
        return {name: table[name]() for name in aovs}


class _Seen:
    """What any pass of a frame showed, for :func:`blank_frame`: a hit, light, a non-zero albedo, a light seen."""

    def __init__(self):
        self.hit = self.lit = self.albedo = self.seen = False

    def add(self, gb: GBuffer, surface: Surface, direct, indirect: np.ndarray) -> None:
        self.hit = self.hit or bool(surface.hit.any())
        self.lit = self.lit or bool(direct.radiance.any() or np.any(indirect) or any(
            e is not None and e.any() for e in (surface.emission, gb.light, gb.background)))
        self.seen = self.seen or gb.emitter is not None
        self.albedo = self.albedo or bool(surface.albedo.any())


class _PixelFilter:
    """Combines the AOV buffers of a pixel's primary rays (one pass per sub-pixel position): the
    :attr:`~usdml.aov.names.AovSpec.filtered` AOVs averaged (a box filter), the others taken from the
    ray nearest the pixel centre; the :attr:`~usdml.aov.names.AovSpec.ranked` (Cryptomatte) AOVs' ids ranked by
    coverage (:class:`usdml.aov.cryptomatte.RankFilter`)."""

    def __init__(self, width: int, height: int):
        self.shape = (height, width)
        self.passes = 0
        self.sums: dict[str, np.ndarray] = {}
        self.nearest: dict[str, np.ndarray] = {}
        self.best = np.full(self.shape, np.inf)
        self.ranks: dict[str, RankFilter] = {}
        self.present: dict[str, np.ndarray] = {}    #: ranked AOV -> the ids :meth:`result` wrote

    def add(self, buffers: dict[str, np.ndarray], offsets: np.ndarray) -> None:
        d2 = ((offsets - 0.5) ** 2).sum(1).reshape(self.shape)
        closer = d2 < self.best
        self.best = np.minimum(self.best, d2)
        for name, b in buffers.items():
            if find_aov(name).ranked:
                self.ranks.setdefault(name, RankFilter(b.size)).add(b)
            elif find_aov(name).filtered:
                self.sums[name] = self.sums.get(name, 0.0) + b.astype(np.float64)
            elif name not in self.nearest:
                self.nearest[name] = b
            else:
                pick = closer if b.ndim == 2 else closer[..., None]
                self.nearest[name] = np.where(pick, b, self.nearest[name])
        self.passes += 1

    def result(self) -> dict[str, np.ndarray]:
        out = {name: (s / self.passes).astype(np.float32) for name, s in self.sums.items()}
        out.update(self.nearest)
        for name, ranks in self.ranks.items():
            pixels, self.present[name] = ranks.result()
            out[name] = pixels.reshape(self.shape + (pixels.shape[1],))
        return out
