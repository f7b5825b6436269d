"""The UsdPreviewSurface BRDF of one light at a point, as usdImaging's ``previewSurface.glslfx`` evaluates
it (``evaluateLight``), without its epsilons: the reference every shading path (NumPy, the compiled
kernels' ``brdf.h``, Warp) matches. Its folder holds the compiled sums of both lobes over a point's lights
(``brdfsum.c``, wrapped by :mod:`usdml.lighting.brdf_sums`).

A point's material is one float32 row of :data:`WIDTH` values (:data:`LAYOUT`); with ``e`` the unit
direction to the eye, ``n`` the shading normal, ``l`` the unit direction to the light, ``h = (e + l)/|e + l|``
and ``fresnel = (1 − e·h)⁵`` (Schlick):

* ``F = F0 + (F90 − F0)·fresnel`` (rgb): the specular lobe's Fresnel;
* ``D(α) = α² / (π ((n·h)²(α² − 1) + 1)²)`` (GGX), ``α = roughness²``;
* ``V(α) = G / (4 (n·l)(n·e)) = 1 / (4 ((n·e)(1 − k) + k)((n·l)(1 − k) + k))``, ``k = α/2`` (Smith–Schlick G
  divided by the microfacet denominator, the n·l and n·e factors cancelled: no epsilon needed);
* ``kd = 1 − F``: what the diffuse lobe keeps (Storm's "glazing angles have less diffuse");
* ``ks = occlusion · (F·D(α)·V(α) + clearcoat·(cF0 + (1 − cF0)·fresnel)·D(αc)·V(αc))``.

A light's contribution is ``E·(ρ/π·kd + ks)`` where ``E`` is its irradiance ``I·cos θ/d²`` (n·l included)
and ``ρ`` the *effective* diffuse reflectance ``diffuseColor·(1 − metallic)·opacity·occlusion`` (folded in
by the caller, as the Lambertian albedo was). Shading paths therefore sum two rgb terms over visible
lights, ``Σ E·kd`` and ``Σ E·ks``, and return ``ρ/π·ΣE·kd + ΣE·ks``; without a material ``kd = 1``, ``ks = 0``
(the Lambertian path, unchanged). Where ``n·e ≤ 0`` (an interpolated normal turned from the eye) the
specular lobes are 0, as Storm's ``max(0, n·e)`` makes them.

The row's parameters (F0, F90 per workflow, α = max(roughness, 0.001)²) are worked out once per point by
:meth:`usdml.scene.shading.MeshShading.at`.
"""

from __future__ import annotations

import numpy as np

#: floats per material row
WIDTH = 16
#: column of each parameter in a row (E: unit direction to the eye)
EYE, F0, F90, ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0, OCCLUSION = 0, 3, 6, 9, 10, 11, 12, 13
LAYOUT = {"eye": (0, 3), "f0": (3, 6), "f90": (6, 9), "alpha": 9, "clearcoat": 10, "clearcoat_alpha": 11,
          "clearcoat_f0": 12, "occlusion": 13}


def ggx(alpha: np.ndarray, n_h: np.ndarray, s2: np.ndarray | None = None) -> np.ndarray:
    """GGX normal distribution D; ``s2`` = |n × h|² = 1 − (n·h)², given without its cancellation near n·h = 1 (where
    a sharp lobe peaks: float32's 1 − (n·h)² alone is off by ~1e-7, several % of α² at roughness 0.05)."""
    a2 = alpha * alpha
    c2 = n_h * n_h
    if s2 is None:
        s2 = np.maximum(1.0 - c2, 0.0)
    d = np.maximum(s2 + c2 * a2, 1e-18)     # (n·h)²(α² − 1) + 1; no 0/0 at α = 0
    return a2 / (np.pi * d * d)


def smith_visibility(alpha: np.ndarray, n_e: np.ndarray, n_l: np.ndarray) -> np.ndarray:
    """``G / (4 (n·l)(n·e))`` with Smith–Schlick G, k = α/2."""
    k = alpha * 0.5
    return 1.0 / (4.0 * (n_e * (1.0 - k) + k) * (n_l * (1.0 - k) + k))


def brdf_terms(rows: np.ndarray, n: np.ndarray, l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(kd, ks)`` ``(N, 3)`` float32 of material ``rows`` (N, WIDTH) at unit shading normals ``n`` (N, 3) toward
    unit light directions ``l`` (N, 3), as the module docstring defines them (NumPy, float32)."""
    rows = np.asarray(rows, np.float32)
    n = np.asarray(n, np.float32)
    l = np.asarray(l, np.float32)
    e = rows[:, 0:3]
    h = e + l
    h = h / np.maximum(np.sqrt((h * h).sum(1)), np.float32(1e-30))[:, None]
    n_l = np.maximum((n * l).sum(1), 0.0)
    n_e = (n * e).sum(1)
    n_h = np.maximum((n * h).sum(1), 0.0)
    e_h = np.maximum((e * h).sum(1), 0.0)
    s2 = (np.cross(n, h) ** 2).sum(1)
    fresnel = (1.0 - e_h) ** 5
    f = rows[:, 3:6] + (rows[:, 6:9] - rows[:, 3:6]) * fresnel[:, None]
    kd = 1.0 - f
    alpha, cc, cc_alpha, cc_f0, occ = (rows[:, c] for c in (ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0,
                                                            OCCLUSION))
    front = n_e > 0
    n_e = np.maximum(n_e, 0.0)
    spec = ggx(alpha, n_h, s2) * smith_visibility(alpha, n_e, n_l)
    coat = cc * (cc_f0 + (1.0 - cc_f0) * fresnel) * ggx(cc_alpha, n_h, s2) * smith_visibility(cc_alpha, n_e, n_l)
    ks = (f * spec[:, None] + coat[:, None]) * np.where(front, occ, 0.0)[:, None]
    return kd.astype(np.float32), ks.astype(np.float32)
