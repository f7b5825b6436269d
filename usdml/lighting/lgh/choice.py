"""``--gi lgh``'s per-frame choice of hierarchy (``--lgh-split``) and blending radius (``--lgh-alpha``).

Two hierarchies can light a frame's VPLs: paper 004's one over all of them, or one per normal class on
one grid (:func:`usdml.lighting.lgh.build.build_lgh_split`). At the same α the split one is the more accurate
wherever a grid light would merge VPLs facing different ways (a ground and a wall), and it visits more
grid lights per pixel.

The α (``--lgh-alpha`` 0, automatic) is the smallest of :data:`PILOT_ALPHAS` within the visit budget
(:data:`usdml.lighting.lgh.shading.AUTO_VISIT_FRACTION` of the VPLs per point) whose unshadowed irradiance
at :data:`PILOT_POINTS` of the frame's points errs at most :data:`PILOT_TARGET` (relative RMSE) against the
VPLs' own unshadowed sum there (:func:`vpl_irradiance`, the cosine emitters brute force gathers). The
gather's cost grows with α (lights visited per point) and its error falls, so this is the cheapest α the
pilot finds close enough, instead of the largest the budget allows.

``--lgh-split auto`` (the default) tries the split hierarchy first, wherever any of its α fits the budget,
and the single one only where the split one has no α within target; where neither has, the (hierarchy, α)
that erred least on the pilot. The split one is built only where the single one's smallest α leaves room
for it. Why the split one first, and not the one whose unshadowed light is closer (the rule before): on
the suite's tuning stages at 100,000 VPLs the single hierarchy's whole-image error with its shadows was up
to 2.85 times its unshadowed error (its member draws mix a grid light's ground and wall VPLs), the split
one's 0.9-1.5 times at α up to 2.5, so an unshadowed comparison picked the single one where it was the
worse (docs/gi.md, "Which hierarchy, and which α").

The hierarchies' limit, every VPL its own light (``--lgh-split each``, :mod:`usdml.lighting.lgh.each`), has no
error of its own and costs :func:`each_visit_cost` of a visit per VPL. Where ``choose`` may take it (``each``:
an automatic α and split, a CPU, S0), the visit budget becomes that cost where it is less, and the limit is taken
wherever the split hierarchy has no α within the budget and the pilot's target (no pilot where none fits); the
single hierarchy is not tried then, as its pilot does not bound its error with shadows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from usdml.parallel import cpu_workers, run_parallel, spans
from usdml.lighting.lgh.shading import AUTO_VISIT_FRACTION, LGHGather, lights_visited

#: the frame's points the pilot measures each α on (seeded). On the tuning stages two disjoint sets of 64 points
#: put the split hierarchy's error at 3.4 % and 8.8 % where 1,024 points put it at 9.8 % (open_1024_s0, α 1.5):
#: 64 points could not tell 5 % from 10 %, 256 cost 0.04 s against 100,000 VPLs (kernels/lgh/lghq.c)
PILOT_POINTS = 256

#: the pilot's unshadowed relative RMSE the α is chosen for: the smallest α of :data:`PILOT_ALPHAS` within the
#: visit budget whose pilot error is at most this. Tuned on the suite's tuning stages at 100,000 VPLs
#: (docs/gi.md, "Which hierarchy, and which α"): the split hierarchy's whole-image error with its shadows
#: was 0.9-1.5 times its unshadowed error at α up to 2.5, so this leaves room under issue 37's 10 % target
PILOT_TARGET = 0.05

#: the blending radius factors the pilot tries, smallest first: paper 004's 1 up to 4 (where the error had
#: stopped falling) in steps of 0.5, halved below 2 (the split hierarchy's error fell from 12-16 % to 4-6 %
#: between α 1 and 2 on the tuning stages)
PILOT_ALPHAS = (1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 3.5, 4.0)

#: the split hierarchy visited 1.4-2.5 times as many lights as the single one at α 1 on the tuning stages
#: (1.2-2.5 at α 1-4): where the single one at its smallest α already visits more than the budget over this, the split
#: one cannot fit it and is not built
SPLIT_VISIT_FACTOR = 1.4

#: what a point's exact sum over every VPL (``--lgh-split each``, :mod:`usdml.lighting.lgh.each`) costs, in visits of
#: the compiled gather per VPL, by the lanes ``lghq_each`` runs on (:func:`usdml.lighting.lgh.native.each_lanes`;
#: the gather's own are AVX2's on both): a VPL's term against a light visited by ``lghq_gather`` (24-36 ns), on the
#: same 2-core CPU (docs/CHANGELOG.md, "Every VPL its own light"): 0.27-0.39 ns with AVX-512; 1.6-1.7 times that
#: with AVX2 and 3.2 times with SSE (one thread, 100,000 lights); 0: a platform without the clones, taken as AVX2
EACH_VISIT_COSTS = {16: 0.015, 8: 0.025, 4: 0.05, 0: 0.025}


def each_visit_cost() -> float:
    """:data:`EACH_VISIT_COSTS` for this CPU (inf where nothing was compiled: the NumPy sum is no cheaper way)."""
    from usdml.lighting.lgh import native as lgh_native

    if lgh_native.library() is None:
        return float("inf")
    return EACH_VISIT_COSTS.get(lgh_native.each_lanes(), EACH_VISIT_COSTS[0])

#: with every VPL as the other way (``choose(each=True)``), the split hierarchy is built only where the single one's
#: α 1 visits, times :data:`SPLIT_VISIT_FACTOR` and this, fit the budget: on the tuning stages at 100,000 VPLs the
#: pilot never took the split one's α below 1.75 (its α 1 erred 12-16 %), and the single one's gather visited
#: 1.9-2.0 times as many lights at α 1.75 as at 1. Building it and its pilot cost 0.25 s of a 0.87 s frame
#: (open_1024_s1, 64 px) that every VPL then lit
SPLIT_ALPHA_GROWTH = 2.0

#: VPLs per block of :func:`vpl_irradiance` (its arrays are points x this)
_BLOCK = 8192


@dataclass
class Choice:
    """What a frame's ``--gi lgh`` lights with."""

    split: str                  #: "none" (one hierarchy), "normal" (one per normal class) or "each" (every VPL)
    alpha: float                #: the blending radius factor (inf for "each")
    lgh: object                 #: the hierarchy (:class:`usdml.lighting.lgh.build.LGH`; "each": :class:`EachLight`)
    #: per hierarchy considered ("none", "normal"): {"alpha", "visits", "within_budget"} as chosen, and for the
    #: one chosen with a pilot, "pilot": [{"alpha", "visits", "rel_rmse"}, ...] for each α tried
    candidates: dict = field(default_factory=dict)


def vpl_irradiance(points: np.ndarray, normals: np.ndarray, position: np.ndarray, intensity: np.ndarray,
                   normal: np.ndarray, clamp_distance: float, meters_per_unit: float = 1.0,
                   compiled: bool = True) -> np.ndarray:
    """``(P, 3)`` float64 unshadowed irradiance at ``points`` (P, 3) with unit ``normals`` from every VPL as the
    LGH models it (``position``, ``intensity`` = Φ/4π, ``normal``: (N, 3)): Σ 4 I max(0, cos θ_l) max(0, cos θ_s)
    / max(d², d_c²) / metersPerUnit², d and the clamp d_c in scene units.

    Pair by pair in double by ``kernels/lgh/lghq.c`` (``lghq_cosine_sum``, blocks of points on the thread pool)
    where it is built and ``compiled``; else by NumPy (:func:`_numpy_irradiance`)."""
    from usdml.lighting.lgh import native as lgh_native

    p = np.ascontiguousarray(np.asarray(points).reshape(-1, 3), np.float32)
    if not compiled or lgh_native.library() is None or len(p) == 0:
        return _numpy_irradiance(points, normals, position, intensity, normal, clamp_distance, meters_per_unit)
    n = np.ascontiguousarray(np.asarray(normals).reshape(-1, 3), np.float32)
    lights = lgh_native.CosineLights(position, intensity, normal)
    out = np.zeros((len(p), 3))
    run_parallel(lambda span: lights.sum(p, n, float(clamp_distance) ** 2, *span, out),
                 spans(len(p), 4 * cpu_workers()), cpu_workers())
    return out / float(meters_per_unit) ** 2


def _numpy_irradiance(points: np.ndarray, normals: np.ndarray, position: np.ndarray, intensity: np.ndarray,
                      normal: np.ndarray, clamp_distance: float, meters_per_unit: float = 1.0) -> np.ndarray:
    """:func:`vpl_irradiance` by NumPy, block by block of VPLs, each term from products of (P, 3) and (3, B)
    matrices: with w = q − p, d² = |q|² + |p|² − 2 p·q, d cos θ_s = q·n_p − p·n_p and d cos θ_l = p·n_q − q·n_q
    (coordinates taken from the points' centre, in float64, so the expansion loses nothing a clamped d² would
    keep)."""
    centre = np.asarray(points, np.float64).reshape(-1, 3).mean(axis=0) if len(points) else np.zeros(3)
    p = np.asarray(points, np.float64).reshape(-1, 3) - centre
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    pp = (p * p).sum(1)[:, None]
    pn = (p * n).sum(1)[:, None]
    clamp2 = float(clamp_distance) ** 2

    def block(a: int) -> np.ndarray:
        q = np.asarray(position[a:a + _BLOCK], np.float64) - centre
        nq = np.asarray(normal[a:a + _BLOCK], np.float64)
        d2 = np.maximum(pp + (q * q).sum(1)[None, :] - 2.0 * (p @ q.T), 0.0)       # (P, B)
        cos_s = np.maximum(n @ q.T - pn, 0.0)                                      # d cos θ_s
        cos_l = np.maximum(p @ nq.T - (q * nq).sum(1)[None, :], 0.0)               # d cos θ_l
        g = 4.0 * cos_s * cos_l / np.maximum(d2 * np.maximum(d2, clamp2), 1e-300)
        g[d2 <= 0.0] = 0.0
        return g @ np.asarray(intensity[a:a + _BLOCK], np.float64)

    # the blocks on the thread pool (NumPy lets go of the GIL), summed in their order: the same sum on any
    # number of cores
    out = np.zeros((len(p), 3))
    for part in run_parallel(block, range(0, len(position), _BLOCK), cpu_workers()):
        out += part
    return out / float(meters_per_unit) ** 2


def choose(one, build_split, points: np.ndarray, normals: np.ndarray, sources: tuple, *, alpha: float = 0.0,
           split: str = "auto", s0: bool = True, clamp_distance: float, meters_per_unit: float = 1.0, seed: int = 0,
           device: str = "cpu", fraction: float = AUTO_VISIT_FRACTION, target: float = PILOT_TARGET,
           each: bool = False, each_cost: float | None = None) -> Choice:
    """The frame's hierarchy and α (module docstring).

    ``one``: the single hierarchy (or None when ``split`` is "normal"); ``build_split()`` makes the split one
    (called at most once, only when needed); ``points``, ``normals`` (P, 3): the frame's shading points;
    ``sources = (positions, intensities, normals)`` the VPLs; ``alpha`` 0 = automatic (else used as given);
    ``split``: "auto", "none" or "normal"; ``s0``: the gathers start from the VPLs (S0); ``clamp_distance``
    and ``meters_per_unit`` as the gathers'; ``seed``: the pilot's points; ``fraction``: the visit budget
    (of the VPLs); ``target``: the pilot error an automatic α is chosen for; ``each``: the hierarchies' limit,
    every VPL its own light (:mod:`usdml.lighting.lgh.each`), may be chosen (``split`` "auto" with an automatic
    α), wherever no hierarchy has an α within target that costs less (``each_cost`` visits per VPL, default
    :func:`each_visit_cost`); ``split`` "each" takes it whatever the rest.
    """
    from usdml.lighting.lgh.each import EachLight

    n_vpls = len(sources[0])
    budget = fraction * max(n_vpls, 1)
    s0_positions = sources[0] if s0 else None
    alphas = np.asarray(PILOT_ALPHAS if alpha <= 0 else (alpha,), np.float64)
    candidates: dict = {}
    each = split == "each" or (each and split == "auto" and alpha <= 0)
    each_visits = (each_visit_cost() if each_cost is None else each_cost) * n_vpls   # in the gather's visits a point
    if each:
        candidates["each"] = {"alpha": None, "visits": float(each_visits) if np.isfinite(each_visits) else None,
                              "within_budget": bool(each_visits <= budget)}

    def limit() -> Choice:
        return Choice("each", float("inf"), EachLight(sources), candidates)

    if split == "each":
        return limit()
    if each and each_visits <= budget:
        # the budget now: what the exact sum costs, where that is less (a hierarchy's α must cost less to be chosen)
        budget = min(budget, each_visits)

    def visits_of(name: str, lgh) -> np.ndarray:
        visits = lights_visited(lgh, points, alphas, s0_positions)
        fits = visits <= budget
        candidates[name] = {"alpha": float(alphas[0]), "visits": float(visits[0]), "within_budget": bool(fits[0])}
        return visits

    if len(points) == 0 and split != "normal":      # a frame that sees no geometry: nothing to choose for
        return Choice("none", float(alphas[0]), one, {"none": {"alpha": float(alphas[0]), "visits": 0.0,
                                                               "within_budget": True}})
    hierarchies: dict = {}                       # name -> (hierarchy, visits per α)
    if split in ("auto", "none"):
        hierarchies["none"] = (one, visits_of("none", one))
        # auto: the split hierarchy too where it may fit (it is built only then)
        grow = SPLIT_ALPHA_GROWTH if each else 1.0
        if split == "auto" and hierarchies["none"][1][0] * SPLIT_VISIT_FACTOR * grow <= budget:
            split_lgh = build_split()
            hierarchies["normal"] = (split_lgh, visits_of("normal", split_lgh))
    else:
        split_lgh = build_split()
        hierarchies["normal"] = (split_lgh, visits_of("normal", split_lgh))
    # the split one first (its shadows too are closer: module docstring), where it fits the budget at all; with
    # every VPL as the other way, the single one not at all: its error with shadows was up to 2.85 times its pilot's
    # (canyon_1024_s1 at 64 px, 100,000 VPLs: its pilot-chosen α erred 8.4 % at 50x, every VPL 1.7 % at 89x)
    names = ("normal",) if each else ("normal", "none")
    order = [n for n in names if n in hierarchies and (hierarchies[n][1] <= budget).any()] \
        or [next(iter(hierarchies))]
    if each and len(points) and (order[0] not in names or not (hierarchies[order[0]][1] <= budget).any()):
        return limit()          # no α of the split hierarchy costs less than every VPL
    if alpha > 0 or len(points) == 0 or (not each and len(order) == 1
                                         and (hierarchies[order[0]][1] <= budget).sum() <= 1):
        # α as given, or one hierarchy with one α (or none) within the budget: nothing for a pilot to decide
        name = order[0]
        visits = hierarchies[name][1]
        at = int(np.argmax(visits <= budget))         # the α within the budget, or the smallest
        c = candidates[name]
        c.update(alpha=float(alphas[at]), visits=float(visits[at]), within_budget=bool(visits[at] <= budget))
        return Choice(name, c["alpha"], hierarchies[name][0], candidates)
    # the pilot: per hierarchy in order, the smallest α within the budget whose unshadowed error on the pilot
    # points is within target; where no hierarchy has one, the (hierarchy, α) that erred least there
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(len(points), min(PILOT_POINTS, len(points)), replace=False))
    pts = np.ascontiguousarray(points[pick], np.float32)
    nrm = np.ascontiguousarray(normals[pick], np.float32)
    exact = None
    least = None
    for name in order:
        lgh, visits = hierarchies[name]
        within = np.flatnonzero(visits <= budget)
        c = candidates[name]
        if len(within) == 0:                       # the last resort: the smallest α, over the budget
            c.update(alpha=float(alphas[0]), visits=float(visits[0]))
            return Choice(name, c["alpha"], lgh, candidates)
        if exact is None:
            exact = vpl_irradiance(pts, nrm, *sources, clamp_distance, meters_per_unit)
            mean = float(exact.mean())
        gather = LGHGather(lgh, float(alphas[within[0]]), 0, seed, meters_per_unit, clamp_distance, device,
                           s0=sources if s0 else None)
        tried = c["pilot"] = []
        for at in within:
            got = gather.at_alpha(float(alphas[at]))(pts, nrm).irradiance.astype(np.float64)
            error = float(np.sqrt(np.mean((got - exact) ** 2)) / mean) if mean > 0 else 0.0
            tried.append({"alpha": float(alphas[at]), "visits": float(visits[at]), "rel_rmse": error})
            if least is None or error < least[2]["rel_rmse"]:
                least = (name, lgh, tried[-1])
            if error <= target:
                c.update(alpha=tried[-1]["alpha"], visits=tried[-1]["visits"], pilot_rel_rmse=error)
                return Choice(name, tried[-1]["alpha"], lgh, candidates)
        best = min(tried, key=lambda t: t["rel_rmse"])
        c.update(alpha=best["alpha"], visits=best["visits"], pilot_rel_rmse=best["rel_rmse"])
    if each:
        return limit()          # no hierarchy within target at less than every VPL's cost
    name, lgh, best = least
    return Choice(name, best["alpha"], lgh, candidates)
