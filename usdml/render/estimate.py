"""A frame's own error estimate for approximate visibility (issue 36 item 2).

Paper 000 §6.1 measures ``ε_v`` and ``ε_s`` by tracing every facing pixel–light pair exactly
(:func:`usdml.compare.compare_visibility`). A frame cannot afford that, so it traces a sample:

* pixels: ``pixels`` (128 to 256, as the frame's own work allows: :data:`BUDGET`) of the frame's hit pixels,
  stratified over the image (the hit pixels in scan order cut into that many equal runs, one pixel drawn
  in each), seeded by the render's seed and the timecode;
* lights: at each of them, every light when the frame has at most ``lights`` (or when every hit pixel is
  sampled and all their pairs are no more than ``pixels`` × ``lights``: the whole frame), else ``lights``
  lights drawn uniformly, its own draw per pixel (without replacement up to :data:`DENSE_LIGHTS` lights,
  :func:`subsets`; with replacement beyond); a non-facing light counts as answered right;
* each sampled pair is answered by the exact backend and by the shadow backend (``occluded``).

A ``LIGHT_MAJOR`` backend (``insm``: a map per light, built anew for every call) would build a map for
nearly every light of the frame again; it answers the sampled pixels against :data:`SHARED_LIGHTS` lights
drawn once (without replacement) instead, and the interval adds the light draw's variance (a
delete-one-light jackknife) to the pixels'.

Per sampled pixel ``p``, with ``h_p`` and ``v_p`` its wrongly hidden and wrongly visible pairs among its
``k`` drawn lights, ``x_p = (h_p + v_p) / k`` and ``d_p = (h_p - v_p) / k``; ``ε_v`` is estimated by the mean
of ``x_p`` (unbiased: the mean over pixels of each pixel's error fraction), ``ε_s`` by the mean of ``|d_p|``
(exact per pixel when every light is drawn; otherwise biased upward, ``E|d_p| >= |E d_p|``).

The 95 % interval treats the pixels as a simple random sample (stratification only narrows the true
spread, so the interval errs wide): Student's t over the per-pixel values, with the finite-population
correction when every light is drawn (so a sample of every hit pixel gives the measured value itself).
Per-pixel values lie in [0, 1] and are mostly 0 on a good approximation, where the t interval is too
narrow (a handful of nonzero pixels); while fewer than :data:`FEW_NONZERO` pixels are nonzero the interval
is widened to hold Wilson's score interval with ``n`` the sampled pixels, which is honest for any [0, 1]
variable (its variance is at most ``μ(1 - μ)``). ``ε_s``'s interval with drawn lights: the upper end is
``mean |d_p|``'s (an upper bound of ``ε_s`` on average), the lower end ``|mean d_p|``'s (``ε_s >= |mean_p
(h_p - v_p)| / n_l``).
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import asdict, dataclass

import numpy as np

from usdml.lighting.direct import facing_pairs
from usdml.scene import Lights
from usdml.visibility.base import LIGHT_MAJOR, VisibilityBackend

#: sampled pixels per frame: at most, at least (when the frame has as many hit pixels)
PIXELS = 256
MIN_PIXELS = 128
#: exact pairs traced per pair the frame shades (the shadow backend's answers: passes × hit pixels × lights);
#: an exact ray costs about ten of an approximate backend's queries, so this keeps the estimate near 5 % of
#: the frame's shading
BUDGET = 1 / 300
#: lights per sampled pixel (every light when the frame has no more)
LIGHTS = 1024
#: a ``LIGHT_MAJOR`` backend's lights, the same for every sampled pixel (module doc)
SHARED_LIGHTS = 32
#: at most this many lights: a pixel's own draw of lights is picked from a dense (pixels, lights) table
DENSE_LIGHTS = 4096
#: fewer nonzero per-pixel values than this: the interval also holds Wilson's (module doc)
FEW_NONZERO = 10
#: two-sided 95 %
Z95 = 1.959963984540054


@dataclass
class VisibilityEstimate:
    """One frame's estimate of ``ε_v`` and ``ε_s`` (fractions, not %) with 95 % intervals (module doc)."""

    eps_v: float
    eps_v_lo: float
    eps_v_hi: float
    eps_s: float
    eps_s_lo: float
    eps_s_hi: float
    pixels: int             #: sampled pixels
    pairs: int              #: sampled pixel–light pairs (facing or not)
    queries: int            #: facing pairs answered by both backends
    exact_per_pixel: bool   #: every light drawn at each sampled pixel
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


def t95(df: int) -> float:
    """Student's t two-sided 95 % quantile for ``df`` degrees of freedom (Cornish–Fisher, 1e-3 at df 3)."""
    if df <= 0:
        return math.inf
    z = Z95
    return (z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * df ** 3))


def wilson(mean: float, n: int, fpc: float = 1.0) -> tuple[float, float]:
    """Wilson's score interval of a [0, 1] mean over ``n`` samples, ``fpc`` the finite-population
    factor of the variance."""
    z2 = Z95 ** 2 * fpc
    centre = (mean + z2 / (2 * n)) / (1 + z2 / n)
    half = math.sqrt(z2 * mean * (1 - mean) / n + z2 * z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def mean_interval(x: np.ndarray, fpc: float) -> tuple[float, float, float]:
    """``(mean, lo, hi)`` of per-pixel values ``x`` in [0, 1] (module doc: t, widened by Wilson's when
    few are nonzero); ``fpc`` = 1 - sampled / population, 0 when every pixel is in."""
    n = len(x)
    mean = float(x.mean()) if n else 0.0
    if n == 0:
        return 0.0, 0.0, 1.0
    if fpc <= 0:
        return mean, mean, mean
    half = t95(n - 1) * float(x.std(ddof=1)) / math.sqrt(n) * math.sqrt(fpc) if n > 1 else math.inf
    lo, hi = max(0.0, mean - half), min(1.0, mean + half)
    if int((x > 0).sum()) < FEW_NONZERO:
        wlo, whi = wilson(mean, n, fpc)
        lo, hi = min(lo, wlo), max(hi, whi)
    return mean, lo, hi


def sample_pixels(n_hit: int, pixels: int, rng: np.random.Generator) -> np.ndarray:
    """Indices into ``n_hit`` hit pixels (scan order): ``pixels`` equal runs, one drawn in each; every
    pixel when there are no more than ``pixels``."""
    if n_hit <= pixels:
        return np.arange(n_hit)
    edges = np.linspace(0, n_hit, pixels + 1)
    pick = np.floor(edges[:-1] + rng.random(pixels) * np.diff(edges)).astype(np.int64)
    return np.minimum(pick, n_hit - 1)


def subsets(rng: np.random.Generator, rows: int, n: int, k: int) -> np.ndarray:
    """``(rows, k)``: each row a uniformly random ``k``-subset of ``range(n)`` (Floyd's algorithm, vectorized
    over the rows: ``k`` draws a row, where random keys over every element and a partition cost ``rows × n``)."""
    out = np.empty((rows, k), np.int64)
    for c, j in enumerate(range(n - k, n)):
        t = rng.integers(0, j + 1, size=rows)
        out[:, c] = np.where((out[:, :c] == t[:, None]).any(axis=1), j, t)
    return out


def frame_rng(seed: int, time: float) -> np.random.Generator:
    """The estimate's generator for a frame: the render's seed and the timecode (to the millisecond)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(round(time * 1000)) & 0xFFFFFFFF, 36])


def estimate_visibility(points: np.ndarray, normals: np.ndarray, geometric: np.ndarray | None, lights: Lights,
                        exact: VisibilityBackend, approx: VisibilityBackend, rng: np.random.Generator,
                        pixels: int = PIXELS, lights_per_pixel: int = LIGHTS,
                        shared_lights: int = SHARED_LIGHTS, frame_pairs: int | None = None) -> VisibilityEstimate:
    """Estimate ``approx``'s ``ε_v`` and ``ε_s`` against ``exact`` at a frame's hit pixels (module doc).

    Parameters
    ----------
    points, normals : (N, 3) every hit pixel's world position and shading normal, in scan order.
    geometric : (N, 3) geometric normals, or None.
    lights : the frame's lights.
    exact, approx : backends brought to the frame.
    rng : :func:`frame_rng`.
    pixels : the most pixels sampled; fewer when ``frame_pairs`` (the pairs the frame shades) times
        :data:`BUDGET` is less than their pairs, never fewer than :data:`MIN_PIXELS`.
    """
    if frame_pairs is not None:
        per_pixel = min(len(lights), shared_lights if approx.supports(LIGHT_MAJOR) else lights_per_pixel)
        pixels = int(np.clip(round(BUDGET * frame_pairs / max(per_pixel, 1)), MIN_PIXELS, pixels))
    sample = PairSample(points, normals, geometric, lights, exact, rng, pixels, lights_per_pixel,
                        shared_lights if approx.supports(LIGHT_MAJOR) else None)
    return sample.estimate(approx.occluded)


class PairSample:
    """The sampled pixel–light pairs of one frame and the exact backend's answers to them (module doc), to
    estimate any number of approximations of the same frame (``--error-budget`` tries its levels on one
    sample: :mod:`usdml.render.budget`).

    ``shared``: a ``LIGHT_MAJOR`` backend's light count (every sampled pixel against the same lights); None:
    each pixel its own draw of ``lights_per_pixel`` lights (every light when there are no more).
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, geometric: np.ndarray | None, lights: Lights,
                 exact: VisibilityBackend, rng: np.random.Generator, pixels: int = PIXELS,
                 lights_per_pixel: int = LIGHTS, shared: int | None = None):
        t0 = _time.perf_counter()
        n_hit, n_l = len(points), len(lights)
        pick = sample_pixels(n_hit, pixels, rng)
        self.m = m = len(pick)
        pts, nrm = points[pick], normals[pick]
        geo = None if geometric is None else geometric[pick]
        self.shared = shared is not None and n_l > shared
        # a frame whose every pair fits the sample's pairs (every hit pixel sampled) is traced whole: its
        # measured error, not a bound of it (an upper end of 4 / pixels with no error would refuse a budget
        # a small frame meets)
        whole = m == n_hit and m * n_l <= pixels * lights_per_pixel
        self.every = not self.shared and (n_l <= lights_per_pixel or whole)
        self.k = shared if self.shared else (n_l if self.every else lights_per_pixel)
        self.fpc = (1.0 - m / n_hit) if (self.every and n_hit) else 1.0
        blocks = []
        if self.shared or self.every:
            drawn = lights.subset(np.sort(rng.choice(n_l, shared, replace=False))) if self.shared else lights
            blocks = list(facing_pairs(pts, nrm, drawn, geo))
        elif n_l <= DENSE_LIGHTS:
            # each pixel its own ``k`` lights without replacement: every pair's facing test, the drawn kept
            chosen = np.zeros((m, n_l), bool)
            np.put_along_axis(chosen, subsets(rng, m, n_l, self.k), True, axis=1)
            # the facing test on every pair, the queries made of the drawn ones only
            blocks = list(facing_pairs(pts, nrm, lights, geo, among=chosen))
        else:
            draws = rng.integers(0, n_l, (m, self.k))
            for i in range(m):
                sub = lights.subset(draws[i])
                for origin, target, normal, distant, _, li in facing_pairs(
                        pts[i:i + 1], nrm[i:i + 1], sub, None if geo is None else geo[i:i + 1]):
                    blocks.append((origin, target, normal, distant, np.full(len(origin), i), li))
        self.queries = 0
        if blocks and self.k:
            self.origin, self.target, self.normal, distant, self.px, self.li = (np.concatenate(a) for a in zip(*blocks))
            self.distant = distant.astype(bool)
            self.px = self.px.astype(np.int64)
            self.li = self.li.astype(np.int64)
            self.ref = exact.occluded(self.origin, self.target, normals=self.normal, distant=self.distant)
            self.queries = len(self.origin)
        self.seconds = _time.perf_counter() - t0

    def estimate(self, occluded) -> VisibilityEstimate:
        """The estimate of the approximation answering ``occluded(origins, targets, normals=, distant=)``."""
        t0 = _time.perf_counter()
        m, k = self.m, self.k
        if self.shared:
            hidden = np.zeros((m, k), np.int64)
            visible = np.zeros((m, k), np.int64)
            if self.queries:
                got = occluded(self.origin, self.target, normals=self.normal, distant=self.distant)
                ref = self.ref
                np.add.at(hidden, (self.px[got & ~ref], self.li[got & ~ref]), 1)
                np.add.at(visible, (self.px[~got & ref], self.li[~got & ref]), 1)
            return _shared_lights(hidden, visible, self.queries, self.seconds + _time.perf_counter() - t0)
        hidden = np.zeros(m, np.int64)
        visible = np.zeros(m, np.int64)
        if self.queries:
            got = occluded(self.origin, self.target, normals=self.normal, distant=self.distant)
            ref = self.ref
            hidden = np.bincount(self.px[got & ~ref], minlength=m)
            visible = np.bincount(self.px[~got & ref], minlength=m)
        kk = max(k, 1)
        x = (hidden + visible) / kk
        d = (hidden - visible) / kk
        eps_v, v_lo, v_hi = mean_interval(x, self.fpc)
        eps_s, s_lo, s_hi = mean_interval(np.abs(d), self.fpc)
        if not self.every and m > 1:
            # |d_p| overstates |h - v| / n_l: the lower end from the signed mean instead (module doc)
            signed = abs(float(d.mean())) - t95(m - 1) * float(d.std(ddof=1)) / math.sqrt(m)
            s_lo = min(s_lo, max(0.0, signed))
        return VisibilityEstimate(eps_v, v_lo, v_hi, eps_s, s_lo, s_hi, m, m * k, self.queries, self.every,
                                  self.seconds + _time.perf_counter() - t0)


def _shared_lights(hidden: np.ndarray, visible: np.ndarray, queries: int, seconds: float) -> VisibilityEstimate:
    """A ``LIGHT_MAJOR`` backend (paper 001: a map per light, built anew for each call) answers the sampled
    pixels against ``k`` (:data:`SHARED_LIGHTS`) lights drawn once without replacement (module doc): pixels and
    lights are then both samples, and each statistic's variance is its pixel part (over the per-pixel values)
    plus its light part (delete-one-light jackknife). ``hidden``, ``visible``: (pixels, k) counts."""
    m, k = hidden.shape
    wrong, signed = (hidden + visible).astype(np.float64), (hidden - visible).astype(np.float64)

    def interval(z: np.ndarray, stat) -> tuple[float, float, float]:
        value = stat(z.sum(1) / k)
        rows = stat(z.sum(1, keepdims=True) / k, per_pixel=True)
        loo = np.array([stat((z.sum(1) - z[:, j]) / (k - 1)) for j in range(k)])
        var = rows.var(ddof=1) / m + (k - 1) / k * ((loo - loo.mean()) ** 2).sum()
        half = t95(min(m, k) - 1) * var ** 0.5
        return value, value - half, value + half

    def mean(x, per_pixel=False):
        return x.ravel() if per_pixel else float(x.mean())

    def mean_abs(x, per_pixel=False):
        return np.abs(x).ravel() if per_pixel else float(np.abs(x).mean())

    eps_v, v_lo, v_hi = interval(wrong, mean)
    if int((wrong.sum(1) > 0).sum()) < FEW_NONZERO:
        wlo, whi = wilson(eps_v, m)
        v_lo, v_hi = min(v_lo, wlo), max(v_hi, whi)
    eps_s, _, s_hi = interval(signed, mean_abs)
    d, d_lo, d_hi = interval(signed, mean)
    s_lo = 0.0 if d_lo <= 0 <= d_hi else min(abs(d_lo), abs(d_hi))
    s_hi = max(s_hi, v_hi) if int((wrong.sum(1) > 0).sum()) < FEW_NONZERO else s_hi
    return VisibilityEstimate(eps_v, max(0.0, v_lo), min(1.0, v_hi), eps_s, s_lo, min(1.0, s_hi), m, m * k, queries,
                              False, seconds)


#: EXR header attributes of an estimate (:func:`header`)
HEADER_KEYS = ("eps_v", "eps_v_lo", "eps_v_hi", "eps_s", "eps_s_lo", "eps_s_hi", "pixels", "pairs")


#: and of a frame under ``--error-budget`` (usdml.render.budget): the budget, the level (-1: every answer exact)
#: and the fractions of the frame's queries re-asked of the exact backend
BUDGET_KEYS = ("budget", "level", "refined_fraction", "near_fraction")


def header(estimate: VisibilityEstimate) -> dict:
    """``usdml:estimate:<key>`` attributes of an estimate for the EXR: :data:`HEADER_KEYS`, and :data:`BUDGET_KEYS`
    under ``--error-budget`` (:class:`usdml.render.budget.BudgetEstimate`)."""
    values = estimate.as_dict()
    out = {f"usdml:estimate:{k}": (int(values[k]) if k in ("pixels", "pairs") else float(values[k]))
           for k in HEADER_KEYS}
    for k in BUDGET_KEYS:
        if k in values:
            value = values[k]
            out[f"usdml:estimate:{k}"] = (-1 if value == "exact" else int(value)) if k == "level" else float(value)
    return out
