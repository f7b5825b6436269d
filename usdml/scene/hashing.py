"""Deterministic per-element random numbers from hashes (no generator state: the same element, the same number,
on one process or many). SplitMix64's finaliser mixes 64-bit integers; :func:`fold_bits` folds the float32 bits of
each row of an array into a hash (a ray, a point); :func:`unit` turns a hash into a float in [0, 1).

Used for stochastic transparency (:mod:`usdml.visibility.exact`), the screen door of partly opaque surfaces
(:mod:`usdml.scene.cutout`) and the dome's specular samples (:mod:`usdml.lighting.dome_specular`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["GOLDEN", "fold_bits", "mix", "point_keys", "unit"]

#: 2⁶⁴ / φ, SplitMix64's increment
GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser of uint64 ``x`` (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def fold_bits(h: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(N,) uint64: ``h`` (N,) with the float32 bits of each column of ``values`` (N, C) folded in, one :func:`mix`
    a column."""
    bits = np.ascontiguousarray(values, np.float32).view(np.uint32).astype(np.uint64)
    for c in range(bits.shape[1]):
        h = mix(h ^ bits[:, c])
    return h


def point_keys(points: np.ndarray) -> np.ndarray:
    """(N,) uint64 hashes of the float32 bits of ``points`` (N, 3): equal points (to the bit), equal keys. A shadow
    ray's target is matched to the light it was aimed at this way (``usdml.visibility.emitter_ends``,
    ``usdml.lighting.area.targets``)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3).astype(np.float32)
    return fold_bits(np.zeros(len(pts), np.uint64), pts)


def unit(h: np.ndarray) -> np.ndarray:
    """(N,) float64 in [0, 1) from the top 53 bits of uint64 hashes ``h``."""
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))
