"""Paper 000 Alg. 5: a voxel array rebuilt per frame by voxelizing once and rotating.

Deforming meshes (and whole scenes marked fully dynamic) cannot keep a precomputed array. Each frame
the geometry is voxelized once, in direction bin 0 (the reference ``V0``), and every other direction
``d`` is filled by rotating ``V0``'s occupied voxels about the cube's centre by ``R_d = M_d M_0ᵀ``
(``M_d``: bin ``d``'s frame, rows ``u, v, w``). The rotation reads precomputed tables
(:class:`RotationTables`): a voxel centre's position in direction ``d`` is the sum of three table
entries, one per axis, so there is neither trigonometry nor a matrix product per voxel. The kernels
are in :mod:`usdml.kernels.voxel.rotate`.

The reference voxelization
    ``V0`` is made as the paper makes it, by depth peeling along its three axes: a voxel is occupied
    where one of the three axis-parallel lines through its centre crosses a triangle
    (:func:`reference_occupied`, rasterized in Warp straight from the triangles, a few ms on the
    creature and the park). A surface is then about one voxel thick from every side, so the rotated
    copies are thin in every direction. (Marking every voxel a surface touches, Alg. 1's rule with
    ``core`` 1, made surfaces up to three voxels thick and over-occluded grazing rays: park ε_v /
    ε_s 31.7 / 27.9 % against 17.8 / 7.1 % now; low-poly creature 1.82 / 1.15 % against 1.80 / 1.11 %.)

Cost and error (measured: README "Deforming and fully dynamic scenes")
    Alg. 1 rasterizes every triangle in every direction, a cost of about the triangles times the
    directions; Alg. 5 voxelizes once and then moves only the occupied voxels, a cost of about the
    occupied voxels times the directions, whatever the triangle count. On a low-poly mesh Alg. 1
    is therefore only a few times slower (warp's 3,968-triangle bear: 2.3×), on a detailed one far
    slower (the creature, that bear Loop-subdivided to 254 k triangles: 20–38×). The rotation reads ``V0``'s
    voxels row by row (a row's two table entries summed once) into directions memset just before.

    ``point`` mapping (the paper) sets the voxel holding each rotated voxel centre: the rotated
    lattice leaves holes in surfaces that are tilted in the target grid, so some rays leak through.
    ``conservative`` sets every voxel a rotated voxel overlaps: no holes, but surfaces become
    up to about two voxels thick (more over-occlusion) and the rebuild costs several times more.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
import time
from typing import Callable

import numpy as np

from usdml.parallel import cpu_workers, run_parallel
from usdml.settings import VOXEL_MAPPINGS
from usdml.visibility.voxel.array import (VoxelArray, array_cube, clear_words, host_words, run_direction_chunks,
                                          warp_module)
from usdml.visibility.voxel.grid import DirectionBins, RowLayout

__all__ = ["MAPPINGS", "RotationTables", "reference_occupied", "rotate_array"]

#: fraction bits of the fixed-point tables (kernels.voxel_rotate.FIX)
FIX_BITS = 16
#: how a rotated voxel marks the target grid (module doc)
MAPPINGS = VOXEL_MAPPINGS
#: directions one CPU launch fills: its words stay in cache from the memset to the last bit set
#: (measured, rotation of a frame at 128³ / 2° on both cores, 4 / 8 / 16 directions: low-poly creature
#: 0.61 / 0.61 / 0.63 s, park 0.30 / 0.28 / 0.26 s; 128: creature 0.65 s)
CPU_DIRECTIONS_PER_LAUNCH = 8
#: directions one call of the compiled rotation fills (it clears and fills them one by one, so its
#: words stay in cache whatever the count): fewer calls, less of the pool's per-task cost (the 254k-
#: triangle creature at 128³ / 2°, both cores: 8 / 64 / 256 directions 0.43 / 0.32 / 0.36 s a frame)
NATIVE_DIRECTIONS_PER_LAUNCH = 64


@dataclass(frozen=True)
class RotationTables:
    """Alg. 5's lookup tables for ``n``³ grids and the direction bins at ``step`` degrees."""

    n: int
    step: float
    rotations: np.ndarray = field(repr=False)   #: (B, 3, 3) R_d = M_d M_0ᵀ
    table: np.ndarray = field(repr=False)       #: (B, 3, n, 3) int32 16.16 fixed point, see kernels.voxel_rotate
    inv_axes: np.ndarray = field(repr=False)    #: (B, 3, 3) float32 R_dᵀ
    reach: np.ndarray = field(repr=False)       #: (B, 3) float32 half extent of a rotated voxel per grid axis
    radius: np.ndarray = field(repr=False)      #: (B, 3) float32 half extent of a grid voxel per rotated axis

    @staticmethod
    @lru_cache(maxsize=4)
    def make(n: int, step: float) -> "RotationTables":
        """The tables for ``n``³ grids at ``step`` degrees (made once per resolution and step)."""
        frames = DirectionBins.make(step).frames.astype(np.float64)
        rot = frames @ frames[0].T                                  # (B, 3, 3)
        x = np.arange(n, dtype=np.float64) + 0.5 - 0.5 * n          # voxel centres, cube-centred
        table = rot.transpose(0, 2, 1)[:, :, None, :] * x[None, None, :, None]     # (B, axis, n, 3)
        table[:, 0, :, :] += 0.5 * n
        reach = 0.5 * np.abs(rot).sum(axis=2)
        radius = 0.5 * np.abs(rot).sum(axis=1)
        return RotationTables(int(n), float(step), rot, np.round(table * (1 << FIX_BITS)).astype(np.int32),
                              rot.transpose(0, 2, 1).astype(np.float32), reach.astype(np.float32),
                              radius.astype(np.float32))

    @property
    def nbytes(self) -> int:
        return int(self.table.nbytes + self.inv_axes.nbytes + self.reach.nbytes + self.radius.nbytes)

    def position(self, d: int, ijl: np.ndarray) -> np.ndarray:
        """(K, 3) position in direction ``d``'s grid (voxels, corner origin) of voxel centres ``ijl``
        of ``V0``, summed from the table the way the kernel sums it (its floor is the voxel set)."""
        ijl = np.asarray(ijl, np.int64).reshape(-1, 3)
        t = self.table[d].astype(np.int64)
        return (t[0, ijl[:, 0]] + t[1, ijl[:, 1]] + t[2, ijl[:, 2]]) / float(1 << FIX_BITS)



def rotate_array(points: np.ndarray, triangles: np.ndarray, resolution: int, step: float, *,
                 mapping: str = "point", device: str = "cpu", workers: int | None = None,
                 bounds=None, out=None, base: int = 0,
                 progress: Callable[[int, int], None] | None = None, source: str = "",
                 native: bool = False) -> VoxelArray:
    """Alg. 5: the array of ``(points, triangles)`` (array space) from one voxelization, rotated.

    ``out``: a Warp ``uint32`` array to fill in place from word ``base`` (the backend's assembled
    words, so a per-frame rebuild allocates and copies nothing); the returned array's ``words`` is
    then a view of it on CPU (empty on a GPU). Default: a new array. ``bounds``: as
    :func:`usdml.visibility.voxel.array.build_array`. ``native``: on CPU with the point mapping, rotate
    with the compiled kernel (``usdml.visibility.voxel.native.rotate_point``, the same integer rule)
    instead of Warp's.
    """
    if mapping not in MAPPINGS:
        raise ValueError(f"voxel mapping must be one of {', '.join(MAPPINGS)}, got {mapping!r}")
    if resolution > MAX_RESOLUTION:
        raise ValueError(f"Alg. 5 rotates voxelizations of up to {MAX_RESOLUTION}^3, got {resolution}^3")
    wp = warp_module()
    kr = _rotate_kernels()
    t0 = time.perf_counter()
    bins = DirectionBins.make(step)
    layout = RowLayout.make(resolution)
    tables = RotationTables.make(resolution, step)
    points, triangles, center, half = array_cube(points, triangles, bounds)
    occupied, samples = reference_occupied(points, triangles, center, half, resolution, bins.frames[0], layout,
                                           device=device, workers=workers)
    sample_seconds = time.perf_counter() - t0
    dev = wp.get_device(device)
    n_dirs, wpd = bins.count, layout.words
    words_np = None
    if out is None:
        words_np = np.zeros(n_dirs * wpd, np.uint32)
        out = wp.array(words_np, dtype=wp.uint32, device=dev, copy=not dev.is_cpu)
        base = 0
    elif not dev.is_cpu or len(occupied) == 0:
        clear_words(out, base, n_dirs * wpd, dev)     # on CPU the launches clear their own directions
    if len(occupied):
        groups = [np.ascontiguousarray(a, np.int32) for a in row_groups(occupied)]
        conservative = int(mapping == "conservative")
        host = out.numpy() if dev.is_cpu else None
        rows = None
        if native and host is not None and not conservative:
            from usdml.visibility.voxel.native import packed_rows, rotate_point

            rows = packed_rows(layout)      # None where the layout does not fit: Warp's kernel then
        if rows is not None:
            tab = np.ascontiguousarray(tables.table.reshape(-1, 3), np.int32)

            def launch(d0, d1):
                rotate_point(*groups, tab, resolution, d0, d1, rows, wpd, int(base), host)
                return d1 - d0
        else:
            g = _device_tables(tables, layout, dev)
            row_ij, row_start, depth = (wp.array(a, dtype=wp.int32, device=dev) for a in groups)
            chunk = len(groups[0]) if dev.is_cpu else 64
            n_chunks = -(-len(groups[0]) // chunk)

            def launch(d0, d1):
                if host is not None:
                    # memset this thread's directions just before it fills them (they stay in cache);
                    # the bits are then set without atomics (a thread owns its directions)
                    host[base + d0 * wpd:base + d1 * wpd] = 0
                wp.launch(kr.rotate_voxels, dim=(d1 - d0, n_chunks), device=dev,
                          inputs=[row_ij, row_start, depth, g["table"], g["inv_axes"], g["reach"], g["radius"],
                                  resolution, conservative, d0, chunk, g["rows"], wpd, int(base),
                                  int(host is None), out])
                return d1 - d0

        # CPU: a few directions per launch, so a launch's words (8 x 180 KiB at 128³ / 2°) stay in cache
        per = (NATIVE_DIRECTIONS_PER_LAUNCH if rows is not None else CPU_DIRECTIONS_PER_LAUNCH) if dev.is_cpu else \
            max(1, min(n_dirs, (1 << 22) // max(len(occupied) * (8 if conservative else 1), 1)))
        run_direction_chunks(n_dirs, per, launch, dev, workers, progress)
    words_np = host_words(out, words_np, base, n_dirs * wpd, dev)
    arr = VoxelArray(words_np, center, float(half), resolution, float(step), samples,
                     time.perf_counter() - t0, sample_seconds, source=source, occupied=int(len(occupied)))
    return arr


def reference_occupied(points: np.ndarray, triangles: np.ndarray, center: np.ndarray, half: float, n: int,
                       frame: np.ndarray, layout: RowLayout | None = None, *, device: str = "cpu",
                       workers: int | None = None) -> tuple[np.ndarray, int]:
    """``V0``: the occupied voxels ``(i, j, l)`` (int32, sorted) of ``(points, triangles)`` (array
    space) in the grid with frame ``frame`` over the cube ``center ± half``, by the paper's depth
    peeling along three axes: a voxel is occupied where one of the three axis-parallel lines through
    its centre crosses a triangle (``kernels.voxel_rotate.reference_raster``), those outside the
    stored rows of ``layout`` dropped. On CPU each core fills its own bit grid over a share of the
    triangles. Returns the voxels and the number of crossings.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        return np.zeros((0, 3), np.int32), 0
    wp = warp_module()
    kr = _rotate_kernels()
    dev = wp.get_device(device)
    words = -(-n ** 3 // 32)
    pts = wp.array(points.astype(np.float32), dtype=wp.vec3, device=dev)
    tri = wp.array(triangles.astype(np.int32), dtype=wp.vec3i, device=dev)
    crossings = wp.zeros(len(triangles), dtype=wp.int32, device=dev)
    args = [wp.mat33(*np.asarray(frame, np.float32).ravel()), wp.vec3(*np.asarray(center, np.float32)), float(half),
            int(n), wp.zeros(0, dtype=wp.int32, device=dev)]
    if dev.is_cpu:
        # shares of about equal work per core (a triangle costs about its projected boxes, in
        # voxels), each into its own grid (no atomics), OR-ed here
        shares = max(1, min(cpu_workers(dev, workers), len(triangles)))
        q = (points - center) @ np.asarray(frame, np.float64).T * (n / (2.0 * half))
        a, b, c = (q[triangles[:, k]] for k in range(3))
        ext = np.maximum(np.maximum(a, b), c) - np.minimum(np.minimum(a, b), c)
        cost = np.cumsum(1.0 + ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0])
        cut = np.searchsorted(cost, np.linspace(0, cost[-1], shares + 1)[1:-1])
        edges = np.concatenate([[0], cut, [len(triangles)]]).astype(np.int64)
        grid = wp.zeros(shares * words, dtype=wp.uint32, device=dev)

        def fill(k):
            if edges[k + 1] > edges[k]:
                wp.launch(kr.reference_raster, dim=int(edges[k + 1] - edges[k]), device=dev,
                          inputs=[pts, tri, int(edges[k])] + args + [0, grid, k * words, crossings])
        run_parallel(fill, range(shares), shares, first_on_caller=True)
        bits = np.bitwise_or.reduce(grid.numpy().reshape(shares, words), axis=0)
    else:
        grid = wp.zeros(words, dtype=wp.uint32, device=dev)
        wp.launch(kr.reference_raster, dim=len(triangles), device=dev,
                  inputs=[pts, tri, 0] + args + [1, grid, 0, crossings])
        bits = grid.numpy()
    v = np.nonzero(np.unpackbits(bits.view(np.uint8), bitorder="little"))[0]
    ijl = np.stack([v // (n * n), (v // n) % n, v % n], axis=1)
    if layout is not None:
        ijl = ijl[layout.word_index(ijl) >= 0]
    return ijl.astype(np.int32), int(crossings.numpy().sum(dtype=np.int64))


#: largest resolution Alg. 5 packs (10 bits per voxel index, see row_groups)
MAX_RESOLUTION = 1024


def row_groups(ijl: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occupied voxels ``(i, j, l)`` as the kernel reads them, grouped by ``V0``'s rows: ``row_ij``
    (``i << 10 | j`` per row, indices < 1024), ``row_start`` (rows + 1 offsets into ``depth``) and
    ``depth`` (``l`` of each voxel), all int32."""
    ijl = np.asarray(ijl, np.int64).reshape(-1, 3)
    key = (ijl[:, 0] << 10) | ijl[:, 1]
    order = np.lexsort((ijl[:, 2], key))
    key = key[order]
    row_ij, start = np.unique(key, return_index=True)
    return (row_ij.astype(np.int32), np.append(start, len(key)).astype(np.int32),
            ijl[order, 2].astype(np.int32))


_DEVICE_TABLES: dict = {}


def _device_tables(tables: RotationTables, layout: RowLayout, dev) -> dict:
    """The tables as Warp arrays on ``dev``, made once per (resolution, step, device)."""
    wp = warp_module()
    key = (tables.n, tables.step, str(dev))
    g = _DEVICE_TABLES.get(key)
    if g is None:
        _DEVICE_TABLES.clear()
        g = {
            "table": wp.array(tables.table.reshape(-1, 3), dtype=wp.vec3i, device=dev),
            "inv_axes": wp.array(tables.inv_axes, dtype=wp.mat33, device=dev),
            "reach": wp.array(tables.reach, dtype=wp.vec3, device=dev),
            "radius": wp.array(tables.radius, dtype=wp.vec3, device=dev),
            "rows": wp.array(np.stack([layout.offset - layout.w0, 32 * layout.w0, 32 * (layout.w0 + layout.nw)], 1)
                             .astype(np.int32), dtype=wp.vec3i, device=dev),
        }
        _DEVICE_TABLES[key] = g
    return g


def _rotate_kernels():
    from usdml.kernels.voxel import rotate as voxel_rotate

    return voxel_rotate
