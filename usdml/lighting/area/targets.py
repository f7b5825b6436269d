"""``--direct lgh``'s shadow rays to lights with area: a ray the hierarchy aims at such a light's centre goes to a
point sampled on it instead (:func:`usdml.lighting.area.sampling.sample_pairs`), so its shadows are soft.

The hierarchy hands the shadow query target positions, not lights: a target is matched to its light by the float32
bits of the light's position (a target is a light's position to the bit: the grid's members and its S0 picks are
the lights' own positions). A point's rays to one light in one query are stratified over it (the k-th of its n rays
takes the k-th point of the n-point lattice, all shifted by the point's and the light's offset), so a light the
samples chose several times is sampled, not hit at one point several times.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from usdml.lighting.area.sampling import sample_pairs, sampled
from usdml.scene import Lights
from usdml.scene.hashing import fold_bits, point_keys
from usdml.visibility.emitter_ends import off_emitters

__all__ = ["AreaTargets"]


class AreaTargets:
    """The lights with area among a hierarchy's lights, and how to aim its shadow rays at them (module doc)."""

    def __init__(self, lights: Lights, seed: int, meters_per_unit: float = 1.0):
        mask = sampled(lights)
        self.lights = lights.subset(mask)
        keys = point_keys(self.lights.position)
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]
        self.seed, self.meters_per_unit = int(seed), float(meters_per_unit)

    @classmethod
    def of(cls, lights: Lights, seed: int, meters_per_unit: float = 1.0) -> "AreaTargets | None":
        """The targets of ``lights``, or None when none of them has area."""
        return cls(lights, seed, meters_per_unit) if len(lights) and sampled(lights).any() else None

    def retarget(self, origins: np.ndarray, targets: np.ndarray, occluded=None) -> np.ndarray:
        """``targets`` (N, 3) with each one at a light with area moved to a point sampled on that light, seen from
        its ray's origin (``origins`` (N, 3)); the others as they are. A point on a mesh light's triangle ends off the
        surface ``occluded``'s backend holds (:func:`usdml.visibility.emitter_ends.off_emitters`)."""
        targets = np.asarray(targets)
        keys = point_keys(targets)
        at = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        rows = np.flatnonzero(self.keys[at] == keys)
        if not len(rows):
            return targets
        light = self.order[at[rows]]
        # the rank of each ray among its point's rays to the same light, and their number
        pair = fold_bits(light.astype(np.uint64), np.asarray(origins, np.float64)[rows].astype(np.float32))
        order = np.argsort(pair, kind="stable")
        sorted_pair = pair[order]
        first = np.flatnonzero(np.r_[True, sorted_pair[1:] != sorted_pair[:-1]])
        sizes = np.diff(np.r_[first, len(order)])
        rank, count = np.empty(len(rows), np.int64), np.empty(len(rows), np.int64)
        rank[order] = np.arange(len(order)) - np.repeat(first, sizes)
        count[order] = np.repeat(sizes, sizes)
        s = sample_pairs(np.asarray(origins, np.float64)[rows], self.lights.subset(light), self.seed, rank, count,
                         self.meters_per_unit)
        out = np.array(targets, copy=True)
        out[rows] = off_emitters(s.targets[:, 0], self.lights, light, occluded)
        return out

    def wrap(self, occluded: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
        """``occluded`` asking its segments to the retargeted points (:meth:`retarget`)."""
        def query(origins, targets, **kw):
            distant = kw.get("distant")
            if distant is not None and np.asarray(distant).any():
                return occluded(origins, targets, **kw)     # directions: no light of the hierarchy
            return occluded(origins, self.retarget(origins, targets, occluded), **kw)
        return query
