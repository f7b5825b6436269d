"""Paper 000 Alg. 5: a voxel array rebuilt per frame by voxelizing once and rotating.

Deforming meshes (and whole scenes marked fully dynamic) cannot keep a precomputed array. Each frame
the geometry is voxelized once, in direction bin 0 (the reference ``V0``, Alg. 1 for one
direction), and every other direction ``d`` is filled by rotating ``V0``'s occupied voxels about the
cube's centre by ``R_d = M_d M_0ᵀ`` (``M_d``: bin ``d``'s frame, rows ``u, v, w``). The rotation
reads precomputed tables (:class:`RotationTables`): a voxel centre's position in direction ``d`` is
the sum of three table entries, one per axis, so there is neither trigonometry nor a matrix product
per voxel. The kernels are in :mod:`usdml.kernels.voxel_rotate`.

Cost and error (measured: README "Deforming and fully dynamic scenes")
    Alg. 1 voxelizes every surface sample (about 9 per occupied voxel at half-voxel spacing) in every
    direction; Alg. 5 voxelizes the samples once and then moves only the occupied voxels, so a
    rebuild costs about the occupied voxels times the directions.

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

from usdml.settings import VOXEL_MAPPINGS
from usdml.visibility.voxel import (PER_FRAME_CORE, VoxelArray, _host_words, _wp, clear_words, prepare_geometry,
                                    run_direction_chunks)
from usdml.visibility.voxel_grid import DirectionBins, RowLayout

__all__ = ["MAPPINGS", "RotationTables", "reference_voxels", "rotate_array"]

#: fraction bits of the fixed-point tables (kernels.voxel_rotate.FIX)
FIX_BITS = 16
#: how a rotated voxel marks the target grid (module doc)
MAPPINGS = VOXEL_MAPPINGS


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



def reference_voxels(samples: np.ndarray, center: np.ndarray, half: float, n: int, frame: np.ndarray,
                     layout: RowLayout | None = None, core: float = 1.0) -> np.ndarray:
    """Occupied voxels ``(i, j, l)`` (int32, sorted, unique) of the voxelization of ``samples`` in the
    direction with frame ``frame`` (rows ``u, v, w``): the voxels the Alg. 1 kernel would set (a
    sample marks its voxel when it lies in the central ``core`` fraction of its row's square), with
    those outside the stored rows dropped."""
    q = ((np.asarray(samples, np.float64) - np.asarray(center, np.float64)) @ np.asarray(frame, np.float64).T
         + half) * (n / (2.0 * half))
    idx = np.floor(q).astype(np.int64)
    keep = np.all((idx >= 0) & (idx < n), axis=1)
    if core < 1.0:
        frac = q[:, :2] - idx[:, :2]
        keep &= np.all((frac >= 0.5 - 0.5 * core) & (frac <= 0.5 + 0.5 * core), axis=1)
    idx = idx[keep]
    key = np.unique((idx[:, 0] * n + idx[:, 1]) * n + idx[:, 2])
    ijl = np.stack([key // (n * n), (key // n) % n, key % n], axis=1)
    if layout is not None:
        r = ijl[:, 0] * n + ijl[:, 1]
        k = ijl[:, 2] // 32 - layout.w0[r]
        ijl = ijl[(k >= 0) & (k < layout.nw[r])]
    return ijl.astype(np.int32)


def rotate_array(points: np.ndarray, triangles: np.ndarray, resolution: int, step: float, *,
                 mapping: str = "point", device: str = "cpu", workers: int | None = None,
                 bounds=None, core: float | None = None, out=None, base: int = 0,
                 progress: Callable[[int, int], None] | None = None, source: str = "") -> VoxelArray:
    """Alg. 5: the array of ``(points, triangles)`` (array space) from one voxelization, rotated.

    ``out``: a Warp ``uint32`` array to fill in place from word ``base`` (the backend's assembled
    words, so a per-frame rebuild allocates and copies nothing); the returned array's ``words`` is
    then a view of it on CPU (empty on a GPU). Default: a new array. ``bounds``: as
    :func:`usdml.visibility.voxel.build_array`; ``core``: ``V0``'s rule (default ``PER_FRAME_CORE``).
    """
    if mapping not in MAPPINGS:
        raise ValueError(f"voxel mapping must be one of {', '.join(MAPPINGS)}, got {mapping!r}")
    if resolution > MAX_RESOLUTION:
        raise ValueError(f"Alg. 5 rotates voxelizations of up to {MAX_RESOLUTION}^3, got {resolution}^3")
    wp = _wp()
    kr = _rotate_kernels()
    t0 = time.perf_counter()
    bins = DirectionBins.make(step)
    layout = RowLayout.make(resolution)
    tables = RotationTables.make(resolution, step)
    core = PER_FRAME_CORE if core is None else float(core)
    center, half, samples = prepare_geometry(points, triangles, resolution, bounds, core)
    occupied = reference_voxels(samples, center, half, resolution, bins.frames[0], layout,
                                core)
    sample_seconds = time.perf_counter() - t0
    dev = wp.get_device(device)
    n_dirs, wpd = bins.count, layout.words
    words_np = None
    if out is None:
        words_np = np.zeros(n_dirs * wpd, np.uint32)
        out = wp.array(words_np, dtype=wp.uint32, device=dev, copy=not dev.is_cpu)
        base = 0
    elif not dev.is_cpu or len(occupied) == 0:
        clear_words(out, base, n_dirs * wpd, dev)
    if len(occupied):
        g = _device_tables(tables, layout, dev)
        occ = wp.array(pack_voxels(occupied), dtype=wp.int32, device=dev)
        chunk = len(occupied) if dev.is_cpu else 1024
        n_chunks = -(-len(occupied) // chunk)
        conservative = int(mapping == "conservative")
        clear = int(dev.is_cpu)

        def launch(d0, d1):
            wp.launch(kr.rotate_voxels, dim=(d1 - d0, n_chunks), device=dev,
                      inputs=[occ, g["table"], g["inv_axes"], g["reach"], g["radius"], resolution, conservative,
                              d0, chunk, g["rows"], wpd, int(base), clear, out])
            return d1 - d0

        per = max(1, min(n_dirs, (1 << 22) // max(len(occupied) * (8 if conservative else 1), 1)))
        run_direction_chunks(n_dirs, per, launch, dev, workers, progress)
    words_np = _host_words(out, words_np, base, n_dirs * wpd, dev)
    arr = VoxelArray(words_np, center, float(half), resolution, float(step), int(len(samples)),
                     time.perf_counter() - t0, sample_seconds, source=source, occupied=int(len(occupied)))
    return arr


#: largest resolution Alg. 5 packs (10 bits per voxel index, see pack_voxels)
MAX_RESOLUTION = 1024


def pack_voxels(ijl: np.ndarray) -> np.ndarray:
    """``(i, j, l)`` packed as the kernel reads them: ``i << 20 | j << 10 | l`` (indices < 1024)."""
    ijl = np.asarray(ijl, np.int64).reshape(-1, 3)
    return ((ijl[:, 0] << 20) | (ijl[:, 1] << 10) | ijl[:, 2]).astype(np.int32)


_DEVICE_TABLES: dict = {}


def _device_tables(tables: RotationTables, layout: RowLayout, dev) -> dict:
    """The tables as Warp arrays on ``dev``, made once per (resolution, step, device)."""
    wp = _wp()
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
    from usdml.kernels import voxel_rotate

    return voxel_rotate
