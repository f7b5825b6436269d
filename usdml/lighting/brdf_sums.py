"""The preview surface's two sums per point over its visible lights, ``(ΣE·kd, ΣE·ks)``, for the shading of a
backend without a fused material kernel (:func:`usdml.lighting.direct.shade_direct` with material rows).

:func:`reference` is NumPy over ``kernels/brdf``'s ``brdf_terms``, the definition. :func:`brdf_sums` is the
compiled ``kernels/brdf/brdfsum.c`` (the same terms from ``kernels/include/brdf.h``, one pass over a block's pairs
where NumPy makes some twenty) where ``pip install`` built it, through ctypes (which releases the GIL, so the
blocks of the thread pool overlap), and :func:`reference` where it did not (no C compiler). Both round every
product and sum the same way; they differ where ``brdf.h``'s square root and fifth power round apart from NumPy's
and where it divides once per lobe, NumPy twice (an ulp or so of a term; tests/test_brdf_native.py states the
agreement).
"""

from __future__ import annotations

import ctypes

import numpy as np

from usdml.kernels.brdf import WIDTH, brdf_terms
from usdml.native import Extension

__all__ = ["EXTENSION", "brdf_sums", "compiled", "describe", "library", "reference"]

_P = ctypes.c_void_p
#: ``brdfsum.c``'s function
EXTENSION = Extension("brdf._brdfsum", {
    "bs_sums": (None, [ctypes.c_int64, ctypes.c_int32, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P]),
})


def library() -> ctypes.CDLL | None:
    """The compiled sums, or None where they were not built (no C compiler at install)."""
    return EXTENSION.library()


def describe() -> str:
    """One line: how the BRDF sums run on this machine."""
    lib, why = EXTENSION.load()
    return f"NumPy (the compiled BRDF sums are {why})" if lib is None else "compiled BRDF sums (kernels/brdf/brdfsum.c)"


def reference(g: np.ndarray, f: np.ndarray | None, w, table, rows: np.ndarray, normals: np.ndarray):
    """``(ΣE·kd, ΣE·ks)`` ``(B, 3)`` float32 of a block of ``B`` points: each pair's irradiance (``g`` (B, L) after
    shadows, pairs with ``g <= 0`` skipped; focus ``f`` (B, L) or None; ``E = g·base + g·f·focus_rgb`` of ``table``,
    a :class:`usdml.scene.light_table.LightTable`) times the BRDF terms of material ``rows`` (B, WIDTH) at unit
    shading ``normals`` (B, 3) toward the unit directions ``w`` (three (B, L) arrays) to the lights, summed per point
    in light order (NumPy)."""
    pi, li = np.nonzero(g > 0)
    e = g[pi, li][:, None] * table.base[li]
    if f is not None:
        e += (g[pi, li] * f[pi, li])[:, None] * table.focus_rgb[li]
    l = np.stack([w[0][pi, li], w[1][pi, li], w[2][pi, li]], axis=1)
    kd, ks = brdf_terms(rows[pi], normals[pi], l)
    n = len(g)
    d = np.stack([np.bincount(pi, e[:, c] * kd[:, c], minlength=n) for c in range(3)], axis=1)
    s = np.stack([np.bincount(pi, e[:, c] * ks[:, c], minlength=n) for c in range(3)], axis=1)
    return d.astype(np.float32), s.astype(np.float32)


def compiled(g: np.ndarray, f: np.ndarray | None, w, table, rows: np.ndarray, normals: np.ndarray):
    """:func:`reference` by the compiled kernel (``RuntimeError`` where it was not built)."""
    lib = library()
    if lib is None:
        raise RuntimeError(f"the compiled BRDF sums are {EXTENSION.load()[1]}")
    g = _c(g)
    n_p, n_l = g.shape
    f = None if f is None else _c(f)
    wx, wy, wz = (_c(x) for x in w)
    rows = _c(rows)
    normals = _c(normals)
    if rows.shape != (n_p, WIDTH) or normals.shape != (n_p, 3) or any(x.shape != g.shape for x in (wx, wy, wz)):
        raise ValueError(f"brdf sums: {n_p} points x {n_l} lights, got rows {rows.shape}, normals {normals.shape}, "
                         f"directions {[x.shape for x in (wx, wy, wz)]}")
    base, focus = _c(table.base), _c(table.focus_rgb)
    diffuse = np.empty((n_p, 3), np.float32)
    specular = np.empty((n_p, 3), np.float32)
    lib.bs_sums(n_p, n_l, g.ctypes.data, None if f is None else f.ctypes.data, wx.ctypes.data, wy.ctypes.data,
                wz.ctypes.data, base.ctypes.data, focus.ctypes.data, rows.ctypes.data, normals.ctypes.data,
                diffuse.ctypes.data, specular.ctypes.data)
    return diffuse, specular


def brdf_sums(g: np.ndarray, f: np.ndarray | None, w, table, rows: np.ndarray, normals: np.ndarray):
    """:func:`reference`'s sums, compiled where built (module doc)."""
    return (compiled if library() is not None else reference)(g, f, w, table, rows, normals)


def _c(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
