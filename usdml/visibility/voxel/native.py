"""The compiled CPU path of the voxel backend: ``kernels/voxel/voxelq.c`` through ctypes.

Why a compiled kernel
    On a CPU the voxel query is compute-bound (docs/voxel.md, "CPU speed"): Warp runs a CPU launch on
    one thread, one query at a time, and its code for this rule ran 1.4-1.8x slower than plain C.
    ``voxelq.c`` answers the same rule 32 queries at a time with AVX-512, 16 with AVX2 (two registers
    per vector; chosen at run time, so one build serves every x86-64 CPU) or one at a time in C, from
    the thread pool of :mod:`usdml.parallel` (ctypes releases the GIL during a call).

What a machine gets
    ``pip install`` builds the library as the optional extension ``usdml.kernels.voxel._voxelq`` (setup.py).
    Without a C compiler it is skipped and :func:`library` returns None: the backend uses the Warp
    kernels, as ``--voxel-cpu-kernel warp`` does; ``usdml info`` names the path (:func:`describe`). A CPU
    without AVX2 (or not x86-64) runs the scalar C kernel. GPUs always run Warp.

Tables (built here from the backend's arrays, what ``kernels/voxel/query.py``'s ``VoxelScene`` holds)
    * ``fold``: per array and direction bin, the 3 x 4 map from array space to the bin's grid in voxels
      (``frame · n / 2R`` and the cube's corner folded in); ``world_fold`` the same from world space
      for the world-space arrays (the static one and the per-frame one: their world -> array maps
      folded in as well), which every ray meets first, in SIMD;
    * the moving instances (Alg. 4) are the rest: rays the world-space arrays leave free are tested
      against them one lane at a time;
    * ``row_start`` / ``row_span``: per row, the offset of its words minus its first word index, and its
      first and end word indices packed ``w0 | w1 << 16``;
    * the instances' world -> array maps (3 x 4) and a BVH over their world boxes (built in C).
"""

from __future__ import annotations

import ctypes

import numpy as np

from usdml.errors import UsdmlError
from usdml.kernels.brdf import WIDTH
from usdml.native import ISAS, Extension, path_line
from usdml.scene.light_table import LightTable

__all__ = ["EXTENSION", "NativeScene", "ShadeList", "compiled_lights", "library", "describe", "isa_width",
           "packed_rows", "rotate_point", "simd_width"]

_f = ctypes.POINTER(ctypes.c_float)
_i = ctypes.POINTER(ctypes.c_int32)
_u = ctypes.POINTER(ctypes.c_uint32)


class _Scene(ctypes.Structure):
    _fields_ = [("words", _u), ("arr_n", _i), ("arr_base", _i), ("arr_inv_h", _f), ("arr_sphere", _f), ("fold", _f),
                ("world_fold", _f * 2), ("row_start", _i), ("row_span", _i), ("wpd", ctypes.c_int32),
                ("n_bins", ctypes.c_int32), ("d_theta", ctypes.c_float), ("n_rings", ctypes.c_int32),
                ("ring_count", _i), ("ring_start", _i), ("n_world", ctypes.c_int32),
                ("world_array", ctypes.c_int32 * 2), ("world_inv", (ctypes.c_float * 12) * 2), ("n_inst", ctypes.c_int32), ("inst_inv", _f),
                ("inst_array", _i), ("n_nodes", ctypes.c_int32), ("node_box", _f), ("node_kids", _i),
                ("bvh_items", _i), ("inst_voxel", ctypes.c_float)]


class _Rule(ctypes.Structure):
    _fields_ = [("offset", ctypes.c_float), ("skip", ctypes.c_float), ("slab", ctypes.c_float),
                ("max_skip", ctypes.c_float), ("end_skip", ctypes.c_float), ("far", ctypes.c_float),
                ("far_center", ctypes.c_float * 3), ("seg", ctypes.c_int32)]


class _Lights(ctypes.Structure):
    _fields_ = [("n", ctypes.c_int32), ("pos", _f), ("axis", _f), ("cylinder_axis", _f), ("cone", _f),
                ("base", _f), ("focus_rgb", _f), ("flags", _i), ("inv_m2", ctypes.c_float),
                ("min_d2", ctypes.c_float), ("target", _f)]


def light_struct(pos, axis, cylinder_axis, cone, base, focus_rgb, flags, inv_m2: float, min_d2: float,
                 target=None) -> _Lights:
    """The lights as the compiled kernels' table (``kernels/include/light_term.h``; the arrays are held by the
    returned object); ``target`` (L, 3): where each light's shadow rays end (None: at ``pos``)."""
    arrs = [_c(x, np.float32).reshape(-1, 3) for x in (pos, axis, cylinder_axis, cone, base, focus_rgb)]
    fl = _c(flags, np.int32)
    lt = _Lights()
    lt.n = len(fl)
    lt.pos, lt.axis, lt.cylinder_axis, lt.cone, lt.base, lt.focus_rgb = (_ptr(a, _f) for a in arrs)
    lt.flags = _ptr(fl, _i)
    lt.inv_m2, lt.min_d2 = float(inv_m2), float(min_d2)
    ends = None if target is None else _c(target, np.float32).reshape(-1, 3)
    lt.target = None if ends is None else _ptr(ends, _f)
    lt._hold = (arrs, fl, ends)
    return lt


def compiled_lights(lights, meters_per_unit: float = 1.0, min_distance: float = 0.0, target=None) -> _Lights:
    """``lights`` (:class:`usdml.scene.Lights`) as the compiled kernels' table: the constants of
    :class:`usdml.scene.light_table.LightTable`, the cone as (cos outer, soft width, focus); ``target`` (L, 3):
    where each light's shadow rays end (None: at its position)."""
    t = LightTable(lights, meters_per_unit, min_distance)
    return light_struct(lights.position, lights.axis, np.ascontiguousarray(t.cylinder_axis.T), t.kernel_cone, t.base,
                        t.focus_rgb, t.flags, t.inv_m2, t.min_d2, target)


_P = ctypes.c_void_p
#: ``voxelq.c``'s functions
EXTENSION = Extension("voxel._voxelq", {
    "vq_simd_width": (ctypes.c_int, [ctypes.c_int32]),
    "vq_simd_isa": (ctypes.c_int, [ctypes.c_int32]),
    "vq_query": (None, [ctypes.POINTER(_Scene), ctypes.POINTER(_Rule), ctypes.c_int64, ctypes.c_int64, _P, _P, _P,
                        _P, ctypes.c_int32, ctypes.c_int32, _P, ctypes.c_int32, ctypes.c_int32, _P]),
    "vq_query_refine": (None, [ctypes.POINTER(_Scene), ctypes.POINTER(_Rule), ctypes.c_int64, ctypes.c_int64, _P, _P,
                               _P, _P, _P, ctypes.c_int32, ctypes.c_int32, ctypes.c_int32, ctypes.c_int32, _P]),
    "vq_shade": (None, [ctypes.POINTER(_Scene), ctypes.POINTER(_Rule), ctypes.POINTER(_Lights), _P, _P, _P,
                        ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, ctypes.c_int32, _P, _P, _P,
                        _P, _P]),
    "vq_shade_refine": (None, [ctypes.POINTER(_Scene), ctypes.POINTER(_Rule), ctypes.POINTER(_Lights), _P, _P, _P,
                               ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, ctypes.c_int32, _P,
                               ctypes.c_int32, _P, _P, _P, _P, _P, _P, _P, _P, ctypes.c_int64, _P, _P, _P]),
    "vq_list_apply": (None, [ctypes.c_int64, _P, _P, _P, _P, _P]),
    "vq_rotate_point": (None, [_P, _P, _P, ctypes.c_int32, _P, ctypes.c_int32, ctypes.c_int32, ctypes.c_int32, _P,
                               ctypes.c_int32, ctypes.c_int64, _P]),
    "vq_build_bvh": (ctypes.c_int32, [ctypes.c_int32, _P, _P, _P, _P, _P]),
})


def library() -> ctypes.CDLL | None:
    """The compiled kernel, or None where it was not built (no C compiler at install)."""
    return EXTENSION.library()


def simd_width(isa: str = "auto") -> int:
    """Queries the compiled kernel answers at once on this CPU with ``isa`` (:data:`usdml.native.ISAS`): 32
    (AVX-512) or 16 (AVX2), as two registers per vector, or 1 (scalar); 0 without the kernel."""
    lib = library()
    return int(lib.vq_simd_width(ISAS[isa])) if lib is not None else 0


def isa_width(isa: str = "auto") -> int:
    """The lanes of one register of the instruction set the compiled kernel runs with ``isa``: 16
    (AVX-512), 8 (AVX2) or 1 (scalar); 0 without the kernel."""
    lib = library()
    return int(lib.vq_simd_isa(ISAS[isa])) if lib is not None else 0


def describe() -> str:
    """One line: which CPU path voxel queries take on this machine (``usdml info``)."""
    lib, why = EXTENSION.load()
    if lib is None:
        return path_line("compiled kernel", why, 0, "queries")
    return path_line("compiled kernel", why, simd_width(), "queries", isa_width())


def packed_rows(layout) -> np.ndarray | None:
    """``layout``'s rows as :func:`rotate_point` reads them, ``offset << 10 | w0 << 5 | nw`` (int32), or
    None where they do not fit (offsets from 2^21 words, rows of more than 31 words)."""
    off, w0, nw = (np.asarray(x, np.int64) for x in (layout.offset, layout.w0, layout.nw))
    if len(off) == 0 or off.max() >= 1 << 21 or (w0 + nw).max() > 31:
        return None
    return np.ascontiguousarray((off << 10) | (w0 << 5) | nw, np.int32)


def rotate_point(row_ij: np.ndarray, row_start: np.ndarray, depth: np.ndarray, table: np.ndarray, n: int, d0: int,
                 d1: int, rows: np.ndarray, wpd: int, base: int, out: np.ndarray) -> None:
    """Alg. 5 with the point mapping for directions ``d0 .. d1 - 1`` into ``out`` (uint32 words, from
    word ``base``), as ``kernels.voxel.rotate.rotate_voxels`` does (its int32 inputs, C-contiguous;
    ``rows`` from :func:`packed_rows`)."""
    library().vq_rotate_point(row_ij.ctypes.data, row_start.ctypes.data, depth.ctypes.data, len(row_ij),
                              table.ctypes.data, int(n), int(d0), int(d1), rows.ctypes.data, int(wpd), int(base),
                              out.ctypes.data)


def _ptr(a: np.ndarray, kind):
    return a.ctypes.data_as(kind)


def _c(a, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


class NativeScene:
    """The tables the compiled kernel reads for one assembled set of arrays (module doc): ``world``
    the indices of the world-space arrays (at most two), the instances the moving prototypes', queried
    with instruction set ``isa`` (:data:`usdml.native.ISAS`). Holds every
    NumPy buffer it points into; rebuild it whenever the backend re-assembles (cheap: per array a
    few hundred KiB of maps; the words themselves are not copied)."""

    def __init__(self, words: np.ndarray, arrays, layout, bins, world: list[int], inst_inv: np.ndarray,
                 inst_array: np.ndarray, inst_lo: np.ndarray, inst_hi: np.ndarray, isa: str = "auto"):
        lib = library()
        if lib is None:
            raise UsdmlError("the compiled voxel kernel was not built on this machine: reinstall usdml with a C "
                             "compiler, or use --voxel-cpu-kernel warp")
        self.lib = lib
        self.kernel = ISAS[isa]
        keep = self._keep = []

        def hold(a):
            keep.append(a)
            return a

        self.words = words
        frames = np.asarray(bins.frames, np.float64)                  # (B, 3, 3) rows u, v, w
        n_bins = frames.shape[0]
        arr_n = hold(_c([a.resolution for a in arrays] or [1], np.int32))
        base = np.concatenate([[0], np.cumsum([a.words.size for a in arrays])[:-1]]) if arrays else np.zeros(1)
        arr_base = hold(_c(base, np.int32))
        inv_h32 = [np.float32(a.resolution) / (np.float32(2.0) * np.float32(a.half)) for a in arrays] or [1.0]
        arr_inv_h = hold(_c(inv_h32, np.float32))
        # every voxel lies within the geometry's bounding sphere (radius half / margin) plus a voxel's
        # diagonal; a little more for float rounding
        arr_sphere = hold(_c([[*np.asarray(a.center, np.float64), a.half * (1.0 + 2.0 * 3 ** 0.5 / a.resolution) * 1.001]
                              for a in arrays] or [[0, 0, 0, 0]], np.float32))
        folds = []
        for a, ih in zip(arrays, inv_h32):
            folds.append(self._fold(frames, float(ih), np.asarray(a.center, np.float64), float(a.half)))
        fold = hold(_c(np.concatenate(folds) if folds else np.zeros((1, 12)), np.float32))
        if len(world) > 2:
            raise ValueError("the compiled kernel takes at most two world-space arrays")
        world_fold = []
        for a_id in world:
            a = arrays[a_id]
            world_fold.append(hold(_c(self._fold(frames, float(inv_h32[a_id]), np.asarray(a.center, np.float64),
                                                 float(a.half), np.asarray(a.to_array, np.float64)), np.float32)))
        w0 = np.asarray(layout.w0, np.int64)
        nw = np.asarray(layout.nw, np.int64)
        if len(w0) and (w0 + nw).max() >= 1 << 15:
            raise UsdmlError("voxel rows longer than the compiled kernel indexes; use --voxel-cpu-kernel warp")
        row_start = hold(_c(np.asarray(layout.offset, np.int64) - w0, np.int32))
        row_span = hold(_c(w0 | ((w0 + nw) << 16), np.int32))
        ring_count = hold(_c(bins.ring_count, np.int32))
        ring_start = hold(_c(bins.ring_start, np.int32))
        k = len(inst_array)
        inv = hold(_c(np.asarray(inst_inv, np.float32).reshape(-1, 4, 4)[:, :3, :].reshape(-1, 12) if k
                      else np.zeros((1, 12)), np.float32))
        ids = hold(_c(inst_array if k else [0], np.int32))
        lo = hold(_c(inst_lo if k else np.zeros((1, 3)), np.float32))
        hi = hold(_c(inst_hi if k else np.zeros((1, 3)), np.float32))
        items = hold(np.zeros(max(k, 1), np.int32))
        box = hold(np.zeros((max(2 * k, 1), 6), np.float32))
        kids = hold(np.zeros((max(2 * k, 1), 2), np.int32))
        nodes = int(lib.vq_build_bvh(k, lo.ctypes.data, hi.ctypes.data, items.ctypes.data, box.ctypes.data,
                                     kids.ctypes.data)) if k else 0
        s = _Scene()
        s.words = _ptr(words, _u)
        s.arr_n, s.arr_base, s.arr_inv_h = _ptr(arr_n, _i), _ptr(arr_base, _i), _ptr(arr_inv_h, _f)
        s.arr_sphere = _ptr(arr_sphere, _f)
        s.fold = _ptr(fold, _f)
        s.row_start, s.row_span = _ptr(row_start, _i), _ptr(row_span, _i)
        s.wpd, s.n_bins, s.d_theta, s.n_rings = int(layout.words), n_bins, float(bins.d_theta), len(bins.ring_count)
        s.ring_count, s.ring_start = _ptr(ring_count, _i), _ptr(ring_start, _i)
        s.n_world = len(world)
        for i, a_id in enumerate(world):
            s.world_array[i] = int(a_id)
            s.world_inv[i][:] = [float(x) for x in np.asarray(arrays[a_id].to_array, np.float32)[:3, :].ravel()]
            s.world_fold[i] = _ptr(world_fold[i], _f)
        s.n_inst, s.inst_inv, s.inst_array = k, _ptr(inv, _f), _ptr(ids, _i)
        s.n_nodes, s.node_box, s.node_kids, s.bvh_items = nodes, _ptr(box, _f), _ptr(kids, _i), _ptr(items, _i)
        s.inst_voxel = self._instance_voxel(inv[:k], arr_inv_h[ids[:k]])
        self.scene = s

    @staticmethod
    def _fold(frames: np.ndarray, inv_h: float, center: np.ndarray, half: float,
              world: np.ndarray | None = None) -> np.ndarray:
        """(B, 12): per bin, rows of the map ``grid = F x + f`` with ``F = frame · inv_h`` (composed with
        ``world``'s 3 x 4 map when given) and ``f = half · inv_h - F c``."""
        F = frames * inv_h
        f = half * inv_h - F @ center
        if world is not None:
            f = F @ world[:3, 3] + f
            F = F @ world[:3, :3]
        return np.concatenate([F, f[:, :, None]], axis=2).reshape(len(frames), 12)

    @staticmethod
    def _instance_voxel(inv: np.ndarray, inv_h: np.ndarray) -> float:
        """The largest voxel edge in world units over instances with world -> array maps ``inv`` (K, 12)
        into arrays of ``inv_h`` voxels per unit: how far :meth:`query_refine`'s shifted rows reach
        per voxel of ``thick`` (an array's voxel stretched by at most 1 / the map's least singular value)."""
        if len(inv) == 0:
            return 0.0
        least = np.linalg.svd(np.asarray(inv, np.float64).reshape(-1, 3, 4)[:, :, :3], compute_uv=False)[:, -1]
        return float(np.max(1.0 / (np.maximum(least, 1e-30) * np.asarray(inv_h, np.float64))) * 1.001)

    @staticmethod
    def rule(offset: float, skip: float, slab: float, max_skip: float, end_skip: float, far: float, far_center,
             seg: int) -> _Rule:
        r = _Rule()
        r.offset, r.skip, r.slab, r.max_skip, r.end_skip, r.far = offset, skip, slab, max_skip, end_skip, far
        r.far_center[:] = [float(x) for x in np.asarray(far_center, np.float32)]
        r.seg = int(seg)
        return r

    @staticmethod
    def _input_kinds(origins: np.ndarray, targets: np.ndarray, normals: np.ndarray, distant: np.ndarray) -> int:
        """The kernel's ``f64_mask`` for the query inputs, checked (C-contiguous float32 or float64 vectors,
        int32 or bool flags)."""
        arrays = (origins, targets, normals)
        for a in arrays:
            if a.dtype not in (np.float32, np.float64) or not a.flags.c_contiguous:
                raise TypeError("query inputs must be C-contiguous float32 or float64")
        if distant.dtype not in (np.int32, np.bool_) or not distant.flags.c_contiguous:
            raise TypeError("distant flags must be C-contiguous int32 or bool")
        return sum(1 << i for i, a in enumerate(arrays) if a.dtype == np.float64)

    def query(self, rule: _Rule, first: int, count: int, origins: np.ndarray, targets: np.ndarray,
              normals: np.ndarray, distant: np.ndarray, want_t: bool, out: np.ndarray) -> None:
        """``out[first:first + count]``: queries ``first ..`` of the C-contiguous (n, 3) float32 or float64
        inputs and (n,) int32 or bool flags (read as they are: no conversion pass). ``out`` float32: the
        distances (-1 free); bool: whether each ray is blocked, written as it is (``want_t`` ignored)."""
        f64 = self._input_kinds(origins, targets, normals, distant)
        flags = out.dtype == np.bool_
        if not flags and out.dtype != np.float32:
            raise TypeError("query output must be float32 or bool")
        self.lib.vq_query(ctypes.byref(self.scene), ctypes.byref(rule), int(first), int(count), origins.ctypes.data,
                          targets.ctypes.data, normals.ctypes.data, distant.ctypes.data, int(want_t), self.kernel,
                          None if flags else out.ctypes.data, f64, int(distant.dtype == np.bool_),
                          out.ctypes.data if flags else None)

    def query_refine(self, rule: _Rule, first: int, count: int, origins: np.ndarray, targets: np.ndarray,
                     normals: np.ndarray, distant: np.ndarray, thick, out: np.ndarray) -> None:
        """``out[first:first + count]`` (uint8), queries ``first ..`` of :meth:`query`'s inputs: bit 0 whether
        each ray is blocked (:meth:`query`'s answer), bit 1 whether that answer is uncertain: at a width of
        ``thick`` (one, or a sequence of at most 4, all looked up in one pass), the rays through the rows that
        many voxels to either side of its own (along the direction bin's two grid axes, over the same voxels;
        ``voxelq.c``'s ``vq_query_refine``) do not all answer as it does."""
        f64 = self._input_kinds(origins, targets, normals, distant)
        if out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise TypeError("query_refine output must be C-contiguous uint8")
        widths = np.ascontiguousarray(np.atleast_1d(np.asarray(thick, np.float32)))
        if not 1 <= len(widths) <= 4:
            raise ValueError(f"query_refine takes 1 to 4 widths, got {len(widths)}")
        self.lib.vq_query_refine(ctypes.byref(self.scene), ctypes.byref(rule), int(first), int(count),
                                 origins.ctypes.data, targets.ctypes.data, normals.ctypes.data, distant.ctypes.data,
                                 widths.ctypes.data, len(widths), self.kernel, f64, int(distant.dtype == np.bool_),
                                 out.ctypes.data)

    def shade(self, rule: _Rule, lights: _Lights, points: np.ndarray, normals: np.ndarray, geometric: np.ndarray,
              first_tile: int, n_tiles: int, tile: int, radiance: np.ndarray, blocked: np.ndarray,
              facing: np.ndarray, material: np.ndarray | None = None, specular: np.ndarray | None = None) -> None:
        """Alg. 3 over tiles ``first_tile ..`` (``kernels/voxel/shading.py``'s ``shade_tiles``): ``radiance`` the sum
        of each visible light's term E; with ``material`` rows (C-contiguous (P, WIDTH) float32, ``kernels/brdf``)
        E·kd, and ``specular`` ((P, 3) float32) E·ks."""
        if material is not None and (material.dtype != np.float32 or not material.flags.c_contiguous
                                     or material.shape != (len(points), WIDTH) or specular is None
                                     or specular.dtype != np.float32 or specular.shape != (len(points), 3)):
            raise TypeError("shade: material must be C-contiguous (P, WIDTH) float32 rows with a (P, 3) float32 "
                            "specular")
        self.lib.vq_shade(ctypes.byref(self.scene), ctypes.byref(rule), ctypes.byref(lights), points.ctypes.data,
                          normals.ctypes.data, geometric.ctypes.data, len(points), int(first_tile), int(n_tiles),
                          int(tile), self.kernel, radiance.ctypes.data, blocked.ctypes.data, facing.ctypes.data,
                          None if material is None else material.ctypes.data,
                          None if material is None else specular.ctypes.data)

    def shade_refine(self, rule: _Rule, lights: _Lights, points: np.ndarray, normals: np.ndarray,
                     geometric: np.ndarray, first_tile: int, n_tiles: int, tile: int, widths: np.ndarray,
                     near: np.ndarray | None, radiance: np.ndarray, blocked: np.ndarray, facing: np.ndarray,
                     listing: ShadeList) -> int:
        """:meth:`shade` with the refinement's rule at ``widths`` (float32, at most 4: :meth:`query_refine`'s
        ``thick``, uncertain at any of them) from tile ``first_tile`` (``voxelq.c``'s ``vq_shade_refine``): each
        uncertain shadow query, and each certain free one at a point with ``near`` set (uint8 per point, or
        None), is appended to ``listing`` (kind 0 and 1) instead of being counted or added. Returns the tile
        to resume from once ``listing`` is emptied (``first_tile + n_tiles``: all shaded); a tile starts only
        while the list has room for all its pairs."""
        widths = _c(widths, np.float32)
        if len(widths) > 4:
            raise ValueError("vq_shade_refine takes at most 4 widths")
        if near is not None and (near.dtype != np.uint8 or not near.flags.c_contiguous or len(near) != len(points)):
            raise TypeError("near flags must be C-contiguous uint8, one per point")
        count = np.array([listing.count], np.int64)
        resume = np.zeros(1, np.int64)
        queries = np.zeros(1, np.int64)
        self.lib.vq_shade_refine(ctypes.byref(self.scene), ctypes.byref(rule), ctypes.byref(lights),
                                 points.ctypes.data, normals.ctypes.data, geometric.ctypes.data, len(points),
                                 int(first_tile), int(n_tiles), int(tile), self.kernel, widths.ctypes.data,
                                 len(widths), None if near is None else near.ctypes.data, radiance.ctypes.data,
                                 blocked.ctypes.data, facing.ctypes.data, listing.point.ctypes.data,
                                 listing.light.ctypes.data, listing.rgb.ctypes.data, listing.kind.ctypes.data,
                                 listing.capacity, count.ctypes.data, resume.ctypes.data, queries.ctypes.data)
        listing.count = int(count[0])
        listing.queries += int(queries[0])
        return int(resume[0])

    def list_apply(self, listing: "ShadeList", free: np.ndarray, radiance: np.ndarray, blocked: np.ndarray) -> None:
        """The caller's answers to ``listing``'s entries (``free``, (count,) bool; ``voxelq.c``'s
        ``vq_list_apply``): each free entry's term added to its point's ``radiance`` ((P, 3) float32), the point's
        ``blocked`` (int32) counted up for the others, in list order."""
        free = np.ascontiguousarray(free, np.bool_)
        if len(free) != listing.count:
            raise ValueError(f"list_apply: {len(free)} answers for {listing.count} entries")
        if radiance.dtype != np.float32 or blocked.dtype != np.int32 or not (radiance.flags.c_contiguous
                                                                               and blocked.flags.c_contiguous):
            raise TypeError("list_apply: radiance must be C-contiguous float32, blocked int32")
        self.lib.vq_list_apply(listing.count, listing.point.ctypes.data, listing.rgb.ctypes.data, free.ctypes.data,
                               radiance.ctypes.data, blocked.ctypes.data)


class ShadeList:
    """:meth:`NativeScene.shade_refine`'s list of the shadow queries it leaves to the caller, ``capacity``
    entries: per entry the point (``point``, int32), the light (``light``, int32), the light's unshadowed
    term (``rgb``, (capacity, 3) float32) and the kind (0 uncertain, 1 certain free at a near point);
    ``count`` entries written, ``queries`` shadow queries answered in all."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.point = np.empty(self.capacity, np.int32)
        self.light = np.empty(self.capacity, np.int32)
        self.rgb = np.empty((self.capacity, 3), np.float32)
        self.kind = np.empty(self.capacity, np.uint8)
        self.count = 0
        self.queries = 0

    def entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(point, light, rgb, kind)`` of the entries written (views)."""
        c = self.count
        return self.point[:c], self.light[:c], self.rgb[:c], self.kind[:c]
