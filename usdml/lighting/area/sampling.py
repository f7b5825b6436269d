"""Points on lights with area, K per shading point and light: stratified, seeded, and decorrelated between shading
points without depending on how the frame is cut into blocks or threads.

Each light's K points come from one 2D point set, the Fibonacci lattice ``((k + ½) / K, frac(k / φ))`` (stratified
in both dimensions for any K), shifted modulo 1 by a Cranley–Patterson offset of its own per (shading point,
light): two :func:`usdml.scene.hashing.unit` numbers keyed by the seed, the shading point's float32 position bits
and the light's (so a light keeps its offsets in any subset of the frame's lights). The unit square is then mapped
onto the shape, and each sample carries ``emit``, its share of the light's ``intensity`` (radiant intensity in
nit·m², or a distant light's irradiance) at the shading point before the receiver's cosine and the shaping cone, so
that ``E ≈ Σ_k emit_k · cos θ_s,k · S_k · V_k · I``:

* disk, mesh triangle (one-sided, sampled uniformly by area ``A``; ``I = L·A``):
  ``emit = max(0, cos θ_l) / (K d²)``, d in metres, θ_l between the light's normal and the point;
* rect (uniform in the solid angle Ω it covers, :func:`_rect`; by area as a disk where Ω is tiny):
  ``emit = Ω / (A K)``, none behind it;
* cylinder (sampled over the half of its side that faces the point, where all of its visible side lies: along
  it uniformly in the angle θ the length subtends from the point, ``t = t_p + h tan θ`` (h the point's distance to
  the axis, t_p its place along it), by ``p(φ) = cos φ / 2`` around it, φ from the direction to the point;
  ``I⊥ = L·2r·length``): ``emit = s · max(0, n_x·(P − x)/d) / (cos φ · K d²)`` with ``s = Δθ (h² + (t − t_p)²) /
  (h · length)`` the uniform density over this one, so the 1/d² along it cancels, and ``sin θ_c / (K d²)`` far
  away; with radius 0 (``treatAsLine``) the line: ``emit = s · sin θ_c / (K d²)``;
* sphere (uniform in the solid angle ``Ω = 2π(1 − cos θ_max)`` it covers seen from the point, the shadow ray to the
  nearer intersection; ``I = L·π r²``): ``emit = Ω / (π r² K)``, no distance: no point-light blow-up at close range;
* distant light with angle ``2α`` (uniform in the cone of directions; ``E₀ = L·π sin²α``):
  ``emit = 2 / ((1 + cos α) K)``.

Each is the point evaluation of :mod:`usdml.lighting.direct` at the sampled point (or, for spheres and distant
lights, tends to it as the light shrinks), so far from a light the mean of its samples is today's point light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdml.scene import Lights, LightType
from usdml.scene.hashing import GOLDEN, fold_bits, mix, unit

__all__ = ["AreaSamples", "lattice", "sample_lights", "sample_pairs", "sampled"]

#: 1/φ, the Fibonacci lattice's second coordinate step
INV_PHI = 0.6180339887498949
#: hash keys of the two halves of a (shading point, light) key
_POINT_KEY = np.uint64(0xA5A5_1F2E_3D4C_5B6A)
_LIGHT_KEY = np.uint64(0x5851_F42D_4C95_7F2D)


def sampled(lights: Lights) -> np.ndarray:
    """``(N,) bool``: the lights whose shadow rays go to sampled points (module doc); points, spheres of radius 0
    (``treatAsPoint`` makes them points already), zero-sized shapes and distant lights of angle 0 stay points."""
    t = np.asarray(lights.type)
    radius, width, height = (np.asarray(a, np.float64) for a in (lights.radius, lights.width, lights.height))
    xf = np.asarray(lights.xform, np.float64).reshape(-1, 4, 4)
    tri_area = np.linalg.norm(np.cross(xf[:, :3, 0], xf[:, :3, 1]), axis=1)
    return (((t == LightType.SPHERE) & (radius > 0)) | ((t == LightType.DISK) & (radius > 0))
            | ((t == LightType.RECT) & (width > 0) & (height > 0)) | ((t == LightType.CYLINDER) & (width > 0))
            | ((t == LightType.TRIANGLE) & (tri_area > 0))
            | ((t == LightType.DISTANT) & (np.asarray(lights.angle, np.float64) > 0)))


def lattice(k: int) -> np.ndarray:
    """``(k, 2) float64`` the Fibonacci lattice in the unit square (module doc)."""
    i = np.arange(k, dtype=np.float64)
    return np.stack([(i + 0.5) / k, np.mod(i * INV_PHI, 1.0)], axis=1)


def shifts(points: np.ndarray, positions: np.ndarray, seed: int, pairs: bool = False) -> np.ndarray:
    """``(P, L, 2) float64`` Cranley–Patterson offsets in [0, 1)² per (shading point, light), keyed by ``seed``
    and the float32 bits of ``points`` (P, 3) and of the lights' ``positions`` (L, 3); ``pairs``: ``(N, 2)`` for
    point i with light i (P = L = N)."""
    hp = fold_bits(np.full(len(points), mix(np.uint64(seed) ^ _POINT_KEY)), points)
    hl = fold_bits(np.full(len(positions), _LIGHT_KEY), positions)
    h = mix(hp ^ hl) if pairs else mix(hp[:, None] ^ hl[None, :])
    return np.stack([unit(h.ravel()), unit(mix(h.ravel() ^ GOLDEN))], axis=1).reshape(h.shape + (2,))


@dataclass
class AreaSamples:
    """K samples on each of L lights from each of P shading points."""

    targets: np.ndarray     #: (P, L, K, 3) float64 world points on the lights, or unit directions (distant)
    directions: np.ndarray  #: (P, L, K, 3) float64 unit directions from the shading point toward the samples
    emit: np.ndarray        #: (P, L, K) float64 each sample's share of its light's intensity (module doc)
    distant: np.ndarray     #: (L,) bool the lights whose targets are directions


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing unit ``n`` (..., 3) to an orthonormal frame (Duff et al. 2017, branchless)."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    t2 = np.stack([b, sign + y * y * a, -y], axis=-1)
    return t1, t2


def _falloff(vec: np.ndarray, inv_m2: float, min_d2: float):
    """Unit directions, distances and ``1 / d²`` in metres (d² clamped at ``min_d2`` scene units²) of ``vec``."""
    d2 = np.einsum("...i,...i->...", vec, vec)
    d = np.sqrt(d2)
    return vec / np.where(d > 0, d, 1.0)[..., None], inv_m2 / np.maximum(d2, min_d2)


def _surface(p, x, normal, inv_m2, min_d2, k):
    """Directions and ``emit`` of one-sided area samples ``x`` (P, L, K, 3) with emission ``normal`` (L, 3)."""
    w, fall = _falloff(x - p, inv_m2, min_d2)
    cos_l = -np.einsum("plki,li->plk", w, normal)
    return w, np.maximum(cos_l, 0.0) * fall / k


def _concentric(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley and Chiu's concentric map of the unit square onto the unit disk: ``(x, y)``."""
    a, b = 2.0 * u - 1.0, 2.0 * v - 1.0
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    safe_a, safe_b = np.where(a == 0, 1.0, a), np.where(b == 0, 1.0, b)
    phi = np.where(first, (np.pi / 4) * b / safe_a, np.pi / 2 - (np.pi / 4) * a / safe_b)
    return r * np.cos(phi), r * np.sin(phi)


#: below this solid angle (sr) a rect is sampled by area: the spherical rectangle's angles cancel in float64
SOLID_ANGLE_MIN = 1e-5


def _rect(p, c, ex, ey, normal, u, v, inv_m2, min_d2, k):
    """Rect samples ``(x, w, emit)``: uniform in the solid angle the rect covers seen from ``p`` (Ureña, Fajardo and
    King 2013, "An area-preserving parametrization for spherical rectangles"), ``emit = Ω / (A K)`` (A in m²), or
    uniform by area (:func:`_surface`) where Ω < :data:`SOLID_ANGLE_MIN`; none behind the emitting side."""
    xl, yl = np.linalg.norm(ex, axis=1), np.linalg.norm(ey, axis=1)
    xa, ya = ex / np.maximum(xl, 1e-300)[:, None], ey / np.maximum(yl, 1e-300)[:, None]
    za = np.cross(xa, ya)
    corner = c - 0.5 * (ex + ey)[None, :, None, :]                          # (1, L, 1, 3)
    d = corner - p                                                          # (P, L, 1, 3)
    z0 = np.einsum("plki,li->plk", d, za)
    flip = z0 > 0
    z0 = np.where(flip, -z0, z0)
    zs = np.where(flip[..., None], -za[None, :, None, :], za[None, :, None, :])
    x0, y0 = np.einsum("plki,li->plk", d, xa), np.einsum("plki,li->plk", d, ya)
    x1, y1 = x0 + xl[None, :, None], y0 + yl[None, :, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        n0 = np.stack([np.zeros_like(z0), z0, -y0], -1) / np.sqrt(z0 * z0 + y0 * y0)[..., None]
        n1 = np.stack([-z0, np.zeros_like(z0), x1], -1) / np.sqrt(z0 * z0 + x1 * x1)[..., None]
        n2 = np.stack([np.zeros_like(z0), -z0, y1], -1) / np.sqrt(z0 * z0 + y1 * y1)[..., None]
        n3 = np.stack([z0, np.zeros_like(z0), -x0], -1) / np.sqrt(z0 * z0 + x0 * x0)[..., None]

        def angle(a, b):
            return np.arccos(np.clip(-np.einsum("...i,...i->...", a, b), -1.0, 1.0))

        g0, g1, g2, g3 = angle(n0, n1), angle(n1, n2), angle(n2, n3), angle(n3, n0)
        b0, b1 = n0[..., 2], n2[..., 2]
        kk = 2 * np.pi - g2 - g3
        omega = g0 + g1 - kk
        au = u * omega + kk
        fu = (np.cos(au) * b0 - b1) / np.sin(au)
        cu = np.clip(np.copysign(1.0, fu) / np.sqrt(fu * fu + b0 * b0), -1.0, 1.0)
        xu = np.clip(-(cu * z0) / np.sqrt(np.maximum(1.0 - cu * cu, 1e-300)), x0, x1)
        dd = np.sqrt(xu * xu + z0 * z0)
        h0, h1 = y0 / np.sqrt(dd * dd + y0 * y0), y1 / np.sqrt(dd * dd + y1 * y1)
        hv = h0 + v * (h1 - h0)
        yv = np.where(hv * hv < 1 - 1e-12, hv * dd / np.sqrt(np.maximum(1.0 - hv * hv, 1e-300)), y1)
    solid = np.isfinite(omega) & (omega > SOLID_ANGLE_MIN) & np.isfinite(xu) & np.isfinite(yv)
    # in the frame (x, y, z) at p the rect's corner is (x0, y0, z0): the sample is p + xu·x + yv·y + z0·z
    offset = (np.nan_to_num(xu)[..., None] * xa[None, :, None, :] + np.nan_to_num(yv)[..., None] * ya[None, :, None, :]
              + z0[..., None] * zs)
    w, _ = _falloff(offset, inv_m2, min_d2)
    front = np.einsum("plki,li->plk", p - c, normal) > 0
    e = np.where(front, np.nan_to_num(omega), 0.0) * (inv_m2 / k) / (xl * yl)[None, :, None]
    x = p + offset
    if not solid.all():         # far off (or degenerate): by area
        x_a = c + (u - 0.5)[..., None] * ex[None, :, None, :] + (v - 0.5)[..., None] * ey[None, :, None, :]
        w_a, e_a = _surface(p, x_a, normal, inv_m2, min_d2, k)
        x, w, e = (np.where(solid[..., None], x, x_a), np.where(solid[..., None], w, w_a), np.where(solid, e, e_a))
    return x, w, e


def sample_lights(points: np.ndarray, lights: Lights, k: int, seed: int, meters_per_unit: float = 1.0,
                  min_distance: float = 0.0) -> AreaSamples:
    """``k`` samples on each of ``lights`` (all of them :func:`sampled`) seen from ``points`` (P, 3) world units
    (module doc); ``min_distance`` clamps the falloff's distance (scene units) as
    :class:`usdml.scene.light_table.LightTable` does."""
    uv = np.mod(lattice(k)[None, None] + shifts(points, lights.position, seed)[:, :, None, :], 1.0)
    return _samples(np.asarray(points, np.float64).reshape(-1, 1, 1, 3), uv, lights, k, meters_per_unit,
                    min_distance)


def sample_pairs(points: np.ndarray, lights: Lights, seed: int, rank: np.ndarray, count: np.ndarray,
                 meters_per_unit: float = 1.0) -> AreaSamples:
    """One sample on light i seen from point i (``points`` (N, 3), ``lights`` N entries, all :func:`sampled`): the
    ``rank[i]``-th point of the lattice of ``count[i]`` (the rays a point sends to one light stratified over it,
    shifted by the point's and the light's offset): arrays ``(N, 1, ...)``, ``distant`` (N,)."""
    rank, count = np.asarray(rank, np.float64), np.maximum(np.asarray(count, np.float64), 1.0)
    base = np.stack([(rank + 0.5) / count, np.mod(rank * INV_PHI, 1.0)], axis=1)
    uv = np.mod(base + shifts(points, lights.position, seed, pairs=True), 1.0)[:, None, :]
    s = _samples(np.asarray(points, np.float64).reshape(1, -1, 1, 3), uv[None], lights, 1, meters_per_unit, 0.0)
    return AreaSamples(s.targets[0], s.directions[0], s.emit[0], s.distant)


def _samples(p_all: np.ndarray, uv: np.ndarray, lights: Lights, k: int, meters_per_unit: float,
             min_distance: float) -> AreaSamples:
    """The samples of :func:`sample_lights` from points ``p`` (P, 1, 1, 3) against every light, or (1, L, 1, 3)
    one point per light, at the unit-square points ``uv`` (P or 1, L, K, 2)."""
    n_p, n_l = p_all.shape[0], len(lights)
    targets = np.zeros((n_p, n_l, k, 3))
    directions = np.zeros((n_p, n_l, k, 3))
    emit = np.zeros((n_p, n_l, k))
    inv_m2, min_d2 = 1.0 / meters_per_unit ** 2, max(min_distance, 1e-12) ** 2
    t = np.asarray(lights.type)
    xf = np.asarray(lights.xform, np.float64).reshape(-1, 4, 4)
    centre = np.asarray(lights.position, np.float64)
    for kind in np.unique(t):
        cols = np.flatnonzero(t == kind)
        p = p_all if p_all.shape[1] == 1 else p_all[:, cols]      # one point per light: the kind's points
        u, v = uv[:, cols][..., 0], uv[:, cols][..., 1]
        c = centre[cols][None, :, None, :]
        m = xf[cols]
        if kind == LightType.RECT:
            sx, sy = np.linalg.norm(m[:, :3, 0], axis=1), np.linalg.norm(m[:, :3, 1], axis=1)
            ex = m[:, :3, 0] / np.where(sx > 0, sx, 1.0)[:, None] * lights.width[cols][:, None]
            ey = m[:, :3, 1] / np.where(sy > 0, sy, 1.0)[:, None] * lights.height[cols][:, None]
            x, w, e = _rect(p, c, ex, ey, np.asarray(lights.axis, np.float64)[cols], u, v, inv_m2, min_d2, k)
        elif kind == LightType.DISK:
            sx, sy = np.linalg.norm(m[:, :3, 0], axis=1), np.linalg.norm(m[:, :3, 1], axis=1)
            # an ellipse of semi-axes R·sx, R·sy, where lights.radius holds R·sqrt(sx·sy)
            scale = lights.radius[cols] / np.sqrt(np.maximum(sx * sy, 1e-300))
            ex, ey = m[:, :3, 0] * scale[:, None], m[:, :3, 1] * scale[:, None]
            a, b = _concentric(u, v)
            x = c + a[..., None] * ex[None, :, None, :] + b[..., None] * ey[None, :, None, :]
            w, e = _surface(p, x, np.asarray(lights.axis, np.float64)[cols], inv_m2, min_d2, k)
        elif kind == LightType.TRIANGLE:
            su = np.sqrt(u)
            x = (m[None, :, None, :3, 3] + (su * (1.0 - v))[..., None] * m[None, :, None, :3, 0]
                 + (su * v)[..., None] * m[None, :, None, :3, 1])
            w, e = _surface(p, x, np.asarray(lights.axis, np.float64)[cols], inv_m2, min_d2, k)
        elif kind == LightType.CYLINDER:
            axis = _unit(m[:, :3, 0])[None, :, None, :]
            length = np.asarray(lights.width, np.float64)[cols][None, :, None]
            radius = np.asarray(lights.radius, np.float64)[cols][None, :, None]
            q = p - c
            t_p = np.einsum("plki,plki->plk", q, axis)
            perp = q - t_p[..., None] * axis
            # along the axis by the angle the length subtends from the point (uniform in θ, t = t_p + h tan θ):
            # the 1/d² along it cancels; ``stretch`` is the uniform density's ratio to it
            h = np.maximum(np.linalg.norm(perp, axis=-1), 1e-12 * np.maximum(length, 1e-300))
            lo, hi = np.arctan((-length / 2 - t_p) / h), np.arctan((length / 2 - t_p) / h)
            at = t_p + h * np.tan(lo + u * (hi - lo))
            stretch = (hi - lo) * (h * h + (at - t_p) ** 2) / (h * np.maximum(length, 1e-300))
            along = np.clip(at, -length / 2, length / 2)[..., None] * axis
            fallback = np.broadcast_to(_unit(m[:, :3, 1])[None, :, None, :], perp.shape)
            n0 = np.where((np.linalg.norm(perp, axis=-1) > 0)[..., None], _unit(perp), fallback)
            phi = np.arcsin(2.0 * v - 1.0)              # p(φ) = cos φ / 2 about the direction to the point
            nx = np.cos(phi)[..., None] * n0 + np.sin(phi)[..., None] * np.cross(axis, n0)
            x = c + along + radius[..., None] * nx
            w, fall = _falloff(x - p, inv_m2, min_d2)
            side = np.maximum(-np.einsum("plki,plki->plk", nx, w), 0.0) / np.maximum(np.cos(phi), 1e-12)
            line = np.sqrt(np.maximum(1.0 - np.einsum("plki,plki->plk", w, axis) ** 2, 0.0))
            e = np.where(radius > 0, side, line) * stretch * fall / k
        elif kind == LightType.SPHERE:
            r = np.asarray(lights.radius, np.float64)[cols][None, :, None]
            to = c - p
            dc = np.linalg.norm(to, axis=-1)
            axis = to / np.where(dc > 0, dc, 1.0)[..., None]
            sin2 = np.minimum((r / np.maximum(dc, 1e-300)) ** 2, 1.0)
            one_minus = sin2 / (1.0 + np.sqrt(1.0 - sin2))        # 1 − cos θ_max without cancellation
            cos_t = 1.0 - u * one_minus
            sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
            t1, t2 = _frame(axis)
            phi = 2 * np.pi * v
            w = ((sin_t * np.cos(phi))[..., None] * t1 + (sin_t * np.sin(phi))[..., None] * t2
                 + cos_t[..., None] * axis)
            b = dc * cos_t                                           # the nearer intersection along w
            hit = b - np.sqrt(np.maximum(r * r - (dc * dc - b * b), 0.0))
            x = p + np.maximum(hit, 0.0)[..., None] * w
            omega = 2 * np.pi * one_minus
            e = np.broadcast_to(omega * inv_m2 / (np.pi * r * r) / k, u.shape)
        elif kind == LightType.DISTANT:
            half = np.radians(np.asarray(lights.angle, np.float64)[cols]) / 2
            cos_a = np.cos(half)[None, :, None]
            cos_t = 1.0 - u * (1.0 - cos_a)
            sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
            toward = -np.asarray(lights.axis, np.float64)[cols]
            t1, t2 = _frame(toward)
            phi = 2 * np.pi * v
            w = ((sin_t * np.cos(phi))[..., None] * t1[None, :, None, :]
                 + (sin_t * np.sin(phi))[..., None] * t2[None, :, None, :] + cos_t[..., None] * toward[None, :, None, :])
            x = w
            e = np.broadcast_to(2.0 / (1.0 + cos_a) / k, u.shape)
        else:
            raise ValueError(f"{LightType(int(kind)).name} lights have no area to sample")
        targets[:, cols], directions[:, cols], emit[:, cols] = x, w, e
    return AreaSamples(targets, directions, emit, t == LightType.DISTANT)
