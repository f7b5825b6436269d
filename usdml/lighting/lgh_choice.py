"""``--gi lgh``'s per-frame choice of hierarchy (``--lgh-split``) and blending radius (``--lgh-alpha``).

Two hierarchies can light a frame's VPLs: paper 004's one over all of them, or one per normal class on
one grid (:func:`usdml.lighting.lgh.build_lgh_split`). At the same α the split one is the more accurate
wherever a grid light would merge VPLs facing different ways (a ground and a wall), and it visits more
grid lights per pixel. Measured on the suite's tuning stages (docs/gi.md), neither wins at every cost:
at the α ten thousand VPLs afford a larger α of the one hierarchy erred as little as the split one for
the same visits, while at a hundred thousand the split one at the largest α the budget allowed erred
1.5-5 times less than the one hierarchy at its largest.

So ``--lgh-split auto`` (the default) lets the frame decide: each hierarchy gets the largest α of
:data:`usdml.lighting.lgh_lighting.AUTO_ALPHAS` its gather affords (:func:`auto_alpha`'s visit budget,
or the given ``--lgh-alpha``), the split one only when it fits that budget, and a pilot decides
between the two: both hierarchies' unshadowed irradiance at :data:`PILOT_POINTS` of the frame's points
against the VPLs' own unshadowed sum there (:func:`vpl_irradiance`, the cosine emitters brute force
gathers, by NumPy), the smaller relative RMSE winning. Shadows are left out on both sides: they are
drawn the same way from either hierarchy, and the hierarchy is what the two differ in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from usdml.lighting.lgh_lighting import AUTO_ALPHAS, AUTO_VISIT_FRACTION, LGHGather, alpha_within, lights_visited

#: the frame's points the pilot compares the hierarchies on (seeded): on the tuning stages the error of
#: 128 points was within a fifth of the whole image's for every hierarchy and α (docs/CHANGELOG.md); the pilot
#: compares two hierarchies on the same points, whose errors differed 1.5-5 times where it mattered
PILOT_POINTS = 64

#: the split hierarchy visited 1.4-2.5 times as many lights as the single one at α 1 on the tuning stages
#: (1.2-2.5 at α 1-4): where the single one at its smallest α already visits more than the budget over this, the split
#: one cannot fit it and is not built
SPLIT_VISIT_FACTOR = 1.4

#: VPLs per block of :func:`vpl_irradiance` (its arrays are points x this)
_BLOCK = 8192


@dataclass
class Choice:
    """What a frame's ``--gi lgh`` lights with."""

    split: str                  #: "none" (one hierarchy) or "normal" (one per normal class)
    alpha: float                #: the blending radius factor
    lgh: object                 #: the hierarchy (:class:`usdml.lighting.lgh.LGH`)
    #: per candidate ("none", "normal"): {"alpha", "visits", "within_budget", "pilot_rel_rmse"} as measured
    candidates: dict = field(default_factory=dict)


def vpl_irradiance(points: np.ndarray, normals: np.ndarray, position: np.ndarray, intensity: np.ndarray,
                   normal: np.ndarray, clamp_distance: float, meters_per_unit: float = 1.0) -> np.ndarray:
    """``(P, 3)`` float64 unshadowed irradiance at ``points`` (P, 3) with unit ``normals`` from every VPL as the
    LGH models it (``position``, ``intensity`` = Φ/4π, ``normal``: (N, 3)): Σ 4 I max(0, cos θ_l) max(0, cos θ_s)
    / max(d², d_c²) / metersPerUnit², d and the clamp d_c in scene units.

    By NumPy, block by block of VPLs, each term from products of (P, 3) and (3, B) matrices: with w = q − p,
    d² = |q|² + |p|² − 2 p·q, d cos θ_s = q·n_p − p·n_p and d cos θ_l = p·n_q − q·n_q (coordinates taken
    from the points' centre, in float64, so the expansion loses nothing a clamped d² would keep)."""
    centre = np.asarray(points, np.float64).reshape(-1, 3).mean(axis=0) if len(points) else np.zeros(3)
    p = np.asarray(points, np.float64).reshape(-1, 3) - centre
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    pp = (p * p).sum(1)[:, None]
    pn = (p * n).sum(1)[:, None]
    out = np.zeros((len(p), 3))
    clamp2 = float(clamp_distance) ** 2
    for a in range(0, len(position), _BLOCK):
        q = np.asarray(position[a:a + _BLOCK], np.float64) - centre
        nq = np.asarray(normal[a:a + _BLOCK], np.float64)
        d2 = np.maximum(pp + (q * q).sum(1)[None, :] - 2.0 * (p @ q.T), 0.0)       # (P, B)
        cos_s = np.maximum(n @ q.T - pn, 0.0)                                      # d cos θ_s
        cos_l = np.maximum(p @ nq.T - (q * nq).sum(1)[None, :], 0.0)               # d cos θ_l
        g = 4.0 * cos_s * cos_l / np.maximum(d2 * np.maximum(d2, clamp2), 1e-300)
        g[d2 <= 0.0] = 0.0
        out += g @ np.asarray(intensity[a:a + _BLOCK], np.float64)
    return out / float(meters_per_unit) ** 2


def choose(one, build_split, points: np.ndarray, normals: np.ndarray, sources: tuple, *, alpha: float = 0.0,
           split: str = "auto", s0: bool = True, clamp_distance: float, meters_per_unit: float = 1.0, seed: int = 0,
           device: str = "cpu", fraction: float = AUTO_VISIT_FRACTION) -> Choice:
    """The frame's hierarchy and α (module docstring).

    ``one``: the single hierarchy (or None when ``split`` is "normal"); ``build_split()`` makes the split one
    (called at most once, only when needed); ``points``, ``normals`` (P, 3): the frame's shading points;
    ``sources = (positions, intensities, normals)`` the VPLs; ``alpha`` 0 = automatic (else used as given);
    ``split``: "auto", "none" or "normal"; ``s0``: the gathers start from the VPLs (S0); ``clamp_distance``
    and ``meters_per_unit`` as the gathers'; ``seed``: the pilot's points.
    """
    n_vpls = len(sources[0])
    budget = fraction * max(n_vpls, 1)
    s0_positions = sources[0] if s0 else None
    alphas = np.asarray(AUTO_ALPHAS if alpha <= 0 else (alpha,), np.float64)
    candidates: dict = {}
    hierarchies: dict = {}

    def candidate(name: str, lgh) -> np.ndarray:
        visits = lights_visited(lgh, points, alphas, s0_positions)
        a, fits = alpha_within(visits, budget) if alpha <= 0 else (float(alpha), bool(visits[0] <= budget))
        candidates[name] = {"alpha": a, "visits": float(visits[list(alphas).index(a)]), "within_budget": fits}
        hierarchies[name] = lgh
        return visits

    want_split = split == "normal"
    if split in ("auto", "none"):
        visits = candidate("none", one)
        # auto: the split hierarchy only where it may fit the budget at the smallest alpha
        want_split = split == "auto" and visits[0] * SPLIT_VISIT_FACTOR <= budget
    if want_split:
        candidate("normal", build_split())
    if split != "auto":
        c = candidates[split]
        return Choice(split, c["alpha"], hierarchies[split], candidates)
    if "normal" not in candidates or not candidates["normal"]["within_budget"] or len(points) == 0:
        return Choice("none", candidates["none"]["alpha"], one, candidates)
    # both fit: the pilot decides
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(len(points), min(PILOT_POINTS, len(points)), replace=False))
    pts = np.ascontiguousarray(points[pick], np.float32)
    nrm = np.ascontiguousarray(normals[pick], np.float32)
    exact = vpl_irradiance(pts, nrm, *sources, clamp_distance, meters_per_unit)
    mean = float(exact.mean())
    for name, c in candidates.items():
        got = LGHGather(hierarchies[name], c["alpha"], 0, seed, meters_per_unit, clamp_distance, device,
                        s0=sources if s0 else None)(pts, nrm).irradiance.astype(np.float64)
        c["pilot_rel_rmse"] = float(np.sqrt(np.mean((got - exact) ** 2)) / mean) if mean > 0 else 0.0
    best = "normal" if candidates["normal"]["pilot_rel_rmse"] < candidates["none"]["pilot_rel_rmse"] else "none"
    return Choice(best, candidates[best]["alpha"], hierarchies[best], candidates)
