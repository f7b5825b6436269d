"""One sparse voxel octree of paper 003: conservative voxelization of triangles (Warp) into 4³ bricks,
the octree over the occupied bricks (NumPy), its key and its cache entry.

The layout (groups of eight child entries, bricks of 64 bits) and the traversal are documented in
:mod:`usdml.kernels.svo.octree`; :class:`SvoTree` holds one tree's arrays and its grid. Building:

1. **Grid**: a cube over the geometry's bounds, or its core bounds where the whole is far larger
   (:func:`svo_bounds`: a ground to the horizon does not stretch it), ``n = 2^depth`` voxels per axis, or for a per-frame
   tree the static tree's lattice (same voxel size and voxel corners) when that is as fine
   (:func:`aligned_grid`), so that geometry voxelizes the same bits whichever tree holds it.
2. **Voxels**: every voxel whose cube (grown by ``SLACK`` voxels for rounding) a triangle touches:
   triangle / box separating axes (``kernels.svo.voxelize``), the triangles split over the CPU
   cores, each thread into its own brick grid (OR-ed after: Warp's CPU atomics are not atomic
   between threads), one atomic launch on a GPU.
3. **Tree**: occupied bricks, then their parents level by level (``unique`` of coordinates >> 1),
   each occupied node given one group of eight entries: about ``8 × 4`` bytes per occupied node plus
   8 bytes per occupied brick.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
import time

import numpy as np

from usdml.cache import Cache, cache_key
from usdml.parallel import cpu_workers, run_parallel
from usdml.scene import content_hash
from usdml.visibility.voxel.array import warp_module
from usdml.visibility.voxel.grid import core_bounds

log = logging.getLogger("usdml")

__all__ = ["SvoTree", "SLACK", "cube_grid", "tree_from_masks", "TOP_LEVEL", "top_level", "top_table", "FORMAT_VERSION", "aligned_grid", "build_tree", "cached_tree", "grid_for",
           "svo_kernels", "tree_from_bricks", "voxelize_bricks", "MIN_DEPTH", "MAX_DEPTH"]

#: bump when the bits or nodes a tree holds for the same inputs change
FORMAT_VERSION = 2
#: voxels a voxel's cube is grown by in the overlap test, so that float rounding never leaves a
#: voxel a triangle touches unset (a surface exactly on a voxel face sets both sides)
SLACK = 1.0e-4
#: 16³ … 2048³ voxels (bricks are 4³, so at least two octree levels above them)
MIN_DEPTH, MAX_DEPTH = 4, 11


def svo_kernels():
    """``usdml.kernels.svo.octree`` (imports Warp)."""
    warp_module()
    from usdml.kernels.svo import octree as svo
    return svo


@dataclass
class SvoTree:
    """One octree (module doc) over ``n³`` voxels of the cube ``lo + [0, n h)³``."""

    nodes: np.ndarray           #: (8 G,) int32 child entries, group 0 the root's
    bricks: np.ndarray          #: (2 B,) uint32 two words per occupied 4³ brick
    lo: np.ndarray              #: (3,) float64 corner of the grid
    h: float                    #: voxel size (world units)
    depth: int                  #: n = 2^depth
    occupied: int = 0           #: occupied voxels
    build_seconds: float = 0.0  #: 0 when loaded from the cache
    voxelize_seconds: float = 0.0
    triangles: int = 0
    key: str = ""
    cached: bool = False
    source: str = ""
    levels: list = field(default_factory=list)   #: occupied nodes per level 1 … depth - 2

    @property
    def n(self) -> int:
        return 1 << self.depth

    @property
    def nbytes(self) -> int:
        return int(self.nodes.nbytes + self.bricks.nbytes)

    def occupancy(self) -> np.ndarray:
        """The voxels as a dense ``(n, n, n)`` bool array indexed ``[x, y, z]`` (tests and tools; n³ bytes)."""
        n, nb = self.n, self.n >> 2
        dense = np.zeros((nb, nb, nb, 4, 4, 4), bool)      # [bz, by, bx, z, y, x]
        keys = self.brick_keys()
        bits = self.bricks.view(np.uint64)
        if len(keys):
            lanes = ((bits[:, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)).astype(bool)
            bz, by, bx = keys // (nb * nb), (keys // nb) % nb, keys % nb
            dense[bz, by, bx] = lanes.reshape(-1, 4, 4, 4)
        return dense.transpose(0, 3, 1, 4, 2, 5).reshape(n, n, n).transpose(2, 1, 0)

    def brick_keys(self) -> np.ndarray:
        """The linear brick index ``(bz nb + by) nb + bx`` of each stored brick, walking the tree."""
        d = self.depth
        groups = np.zeros(1, np.int64)
        coords = np.zeros((1, 3), np.int64)
        for level in range(1, d - 1):
            e = self.nodes.reshape(-1, 8)[groups]                  # (k, 8)
            g, octant = np.nonzero(e)
            child = coords[g] * 2 + np.stack([octant & 1, (octant >> 1) & 1, (octant >> 2) & 1], 1)
            entries = e[g, octant].astype(np.int64)
            groups, coords = entries, child
        nb = 1 << (d - 2)
        order = np.argsort(groups)                                 # entries are brick index + 1
        c = coords[order]
        return (c[:, 2] * nb + c[:, 1]) * nb + c[:, 0]


#: deepest level of the dense top table (``top_table``) the compiled SIMD walk starts its descents from:
#: 64³ cells, 1 MiB (at 256³ the bricks' own level: a descent is one read of the table, one of a brick)
TOP_LEVEL = 6


def top_level(depth: int) -> int:
    """The level of a tree's top table: ``TOP_LEVEL``, or the bricks' level ``depth - 2`` for smaller
    trees."""
    return min(TOP_LEVEL, depth - 2)


def top_table(nodes: np.ndarray, depth: int) -> np.ndarray:
    """The first ``T = top_level(depth)`` levels of the octree as one dense table over the level-T
    cells (``(cz · 2^T + cy) · 2^T + cx``): the cell's entry (its child group, or at ``T = depth - 2``
    its brick + 1) when every node down to it is occupied, else ``-shift`` of the shallowest empty node
    holding it (``size = 2^shift`` voxels). The SIMD walk reads one entry where the descent from the
    root reads T: the same node, the same answer."""
    T = top_level(depth)
    groups = nodes.reshape(-1, 8)
    table = np.zeros(1, np.int64)              # level 0: the root, child group 0
    for level in range(1, T + 1):
        m = 1 << level
        z, y, x = np.meshgrid(np.arange(m), np.arange(m), np.arange(m), indexing="ij")
        parent = table[((z >> 1) * (m >> 1) + (y >> 1)) * (m >> 1) + (x >> 1)].ravel()
        octant = ((x & 1) | ((y & 1) << 1) | ((z & 1) << 2)).ravel()
        entry = np.where(parent > 0, groups[np.maximum(parent, 0), octant], 0) if level > 1 else groups[0, octant]
        if level == 1:
            table = np.where(entry > 0, entry, -(depth - 1))
        else:
            table = np.where(parent < 0, parent, np.where(entry > 0, entry, -(depth - level)))
    return np.ascontiguousarray(table, np.int32)


#: the grid covers every triangle unless that box is this many times the core bounds' size (a ground
#: to the horizon): a tree costs little, but a Cornell box's walls are its scene
TRIM_RATIO = 4.0


def svo_bounds(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The box a static tree covers: every triangle's, or :func:`core_bounds` where those are
    ``TRIM_RATIO`` times smaller; and how many triangles reach outside it."""
    lo, hi, outside = core_bounds(points, triangles)
    if outside:
        used = np.asarray(points, np.float64).reshape(-1, 3)[np.unique(np.asarray(triangles).ravel())]
        flo, fhi = used.min(0), used.max(0)
        if np.max(fhi - flo) <= TRIM_RATIO * max(float(np.max(hi - lo)), 1e-12):
            return flo, fhi, 0
    return lo, hi, outside


def cube_grid(lo: np.ndarray, hi: np.ndarray, depth: int) -> tuple[np.ndarray, float]:
    """Corner and voxel size of the ``2^depth``-voxel cube around the box ``lo .. hi`` (a voxel of
    margin on each side)."""
    n = 1 << depth
    side = float(np.max(hi - lo))
    side = max(side, 1e-6 * max(1.0, float(np.abs(lo).max(initial=0.0))))
    h = side * (1.0 + 2.0 / n) / n
    center = 0.5 * (lo + hi)
    return center - 0.5 * n * h, h


def grid_for(points: np.ndarray, triangles: np.ndarray, depth: int) -> tuple[np.ndarray, float, int]:
    """The cube of a tree over ``(points, triangles)`` at ``2^depth`` voxels (:func:`svo_bounds`'s box):
    corner, voxel size and how many triangles reach outside it (they voxelize only inside)."""
    lo, hi, outside = svo_bounds(points, triangles)
    return (*cube_grid(lo, hi, depth), outside)


def aligned_grid(lo: np.ndarray, hi: np.ndarray, ref_lo: np.ndarray, ref_h: float,
                 max_depth: int) -> tuple[np.ndarray, float, int] | None:
    """A per-frame tree's grid on the static tree's lattice (corner a whole number of voxels from
    ``ref_lo``, voxel ``ref_h``): ``(lo, h, depth)`` with the smallest depth >= ``MIN_DEPTH`` whose cube
    holds the box ``lo .. hi``; None when even ``max_depth`` is too small (the caller then sizes a
    grid of its own)."""
    i0 = np.floor((lo - ref_lo) / ref_h) - 1
    i1 = np.ceil((hi - ref_lo) / ref_h) + 1
    need = float(np.max(i1 - i0))
    depth = max(MIN_DEPTH, int(np.ceil(np.log2(max(need, 1.0)))))
    if depth > max_depth:
        return None
    return ref_lo + i0 * ref_h, float(ref_h), depth


def voxelize_bricks(points: np.ndarray, triangles: np.ndarray, lo: np.ndarray, h: float, depth: int,
                    device: str = "cpu", workers: int | None = None) -> np.ndarray:
    """The dense brick grid (:mod:`usdml.kernels.svo.octree`) of every voxel the triangles touch, as
    ``(nb³,) uint64`` (``nb = n / 4``)."""
    wp = warp_module()
    k = svo_kernels()
    dev = wp.get_device(device)
    n = 1 << depth
    words = 2 * (n >> 2) ** 3
    tris = np.ascontiguousarray(np.asarray(triangles, np.int32).reshape(-1, 3))
    if len(tris) == 0:
        return np.zeros(words // 2, np.uint64)
    pts = wp.array(np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3)), dtype=wp.vec3, device=dev)
    tri = wp.array(tris, dtype=wp.vec3i, device=dev)
    lo32 = wp.vec3(*np.asarray(lo, np.float32))
    inv_h = float(1.0 / h)
    if not dev.is_cpu:
        out = wp.zeros(words, dtype=wp.uint32, device=dev)
        wp.launch(k.voxelize, dim=len(tris), device=dev, inputs=[pts, tri, 0, lo32, inv_h, n, SLACK, 1, out])
        return out.numpy().view(np.uint64)
    workers = cpu_workers("cpu", workers)
    # interleave big and small triangles between threads: spans of a Morton-ordered mesh are uneven
    spans = np.linspace(0, len(tris), min(workers, len(tris)) + 1).astype(np.int64)

    def run(span):
        a, b = int(span[0]), int(span[1])
        grid = wp.zeros(words, dtype=wp.uint32, device=dev)
        wp.launch(k.voxelize, dim=b - a, device=dev, inputs=[pts, tri, a, lo32, inv_h, n, SLACK, 0, grid])
        return grid.numpy()
    wp.load_module(k, device=dev)
    grids = run_parallel(run, list(zip(spans[:-1], spans[1:])), workers)
    out = grids[0]
    for g in grids[1:]:
        np.bitwise_or(out, g, out=out)
    return out.view(np.uint64)


def tree_from_bricks(masks: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """``(nodes, bricks, occupied nodes per level)`` of the octree over a dense brick grid
    (:func:`voxelize_bricks`), laid out as :mod:`usdml.kernels.svo.octree` reads it."""
    nb = 1 << (depth - 2)
    occ = np.flatnonzero(masks)
    bricks = np.ascontiguousarray(masks[occ]).view(np.uint32)
    # coordinates of the occupied nodes per level, level depth-2 = bricks (sorted by linear key)
    x, y, z = occ % nb, (occ // nb) % nb, occ // (nb * nb)
    coords = {depth - 2: np.stack([x, y, z], 1).astype(np.int64)}
    keys = {depth - 2: occ.astype(np.int64)}
    for level in range(depth - 3, -1, -1):
        m = 1 << level
        c = coords[level + 1] >> 1
        key = np.unique((c[:, 2] * m + c[:, 1]) * m + c[:, 0])
        keys[level] = key
        coords[level] = np.stack([key % m, (key // m) % m, key // (m * m)], 1)
    counts = [len(keys[level]) for level in range(depth - 1)]      # level 0: the root (0 or 1 node)
    if not len(occ):
        return np.zeros(8, np.int32), bricks, [0] * (depth - 2)
    # group of each node at level l-1 (one per occupied node): G_1 = 0 for the root's group
    group_base = {1: 0}
    for level in range(2, depth - 1):
        group_base[level] = group_base[level - 1] + counts[level - 2]
    total = group_base[depth - 2] + counts[depth - 3]
    nodes = np.zeros(8 * total, np.int32)
    for level in range(1, depth - 1):
        c = coords[level]
        p = c >> 1
        m = 1 << (level - 1)
        parent = np.searchsorted(keys[level - 1], (p[:, 2] * m + p[:, 1]) * m + p[:, 0])
        octant = (c[:, 0] & 1) | ((c[:, 1] & 1) << 1) | ((c[:, 2] & 1) << 2)
        rank = np.arange(len(c), dtype=np.int64)
        value = rank + 1 if level == depth - 2 else group_base[level + 1] + rank
        nodes[8 * (group_base[level] + parent) + octant] = value
    return nodes, bricks, counts[1:]


def build_tree(points, triangles, depth: int, *, device: str = "cpu", workers: int | None = None,
               grid: tuple | None = None, source: str = "") -> SvoTree:
    """The tree of ``(points, triangles)`` at ``2^depth`` voxels, on ``grid = (lo, h)`` when given
    (:func:`aligned_grid`) else on :func:`grid_for`'s cube."""
    t0 = time.perf_counter()
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    lo, h = grid if grid is not None else grid_for(points, triangles, depth)[:2]
    masks = voxelize_bricks(points, triangles, lo, h, depth, device=device, workers=workers)
    tree = tree_from_masks(masks, lo, h, depth, source=source)
    tree.voxelize_seconds = time.perf_counter() - t0 - tree.build_seconds
    tree.build_seconds = time.perf_counter() - t0
    tree.triangles = len(triangles)
    return tree


def tree_from_masks(masks: np.ndarray, lo, h: float, depth: int, source: str = "") -> SvoTree:
    """The tree over a dense brick grid already voxelized (:func:`voxelize_bricks`; the per-frame tree
    ORs its members' grids), ``build_seconds`` the octree's alone."""
    t0 = time.perf_counter()
    nodes, bricks, levels = tree_from_bricks(masks, depth)
    occupied = int(np.unpackbits(bricks.view(np.uint8)).sum()) if bricks.size else 0
    return SvoTree(nodes, bricks, np.asarray(lo, np.float64), float(h), int(depth), occupied,
                   time.perf_counter() - t0, source=source, levels=levels)


def tree_key(points, triangles, depth: int) -> str:
    """The cache key of the static tree of ``(points, triangles)`` (its grid follows from them)."""
    return cache_key("svo", FORMAT_VERSION, depth, content_hash(np.asarray(points, np.float32)),
                     content_hash(np.asarray(triangles, np.int32)))


def cached_tree(points, triangles, depth: int, cache: Cache | None, *, device: str = "cpu",
                workers: int | None = None, grid: tuple | None = None, source: str = "") -> SvoTree:
    """:func:`build_tree` through ``cache`` (the static tree: built once, loaded next time; a damaged
    entry is reported and rebuilt); ``grid``: :func:`grid_for`'s, when the caller has it already."""
    key = tree_key(points, triangles, depth)
    if cache is not None:
        got = cache.load("svo", key)
        if got is not None:
            data, meta = got
            g = int(meta["nodes"])
            return SvoTree(data[:g].view(np.int32).copy(), data[g:].copy(), np.asarray(meta["lo"], np.float64),
                           float(meta["h"]), int(meta["depth"]), int(meta["occupied"]), triangles=int(meta["triangles"]),
                           key=key, cached=True, source=source, levels=list(meta["levels"]))
    tree = build_tree(points, triangles, depth, device=device, workers=workers, grid=grid, source=source)
    tree.key = key
    if cache is not None:
        data = np.concatenate([tree.nodes.view(np.uint32), tree.bricks])
        cache.store("svo", key, data, {"nodes": int(tree.nodes.size), "lo": tree.lo.tolist(), "h": tree.h,
                                       "depth": tree.depth, "occupied": tree.occupied, "triangles": tree.triangles,
                                       "levels": tree.levels, "format": FORMAT_VERSION, "source": source})
    return tree
