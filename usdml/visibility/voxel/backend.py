"""The ``voxel`` visibility backend: paper 000's per-direction voxel arrays, shared by instances.

Arrays (paper 000 Alg. 4)
    * **static**: every mesh that does not deform and every prototype whose instances never move,
      flattened into world space: one array, built once (or loaded from the cache).
    * **one per moving prototype**: built in prototype space and shared by all its instances; a
      query is moved into each instance's space by the instance's inverse transform. Only the
      instances whose world box the ray meets are visited (a Warp BVH over the boxes, rebuilt per
      frame: cheap), so the cost does not grow with the number of instances in the scene.
    * **per frame**: deforming meshes and prototypes (or, ``fully_dynamic``, every mesh and instance,
      and then no other array) in one world-space array rebuilt on frames where one of them changed:
      by Alg. 5 (one voxelization rotated, :mod:`usdml.visibility.voxel.rotate`) or Alg. 1, written
      into its slot of the assembled words (nothing reallocated or copied per frame).

    One array (its cube, Alg. 1, the cache) is :mod:`usdml.visibility.voxel.array`; directions, rows
    and packing are in :mod:`usdml.visibility.voxel.grid`; the query kernels in
    :mod:`usdml.kernels.voxel.query`, the fused shading kernel (Alg. 3) in :mod:`usdml.kernels.voxel.shading`.

Leaving the surface (self-occlusion) and its cost
    The voxels around a shading point hold its own surface. A shadow ray therefore starts
    ``normal_offset`` voxels (of the static array, in world units) off the surface along the normal
    turned toward the light, and ignores its first ``skip`` voxels, or more at grazing angles: until it
    is ``slab`` voxels above the tangent plane (``slab / sin β`` voxels along the ray, at most
    ``max_skip``). It also ignores its last ``end_skip`` voxels so a light mounted on a wall is not
    hidden by the wall. The cost: occluders closer than about ``normal_offset + slab`` voxels to the
    shading point (contact shadows, fins and sills on a facade) or ``end_skip`` voxels to the light do
    not shadow. ``usdml compare`` splits the errors into near-field and far-field to measure it.

    ``max_skip`` is 2 (``MAX_SKIP``): with one-voxel-thin surfaces a grazing ray needs less room to
    leave its own, and a longer skip lets it through nearby occluders. Measured ε_v / ε_s at 128³ /
    2° (128 px), max_skip 4 -> 2 (-> 1): city 1.99 / 1.25 -> 1.86 / 1.10 (-> 1.83 / 1.02), planes
    2.43 / 1.53 -> 2.31 / 1.39, low-poly creature (3,968 triangles) 1.80 / 1.11 -> 1.81 / 1.13, park 17.8 / 7.1 -> 17.5 / 6.9
    (-> 18.7 / 7.8: its grazing ground rays start hidden). With Alg. 5's conservative mapping the
    per-frame surfaces are about two voxels thick and 2 is too short (park 29.9 / 25.1 -> 38.1 /
    34.9 %), so it keeps 4 (``CONSERVATIVE_MAX_SKIP``).
"""

from __future__ import annotations

from dataclasses import dataclass
import logging
import threading
import time
from typing import Callable

import numpy as np

from usdml.cache import Cache
from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, run_bands
from usdml.scene import Changes, Lights, LightType, Snapshot, world_geometry
from usdml.scene.light_table import LightTable
from usdml.settings import VOXEL_REBUILDS
from usdml.visibility.base import (BAKE, HIT_DISTANCES, MEMORY_ESTIMATE, REFINE, SHADE_DIRECT, STATS, DirectResult,
                                   VisibilityBackend, as_flags, as_vectors, baked_entry, baked_line, members_changed,
                                   scene_sphere, settings_with)
from usdml.visibility.emitter_ends import EmitterEnds
from usdml.visibility.voxel.array import (CORE, VoxelArray, array_cost, available_memory, build_array, cached_array,
                                          normalizing_transform, voxel_kernels, warp_module)
from usdml.visibility.voxel.budget import array_roles, memory_estimate, memory_line
from usdml.visibility.voxel.grid import DirectionBins, RowLayout, core_bounds
from usdml.visibility.voxel.rotate import MAX_RESOLUTION, rotate_array
from usdml.zorder import morton_order

log = logging.getLogger("usdml")

__all__ = ["VoxelBackend", "MAX_SKIP", "CONSERVATIVE_MAX_SKIP", "SHADE_TILE"]

#: how the per-frame array is rebuilt: Alg. 5 (rotate one voxelization) or Alg. 1 (every direction)
REBUILDS = VOXEL_REBUILDS
#: most voxels a grazing shadow ray skips to leave its surface (module doc, "Leaving the surface"),
#: and with Alg. 5's conservative mapping, whose per-frame surfaces are about two voxels thick
MAX_SKIP = 2.0
CONSERVATIVE_MAX_SKIP = 4.0
#: points per tile of the CPU shading kernel (kernels.direct_shading.shade_tiles)
SHADE_TILE = 64
#: the most entries a thread's list of handed-back pairs holds (shade_refined)
LIST_ENTRIES = 1 << 20
#: ``REFINE``: per level (1, 2, ...), the thick-ray rule's sideways shift and the blind zone's reach beyond the
#: ray's offset and skip, in voxels of the static array (usdml.visibility.refine)
THICK = (1.0, 1.5, 2.5, 4.0)
BLIND = (0.0, 0.5, 1.0, 2.0)


def widened(rule: Callable[[float], tuple[np.ndarray, np.ndarray]], level: int) -> tuple[np.ndarray, np.ndarray]:
    """``REFINE`` at ``level``: ``rule(width)``'s answers, uncertain where any width of ``THICK`` up to the
    level's says so."""
    blocked, uncertain = rule(THICK[0])
    for width in THICK[1:min(max(level, 1), len(THICK))]:
        uncertain = uncertain | rule(width)[1]
    return blocked, uncertain


@dataclass
class _Group:
    members: tuple
    array: VoxelArray | None
    geometry_key: str = ""


def _shading_kernels():
    from usdml.kernels.voxel import shading as direct_shading

    return direct_shading




def _reference_voxel(arrays: list[VoxelArray], world_ids: list[int]) -> float:
    """World units of "one voxel" for the ray rule's offset: the static (first world-space) array's
    voxel along its smallest world extent, else the finest array's."""
    if world_ids:
        a = arrays[world_ids[0]]
        return a.voxel_size / float(np.max(np.abs(np.diag(a.to_array)[:3])))
    return min((a.voxel_size for a in arrays), default=0.0)


def _direct_result(order: np.ndarray, rad: np.ndarray, blocked: np.ndarray, facing: np.ndarray, albedo,
                   all_cast: bool, spec: np.ndarray | None = None):
    """The shading kernels' per-point sums (in ``order``) as a :class:`DirectResult`; ``spec``: the specular sums
    of material shading (``rad`` then the sums of E·kd), None: Lambertian."""
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    radiance = rad[inverse] * (np.asarray(albedo, np.float32) / np.float32(np.pi))
    specular = None
    if spec is not None:
        specular = spec[inverse]
        radiance += specular
    fac = facing[inverse]
    blk = blocked[inverse]
    shadow = np.where(fac > 0, blk / np.maximum(fac, 1), 0.0).astype(np.float32)
    queries = int(fac.sum()) if all_cast else -1
    return DirectResult(radiance.astype(np.float32), shadow, fac.astype(np.int32), queries, specular)


class VoxelBackend(VisibilityBackend):
    """Shadow rays by paper 000's voxel arrays (see the module doc for what is built and the costs).

    Parameters
    ----------
    settings : a :class:`usdml.settings.UsdmlSettings` (None: the table's defaults); the backend reads its
        ``voxel_*`` fields, ``direction_step`` and ``fully_dynamic`` (:data:`usdml.params.PARAMS` says what
        each means; 0 for ``voxel_max_skip`` / ``voxel_memory_limit``: automatic, ``MAX_SKIP`` or
        ``CONSERVATIVE_MAX_SKIP`` with the conservative mapping, 80 % of the available memory)
    **values : those fields by name, over ``settings`` (``voxel_resolution=32, direction_step=10.0``)
    device : Warp device, ``cpu`` or ``cuda``
    cache : a :class:`usdml.cache.Cache`, a folder, or None for the default folder; ``False``: no cache
    native_isa, workers : the compiled kernel's instruction set (``usdml.native.ISAS``) and CPU threads
    report : called with one line before anything is built (cost of each array), default: log.info
    progress : ``progress(done, total, label, unit)`` while building (label ``voxel array (<what>)``,
        unit ``directions``)

    Built from settings by the default ``from_settings``. Declares every optional capability
    (:mod:`usdml.visibility.base`): ``SHADE_DIRECT`` (:meth:`shade_direct`, Alg. 3 in one kernel),
    ``HIT_DISTANCES`` (in voxels of the array hit), ``STATS`` and ``MEMORY_ESTIMATE``
    (:mod:`usdml.visibility.voxel.budget`).

    After each :meth:`update`, ``built`` lists the arrays it built or loaded (empty when nothing
    changed that arrays hold: moving lights or a moving camera cost nothing) and ``stats`` holds the
    counts, bytes and ``dynamic_seconds`` of the last per-frame rebuild.
    """

    name = "voxel"
    summary = "per-direction voxel arrays, shared by a prototype's instances (paper 000)"
    capabilities = frozenset({SHADE_DIRECT, HIT_DISTANCES, STATS, MEMORY_ESTIMATE, BAKE, REFINE})
    reads_settings = True
    refine_levels = len(THICK)

    def __init__(self, settings=None, *, device: str = "cpu", cache=None, native_isa: str = "auto",
                 workers: int | None = None, report: Callable[[str], None] | None = None,
                 progress: Callable[[int, int, str, str], None] | None = None, **values) -> None:
        # every knob is a setting (the parameter table's default, checked there), ``values`` by field name
        s = settings_with(settings, values)
        self.resolution, self.step = int(s.voxel_resolution), float(s.direction_step)
        self.rebuild, self.mapping, self.fully_dynamic = s.voxel_rebuild, s.voxel_mapping, s.fully_dynamic
        self.device = device
        self.core, self.frame_core = float(s.voxel_core), float(s.voxel_frame_core)
        cpu_kernel = s.voxel_cpu_kernel
        # the compiled CPU kernel (usdml.visibility.voxel.native) unless Warp is asked for or it was not
        # built; a GPU always runs Warp. ``native_isa``: its instruction set (usdml.native.ISAS; narrower
        # ones are for measuring and tests)
        self.native = False
        if str(device).startswith("cpu") and cpu_kernel != "warp":
            from usdml.visibility.voxel import native as voxel_native
            if voxel_native.library() is not None:
                self.native = True
            elif cpu_kernel == "native":
                raise UsdmlError(f"--voxel-cpu-kernel native: {voxel_native.describe()}")
        self.native_isa = native_isa
        self._native = None
        self.cache = None if cache is False else (cache if isinstance(cache, Cache) else Cache(cache))
        # 0 = automatic: 80 % of the available memory, the mapping's longest skip
        self.memory_limit = int(s.voxel_memory_limit * 2**30) or None
        self.normal_offset, self.skip, self.slab = float(s.voxel_normal_offset), float(s.voxel_skip), float(s.voxel_slab)
        self.max_skip = float(s.voxel_max_skip or (MAX_SKIP if self.mapping == "point" else CONSERVATIVE_MAX_SKIP))
        self.end_skip, self.segment = float(s.voxel_end_skip), int(s.voxel_segment)
        self.workers = cpu_workers("cpu", workers)
        self.report = report or (lambda line: log.info(line))
        self.progress = progress
        self.bins = DirectionBins.make(self.step)
        self.layout = RowLayout.make(self.resolution)
        self._static: _Group | None = None
        self._deforming: _Group | None = None
        self._protos: dict[str, VoxelArray] = {}      # prototype geometry hash -> array
        self._gpu: dict = {}
        self._ends: EmitterEnds | None = None     # the snapshot's triangle lights (usdml.visibility.emitter_ends)
        self._scene = None
        self.stats: dict = {"builds": 0, "loaded": 0, "build_seconds": 0.0, "bytes": 0, "arrays": 0,
                            "dynamic_rebuilds": 0, "dynamic_seconds": 0.0}
        self.built: list[str] = []
        self._reported: set[str] = set()

    @classmethod
    def bake_skip(cls, settings) -> tuple[str, dict] | None:
        """A fully dynamic scene's array is rebuilt every frame: nothing to cache."""
        if not settings.fully_dynamic:
            return None
        return ("fully dynamic (usdml:voxel:fullyDynamic or --fully-dynamic): its voxel array is rebuilt every frame "
                "and not cached; nothing to bake (--no-fully-dynamic bakes the static and prototype arrays)",
                {"fully_dynamic": True, "arrays": []})

    def baked(self) -> tuple[dict, list[str], str]:
        """The static and prototype arrays (``usdml bake``): cached, and where; deforming ones are not."""
        arrays = [baked_entry(self, "voxel", a, samples=a.samples) for a in self.arrays]
        lines = [baked_line(a, f"{a['bytes'] / 2**20:.1f} MiB", "deforming: rebuilt per frame, not cached")
                 for a in arrays]
        fields = {"voxel_resolution": self.resolution, "direction_step": self.step, "directions": self.bins.count,
                  "arrays": arrays, "built": self.stats["builds"], "loaded": self.stats["loaded"]}
        return fields, lines, (f"{len(arrays)} array(s) at {self.resolution}^3 / {self.step:g} deg "
                               f"({self.bins.count} directions)")

    @classmethod
    def memory_estimate(cls, snapshot: Snapshot, settings) -> dict:
        """The arrays ``snapshot`` needs at ``settings`` and their bytes (``usdml info``'s ``voxelMemory``)."""
        return memory_estimate(snapshot, settings)

    @classmethod
    def memory_line(cls, estimate: dict) -> str:
        return memory_line(estimate)

    @classmethod
    def cpu_path(cls) -> str:
        """The CPU path queries take at ``--voxel-cpu-kernel auto`` (:func:`voxel_native.describe`)."""
        from usdml.visibility.voxel import native as voxel_native
        return voxel_native.describe()

    def describe(self) -> dict:
        """Resolution, directions, arrays (bytes, loaded from the cache, build seconds) and how the
        per-frame array is rebuilt, for ``usdml bench`` / ``usdml compare``."""
        return {"voxel_resolution": self.resolution, "direction_step": self.step, "bytes": int(self.stats["bytes"]),
                "directions": self.bins.count, "arrays": self.stats["arrays"],
                "arrays_loaded_from_cache": self.stats["loaded"], "array_build_seconds": self.stats["build_seconds"],
                "fully_dynamic": self.fully_dynamic, "voxel_rebuild": self.rebuild, "cpu_kernel": self.kernel_name}

    @property
    def kernel_name(self) -> str:
        """Which kernels answer queries: ``warp``, ``native-avx512``, ``native-avx2`` or ``native-scalar``."""
        if not self.native:
            return "warp"
        from usdml.native import kernel_label
        from usdml.visibility.voxel.native import isa_width
        return kernel_label(isa_width(self.native_isa))

    # ------------------------------------------------------------------ building

    def _array(self, points, triangles, source: str, cacheable: bool = True, trim: bool = False,
               per_frame: bool = False, out=None, base: int = 0) -> VoxelArray:
        """Build (or load) the array of ``(points, triangles)``; ``trim``: a world-space array (trimmed
        box stretched to a cube); ``per_frame``: the per-frame array, rebuilt by ``self.rebuild``
        (into ``out`` from word ``base`` when given)."""
        def prog(done, total):
            if self.progress:
                self.progress(done, total, f"voxel array ({source})", "directions")
        bounds, to_array = None, np.eye(4)
        if trim:
            lo, hi, outside = core_bounds(points, triangles)
            if outside and source not in self._reported:
                self._reported.add(source)
                self.report(f"voxel array of the {source} covers {np.round(lo, 2).tolist()} .. "
                            f"{np.round(hi, 2).tolist()}; {outside} of {len(triangles)} triangles reach outside "
                            "it and shadow only within it")
            to_array = normalizing_transform(lo, hi)
            points = np.asarray(points, np.float64) @ to_array[:3, :3].T + to_array[:3, 3]
            bounds = (to_array[:3, :3] @ lo + to_array[:3, 3], to_array[:3, :3] @ hi + to_array[:3, 3])
        if per_frame:
            t0 = time.perf_counter()
            if self.rebuild == "rotate":
                arr = rotate_array(points, triangles, self.resolution, self.step, mapping=self.mapping,
                                   device=self.device, workers=self.workers, bounds=bounds,
                                   out=out, base=base, progress=prog, source=source, native=self.native)
            else:
                arr = build_array(points, triangles, self.resolution, self.step, device=self.device,
                                  workers=self.workers, progress=prog, source=source, bounds=bounds,
                                  core=self.frame_core, out=out, base=base)
            self.stats["dynamic_rebuilds"] += 1
            self.stats["dynamic_seconds"] = time.perf_counter() - t0
        else:
            arr = cached_array(points, triangles, self.resolution, self.step, self.cache if cacheable else None,
                               device=self.device, progress=prog, source=source, bounds=bounds, core=self.core)
        arr.to_array = to_array
        self.built.append(source)
        if arr.cached:
            self.stats["loaded"] += 1
        else:
            self.stats["builds"] += 1
            self.stats["build_seconds"] += arr.build_seconds
        return arr

    @property
    def _frame_source(self) -> str:
        """What the per-frame array holds, for messages and ``built``."""
        return "dynamic scene" if self.fully_dynamic else "deforming geometry"

    def plan(self, snapshot: Snapshot) -> list[tuple[str, tuple]]:
        """The arrays ``snapshot`` needs (:func:`usdml.visibility.voxel.budget.array_roles`)."""
        return array_roles(snapshot, self.fully_dynamic)

    def check_memory(self, count: int, quiet: bool = False) -> int:
        """Say what ``count`` arrays cost and refuse (``UsdmlError``) when they would not fit;
        ``quiet``: a per-frame rebuild into memory already held (nothing said or checked)."""
        each = array_cost(self.resolution, self.step)
        total = each * count
        if quiet:
            return total
        limit = self.memory_limit if self.memory_limit is not None else int(0.8 * available_memory())
        self.report(f"voxel arrays: {count} x {each / 2**20:.1f} MiB = {total / 2**30:.2f} GiB "
                    f"({self.resolution}^3 voxels, {self.bins.count} directions at {self.step:g} deg)")
        if total > limit:
            raise UsdmlError(
                f"voxel arrays need {total / 2**30:.2f} GiB ({count} x {each / 2**20:.1f} MiB at "
                f"{self.resolution}^3 / {self.step:g} deg) but only {limit / 2**30:.2f} GiB is available; "
                f"lower --voxel-resolution or raise --direction-step")
        return total

    def update(self, snapshot: Snapshot, changes: Changes | None = None) -> None:
        """Build what ``changes`` says changed: the static array and prototype arrays only when their
        geometry changed (else kept, or loaded from the cache), the per-frame array only when one of
        its meshes or instances changed (Alg. 5 into its slot of the assembled words: nothing is
        reallocated or copied)."""
        plan = self.plan(snapshot)
        self._ends = EmitterEnds.of(snapshot.lights)
        roles = dict(plan)
        static = roles.get("static")
        per_frame = roles.get("deforming", roles.get("dynamic"))
        if per_frame is not None and self.rebuild == "rotate":
            if self.resolution > MAX_RESOLUTION:
                raise UsdmlError(f"--voxel-rebuild rotate (Alg. 5) handles up to {MAX_RESOLUTION}^3 voxels, got "
                                 f"{self.resolution}^3; lower --voxel-resolution or use --voxel-rebuild geometry")
        moving = [] if self.fully_dynamic else \
            [p for p in snapshot.prototypes if p.animated and not p.deforming and p.triangle_count]
        self.built = []
        need_static = static is not None and members_changed(
            self._static and self._static.members, static, changes, lambda path: changes.static)
        proto_hashes = {p.path: p.geometry_hash() for p in moving}
        new_protos = {h for h in proto_hashes.values() if h not in self._protos}
        need_frame = per_frame is not None and members_changed(
            self._deforming and self._deforming.members, per_frame, changes,
            lambda path: path in changes.deforming or changes.static)
        if (need_static or new_protos) and self._deforming is not None and self._deforming.array is not None \
                and self._deforming.array.words.size == 0:
            # rebuilt in place on a GPU, its words live only there: re-assembling needs it built anew
            need_frame = per_frame is not None
        building = int(need_static) + len(new_protos) + int(need_frame)
        if building:
            self.check_memory(len(plan), quiet=not (need_static or new_protos) and self._deforming is not None)
        if static is None:
            self._static = None
        elif need_static:
            pts, tris = world_geometry(snapshot, static)
            self._static = _Group(static, self._array(pts, tris, "static scene", trim=True) if len(tris) else None)
        for p in moving:
            h = proto_hashes[p.path]
            if h not in self._protos:
                pts, tris = p.merged()
                self._protos[h] = self._array(pts, tris, f"prototype {p.name}")
        self._protos = {h: a for h, a in self._protos.items() if h in set(proto_hashes.values())}
        source = self._frame_source
        in_place = False
        if per_frame is None:
            self._deforming = None
        elif need_frame:
            pts, tris = world_geometry(snapshot, per_frame)
            slot = self._gpu.get("frame_slot")
            # in place when only the per-frame array changes and it already has its slot
            in_place = (slot is not None and not need_static and not new_protos and len(tris) > 0
                        and self._deforming is not None and self._deforming.array is not None)
            arr = None
            if len(tris):
                arr = self._array(pts, tris, source, cacheable=False, trim=True, per_frame=True,
                                  out=self._gpu["words"] if in_place else None, base=slot or 0)
            self._deforming = _Group(per_frame, arr)
        self._assemble(snapshot, moving, proto_hashes, rebuild_words=(bool(building) and not in_place) or not self._gpu)

    def per_frame_rebuild_seconds(self, snapshot: Snapshot, repeats: int = 3) -> dict:
        """Seconds to rebuild this frame's per-frame array by Alg. 5 (``rebuild_seconds``) and by Alg. 1
        from the geometry (``full_rebuild_seconds``), each in place as a render does (the median of
        ``repeats`` rebuilds, taken in turn), and their ratio; the array is left as ``self.rebuild``
        builds it. Empty when nothing is rebuilt per frame. Call after :meth:`update` for ``snapshot``."""
        if self._deforming is None or self._deforming.array is None or "frame_slot" not in self._gpu:
            return {}
        pts, tris = world_geometry(snapshot, self._deforming.members)
        source = self._frame_source
        seconds = {m: [] for m in REBUILDS}
        keep = self.rebuild
        try:
            for _ in range(max(1, int(repeats))):
                for method in [m for m in REBUILDS if m != keep] + [keep]:
                    self.rebuild = method
                    arr = self._array(pts, tris, source, cacheable=False, trim=True, per_frame=True,
                                      out=self._gpu["words"], base=self._gpu["frame_slot"])
                    seconds[method].append(self.stats["dynamic_seconds"])
        finally:
            self.rebuild = keep
        self._deforming = _Group(self._deforming.members, arr)
        rotate, geometry = float(np.median(seconds["rotate"])), float(np.median(seconds["geometry"]))
        return {"rebuild_seconds": rotate, "full_rebuild_seconds": geometry,
                "rebuild_speedup": geometry / max(rotate, 1e-12), "rebuild_repeats": len(seconds["rotate"]),
                "mapping": self.mapping, "occupied_voxels": int(arr.occupied) if keep == "rotate" else None}

    def _assemble(self, snapshot: Snapshot, moving, proto_hashes, rebuild_words: bool) -> None:
        """Concatenate the arrays for the kernels (when ``rebuild_words`` or their number changed) and
        rebuild the instance table and its BVH, the arrays' cubes and the ray rule's scales."""
        arrays, world_ids, proto_index = self._array_order()
        if rebuild_words or self._gpu.get("n_arrays") != len(arrays):
            self._gpu = self._upload_words(arrays)
            self.stats["bytes"] = int(sum(a.words.size for a in arrays) * 4)
            self.stats["arrays"] = len(arrays)
        g = self._gpu
        wp = warp_module()
        dev = wp.get_device(self.device)
        # cubes move with the per-frame array: refreshed every frame (a few floats per array)
        g["center"] = wp.array(np.array([a.center for a in arrays] or [[0, 0, 0]], np.float32), dtype=wp.vec3, device=dev)
        g["half"] = wp.array(np.array([a.half for a in arrays] or [1.0], np.float32), dtype=float, device=dev)
        table = self._instance_table(arrays, world_ids, moving, proto_index, proto_hashes)
        self._upload_instances(g, *table)
        g["static"] = world_ids[0] if world_ids else -1
        if self.native:
            from usdml.visibility.voxel.native import NativeScene
            # the world-space arrays go to the kernel as such, not as identity-placed instances
            skip = max(0, len(world_ids) - 1)
            self._native = NativeScene(g["words_np"], arrays, self.layout, self.bins, world_ids,
                                       *(x[skip:] for x in table), isa=self.native_isa)
        g["static_inv"] = wp.mat44(*(arrays[world_ids[0]].to_array if world_ids else np.eye(4)).astype(np.float32).ravel())
        self.reference_voxel = _reference_voxel(arrays, world_ids)
        self._scene = scene_sphere(snapshot)
        self.arrays = arrays

    def _array_order(self) -> tuple[list[VoxelArray], list[int], dict[str, int]]:
        """Every array in the order the kernels see them: the world-space ones (static, then
        per-frame; their indices) first, then one per prototype hash (hash -> index)."""
        arrays: list[VoxelArray] = []
        world_ids = []
        for g in (self._static, self._deforming):
            if g is not None and g.array is not None:
                world_ids.append(len(arrays))
                arrays.append(g.array)
        proto_index = {}
        for h, a in self._protos.items():
            proto_index[h] = len(arrays)
            arrays.append(a)
        return arrays, world_ids, proto_index

    def _upload_words(self, arrays: list[VoxelArray]) -> dict:
        """The kernels' buffers: every array's words in one Warp array (on CPU the arrays become
        views into it) with each array's table row, and the shared row layout and direction bins."""
        wp = warp_module()
        dev = wp.get_device(self.device)
        total = sum(a.words.size for a in arrays)
        if total >= 2 ** 31:
            raise UsdmlError(f"voxel arrays hold {total} words, more than one Warp array can index (2^31); "
                             "lower --voxel-resolution or raise --direction-step")
        if len(arrays) == 1 and arrays[0].words.dtype == np.uint32 and arrays[0].words.flags.c_contiguous:
            words = arrays[0].words     # one array (a static scene alone): used as it is, not copied
        else:
            words = np.concatenate([a.words for a in arrays]) if arrays else np.zeros(1, np.uint32)
        bases = np.concatenate([[0], np.cumsum([a.words.size for a in arrays])[:-1]]).astype(np.int64) \
            if arrays else np.zeros(0, np.int64)
        arr_int = np.zeros((max(1, len(arrays)), 4), np.int32)
        for i, a in enumerate(arrays):
            arr_int[i] = (a.resolution, self.layout.words, bases[i], 0)
            if dev.is_cpu:
                # the assembled words are the only copy (per-frame rebuilds write into them)
                a.words = words[bases[i]:bases[i] + a.words.size]
        g = {
            "words_np": words,
            "words": wp.array(words, dtype=wp.uint32, device=dev, copy=not dev.is_cpu),
            "int": wp.array(arr_int, dtype=wp.int32, device=dev),
            "w0": wp.array(self.layout.w0, dtype=wp.int32, device=dev),
            "nw": wp.array(self.layout.nw, dtype=wp.int32, device=dev),
            "off": wp.array(self.layout.offset, dtype=wp.int32, device=dev),
            "frames": wp.array(self.bins.frames, dtype=wp.mat33, device=dev),
            "ring_count": wp.array(self.bins.ring_count, dtype=wp.int32, device=dev),
            "ring_start": wp.array(self.bins.ring_start, dtype=wp.int32, device=dev),
            "n_arrays": len(arrays),
        }
        if self._deforming is not None and self._deforming.array is not None:
            g["frame_slot"] = int(bases[[a is self._deforming.array for a in arrays].index(True)])
        return g

    @staticmethod
    def _instance_table(arrays: list[VoxelArray], world_ids: list[int], moving, proto_index: dict[str, int],
                        proto_hashes: dict[str, str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Alg. 4's instances: ``(K, 4, 4)`` float32 world -> array space, ``(K,)`` int32 array index and
        ``(K, 3)`` float32 world box corners. The static and per-frame arrays are both world space;
        with both, the per-frame one is an identity-placed "instance" so a query still tests both."""
        inv, ids, lo, hi = [], [], [], []
        for a_id in world_ids[1:]:
            a = arrays[a_id]
            inv.append(a.to_array)
            ids.append(a_id)
            back = np.linalg.inv(a.to_array)
            corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * a.half + a.center
            world = corners @ back[:3, :3].T + back[:3, 3]
            lo.append(world.min(0))
            hi.append(world.max(0))
        for p in moving:
            a_id = proto_index[proto_hashes[p.path]]
            a = arrays[a_id]
            xf = np.asarray(p.xforms, np.float64).reshape(-1, 4, 4)
            # world = M @ local (column vectors)
            c_world = xf[:, :3, :3] @ a.center + xf[:, :3, 3]
            scale = np.linalg.norm(xf[:, :3, :3], axis=1).max(axis=1)
            r_world = a.half * scale
            inv.append(np.linalg.inv(xf))
            ids.append(np.full(len(xf), a_id))
            lo.append(c_world - r_world[:, None])
            hi.append(c_world + r_world[:, None])
        if not inv:
            return (np.zeros((0, 4, 4), np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32),
                    np.zeros((0, 3), np.float32))
        return (np.concatenate([np.asarray(m).reshape(-1, 4, 4) for m in inv]).astype(np.float32),
                np.concatenate([np.atleast_1d(i) for i in ids]).astype(np.int32),
                np.concatenate([np.asarray(x).reshape(-1, 3) for x in lo]).astype(np.float32),
                np.concatenate([np.asarray(x).reshape(-1, 3) for x in hi]).astype(np.float32))

    def _upload_instances(self, g: dict, inv: np.ndarray, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        """The instance table into the kernels' buffers ``g``, with a Warp BVH over the world boxes."""
        wp = warp_module()
        dev = wp.get_device(self.device)
        if len(ids):
            g["inst_inv"] = wp.array(inv, dtype=wp.mat44, device=dev)
            g["inst_array"] = wp.array(ids, dtype=wp.int32, device=dev)
            g["lowers"] = wp.array(lo, dtype=wp.vec3, device=dev)
            g["uppers"] = wp.array(hi, dtype=wp.vec3, device=dev)
            g["bvh"] = wp.Bvh(g["lowers"], g["uppers"])
            g["bvh_id"] = g["bvh"].id
        else:
            g["inst_inv"] = wp.zeros(1, dtype=wp.mat44, device=dev)
            g["inst_array"] = wp.zeros(1, dtype=wp.int32, device=dev)
            g["bvh"] = None
            g["bvh_id"] = wp.uint64(0)
        g["n_inst"] = len(ids)

    # ------------------------------------------------------------------ queries

    def _scene_struct(self):
        """The arrays as the kernels' ``VoxelScene``."""
        g, k = self._gpu, voxel_kernels()
        vs = k.VoxelScene()
        vs.words, vs.arr_center, vs.arr_half, vs.arr_int = g["words"], g["center"], g["half"], g["int"]
        vs.row_w0, vs.row_nw, vs.row_off, vs.frames = g["w0"], g["nw"], g["off"], g["frames"]
        vs.d_theta, vs.ring_count, vs.ring_start = float(self.bins.d_theta), g["ring_count"], g["ring_start"]
        vs.static_array, vs.static_inv = int(g["static"]), g["static_inv"]
        vs.bvh, vs.n_inst, vs.inst_inv, vs.inst_array = g["bvh_id"], int(g["n_inst"]), g["inst_inv"], g["inst_array"]
        return vs

    def _rule_values(self) -> dict:
        """The ray rule's values (``kernels.voxel.RayRule``'s fields)."""
        c, r = self._scene
        # a distant ray ends its distance from the scene's centre plus the scene's diameter away
        # (per ray, in the kernel: a reduction over millions of origins cost a quarter of a query)
        return dict(offset=float(self.normal_offset * self.reference_voxel), skip=self.skip, slab=self.slab,
                    max_skip=self.max_skip, end_skip=self.end_skip, far=2.0 * r + 1.0,
                    far_center=np.asarray(c, np.float32), seg=self.segment)

    def _native_rule(self):
        """The compiled kernel's ray rule."""
        from usdml.visibility.voxel.native import NativeScene
        return NativeScene.rule(**self._rule_values())

    def _ray_rule(self):
        """The kernels' ``RayRule``."""
        v = self._rule_values()
        rule = voxel_kernels().RayRule()
        rule.offset, rule.skip, rule.slab, rule.max_skip = v["offset"], v["skip"], v["slab"], v["max_skip"]
        rule.end_skip, rule.far, rule.seg = v["end_skip"], v["far"], v["seg"]
        rule.far_center = warp_module().vec3(*v["far_center"])
        return rule

    def _split(self, n: int, launch: Callable[[int, int], None], bands_per_worker: int = 8) -> None:
        """Run ``launch(first, count)`` over ``n`` items: one launch on a GPU, ``bands_per_worker`` bands
        per thread on CPU (a Warp launch's first band alone first: it loads the module; the compiled
        kernel has nothing to load, and its bands all start at once)."""
        wp = warp_module()
        dev = wp.get_device(self.device)
        if n == 0:
            return
        if not dev.is_cpu:
            launch(0, n)
            wp.synchronize_device(dev)
            return
        run_bands(n, launch, self.workers, bands_per_worker, first_on_caller=self._native is None)

    @property
    def words(self):
        """Every array's words as the kernels read them, one Warp ``uint32`` array (None before
        :meth:`update`): a per-frame rebuild writes into it in place."""
        return self._gpu.get("words")

    @property
    def host_words(self) -> np.ndarray | None:
        """The same words on the host, ``(W,) uint32`` (on CPU the very memory the kernels read)."""
        return self._gpu.get("words_np")

    @property
    def emitter_offset(self) -> float:
        """A ray's end on a mesh light's triangle is moved off it by the start's offset, ``normal_offset`` voxels."""
        return self.normal_offset * self.reference_voxel if self._gpu else 0.0

    def _ended(self, targets, distant):
        """``targets`` with those on a mesh light's triangle moved off its surface (usdml.visibility.emitter_ends) by
        the start's offset: ``normal_offset`` voxels."""
        if self._ends is None:
            return targets
        return self._ends.lift(targets, distant, self.normal_offset * self.reference_voxel)

    def hit_distances(self, origins, targets, *, normals=None, distant=None, want_distance: bool = True) -> np.ndarray:
        """Distance in voxels from each ray's (offset, skipped) start to the first occupied voxel; -1: free."""
        return self._hits(origins, self._ended(targets, distant), normals, distant, want_distance)

    def _hits(self, origins, targets, normals, distant, want_distance: bool) -> np.ndarray:
        """:meth:`hit_distances` of targets as given."""
        if not self._gpu:
            raise RuntimeError("VoxelBackend.update() must be called before queries")
        if self._native is not None:
            return self._native_hits(origins, targets, normals, distant, want_distance)
        wp = warp_module()
        k = voxel_kernels()
        dev = wp.get_device(self.device)
        # float32 once, and on CPU wrapped rather than copied again
        origins = np.ascontiguousarray(as_vectors(origins, "origins", dtype=np.float32))
        n = origins.shape[0]
        targets = np.ascontiguousarray(as_vectors(targets, "targets", n, dtype=np.float32))
        normals = np.zeros((n, 3), np.float32) if normals is None else \
            np.ascontiguousarray(as_vectors(normals, "normals", n, dtype=np.float32))
        distant = np.zeros(n, np.int32) if distant is None else as_flags(distant, "distant", n).astype(np.int32)
        if n == 0 or self._gpu["n_arrays"] == 0:
            return np.full(n, -1.0, np.float32)
        out = wp.zeros(n, dtype=float, device=dev)
        wrap = dict(device=dev, copy=not dev.is_cpu)
        o = wp.array(origins, dtype=wp.vec3, **wrap)
        t = wp.array(targets, dtype=wp.vec3, **wrap)
        nm = wp.array(normals, dtype=wp.vec3, **wrap)
        di = wp.array(distant, dtype=wp.int32, **wrap)
        rule, vs = self._ray_rule(), self._scene_struct()

        def launch(first, count):
            wp.launch(k.query_segments, dim=count, device=dev,
                      inputs=[o, t, nm, di, first, rule, int(want_distance), vs, out])
        self._split(n, launch)
        return out.numpy()

    def _native_hits(self, origins, targets, normals, distant, want_distance: bool, blocked: bool = False) -> np.ndarray:
        """:meth:`hit_distances` by the compiled kernel, which reads float64 inputs and bool flags as they
        are (converting 7 M float64 rays to float32 first cost about a third of the city's bench); with
        ``blocked``, :meth:`occluded`'s flags, written by the kernel as they are."""
        origins, targets, normals, distant = self._native_inputs(origins, targets, normals, distant)
        n = len(origins)
        res = np.empty(n, bool if blocked else np.float32)
        if n == 0 or self._gpu["n_arrays"] == 0:
            res[:] = False if blocked else -1.0
            return res
        rule = self._native_rule()
        self._split(n, lambda first, count: self._native.query(rule, first, count, origins, targets, normals, distant,
                                                               want_distance, res), bands_per_worker=2)
        return res

    @staticmethod
    def _native_inputs(origins, targets, normals, distant) -> tuple:
        """The compiled kernel's query inputs, checked and C-contiguous but read in place (float32 or
        float64, bool or int32 flags): no conversion pass over them; zero normals, no distant flags when
        not given."""
        origins = np.ascontiguousarray(as_vectors(origins, "origins", dtype=None))
        n = origins.shape[0]
        targets = np.ascontiguousarray(as_vectors(targets, "targets", n, dtype=None))
        normals = np.zeros((n, 3), np.float32) if normals is None else \
            np.ascontiguousarray(as_vectors(normals, "normals", n, dtype=None))
        distant = np.zeros(n, bool) if distant is None else np.ascontiguousarray(as_flags(distant, "distant", n))
        return origins, targets, normals, distant

    def _native_refine(self, origins, targets, normals, distant, thick) -> tuple[np.ndarray, np.ndarray]:
        """``REFINE``'s thick-ray rule by the compiled kernel (``vq_query_refine``): ``(blocked, uncertain)``,
        two ``(N,) bool``: :meth:`occluded`'s answers (the very same) and whether each is uncertain: the
        rays through the rows ``thick`` voxels to either side of the query's own (along its direction bin's
        two grid axes, over the same voxels, in every array it visits) and it do not all answer alike; with
        several widths (at most 4), at any of them, all looked up in one pass. Arguments as :meth:`occluded`."""
        origins, targets, normals, distant = self._native_inputs(origins, targets, normals, distant)
        n = len(origins)
        code = np.zeros(n, np.uint8)
        if n and self._gpu["n_arrays"]:
            rule = self._native_rule()
            # the cost per ray varies more than a plain query's (a ray ends when all five are blocked)
            self._split(n, lambda first, count: self._native.query_refine(rule, first, count, origins, targets,
                                                                          normals, distant, thick, code),
                        bands_per_worker=4)
        return (code & 1) != 0, (code & 2) != 0

    def occluded(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        targets = self._ended(targets, distant)
        if self._native is not None:      # set by update() (hit_distances says when it was not called)
            return self._native_hits(origins, targets, normals, distant, False, blocked=True)
        return self._hits(origins, targets, normals, distant, False) >= 0.0

    def occluded_uncertain(self, origins, targets, *, normals=None, distant=None, level: int = 1):
        """``REFINE``: the thick-ray rule (:func:`usdml.visibility.refine.thick_ray`) at each width of ``THICK`` up
        to ``level``'s (a wider rule alone can step over a thin occluder a narrower one meets: the union keeps
        every level a superset of the one below)."""
        targets = self._ended(targets, distant)
        if self._native is not None:
            # every width up to the level's in one pass of the compiled kernel (a pass per width cost level 2
            # 0.70-0.76 exact rays a query on a tuning city, one pass 0.44-0.49)
            return self._native_refine(origins, targets, normals, distant, THICK[:min(max(level, 1), len(THICK))])
        from usdml.visibility.refine import thick_ray

        def rule(width):
            return thick_ray(self.occluded, origins, targets, normals, distant, width * self.reference_voxel)
        return widened(rule, level)

    def blind_reach(self, level: int) -> float:
        """``REFINE``: how far along a ray (world units) an occluder may go unseen: the offset, the longest
        skip, and ``BLIND[level - 1]`` voxels more (usdml.visibility.refine)."""
        extra = BLIND[min(max(level, 1), len(BLIND)) - 1]
        return (self.normal_offset + max(self.skip, self.max_skip) + extra) * self.reference_voxel

    def _light_struct(self, lights: Lights, meters_per_unit: float, min_distance: float):
        """The lights as the shading kernel's ``LightTable`` (the constants of
        :class:`usdml.scene.light_table.LightTable`; the compiled kernel's table on the native path), and
        whether every light casts shadows."""
        if self._native is not None:
            from usdml.visibility.voxel.native import compiled_lights
            distant = np.asarray(lights.type) == LightType.DISTANT
            ends = self._ended(lights.position, distant)        # rays to a mesh light's triangle: off its surface
            return (compiled_lights(lights, meters_per_unit, min_distance, None if ends is lights.position else ends),
                    bool(np.asarray(lights.shadow).all()))
        t = LightTable(lights, meters_per_unit, min_distance)
        flags = t.flags        # LightFlag bits, which the kernels name as the same constants
        wp, ks = warp_module(), _shading_kernels()
        dev = wp.get_device(self.device)
        lt = ks.LightTable()
        lt.pos = wp.array(lights.position.astype(np.float32), dtype=wp.vec3, device=dev)
        lt.axis = wp.array(lights.axis.astype(np.float32), dtype=wp.vec3, device=dev)
        lt.flags = wp.array(flags, dtype=wp.int32, device=dev)
        lt.cylinder_axis = wp.array(np.ascontiguousarray(t.cylinder_axis.T), dtype=wp.vec3, device=dev)
        lt.cone = wp.array(t.kernel_cone, dtype=wp.vec3, device=dev)
        lt.base = wp.array(t.base, dtype=wp.vec3, device=dev)
        lt.focus_rgb = wp.array(t.focus_rgb, dtype=wp.vec3, device=dev)
        lt.inv_m2, lt.min_d2 = float(t.inv_m2), float(t.min_d2)
        return lt, bool(t.casts.all())

    def shade_direct(self, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
                     progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
                     min_distance: float = 0.0, geometric: np.ndarray | None = None,
                     material: np.ndarray | None = None, *, plain: Callable[..., DirectResult]) -> DirectResult:
        """Alg. 3 in one kernel (``kernels.direct_shading.shade_tiles``): every pixel against every
        light with voxel shadow rays; the same shading as ``plain``
        (:func:`usdml.lighting.direct.shade_direct`), which shades what has no kernel to run (no points,
        no lights, nothing built; ``material`` rows without the compiled kernel: ``plain`` over :meth:`occluded`)."""
        n_p, n_l = len(points), len(lights)
        options = dict(meters_per_unit=meters_per_unit, min_distance=min_distance, geometric=geometric)
        if material is not None:
            options["material"] = material
        # rays to a mesh light's triangles end off its surface (self._ended): the Warp kernel ends them at the light
        triangles = self._native is None and self._ends is not None and \
            bool((np.asarray(lights.type) == LightType.TRIANGLE).any())
        if n_p == 0 or n_l == 0 or not self._gpu or (material is not None and self._native is None) or triangles:
            return plain(points, normals, albedo, lights, self.occluded if self._gpu else None, progress, **options)
        lt, all_cast = self._light_struct(lights, meters_per_unit, min_distance)
        pts = np.asarray(points, np.float32)
        if self._native is not None:
            return self._shade_native(pts, normals, albedo, geometric, lt, all_cast, progress, material)
        wp, ks = warp_module(), _shading_kernels()
        dev = wp.get_device(self.device)
        rad = wp.zeros(n_p, dtype=wp.vec3, device=dev)
        blocked = wp.zeros(n_p, dtype=wp.int32, device=dev)
        facing = wp.zeros(n_p, dtype=wp.int32, device=dev)
        rule, vs = self._ray_rule(), self._scene_struct()
        # tiles of spatially coherent points (Morton order of their cells): one light's rays from a
        # tile share bins and rows (kernels.direct_shading.shade_tiles); on a GPU one point per tile
        tile = SHADE_TILE if dev.is_cpu else 1
        order = morton_order(pts) if tile > 1 else np.arange(n_p)
        p_wp = wp.array(pts[order], dtype=wp.vec3, device=dev)
        n_wp = wp.array(np.asarray(normals, np.float32)[order], dtype=wp.vec3, device=dev)
        g_wp = n_wp if geometric is None else wp.array(np.asarray(geometric, np.float32)[order], dtype=wp.vec3,
                                                       device=dev)
        n_tiles = -(-n_p // tile)

        def launch(first_tile, count):
            wp.launch(ks.shade_tiles, dim=count, device=dev,
                      inputs=[p_wp, n_wp, g_wp, first_tile * tile, tile, lt, rule, vs, rad, blocked, facing])
            if progress is not None:
                progress(min(n_p, (first_tile + count) * tile) - first_tile * tile)
        self._split(n_tiles, launch)
        return _direct_result(order, rad.numpy(), blocked.numpy(), facing.numpy(), albedo, all_cast)

    def _shade_native(self, pts, normals, albedo, geometric, lt, all_cast: bool, progress, material=None):
        """:meth:`shade_direct` by the compiled kernel: the same tiles, over the thread pool; with ``material`` rows
        both lobes of the preview surface summed in the kernel (``kernels/include/brdf.h``)."""
        n_p = len(pts)
        order = morton_order(pts)
        p = np.ascontiguousarray(pts[order])
        nm = np.ascontiguousarray(np.asarray(normals, np.float32)[order])
        g = nm if geometric is None else np.ascontiguousarray(np.asarray(geometric, np.float32)[order])
        rad = np.zeros((n_p, 3), np.float32)
        blocked = np.zeros(n_p, np.int32)
        facing = np.zeros(n_p, np.int32)
        rows = spec = None
        if material is not None:
            rows = np.ascontiguousarray(np.asarray(material, np.float32)[order])
            spec = np.zeros((n_p, 3), np.float32)
        rule = self._native_rule()
        n_tiles = -(-n_p // SHADE_TILE)

        def launch(first_tile, count):
            self._native.shade(rule, lt, p, nm, g, first_tile, count, SHADE_TILE, rad, blocked, facing, rows, spec)
            if progress is not None:
                progress(min(n_p, (first_tile + count) * SHADE_TILE) - first_tile * SHADE_TILE)
        self._split(n_tiles, launch)
        return _direct_result(order, rad, blocked, facing, albedo, all_cast, spec)

    def shade_refined(self, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
                      progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
                      min_distance: float = 0.0, geometric: np.ndarray | None = None, *, level: int,
                      near: np.ndarray | None,
                      resolve: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> tuple[DirectResult, dict]:
        """:meth:`shade_direct` with ``REFINE`` at ``level`` in the fused compiled kernel (``vq_shade_refine``):
        every shadow query answered by the thick-ray rule at the widths ``THICK[:level]`` (uncertain at any,
        blocked as :meth:`occluded`), the certain ones shaded in the kernel but the free ones of points with
        ``near`` set ((P,) bool, or None: none). Those and the uncertain ones are handed, a band of tiles at a
        time, to ``resolve(point_index, light_index, kind) -> (K,) bool`` free (indices into ``points`` and
        ``lights``; kind 0 uncertain, 1 free at a near point; called from the thread pool, several bands at
        once): the light of each it answers free is added, the others counted blocked. Returns the result and
        ``{"uncertain": kind-0 entries, "near": kind-1 entries, "queries": shadow queries}``. Without the
        compiled kernel: NotImplementedError (the caller shades by :meth:`occluded`-style queries instead)."""
        if self._native is None:
            raise NotImplementedError("the fused refined shading needs the compiled voxel kernel")
        from usdml.visibility.voxel.native import ShadeList
        n_p, n_l = len(points), len(lights)
        stats = {"uncertain": 0, "near": 0, "queries": 0}
        rad = np.zeros((n_p, 3), np.float32)
        blocked = np.zeros(n_p, np.int32)
        facing = np.zeros(n_p, np.int32)
        if n_p == 0 or n_l == 0:
            return _direct_result(np.arange(n_p), rad, blocked, facing, albedo, True), stats
        lt, all_cast = self._light_struct(lights, meters_per_unit, min_distance)
        pts = np.asarray(points, np.float32)
        order = morton_order(pts)
        p = np.ascontiguousarray(pts[order])
        nm = np.ascontiguousarray(np.asarray(normals, np.float32)[order])
        g = nm if geometric is None else np.ascontiguousarray(np.asarray(geometric, np.float32)[order])
        near_u8 = None if near is None else np.ascontiguousarray(as_flags(near, "near", n_p)[order], np.uint8)
        widths = np.asarray(THICK[:max(int(level), 0)], np.float32)
        rule = self._native_rule()
        n_tiles = -(-n_p // SHADE_TILE)
        tile_pairs = SHADE_TILE * n_l
        lock = threading.Lock()

        def launch(first_tile, count):
            end = first_tile + count
            # a tile starts while the list holds all its pairs: at least one tile's, at most about 1 M entries
            # (4 M: the same seconds and 145 MiB more peak on unseen_city_1's budgeted 512 px frame)
            listing = ShadeList(max(tile_pairs, min(tile_pairs * count, LIST_ENTRIES)))
            kinds = np.zeros(2, np.int64)
            t = first_tile
            while t < end:
                listing.count = 0
                nxt = self._native.shade_refine(rule, lt, p, nm, g, t, end - t, SHADE_TILE, widths, near_u8, rad,
                                                blocked, facing, listing)
                pi, li, rgb, kind = listing.entries()
                if len(pi):
                    free = np.asarray(resolve(order[pi], li.copy(), kind.copy()), bool)
                    # each free entry's light added to its point, the others counted blocked (in C: four
                    # bincounts over the list cost a tenth of the refined frame)
                    self._native.list_apply(listing, free, rad, blocked)
                    near_n = int(np.count_nonzero(kind))
                    kinds += (len(kind) - near_n, near_n)
                t = nxt
            with lock:
                stats["uncertain"] += int(kinds[0])
                stats["near"] += int(kinds[1])
                stats["queries"] += listing.queries
            if progress is not None:
                progress(min(n_p, end * SHADE_TILE) - first_tile * SHADE_TILE)
        self._split(n_tiles, launch)
        return _direct_result(order, rad, blocked, facing, albedo, all_cast), stats

    def close(self) -> None:
        self._gpu = {}
        self._native = None
