"""``--error-budget E`` (issue 36 item 3): each frame's refinement level, chosen so its estimated ε_v holds.

Per frame, before the direct light is shaded, one sample of its pixel–light pairs is traced exactly
(:class:`usdml.render.estimate.PairSample`), then answered by the approximate backend refined at level 0
(no refinement), 1, 2, ... (:class:`usdml.visibility.refine.Refined`: its rule widened step by step); the
frame is shaded at the first level whose estimated 95 % upper bound of ε_v is at most ``E``, and carries
that level's estimate. When no level of the backend's rule gets there, or a level would re-ask
more than :data:`MAX_REFINED` of the sample's answers of the exact backend, or its rule alone costs an exact
ray a query or more (the backend's ``refine_costs``: the octree's NumPy thick ray) -- slower than exact alone
either way -- every answer of the frame is exact (the limit, where ε_v is 0) and one warning line names the
frame. ``E = 0`` is that limit at once: the exact
backend's pixels. ``E = 1`` (the default) is no budget: the backend as it is.

The sample is larger than a plain frame's estimate (:data:`PIXELS_PER_BUDGET` / ``E`` pixels, from
:data:`MIN_PIXELS` to :data:`MAX_PIXELS`, :data:`LIGHTS` lights each): a bound on a mean of per-pixel
fractions can only be as low as about 4 / pixels when the sampled pixels show no error (Wilson's interval,
:func:`usdml.render.estimate.mean_interval`), so a budget of 0.003 needs over 1,300 pixels to be provable.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import asdict, dataclass, field

import numpy as np

from usdml.errors import log
from usdml.render.estimate import PairSample, VisibilityEstimate, frame_rng
from usdml.scene import Lights
from usdml.visibility.base import LIGHT_MAJOR, VisibilityBackend
from usdml.visibility.refine import EXACT, Refined

#: sampled pixels per unit of 1 / budget, and their bounds
PIXELS_PER_BUDGET = 8.0
MIN_PIXELS = 1024
MAX_PIXELS = 8192
#: lights drawn per sampled pixel (a LIGHT_MAJOR backend: lights shared by every sampled pixel)
LIGHTS = 32
SHARED_LIGHTS = 32
#: no budget: the default
OFF = 1.0
#: a level re-asking more than this share of the sample's answers of the exact backend (uncertain and blind
#: zone) is slower than exact alone (an exact ray costs several approximate queries): the frame goes exact
MAX_REFINED = 0.5


@dataclass
class BudgetEstimate(VisibilityEstimate):
    """A frame's estimate under ``--error-budget``: the chosen level's (module doc), with the budget's choice."""

    budget: float = OFF
    level: int | str = 0                #: the refinement level; ``"exact"``: every answer of the frame exact
    met: bool = True                    #: a level of the rule held the budget
    levels: dict[str, float] = field(default_factory=dict)     #: each tried level's ``eps_v_hi``
    #: of the frame's queries, those re-asked of the exact backend and those in the blind zone (after its
    #: passes: :meth:`usdml.visibility.refine.Refined.fractions`; None before)
    refined_fraction: float | None = None
    near_fraction: float | None = None

    def as_dict(self) -> dict:
        """The fields by name, the fractions once the frame has them."""
        return {k: v for k, v in asdict(self).items() if v is not None}


def active(budget: float, shadow: VisibilityBackend, primary: VisibilityBackend) -> bool:
    """Whether a budget refines anything: under 1, and an approximate shadow backend."""
    return budget < OFF and shadow is not primary


def sample_pixels(budget: float) -> int:
    """Pixels sampled per frame for ``budget`` (module doc)."""
    if budget <= 0:
        return MIN_PIXELS
    return int(np.clip(math.ceil(PIXELS_PER_BUDGET / budget), MIN_PIXELS, MAX_PIXELS))


def choose_level(refined: Refined, points: np.ndarray, normals: np.ndarray, geometric: np.ndarray | None,
                 lights: Lights, budget: float, seed: int, time: float, where: str) -> BudgetEstimate:
    """Set ``refined.level`` for the frame at ``time`` (module doc) from its first pass's hit pixels; return the
    frame's estimate with ``budget``, ``level`` (``"exact"`` at the limit), ``met`` (a level of the rule held the
    budget) and ``levels`` (each tried level's ``eps_v_hi``). ``where`` starts the warning (the stage)."""
    t0 = _time.perf_counter()
    exact = refined.exact
    if budget <= 0 or len(lights) == 0 or len(points) == 0:
        refined.level = EXACT if budget <= 0 else 0
        est = VisibilityEstimate(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, True)
        return BudgetEstimate(**est.as_dict(), budget=budget, level="exact" if budget <= 0 else 0, met=True)
    shared = SHARED_LIGHTS if refined.approx.supports(LIGHT_MAJOR) else None
    sample = PairSample(points, normals, geometric, lights, exact, frame_rng(seed, time), sample_pixels(budget),
                        LIGHTS, shared)
    tried: dict[str, float] = {}
    chosen, est, share = None, None, 0.0
    cost = 0.0
    for level in range(0, refined.approx.refine_levels + 1):
        cost = refined.approx.refine_cost(level)
        if cost >= 1.0:
            break
        refined.reset()
        est = sample.estimate(lambda o, t, level=level, **kw: refined.answer(o, t, level=level, **kw)[0])
        tried[str(level)] = est.eps_v_hi
        share = sum(refined.fractions().values())          # re-asked and blind-zone rays, per query
        if share > MAX_REFINED:
            break
        if est.eps_v_hi <= budget:
            chosen = level
            break
        if est.eps_v == 0:      # no wrong answer: the bound is the sample's size, which no wider rule lowers
            break
    met = chosen is not None
    if not met:
        chosen = EXACT
        if cost >= 1.0:
            why = (f"estimated eps_v up to {100 * est.eps_v_hi:.2f} % at level {level - 1}, and its rule costs "
                   f"{cost:g} exact rays a query at level {level} (exact alone is faster)")
        elif share > MAX_REFINED:
            why = f"it re-asks {100 * share:.0f} % of the answers at level {level} (exact alone is faster)"
        elif est.eps_v == 0:
            why = (f"its sample of {est.pixels:,} pixels found no wrong answer, which bounds eps_v at "
                   f"{100 * est.eps_v_hi:.2f} % only: too few pixels to show the budget")
        else:
            why = f"estimated eps_v up to {100 * est.eps_v_hi:.2f} % at its widest rule"
        log.warning(f"{where}: frame {time:g}: --error-budget {budget:g} not met by {refined.approx.name}'s "
                    f"refinement ({why}); every answer of the frame is exact")
        est = VisibilityEstimate(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, est.pixels, est.pairs, est.queries, False)
    refined.level = chosen
    refined.reset()
    est.seconds = _time.perf_counter() - t0
    return BudgetEstimate(**est.as_dict(), budget=budget, level="exact" if chosen == EXACT else chosen, met=met,
                          levels=tried)
