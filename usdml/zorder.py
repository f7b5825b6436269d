"""Points in Z-order: neighbours in space near one another in a list (the CPU shading tiles of the voxel
backend, the bench's query order, the LGH's member draws)."""

from __future__ import annotations

import numpy as np

__all__ = ["morton_order"]


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting ``points`` along a Z-order curve of a 2^10 grid over their bounds."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")
