"""A dome light's specular reflection on preview surfaces, by sampling the BRDF's GGX lobes (no ``pxr`` here).

A dome stands in the frame as K distant lights (:mod:`usdml.lighting.dome`): right for the diffuse lobe, which
integrates the dome against a cosine, but a glossy or mirror lobe sees only those K directions, so a smooth
sphere shows K sparkles where Storm shows the environment. So a dome's light is split by lobe:

* the **diffuse** lobe (``E·ρ/π·kd``) from the K distant lights, as before (:func:`usdml.lighting.direct.shade_direct`
  with those lights marked ``diffuse_only``);
* the **specular and clearcoat** lobes (``L·ks·cos``) here: ``S`` directions per point drawn from the lobes
  themselves (GGX half vectors, α of the lobe; with a clearcoat each lobe half the time, weighted by the mixture
  pdf: the balance heuristic over the two), each a shadow ray toward the dome (``occluded`` with ``distant``) and
  the dome's radiance in that direction:

      L_s ≈ 1/S Σ L(ω_i)·V(ω_i)·ks(ω_i)·(n·ω_i) / p(ω_i),   p(ω) = Σ_lobes w_lobe D(h)(n·h) / (4 e·h)

  At roughness → 0 one sample is the mirror direction, exactly; rough lobes converge with S and with the
  frame's pixel samples. The samples are a randomly shifted rank-1 lattice per point (stratified), seeded
  from the frame's seed and the point's position bits: the same frame gives the same pixels.

The D and h of the pdf are computed exactly as :func:`usdml.kernels.brdf.brdf_terms` computes them (float32, h from
e + l), so ks/p cancels D even for the sharpest lobe.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from usdml.kernels.brdf import ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, EYE, brdf_terms, ggx
from usdml.scene import Dome
from usdml.scene.hashing import GOLDEN, fold_bits, unit

__all__ = ["DOME_SPECULAR_SAMPLES", "dome_specular"]

#: GGX samples per point and pass for a dome's specular lobes (a pass's pixels are also sampled by pixel samples)
DOME_SPECULAR_SAMPLES = 16
_GOLDEN = 0.6180339887498949


def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (K, 3) orthogonal to unit normals ``n`` (Duff et al.'s branchless basis)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] * n[:, 0] * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] * n[:, 1] * a, -n[:, 1]], axis=1)
    return t, s


def _shifts(points: np.ndarray, seed: int) -> np.ndarray:
    """(P, 3) uniform shifts per point from the seed and the bits of its position (deterministic)."""
    with np.errstate(over="ignore"):
        h = fold_bits(np.full(len(points), np.uint64(seed) * GOLDEN + np.uint64(0xD0E5), np.uint64), points)
        out = []
        for k in range(3):
            g = h * np.uint64(2 * k + 1) + np.uint64(k * 0x632BE59BD9B4E019)
            out.append(unit((g ^ (g >> np.uint64(31))) * np.uint64(0xD6E8FEB86659FD93)))
    return np.stack(out, axis=1)


def dome_specular(points: np.ndarray, normals: np.ndarray, geometric: np.ndarray | None, rows: np.ndarray,
                  domes: list[Dome], occluded: Callable[..., np.ndarray] | None, seed: int = 0,
                  samples: int = DOME_SPECULAR_SAMPLES) -> np.ndarray:
    """``(P, 3)`` float32 specular radiance of the ``domes`` at ``points`` with shading ``normals``, geometric
    normals ``geometric`` (None: the shading ones) and material ``rows`` (``kernels/brdf``); ``occluded`` a
    visibility backend's shadow query (None: unshadowed). Module doc."""
    n_p = len(points)
    out = np.zeros((n_p, 3), np.float64)
    rows = np.asarray(rows, np.float32)
    lit = [d for d in domes if np.any(np.asarray(d.radiance) != 0)]
    if not n_p or not lit or samples <= 0:
        return out.astype(np.float32)
    n = np.asarray(normals, np.float64)
    ng = n if geometric is None else np.asarray(geometric, np.float64)
    e = rows[:, EYE:EYE + 3].astype(np.float64)
    glossy = np.flatnonzero(((n * e).sum(1) > 0) & ((rows[:, 3:9] != 0).any(1) | (rows[:, CLEARCOAT] > 0)))
    if not len(glossy):
        return out.astype(np.float32)
    t_axis, s_axis = _frame(n[glossy])
    shift = _shifts(points[glossy], seed)
    coat = rows[glossy, CLEARCOAT] > 0
    for i in range(samples):
        u = (shift + np.array([(i + 0.5) / samples, (i * _GOLDEN) % 1.0, (i * _GOLDEN * _GOLDEN) % 1.0])) % 1.0
        use_coat = coat & (u[:, 2] < 0.5)
        alpha = np.where(use_coat, rows[glossy, CLEARCOAT_ALPHA], rows[glossy, ALPHA]).astype(np.float64)
        xi = np.minimum(u[:, 0], 1.0 - 1e-12)
        tan2 = alpha * alpha * xi / (1.0 - xi)
        cos_h = 1.0 / np.sqrt(1.0 + tan2)
        sin_h = np.sqrt(np.maximum(0.0, 1.0 - cos_h * cos_h))
        phi = 2.0 * np.pi * u[:, 1]
        h = (sin_h * np.cos(phi))[:, None] * t_axis + (sin_h * np.sin(phi))[:, None] * s_axis \
            + cos_h[:, None] * n[glossy]
        ee = e[glossy]
        e_h = (ee * h).sum(1)
        l = 2.0 * e_h[:, None] * h - ee
        l /= np.maximum(np.linalg.norm(l, axis=1, keepdims=True), 1e-300)
        ok = (e_h > 0) & ((n[glossy] * l).sum(1) > 0) & ((ng[glossy] * l).sum(1) > 0)
        k = np.flatnonzero(ok)
        if not len(k):
            continue
        pts, rr, nn, ll = glossy[k], rows[glossy[k]], n[glossy[k]].astype(np.float32), l[k].astype(np.float32)
        _kd, ks = brdf_terms(rr, nn, ll)
        # the pdf from the same float32 h, n·h and |n × h|² as brdf_terms: ks / pdf cancels D
        ef = rr[:, EYE:EYE + 3]
        hf = ef + ll
        hf /= np.maximum(np.sqrt((hf * hf).sum(1)), np.float32(1e-30))[:, None]
        n_h = np.maximum((nn * hf).sum(1), 0.0)
        s2 = (np.cross(nn, hf) ** 2).sum(1)
        e_hf = np.maximum((ef * hf).sum(1), np.float32(1e-30))
        w_coat = np.where(coat[k], 0.5, 0.0).astype(np.float32)
        pdf = ((1.0 - w_coat) * ggx(rr[:, ALPHA], n_h, s2)
               + w_coat * ggx(rr[:, CLEARCOAT_ALPHA], n_h, s2)) * n_h / (4.0 * e_hf)
        cos_l = np.maximum((nn * ll).sum(1), 0.0)
        weight = ks.astype(np.float64) * (cos_l / np.maximum(pdf, 1e-30)).astype(np.float64)[:, None]
        shadowed = None
        if occluded is not None and any(d.shadow for d in lit):
            shadowed = occluded(points[pts], l[k], normals=ng[pts], distant=np.ones(len(k), bool))
        for dome in lit:
            radiance = dome.radiance_at(l[k])
            if dome.shadow and shadowed is not None:
                radiance[shadowed] = 0.0
            out[pts] += weight * radiance      # each point once per sample: no repeated indices
    return (out / samples).astype(np.float32)
