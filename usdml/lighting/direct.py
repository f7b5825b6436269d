"""Direct many-light shading (paper 000, Alg. 3): every pixel against every light, any visibility backend.

For a surface point P with unit normal n and Lambertian albedo ρ, each light contributes
outgoing radiance ``ρ/π · E``, with irradiance

* point, sphere, disk, rect lights (treated as points at their centre):
  ``E = I · S(θ_l) · max(0, n·ω) / d²`` where ω is the unit direction to the light, d its distance,
  θ_l the angle between the light's axis and −ω, ``I`` the light's radiant intensity
  (:class:`usdml.scene.Lights`); disk and rect lights emit one-sided with a ``max(0, cos θ_l)``
  profile, sphere and point lights isotropically;
* distant lights: ``E = E₀ · max(0, n·ω)`` with ω = −axis.

``S`` is UsdLux shaping: zero outside the cone half-angle, a smoothstep from ``cos(angle)`` to
``cos(angle·(1−softness))`` across the cone edge, and focus as ``focusTint + (1 − focusTint)·cos^focus θ_l``.

A light *faces* a point when its unshadowed contribution is non-zero; the ``shadow`` AOV is the
fraction of facing lights that are blocked (paper 000's hiddenLightsN / n).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from usdml.scene import Lights, LightType

#: (pixel, light) pairs evaluated per chunk: bounds memory at a few hundred MB
PAIRS_PER_CHUNK = 1 << 21


@dataclass
class DirectResult:
    radiance: np.ndarray    #: (P, 3) float32 outgoing radiance ρ/π·ΣE over visible lights
    shadow: np.ndarray      #: (P,) float32 blocked / facing, 0 where no light faces
    facing: np.ndarray      #: (P,) int32 number of lights facing each point
    queries: int            #: shadow queries asked of the backend


def shaping(lights: Lights, idx: np.ndarray, cos_l: np.ndarray) -> np.ndarray:
    """UsdLux cone, softness and focus: ``(K, 3)`` factor for lights ``idx`` at off-axis cosine ``cos_l``."""
    angle = np.radians(np.minimum(lights.cone_angle[idx], 180.0))
    soft = np.clip(lights.cone_softness[idx], 0.0, 1.0)
    outer = np.cos(angle)
    inner = np.cos(angle * (1.0 - soft))
    width = inner - outer
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(width > 1e-12, (cos_l - outer) / np.where(width > 1e-12, width, 1.0), (cos_l >= outer) * 1.0)
    x = np.clip(x, 0.0, 1.0)
    cone = np.where(lights.cone_angle[idx] >= 180.0, 1.0, x * x * (3.0 - 2.0 * x))
    focus = lights.focus[idx]
    factor = np.broadcast_to(cone[:, None], (len(idx), 3)).copy()
    shaped = focus > 0
    if shaped.any():
        c = np.clip(cos_l[shaped], 0.0, 1.0) ** focus[shaped]
        tint = lights.focus_tint[idx[shaped]]
        factor[shaped] *= tint + (1.0 - tint) * c[:, None]
    return factor


def _unshadowed(points: np.ndarray, normals: np.ndarray, lights: Lights, pi: np.ndarray,
                li: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Irradiance ``(K, 3)`` and the shadow-ray target for the pairs (pixel ``pi``, light ``li``)."""
    p, n = points[pi], normals[pi]
    ltype = lights.type[li]
    distant = ltype == LightType.DISTANT
    to_light = lights.position[li] - p
    to_light[distant] = -lights.axis[li[distant]]
    d2 = np.einsum("ij,ij->i", to_light, to_light)
    d2[distant] = 1.0
    d = np.sqrt(d2)
    w = to_light / np.where(d > 0, d, 1.0)[:, None]
    cos_s = np.einsum("ij,ij->i", n, w)
    cos_l = -np.einsum("ij,ij->i", lights.axis[li], w)        # off-axis cosine at the light
    one_sided = (ltype == LightType.DISK) | (ltype == LightType.RECT)
    profile = np.where(one_sided, np.maximum(cos_l, 0.0), 1.0)
    falloff = np.where(distant, 1.0, 1.0 / np.maximum(d2, 1e-12))
    scalar = np.maximum(cos_s, 0.0) * profile * falloff * (d > 0)
    e = lights.intensity[li].astype(np.float64) * scalar[:, None] * shaping(lights, li, cos_l)
    return e, w


def shade_direct(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights: Lights,
                 occluded: Callable[..., np.ndarray] | None,
                 progress: Callable[[int], None] | None = None) -> DirectResult:
    """Shade ``P`` surface points by every light.

    Parameters
    ----------
    points, normals, albedo : (P, 3) world positions, unit shading normals, linear RGB albedo.
    lights : all lights of the frame.
    occluded : ``occluded(origins, targets, normals=, distant=) -> (K,) bool`` of a visibility
        backend (:meth:`usdml.visibility.VisibilityBackend.occluded`); None shades unshadowed.
    progress : called with the number of points finished after each chunk.
    """
    n_p, n_l = len(points), len(lights)
    radiance = np.zeros((n_p, 3), np.float64)
    blocked = np.zeros(n_p, np.int64)
    facing = np.zeros(n_p, np.int64)
    queries = 0
    if n_l == 0 or n_p == 0:
        return DirectResult(radiance.astype(np.float32), np.zeros(n_p, np.float32), facing.astype(np.int32), 0)
    step = max(1, PAIRS_PER_CHUNK // n_l)
    casts = lights.shadow
    for lo in range(0, n_p, step):
        hi = min(n_p, lo + step)
        pi = np.repeat(np.arange(lo, hi), n_l)
        li = np.tile(np.arange(n_l), hi - lo)
        e, w = _unshadowed(points, normals, lights, pi, li)
        live = e.max(axis=1) > 0
        pi, li, e, w = pi[live], li[live], e[live], w[live]
        np.add.at(facing, pi, 1)
        if occluded is not None and len(pi):
            test = casts[li]
            hit = np.zeros(len(pi), bool)
            if test.any():
                distant = lights.type[li[test]] == LightType.DISTANT
                targets = np.where(distant[:, None], w[test], lights.position[li[test]])
                hit[test] = occluded(points[pi[test]], targets, normals=normals[pi[test]], distant=distant)
                queries += int(test.sum())
            np.add.at(blocked, pi[hit], 1)
            e[hit] = 0.0
        for c in range(3):
            radiance[:, c] += np.bincount(pi, weights=e[:, c], minlength=n_p)
        if progress is not None:
            progress(hi - lo)
    radiance *= albedo / np.pi
    shadow = np.where(facing > 0, blocked / np.maximum(facing, 1), 0.0)
    return DirectResult(radiance.astype(np.float32), shadow.astype(np.float32), facing.astype(np.int32), queries)
