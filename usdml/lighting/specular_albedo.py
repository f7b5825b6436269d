"""How much light a preview surface's specular lobes reflect in all, for indirect light (no ``pxr`` here).

usdml's indirect light (VPLs, :mod:`usdml.lighting.vpl`, gathered by ``--gi``) moves light between surfaces as if
they were diffuse. A metal has no diffuse reflectance, so with its diffuse reflectance alone a metal floor would
send no light on and receive none (``tools/glossy_gi.py`` measured it: the floor's indirect at 0.015 of a path
tracer's, the walls' at 0.84). So for indirect light a surface is given its whole reflectance, diffuse plus what
its specular and clearcoat lobes reflect over the hemisphere (the *directional albedo*):

    ρ_gi(e) = ρ·(1 − F0 − (F90 − F0)·C(n·e))
              + occlusion·( F0·A(n·e, α) + (F90 − F0)·B(n·e, α) + clearcoat·(R²·A(n·e, α_c) + (1 − R²)·B(n·e, α_c)) )

with ``A = ∫ D·V·(n·l) dω`` and ``B = ∫ D·V·(n·l)·(1 − e·h)⁵ dω`` the preview surface's own GGX and Smith–Schlick
terms (``kernels/brdf``), tabulated once over n·e and α by GGX importance sampling (Karis's split sum, without
the environment), and ``C`` the cosine-weighted mean of Schlick's ``(1 − e·h)⁵`` over the diffuse lobe (its
``kd = 1 − F`` averaged, as direct light applies it light by light). A VPL left on such a surface carries ρ_gi for the direction the light came from (by
reciprocity, the share of that light the surface reflects) and a receiver reflects ρ_gi/π of its gathered
irradiance toward the eye: the energy of a glossy bounce, spread as a diffuse one (no reflections of the scene
in a metal's indirect light). The measured effect is in docs/materials.md.
"""

from __future__ import annotations

import numpy as np

from usdml.kernels.brdf import ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0, EYE, F0, F90, OCCLUSION, \
    smith_visibility

__all__ = ["indirect_albedo", "specular_albedo", "split_sum_table"]

#: the table's cells: n·e in [0, 1] and α in [0, 1]
TABLE_SIZE = 32
#: GGX samples per cell (a stratified 2-D lattice)
TABLE_SAMPLES = 512
_TABLE: tuple[np.ndarray, np.ndarray] | None = None
_DIFFUSE: np.ndarray | None = None


def split_sum_table() -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` (TABLE_SIZE, TABLE_SIZE) float64 over (n·e, α) at cell centres (module doc), made once."""
    global _TABLE
    if _TABLE is None:
        size, k = TABLE_SIZE, TABLE_SAMPLES
        mu = (np.arange(size) + 0.5) / size
        alpha = np.maximum((np.arange(size) + 0.5) / size, 1e-3)
        i = np.arange(k)
        u1, u2 = (i + 0.5) / k, (i * 0.6180339887498949) % 1.0
        a_table = np.zeros((size, size))
        b_table = np.zeros((size, size))
        for col, a in enumerate(alpha):
            tan2 = a * a * u1 / (1.0 - u1)
            cos_h = 1.0 / np.sqrt(1.0 + tan2)
            sin_h = np.sqrt(1.0 - cos_h * cos_h)
            phi = 2.0 * np.pi * u2
            h = np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], axis=1)      # n = +z
            for row, m in enumerate(mu):
                e = np.array([np.sqrt(1.0 - m * m), 0.0, m])
                e_h = h @ e
                l_z = 2.0 * e_h * h[:, 2] - m
                ok = (e_h > 0) & (l_z > 0)
                # estimator of ∫ D V (n·l) dω with pdf D (n·h) / (4 e·h): V (n·l) 4 (e·h) / (n·h)
                w = np.where(ok, smith_visibility(a, m, np.maximum(l_z, 0.0)) * np.maximum(l_z, 0.0) * 4.0
                             * e_h / cos_h, 0.0)
                fres = (1.0 - np.clip(e_h, 0.0, 1.0)) ** 5
                a_table[row, col] = w.mean()
                b_table[row, col] = (w * fres).mean()
        _TABLE = (a_table, b_table)
    return _TABLE


def diffuse_fresnel_table() -> np.ndarray:
    """(TABLE_SIZE,) ``C(n·e) = 1/π ∫ (1 − e·h)⁵ (n·l) dω_l``: the cosine-weighted mean of Schlick's weight over
    the diffuse lobe's light directions, so that its kept share ``1 − F`` averages ``1 − F0 − (F90 − F0)·C``."""
    global _DIFFUSE
    if _DIFFUSE is None:
        size, k = TABLE_SIZE, TABLE_SAMPLES
        i = np.arange(k)
        u1, u2 = (i + 0.5) / k, (i * 0.6180339887498949) % 1.0
        r, phi = np.sqrt(u1), 2.0 * np.pi * u2          # cosine-distributed l about n = +z
        l = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], axis=1)
        out = np.zeros(size)
        for row, m in enumerate((np.arange(size) + 0.5) / size):
            e = np.array([np.sqrt(1.0 - m * m), 0.0, m])
            h = l + e
            h /= np.linalg.norm(h, axis=1, keepdims=True)
            out[row] = ((1.0 - np.clip(h @ e, 0.0, 1.0)) ** 5).mean()
        _DIFFUSE = out
    return _DIFFUSE


def indirect_albedo(albedo: np.ndarray, rows: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(K, 3) float32 reflectance a surface bounces indirect light with: the diffuse reflectance ``albedo`` times
    its lobe's mean kept share ``1 − F`` over the cosine lobe (as direct light applies ``kd = 1 − F`` per light)
    plus :func:`specular_albedo`; ``rows``' EYE the direction of interest (the eye, or where the light came from)."""
    rows = np.asarray(rows, np.float64)
    mu = np.clip((rows[:, EYE:EYE + 3] * np.asarray(normals, np.float64)).sum(1), 0.0, 1.0)
    table = diffuse_fresnel_table()
    c = np.interp(mu, (np.arange(TABLE_SIZE) + 0.5) / TABLE_SIZE, table)
    f0, f90 = rows[:, F0:F0 + 3], rows[:, F90:F90 + 3]
    kept = np.clip(1.0 - f0 - (f90 - f0) * c[:, None], 0.0, 1.0)
    return (np.asarray(albedo, np.float64) * kept + specular_albedo(rows, normals)).astype(np.float32)


def _lookup(table: np.ndarray, mu: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Bilinear lookup at cell centres, clamped at the edges."""
    size = table.shape[0]
    x = np.clip(mu * size - 0.5, 0.0, size - 1.0)
    y = np.clip(alpha * size - 0.5, 0.0, size - 1.0)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, size - 1), np.minimum(y0 + 1, size - 1)
    fx, fy = x - x0, y - y0
    return (table[x0, y0] * (1 - fx) * (1 - fy) + table[x1, y0] * fx * (1 - fy)
            + table[x0, y1] * (1 - fx) * fy + table[x1, y1] * fx * fy)


def specular_albedo(rows: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(K, 3) float32 share of light the specular and clearcoat lobes of material ``rows`` (``kernels/brdf``,
    their EYE the direction of interest) reflect over the hemisphere at unit ``normals`` (K, 3)."""
    rows = np.asarray(rows, np.float64)
    a_table, b_table = split_sum_table()
    mu = np.clip((rows[:, EYE:EYE + 3] * np.asarray(normals, np.float64)).sum(1), 0.0, 1.0)
    f0, f90 = rows[:, F0:F0 + 3], rows[:, F90:F90 + 3]
    a, b = _lookup(a_table, mu, rows[:, ALPHA]), _lookup(b_table, mu, rows[:, ALPHA])
    out = f0 * a[:, None] + (f90 - f0) * b[:, None]
    coat = rows[:, CLEARCOAT]
    if coat.any():
        ac, bc = _lookup(a_table, mu, rows[:, CLEARCOAT_ALPHA]), _lookup(b_table, mu, rows[:, CLEARCOAT_ALPHA])
        cf0 = rows[:, CLEARCOAT_F0]
        out += (coat * (cf0 * ac + (1.0 - cf0) * bc))[:, None]
    out *= np.where(mu > 0, rows[:, OCCLUSION], 0.0)[:, None]
    return out.astype(np.float32)
