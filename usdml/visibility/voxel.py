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
      by Alg. 5 (one voxelization rotated, :mod:`usdml.visibility.voxel_rotate`) or Alg. 1, written
      into its slot of the assembled words (nothing reallocated or copied per frame).

    Every array covers its geometry's bounding sphere (so every direction's rotated cube holds it);
    directions, rows and packing are in :mod:`usdml.visibility.voxel_grid`, the kernels in
    :mod:`usdml.kernels.voxel`.

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
    2.43 / 1.53 -> 2.31 / 1.39, creature 1.80 / 1.11 -> 1.81 / 1.13, park 17.8 / 7.1 -> 17.5 / 6.9
    (-> 18.7 / 7.8: its grazing ground rays start hidden). With Alg. 5's conservative mapping the
    per-frame surfaces are about two voxels thick and 2 is too short (park 29.9 / 25.1 -> 38.1 /
    34.9 %), so it keeps 4 (``CONSERVATIVE_MAX_SKIP``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import logging
import os
import time
from typing import Callable

import numpy as np

from usdml.cache import Cache, CacheCorrupt, cache_key
from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, iter_parallel, run_parallel
from usdml.scene import Changes, Lights, Snapshot, content_hash
from usdml.settings import VOXEL_REBUILDS
from usdml.visibility.base import VisibilityBackend, as_flags, as_vectors, members_changed
from usdml.visibility.voxel_grid import DirectionBins, RowLayout, clip_to_box, core_bounds, surface_samples

log = logging.getLogger("usdml")

__all__ = ["VoxelArray", "VoxelBackend", "build_array", "array_cost", "available_memory"]

#: bump when the bits an array holds for the same inputs change
FORMAT_VERSION = 2
#: how the per-frame array is rebuilt: Alg. 5 (rotate one voxelization) or Alg. 1 (every direction)
REBUILDS = VOXEL_REBUILDS
#: sample spacing and dedup grid as fractions of the voxel size times the core fraction: a plane
#: crossing a row's axis then has a sample within 0.58 · 0.5 + 1.73 · 0.12 = 0.5 of its core's
#: half width of the crossing, inside the core (no holes along rows; see voxel_grid)
SAMPLE_SPACING = 0.5
SNAP = 0.12
#: the voxelization rule of the arrays built once and cached (static scene, prototypes): 0 marks
#: the voxels where rows' centre lines cross the surface (rasterized, module doc); a fraction > 0
#: marks the voxel of every surface sample lying in that central part of its row's square
#: (kernels.voxel.voxelize: 1 is every voxel a surface touches, occluders a voxel fatter). Measured
#: at 128³ / 2° on the city (ε_v / ε_s, build): 1: 2.8 / 2.4 %, 59 s; 0.5: 2.13 / 1.63 %, 155 s;
#: 0: 1.99 / 1.25 %, 50-58 s.
CORE = 0.0
#: the same for per-frame arrays rebuilt by Alg. 1 (``rebuild="geometry"``). Measured at 128³ / 2°
#: (ε_v / ε_s, rebuild): creature 1: 1.85 / 1.19 %, 6.4 s; 0: 1.77 / 1.08 %, 1.3 s; park 1: 32.0 /
#: 29.0 %, 3.0 s; 0: 19.0 / 9.6 %, 1.6 s. (Alg. 5's reference voxelization has its own rule:
#: voxel_rotate.)
PER_FRAME_CORE = 0.0
#: most voxels a grazing shadow ray skips to leave its surface (module doc, "Leaving the surface"),
#: and with Alg. 5's conservative mapping, whose per-frame surfaces are about two voxels thick
MAX_SKIP = 2.0
CONSERVATIVE_MAX_SKIP = 4.0
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


#: points per tile of the CPU shading kernel (kernels.voxel.shade_tiles)
SHADE_TILE = 64


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting ``points`` along a Z-order curve of a 2^10 grid over their bounds."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


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


def _wp():
    from usdml.kernels import warp

    return warp()


def _kernels():
    from usdml.kernels import voxel

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
    to fill in place from word ``base`` (see :func:`usdml.visibility.voxel_rotate.rotate_array`);
    default: a new array.
    """
    wp = _wp()
    k = _kernels()
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
    arr = VoxelArray(_host_words(out, out_np, base, n_dirs * wpd, dev), center, float(half), resolution,
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


def _host_words(out, out_np, base: int, count: int, dev) -> np.ndarray:
    """The words an in-place or new build wrote: a view on CPU, a copy from a GPU for a new array,
    and empty for an in-place GPU build (they stay on the device)."""
    wp = _wp()
    if not dev.is_cpu:
        wp.synchronize_device(dev)
        return out.numpy() if out_np is not None else np.zeros(0, np.uint32)
    return out_np if out_np is not None else out.numpy()[base:base + count]


def array_key(points: np.ndarray, triangles: np.ndarray, resolution: int, step: float, bounds=None,
              core: float | None = None) -> str:
    box = None if bounds is None else [np.asarray(b, np.float64).round(9).tolist() for b in bounds]
    return cache_key("voxel-array", FORMAT_VERSION, SAMPLE_SPACING, SNAP, SPHERE_MARGIN, int(resolution), float(step),
                     box, float(CORE if core is None else core), content_hash(np.asarray(points, np.float32), np.asarray(triangles, np.int32)))


def cached_array(points, triangles, resolution: int, step: float, cache: Cache | None, *,
                 device: str = "cpu", progress=None, source: str = "", bounds=None, core=None) -> VoxelArray:
    """The array of ``(points, triangles)``, from ``cache`` when it holds a valid copy, else built
    (and stored). A damaged entry is reported and rebuilt."""
    key = array_key(points, triangles, resolution, step, bounds, core)
    if cache is not None:
        try:
            got = cache.get("voxel", key)
        except CacheCorrupt as e:
            log.warning(f"voxel cache: {e}; rebuilding")
            got = None
        if got is not None:
            words, meta = got
            return VoxelArray(words, np.asarray(meta["center"], np.float64), float(meta["half"]),
                              int(meta["resolution"]), float(meta["step"]), int(meta.get("samples", 0)),
                              key=key, source=source, cached=True)
    arr = build_array(points, triangles, resolution, step, device=device, progress=progress, source=source,
                      bounds=bounds, core=core)
    arr.key = key
    if cache is not None:
        try:
            cache.put("voxel", key, arr.words, {"center": arr.center.tolist(), "half": arr.half,
                                                "resolution": resolution, "step": step, "samples": arr.samples,
                                                "format": FORMAT_VERSION, "source": source})
        except OSError as e:
            log.warning(f"voxel cache: could not write {cache.path('voxel', key)} ({e}); continuing without it")
    return arr


@dataclass
class _Group:
    members: tuple
    array: VoxelArray | None
    geometry_key: str = ""


def _world_geometry(snapshot: Snapshot, members) -> tuple[np.ndarray, np.ndarray]:
    from usdml.scene import world_geometry

    return world_geometry(snapshot, members)


class VoxelBackend(VisibilityBackend):
    """Shadow rays by paper 000's voxel arrays (see the module doc for what is built and the costs).

    Parameters
    ----------
    resolution : voxels per axis of each direction's voxelization (default 128)
    step : direction bin step in degrees (default 2)
    device : Warp device, ``cpu`` or ``cuda``
    cache : a :class:`usdml.cache.Cache`, a folder, or None for the default folder; ``False``: no cache
    memory_limit : bytes the arrays may take; default: what the machine has available
    normal_offset, skip, slab, max_skip, end_skip : leaving the surface, in voxels (module doc);
        ``max_skip`` defaults to ``MAX_SKIP``, or ``CONSERVATIVE_MAX_SKIP`` with the conservative mapping
    segment : voxels looked up per row (a divisor of 32): the ray picks its row anew every segment
    core, frame_core : the voxelization rule of cached arrays (default ``CORE``) and of per-frame
        arrays rebuilt by Alg. 1 (``PER_FRAME_CORE``): 0, the default, rasterizes rows' centre
        lines; a fraction > 0 is the central part of a row a surface sample must lie in
    rebuild : how the per-frame array (deforming meshes, or everything when ``fully_dynamic``) is
        rebuilt: ``rotate`` (Alg. 5, :mod:`usdml.visibility.voxel_rotate`) or ``geometry`` (Alg. 1)
    mapping : Alg. 5's ``point`` (the paper) or ``conservative`` mapping of rotated voxels
    fully_dynamic : put every mesh and instance in the per-frame array (``usdml:voxel:fullyDynamic``:
        scenes where much moves), instead of a static array plus one array per moving prototype
    report : called with one line before anything is built (cost of each array), default: log.info
    progress : ``progress(done, total, label)`` while building

    After each :meth:`update`, ``built`` lists the arrays it built or loaded (empty when nothing
    changed that arrays hold: moving lights or a moving camera cost nothing) and ``stats`` holds the
    counts, bytes and ``dynamic_seconds`` of the last per-frame rebuild.
    """

    name = "voxel"

    def __init__(self, *, resolution: int = 128, step: float = 2.0, device: str = "cpu", cache=None,
                 memory_limit: int | None = None, normal_offset: float = 1.0, skip: float = 1.0,
                 slab: float = 1.0, max_skip: float | None = None, end_skip: float = 1.0, segment: int = 32,
                 core: float | None = None, frame_core: float | None = None, rebuild: str = "rotate",
                 mapping: str = "point",
                 fully_dynamic: bool = False, workers: int | None = None, report: Callable[[str], None] | None = None,
                 progress: Callable[[int, int, str], None] | None = None) -> None:
        self.resolution = int(resolution)
        self.step = float(step)
        if not (4 <= self.resolution <= 2048):
            raise UsdmlError(f"voxel resolution must be in [4, 2048], got {self.resolution}")
        if not (0.1 <= self.step <= 90):
            raise UsdmlError(f"direction step must be in [0.1, 90] degrees, got {self.step:g}")
        if segment not in (1, 2, 4, 8, 16, 32):
            raise UsdmlError(f"voxel segment must divide 32, got {segment}")
        if rebuild not in REBUILDS:
            raise UsdmlError(f"voxel rebuild must be one of {', '.join(REBUILDS)}, got {rebuild!r}")
        from usdml.visibility.voxel_rotate import MAPPINGS
        if mapping not in MAPPINGS:
            raise UsdmlError(f"voxel mapping must be one of {', '.join(MAPPINGS)}, got {mapping!r}")
        self.rebuild, self.mapping, self.fully_dynamic = rebuild, mapping, bool(fully_dynamic)
        self.device = device
        self.core = CORE if core is None else float(core)
        self.frame_core = PER_FRAME_CORE if frame_core is None else float(frame_core)
        for name, value in (("core", self.core), ("frame core", self.frame_core)):
            if not (0.0 <= value <= 1.0):
                raise UsdmlError(f"voxel {name} must be in [0, 1] (0: rows' centre lines), got {value:g}")
        self.cache = None if cache is False else (cache if isinstance(cache, Cache) else Cache(cache))
        self.memory_limit = memory_limit
        self.normal_offset, self.skip, self.slab = float(normal_offset), float(skip), float(slab)
        if max_skip is None:
            max_skip = MAX_SKIP if self.mapping == "point" else CONSERVATIVE_MAX_SKIP
        self.max_skip, self.end_skip, self.segment = float(max_skip), float(end_skip), int(segment)
        self.workers = cpu_workers("cpu", workers)
        self.report = report or (lambda line: log.info(line))
        self.progress = progress
        self.bins = DirectionBins.make(self.step)
        self.layout = RowLayout.make(self.resolution)
        self._static: _Group | None = None
        self._deforming: _Group | None = None
        self._protos: dict[str, VoxelArray] = {}      # prototype geometry hash -> array
        self._gpu: dict = {}
        self._scene = None
        self.stats: dict = {"builds": 0, "loaded": 0, "build_seconds": 0.0, "bytes": 0, "arrays": 0,
                            "dynamic_rebuilds": 0, "dynamic_seconds": 0.0}
        self.built: list[str] = []
        self._reported: set[str] = set()

    # ------------------------------------------------------------------ building

    def _array(self, points, triangles, source: str, cacheable: bool = True, trim: bool = False,
               per_frame: bool = False, out=None, base: int = 0) -> VoxelArray:
        """Build (or load) the array of ``(points, triangles)``; ``trim``: a world-space array (trimmed
        box stretched to a cube); ``per_frame``: the per-frame array, rebuilt by ``self.rebuild``
        (into ``out`` from word ``base`` when given)."""
        def prog(done, total):
            if self.progress:
                self.progress(done, total, source)
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
                from usdml.visibility.voxel_rotate import rotate_array
                arr = rotate_array(points, triangles, self.resolution, self.step, mapping=self.mapping,
                                   device=self.device, workers=self.workers, bounds=bounds,
                                   out=out, base=base, progress=prog, source=source)
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
        """The arrays ``snapshot`` needs (:func:`usdml.voxel_budget.array_roles`)."""
        from usdml.voxel_budget import array_roles

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
        roles = dict(plan)
        static = roles.get("static")
        per_frame = roles.get("deforming", roles.get("dynamic"))
        if per_frame is not None and self.rebuild == "rotate":
            from usdml.visibility.voxel_rotate import MAX_RESOLUTION
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
            pts, tris = _world_geometry(snapshot, static)
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
            pts, tris = _world_geometry(snapshot, per_frame)
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
        pts, tris = _world_geometry(snapshot, self._deforming.members)
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
        """Concatenate the arrays for the kernels and rebuild the instance table and BVH."""
        wp = _wp()
        dev = wp.get_device(self.device)
        arrays: list[VoxelArray] = []
        static_ids = []
        for g in (self._static, self._deforming):
            if g is not None and g.array is not None:
                static_ids.append(len(arrays))
                arrays.append(g.array)
        proto_index = {}
        for h, a in self._protos.items():
            proto_index[h] = len(arrays)
            arrays.append(a)
        if rebuild_words or self._gpu.get("n_arrays") != len(arrays):
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
            self._gpu = g
            self.stats["bytes"] = int(sum(a.words.size for a in arrays) * 4)
            self.stats["arrays"] = len(arrays)
        g = self._gpu
        # cubes move with the per-frame array: refreshed every frame (a few floats per array)
        g["center"] = wp.array(np.array([a.center for a in arrays] or [[0, 0, 0]], np.float32), dtype=wp.vec3, device=dev)
        g["half"] = wp.array(np.array([a.half for a in arrays] or [1.0], np.float32), dtype=float, device=dev)
        # the static and deforming arrays are both world space; with both, the deforming one is
        # visited as an identity "instance" so a query still tests both
        inv, ids, lo, hi = [], [], [], []
        extra = static_ids[1:]
        for a_id in extra:
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
        n_inst = 0
        if inv:
            inv_m = np.concatenate([np.asarray(m).reshape(-1, 4, 4) for m in inv]).astype(np.float32)
            ids_a = np.concatenate([np.atleast_1d(i) for i in ids]).astype(np.int32)
            lo_a = np.concatenate([np.asarray(x).reshape(-1, 3) for x in lo]).astype(np.float32)
            hi_a = np.concatenate([np.asarray(x).reshape(-1, 3) for x in hi]).astype(np.float32)
            n_inst = len(ids_a)
            g["inst_inv"] = wp.array(inv_m, dtype=wp.mat44, device=dev)
            g["inst_array"] = wp.array(ids_a, dtype=wp.int32, device=dev)
            g["lowers"] = wp.array(lo_a, dtype=wp.vec3, device=dev)
            g["uppers"] = wp.array(hi_a, dtype=wp.vec3, device=dev)
            g["bvh"] = wp.Bvh(g["lowers"], g["uppers"])
            g["bvh_id"] = g["bvh"].id
        else:
            g["inst_inv"] = wp.zeros(1, dtype=wp.mat44, device=dev)
            g["inst_array"] = wp.zeros(1, dtype=wp.int32, device=dev)
            g["bvh"] = None
            g["bvh_id"] = wp.uint64(0)
        g["n_inst"] = n_inst
        g["static"] = static_ids[0] if static_ids else -1
        g["static_inv"] = wp.mat44(*(arrays[static_ids[0]].to_array if static_ids else np.eye(4)).astype(np.float32).ravel())
        # world units: offset by the static array's voxel (its smallest world extent), else the finest array's
        if static_ids:
            a = arrays[static_ids[0]]
            self.reference_voxel = a.voxel_size / float(np.max(np.abs(np.diag(a.to_array)[:3])))
        else:
            self.reference_voxel = min((a.voxel_size for a in arrays), default=0.0)
        bounds = snapshot.world_bounds()
        if bounds is not None:
            lo_b, hi_b = (np.asarray(b, np.float64) for b in bounds)
            self._scene = (0.5 * (lo_b + hi_b), 0.5 * float(np.linalg.norm(hi_b - lo_b)))
        else:
            self._scene = (np.zeros(3), 1.0)
        self.arrays = arrays

    # ------------------------------------------------------------------ queries

    def _scene_struct(self):
        """The arrays as the kernels' ``VoxelScene``."""
        g, k = self._gpu, _kernels()
        vs = k.VoxelScene()
        vs.words, vs.arr_center, vs.arr_half, vs.arr_int = g["words"], g["center"], g["half"], g["int"]
        vs.row_w0, vs.row_nw, vs.row_off, vs.frames = g["w0"], g["nw"], g["off"], g["frames"]
        vs.d_theta, vs.ring_count, vs.ring_start = float(self.bins.d_theta), g["ring_count"], g["ring_start"]
        vs.static_array, vs.static_inv = int(g["static"]), g["static_inv"]
        vs.bvh, vs.n_inst, vs.inst_inv, vs.inst_array = g["bvh_id"], int(g["n_inst"]), g["inst_inv"], g["inst_array"]
        return vs

    def _ray_rule(self):
        """The kernels' ``RayRule``."""
        c, r = self._scene
        rule = _kernels().RayRule()
        rule.offset = float(self.normal_offset * self.reference_voxel)
        rule.skip, rule.slab, rule.max_skip, rule.end_skip = self.skip, self.slab, self.max_skip, self.end_skip
        # a distant ray ends its distance from the scene's centre plus the scene's diameter away
        # (per ray, in the kernel: a reduction over millions of origins cost a quarter of a query)
        rule.far, rule.far_center = 2.0 * r + 1.0, _wp().vec3(*np.asarray(c, np.float32))
        rule.seg = self.segment
        return rule

    def _split(self, n: int, launch: Callable[[int, int], None]) -> None:
        """Run ``launch(first, count)`` over ``n`` items: one launch on a GPU, bands over threads on CPU."""
        wp = _wp()
        dev = wp.get_device(self.device)
        if n == 0:
            return
        if not dev.is_cpu:
            launch(0, n)
            wp.synchronize_device(dev)
            return
        bands = min(n, self.workers * 8)
        edges = np.linspace(0, n, bands + 1).astype(np.int64)
        jobs = [(int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        run_parallel(lambda j: launch(*j), jobs, self.workers, first_on_caller=True)

    def hit_distances(self, origins, targets, *, normals=None, distant=None, want_distance: bool = True) -> np.ndarray:
        """Distance in voxels from each ray's (offset, skipped) start to the first occupied voxel; -1: free."""
        if not self._gpu:
            raise RuntimeError("VoxelBackend.update() must be called before queries")
        wp = _wp()
        k = _kernels()
        dev = wp.get_device(self.device)
        # float32 once, and on CPU wrapped rather than copied again
        origins = np.ascontiguousarray(as_vectors(origins, "origins", dtype=np.float32))
        n = origins.shape[0]
        targets = np.ascontiguousarray(as_vectors(targets, "targets", n, dtype=np.float32))
        normals = np.zeros((n, 3), np.float32) if normals is None else \
            np.ascontiguousarray(as_vectors(normals, "normals", n, dtype=np.float32))
        distant = np.zeros(n, np.int32) if distant is None else as_flags(distant, "distant", n).astype(np.int32)
        out = wp.zeros(n, dtype=float, device=dev)
        if n == 0 or self._gpu["n_arrays"] == 0:
            return np.full(n, -1.0, np.float32)
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

    def occluded(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        return self.hit_distances(origins, targets, normals=normals, distant=distant, want_distance=False) >= 0.0

    def shade_direct(self, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
                     progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
                     min_distance: float = 0.0, geometric: np.ndarray | None = None):
        """Alg. 3 in one kernel: every pixel against every light with voxel shadow rays; the same
        shading as :func:`usdml.lighting.direct.shade_direct` (returns its ``DirectResult``)."""
        from usdml.lighting.direct import DirectResult, LightTable, cone_edges

        wp = _wp()
        k = _kernels()
        dev = wp.get_device(self.device)
        n_p, n_l = len(points), len(lights)
        if n_p == 0 or n_l == 0 or not self._gpu:
            from usdml.lighting.direct import shade_direct
            return shade_direct(points, normals, albedo, lights, self.occluded if self._gpu else None,
                                progress, meters_per_unit=meters_per_unit, min_distance=min_distance,
                                geometric=geometric)
        t = LightTable(lights, meters_per_unit, min_distance)
        flags = t.flags
        outer, width = cone_edges(lights.cone_angle, lights.cone_softness)
        cone = np.stack([outer, np.where(width <= 1e-12, 0.0, width), lights.focus], axis=1).astype(np.float32)
        pts = np.asarray(points, np.float32)
        lt = k.LightTable()
        lt.pos = wp.array(lights.position.astype(np.float32), dtype=wp.vec3, device=dev)
        lt.axis = wp.array(lights.axis.astype(np.float32), dtype=wp.vec3, device=dev)
        lt.flags = wp.array(flags.astype(np.int32), dtype=wp.int32, device=dev)
        lt.cylinder_axis = wp.array(np.ascontiguousarray(t.cylinder_axis.T), dtype=wp.vec3, device=dev)
        lt.cone = wp.array(cone, dtype=wp.vec3, device=dev)
        lt.base = wp.array(t.base, dtype=wp.vec3, device=dev)
        lt.focus_rgb = wp.array(t.focus_rgb, dtype=wp.vec3, device=dev)
        lt.inv_m2, lt.min_d2 = float(t.inv_m2), float(t.min_d2)
        rad = wp.zeros(n_p, dtype=wp.vec3, device=dev)
        blocked = wp.zeros(n_p, dtype=wp.int32, device=dev)
        facing = wp.zeros(n_p, dtype=wp.int32, device=dev)
        rule, vs = self._ray_rule(), self._scene_struct()
        # tiles of spatially coherent points (Morton order of their cells): one light's rays from a
        # tile share bins and rows (kernels.voxel.shade_tiles); on a GPU one point per tile
        tile = SHADE_TILE if dev.is_cpu else 1
        order = morton_order(pts) if tile > 1 else np.arange(n_p)
        p_wp = wp.array(pts[order], dtype=wp.vec3, device=dev)
        n_wp = wp.array(np.asarray(normals, np.float32)[order], dtype=wp.vec3, device=dev)
        g_wp = n_wp if geometric is None else wp.array(np.asarray(geometric, np.float32)[order], dtype=wp.vec3,
                                                       device=dev)
        n_tiles = -(-n_p // tile)

        def launch(first_tile, count):
            wp.launch(k.shade_tiles, dim=count, device=dev,
                      inputs=[p_wp, n_wp, g_wp, first_tile * tile, tile, lt, rule, vs, rad, blocked, facing])
            if progress is not None:
                progress(min(n_p, (first_tile + count) * tile) - first_tile * tile)
        self._split(n_tiles, launch)
        inverse = np.empty_like(order)
        inverse[order] = np.arange(n_p)
        radiance = rad.numpy()[inverse] * (np.asarray(albedo, np.float32) / np.float32(np.pi))
        fac = facing.numpy()[inverse]
        blk = blocked.numpy()[inverse]
        shadow = np.where(fac > 0, blk / np.maximum(fac, 1), 0.0).astype(np.float32)
        queries = int(fac.sum()) if t.casts.all() else -1
        return DirectResult(radiance.astype(np.float32), shadow, fac.astype(np.int32), queries)

    def close(self) -> None:
        self._gpu = {}
