"""The compiled CPU path of the LGH's gather and shadow-ray targets: ``kernels/lgh/lghq.c`` through ctypes.

Why compiled: Warp runs a CPU launch on one thread, one point at a time, and its code for the gather
spent about 25 ns per light visited (the city at 100k VPLs, alpha 4: some 4,300 lights in each of the
stratified sweep's two passes per point, 3.7 s of a 256 px frame on two cores). ``lghq.c`` is the
rule of :mod:`usdml.kernels.lgh.shading`'s ``lgh_gather`` and ``cluster_targets``, expression by
expression with Warp's random numbers, called on blocks of rows from the thread pool of
:mod:`usdml.parallel` (ctypes releases the GIL during a call).

What a machine gets: ``pip install`` builds it as the optional extension ``usdml.kernels._lghq``
(setup.py). Without a C compiler :func:`library` returns None and the LGH runs the Warp kernels
(``--lgh-cpu-kernel warp`` does the same); ``usdml info`` names the path (:func:`describe`). GPUs run
Warp.
"""

from __future__ import annotations

import copy
import ctypes

import numpy as np

from usdml.native import Extension

__all__ = ["EXTENSION", "library", "describe", "simd", "Gather", "Members", "sums", "CosineLights", "EachLights", "EACH_GROUP", "each_lanes", "isotropic_share", "guide"]

_P = ctypes.c_void_p
_i32, _i64, _f32 = ctypes.c_int32, ctypes.c_int64, ctypes.c_float


class _Gather(ctypes.Structure):
    _fields_ = [("n_levels", _i32), ("level_origin", _P), ("level_spacing", _P), ("level_dims", _P),
                ("level_offset", _P), ("vertex_light", _P), ("light_pos", _P), ("light_int", _P), ("light_lobe", _P),
                ("light_std", _P), ("light_count", _P), ("m", _i32), ("s0", _i32), ("s0_cells", _i32 * 3),
                ("s0_start", _P), ("s0_light", _P), ("s0_pos", _P), ("s0_int", _P), ("s0_lobe", _P), ("alpha", _f32),
                ("inv_m2", _f32), ("clamp_d2", _f32), ("samples", _i32), ("jitter", _i32), ("seed", _i32),
                ("tiles", _i32), ("stratified", _i32), ("occupancy", _P), ("occ_offset", _P), ("occ_words", _P),
                ("level_rank", _P), ("top_rank", _i32)]


class _Outputs(ctypes.Structure):
    _fields_ = [("irradiance", _P), ("count", _P), ("sample_pos", _P), ("sample_ok", _P), ("sample_light", _P),
                ("sample_weight", _P), ("sample_blend", _P), ("sample_lum", _P), ("stride", _i32)]


class _Members(ctypes.Structure):
    _fields_ = [("start", _P), ("stop", _P), ("rows", _P), ("guide", _P), ("positions", _P), ("grid_lights", _i32),
                ("inv_m2", _f32), ("clamp_d2", _f32)]


#: ``lghq.c``'s member record: the running sum, then the member light's position, intensity, normal, index
ROW = np.dtype([("cum", np.float64), ("pos", np.float32, 3), ("inten", np.float32, 3), ("nrm", np.float32, 3),
                ("member", np.int32)])


#: ``lghq.c``'s functions; opened with the light terms 8 at a time where the CPU has AVX2
EXTENSION = Extension("lgh._lghq", {
    "lghq_gather": (ctypes.c_int, [ctypes.POINTER(_Gather), _P, _P, _P, _i64, _i64, _i64, ctypes.POINTER(_Outputs)]),
    "lghq_gather_brdf": (ctypes.c_int, [ctypes.POINTER(_Gather), _P, _P, _P, _i64, _i64, _i64,
                                         ctypes.POINTER(_Outputs), _P, _P, _P]),
    "lghq_simd": (ctypes.c_int, [ctypes.c_int]),
    "lghq_targets": (None, [ctypes.POINTER(_Members), _P, _P, _i32, _i64, _i32, _P, _P, _i32, _P, _P, _P, _P,
                            _i64, _i64, _P, _P]),
    "lghq_sums": (None, [_P, _P, _i64, _i64, _i64, _P, _P]),
    "lghq_guide": (None, [_P, _P, _P, _i64, _P]),
    "lghq_cosine_sum": (None, [_P, _P, _P, _i64, ctypes.c_double, _i64, _i64, _P]),
    "lghq_each_lanes": (ctypes.c_int, []),
    "lghq_each_chunk": (ctypes.c_int, []),
    "lghq_each": (ctypes.c_int, [_P, _P, _P, _P, _P, _i64, _i32, _f32, _f32, _i32, _i32, _i64, _i64, _i64, _P, _P,
                                 _P, _P, _P, _P]),
    "lghq_each_brdf": (ctypes.c_int, [_P, _P, _P, _P, _i64, _i32, _f32, _f32, _i32, _i32, _i64, _i64, _i64, _P, _P,
                                      _P, _P, _P, _P, _P, _P, _P]),
    "lghq_atrous_step": (None, [_P, _P, _P, _P, _P, _i32, _i32, _i32, _i32, _f32, _f32, _f32, _i32, _i32, _P]),
}, on_load=lambda lib: lib.lghq_simd(1))


def library() -> ctypes.CDLL | None:
    """The compiled gather, or None where it was not built (no C compiler at install)."""
    return EXTENSION.library()


def describe() -> str:
    """One line: which CPU path the LGH's gather and shadow targets take on this machine (``usdml info``)."""
    lib, why = EXTENSION.load()
    if lib is not None:
        width = lib.lghq_simd(-1)
        return f"compiled gather (kernels/lgh/lghq.c), one point per thread, light terms {'8 at a time (AVX2)' if width == 8 else 'one at a time'}"
    return f"Warp kernels, one point per thread (compiled gather {why})"


def simd(allow: bool = True) -> int:
    """The gather's light terms 8 at a time (AVX2, where the CPU has it) or, with ``allow`` False, one at a
    time (the same bits; for tests and measurements): the width it runs. 0 without the library."""
    lib = library()
    return 0 if lib is None else int(lib.lghq_simd(int(bool(allow))))


def _c(a, dtype) -> np.ndarray:
    return np.ascontiguousarray(a, dtype)


def _ptr(a: np.ndarray | None) -> int | None:
    return None if a is None else a.ctypes.data


def _occupancy(dims: np.ndarray, offset: np.ndarray, vertex_light: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One bit per grid vertex, set where it holds a light: per level, each column (i, j) as
    ceil(dims_k / 64) little-endian 64-bit words along k (``lghq.c``'s ``occupancy``), the levels one
    after another: ``(words (uint64), first word of each level (int64), words per column (int32))``."""
    parts, starts, widths = [], [], []
    at = 0
    for (d0, d1, d2), off in zip(np.asarray(dims, np.int64).reshape(-1, 3), np.asarray(offset, np.int64)):
        words = (int(d2) + 63) // 64
        held = np.zeros((int(d0), int(d1), words * 64), bool)
        held[:, :, :d2] = (vertex_light[off:off + d0 * d1 * d2] >= 0).reshape(d0, d1, d2)
        packed = np.packbits(held, axis=2, bitorder="little").reshape(-1)
        parts.append(np.frombuffer(packed.tobytes(), "<u8"))
        starts.append(at)
        widths.append(words)
        at += len(parts[-1])
    return (np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros(1, np.uint64), np.uint64),
            np.asarray(starts, np.int64), np.asarray(widths, np.int32))


class Gather:
    """``lghq_gather``'s tables for one hierarchy and its settings (the arguments of
    :class:`usdml.lighting.lgh.shading.LGHGather`; the arrays are held here)."""

    def __init__(self, flat: tuple, s0: tuple | None, alpha: float, inv_m2: float, clamp_d2: float, samples: int,
                 jitter: bool, seed: int, tiles: int, stratified: bool):
        origin, spacing, dims, offset, vertex_light, pos, inten, std, lobe, count, rank = flat
        self._hold = hold = [_c(origin, np.float32), _c(spacing, np.float32), _c(dims, np.int32),
                             _c(offset, np.int32), _c(vertex_light, np.int32), _c(pos, np.float32),
                             _c(inten, np.float32), _c(lobe, np.float32), _c(std, np.float32), _c(count, np.float32)]
        g = self.table = _Gather()
        g.n_levels = len(hold[1])
        (g.level_origin, g.level_spacing, g.level_dims, g.level_offset, g.vertex_light, g.light_pos, g.light_int,
         g.light_lobe, g.light_std, g.light_count) = (_ptr(a) for a in hold)
        g.m = len(hold[5])
        if s0 is not None:
            cells, start, order, s0_pos, s0_int, s0_lobe = s0
            arrays = [_c(start, np.int32), _c(order, np.int32), _c(s0_pos, np.float32), _c(s0_int, np.float32),
                      _c(s0_lobe, np.float32)]
            hold += arrays
            g.s0 = 1
            g.s0_cells[:] = [int(c) for c in cells]
            g.s0_start, g.s0_light, g.s0_pos, g.s0_int, g.s0_lobe = (_ptr(a) for a in arrays)
        g.alpha, g.inv_m2, g.clamp_d2 = float(alpha), float(inv_m2), float(clamp_d2)
        g.samples, g.jitter, g.seed = int(samples), int(bool(jitter)), int(seed)
        g.tiles, g.stratified = int(max(tiles, 1)), int(bool(stratified))
        occupancy, occ_offset, occ_words = _occupancy(hold[2], hold[3], hold[4])
        hold += [occupancy, occ_offset, occ_words]
        g.occupancy, g.occ_offset, g.occ_words = (_ptr(a) for a in (occupancy, occ_offset, occ_words))
        rank = _c(rank, np.int32)
        hold.append(rank)
        g.level_rank, g.top_rank = _ptr(rank), int(rank.max())

    def at_alpha(self, alpha: float) -> "Gather":
        """These tables at blending radius factor ``alpha`` (the arrays shared, the table copied)."""
        other = copy.copy(self)
        other.table = _Gather.from_buffer_copy(self.table)
        other.table.alpha = float(alpha)
        return other

    def __call__(self, points: np.ndarray, normals: np.ndarray, tile: np.ndarray, lo: int, hi: int, first: int,
                 outputs: tuple, brdf: tuple | None = None) -> None:
        """Rows ``lo .. hi - 1`` of ``points`` / ``normals`` (P, 3) float32 and ``tile`` (P,) int32 into
        ``outputs`` = (irradiance, count, pos, ok, light, weight, blend, lum), C-contiguous, zeroed; the
        rows' random streams numbered ``first + row``. ``brdf = (material (P, WIDTH), albedo (P, 3), specular
        (P, 3))`` float32, C-contiguous: the preview surface (``lghq_gather_brdf``): ``irradiance`` gets the outgoing
        radiance, ``specular`` its specular part, the samples are drawn and weighed by each light's radiance."""
        irr, cnt, spos, sok, slight, sweight, sblend, slum = outputs
        out = _Outputs(*(a.ctypes.data for a in outputs), spos.shape[1])
        args = (ctypes.byref(self.table), points.ctypes.data, normals.ctypes.data, tile.ctypes.data, int(lo), int(hi),
                int(first), ctypes.byref(out))
        ok = (library().lghq_gather(*args) if brdf is None else
              library().lghq_gather_brdf(*args, *(a.ctypes.data for a in brdf)))
        if not ok:
            raise MemoryError("the LGH gather ran out of memory for a point's list of lights")


class Members:
    """``lghq_targets``' tables: a :class:`usdml.lighting.lgh.shading.ClusterSampler`'s members."""

    def __init__(self, start, stop, cum, guide, member, positions, intensity, normals, grid_lights: int,
                 inv_m2: float, clamp_d2: float):
        member = np.asarray(member, np.int64)
        rows = np.zeros(len(cum), ROW)            # len(member) + 1: the last row holds only the total
        rows["cum"] = cum
        rows["member"][:-1] = member
        for name, a in (("pos", positions), ("inten", intensity), ("nrm", normals)):
            rows[name][:-1] = np.asarray(a, np.float32).reshape(-1, 3)[member]
        positions = _c(positions, np.float32)
        self._hold = hold = [_c(start, np.int32), _c(stop, np.int32), rows, _c(guide, np.int32), positions]
        self.table = _Members(*(a.ctypes.data for a in hold), int(grid_lights), float(inv_m2), float(clamp_d2))

    def __call__(self, lights, fallback, seed: int, first: int, runs, reweight: tuple | None, lo: int, hi: int,
                 out: np.ndarray, out_weight: np.ndarray) -> None:
        """Samples ``lo .. hi - 1`` (C-contiguous int32 / float32 arrays, as ``cluster_targets`` takes them):
        ``runs = (rank, length)`` or None, ``reweight = (points, normals, pixel, blend)`` or None."""
        rank, length = runs if runs is not None else (None, None)
        pts, nrm, pixel, blend = reweight if reweight is not None else (None, None, None, None)
        library().lghq_targets(ctypes.byref(self.table), lights.ctypes.data, fallback.ctypes.data, int(seed),
                               int(first), int(runs is not None), _ptr(rank), _ptr(length), int(reweight is not None),
                               _ptr(pts), _ptr(nrm), _ptr(pixel), _ptr(blend), int(lo), int(hi), out.ctypes.data,
                               out_weight.ctypes.data)


def sums(visible: np.ndarray, weight: np.ndarray, num: np.ndarray, den: np.ndarray, lo: int, hi: int) -> None:
    """Points ``lo .. hi - 1``: ``num`` = Σ_s V_s w_s and ``den`` = Σ_s w_s per channel (``visible`` (P, k)
    float32, ``weight`` (P, k, 3) float32, ``num`` / ``den`` (P, 3) float32, all C-contiguous), summed in
    double (``lghq_sums``)."""
    library().lghq_sums(visible.ctypes.data, weight.ctypes.data, visible.shape[1], int(lo), int(hi), num.ctypes.data,
                        den.ctypes.data)


class CosineLights:
    """``lghq_cosine_sum``'s lights: positions, normals and intensities (Φ/4π) of N one-sided cosine emitters as
    nine float32 columns."""

    def __init__(self, positions: np.ndarray, intensity: np.ndarray, normals: np.ndarray):
        self.n = len(positions)
        self._columns = np.ascontiguousarray(np.concatenate([np.asarray(a, np.float32).reshape(-1, 3).T for a in
                                                             (positions, normals, intensity)]), np.float32)
        self._pointers = (ctypes.c_void_p * 9)(*(self._columns[i].ctypes.data for i in range(9)))

    def sum(self, points: np.ndarray, normals: np.ndarray, clamp_d2: float, lo: int, hi: int, out: np.ndarray) -> None:
        """Points ``lo .. hi - 1`` (``points``, ``normals``: (P, 3) float32, C-contiguous): ``out`` (P, 3) float64
        += every light's unshadowed irradiance, in scene units (no metersPerUnit)."""
        library().lghq_cosine_sum(points.ctypes.data, normals.ctypes.data, self._pointers, self.n, float(clamp_d2),
                                  int(lo), int(hi), out.ctypes.data)


#: ``lghq_each`` takes its lights in groups of this many (``EACH_GROUP``; :class:`EachLights` pads with lights that
#: add nothing)
EACH_GROUP = 64


def each_lanes() -> int:
    """The lanes ``lghq_each`` runs on this CPU: 16 (AVX-512), 8 (AVX2), 4 (SSE), 0 where unknown (no function
    clones on this platform) or where nothing was compiled."""
    lib = library()
    return 0 if lib is None else int(lib.lghq_each_lanes())


#: ``lghq_each``'s modes: the lights' terms (every isotropic share a 0, every one 1, or mixed)
EACH_MODES = {"cosine": 0, "isotropic": 1, "mixed": 2}


def isotropic_share(normals: np.ndarray) -> np.ndarray:
    """``(N,)`` float64: each light's isotropic share in the LGH's lobe, ``a = 1 - |normal|`` (0 for a VPL or a disk
    light's unit normal, 1 for a point light's zero normal), rounding off a unit normal's float error."""
    share = np.clip(1.0 - np.sqrt((np.asarray(normals, np.float64).reshape(-1, 3) ** 2).sum(axis=1)), 0.0, 1.0)
    share[share < 1e-6] = 0.0
    return share


class EachLights:
    """``lghq_each``'s lights: N emitters as the LGH models them (positions, normals, intensities), an isotropic
    share a = 1 - |normal| plus a one-sided cosine lobe about the normal (VPLs and disk lights: unit normals;
    point lights: no normal), as eleven float32 columns (the tenth each intensity's luminance, the eleventh a),
    padded to a multiple of :data:`EACH_GROUP` with lights of no intensity, no normal and a = 0. ``normals``
    None: every light isotropic."""

    def __init__(self, positions: np.ndarray, intensity: np.ndarray, normals: np.ndarray | None):
        self.n = len(positions)
        padded = -(-self.n // EACH_GROUP) * EACH_GROUP
        self._columns = np.zeros((11, padded), np.float32)
        self._columns[0:3, :self.n] = np.asarray(positions, np.float32).reshape(-1, 3).T
        self._columns[6:9, :self.n] = np.asarray(intensity, np.float32).reshape(-1, 3).T
        if normals is not None:
            self._columns[3:6, :self.n] = np.asarray(normals, np.float32).reshape(-1, 3).T
        self._columns[10, :self.n] = isotropic_share(self._columns[3:6, :self.n].T)
        lum = np.array([0.2126, 0.7152, 0.0722], np.float32)   # lghq.c's LUMA0..2
        self._columns[9, :self.n] = np.maximum(lum @ self._columns[6:9, :self.n], 0.0)
        self._columns[:3, self.n:] = self._columns[:3, :1] if self.n else 0.0
        self._pointers = (ctypes.c_void_p * 11)(*(self._columns[i].ctypes.data for i in range(11)))
        self.padded = padded
        a = self._columns[10, :self.n]
        self.mode = ("cosine" if not (a > 0).any() else "isotropic" if (a == 1.0).all() else "mixed")
        # each chunk's box (centre, half extents) of the kernel's chunks of lights: a point skips a chunk whose
        # box lies behind its tangent plane (the lights are in Morton order, so a chunk is a compact region)
        chunk = int(library().lghq_each_chunk())
        chunks = -(-padded // chunk)
        pos = self._columns[:3].T
        self._box = np.zeros((chunks, 6), np.float32)
        for c in range(chunks):
            part = pos[c * chunk:(c + 1) * chunk].astype(np.float64)
            lo, hi = part.min(axis=0), part.max(axis=0)
            self._box[c, :3] = 0.5 * (lo + hi)
            self._box[c, 3:] = 0.5 * (hi - lo) * (1 + 1e-6) + 1e-6 * (np.abs(lo) + np.abs(hi))
        # each group's one unit normal where all its lights have it (and a = 0), else NaN (equal to no normal): a
        # pair of points whose normals are that one skips the group (each term's cos θ_s or cos θ_l is then at
        # most 0: the same dot product, negated)
        groups = padded // EACH_GROUP
        nrm = self._columns[3:6].T.reshape(groups, EACH_GROUP, 3)
        same = (nrm == nrm[:, :1]).all(axis=(1, 2)) & (self._columns[10].reshape(groups, EACH_GROUP) == 0).all(1)
        same &= np.abs((nrm[:, 0] ** 2).sum(1) - 1.0) < 1e-5
        self._group_normal = np.ascontiguousarray(np.where(same[:, None], nrm[:, 0], np.nan), np.float32)
        self.shared = float(same.mean()) if groups else 0.0    # the groups with one normal

    def gather(self, points: np.ndarray, normals: np.ndarray, clamp_d2: float, inv_m2: float, samples: int, seed: int,
               first: int, lo: int, hi: int, out: tuple, cull: bool = True) -> None:
        """Points ``lo .. hi - 1`` (``points``, ``normals``: (P, 3) float32, C-contiguous; point p's random stream
        ``first + p``): ``out = (irradiance (P, 3) f32, count (P,) f32, light (P, k) int32, weight (P, k, 3) f32,
        lum (P, k) f32, ok (P, k) uint8)`` written for those rows (``lghq_each``; count: the lights that reach
        the point). ``cull``: skip the chunks behind a point and the groups whose one normal is the point's (the same
        answers, bit for bit)."""
        if not library().lghq_each(points.ctypes.data, normals.ctypes.data, self._pointers,
                                   self._box.ctypes.data if cull else None,
                                   self._group_normal.ctypes.data if cull else None,
                                   self.padded,
                                   EACH_MODES[self.mode], float(clamp_d2), float(inv_m2), int(samples), int(seed),
                                   int(first), int(lo), int(hi), *(a.ctypes.data for a in out)):
            raise MemoryError("lghq_each: no memory for a point's running sums")

    def gather_brdf(self, points: np.ndarray, normals: np.ndarray, material: np.ndarray, albedo: np.ndarray,
                    clamp_d2: float, inv_m2: float, samples: int, seed: int, first: int, lo: int, hi: int,
                    out: tuple, cull: bool = True) -> None:
        """:meth:`gather` with the preview surface (``lghq_each_brdf``): ``material`` (P, WIDTH) and ``albedo`` (P, 3)
        float32, C-contiguous; ``out = (radiance (P, 3), specular (P, 3), count, light, weight, lum, ok)``: every
        light's outgoing radiance and its specular part, the draws in proportion to each light's radiance."""
        radiance, specular, count, light, weight, lum, ok = out
        if not library().lghq_each_brdf(points.ctypes.data, normals.ctypes.data, self._pointers,
                                        self._box.ctypes.data if cull else None, self.padded, EACH_MODES[self.mode],
                                        float(clamp_d2), float(inv_m2), int(samples), int(seed), int(first), int(lo),
                                        int(hi), material.ctypes.data, albedo.ctypes.data, radiance.ctypes.data,
                                        specular.ctypes.data, *(a.ctypes.data for a in (count, light, weight, lum, ok))):
            raise MemoryError("lghq_each_brdf: no memory for a point's light terms")


def guide(cum: np.ndarray, start: np.ndarray, stop: np.ndarray, rows: int) -> np.ndarray:
    """:func:`usdml.lighting.lgh.shading._guide_table` by ``lghq_guide``: ``(max(rows, 1),)`` int32."""
    cum = _c(cum, np.float64)
    start, stop = _c(start, np.int64), _c(stop, np.int64)
    out = np.zeros(max(rows, 1), np.int32)
    library().lghq_guide(cum.ctypes.data, start.ctypes.data, stop.ctypes.data, len(start), out.ctypes.data)
    return out
