"""The ``svo`` visibility backend: paper 003's sparse voxel octree and its restart traversal.

Trees
    * **static**: every mesh that does not deform and every prototype whose instances never move,
      flattened into world space: one tree, built once (or loaded from the cache).
    * **per frame**: deforming meshes and the instances of moving prototypes, flattened into world
      space and voxelized again on frames where one of them changed, member by member: one that did
      not change keeps its brick grid while the tree's grid stays (report ``dynamic_seconds``;
      ``usdml bench`` reports ``per_frame_rebuild_seconds``). Its grid is ``resolution`` voxels over
      its own geometry, or the static tree's lattice (same voxel size, voxel corners) where that is
      as fine, so that moving geometry is voxelized no coarser than the scene (a creature on a
      large ground gets voxels of its own size, not the ground's). Instances and their flattened
      copies voxelize to the same bits, in the static tree or in the per-frame one.

    A query walks the static tree, then the per-frame one; the first occupied voxel ends it. One
    tree (grid, voxelization, octree, cache) is :mod:`usdml.visibility.svo.tree`; the kernels are
    :mod:`usdml.kernels.svo.octree` (Warp: CPU fallback and CUDA) and ``kernels/svo/svoq.c`` (the compiled CPU
    traversal, :mod:`usdml.visibility.svo.native`).

Resolution
    ``resolution`` voxels per axis of the static tree (a power of two); 0 picks the paper's: 128³
    for a room (its Cornell box), 256³ for a large scene (its Sponza): 128 when the scene's bounds
    are at most ``ROOM_METERS`` across (metres by the stage's metersPerUnit), else 256.

Leaving the surface and shrinking the segment (Fig. 3, line 2) and its cost
    Both ends of a shadow segment lie in occupied voxels (the shading point's own surface; a VPL's
    surface, or a light's fixture). Paper 003 shrinks the segment by an epsilon; with conservative
    voxels a surface is one to two voxels thick, so here, as for the voxel arrays: the ray starts
    ``normal_offset`` voxels off the surface along the normal turned toward the light, ignores its
    first ``skip`` voxels, or until it is ``slab`` voxels above the tangent plane (``slab / sin β``,
    at most ``max_skip``), and ignores its last ``end_skip`` voxels. The cost: occluders closer than
    about ``normal_offset + slab`` voxels to the shading point (contact shadows) or ``end_skip``
    voxels to the light do not shadow; ``usdml compare`` splits the error into near and far field.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from usdml.cache import Cache
from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, run_bands
from usdml.scene import Changes, Snapshot, world_geometry
from usdml.visibility.base import (BAKE, HIT_DISTANCES, MEMORY_ESTIMATE, REFINE, STATS, VisibilityBackend, as_flags,
                                   as_vectors, baked_entry, baked_line, members_changed, scene_sphere, settings_with,
                                   static_members)
from usdml.visibility.emitter_ends import EmitterEnds
from usdml.visibility.svo.tree import (SvoTree, aligned_grid, cached_tree, cube_grid,
                                       svo_bounds, svo_kernels, top_level, top_table, tree_from_masks,
                                       voxelize_bricks)
from usdml.visibility.voxel.array import warp_module

log = logging.getLogger("usdml")

__all__ = ["SvoBackend", "ROOM_METERS", "auto_resolution", "tree_members"]

#: a scene at most this many metres across is a room (paper 003: 128³), larger ones get 256³
ROOM_METERS = 20.0
#: most bytes of per-member brick grids the per-frame tree keeps (beyond it every member is voxelized
#: again each frame something moved): 64 grids at 128³, 8 at 256³
MEMBER_CACHE_BYTES = 16 * 2**20
#: leaving the surface, in voxels of the static tree (module doc)
NORMAL_OFFSET, SKIP, SLAB, MAX_SKIP, END_SKIP = 1.0, 1.0, 1.0, 2.0, 1.0


def auto_resolution(snapshot: Snapshot) -> int:
    """The paper's resolution for ``snapshot`` (module doc, "Resolution")."""
    bounds = snapshot.world_bounds()
    if bounds is None:
        return 128
    span = float(np.max(np.asarray(bounds[1], np.float64) - np.asarray(bounds[0], np.float64)))
    return 128 if span * snapshot.meters_per_unit <= ROOM_METERS else 256


def _frame_members_changed(before, members: tuple, changes: Changes | None) -> bool:
    """:func:`members_changed` for per-frame members: a mesh changed when it deformed (or the static
    part did)."""
    return members_changed(before, members, changes, lambda path: path in changes.deforming or changes.static)


def _member_changed(member: tuple, changes: Changes | None) -> bool:
    """Whether one per-frame ``member`` (``("mesh" | "proto", path)``) moved or deformed by ``changes``."""
    return _frame_members_changed((member,), (member,), changes)


def tree_members(snapshot: Snapshot) -> tuple[tuple, tuple]:
    """``(static, per-frame)`` members (``("mesh" | "proto", path)``) of ``snapshot``'s trees."""
    static = static_members(snapshot)
    frame = tuple([("mesh", m.path) for m in snapshot.meshes if m.deforming]
                  + [("proto", p.path) for p in snapshot.prototypes
                     if (p.animated or p.deforming) and p.triangle_count])
    return static, frame


class SvoBackend(VisibilityBackend):
    """Shadow rays through a sparse voxel octree (paper 003; module doc).

    Parameters
    ----------
    settings : a :class:`usdml.settings.UsdmlSettings` (None: the table's defaults); the backend reads
        ``svo_resolution`` (0: automatic, module doc) and ``svo_cpu_kernel``
    **values : those fields by name, over ``settings`` (``svo_resolution=64``)
    device : Warp device, ``cpu`` or ``cuda``
    cache : a :class:`usdml.cache.Cache`, a folder, or None for the default folder; ``False``: no cache
    normal_offset, skip, slab, max_skip, end_skip : leaving the surface, in voxels (module doc)
    report, progress : as every backend (:mod:`usdml.visibility.base`)

    ``stats`` after each :meth:`update`: bytes, nodes, bricks, occupied voxels, build and per-frame
    seconds; ``built`` names the trees it built or loaded.
    """

    name = "svo"
    summary = "sparse voxel octree, restart traversal (paper 003)"
    capabilities = frozenset({HIT_DISTANCES, STATS, MEMORY_ESTIMATE, BAKE, REFINE})
    refine_levels = 4
    #: the thick-ray rule over :meth:`occluded` (five octree queries per width, level L's L widths, in NumPy):
    #: measured 5.9 (stages/city.usda) to 14.6 (boxes) exact rays a query at level 1, 6.8 and 7.2 on the
    #: tuning cities (tools/make_city.py --seed 0, 2), each level about one more width's worth: never cheaper
    #: than exact, so a budget the octree alone does not hold goes exact
    refine_costs = (5.8, 11.6, 17.4, 23.2)
    reads_settings = True

    def __init__(self, settings=None, *, device: str = "cpu", cache=None, normal_offset: float = NORMAL_OFFSET,
                 skip: float = SKIP, slab: float = SLAB, max_skip: float = MAX_SKIP, end_skip: float = END_SKIP,
                 native_isa: str = "auto", workers: int | None = None,
                 report: Callable[[str], None] | None = None,
                 progress: Callable[[int, int, str, str], None] | None = None, **values) -> None:
        s = settings_with(settings, values)
        self.resolution, cpu_kernel = int(s.svo_resolution), s.svo_cpu_kernel
        self.device = device
        self.cache = None if cache is False else (cache if isinstance(cache, Cache) else Cache(cache))
        self.normal_offset, self.skip, self.slab = float(normal_offset), float(skip), float(slab)
        self.max_skip, self.end_skip = float(max_skip), float(end_skip)
        self.workers = cpu_workers(device, workers)
        self.report = report or (lambda line: log.info(line))
        self.progress = progress
        self.native, self.native_isa = False, native_isa
        if str(device).startswith("cpu") and cpu_kernel != "warp":
            from usdml.visibility.svo import native as svo_native
            if svo_native.library() is not None:
                self.native = True
            elif cpu_kernel == "native":
                raise UsdmlError(f"--svo-cpu-kernel native: {svo_native.describe()}")
        self._static: tuple | None = None          # (members, tree or None)
        self._member_masks: dict = {}              # per-frame member -> its brick grid (_build_frame)
        self._member_key = None                    # the grid those were voxelized on
        self._frame: tuple | None = None
        self._gpu: dict = {}
        self._native = None
        self._ends: EmitterEnds | None = None     # the snapshot's triangle lights (usdml.visibility.emitter_ends)
        self.depth = 0
        self.stats: dict = {"builds": 0, "loaded": 0, "build_seconds": 0.0, "bytes": 0, "trees": 0,
                            "dynamic_rebuilds": 0, "dynamic_seconds": 0.0}
        self.built: list[str] = []
        self._described: dict | None = None        # describe() of the last trees, kept past close()

    def baked(self) -> tuple[dict, list[str], str]:
        """The static tree (``usdml bake``): cached, and where; per-frame trees are rebuilt every frame."""
        trees = [baked_entry(self, "svo", t, resolution=t.n, occupied_voxels=t.occupied) for t in self.trees]
        lines = [baked_line(t, f"{t['resolution']}^3, {t['occupied_voxels']:,} voxels, {t['bytes'] / 2**20:.2f} MiB",
                            "rebuilt per frame, not cached") for t in trees]
        fields = {"backend": "svo", "trees": trees, "built": self.stats["builds"], "loaded": self.stats["loaded"]}
        return fields, lines, f"{len(trees)} tree(s)"

    @classmethod
    def memory_estimate(cls, snapshot: Snapshot, settings) -> dict:
        """Bounds said before anything is built (``upperBound``: the size depends on the voxels): a tree
        at ``n³`` holds at most every 4³ brick (8 bytes each), a group of eight entries per node above
        them and the compiled walk's top table (``treeBytes``, per tree); building one holds a
        dense brick grid of ``n³ / 8`` bytes per CPU thread for a moment (``buildBytes``)."""
        n = int(getattr(settings, "svo_resolution", 0) or 0) or auto_resolution(snapshot)
        static, frame = tree_members(snapshot)
        trees = int(bool(static)) + int(bool(frame))
        bricks = (n // 4) ** 3
        groups = sum(8 ** level for level in range(max(1, n.bit_length() - 3)))
        depth = n.bit_length() - 1
        tree = 8 * bricks + 32 * groups + 4 * 8 ** top_level(depth)      # + the compiled walk's top table
        build = n ** 3 // 8 * cpu_workers("cpu")
        return {"resolution": n, "trees": trees, "treeBytes": tree * trees, "buildBytes": build,
                "totalBytes": tree * trees + build, "upperBound": True}

    @classmethod
    def memory_line(cls, estimate: dict) -> str:
        return (f"{estimate['trees']} tree(s) at {estimate['resolution']}^3, at most "
                f"{estimate['treeBytes'] / 2**20:.1f} MiB (+ {estimate['buildBytes'] / 2**20:.1f} MiB while building)")

    @classmethod
    def cpu_path(cls) -> str:
        from usdml.visibility.svo import native as svo_native
        return svo_native.describe()

    @property
    def kernel_name(self) -> str:
        """Which kernels answer queries: ``warp``, ``native-avx512``, ``native-avx2`` or ``native-scalar``."""
        if not self.native:
            return "warp"
        from usdml.visibility.svo.native import simd_width
        from usdml.native import kernel_label
        return kernel_label(simd_width(self.native_isa))

    def describe(self) -> dict:
        """Resolution, trees (bytes, nodes, bricks, voxels), build seconds and the CPU kernel, for
        ``usdml bench`` / ``usdml compare`` (kept after :meth:`close`: the last trees')."""
        if not self.trees:
            return dict(self._described) if self._described else self._describe()
        self._described = self._describe()
        return dict(self._described)

    def _describe(self) -> dict:
        trees = self.trees
        return {"svo_resolution": self.resolution or (1 << self.depth), "svo_depth": self.depth,
                "bytes": int(self.stats["bytes"]), "trees": len(trees),
                "nodes": int(sum(t.nodes.size for t in trees)), "bricks": int(sum(t.bricks.size // 2 for t in trees)),
                "occupied_voxels": int(sum(t.occupied for t in trees)),
                "voxel_size": float(trees[0].h) if trees else 0.0,
                "trees_loaded_from_cache": self.stats["loaded"], "tree_build_seconds": self.stats["build_seconds"],
                "cpu_kernel": self.kernel_name}

    @property
    def trees(self) -> list[SvoTree]:
        return [g[1] for g in (self._static, self._frame) if g is not None and g[1] is not None]

    # ------------------------------------------------------------------ building

    def _frame_grid(self, bounds: tuple) -> tuple[tuple, int]:
        """The per-frame tree's grid ``((lo, h), depth)`` over ``bounds = (lo, hi)`` (module doc, "Trees")."""
        grid, depth = cube_grid(bounds[0], bounds[1], self.depth), self.depth
        ref = self._static[1] if self._static is not None else None
        if ref is not None and ref.h <= grid[1]:
            # the static lattice where it is as fine as a grid of the geometry's own (module doc)
            got = aligned_grid(bounds[0], bounds[1], ref.lo, ref.h, self.depth)
            if got is not None:
                grid, depth = got[:2], got[2]
        return grid, depth

    def _build_frame(self, snapshot: Snapshot, members: tuple, changes: Changes | None = None) -> SvoTree | None:
        """The per-frame tree: each member voxelized into its own brick grid, the grids OR-ed. A member
        that did not change (``changes``) keeps its grid while the tree's grid stays the same, so only
        what moved is flattened and voxelized again (``stats["dynamic_members_voxelized"]``)."""
        t0 = time.perf_counter()
        if all(_member_changed(m, changes) for m in members):
            # everything moved: one flattening and one launch over all of them (park: 0.025 s against
            # 0.05 member by member); no member grids kept
            pts, tris = world_geometry(snapshot, members)
            self._member_masks, self._member_key = {}, None
            if not len(tris):
                return None
            used = np.asarray(pts, np.float64).reshape(-1, 3)
            grid, depth = self._frame_grid((used.min(0), used.max(0)))
            masks = voxelize_bricks(pts, tris, grid[0], grid[1], depth, device=self.device, workers=self.workers)
            return self._frame_tree(masks, grid, depth, t0, [(None, None, len(tris))], len(members))
        old = self._member_masks
        geo: dict = {}

        def geometry(m):
            if m not in geo:
                geo[m] = world_geometry(snapshot, (m,))
            return geo[m]
        # each member's box and triangle count: kept for members that did not change
        info = {}
        for m in members:
            if m in old and not _member_changed(m, changes):
                info[m] = old[m][1]
            else:
                mp, mt = geometry(m)
                used = np.asarray(mp, np.float64).reshape(-1, 3)
                info[m] = (used.min(0), used.max(0), len(mt)) if len(mt) else None
        boxes = [b for b in info.values() if b is not None]
        if not boxes:
            self._member_masks = {}
            return None
        bounds = (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))
        grid, depth = self._frame_grid(bounds)
        key = (tuple(np.asarray(grid[0], np.float64).tolist()), float(grid[1]), int(depth))
        n = 1 << depth
        # a grid per member is kept only while they all fit in MEMBER_CACHE_BYTES
        keep = len(members) * n ** 3 // 8 <= MEMBER_CACHE_BYTES
        same_grid = self._member_key == key
        masks, voxelized, fresh, owned = None, 0, {}, False
        for m in members:
            if info[m] is None:
                continue
            got = old[m][0] if (same_grid and m in old and not _member_changed(m, changes)) else None
            if got is None:
                mp, mt = geometry(m)
                got = voxelize_bricks(mp, mt, grid[0], grid[1], depth, device=self.device, workers=self.workers)
                voxelized += 1
            if keep:
                fresh[m] = (got, info[m])
            if masks is None:
                masks, owned = got, False             # a member's own grid: never written into
            elif owned:
                np.bitwise_or(masks, got, out=masks)
            else:
                masks, owned = np.bitwise_or(masks, got), True
        self._member_masks, self._member_key = fresh, key
        return self._frame_tree(masks, grid, depth, t0, boxes, voxelized)

    def _frame_tree(self, masks, grid, depth: int, t0: float, boxes: list, voxelized: int) -> SvoTree:
        """The per-frame tree over its voxelized ``masks``, with its counters."""
        t1 = time.perf_counter()
        tree = tree_from_masks(masks, grid[0], grid[1], depth, source="moving and deforming geometry")
        tree.voxelize_seconds, tree.triangles = t1 - t0, int(sum(b[2] for b in boxes))
        self.stats["dynamic_rebuilds"] += 1
        self.stats["dynamic_members_voxelized"] = voxelized
        self.stats["dynamic_seconds"] = time.perf_counter() - t0
        self.built.append(tree.source)
        return tree

    def update(self, snapshot: Snapshot, changes: Changes | None = None) -> None:
        """Build the static tree when its geometry changed (else keep it, or load it from the cache) and
        the per-frame tree when one of its meshes or instances changed."""
        static, frame = tree_members(snapshot)
        self._ends = EmitterEnds.of(snapshot.lights)
        self.built = []
        if not self.depth:
            # a power of two from 16 to 2048 (the parameter table's choices, checked in __init__)
            n = self.resolution or auto_resolution(snapshot)
            self.depth = n.bit_length() - 1
            self._check_memory(n)
        rebuilt = False
        if not static:
            self._static = None
        elif members_changed(self._static and self._static[0], static, changes, lambda path: changes.static):
            pts, tris = world_geometry(snapshot, static)
            tree = None
            if len(tris):
                # the box once: for the report and for the grid of a tree not in the cache
                lo, hi, outside = svo_bounds(pts, tris)
                if outside:
                    self.report(f"svo of the static scene covers {np.round(lo, 2).tolist()} .. {np.round(hi, 2).tolist()}; "
                                f"{outside} of {len(tris)} triangles reach outside it and shadow only within it")
                tree = cached_tree(pts, tris, self.depth, self.cache, device=self.device, workers=self.workers,
                                   grid=cube_grid(lo, hi, self.depth), source="static scene")
                self.built.append(tree.source)
                if tree.cached:
                    self.stats["loaded"] += 1
                else:
                    self.stats["builds"] += 1
                    self.stats["build_seconds"] += tree.build_seconds
            self._static = (static, tree)
            rebuilt = True
        if not frame:
            self._frame = None
        elif rebuilt or _frame_members_changed(self._frame and self._frame[0], frame, changes):
            self._frame = (frame, self._build_frame(snapshot, frame, None if rebuilt else changes))
            rebuilt = True
        if rebuilt or not self._gpu:
            self._assemble()
        self._scene = scene_sphere(snapshot)

    def _check_memory(self, n: int) -> None:
        """Refuse (one line) a resolution whose build would not fit: each CPU thread voxelizes into a
        dense brick grid of ``n³ / 8`` bytes (:meth:`memory_estimate`)."""
        from usdml.visibility.voxel.array import available_memory

        need = n ** 3 // 8 * (self.workers + 1)
        limit = int(0.8 * available_memory())
        if need > limit:
            raise UsdmlError(f"--svo-resolution {n}: building the octree needs {need / 2**30:.1f} GiB "
                             f"({self.workers} threads x {n ** 3 // 8 / 2**30:.2f} GiB of bricks, and the merge) "
                             f"but {limit / 2**30:.1f} GiB is available; lower --svo-resolution")
        if need > 2**28:
            self.report(f"svo: building at {n}^3 holds {need / 2**30:.2f} GiB of dense bricks for a moment")

    def per_frame_rebuild_seconds(self, snapshot: Snapshot, repeats: int = 3) -> dict:
        """Seconds to voxelize and build the per-frame tree again (the median of ``repeats``), as a
        render does on a frame where something moved; empty when nothing is rebuilt per frame."""
        if self._frame is None or self._frame[1] is None:
            return {}
        seconds, voxelize = [], []
        for _ in range(max(1, int(repeats))):
            tree = self._build_frame(snapshot, self._frame[0])      # every member: a frame where all moved
            seconds.append(self.stats["dynamic_seconds"])
            voxelize.append(tree.voxelize_seconds)
        self._frame = (self._frame[0], tree)
        self._assemble()
        return {"rebuild_seconds": float(np.median(seconds)), "voxelize_seconds": float(np.median(voxelize)),
                "rebuild_repeats": len(seconds), "rebuild_triangles": tree.triangles,
                "occupied_voxels": tree.occupied}

    def _assemble(self) -> None:
        """Concatenate the trees for the kernels (node and brick bases per tree)."""
        trees = self.trees
        node_base = np.cumsum([0] + [t.nodes.size for t in trees])[:-1]
        brick_base = np.cumsum([0] + [t.bricks.size // 2 for t in trees])[:-1]
        nodes = np.concatenate([t.nodes for t in trees]) if trees else np.zeros(8, np.int32)
        bricks = np.concatenate([t.bricks for t in trees]) if trees else np.zeros(2, np.uint32)
        tint = np.array([[t.depth, nb, bb, 0] for t, nb, bb in zip(trees, node_base, brick_base)] or [[0, 0, 0, 0]],
                        np.int32)
        lo = np.array([t.lo for t in trees] or [[0, 0, 0]], np.float32)
        inv_h = np.array([1.0 / t.h for t in trees] or [1.0], np.float32)
        self.stats["bytes"] = int(nodes.nbytes + bricks.nbytes)
        self.stats["trees"] = len(trees)
        self.reference_voxel = float(trees[0].h) if trees else 0.0
        self._gpu = {"nodes": nodes, "bricks": bricks, "int": tint, "lo": lo, "inv_h": inv_h, "n_trees": len(trees)}
        self._warp = None
        self._native = None
        if self.native and trees:
            from usdml.visibility.svo.native import NativeSvo
            tops = [top_table(t.nodes, t.depth) for t in trees]
            tint[:, 3] = np.cumsum([0] + [x.size for x in tops])[:-1]
            self.stats["bytes"] += int(sum(x.nbytes for x in tops))      # the compiled walk's top tables
            self._native = NativeSvo(nodes, bricks, tint, lo, inv_h, np.concatenate(tops), isa=self.native_isa)

    def _warp_scene(self):
        if self._warp is None:
            wp = warp_module()
            k = svo_kernels()
            dev = wp.get_device(self.device)
            g = self._gpu
            vs = k.SvoScene()
            vs.nodes = wp.array(g["nodes"], dtype=wp.int32, device=dev)
            vs.bricks = wp.array(g["bricks"], dtype=wp.uint32, device=dev)
            vs.tree_lo = wp.array(g["lo"], dtype=wp.vec3, device=dev)
            vs.tree_inv_h = wp.array(g["inv_h"], dtype=float, device=dev)
            vs.tree_int = wp.array(g["int"], dtype=wp.vec4i, device=dev)
            vs.n_trees = int(g["n_trees"])
            self._warp = vs
        return self._warp

    def _rule_values(self) -> dict:
        h = self.reference_voxel
        c, r = self._scene
        return dict(offset=self.normal_offset * h, skip=self.skip * h, slab=self.slab * h, max_skip=self.max_skip * h,
                    end_skip=self.end_skip * h, far=2.0 * r + 1.0, far_center=np.asarray(c, np.float32))

    def _warp_rule(self):
        wp = warp_module()
        rule = svo_kernels().SvoRule()
        for key, value in self._rule_values().items():
            setattr(rule, key, wp.vec3(*value) if key == "far_center" else float(value))
        return rule

    # ------------------------------------------------------------------ queries

    def _split(self, n: int, launch: Callable[[int, int], None], bands_per_worker: int) -> None:
        # a Warp launch's first band alone first (it loads the module); the compiled walk's all at once
        run_bands(n, launch, self.workers, bands_per_worker, first_on_caller=self._native is None)

    @property
    def emitter_offset(self) -> float:
        """A ray's end on a mesh light's triangle is moved off it by the start's offset, ``normal_offset`` voxels."""
        return self.normal_offset * self.reference_voxel if self._gpu else 0.0

    def hit_distances(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        """Distance in voxels (of the tree hit) from each ray's offset start to its first occupied voxel; -1: free.
        A target on a mesh light's triangle ends ``normal_offset`` voxels off its surface
        (:mod:`usdml.visibility.emitter_ends`)."""
        if not self._gpu:
            raise RuntimeError("SvoBackend.update() must be called before queries")
        origins = as_vectors(origins, "origins", dtype=None)
        n = origins.shape[0]
        targets = as_vectors(targets, "targets", n, dtype=None)
        if self._ends is not None:
            targets = self._ends.lift(targets, distant, self.normal_offset * self.reference_voxel)
        if n == 0 or self._gpu["n_trees"] == 0:
            return np.full(n, -1.0, np.float32)
        if self._native is not None:
            normals = None if normals is None else np.ascontiguousarray(as_vectors(normals, "normals", n, dtype=None))
            distant = None if distant is None else np.ascontiguousarray(as_flags(distant, "distant", n))
            res = np.empty(n, np.float32)
            rule = self._native.rule(**self._rule_values())
            o, t = np.ascontiguousarray(origins), np.ascontiguousarray(targets)
            self._split(n, lambda first, count: self._native.query(rule, first, count, o, t, normals, distant, res),
                        bands_per_worker=4)
            return res
        wp = warp_module()
        k = svo_kernels()
        dev = wp.get_device(self.device)
        f32 = dict(dtype=np.float32)
        origins = np.ascontiguousarray(origins, **f32)
        targets = np.ascontiguousarray(targets, **f32)
        normals = np.zeros((n, 3), np.float32) if normals is None else \
            np.ascontiguousarray(as_vectors(normals, "normals", n), **f32)
        distant = np.zeros(n, np.int32) if distant is None else as_flags(distant, "distant", n).astype(np.int32)
        wrap = dict(device=dev, copy=not dev.is_cpu)
        o = wp.array(origins, dtype=wp.vec3, **wrap)
        t = wp.array(targets, dtype=wp.vec3, **wrap)
        nm = wp.array(normals, dtype=wp.vec3, **wrap)
        di = wp.array(distant, dtype=wp.int32, **wrap)
        out = wp.zeros(n, dtype=float, device=dev)
        rule, vs = self._warp_rule(), self._warp_scene()

        def launch(first, count):
            wp.launch(k.query_segments, dim=count, device=dev, inputs=[o, t, nm, di, first, rule, vs, out])
        if dev.is_cpu:
            self._split(n, launch, bands_per_worker=8)
        else:
            launch(0, n)
            wp.synchronize_device(dev)
        return out.numpy()

    def occluded(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        return self.hit_distances(origins, targets, normals=normals, distant=distant) >= 0.0

    def occluded_uncertain(self, origins, targets, *, normals=None, distant=None, level: int = 1):
        """``REFINE``: the voxel backend's rule at the octree's leaf voxels
        (:meth:`usdml.visibility.voxel.backend.VoxelBackend.occluded_uncertain`; the thick-ray rule over
        :meth:`occluded`)."""
        from usdml.visibility.refine import thick_ray
        from usdml.visibility.voxel.backend import widened

        h = self.reference_voxel
        if self._ends is not None:      # the centre ray's end as occluded's (thick_ray's other rays are offset)
            targets = self._ends.lift(targets, distant, self.normal_offset * h)
        return widened(lambda width: thick_ray(self.occluded, origins, targets, normals, distant, width * h), level)

    def blind_reach(self, level: int) -> float:
        """``REFINE``: the voxel backend's blind zone (:meth:`usdml.visibility.voxel.backend.VoxelBackend.blind_reach`)
        in leaf voxels."""
        from usdml.visibility.voxel.backend import BLIND

        extra = BLIND[min(max(level, 1), len(BLIND)) - 1]
        return (self.normal_offset + max(self.skip, self.max_skip) + extra) * self.reference_voxel

    def close(self) -> None:
        if self.trees:
            self._described = self._describe()
        self._gpu, self._warp, self._native = {}, None, None
        self._static = self._frame = None

