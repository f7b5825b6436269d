"""Render one timecode: snapshot → backend update → G-buffer → direct lighting → AOV buffers.

Passes never reach back into USD: a frame reads its snapshot and the backends' state only. Primary
rays always use the exact (Embree) backend; shadow rays use the configured visibility backend (the
same object when it is ``exact``). ``--gi svo`` casts its (pixel, VPL) rays with a backend of its own
(:func:`usdml.lighting.interleaved.gi_visibility_backend`, whatever ``--visibility`` is), built,
updated and closed with the others.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from usdml.aov.names import find_aov
from usdml.errors import UsdmlError, log
from usdml.render.gbuffer import GBuffer, build_gbuffer, pixel_offsets
from usdml.lighting.dome import dome_to_distant_lights
from usdml.scene import Camera, Lights, Snapshot, diff
from usdml.settings import UsdmlSettings
from usdml.stage.delegate import StageDelegate, require_geometry
from usdml.visibility import ExactBackend, make_backend
from usdml.visibility.base import LIGHT_MAJOR

#: AOVs written when neither --aovs nor RenderSettings choose
DEFAULT_AOVS = ("color", "direct", "indirect", "shadow", "depth", "normal", "P", "albedo", "primId", "instanceId")


def camera_light(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, camera: Camera) -> np.ndarray:
    """usdrecord's default camera light: a light at the eye without falloff, unit diffuse intensity.

    Storm's simple lighting gives ``albedo · max(0, n·l)``; as radiance that is ``albedo/π · E`` with
    ``E = π · max(0, n·l)``. It never casts a visible shadow (it sits at the eye). Returns (P, 3) float32.
    """
    eye = camera.xform[:3, 3]
    if camera.projection == "orthographic":
        to_eye = np.broadcast_to(camera.xform[:3, 2], points.shape)
    else:
        to_eye = eye - points
    to_eye = to_eye / np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-30)
    cos = np.maximum(np.einsum("ij,ij->i", normals.astype(np.float64), to_eye), 0.0)
    return (albedo * cos[:, None]).astype(np.float32)


def conform_camera(camera: Camera, width: int, height: int) -> Camera:
    """Expand the film back to the image aspect (UsdRender's default ``expandAperture`` policy)."""
    aspect = width / height
    if abs(camera.aspect - aspect) < 1e-9:
        return camera
    if aspect > camera.aspect:
        return replace(camera, horizontal_aperture=camera.vertical_aperture * aspect)
    return replace(camera, vertical_aperture=camera.horizontal_aperture / aspect)


@dataclass
class FrameResult:
    time: float
    buffers: dict[str, np.ndarray]      #: AOV name -> (H, W[, C]) array, row 0 at the top
    camera: Camera                      #: the conformed camera the frame was rendered with
    snapshot: Snapshot
    stats: dict = field(default_factory=dict)


class FrameRenderer:
    """Renders timecodes of one stage in order, updating the backends with what changed."""

    def __init__(self, delegate: StageDelegate, settings: UsdmlSettings, device: str = "cpu",
                 camera_light: bool = True, backend_options: dict | None = None, gi_visibility: str | None = None):
        self.delegate = delegate
        self.camera_light = camera_light
        self.settings = settings
        self.device = device
        self.exact = ExactBackend()
        self.backend = self.exact if settings.visibility == self.exact.name else \
            make_backend(settings.visibility, settings, device, **(backend_options or {}))
        self.gi_backend = None          # --gi svo's shadow rays; ``gi_visibility`` overrides its backend
        if settings.gi == "svo":
            from usdml.lighting.interleaved import GI_VISIBILITY, gi_visibility_backend

            name = gi_visibility or GI_VISIBILITY
            shared = [b for b in (self.backend, self.exact) if b.name == name]
            self.gi_backend = shared[0] if shared else gi_visibility_backend(settings, device, name)
        self._target_lift = 0.0
        self._previous: Snapshot | None = None
        self._told_camera_light = False
        self._told_no_vpls = False
        self._told_no_grid = False

    def frame_lights(self, snap: Snapshot) -> Lights:
        """The snapshot's lights plus each dome light importance-sampled into distant lights.

        The dome's samples use the same seed every frame, so a static dome does not flicker.
        """
        if not snap.domes:
            return snap.lights
        domes = [dome_to_distant_lights(d, self.settings.dome_samples, self.settings.seed, snap.meters_per_unit)
                 for d in snap.domes]
        return Lights.concat([snap.lights] + domes)

    def _own_gi_backend(self) -> bool:
        return self.gi_backend is not None and self.gi_backend is not self.exact and self.gi_backend is not self.backend

    def close(self) -> None:
        self.exact.close()
        if self.backend is not self.exact:
            self.backend.close()
        if self._own_gi_backend():
            self.gi_backend.close()

    def render(self, time: float, width: int, height: int, aovs: set[str],
               progress: Callable[[int], None] | None = None) -> FrameResult:
        """Render ``aovs`` of timecode ``time`` at ``width`` × ``height``; ``progress(n)`` per shaded pixels."""
        stats: dict = {}
        t0 = _time.perf_counter()
        snap, lights, camera = self.advance(time, width, height, stats)
        stats.update(gbuffer_seconds=0.0, shading_seconds=0.0, shadow_queries=0)
        samples = self.settings.pixel_samples
        pixel_progress = None if progress is None else (lambda n: progress(n / samples))
        vpl_field = None
        if self.settings.gi != "none":       # one set of VPLs for every pass of the frame
            from usdml.lighting.gi import prepare_vpls

            vpl_field = prepare_vpls(snap, self.exact, lights, self.settings, device=self.device)
            stats["gi_seconds"] = vpl_field.stats["vpl_seconds"] + vpl_field.stats.get("lgh_seconds", 0.0)
        direct_field = None
        if self.settings.direct == "lgh":    # one hierarchy over the stage's lights for every pass of the frame
            from usdml.lighting.lgh_direct import prepare_direct

            direct_field = prepare_direct(lights, self.settings.lgh_levels, device=self.device)
            stats["direct_lgh"] = dict(direct_field.stats)
            if direct_field.lgh is None and len(direct_field.rest) and not self._told_no_grid:
                log.warning(f"{self.delegate.path}: --direct lgh: none of its {len(direct_field.rest)} light(s) at time "
                            f"{snap.time:g} can go in the hierarchy (distant, dome or cylinder lights, shaping cones "
                            "or focus, shadows off, black): all are shaded every-light, as --direct all")
                self._told_no_grid = True
        image = _PixelFilter(width, height)
        passes = list(pixel_offsets(width, height, samples, self.settings.seed))
        shaded = [None] * len(passes)
        if len(passes) > 1 and self.backend.supports(LIGHT_MAJOR) and direct_field is None:
            shaded = self._shade_passes(snap, lights, camera, width, height, passes, stats, pixel_progress)
        for offsets, pre in zip(passes, shaded):
            gb, direct, indirect = self._trace(snap, lights, camera, width, height, offsets, stats, pixel_progress,
                                               vpl_field, pre, direct_field)
            image.add(self._buffers(gb, gb.hit.ravel(), direct, indirect, camera, aovs), offsets)
        stats["lights"] = len(lights)
        stats["pixels"] = width * height
        stats["pixel_samples"] = samples
        stats["seconds"] = _time.perf_counter() - t0
        return FrameResult(time=time, buffers=image.result(), camera=camera, snapshot=snap, stats=stats)

    def advance(self, time: float, width: int, height: int,
                stats: dict | None = None) -> tuple[Snapshot, Lights, Camera]:
        """Move to timecode ``time``: its snapshot, the backends updated with what changed since the last
        frame, ``(snapshot with the camera conformed to width × height, the frame's lights, that camera)``;
        seconds of each step into ``stats``."""
        stats = {} if stats is None else stats
        t0 = _time.perf_counter()
        snap = self.delegate.snapshot(time)
        require_geometry(self.delegate, snap)
        stats["snapshot_seconds"] = _time.perf_counter() - t0
        changes = diff(self._previous, snap)
        t1 = _time.perf_counter()
        self.exact.update(snap, changes)
        if self.backend is not self.exact:
            self.backend.update(snap, changes)
        stats["update_seconds"] = _time.perf_counter() - t1
        if self._own_gi_backend():
            t1 = _time.perf_counter()
            self.gi_backend.update(snap, changes)
            stats["gi_update_seconds"] = _time.perf_counter() - t1
        if self.gi_backend is not None:
            from usdml.lighting.interleaved import target_lift

            self._target_lift = target_lift(self.gi_backend)
        self._previous = snap
        camera = conform_camera(snap.camera, width, height)
        return replace(snap, camera=camera), self.frame_lights(snap), camera

    def _shade_passes(self, snap: Snapshot, lights: Lights, camera: Camera, width: int, height: int,
                      passes: list, stats: dict, progress: Callable[[float], None] | None) -> list:
        """``(G-buffer, direct light)`` of every pass, shaded by one call: a ``LIGHT_MAJOR`` backend builds
        its per-light structures (paper 001's maps) once per call, so once per frame, not once per pass."""
        from usdml.lighting.direct import DirectResult

        t2 = _time.perf_counter()
        gbs = [build_gbuffer(snap, self.exact, width, height, offsets) for offsets in passes]
        stats["gbuffer_seconds"] += _time.perf_counter() - t2
        t3 = _time.perf_counter()
        hits = [gb.hit.ravel() for gb in gbs]

        def stacked(field: str) -> np.ndarray:
            return np.concatenate([getattr(gb, field).reshape(-1, 3)[hit] for gb, hit in zip(gbs, hits)])
        direct = self.backend.shade_direct(stacked("position"), stacked("normal"), stacked("albedo"), lights, progress,
                                           meters_per_unit=snap.meters_per_unit, geometric=stacked("geometric"))
        stats["shading_seconds"] += _time.perf_counter() - t3
        out, lo = [], 0
        for i, (gb, hit) in enumerate(zip(gbs, hits)):
            hi = lo + int(hit.sum())
            out.append((gb, DirectResult(direct.radiance[lo:hi], direct.shadow[lo:hi], direct.facing[lo:hi],
                                         direct.queries if i == 0 else 0)))
            lo = hi
        return out

    def _trace(self, snap: Snapshot, lights: Lights, camera: Camera, width: int, height: int,
               offsets: np.ndarray, stats: dict, progress: Callable[[float], None] | None, vpl_field=None,
               shaded: tuple | None = None, direct_field=None):
        """One primary ray per pixel through ``offsets``: its G-buffer, direct and indirect light
        (gathered from ``vpl_field``, :func:`usdml.lighting.gi.prepare_vpls`); ``shaded``: the pass's
        G-buffer and direct light already made (:meth:`_shade_passes`); ``direct_field``: the frame's
        lights for ``--direct lgh`` (:func:`usdml.lighting.lgh_direct.prepare_direct`)."""
        t2 = _time.perf_counter()
        gb = build_gbuffer(snap, self.exact, width, height, offsets) if shaded is None else shaded[0]
        stats["gbuffer_seconds"] += _time.perf_counter() - t2
        t3 = _time.perf_counter()
        hit = gb.hit.ravel()
        # a SHADE_DIRECT backend shades in one kernel; the others through lighting.direct over their
        # shadow rays (VisibilityBackend.shade_direct)
        geometric = gb.geometric.reshape(-1, 3)[hit]
        if direct_field is not None:
            from usdml.lighting.lgh_direct import shade_lgh_direct

            def shade_rest(p, n, a, rest, geometric=None):
                return self.backend.shade_direct(p, n, a, rest, None, meters_per_unit=snap.meters_per_unit,
                                                 geometric=geometric)

            direct, s = shade_lgh_direct(gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit],
                                         gb.albedo.reshape(-1, 3)[hit], direct_field, self.backend.occluded,
                                         shade_rest, self.settings, meters_per_unit=snap.meters_per_unit,
                                         image=(gb.hit, gb.position), geometric=geometric, device=self.device)
            for k, v in s.items():
                stats["direct_lgh"][k] = stats["direct_lgh"].get(k, 0) + v if isinstance(v, (int, float)) else v
            if progress is not None:
                progress(int(hit.sum()))
        else:
            direct = shaded[1] if shaded is not None else \
                self.backend.shade_direct(gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit],
                                          gb.albedo.reshape(-1, 3)[hit], lights, progress,
                                          meters_per_unit=snap.meters_per_unit, geometric=geometric)
        if self.camera_light and len(lights) == 0:
            direct.radiance[:] = camera_light(gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit],
                                              gb.albedo.reshape(-1, 3)[hit], camera)
            stats["camera_light"] = True
            if not self._told_camera_light:
                log.warning(f"{self.delegate.path}: no lights at time {snap.time:g}; lit by a camera light as "
                            "usdrecord does (--disableCameraLight to turn it off)")
                self._told_camera_light = True
        stats["shading_seconds"] += _time.perf_counter() - t3
        indirect = np.zeros_like(direct.radiance)
        if vpl_field is not None:
            from usdml.lighting.gi import indirect_lighting

            t4 = _time.perf_counter()
            occluded = (self.gi_backend or self.backend).occluded
            gi = indirect_lighting(
                snap, self.exact, occluded, lights, gb.position.reshape(-1, 3)[hit],
                gb.normal.reshape(-1, 3)[hit], gb.albedo.reshape(-1, 3)[hit], self.settings,
                image=(gb.hit, gb.position), device=self.device, vpl_field=vpl_field, geometric=geometric,
                target_lift=self._target_lift)
            indirect = gi.radiance
            stats["gi"] = gi.stats                  # the last pass's
            if gi.stats.get("vpls") == 0 and not self._told_no_vpls:
                why = ("the stage has no lights (a camera light adds no indirect light)" if len(lights) == 0
                       else f"no light path from its {len(lights)} light(s) reached the geometry")
                log.warning(f"{self.delegate.path}: --gi {self.settings.gi}: no VPLs at time {snap.time:g}: {why}; "
                            "indirect is 0")
                self._told_no_vpls = True
            stats["gi_seconds"] = stats.get("gi_seconds", 0.0) + _time.perf_counter() - t4
        if progress is not None:
            progress(int((~hit).sum()))          # background pixels: nothing to shade
        stats["shadow_queries"] += direct.queries
        return gb, direct, indirect

    @staticmethod
    def _buffers(gb: GBuffer, hit: np.ndarray, direct, indirect: np.ndarray, camera: Camera,
                 aovs: set[str]) -> dict[str, np.ndarray]:
        h, w = gb.height, gb.width

        def scatter(values: np.ndarray, channels: int) -> np.ndarray:
            out = np.zeros((h * w, channels) if channels > 1 else (h * w,), np.float32)
            out[hit] = values
            return out.reshape((h, w, channels) if channels > 1 else (h, w))

        radiance = scatter(direct.radiance, 3)
        indirect_img = scatter(indirect, 3)
        beauty = radiance + indirect_img
        alpha = gb.hit.astype(np.float32)
        world_to_eye = np.linalg.inv(camera.xform)
        table = {
            "color": lambda: np.concatenate([beauty * alpha[..., None], alpha[..., None]], axis=2),
            "direct": lambda: radiance,
            "indirect": lambda: indirect_img,
            "shadow": lambda: scatter(direct.shadow, 1),
            "lightCount": lambda: scatter(direct.facing.astype(np.float32), 1),
            "depth": lambda: gb.depth,
            "normal": lambda: gb.normal,
            "Neye": lambda: (gb.normal.reshape(-1, 3) @ world_to_eye[:3, :3].T).reshape(h, w, 3) * alpha[..., None],
            "P": lambda: gb.position.astype(np.float32),
            "Peye": lambda: ((gb.position.reshape(-1, 3) @ world_to_eye[:3, :3].T + world_to_eye[:3, 3])
                             .reshape(h, w, 3) * alpha[..., None]).astype(np.float32),
            "albedo": lambda: gb.albedo,
            "primId": lambda: gb.prim_id,
            "instanceId": lambda: gb.instance_id,
        }
        unknown = sorted(set(aovs) - set(table))
        if unknown:
            raise UsdmlError(f"unknown AOV(s) {', '.join(unknown)}; usdml writes {', '.join(table)}")
        return {name: table[name]() for name in aovs}


class _PixelFilter:
    """Combines the AOV buffers of a pixel's primary rays (one pass per sub-pixel position): the
    :attr:`~usdml.aov.names.AovSpec.filtered` AOVs averaged (a box filter), the others taken from the
    ray nearest the pixel centre."""

    def __init__(self, width: int, height: int):
        self.shape = (height, width)
        self.passes = 0
        self.sums: dict[str, np.ndarray] = {}
        self.nearest: dict[str, np.ndarray] = {}
        self.best = np.full(self.shape, np.inf)

    def add(self, buffers: dict[str, np.ndarray], offsets: np.ndarray) -> None:
        d2 = ((offsets - 0.5) ** 2).sum(1).reshape(self.shape)
        closer = d2 < self.best
        self.best = np.minimum(self.best, d2)
        for name, b in buffers.items():
            if find_aov(name).filtered:
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
        return out
