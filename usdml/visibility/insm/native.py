"""The compiled CPU path of the insm backend's per-light maps: ``kernels/insm/insmr.c`` through ctypes.

Why compiled: Warp runs a CPU launch on one thread and its code spent 26 ns per triangle only to
reject it against a cube's six faces and 160 ns to rasterize one (docs/insm.md); ``insmr.c`` does one
light's receiver tiles, rasterization and lookups with the rules of :mod:`usdml.kernels.insm.maps`, called
from the thread pool of :mod:`usdml.parallel` (ctypes releases the GIL during a call).

What a machine gets: ``pip install`` builds it as the optional extension ``usdml.kernels._insmr``
(setup.py). Without a C compiler :func:`library` returns None and the backend runs the Warp kernels
(``--insm-cpu-kernel warp`` does the same); ``usdml info`` names the path (:func:`describe`).
"""

from __future__ import annotations

import ctypes

import numpy as np

from usdml.native import Extension

__all__ = ["EXTENSION", "library", "describe", "light", "pyramid_blocks", "refine_floats"]

_P, _i32, _i64, _f32 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_float
#: ``insmr.c``'s function
EXTENSION = Extension("insm._insmr", {
    "insm_light": (None, [_P, _i64, _P, _P, _i64, _P, _P, _P, _P, _P, _i32, _i32, _i32, _P, _i32, _P, _i32, _P, _P,
                          _P, _P, _i64, _f32, _f32, _P, _P, _P, _i32, _P, _P, _P, _P, _P, _P, _P,
                          _P, _P, _P, _P, _i32]),
})


def library() -> ctypes.CDLL | None:
    """The compiled maps, or None where they were not built (no C compiler at install)."""
    return EXTENSION.library()


def describe() -> str:
    """One line: which CPU path the insm backend's maps take on this machine (``usdml info``)."""
    lib, why = EXTENSION.load()
    return "compiled maps (kernels/insm/insmr.c), one light per thread" if lib is not None else \
        f"Warp kernels, one light per thread (compiled maps {why})"


def pyramid_blocks(size: int) -> int:
    """Blocks of one view's pyramid above its ``size``² texels (``insmr.c``'s ``pyramid_levels``): ``ceil(size /
    2^L)²`` for ``L = 1`` up to one block."""
    total, side = 0, int(size)
    while side > 1:
        side = (side + 1) // 2
        total += side * side
    return total


def refine_floats(size: int, n_views: int) -> int:
    """Floats of the scratch a refining call (:func:`light`'s ``refine``) needs for ``n_views`` views of
    ``size``² texels: per view a map of the triangles' spacings, a triple per texel and a triple per block of
    its pyramid."""
    return int(n_views) * (4 * int(size) ** 2 + 3 * pyramid_blocks(size))


def light(tris: np.ndarray, clusters: tuple, views: tuple, first_view: int, n_views: int, cube: bool,
          position: np.ndarray, size: int, buffers: tuple, points: np.ndarray, normals: np.ndarray, offset: float,
          bias: float, out: np.ndarray | None, seconds: np.ndarray, shade: tuple | None = None,
          refine: tuple | None = None, hand_level: int = 0) -> None:
    """One light's maps and lookups (``insm_light``): ``tris`` (3T, 3) float32 and their
    :func:`usdml.visibility.insm.mesh.clusters` (first triangles, boxes), ``views`` the C-contiguous
    (origin, rot, proj, kind, near) arrays of every view, ``buffers`` (depth, tile_z, view_z) float32 of
    at least ``n_views`` views, ``points`` / ``normals`` (geometric) (P, 3) float32, ``seconds`` (3,)
    float64 accumulating receivers, rasterization, lookups. Either ``out`` (P,) uint8 answers, or
    ``shade`` = (light table (:func:`usdml.visibility.voxel.native.compiled_lights`), this light's row,
    (P, 3) float32 shading normals, (P, 3) float32 and (P,) uint8 scratch, (P, 3) float32 radiance,
    (P,) int32 blocked and facing, (1,) int64 queries) accumulated: the light's share of Alg. 3.
    ``refine`` = (triangles' (T,) float32 sample spacings, float32 scratch of at least :func:`refine_floats`,
    the float32 rule ``levels, jump, r0, c[levels], band[levels]``, (P,) uint8 grades): with ``out``, each
    answer's grade too (:mod:`usdml.visibility.insm.backend`, "Refinement"), the answers unchanged; with ``shade``,
    the looked-up points graded ``1 .. hand_level`` are handed back (counted facing and asked, neither blocked
    nor lit; their grade kept, 0 for every other point) for the caller to answer."""
    origin, rot, proj, kind, near = views
    depth, tile_z, view_z = buffers
    pos = np.ascontiguousarray(position, np.float32)
    tiles = int(round((tile_z.size // max(view_z.size, 1)) ** 0.5))
    first, boxes = clusters
    if shade is None:
        extra = [None, 0, None, None, None, None, None, None, None]
    else:
        table, row, shading, rgb, code, radiance, blocked, facing, queries = shade
        extra = [ctypes.byref(table), int(row), shading.ctypes.data, rgb.ctypes.data, code.ctypes.data,
                 radiance.ctypes.data, blocked.ctypes.data, facing.ctypes.data, queries.ctypes.data]
    library().insm_light(tris.ctypes.data, len(tris) // 3, first.ctypes.data, boxes.ctypes.data, len(boxes),
                         origin.ctypes.data, rot.ctypes.data, proj.ctypes.data, kind.ctypes.data, near.ctypes.data,
                         int(first_view), int(n_views), int(bool(cube)), pos.ctypes.data, int(size),
                         depth.ctypes.data, tiles, tile_z.ctypes.data, view_z.ctypes.data, points.ctypes.data,
                         normals.ctypes.data, len(points), float(offset), float(bias),
                         None if out is None else out.ctypes.data, seconds.ctypes.data, *extra,
                         *([None] * 4 if refine is None else [a.ctypes.data for a in refine]), int(hand_level))
