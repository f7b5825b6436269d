"""Shadow rays that end on an emitting surface: a mesh light's triangle (:attr:`usdml.scene.LightType.TRIANGLE`).

A voxel backend's shadow ray leaves its own surface by ``normal_offset`` voxels along the normal and a skip (the
start's rule); at the light it ignores only ``end_skip`` voxels along the ray. A light mounted in front of a wall
is clear of it, but a mesh light's triangle *is* the surface: its own voxels (one to two thick) hold the end of
every ray to it, and a ray that arrives at a grazing angle crosses them for ``thickness / sin β`` voxels, far more
than ``end_skip``. Measured on a 2 × 2 panel of 128 triangles 2 units above a ground (96 px,
``tools/mesh_light_accuracy.py``): voxel 11.5 % median off exact, svo 100 % (every ray far from the panel blocked).

So the end gets the start's rule: a target at a triangle light's position (its centroid, exactly as the snapshot
gives it: matched on its float32 bits) moves ``lift`` along the triangle's normal, to the emitting side the ray
comes from, and the ray ends there, clear of the surface's voxels; the voxel backend's compiled fused kernel takes
the same ends as its light table's ``target``. The cost is the start's: an occluder closer than ``lift`` to the
emitting surface does not shadow it.
"""

from __future__ import annotations

import numpy as np

from usdml.scene import Lights, LightType
from usdml.scene.hashing import point_keys

__all__ = ["EmitterEnds", "off_emitters"]


def off_emitters(targets: np.ndarray, lights: Lights, index: np.ndarray, occluded) -> np.ndarray:
    """Points sampled on lights (``targets`` (N, 3), on lights ``index`` (N,) of ``lights``) as shadow-ray ends for
    ``occluded`` (a backend's bound method): those on a triangle light moved its backend's ``emitter_offset`` along
    the triangle's normal, off the surface the backend holds (the ends :class:`EmitterEnds` gives its centroid);
    ``targets`` itself where none moves. Used wherever a point is sampled on a light for a shadow ray (lights with
    area, ``usdml.lighting.area``)."""
    lift = float(getattr(getattr(occluded, "__self__", None), "emitter_offset", 0.0) or 0.0)
    on = (np.asarray(lights.type)[index] == LightType.TRIANGLE) if lift > 0 else None
    if on is None or not on.any():
        return targets
    out = np.array(targets, np.float64)
    out[on] += np.asarray(lights.axis, np.float64)[np.asarray(index)[on]] * lift
    return out


class EmitterEnds:
    """The snapshot's triangle lights as shadow-ray ends: ``lift(targets, distant, distance)``."""

    def __init__(self, position: np.ndarray, normal: np.ndarray):
        self.position = np.asarray(position, np.float32).reshape(-1, 3)
        keys = point_keys(self.position)
        order = np.argsort(keys, kind="stable")
        self._keys, self._order = keys[order], order
        self.normal = np.asarray(normal, np.float64).reshape(-1, 3)

    @classmethod
    def of(cls, lights: Lights) -> "EmitterEnds | None":
        """The triangle lights of ``lights``; None when there is none (nothing to look up)."""
        tri = np.asarray(lights.type) == LightType.TRIANGLE
        if not tri.any():
            return None
        return cls(np.asarray(lights.position)[tri], np.asarray(lights.axis)[tri])

    def lift(self, targets: np.ndarray, distant: np.ndarray | None, distance: float) -> np.ndarray:
        """``targets`` (N, 3) with those at a triangle light's position moved ``distance`` (world units) along its
        normal (distant rows untouched); the same array when none is."""
        t = np.asarray(targets)
        if not len(t) or distance <= 0:
            return targets
        keys = point_keys(t)
        at = np.minimum(np.searchsorted(self._keys, keys), len(self._keys) - 1)
        light = self._order[at]
        hit = (self._keys[at] == keys) & (self.position[light] == np.asarray(t, np.float32)).all(axis=1)
        if distant is not None:
            hit &= ~np.asarray(distant, bool)
        if not hit.any():
            return targets
        out = np.array(t, np.float64)
        out[hit] += self.normal[light[hit]] * distance
        return out
