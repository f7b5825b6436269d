"""The ``insm`` visibility backend: paper 001's intermediate shadow maps.

Per frame (Alg. 1; nothing is precomputed, so a moving or deforming scene costs what a static one
does): ``K`` depth images of the scene from viewpoints on its bounding box, each triangulated into a
world-space mesh without triangles across depth discontinuities (:mod:`usdml.visibility.insm.mesh`).
Per light, a shadow map is rasterized from those triangles alone (:mod:`usdml.kernels.insm.maps`) and the
shading points look their visibility up in it: the cost grows with the lights and the maps' sizes,
not with the scene's triangles. The depth images are rebuilt only on frames where geometry changed.

The box
    The viewpoints sit on the box of the scene's detail, the one the octree covers
    (:func:`usdml.visibility.svo.tree.svo_bounds`): a ground of a few huge triangles reaching far past
    the rest does not stretch it (the city: 1,400 m across with its ground, 348 m without), so the
    depth images' pixels land on geometry that casts shadows.

Maps per light (``S × S`` texels per view, ``S`` = ``light_resolution``)
    * point, sphere, disk, rect and cylinder lights (points at their centre, as every backend):
      a cube map, six 90° views;
    * spot lights (a shaping cone of at most ``SPOT_MAX_DEG``): one perspective view of the cone;
    * distant lights (and a dome's samples): one orthographic view over the scene's bounding sphere.

Leaving the surface (what a shadow map's depth bias is; paper 001 names none, so usdml's, measured)
    A shading point moves ``offset`` texels of the light's map (a texel's world size at its depth)
    along its geometric normal turned toward the light, then compares its depth, less ``bias`` texels,
    with the map's 2 × 2 nearest texels weighted bilinearly (percentage-closer filtering, blocked
    above one half). The cost: an occluder closer than about ``offset + bias`` texels to the point
    casts no shadow on it, and a reconstructed surface that bulges out of the real one by more (a
    concave region sampled coarsely) shadows itself.

Queries the maps cannot answer
    :meth:`shade_direct` answers every (pixel, light) pair of the frame's lights from the maps, one
    light at a time (a map lives while its light is answered: one per thread). :meth:`occluded`
    answers a segment from a map when its target is one of the frame's lights (a light of the
    snapshot, or of the last :meth:`shade_direct`: dome samples); any other target (a VPL, an LGH
    shadow sample) goes to the exact backend the insm backend holds (it also casts the depth images'
    rays), counted in ``stats["exact_queries"]``.

Refinement (``REFINE``: :meth:`InsmBackend.occluded_uncertain`)
    The maps are rasterized from triangles between depth-image samples, so an occluder's outline in a map
    is off by up to about the spacing ``h`` of the samples it was reconstructed from (a triangle's ``h``:
    ``sqrt(2 · area)``, the geometric mean of its two legs), and a thin gap or a thin part narrower than that
    may be missing. A lookup's answer is *uncertain* at level ``k`` when

    * a *silhouette* of the map, an occluder's outline, lies between its sides and within reach: a texel
      whose neighbour is farther by more than ``REFINE_JUMP`` texels of depth than the plane through the
      texel and the one behind it (so a plane at any slope has none; an empty neighbour counts where its
      tile had receivers, as at least that tile's farthest compared depth), with the texel in front of the
      lookup's compared depth and the neighbour not in front of it by more than ``REFINE_JUMP`` texels (the
      receiver's own surface beyond the outline: moved, the outline would change the answer), within
      ``c[k] · h · a / z`` texels of the lookup (``a`` the map's texels per unit of ``x / z``, ``z`` the
      silhouette's depth: ``c[k] · h`` world units across the ray at the occluder; ``h · a`` orthographic),
      plus ``REFINE_R0`` texels of the lookup's own footprint. A cube map's four faces beside the lookup's
      are searched too, the point projected into each (the seam);
    * or one of its 2 × 2 texels lies within ``band[k]`` texels of its compared depth (the bias band);
    * or it lies outside every view.

    ``c`` and ``band`` widen with the level (:data:`REFINE_C`, :data:`REFINE_BAND`: a higher level flags a
    superset). The compiled maps grade every answer in the pass that answers it, one map build for all
    levels: the triangles' ``h`` is kept per texel beside the depth as the map is rasterized, the
    silhouettes go into a max/min pyramid per view, and each lookup searches it (``kernels/insm/insmr.c``). The
    answers are the same as :meth:`InsmBackend.occluded`'s. Rows the exact backend answers are certain. The
    fused shading grades too (:meth:`InsmBackend.shade_refined`, what :class:`usdml.visibility.refine.Refined`
    calls): a map per light for every pixel, the pairs uncertain at the level handed back a light at a time.

    The Warp kernels (``--insm-cpu-kernel warp``, and CUDA) grade by a simpler rule: the same silhouettes
    and bias band, but no sample spacings and no pyramid: a silhouette counts within a fixed footprint of
    ``2 f[k] × 2 f[k]`` texels around the lookup (:data:`REFINE_FOOTPRINT`), and a footprint reaching past
    its view's side is uncertain (the seam; :func:`usdml.kernels.insm.maps.lookup_points`). Its reach does not
    grow with the occluder's nearness to the light or its triangles' size, so it holds fewer of the wrong
    answers at a level.

    Measured at 128 px against the exact backend, 64 of the stage's lights, every facing pair (ε_v per pixel
    over those lights), levels 1 - 5 of the compiled rule, tuned on the dragon and the city:

    ========  =========  ===========================  ==============================  ===================
    stage     wrong      flagged                      wrong answers flagged           ε_v left
    ========  =========  ===========================  ==============================  ===================
    dragon    4.0 %      9 / 14 / 19 / 26 / 35 %      74 / 86 / 93 / 97 / 99 %        3.80 % -> 1.01 /
                                                                                      0.55 / 0.27 / 0.11
                                                                                      / 0.03 %
    city      7.9 %      14 / 25 / 38 / 54 / 69 %     51 / 69 / 84 / 93 / 97 %        6.16 % -> 3.01 /
                                                                                      1.89 / 0.98 / 0.46
                                                                                      / 0.20 %
    creature  11.6 %     24 / 32 / 40 / 48 / 57 %     63 / 74 / 84 / 92 / 97 %        10.9 % -> 0.38 %
    park      31.3 %     41 / 57 / 68 / 76 / 82 %     58 / 76 / 87 / 93 / 96 %        30.0 % -> 1.30 %
    ========  =========  ===========================  ==============================  ===================

    (creature and park: not tuned on; ε_v at level 5.) Street lights among buildings reconstructed from
    metre-wide samples have most of their answers near an outline: the city's rule must flag about half
    its pairs to hold nine wrong answers in ten. The Warp path's rule holds 93 % of the dragon's wrong answers
    at level 4 (20 % flagged) but 67 % of the city's at level 5 (26 % flagged). Grading costs the compiled
    maps about 1.5 - 2 times a plain pass (the spacing beside each texel, the silhouettes and their pyramid,
    a search per lookup); ``tests/test_insm_refine.py`` holds the closed-form checks.
"""

from __future__ import annotations

import hashlib
import logging
import queue
import threading
import time
from dataclasses import dataclass, fields
from typing import Callable

import numpy as np

from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, iter_parallel, run_parallel
from usdml.scene import Changes, Lights, LightType, Snapshot, world_geometry
from usdml.visibility.base import (LIGHT_MAJOR, MEMORY_ESTIMATE, REFINE, SHADE_DIRECT, STATS, DirectResult,
                                   VisibilityBackend, all_members, as_flags, as_vectors, scene_sphere, settings_with)
from usdml.visibility.exact import ExactBackend
from usdml.visibility.insm.mesh import clusters, depth_images, insm_views, triangulate
from usdml.visibility.svo.tree import svo_bounds
from usdml.visibility.voxel.array import warp_module

log = logging.getLogger("usdml")

__all__ = ["InsmBackend", "LightViews", "light_views", "triangle_spacing", "refine_rule", "SPOT_MAX_DEG", "REFINE_C",
           "REFINE_BAND", "REFINE_FOOTPRINT"]

#: a spot light whose cone is at most this half-angle gets one map of its cone, wider ones a cube map
SPOT_MAX_DEG = 60.0
#: leaving the surface, in texels of the light's map (module doc)
OFFSET_TEXELS, BIAS_TEXELS = 1.0, 1.0
#: the near plane of a light's perspective views, as a fraction of the scene's diagonal
NEAR_FRACTION = 1e-5
#: most bytes of (light, point) answers held at once by :meth:`InsmBackend.shade_direct`
ANSWER_BYTES = 1 << 27
#: blocks of consecutive lights the compiled maps shade and sum apart, added in order (a fixed count, so the pixels
#: do not depend on the threads; 64 keeps 16 threads balanced at a few blocks each)
LIGHT_BLOCKS = 64
#: most bytes of maps one CUDA batch rasterizes at once
CUDA_MAP_BYTES = 1 << 29
PERSPECTIVE, ORTHOGRAPHIC = 0, 1
#: texels per side of a receiver tile (``usdml.kernels.insm.maps.TILE``)
TILE = 16
#: refinement (module doc, "Refinement"), per level 1 .. 5: the reach of an outline in its triangles' sample
#: spacings, the bias band in texels, and the Warp path's footprint half-width in texels
REFINE_C = (0.1, 0.2, 0.35, 0.6, 1.0)
REFINE_BAND = (0.25, 0.4, 0.5, 0.75, 1.0)
REFINE_FOOTPRINT = (1, 2, 3, 5, 8)
#: a silhouette: a neighbour farther than the plane's continuation by this many texels of depth
REFINE_JUMP = 4.0
#: the lookup's own footprint, in texels, added to every reach
REFINE_R0 = 1.0


def refine_rule() -> np.ndarray:
    """The compiled maps' rule (``kernels/insm/insmr.c``): ``levels, jump, r0, c[levels], band[levels]``, float32."""
    return np.array([len(REFINE_C), REFINE_JUMP, REFINE_R0, *REFINE_C, *REFINE_BAND], np.float32)


def kernels():
    """:mod:`usdml.kernels.insm.maps` (imports Warp)."""
    warp_module()
    from usdml.kernels.insm import maps as insm
    return insm


@dataclass
class LightViews:
    """The views of a set of lights' maps (:mod:`usdml.kernels.insm.maps`, "Views"), as kernel arrays."""

    position: np.ndarray    #: (L, 3) float32 light positions (distant: unused)
    cube: np.ndarray        #: (L,) int32 1 where the light's views are a cube (six views)
    first: np.ndarray       #: (L + 1,) int32 light l's views are first[l] .. first[l + 1]
    origin: np.ndarray      #: (V, 3) float32
    rot: np.ndarray         #: (V, 3, 3) float32 rows right, up, forward
    proj: np.ndarray        #: (V, 4) float32 ax, bx, ay, by
    kind: np.ndarray        #: (V,) int32 PERSPECTIVE or ORTHOGRAPHIC
    near: np.ndarray        #: (V,) float32

    def __len__(self) -> int:
        return len(self.cube)

    @property
    def views(self) -> int:
        return len(self.kind)


#: the six faces of a cube map: forward, up (face f's forward is the dominant axis the lookup picks)
_CUBE = [((1, 0, 0), (0, 1, 0)), ((-1, 0, 0), (0, 1, 0)), ((0, 1, 0), (0, 0, -1)), ((0, -1, 0), (0, 0, 1)),
         ((0, 0, 1), (0, 1, 0)), ((0, 0, -1), (0, 1, 0))]


def _basis(forward, up) -> np.ndarray:
    f = np.asarray(forward, np.float64)
    f = f / np.linalg.norm(f)
    u = np.asarray(up, np.float64)
    if abs(float(np.dot(f, u))) > 0.99:
        u = np.roll(u, 1)
    right = np.cross(u, f)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(f, right), f])


def light_views(position: np.ndarray, axis: np.ndarray, distant: np.ndarray, cone_deg: np.ndarray,
                centre: np.ndarray, radius: float, size: int) -> LightViews:
    """Views of ``L`` lights' maps at ``size`` texels (module doc, "Maps per light").

    ``position`` (L, 3) world, ``axis`` (L, 3) the direction each light emits (distant: travels),
    ``distant`` (L,) bool, ``cone_deg`` (L,) shaping half-angle (180: none); the scene's bounding sphere
    ``centre``, ``radius`` places the distant lights' views and the near planes."""
    n = len(position)
    near = NEAR_FRACTION * 2.0 * radius
    half = size / 2.0
    cube = np.zeros(n, np.int32)
    first = [0]
    origin, rot, proj, kind = [], [], [], []
    for i in range(n):
        if distant[i]:
            f = np.asarray(axis[i], np.float64)
            origin.append(np.asarray(centre, np.float64) - f / np.linalg.norm(f) * (1.01 * radius))
            rot.append(_basis(f, (0, 1, 0)))
            a = size / (2.02 * radius)
            proj.append((a, half, a, half))
            kind.append(ORTHOGRAPHIC)
        elif cone_deg[i] <= SPOT_MAX_DEG:
            origin.append(position[i])
            rot.append(_basis(axis[i], (0, 1, 0)))
            a = half / np.tan(np.radians(min(float(cone_deg[i]) * 1.02 + 0.1, 89.0)))
            proj.append((a, half, a, half))
            kind.append(PERSPECTIVE)
        else:
            cube[i] = 1
            for forward, up in _CUBE:
                origin.append(position[i])
                rot.append(_basis(forward, up))
                proj.append((half, half, half, half))
                kind.append(PERSPECTIVE)
        first.append(len(kind))
    v = len(kind)
    return LightViews(np.asarray(position, np.float32).reshape(n, 3), cube, np.asarray(first, np.int32),
                      np.asarray(origin, np.float32).reshape(v, 3), np.asarray(rot, np.float32).reshape(v, 3, 3),
                      np.asarray(proj, np.float32).reshape(v, 4), np.asarray(kind, np.int32),
                      np.full(v, near, np.float32))


def insm_box(snapshot: Snapshot) -> tuple[np.ndarray, np.ndarray] | None:
    """The box the depth images' viewpoints are placed on (module doc, "The box"); None for an empty
    scene."""
    members = all_members(snapshot)
    points, triangles = world_geometry(snapshot, members)
    if not len(triangles):
        return None
    lo, hi, _ = svo_bounds(points, triangles)
    return lo, hi


def triangle_spacing(tris: np.ndarray) -> np.ndarray:
    """``(T,) float32`` sample spacing of each reconstructed triangle (``(3T, 3)`` corners): ``sqrt(2 · area)``,
    the geometric mean of the legs of a triangle between a 2 × 2 block of depth-image samples (module doc,
    "Refinement")."""
    t = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return np.sqrt(np.linalg.norm(cross, axis=1)).astype(np.float32)


def take_lights(lights: Lights, index) -> Lights:
    """The lights ``index`` selects (a slice or an index array), every field cut alike."""
    kw = {}
    for f in fields(lights):
        value = getattr(lights, f.name)
        kw[f.name] = [value[i] for i in np.arange(len(lights))[index]] if isinstance(value, list) else value[index]
    return Lights(**kw)


def _key(row) -> bytes:
    return np.asarray(row, np.float32).tobytes()


class InsmBackend(VisibilityBackend):
    """Shadows from intermediate shadow maps (paper 001; module doc).

    Parameters
    ----------
    settings : a :class:`usdml.settings.UsdmlSettings` (None: the table's defaults); the backend reads
        ``insm_count`` (``K``), ``insm_resolution`` (``w``), ``insm_light_resolution`` (``S``),
        ``insm_threshold`` (``κ`` of the triangulation, :mod:`usdml.visibility.insm.mesh`) and ``insm_cpu_kernel``
    **values : those fields by name, over ``settings`` (``insm_light_resolution=128``)
    offset, bias : leaving the surface, in texels of the light's map (module doc)
    device : Warp device, ``cpu`` or ``cuda``
    report, progress : as every backend (:mod:`usdml.visibility.base`)

    ``stats`` after each frame: depth-image, triangulation, map and lookup seconds, reconstructed
    triangles, lights mapped, queries answered by maps and by the exact backend.
    """

    name = "insm"
    summary = "intermediate shadow maps: per-light maps rasterized from K triangulated depth images (paper 001)"
    capabilities = frozenset({SHADE_DIRECT, STATS, MEMORY_ESTIMATE, LIGHT_MAJOR, REFINE})
    reads_settings = True
    refine_levels = len(REFINE_C)

    def __init__(self, settings=None, *, offset: float = OFFSET_TEXELS, bias: float = BIAS_TEXELS,
                 device: str = "cpu", workers: int | None = None, report: Callable[[str], None] | None = None,
                 progress: Callable[..., None] | None = None, **values) -> None:
        s = settings_with(settings, values)
        self.count, self.resolution = int(s.insm_count), int(s.insm_resolution)
        self.light_resolution, self.threshold = int(s.insm_light_resolution), float(s.insm_threshold)
        cpu_kernel = s.insm_cpu_kernel
        self.offset, self.bias = float(offset), float(bias)
        self.device = device
        self.workers = cpu_workers(device, workers)
        self.report = report or (lambda line: log.info(line))
        self.exact = ExactBackend(workers=workers)
        self.native = False
        if str(device).startswith("cpu") and cpu_kernel != "warp":
            from usdml.visibility.insm import native as insm_native
            self.native = insm_native.library() is not None
            if not self.native and cpu_kernel == "native":
                raise UsdmlError(f"--insm-cpu-kernel native: {insm_native.describe()}")
        self._tris = None              # (3T, 3) float32 reconstructed triangles of the frame
        self._tris_wp = self._clusters = self._spacing = None
        self._graded = None            # the last occluded_uncertain call: (key, blocked, grades)
        self._graded_lock = threading.Lock()
        self._scene = (np.zeros(3), 1.0)
        self._known: dict[bytes, tuple] = {}   # target key -> (position, axis, distant, cone)
        self._buffers: queue.Queue | None = None
        self.stats: dict = {}
        self._reset_stats()

    def _reset_stats(self) -> None:
        self.stats.update(depth_seconds=0.0, triangulate_seconds=0.0, receiver_seconds=0.0, map_seconds=0.0,
                          lookup_seconds=0.0, last_maps=0, last_receiver_seconds=0.0, last_map_seconds=0.0,
                          last_lookup_seconds=0.0,
                          maps=0, map_queries=0, exact_queries=0)

    @classmethod
    def memory_estimate(cls, snapshot: Snapshot, settings) -> dict:
        """Bytes before anything is built: the depth images and their hit points (``K w²`` × 16 B), the
        reconstructed triangles (at most two per sample, 36 B each), one map of six views per CPU thread
        (``6 S²`` × 4 B) and the answers :meth:`shade_direct` holds at once (at most ``ANSWER_BYTES``);
        the exact backend it holds costs what ``exact`` does."""
        k = int(getattr(settings, "insm_count", 10) or 10)
        w = int(getattr(settings, "insm_resolution", 128) or 128)
        s = int(getattr(settings, "insm_light_resolution", 512) or 512)
        images = k * w * w * 16
        tris = 2 * k * w * w * 36
        maps = 6 * s * s * 4 * cpu_workers("cpu")
        return {"count": k, "resolution": w, "lightResolution": s, "imageBytes": images, "triangleBytes": tris,
                "mapBytes": maps, "answerBytes": ANSWER_BYTES, "totalBytes": images + tris + maps + ANSWER_BYTES,
                "upperBound": True}

    @classmethod
    def cpu_path(cls) -> str:
        from usdml.visibility.insm import native as insm_native
        return insm_native.describe()

    @classmethod
    def memory_line(cls, estimate: dict) -> str:
        return (f"{estimate['count']} depth images at {estimate['resolution']}^2, at most "
                f"{estimate['triangleBytes'] / 2**20:.1f} MiB of triangles; maps {estimate['lightResolution']}^2 "
                f"per view, {estimate['mapBytes'] / 2**20:.1f} MiB for the threads; at most "
                f"{estimate['answerBytes'] / 2**20:.0f} MiB of answers; plus the exact backend's scene")

    def describe(self) -> dict:
        return {"cpu_kernel": "native" if self.native else "warp", "insm_count": self.count, "insm_resolution": self.resolution,
                "insm_light_resolution": self.light_resolution, "insm_threshold": self.threshold,
                "reconstructed_triangles": self.triangles,
                **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.stats.items()}}

    @property
    def triangles(self) -> int:
        return 0 if self._tris is None else len(self._tris) // 3

    # ------------------------------------------------------------------ per frame

    def update(self, snapshot: Snapshot, changes: Changes | None = None) -> None:
        """Update the exact backend; cast the depth images again and triangulate them when geometry
        changed (Alg. 1, lines 1-3); remember the snapshot's lights as targets the maps answer."""
        self._reset_stats()
        self.exact.update(snapshot, changes)
        geometry = changes is None or self._tris is None or changes.static or bool(changes.deforming) \
            or any(changes.prototypes.values())
        if geometry:
            self._build(snapshot)
        self._known = {}
        self._graded = None
        self._remember(snapshot.lights)

    def _build(self, snapshot: Snapshot) -> None:
        self._scene = scene_sphere(snapshot)
        t0 = time.perf_counter()
        bounds = insm_box(snapshot)
        if bounds is None:
            self._tris, self._tris_wp, self._spacing = np.zeros((0, 3), np.float32), None, None
            return
        self.box = bounds
        views = insm_views(bounds[0], bounds[1], self.count, self.resolution, snapshot.up_axis)
        depth, points, normals = depth_images(self.exact, views, self.resolution)
        t1 = time.perf_counter()
        self._tris = triangulate(depth, points, views, self.threshold, normals)
        self._tris_wp = self._clusters = self._spacing = None
        t2 = time.perf_counter()
        self.stats.update(depth_seconds=t1 - t0, triangulate_seconds=t2 - t1)

    def per_frame_rebuild_seconds(self, snapshot: Snapshot, repeats: int = 3) -> dict:
        """Seconds to cast the depth images and triangulate them again (the median of ``repeats``): what
        every frame whose geometry moved costs before its lights' maps."""
        depth, tri = [], []
        for _ in range(max(1, int(repeats))):
            self._build(snapshot)
            depth.append(self.stats["depth_seconds"])
            tri.append(self.stats["triangulate_seconds"])
        return {"rebuild_seconds": float(np.median(depth) + np.median(tri)),
                "depth_image_seconds": float(np.median(depth)), "triangulate_seconds": float(np.median(tri)),
                "rebuild_repeats": len(depth), "reconstructed_triangles": self.triangles}

    def _remember(self, lights: Lights) -> None:
        """Targets the maps answer: lights' positions, and distant lights' directions toward them."""
        self._graded = None            # which rows the maps answer may change
        for i in range(len(lights)):
            distant = lights.type[i] == LightType.DISTANT
            target = -lights.axis[i] if distant else lights.position[i]
            self._known[_key(target)] = (lights.position[i], lights.axis[i], bool(distant),
                                         float(lights.cone_angle[i]))

    # ------------------------------------------------------------------ maps

    def _corners(self) -> np.ndarray:
        """The reconstructed triangles' corners, C-contiguous; one degenerate triangle for none (the
        kernels take no empty array)."""
        return np.ascontiguousarray(self._tris if len(self._tris) else np.zeros((3, 3), np.float32))

    def _spacings(self) -> np.ndarray:
        """Each of :meth:`_corners`' triangles' sample spacing (:func:`triangle_spacing`), made once per set of
        triangles."""
        if self._spacing is None:
            self._spacing = triangle_spacing(self._corners())
        return self._spacing

    def _triangles_wp(self):
        if self._tris_wp is None:
            wp = warp_module()
            self._tris_wp = wp.array(self._corners(), dtype=wp.vec3, device=self.device)
        return self._tris_wp

    def _views(self, position, axis, distant, cone) -> LightViews:
        c, r = self._scene
        return light_views(position, axis, distant, cone, c, r, self.light_resolution)

    def _light_views(self, lights: Lights) -> LightViews:
        """The views of ``lights``' maps (:func:`light_views`)."""
        return self._views(lights.position, lights.axis, lights.type == LightType.DISTANT, lights.cone_angle)

    def _native_inputs(self, lv: LightViews) -> tuple[np.ndarray, tuple, tuple]:
        """What the compiled maps read for ``lv``: the triangles, their clusters (made once per set of
        triangles) and the views' arrays."""
        if self._clusters is None:
            self._clusters = clusters(self._tris)
        views = tuple(np.ascontiguousarray(a) for a in (lv.origin, lv.rot, lv.proj, lv.kind, lv.near))
        return self._corners(), self._clusters, views

    def _native_buffers(self, n_views: int) -> tuple:
        """One thread's maps for the compiled path: depths, receiver tiles and per-view depths of
        ``n_views`` views."""
        size = self.light_resolution
        tiles = -(-size // TILE)
        return (np.empty(n_views * size * size, np.float32), np.empty(n_views * tiles * tiles, np.float32),
                np.empty(n_views, np.float32))

    def _count_maps(self, n_lights: int, seconds: np.ndarray) -> None:
        """Add a call's maps and its receiver / map / lookup seconds (summed over threads) to ``stats``, and
        keep the call's own (``usdml bench`` calls :meth:`occluded` several times per frame)."""
        receivers, maps, lookups = (float(x) for x in seconds)
        self.stats["receiver_seconds"] += receivers
        self.stats["map_seconds"] += maps
        self.stats["lookup_seconds"] += lookups
        self.stats["maps"] += n_lights
        self.stats.update(last_maps=n_lights, last_receiver_seconds=receivers, last_map_seconds=maps,
                          last_lookup_seconds=lookups)

    def answer(self, lv: LightViews, jobs: list) -> None:
        """Rasterize each job's lights' maps and look its points up in them.

        ``jobs``: ``(l0, l1, points, normals, out)``: lights ``l0 .. l1`` of ``lv``, ``(P, 3) float32``
        C-contiguous points and normals, ``out`` a ``((l1 - l0) · P,) uint8`` array written light-major
        (1: blocked), and optionally ``grade``, an array like ``out`` for each answer's grade (module doc,
        "Refinement": 0 certain at every level, else the first level that flags it), the answers the same.
        On a CPU each job is one light and the jobs run over the threads, each on maps of its own (the
        compiled path, or Warp's kernels); on a GPU a job is a batch of lights."""
        wp = warp_module()
        dev = wp.get_device(self.device)
        size = self.light_resolution
        tiles = -(-size // TILE)
        most = int(np.max(np.diff(lv.first))) if len(lv) else 1
        pool: queue.Queue = queue.Queue()
        seconds = np.zeros(3)
        lock = threading.Lock()
        native = self.native and dev.is_cpu
        scratches: queue.Queue = queue.Queue()
        if native:
            from usdml.visibility.insm import native as insm_native
            tris, cl, views = self._native_inputs(lv)
            rule = refine_rule()

            def buffers(n_views: int) -> tuple:
                return self._native_buffers(max(n_views, most))
        else:
            launch = self._warp_launcher(lv, size, tiles)

            def buffers(n_views: int) -> tuple:
                n = max(n_views, most)
                return (wp.empty(n * size * size, dtype=float, device=dev),
                        wp.empty(n * tiles * tiles, dtype=float, device=dev), wp.empty(n, dtype=float, device=dev))

        def run(job) -> None:
            l0, l1, pts, nrm, out, *rest = job
            grade = rest[0] if rest else None
            n_views = int(lv.first[l1] - lv.first[l0])
            try:
                held = pool.get_nowait()
            except queue.Empty:
                held = None
            if held is None or held[2].shape[0] < n_views:
                held = buffers(n_views)
            mine = np.zeros(3)
            if native:
                refine = None
                if grade is not None:
                    try:
                        scratch = scratches.get_nowait()
                    except queue.Empty:
                        scratch = None
                    need = insm_native.refine_floats(size, max(n_views, most))
                    if scratch is None or scratch.size < need:
                        scratch = np.empty(need, np.float32)
                    refine = (self._spacings(), scratch, rule, grade)
                insm_native.light(tris, cl, views, int(lv.first[l0]), n_views, bool(lv.cube[l0]), lv.position[l0],
                                  size, held, pts, nrm, self.offset, self.bias, out, mine, refine=refine)
                if refine is not None:
                    scratches.put(refine[1])
            else:
                launch(l0, l1, pts, nrm, out, held, mine, grade)
            with lock:
                seconds[:] += mine
            pool.put(held)

        run_parallel(run, jobs, self.workers, first_on_caller=not native)
        self._count_maps(len(lv) if jobs else 0, seconds)

    def _warp_launcher(self, lv: LightViews, size: int, tiles: int):
        """``launch(l0, l1, points, normals, out, buffers, seconds, grade)``: one job of :meth:`answer` by the
        Warp kernels (:mod:`usdml.kernels.insm.maps`), on the backend's device; with ``grade`` (not None) the
        answers' grades by the Warp path's rule too (:func:`usdml.kernels.insm.maps.lookup_points`)."""
        wp = warp_module()
        k = kernels()
        dev = wp.get_device(self.device)
        arr = dict(device=dev)
        va = dict(origin=wp.array(lv.origin, dtype=wp.vec3, **arr), rot=wp.array(lv.rot, dtype=wp.mat33, **arr),
                  proj=wp.array(lv.proj, dtype=wp.vec4, **arr), kind=wp.array(lv.kind, dtype=wp.int32, **arr),
                  near=wp.array(lv.near, dtype=float, **arr))
        la = dict(pos=wp.array(lv.position, dtype=wp.vec3, **arr), cube=wp.array(lv.cube, dtype=wp.int32, **arr),
                  first=wp.array(lv.first[:-1].copy(), dtype=wp.int32, **arr))
        tris = self._triangles_wp()
        n_tris = self.triangles
        atomic = 0 if dev.is_cpu else 1
        wrap = dict(device=dev, copy=not dev.is_cpu)

        rule = (wp.array(np.asarray(REFINE_FOOTPRINT, np.int32), dtype=wp.int32, **arr),
                wp.array(np.asarray(REFINE_BAND, np.float32), dtype=float, **arr))

        def launch(l0, l1, pts, nrm, out, buffers, seconds, grade=None) -> None:
            depth, tile_z, view_z = buffers
            n_views = int(lv.first[l1] - lv.first[l0])
            v0 = int(lv.first[l0])
            p = wp.array(pts, dtype=wp.vec3, **wrap)
            n = wp.array(nrm, dtype=wp.vec3, **wrap)
            o = wp.array(out, dtype=wp.uint8, device=dev, copy=False) if dev.is_cpu else \
                wp.zeros(out.size, dtype=wp.uint8, device=dev)
            t0 = time.perf_counter()
            looked = (p, n, la["pos"], la["cube"], la["first"], va["origin"], va["rot"], va["proj"], va["kind"],
                      va["near"], v0, size)
            tile_z.fill_(-1.0e30)
            view_z.fill_(-1.0e30)
            wp.launch(k.receiver_tiles, dim=(l1 - l0, len(pts)), device=dev,
                      inputs=[*looked, self.offset, self.bias, l0, tiles, tile_z, view_z])
            t1 = time.perf_counter()
            depth.fill_(-1.0e30)
            if n_tris and dev.is_cpu and l1 - l0 == 1 and lv.cube[l0]:
                # one cube on one thread: each triangle tested against the six faces at once
                wp.launch(k.raster_cube, dim=n_tris, device=dev,
                          inputs=[tris, wp.vec3(*lv.position[l0]), va["rot"], va["proj"], va["near"], v0, size,
                                  atomic, depth, tiles, tile_z, view_z])
            elif n_tris:
                wp.launch(k.raster_views, dim=(n_views, n_tris), device=dev,
                          inputs=[tris, va["origin"], va["rot"], va["proj"], va["kind"], va["near"], v0, size,
                                  atomic, depth, tiles, tile_z, view_z])
            t2 = time.perf_counter()
            if grade is None:
                g, levels = o, 0                  # answers only: no grade is written
            else:
                g = wp.array(grade, dtype=wp.uint8, device=dev, copy=False) if dev.is_cpu else \
                    wp.zeros(grade.size, dtype=wp.uint8, device=dev)
                levels = self.refine_levels
            wp.launch(k.lookup_points, dim=(l1 - l0, len(pts)), device=dev,
                      inputs=[*looked, depth, self.offset, self.bias, l0, o, tiles, tile_z, *rule, levels, REFINE_JUMP,
                              g])
            if grade is not None and not dev.is_cpu:
                grade[:] = g.numpy()
            if not dev.is_cpu:
                out[:] = o.numpy()
            t3 = time.perf_counter()
            seconds += (t1 - t0, t2 - t1, t3 - t2)
        return launch

    def _batches(self, lv: LightViews) -> list[tuple[int, int]]:
        """Light ranges answered together: one light per job on a CPU, as many as ``CUDA_MAP_BYTES`` of
        maps hold on a GPU."""
        if str(self.device).startswith("cpu"):
            return [(i, i + 1) for i in range(len(lv))]
        per_view = 4 * self.light_resolution ** 2
        out, l0 = [], 0
        while l0 < len(lv):
            l1 = l0 + 1
            while l1 < len(lv) and (lv.first[l1 + 1] - lv.first[l0]) * per_view <= CUDA_MAP_BYTES:
                l1 += 1
            out.append((l0, l1))
            l0 = l1
        return out

    def blocked_lights(self, lights: Lights, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``(L, P) uint8``: 1 where light ``l`` is blocked from point ``p`` by its map (every light, also
        those that cast no shadow: the caller skips them)."""
        return self._blocked(self._light_views(lights), points, normals)

    def _blocked(self, lv: LightViews, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``(L, P) uint8`` answers of the lights of ``lv`` for ``points`` (:meth:`answer`)."""
        n_p = len(points)
        out = np.zeros((len(lv), n_p), np.uint8)
        if not len(lv) or not n_p:
            return out
        pts = np.ascontiguousarray(points, np.float32)
        nrm = np.ascontiguousarray(normals, np.float32)
        flat = out.reshape(-1)
        self.answer(lv, [(l0, l1, pts, nrm, flat[l0 * n_p:l1 * n_p]) for l0, l1 in self._batches(lv)])
        return out

    # ------------------------------------------------------------------ queries

    def shade_direct(self, points, normals, albedo, lights, progress=None, meters_per_unit: float = 1.0,
                     min_distance: float = 0.0, geometric=None, material=None, *, plain) -> DirectResult:
        """Alg. 3 with a map lookup in place of each ray (module doc): the answers of every (point,
        light) pair, light by light, then ``plain`` (:func:`usdml.lighting.direct.shade_direct`) over them;
        lights in chunks of at most ``ANSWER_BYTES`` of answers. The compiled maps shade in one call. With
        ``material`` rows: ``plain`` over :meth:`occluded` (no map kernel sums the BRDF)."""
        if material is not None:
            return plain(points, normals, albedo, lights, self.occluded, progress, meters_per_unit=meters_per_unit,
                         min_distance=min_distance, geometric=geometric, material=material)
        self._remember(lights)
        n_p, n_l = len(points), len(lights)
        if self.native and n_p and n_l:
            result = self._shade_native(points, normals, albedo, lights, meters_per_unit, min_distance, geometric)
            if progress is not None:
                progress(n_p)
            return result
        offset = geometric if geometric is not None else normals
        step = max(1, ANSWER_BYTES // max(n_p, 1))
        radiance = np.zeros((n_p, 3), np.float32)
        blocked = np.zeros(n_p, np.float64)
        facing = np.zeros(n_p, np.int64)
        queries = 0
        casts = np.asarray(lights.shadow, bool)
        for l0 in range(0, max(n_l, 1), step):
            sl = slice(l0, min(n_l, l0 + step))
            part = take_lights(lights, sl) if (l0 or step < n_l) else lights
            answers = np.zeros((len(part), n_p), np.uint8)
            cast = np.flatnonzero(casts[sl])
            if len(cast):
                answers[cast] = self.blocked_lights(take_lights(part, cast), points, offset)
            r = plain(points, normals, albedo, part, None, None, meters_per_unit=meters_per_unit,
                      min_distance=min_distance, geometric=geometric,
                      answers=np.ascontiguousarray(answers.T))     # (P, L): each block reads its rows
            radiance += r.radiance
            blocked += r.shadow.astype(np.float64) * r.facing
            facing += r.facing
            queries += r.queries
            if progress is not None:
                progress(int(round(n_p * (sl.stop - sl.start) / max(n_l, 1))))
        self.stats["map_queries"] += queries
        shadow = np.where(facing > 0, np.rint(blocked) / np.maximum(facing, 1), 0.0).astype(np.float32)
        return DirectResult(radiance, shadow, facing.astype(np.int32), queries)

    def _specs(self, targets: np.ndarray, distant: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
        """Group query ``targets`` by light: ``(inverse, known, specs)``: each row's group, whether
        each group is a light the maps answer (module doc), and those groups' ``(position, axis,
        distant, cone)``."""
        bits = np.ascontiguousarray(np.asarray(targets, np.float32)).view(np.uint32).astype(np.uint64)
        code = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)) \
            ^ (bits[:, 2] * np.uint64(0x165667B19E3779F9)) ^ distant.astype(np.uint64)
        uniq, first, inverse = np.unique(code, return_index=True, return_inverse=True)
        known = np.zeros(len(uniq), bool)
        specs = []
        for g, row in enumerate(first):
            spec = self._known.get(_key(targets[row]))
            if spec is not None and spec[2] == bool(distant[row]):
                known[g] = True
            specs.append(spec)
        return inverse.reshape(-1), known, specs

    def shade_refined(self, points, normals, albedo, lights: Lights, progress=None, meters_per_unit: float = 1.0,
                      min_distance: float = 0.0, geometric=None, *, level: int, near=None,
                      resolve: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> tuple[DirectResult, dict]:
        """``REFINE`` in the fused shading (:class:`usdml.visibility.refine.Refined`'s hook): :meth:`shade_direct`'s
        compiled pass, a map per light for every point, with each looked-up pair graded (module doc,
        "Refinement"); the pairs uncertain at ``level`` are neither lit nor blocked there but handed, a light at
        a time, to ``resolve(point_index, light_index, kind) -> (K,) bool`` free (kind 0; called from the thread
        pool, several lights at once) and shaded by its answers. The maps have no blind zone: ``near`` is not
        used. Returns the result and ``{"uncertain": pairs handed back, "near": 0, "queries": shadow queries}``.
        Without the compiled maps: ``NotImplementedError`` (the caller asks :meth:`occluded_uncertain`)."""
        if not self.native:
            raise NotImplementedError("the fused refined shading needs the compiled insm maps")
        level = int(level)
        if not 1 <= level <= self.refine_levels:
            raise ValueError(f"level must be in [1, {self.refine_levels}], got {level}")
        self._remember(lights)
        n_p = len(points)
        if not n_p or not len(lights):
            return DirectResult(np.zeros((n_p, 3), np.float32), np.zeros(n_p, np.float32), np.zeros(n_p, np.int32),
                                0), {"uncertain": 0, "near": 0, "queries": 0}
        result, handed = self._shade_native(points, normals, albedo, lights, meters_per_unit, min_distance, geometric,
                                            refine=(level, resolve))
        if progress is not None:
            progress(n_p)
        return result, {"uncertain": handed, "near": 0, "queries": result.queries}

    def _shade_native(self, points, normals, albedo, lights: Lights, meters_per_unit: float, min_distance: float,
                      geometric, refine: tuple | None = None):
        """:meth:`shade_direct` in the compiled maps: each light's map, lookups and share of Alg. 3 in one
        call (``kernels/include/light_term.h``'s UsdLux rules, the voxel kernel's), sums per block of lights
        added in block order (:data:`LIGHT_BLOCKS`); nothing of (points x lights) is held. With ``refine`` =
        ``(level, resolve)`` (:meth:`shade_refined`): the result and the number of pairs handed back."""
        from usdml.visibility.insm import native as insm_native
        from usdml.visibility.voxel.native import compiled_lights

        n_p = len(points)
        lv = self._light_views(lights)
        table = compiled_lights(lights, meters_per_unit, min_distance)
        f32 = dict(dtype=np.float32)
        pts = np.ascontiguousarray(points, **f32)
        shading = np.ascontiguousarray(normals, **f32)
        geo = np.ascontiguousarray(geometric if geometric is not None else normals, **f32)
        tris, cl, views = self._native_inputs(lv)
        size = self.light_resolution
        most = int(np.max(np.diff(lv.first)))
        pool: queue.Queue = queue.Queue()
        held_all: list = []
        lock = threading.Lock()

        level, resolve = refine if refine is not None else (0, None)
        rule = refine_rule()

        def run(block: tuple[int, int]) -> tuple:
            """The sums over lights ``block[0] .. block[1] - 1``, in light order, with a thread's scratch."""
            try:
                held = pool.get_nowait()
            except queue.Empty:
                graded = None if resolve is None else \
                    (np.empty(insm_native.refine_floats(size, most), np.float32), np.zeros(n_p, np.uint8),
                     np.zeros(1, np.int64))
                held = (self._native_buffers(most), (np.empty((n_p, 3), np.float32), np.empty(n_p, np.uint8)),
                        np.zeros(3), graded)
                with lock:
                    held_all.append(held)
            buffers, scratch, seconds, graded = held
            acc = (np.zeros((n_p, 3), np.float32), np.zeros(n_p, np.int32), np.zeros(n_p, np.int32),
                   np.zeros(1, np.int64))
            rgb, rad, blk = scratch[0], acc[0], acc[1]
            for li in range(*block):
                insm_native.light(tris, cl, views, int(lv.first[li]), int(lv.first[li + 1] - lv.first[li]),
                                  bool(lv.cube[li]), lv.position[li], size, buffers, pts, geo, self.offset, self.bias,
                                  None, seconds, (table, li, shading, *scratch, *acc),
                                  refine=None if graded is None else (self._spacings(), graded[0], rule, graded[1]),
                                  hand_level=level)
                if graded is not None:
                    # the handed-back pairs answered exactly: lit where free, else blocked
                    rows = np.flatnonzero(graded[1])
                    if len(rows):
                        free = np.asarray(resolve(rows, np.full(len(rows), li, np.int64),
                                                  np.zeros(len(rows), np.int8)), bool)
                        rad[rows[free]] += rgb[rows[free]]
                        blk[rows[~free]] += 1
                        graded[2][0] += len(rows)
            pool.put(held)
            return acc

        # the lights in LIGHT_BLOCKS blocks whatever the cores, each summed in light order and the blocks added in
        # block order: the same pixels on any number of threads (per-thread sums were added in whatever order
        # the threads took the lights, which moved a pixel by a float32 step from run to run)
        edges = np.linspace(0, len(lights), min(len(lights), LIGHT_BLOCKS) + 1).astype(np.int64)
        radiance = np.zeros((n_p, 3), np.float32)
        blocked = np.zeros(n_p, np.int64)
        facing = np.zeros(n_p, np.int64)
        queries, seconds, handed = 0, np.zeros(3), 0
        for rad, blk, fac, q in iter_parallel(run, [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])],
                                              self.workers):
            radiance += rad
            blocked += blk
            facing += fac
            queries += int(q[0])
        for _, _, sec, graded in held_all:
            seconds += sec
            handed += 0 if graded is None else int(graded[2][0])
        radiance *= np.asarray(albedo, np.float32) / np.float32(np.pi)
        shadow = np.where(facing > 0, blocked / np.maximum(facing, 1), 0.0).astype(np.float32)
        self._count_maps(len(lights), seconds)
        self.stats["map_queries"] += queries
        result = DirectResult(radiance, shadow, facing.astype(np.int32), queries)
        return result if refine is None else (result, handed)

    def occluded(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        """Segments to one of the frame's lights from its map, the others by the exact backend (module doc)."""
        return self._occluded(origins, targets, normals, distant, graded=False)[0]

    def occluded_uncertain(self, origins, targets, *, normals=None, distant=None,
                           level: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``REFINE``: :meth:`occluded`'s answers and which are uncertain at ``level`` (1 .. ``refine_levels``)
        by the rule of the module doc ("Refinement"); rows the exact backend answers are certain.

        Every level's flags come from one pass (each answer's grade: the first level that flags it), and the
        last call's answers and grades are kept: the same queries asked again at another level (``--error-budget``
        widening its rule over one sample) build no map."""
        level = int(level)
        if not 1 <= level <= self.refine_levels:
            raise ValueError(f"level must be in [1, {self.refine_levels}], got {level}")
        origins = as_vectors(origins, "origins")
        n = origins.shape[0]
        targets = as_vectors(targets, "targets", n)
        distant = np.zeros(n, bool) if distant is None else as_flags(distant, "distant", n)
        normals = np.zeros((n, 3)) if normals is None else as_vectors(normals, "normals", n)
        key = self._query_key(origins, targets, normals, distant)
        with self._graded_lock:
            kept = self._graded
        if kept is not None and kept[0] == key:
            blocked, grades = kept[1], kept[2]
        else:
            blocked, grades = self._occluded(origins, targets, normals, distant, graded=True)
            with self._graded_lock:
                self._graded = (key, blocked, grades)
        return blocked.copy(), (grades != 0) & (grades <= level)

    @staticmethod
    def _query_key(*arrays) -> bytes:
        """A digest of a call's query arrays (:meth:`occluded_uncertain`'s last call)."""
        h = hashlib.blake2b(digest_size=16)
        for a in arrays:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.data)
        return h.digest()

    def _occluded(self, origins, targets, normals, distant, graded: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`occluded`'s answers and, when ``graded``, each answer's grade (``(N,) uint8``, :meth:`answer`;
        0 for the rows the exact backend answers)."""
        origins = as_vectors(origins, "origins")
        n = origins.shape[0]
        targets = as_vectors(targets, "targets", n)
        distant = np.zeros(n, bool) if distant is None else as_flags(distant, "distant", n)
        normals = np.zeros((n, 3)) if normals is None else as_vectors(normals, "normals", n)
        out = np.zeros(n, bool)
        grades = np.zeros(n, np.uint8) if graded else None
        if n == 0:
            return out, grades
        if self._tris is None:
            raise RuntimeError("InsmBackend.update() must be called before queries")
        inverse, known, specs = self._specs(targets, distant)
        rest = np.flatnonzero(~known[inverse])
        if len(rest):
            out[rest] = self.exact.occluded(origins[rest], targets[rest], normals=normals[rest], distant=distant[rest])
            self.stats["exact_queries"] += len(rest)
        groups = np.flatnonzero(known)
        if not len(groups):
            return out, grades
        order = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[order], np.arange(len(known) + 1))
        lv = self._views(*(np.array([specs[g][i] for g in groups]) for i in range(4)))
        jobs, rows = [], []
        for li, g in enumerate(groups):
            idx = order[bounds[g]:bounds[g + 1]]
            job = (li, li + 1, np.ascontiguousarray(origins[idx], np.float32),
                   np.ascontiguousarray(normals[idx], np.float32), np.zeros(len(idx), np.uint8))
            jobs.append(job + ((np.zeros(len(idx), np.uint8),) if graded else ()))
            rows.append(idx)
        self.answer(lv, jobs)
        for idx, job in zip(rows, jobs):
            out[idx] = job[4] != 0
            if graded:
                grades[idx] = job[5]
        self.stats["map_queries"] += int(sum(len(r) for r in rows))
        return out, grades

    def occluded_matrix(self, points, normals, light_positions, light_distant=None, light_directions=None):
        """``LIGHT_MAJOR``: every point against every light, light by light (one map each); lights that
        are not the frame's (:meth:`occluded`) are mapped as well, as plain point or distant lights."""
        points = as_vectors(points, "points")
        n_p = points.shape[0]
        normals = np.zeros((n_p, 3)) if normals is None else as_vectors(normals, "normals", n_p)
        positions = as_vectors(light_positions, "light_positions")
        n_l = len(positions)
        distant = np.zeros(n_l, bool) if light_distant is None else as_flags(light_distant, "light_distant", n_l)
        axis = np.zeros((n_l, 3)) if light_directions is None else as_vectors(light_directions, "light_directions", n_l)
        if distant.any() and light_directions is None:
            raise ValueError("light_directions is required for distant lights")
        cone = np.full(n_l, 180.0)
        for i in range(n_l):
            target = -axis[i] / np.linalg.norm(axis[i]) if distant[i] else positions[i]
            spec = self._known.get(_key(target))
            if spec is not None and spec[2] == bool(distant[i]):
                axis[i], cone[i] = spec[1], spec[3]
        blocked = self._blocked(self._views(positions, axis, distant, cone), points, normals)
        self.stats["map_queries"] += n_p * n_l
        return blocked.view(bool).T

    def close(self) -> None:
        self.exact.close()
        self._tris_wp = None
