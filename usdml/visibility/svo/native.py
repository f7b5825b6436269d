"""The compiled CPU traversal of the svo backend: ``kernels/svo/svoq.c`` through ctypes.

Why compiled: Warp runs a CPU launch on one thread and its code for the voxel arrays' rule ran
1.4-1.8x slower than plain C (docs/voxel.md); the SVO walk is a loop of dependent loads and
branches, which Warp's CPU code handles worse still (docs/svo.md has the figures). ``svoq.c`` answers
the rule of :mod:`usdml.kernels.svo.octree` in the same float32 arithmetic from the thread pool of
:mod:`usdml.parallel` (ctypes releases the GIL during a call).

What a machine gets: ``pip install`` builds it as the optional extension ``usdml.kernels._svoq``
(setup.py). Without a C compiler :func:`library` returns None and the backend runs the Warp kernels,
as ``--svo-cpu-kernel warp`` does; ``usdml info`` names the path (:func:`describe`). GPUs run Warp.
"""

from __future__ import annotations

import ctypes

import numpy as np

# the instruction sets (ISAS: the numbers svoq.c's pick takes are voxelq.c's) and the info line
from usdml.native import ISAS, Extension, path_line

__all__ = ["EXTENSION", "ISAS", "NativeSvo", "library", "describe", "isa_width", "simd_width"]

_f = ctypes.POINTER(ctypes.c_float)
_i = ctypes.POINTER(ctypes.c_int32)
_u = ctypes.POINTER(ctypes.c_uint32)


class _Scene(ctypes.Structure):
    _fields_ = [("nodes", _i), ("bricks", _u), ("tree_int", _i), ("tree_lo", _f), ("tree_inv_h", _f),
                ("n_trees", ctypes.c_int32), ("tops", _i), ("top_level", ctypes.c_int32)]


class _Rule(ctypes.Structure):
    _fields_ = [("offset", ctypes.c_float), ("skip", ctypes.c_float), ("slab", ctypes.c_float),
                ("max_skip", ctypes.c_float), ("end_skip", ctypes.c_float), ("far", ctypes.c_float),
                ("far_center", ctypes.c_float * 3)]


_P = ctypes.c_void_p
#: ``svoq.c``'s functions
EXTENSION = Extension("svo._svoq", {
    "svo_query": (None, [ctypes.POINTER(_Scene), ctypes.POINTER(_Rule), ctypes.c_int64, ctypes.c_int64,
                         _P, ctypes.c_int32, _P, ctypes.c_int32, _P, ctypes.c_int32, _P, ctypes.c_int32, _P]),
    "svo_simd_width": (ctypes.c_int, [ctypes.c_int32]),
})


def library() -> ctypes.CDLL | None:
    """The compiled traversal, or None where it was not built (no C compiler at install)."""
    return EXTENSION.library()


def simd_width(isa: str = "auto") -> int:
    """Rays the compiled walk takes at once on this CPU with ``isa`` (:data:`ISAS`): 16 (AVX-512), 8
    (AVX2) or 1 (scalar); 0 without it."""
    lib = library()
    return int(lib.svo_simd_width(ISAS[isa])) if lib is not None else 0


#: the walk runs one ray per lane of one register: its width is its instruction set's
isa_width = simd_width


def describe() -> str:
    """One line: which CPU path SVO queries take on this machine (``usdml info``)."""
    lib, why = EXTENSION.load()
    return path_line("compiled traversal", why, simd_width() if lib is not None else 0, "rays")


def _f64(a: np.ndarray) -> int:
    if a.dtype == np.float64:
        return 1
    if a.dtype == np.float32:
        return 0
    raise TypeError(f"expected float32 or float64, got {a.dtype}")


class NativeSvo:
    """The trees of a :class:`usdml.visibility.svo.backend.SvoBackend` as ``svoq.c`` reads them: nodes, bricks,
    per tree ``(depth, node_base, brick_base, top_base)``, corners, 1 / voxel size, and the trees' top
    tables (:func:`usdml.visibility.svo.tree.top_table`) concatenated. The arrays are kept here, so the
    pointers stay valid as long as this object."""

    def __init__(self, nodes, bricks, tree_int, tree_lo, tree_inv_h, tops, isa: str = "auto"):
        from usdml.visibility.svo.tree import TOP_LEVEL
        self.kernel = ISAS[isa]
        self._keep = [np.ascontiguousarray(nodes, np.int32), np.ascontiguousarray(bricks, np.uint32),
                      np.ascontiguousarray(tree_int, np.int32), np.ascontiguousarray(tree_lo, np.float32),
                      np.ascontiguousarray(tree_inv_h, np.float32), np.ascontiguousarray(tops, np.int32)]
        nd, br, ti, lo, ih, tp = self._keep
        self.scene = _Scene(nd.ctypes.data_as(_i), br.ctypes.data_as(_u), ti.ctypes.data_as(_i),
                            lo.ctypes.data_as(_f), ih.ctypes.data_as(_f), int(ti.shape[0]), tp.ctypes.data_as(_i),
                            TOP_LEVEL)

    @staticmethod
    def rule(offset, skip, slab, max_skip, end_skip, far, far_center) -> _Rule:
        return _Rule(offset, skip, slab, max_skip, end_skip, far, (ctypes.c_float * 3)(*np.asarray(far_center, float)))

    def query(self, rule: _Rule, first: int, count: int, origins: np.ndarray, targets: np.ndarray,
              normals: np.ndarray | None, distant: np.ndarray | None, out: np.ndarray) -> None:
        """Queries ``first .. first + count - 1`` into ``out`` (float32): ``(N, 3)`` float32 or float64
        C-contiguous inputs read in place, ``distant`` bool (or None), ``normals`` None: no normals."""
        if distant is not None and distant.dtype != np.bool_:
            raise TypeError("distant must be bool")
        library().svo_query(ctypes.byref(self.scene), ctypes.byref(rule), int(first), int(count),
                            origins.ctypes.data, _f64(origins), targets.ctypes.data, _f64(targets),
                            None if normals is None else normals.ctypes.data,
                            0 if normals is None else _f64(normals),
                            None if distant is None else distant.ctypes.data, self.kernel, out.ctypes.data)
