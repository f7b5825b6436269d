"""One voxel array of paper 000: bit-packed voxelizations of one geometry in every direction bin.

An array covers its geometry's bounding sphere (so every direction's rotated cube holds it; a
world-space array's box is first stretched toward a cube, :func:`normalizing_transform`). This module
builds arrays (Alg. 1, :func:`build_array`), keys and caches them (:func:`array_key`,
:func:`cached_array`, in the compact form of :mod:`usdml.visibility.voxel.codec`), says what they
cost (:func:`array_cost`, :func:`available_memory`) and holds the Warp helpers the builders share
(:func:`warp_module`, :func:`clear_words`, :func:`host_words`).
The backend that assembles arrays and answers queries is :mod:`usdml.visibility.voxel.backend`; Alg. 5's
rebuild is :mod:`usdml.visibility.voxel.rotate`; directions, rows and packing are in
:mod:`usdml.visibility.voxel.grid`, the kernels in :mod:`usdml.kernels.voxel.query`.

Building (Alg. 1)
    The paper depth-peels the rotated scene along three axes. Here each direction's voxelization
    sets, for every row, the voxels where the row's centre line crosses a triangle: each triangle is
    rasterized onto the rows whose centres its projection holds (``CORE`` 0,
    ``kernels.voxel.voxelize_triangles``). The lines of the other two axes (the paper's other two
    peels) add voxels only where a surface runs along the rows, which rays in that direction barely
    see: measured on the city at 128³ / 2° they made ε_v / ε_s worse (1.99 / 1.25 % -> 2.38 /
    1.91 %, more wrongly hidden rays) and the build 2x longer, so they are not peeled. The older rule,
    ``core`` > 0, samples every triangle on a lattice finer than a voxel and sets the voxel holding
    each rotated sample that lies in the central ``core`` fraction of its row: a cost set by surface
    area, and thicker surfaces. Directions are split over the CPU cores.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
import os
import time
from typing import Callable

import numpy as np

from usdml.cache import Cache, cache_key
from usdml.parallel import cpu_workers, iter_parallel
from usdml.scene import content_hash
from usdml.visibility.voxel import codec as voxel_codec
from usdml.visibility.voxel.grid import DirectionBins, RowLayout, clip_to_box, surface_samples

log = logging.getLogger("usdml")

__all__ = ["VoxelArray", "array_cost", "array_cube", "array_key", "available_memory", "bounding_sphere",
           "build_array", "cached_array", "clear_words", "host_words", "normalizing_transform",
           "run_direction_chunks", "voxel_kernels", "warp_module"]

#: bump when the bits an array holds for the same inputs change
FORMAT_VERSION = 2
#: sample spacing and dedup grid as fractions of the voxel size times the core fraction: a plane
#: crossing a row's axis then has a sample within 0.58 · 0.5 + 1.73 · 0.12 = 0.5 of its core's
#: half width of the crossing, inside the core (no holes along rows; see voxel.grid)
SAMPLE_SPACING = 0.5
SNAP = 0.12
#: the voxelization rule of the arrays built once and cached (static scene, prototypes): 0 marks
#: the voxels where rows' centre lines cross the surface (rasterized, module doc); a fraction > 0
#: marks the voxel of every surface sample lying in that central part of its row's square
#: (kernels.voxel.voxelize: 1 is every voxel a surface touches, occluders a voxel fatter). Measured
#: at 128³ / 2° on the city (ε_v / ε_s, build): 1: 2.8 / 2.4 %, 59 s; 0.5: 2.13 / 1.63 %, 155 s;
#: 0: 1.99 / 1.25 %, 50-58 s.
CORE = 0.0
#: margin on the bounding sphere so that float rounding never puts a sample outside the cube
SPHERE_MARGIN = 1.002


@dataclass
class VoxelArray:
    """One array: bit-packed voxelizations of one geometry in every direction bin."""

    words: np.ndarray           #: (directions * words_per_direction,) uint32
    center: np.ndarray          #: (3,) float64 bounding-sphere centre (array space)
    half: float                 #: half size of the cube = sphere radius × margin
    resolution: int
    step: float
    samples: int = 0            #: items voxelized: surface samples (``core`` > 0) or triangles (0)
    build_seconds: float = 0.0  #: 0 when loaded from the cache
    sample_seconds: float = 0.0  #: part of build_seconds spent preparing the geometry (sampling)
    occupied: int = 0           #: occupied voxels of the reference voxelization (Alg. 5 rebuilds)
    key: str = ""
    source: str = ""            #: what it holds (for messages)
    cached: bool = False
    #: (4, 4) world (or prototype) space -> array space; world-space arrays are stretched so that
    #: their box is closer to a cube (:func:`normalizing_transform`)
    to_array: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def nbytes(self) -> int:
        return int(self.words.nbytes)

    @property
    def voxel_size(self) -> float:
        return 2.0 * self.half / self.resolution


def array_cost(resolution: int, step: float) -> int:
    """Bytes of one array at ``resolution``³ / ``step`` degrees (said before building)."""
    return DirectionBins.make(step).count * RowLayout.make(resolution).words * 4


#: largest stretch between the axes of a world-space array's box (normalizing_transform)
MAX_ANISOTROPY = 4.0


def normalizing_transform(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """World -> array space for a world-space array covering box ``[lo, hi]``: centred on the box,
    each axis scaled so its extent approaches the longest one (by at most ``MAX_ANISOTROPY``).

    A city is wide and flat (350 × 106 × 350 here) and its lights hang a few metres above the street:
    with cubic voxels the vertical resolution is that of the widest axis and rays grazing the street
    run inside the street's voxel layer. Stretching the box to a cube gives every axis the same number
    of voxels; rows stay straight lines in world space, so queries just move their endpoints (the
    same path as instances, Alg. 4).
    """
    ext = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    top = float(ext.max()) if ext.max() > 0 else 1.0
    scale = top / np.maximum(ext, top / MAX_ANISOTROPY)
    m = np.eye(4)
    m[:3, :3] = np.diag(scale)
    m[:3, 3] = -scale * 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    return m


def available_memory() -> int:
    """Bytes of memory this process can still take (``MemAvailable``), or physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 40


def warp_module():
    """The initialized, quiet ``warp`` module (imported on first use: listing or planning arrays needs no Warp)."""
    from usdml.kernels import warp

    return warp()


def voxel_kernels():
    """:mod:`usdml.kernels.voxel.query` (Alg. 1 and 2), imported on first use."""
    from usdml.kernels.voxel import query as voxel

    return voxel


def bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre of the bounding box and the largest distance of a point from it."""
    lo, hi = points.min(axis=0).astype(np.float64), points.max(axis=0).astype(np.float64)
    c = 0.5 * (lo + hi)
    r = float(np.sqrt(((points.astype(np.float64) - c) ** 2).sum(axis=1).max()))
    return c, max(r, 1e-6 * max(1.0, float(np.abs(c).max())), 1e-9)


def array_cube(points: np.ndarray, triangles: np.ndarray, bounds: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The geometry an array holds and its cube: ``(points, triangles, centre, half size)``.

    ``bounds`` (a box) restricts the array to that box (triangles are clipped to it); default: all
    of the geometry.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if bounds is not None:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
        points, triangles, _ = clip_to_box(points, triangles, lo, hi)
        center, radius = 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-9)
    else:
        center, radius = bounding_sphere(points[np.unique(triangles)] if len(triangles) else points)
    return points, triangles, center, float(radius * SPHERE_MARGIN)


def sample_spacing(half: float, resolution: int, core: float) -> float:
    """Largest distance between surface samples for an array of ``resolution`` over half size ``half``."""
    return SAMPLE_SPACING * core * 2.0 * half / resolution


def prepare_geometry(points: np.ndarray, triangles: np.ndarray, resolution: int,
                     bounds: tuple[np.ndarray, np.ndarray] | None, core: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Alg. 1's input for the sampled rule (``core`` > 0): the array's cube (centre, half size,
    :func:`array_cube`) and the surface samples that mark voxels."""
    points, triangles, center, half = array_cube(points, triangles, bounds)
    h = 2.0 * half / resolution
    return center, half, surface_samples(points, triangles, sample_spacing(half, resolution, core), snap=SNAP * core * h)


def run_direction_chunks(n_dirs: int, per: int, launch: Callable[[int, int], int], device,
                         workers: int | None = None, progress: Callable[[int, int], None] | None = None) -> None:
    """``launch(d0, d1)`` over directions ``0 … n_dirs`` in chunks of ``per``: over the CPU cores (the
    first chunk alone first: it compiles or loads the module before threads race for it), or one
    after another on a GPU; ``progress(done, n_dirs)`` after each chunk."""
    chunks = [(d0, min(n_dirs, d0 + per)) for d0 in range(0, n_dirs, max(1, per))]
    done = 0
    for k in iter_parallel(lambda c: launch(*c), chunks, cpu_workers(device, workers), first_on_caller=True):
        done += k
        if progress:
            progress(done, n_dirs)


def build_array(points: np.ndarray, triangles: np.ndarray, resolution: int, step: float, *,
                device: str = "cpu", workers: int | None = None,
                progress: Callable[[int, int], None] | None = None, source: str = "",
                bounds: tuple[np.ndarray, np.ndarray] | None = None, core: float | None = None,
                out=None, base: int = 0) -> VoxelArray:
    """Alg. 1: voxelize triangles ``(points, triangles)`` (array space) in every direction bin.

    ``core``: the rule (module doc), default ``CORE``: 0 rasterizes the rows' centre lines
    (``kernels.voxel.voxelize_triangles``), > 0 voxelizes surface samples lying in that central
    fraction of their row (``kernels.voxel.voxelize``). ``bounds``: see :func:`array_cube`.
    ``progress(done, total)`` is called with directions finished. ``out``: a Warp ``uint32`` array
    to fill in place from word ``base`` (see :func:`usdml.visibility.voxel.rotate.rotate_array`);
    default: a new array.
    """
    wp = warp_module()
    k = voxel_kernels()
    t0 = time.perf_counter()
    core = CORE if core is None else float(core)
    bins = DirectionBins.make(step)
    layout = RowLayout.make(resolution)
    if core > 0:
        center, half, samples = prepare_geometry(points, triangles, resolution, bounds, core)
        items = len(samples)
    else:
        points, triangles, center, half = array_cube(points, triangles, bounds)
        items = len(triangles)
    sample_seconds = time.perf_counter() - t0
    n_dirs, wpd = bins.count, layout.words
    dev = wp.get_device(device)
    out_np = None
    if out is None:
        out_np = np.zeros(n_dirs * wpd, np.uint32)
        out = wp.array(out_np, dtype=wp.uint32, device=dev, copy=not dev.is_cpu)
        base = 0
    else:
        clear_words(out, base, n_dirs * wpd, dev)
    if items:
        rows = [wp.array(a, dtype=wp.int32, device=dev) for a in (layout.w0, layout.nw, layout.offset)]
        frames = wp.array(bins.frames, dtype=wp.mat33, device=dev)
        c32 = wp.vec3(*center.astype(np.float32))
        chunk = items if dev.is_cpu else 4096
        n_chunks = -(-items // chunk)
        if core > 0:
            kernel, head = k.voxelize, [wp.array(samples, dtype=wp.vec3, device=dev), c32, float(half), resolution, core]
            tail, per_item = [out], 1
        else:
            kernel = k.voxelize_triangles
            head = [wp.array(points.astype(np.float32), dtype=wp.vec3, device=dev),
                    wp.array(triangles.astype(np.int32), dtype=wp.vec3i, device=dev), c32, float(half), resolution]
            tail, per_item = [int(not dev.is_cpu), out], 4

        def launch(d0, d1):
            wp.launch(kernel, dim=(d1 - d0, n_chunks), device=dev,
                      inputs=head + [frames, d0, chunk] + rows + [wpd, int(base)] + tail)
            return d1 - d0

        # directions per launch: enough work per launch, frequent progress
        run_direction_chunks(n_dirs, max(1, min(n_dirs, (1 << 24) // max(items * per_item, 1))), launch, dev,
                             workers, progress)
    arr = VoxelArray(host_words(out, out_np, base, n_dirs * wpd, dev), center, float(half), resolution,
                     float(step), int(items), time.perf_counter() - t0, sample_seconds, source=source)
    log.debug(f"voxel array {source}: {items} {'samples' if core > 0 else 'triangles'} ready in "
              f"{sample_seconds:.2f} s, {n_dirs} directions in {arr.build_seconds - sample_seconds:.2f} s")
    return arr


def clear_words(out, base: int, count: int, dev) -> None:
    """Zero words ``base … base + count`` of Warp array ``out``."""
    if dev.is_cpu:
        out.numpy()[base:base + count] = 0
    else:
        out[base:base + count].zero_()


def host_words(out, out_np, base: int, count: int, dev) -> np.ndarray:
    """The words an in-place or new build wrote: a view on CPU, a copy from a GPU for a new array,
    and empty for an in-place GPU build (they stay on the device)."""
    wp = warp_module()
    if not dev.is_cpu:
        wp.synchronize_device(dev)
        return out.numpy() if out_np is not None else np.zeros(0, np.uint32)
    return out_np if out_np is not None else out.numpy()[base:base + count]


def array_key(points: np.ndarray, triangles: np.ndarray, resolution: int, step: float, bounds=None,
              core: float | None = None) -> str:
    """Cache key of the array of ``(points, triangles)`` at these parameters (with :data:`FORMAT_VERSION`)."""
    box = None if bounds is None else [np.asarray(b, np.float64).round(9).tolist() for b in bounds]
    return cache_key("voxel-array", FORMAT_VERSION, SAMPLE_SPACING, SNAP, SPHERE_MARGIN, int(resolution), float(step),
                     box, float(CORE if core is None else core), content_hash(np.asarray(points, np.float32), np.asarray(triangles, np.int32)))


def cached_array(points, triangles, resolution: int, step: float, cache: Cache | None, *,
                 device: str = "cpu", progress=None, source: str = "", bounds=None, core=None) -> VoxelArray:
    """The array of ``(points, triangles)``, from ``cache`` when it holds a valid copy, else built
    (and stored). A damaged entry is reported and rebuilt."""
    key = array_key(points, triangles, resolution, step, bounds, core)
    if cache is not None:
        got = cache.load("voxel", key)
        words = None if got is None else _expand(cache, key, *got, resolution)
        if words is not None:
            meta = got[1]
            return VoxelArray(words, np.asarray(meta["center"], np.float64), float(meta["half"]),
                              int(meta["resolution"]), float(meta["step"]), int(meta.get("samples", 0)),
                              key=key, source=source, cached=True)
    arr = build_array(points, triangles, resolution, step, device=device, progress=progress, source=source,
                      bounds=bounds, core=core)
    arr.key = key
    if cache is not None:
        packed, codec = voxel_codec.encode(arr.words, resolution)
        cache.store("voxel", key, packed, {"center": arr.center.tolist(), "half": arr.half,
                                           "resolution": resolution, "step": step, "samples": arr.samples,
                                           "format": FORMAT_VERSION, "source": source, **codec})
    return arr


def _expand(cache: Cache, key: str, packed: np.ndarray, meta: dict, resolution: int) -> np.ndarray | None:
    """The words of a loaded entry (:mod:`usdml.visibility.voxel.codec`); None (entry removed, a
    warning) when they do not decode."""
    try:
        return voxel_codec.decode(packed, meta, resolution)
    except (ValueError, KeyError, TypeError) as e:
        path = cache.path("voxel", key)
        log.warning(f"voxel cache: {path}: does not decode ({e}); rebuilding")
        path.unlink(missing_ok=True)
        return None
