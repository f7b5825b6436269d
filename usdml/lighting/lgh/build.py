"""Lighting grid hierarchy construction (paper 004 §3.1) over point lights such as VPLs.

Grid geometry. The hierarchy spans the bounding box of the lights, with its origin at the box's
min corner. The top level L is a single cell whose edge is the box's longest edge, so
``h_L = max(hi - lo)`` and ``h_l = h_1 · 2^(l-1)`` with ``h_1 = h_L / 2^(L-1)`` (scene units). Level 1
(S1) has ``c = ceil(extent / h_1)`` cells per axis (at least 1); level l has ``ceil(c / 2^(l-1))``, so
vertex ``j`` of level l coincides with S1 vertex ``j · 2^(l-1)`` and the top level has 2×2×2
vertices. Lights that all sit at one point get ``h_L = 1`` scene unit.

Construction, as the paper splits it:

1. bounds of all lights;
2. S1 by *scatter*: each light adds its RGB intensity, times its trilinear weight, to the 8 S1
   vertices around it, together with the luminance-weighted first and second moments of its
   position and, for lights with a normal (VPLs), of its normal (kernels: ``usdml.kernels.lgh.build``);
3. levels 2..L by *gather* from the S1 grid lights (not from the input lights): each level-l vertex
   sums the S1 grid lights in its support, each weighted by the level-l trilinear weight of its
   illumination centre, so every level conserves the total intensity and the global
   luminance-weighted centre;
4. stream compaction per level (vertices with zero luminance weight are dropped) and
   finalization: ``position = Σ w lum p / Σ w lum``, ``variance = E|p|² − |E p|²`` and
   ``lobe = Σ w lum n / Σ w lum`` (the mean normal ν, |ν| ≤ 1, zero for isotropic lights);
5. merge: all levels land in one buffer per attribute (S1 first) and come back to the host once.

Luminance is Rec. 709 (0.2126, 0.7152, 0.0722). On CPU Warp runs a launch on one thread and releases
the GIL while it runs, so the S1 scatter is split into concurrent launches over x-slabs of the
lights that touch disjoint vertices of the one S1 grid (the lights near the slab boundaries are
scattered after them), and the gather and compaction of the levels run as independent launches, all
from a thread pool.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field, replace

import numpy as np

from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, run_parallel

LUMA = np.array([0.2126, 0.7152, 0.0722])
#: more levels than this is a mistake (S1 would have 2^11 cells along the longest edge)
MAX_LEVELS = 12
#: refuse an S1 grid with more vertices than this (32 bytes per vertex for the accumulation grid)
MAX_S1_VERTICES = 1 << 25
#: below this many lights (or gather vertices) per launch, splitting a CPU launch across threads costs
#: more (pool, slab selection and upload of the lights) than it saves
_SPLIT_MIN = 65536
#: compaction of fewer grid vertices than this (all levels) runs inline
_COMPACT_SPLIT_MIN = 1 << 18


@dataclass
class LGHLevel:
    level: int                 #: 1 = S1 (finest grid) ... L = coarsest (a single cell, 8 vertices)
    spacing: float             #: h_l = h_1 · 2^(l-1), scene units
    origin: np.ndarray         #: (3,) float64 grid origin (min corner), scene units
    dims: np.ndarray           #: (3,) int64 vertices per axis; flat vertex index (i·ny + j)·nz + k
    position: np.ndarray       #: (M, 3) float32 illumination-weighted centre of each non-empty grid light
    intensity: np.ndarray      #: (M, 3) float32 RGB radiant intensity (Σ trilinear-weighted input intensities)
    variance: np.ndarray       #: (M,) float32 E|p − position|², scene units², of the illumination around position
    vertex: np.ndarray         #: (M,) int64 flat grid-vertex index of each light, increasing
    lobe: np.ndarray = field(default=None, repr=False)  #: (M, 3) float32 mean emission normal ν, |ν| <= 1
    #: (M,) float32 the input lights each grid light stands for: the sum of their trilinear weights
    #: (fractional; every level's counts sum to the number of lights of non-zero luminance)
    count: np.ndarray = field(default=None, repr=False)
    #: (K,) int64 the input lights this level was built from (a hierarchy split by normal,
    #: :func:`build_lgh_split`: one normal class's), or None for all of them
    members: np.ndarray | None = field(default=None, repr=False)


@dataclass
class LGH:
    levels: list[LGHLevel]     #: levels[0] is S1
    h1: float                  #: S1 spacing, scene units
    bounds: tuple[np.ndarray, np.ndarray]  #: (lo, hi) (3,) float64 bounding box of the lights
    stats: dict                #: seconds per step (bounds, s1, levels, compaction, merge, total) and counts
    #: all levels merged (paper 004 §4.2 "merge levels"): level l's lights are rows offsets[l-1]:offsets[l];
    #: each LGHLevel's arrays are views of these
    position: np.ndarray = field(default=None, repr=False)    #: (ΣM, 3) float32
    intensity: np.ndarray = field(default=None, repr=False)   #: (ΣM, 3) float32
    variance: np.ndarray = field(default=None, repr=False)    #: (ΣM,) float32
    offsets: np.ndarray = field(default=None, repr=False)     #: (L+1,) int64
    lobe: np.ndarray = field(default=None, repr=False)        #: (ΣM, 3) float32
    count: np.ndarray = field(default=None, repr=False)       #: (ΣM,) float32

    @property
    def depth(self) -> int:
        """L, the number of levels (a split hierarchy lists a level once per normal class)."""
        return max((lv.level for lv in self.levels), default=0)

    def level_lights(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """``(position (M, 3), intensity (M, 3))`` of level ``level``'s grid lights (1 = S1), every class's."""
        rows = [lv for lv in self.levels if lv.level == level]
        return (np.concatenate([lv.position for lv in rows]).reshape(-1, 3),
                np.concatenate([lv.intensity for lv in rows]).reshape(-1, 3))


#: the normal classes of :func:`build_lgh_split`: a VPL's class is the axis its normal leans along most,
#: and that axis's sign (+x, -x, +y, -y, +z, -z)
NORMAL_CLASSES = 6


def normal_class(normal: np.ndarray) -> np.ndarray:
    """(N,) int: each of ``normal`` (N, 3)'s class, 2·axis of its largest |component| + (that component < 0)."""
    n = np.asarray(normal, np.float32).reshape(-1, 3)
    axis = np.argmax(np.abs(n), axis=1)
    return (2 * axis + (n[np.arange(len(n)), axis] < 0)).astype(np.int64)


def _warp():
    from usdml.kernels import warp

    return warp()


def _check_normals(normal, shape) -> np.ndarray | None:
    if normal is None:
        return None
    n = np.asarray(normal, np.float32)
    if n.shape != shape:
        raise UsdmlError(f"LGH: light normals must have shape {shape} like the positions, got {n.shape}")
    if not np.isfinite(n).all():
        raise UsdmlError("LGH: light normals contain NaN or infinity")
    return n


def _check_inputs(position, intensity) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(position)
    if p.ndim != 2 or p.shape[1] != 3:
        raise UsdmlError(f"LGH: light positions must have shape (N, 3), got {p.shape}")
    i = np.asarray(intensity, np.float32)
    if i.shape != p.shape:
        raise UsdmlError(f"LGH: light intensities must have shape {p.shape} like the positions, got {i.shape}")
    if not np.isfinite(p).all():
        raise UsdmlError("LGH: light positions contain NaN or infinity")
    if not np.isfinite(i).all() or (i < 0).any():
        raise UsdmlError("LGH: light intensities must be finite and non-negative")
    return p, i


def _grid(lo: np.ndarray, hi: np.ndarray, levels: int) -> tuple[float, np.ndarray]:
    """``(h_1, S1 cells per axis)`` for a hierarchy of ``levels`` levels over the box ``lo``..``hi``."""
    extent = hi - lo
    top = float(extent.max())
    if top <= 0.0:
        top = 1.0
    fine = 1 << (levels - 1)
    # in units of the top cell the longest axis is exactly 1, so it gets exactly 2^(L-1) S1 cells
    cells = np.maximum(np.ceil(extent / top * fine - 1e-9), 1).astype(np.int64)
    return top / fine, cells


def _level_dims(cells1: np.ndarray, level: int) -> np.ndarray:
    stride = 1 << (level - 1)
    return -(-cells1 // stride) + 1


def _check_levels(levels: int, cells1: np.ndarray) -> None:
    if levels > MAX_LEVELS:
        raise UsdmlError(f"LGH: {levels} levels requested; at most {MAX_LEVELS} are supported "
                         f"(use fewer levels, or 0 for the paper's automatic rule)")
    if levels < 1:
        raise UsdmlError(f"LGH: the number of levels must be at least 1 (or 0 for automatic), got {levels}")
    n = int(np.prod(cells1 + 1))
    if n > MAX_S1_VERTICES:
        raise UsdmlError(f"LGH: {levels} levels make an S1 grid of {'x'.join(map(str, cells1 + 1))} = {n:,} "
                         f"vertices (limit {MAX_S1_VERTICES:,}); use fewer levels, or 0 for automatic")


def _slices(work: int, parts: int, n: int | None = None) -> list[tuple[int, int]]:
    """``[lo, hi)`` ranges splitting ``n`` items (default ``work``) over at most ``parts`` launches of at
    least _SPLIT_MIN units of ``work`` each."""
    n = work if n is None else n
    if n == 0:
        return [(0, 0)]
    parts = max(1, min(parts, work // _SPLIT_MIN, n))
    step = -(-n // parts)
    return [(a, min(n, a + step)) for a in range(0, n, step)]


def _slabs(p: np.ndarray, lo: np.ndarray, h1: float, cells_x: int, parts: int) -> list:
    """Light rows for concurrent S1 scatters into one grid: ``parts`` x-slabs whose lights touch
    disjoint vertices, then the lights within 2 cells of a slab boundary (scattered after the slabs).

    A light in S1 cell i writes vertices i and i + 1 along x; the cell is taken here in float64 and
    in the kernel in float32, which may differ by one at a boundary, so a slab ends at b − 3 below a
    boundary b and starts at b + 1 above it, and the cells b − 2 .. b go last. ``None`` stands for
    every light: ``[None, []]`` when one part is asked for or the grid is too thin to split.
    """
    if parts <= 1 or cells_x < 8 * parts:
        return [None, np.zeros(0, np.int64)]
    cell = np.clip(np.floor((np.asarray(p[:, 0], np.float64) - lo[0]) / h1), 0, cells_x - 1).astype(np.int64)
    cuts = np.unique(np.quantile(cell, np.linspace(0, 1, parts + 1)[1:-1]).astype(np.int64))
    cuts = cuts[(cuts >= 3) & (cuts < cells_x)]
    edges = np.concatenate([[-1], cuts, [cells_x + 2]])
    out = [np.nonzero((cell > edges[j]) & (cell <= edges[j + 1] - 3))[0] for j in range(len(edges) - 1)]
    seam = np.zeros(len(cell), bool)
    for c in cuts:
        seam |= (cell >= c - 2) & (cell <= c)
    return out + [np.nonzero(seam)[0]]


def _bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float64 of (N, 3) points; per column, which NumPy does ~20x faster than ``min(axis=0)``."""
    if len(p) == 0:
        return np.zeros(3), np.zeros(3)
    return (np.array([p[:, k].min() for k in range(3)], np.float64),
            np.array([p[:, k].max() for k in range(3)], np.float64))


def _upload(wp, position: np.ndarray, intensity: np.ndarray, lo: np.ndarray, device: str):
    """Lights on ``device``: positions relative to the grid origin ``lo``, as float32."""
    p = np.asarray(position)
    # float32 minus its own (float32) minimum stays exact to an ulp; float64 is shifted before the cast
    local = p - lo.astype(p.dtype) if p.dtype == np.float32 else (p.astype(np.float64) - lo).astype(np.float32)
    return (wp.array(np.ascontiguousarray(local, np.float32), dtype=wp.vec3, device=device),
            wp.array(np.ascontiguousarray(intensity, np.float32), dtype=wp.vec3, device=device))


def _count_s1(wp, pos_w, int_w, lo, hi, levels: int, device: str) -> int:
    from usdml.kernels.lgh.build import mark_s1

    h1, cells = _grid(lo, hi, levels)
    dims = cells + 1
    flags = wp.zeros(int(dims.prod()), dtype=wp.uint8, device=device)
    wdims = wp.vec3i(*map(int, dims))
    spans = _slices(len(pos_w), cpu_workers(device))

    def mark(span):
        a, b = span
        if b > a:
            wp.launch(mark_s1, dim=b - a, device=device, inputs=[pos_w[a:b], int_w[a:b], float(h1), wdims, flags])

    # every writer stores 1: concurrent launches into one flag grid are harmless
    run_parallel(mark, spans, len(spans))
    return int(np.count_nonzero(flags.numpy()))


def _auto_levels(n: int, lo, hi, lights, device: str) -> int:
    """auto_levels over uploaded lights (``lights`` = (positions, intensities) on ``device``, or None)."""
    best = 1
    for levels in range(1, MAX_LEVELS + 1):
        _, cells = _grid(lo, hi, levels)
        vertices = int(np.prod(cells + 1))
        if vertices > MAX_S1_VERTICES:
            break
        if vertices * 2 < n:     # the whole grid is below n/2: no need to look at the lights
            best = levels
            continue
        if lights is None or _count_s1(_warp(), *lights, lo, hi, levels, device) * 2 >= n:
            break
        best = levels
    return best


def count_s1(position: np.ndarray, intensity: np.ndarray | None, levels: int, device: str = "cpu") -> int:
    """|S1|: the number of non-empty S1 grid lights of a ``levels``-level hierarchy over ``position`` (N, 3)."""
    p, i = _check_inputs(position, np.ones(np.shape(position), np.float32) if intensity is None else intensity)
    lo, hi = _bounds(p)
    _check_levels(levels, _grid(lo, hi, levels)[1])
    wp = _warp()
    return _count_s1(wp, *_upload(wp, p, i, lo, device), lo, hi, levels, device)


def auto_levels(n_lights: int, position: np.ndarray | None = None, intensity: np.ndarray | None = None,
                device: str = "cpu") -> int:
    """The paper's level count (paper 004 §4.3): the largest L with |S1| < n_lights / 2.

    |S1| is the number of *non-empty* S1 grid lights, which depends on where the lights are
    (``position`` (N, 3) scene units; lights of zero ``intensity`` (N, 3) RGB mark nothing).
    It is evaluated from L = 1 upwards and the search stops at the first L that breaks the rule
    (|S1| grows with L: refining the grid does not empty vertices in practice). A level count whose
    whole S1 grid has fewer than n_lights / 2 vertices passes without looking at the lights, so
    usually only the first L that breaks the rule costs a marking pass (O(N + S1 vertices), no
    accumulation). The result is at least 1 and at most :data:`MAX_LEVELS`, and never makes an S1
    grid over :data:`MAX_S1_VERTICES`. Without ``position`` the lights are taken to fill a cube and
    only the vertex-count bound is used (every S1 vertex counted as lit).
    """
    n = int(n_lights)
    if position is None:
        return _auto_levels(n, np.zeros(3), np.ones(3), None, device)
    p, i = _check_inputs(position, np.ones(np.shape(position), np.float32) if intensity is None else intensity)
    if n <= 0 or len(p) == 0:
        return 1
    lo, hi = _bounds(p)
    wp = _warp()
    return _auto_levels(n, lo, hi, _upload(wp, p, i, lo, device), device)


def s1_spacing(position: np.ndarray, intensity: np.ndarray, levels: int = 0, device: str = "cpu") -> float:
    """h_1, the S1 spacing (scene units) of the hierarchy ``build_lgh(position, intensity, levels)``
    builds, without building it: the VPL gathers that clamp their geometry term as the LGH does
    (``--gi svo``) need only this. ``position`` (N, 3), ``intensity`` (N, 3) as :func:`build_lgh`."""
    p, i = _check_inputs(position, intensity)
    if len(p) == 0:
        return 0.0
    if int(levels) == 0:
        levels = auto_levels(len(p), p, i, device)
    lo, hi = _bounds(p)
    return float(_grid(lo, hi, int(levels))[0])


def build_lgh(position: np.ndarray, intensity: np.ndarray, levels: int = 0, device: str = "cpu",
              normal: np.ndarray | None = None, bounds: tuple | None = None) -> LGH:
    """Build a lighting grid hierarchy over point lights (paper 004 §3.1).

    ``position``: (N, 3) float32/float64 scene units; ``intensity``: (N, 3) float32 RGB isotropic
    radiant intensity (non-negative; power 4π·I). ``normal``: (N, 3) unit normals of cosine emitters
    (VPLs: power 4π·I into the hemisphere about n, radiant intensity 4·I·max(0, cos)), or None for
    isotropic lights; each grid light gets the mean normal ν of what it aggregates (``lobe``).
    ``levels``: the number of levels L (1..:data:`MAX_LEVELS`), or 0 for :func:`auto_levels`.
    ``device``: a Warp device (``cpu``, ``cuda``, ``cuda:0``). ``bounds = (lo, hi)`` (3,) each: the box
    the grid spans, holding every light (default: the lights' own bounding box).
    Raises :class:`UsdmlError` for malformed lights or an absurd level count.
    """
    wp = _warp()
    from usdml.kernels.lgh import build as K

    t_start = _time.perf_counter()
    p, inten = _check_inputs(position, intensity)
    nrm = _check_normals(normal, p.shape)
    n = len(p)
    stats: dict = {"n_lights": n, "device": str(device)}

    def sync():
        if not str(device).startswith("cpu"):
            wp.synchronize_device(device)

    t0 = _time.perf_counter()
    lo, hi = _bounds(p) if bounds is None else (np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64))
    stats["bounds"] = _time.perf_counter() - t0
    t0 = _time.perf_counter()
    pos_w, int_w = _upload(wp, p, inten, lo, device)
    stats["upload"] = _time.perf_counter() - t0
    t0 = _time.perf_counter()
    if int(levels) == 0:
        levels = _auto_levels(n, lo, hi, (pos_w, int_w), device) if n else 1
    stats["auto_levels"] = _time.perf_counter() - t0
    levels = int(levels)
    h1, cells1 = _grid(lo, hi, levels)
    _check_levels(levels, cells1)
    stats["levels"] = levels
    workers = cpu_workers(device)
    stats["workers"] = workers
    # -- S1 by scatter into one grid: concurrent launches over x-slabs of the lights (disjoint vertices)
    t0 = _time.perf_counter()
    dims1 = cells1 + 1
    v1 = int(dims1.prod())
    wdims1 = wp.vec3i(*map(int, dims1))
    s1 = wp.zeros(v1, dtype=K.acc8, device=device)
    s1_lobe = wp.zeros(v1, dtype=wp.vec4, device=device)
    parts = _slabs(p, lo, h1, int(cells1[0]), len(_slices(n, workers)))
    no_normal = wp.zeros(1, dtype=wp.vec3, device=device)

    def scatter(rows):
        if rows is None or len(rows):
            pw, iw = (pos_w, int_w) if rows is None else _upload(wp, p[rows], inten[rows], lo, device)
            nw = no_normal if nrm is None else wp.array(nrm if rows is None else nrm[rows], dtype=wp.vec3,
                                                        device=device)
            wp.launch(K.scatter_s1, dim=len(pw), device=device,
                      inputs=[pw, iw, nw, int(nrm is not None), float(h1), wdims1], outputs=[s1, s1_lobe])

    run_parallel(scatter, parts[:-1], workers)
    scatter(parts[-1])            # the lights near the slab boundaries, once the slabs are done
    sync()
    stats["s1"] = _time.perf_counter() - t0
    stats["s1_vertices"] = v1
    stats["scatter_launches"] = sum(1 for rows in parts if rows is None or len(rows))

    # -- levels 2..L by gather from S1: every level (and slices of the big ones) is its own launch
    t0 = _time.perf_counter()
    s1_lights = wp.empty(v1, dtype=K.acc8, device=device)
    wp.launch(K.s1_grid_lights, dim=v1, device=device, inputs=[s1, float(h1), wdims1], outputs=[s1_lights])
    blocks = -(-dims1 // int(K.BLOCK))
    wblocks = wp.vec3i(*map(int, blocks))
    occupied = wp.zeros(int(blocks.prod()), dtype=wp.uint8, device=device)
    wp.launch(K.mark_blocks, dim=v1, device=device, inputs=[s1_lights, wdims1, wblocks], outputs=[occupied])
    grid_of = {1: (dims1, s1, s1_lobe)}
    tasks = []
    for level in range(2, levels + 1):
        dims = _level_dims(cells1, level)
        count = int(dims.prod())
        acc = wp.empty(count, dtype=K.acc8, device=device)
        acc_lobe = wp.empty(count, dtype=wp.vec4, device=device)
        grid_of[level] = (dims, acc, acc_lobe)
        wdims = wp.vec3i(*map(int, dims))
        # a level-l vertex visits (2·2^(l-1) + 1)³ S1 vertices: split by that work, not by vertex count
        for a, b in _slices(count * (2 * (1 << (level - 1)) + 1) ** 3, workers, count):
            tasks.append((level, wdims, acc, acc_lobe, a, b))

    def gather(task):
        level, wdims, acc, acc_lobe, a, b = task
        wp.launch(K.gather_level, dim=b - a, device=device,
                  inputs=[s1_lights, wdims1, wblocks, occupied, 1 << (level - 1), float(h1 * (1 << (level - 1))),
                          wdims, a, s1_lobe],
                  outputs=[acc, acc_lobe])

    run_parallel(gather, tasks, workers)
    sync()
    stats["gather"] = _time.perf_counter() - t0

    # -- stream compaction (exclusive scan of non-empty flags) straight into merged buffers
    t0 = _time.perf_counter()

    def scan(level):
        dims, acc, _ = grid_of[level]
        count = int(dims.prod())
        flags = wp.empty(count, dtype=int, device=device)
        slot = wp.empty(count, dtype=int, device=device)
        wp.launch(K.mark_nonempty, dim=count, device=device, inputs=[acc], outputs=[flags])
        wp.utils.array_scan(flags, slot, inclusive=False)
        return slot, flags

    all_vertices = sum(int(dims.prod()) for dims, _, _ in grid_of.values())
    compact_workers = workers if all_vertices >= _COMPACT_SPLIT_MIN else 1
    scans = run_parallel(scan, range(1, levels + 1), compact_workers)
    # the last slot plus the last flag is the level's light count (one small read per level)
    counts = [int(slot[len(slot) - 1:].numpy()[0] + flags[len(flags) - 1:].numpy()[0]) for slot, flags in scans]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    total = int(offsets[-1])
    out_pos = wp.empty(total, dtype=wp.vec3, device=device)
    out_int = wp.empty(total, dtype=wp.vec3, device=device)
    out_var = wp.empty(total, dtype=float, device=device)
    out_vtx = wp.empty(total, dtype=wp.int64, device=device)
    out_lobe = wp.empty(total, dtype=wp.vec3, device=device)
    out_count = wp.empty(total, dtype=float, device=device)
    origin = wp.vec3(*map(float, lo))

    def compact(level):
        dims, acc, acc_lobe = grid_of[level]
        slot, _ = scans[level - 1]
        wp.launch(K.compact_level, dim=int(dims.prod()), device=device,
                  inputs=[acc, slot, int(offsets[level - 1]), origin, float(h1 * (1 << (level - 1))),
                          wp.vec3i(*map(int, dims)), acc_lobe],
                  outputs=[out_pos, out_int, out_var, out_vtx, out_lobe, out_count])

    run_parallel(compact, range(1, levels + 1), compact_workers)
    sync()
    stats["compaction"] = _time.perf_counter() - t0

    # -- merge: one host copy of all levels; each level's arrays are views into it
    t0 = _time.perf_counter()
    pos_np = np.array(out_pos.numpy(), np.float32).reshape(-1, 3)
    int_np = np.array(out_int.numpy(), np.float32).reshape(-1, 3)
    var_np = np.array(out_var.numpy(), np.float32).reshape(-1)
    vtx_np = np.array(out_vtx.numpy(), np.int64).reshape(-1)
    lobe_np = np.array(out_lobe.numpy(), np.float32).reshape(-1, 3)
    count_np = np.array(out_count.numpy(), np.float32).reshape(-1)
    out = []
    for level in range(1, levels + 1):
        a, b = offsets[level - 1], offsets[level]
        out.append(LGHLevel(level=level, spacing=float(h1 * (1 << (level - 1))), origin=lo.copy(),
                            dims=grid_of[level][0].astype(np.int64), position=pos_np[a:b],
                            intensity=int_np[a:b], variance=var_np[a:b], vertex=vtx_np[a:b], lobe=lobe_np[a:b],
                            count=count_np[a:b]))
    stats["merge"] = _time.perf_counter() - t0
    stats["lights_per_level"] = counts
    stats["total"] = _time.perf_counter() - t_start
    return LGH(levels=out, h1=float(h1), bounds=(lo, hi), stats=stats, position=pos_np, intensity=int_np,
               variance=var_np, offsets=offsets, lobe=lobe_np, count=count_np)


def build_lgh_split(position: np.ndarray, intensity: np.ndarray, normal: np.ndarray, levels: int = 0,
                    device: str = "cpu") -> LGH:
    """One hierarchy per normal class (:func:`normal_class`) on one grid, as one :class:`LGH`.

    A coarse grid light of one hierarchy merges VPLs on a ground and on a wall into one centre and one
    mean normal, which lights the ground from too low and too weakly (the suite's open stages,
    docs/gi.md). Here the VPLs of each class get a hierarchy of their own, all over the grid of all the
    VPLs (the same bounds and level count, so that the level-l grid lights of every class share its
    spacing and S0's buckets), and the result lists each level once per class (``LGHLevel.members``:
    the class's VPLs; ``level`` the level), levels in order, the classes in order within a level. The
    gather walks every entry and blends it as its level (``kernels/lgh/lghq.c``, ``level_rank``).
    Arguments as :func:`build_lgh`.
    """
    p, inten = _check_inputs(position, intensity)
    nrm = _check_normals(normal, p.shape)
    t_start = _time.perf_counter()
    if nrm is None or len(p) == 0:
        return build_lgh(p, inten, levels, device, nrm)
    lo, hi = _bounds(p)
    if int(levels) == 0:
        levels = auto_levels(len(p), p, inten, device)
    klass = normal_class(nrm)
    groups = [rows for rows in (np.flatnonzero(klass == c) for c in range(NORMAL_CLASSES)) if len(rows)]

    def build(rows):
        return rows, build_lgh(p[rows], inten[rows], int(levels), device, nrm[rows], bounds=(lo, hi))

    # the classes' builds are independent: concurrent (each one's launches release the GIL, and a small
    # class's build is mostly launch overhead)
    parts = run_parallel(build, groups, cpu_workers(device))
    out = [replace(part.levels[level - 1], members=rows) for level in range(1, int(levels) + 1) for rows, part in parts]
    sizes = [len(lv.position) for lv in out]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    merged = {name: np.concatenate([getattr(lv, name) for lv in out]) for name in
              ("position", "intensity", "variance", "lobe", "count")}
    for lv, a, b in zip(out, offsets[:-1], offsets[1:]):    # each entry's arrays as views of the merged ones
        for name, arr in merged.items():
            setattr(lv, name, arr[a:b])
    stats = {"n_lights": len(p), "device": str(device), "levels": int(levels), "classes": len(parts),
             "lights_per_level": [sum(size for size, lv in zip(sizes, out) if lv.level == level)
                                  for level in range(1, int(levels) + 1)],
             "total": _time.perf_counter() - t_start}
    return LGH(levels=out, h1=parts[0][1].h1, bounds=(lo, hi), stats=stats, offsets=offsets, **merged)
