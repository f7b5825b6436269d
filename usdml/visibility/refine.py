"""Refinement of uncertain answers (issue 36): an approximate backend's answers, the uncertain ones exact.

An approximate backend that declares ``REFINE`` answers each shadow query and says whether the answer is
*certain* by a rule of its own geometry (:meth:`usdml.visibility.base.VisibilityBackend.occluded_uncertain`),
widened by a level (1 the narrowest, up to its ``refine_levels``). :class:`Refined` puts it in front of
the exact backend (Embree, already built for the primary rays):

1. the backend's answers and uncertain flags at the level;
2. the *blind zone*: a voxel method cannot see an occluder within the first few voxels of a ray (it
   skips them to leave its own surface, ``blind_reach``), where contact shadows are. Each distinct ray
   start is probed with :data:`PROBES` short exact rays over that reach; where one hits (other geometry
   within reach: a wall's foot, a sill), the rays answered *free* are traced exactly over that first
   stretch (a hit there blocks the segment: exact's own answer for part of it);
3. the uncertain answers re-asked of the exact backend, in one batch, on the same threads.

Level 0 is the backend alone (no refinement); a level above ``refine_levels`` answers everything exactly
(``EXACT``), which gives the exact backend's pixels. ``--error-budget`` picks the level per frame
(:mod:`usdml.render.budget`).

The thick-ray rule (:func:`thick_ray`) is the voxel methods' rule: an answer is uncertain when the rays
shifted sideways by ``width`` voxels in four directions across the ray do not all give it. It catches
rays that pass within that width of occupied voxels (thin geometry missed or voxels over-covering an edge,
the direction bin's tilt over a long ray) and blocking voxels at a surface's edge. Measured on
``stages/city.usda`` at 128 px (7.3 M facing pairs, voxel 128³ / 2°): width 1.5 flags 8.0 % of the pairs
and holds 82 % of the wrong answers; what it misses lies almost all within two voxels of the ray's start
(the blind zone: 2 above). Both together leave ε_v 0.09 %, from 1.85 %.
"""

from __future__ import annotations

import threading
from types import MappingProxyType

import numpy as np

from usdml.visibility.base import (LIGHT_MAJOR, REFINE, SHADE_DIRECT, DirectResult, VisibilityBackend, as_flags,
                                   as_vectors)

__all__ = ["Refined", "thick_ray", "EXACT", "PROBES"]

#: the level at which every answer is exact
EXACT = 1 << 20
#: short exact rays probing the blind zone at each distinct ray start (a fixed pattern over the hemisphere)
PROBES = 16


def _across(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across each unit direction ``d`` (N, 3), perpendicular to it and to each other."""
    a = np.where(np.abs(d[:, :1]) < 0.6, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    u = np.cross(d, a)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-30)
    return u, np.cross(d, u)


def thick_ray(occluded, origins: np.ndarray, targets: np.ndarray, normals, distant, width: float,
              blocked: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(blocked, uncertain)`` by the thick-ray rule (module doc): ``occluded`` (a backend's) over the rays and
    over the four rays shifted by ``width`` (world units) across each: the end moved by the shift, the start by
    its part along the surface (``normals``; a distant ray's target is a direction and stays). ``blocked``: the
    unshifted answers when known."""
    origins = np.asarray(origins, np.float64)
    targets = np.asarray(targets, np.float64)
    n = len(origins)
    distant = np.zeros(n, bool) if distant is None else np.asarray(distant, bool)
    kw = dict(normals=normals, distant=distant)
    if blocked is None:
        blocked = occluded(origins, targets, **kw)
    if n == 0 or width <= 0:
        return blocked, np.zeros(n, bool)
    d = np.where(distant[:, None], targets, targets - origins)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    u, v = _across(d)
    # a shifted ray still starts on its surface: its start moves along the tangent plane only (a start moved
    # under a ground would see the ground block it)
    if normals is not None:
        nrm = np.asarray(normals, np.float64)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    same = np.ones(n, bool)
    moves_target = ~distant[:, None]
    for s in (u, -u, v, -v):
        shift = s * width
        start = shift if normals is None else shift - np.einsum("ij,ij->i", shift, nrm)[:, None] * nrm
        same &= occluded(origins + start, targets + shift * moves_target, **kw) == blocked
    return blocked, ~same


def _hemisphere(k: int) -> np.ndarray:
    """``k`` fixed directions over the +z hemisphere (a spiral, cosine-weighted), (k, 3)."""
    i = np.arange(k) + 0.5
    r = np.sqrt(i / k)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


def _runs(origins: np.ndarray, starts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One row of each distinct ray start and each row's start (an index into the first): by ``starts`` (each
    row's point, equal for rows from one point) when given, else each run of equal consecutive ``origins``."""
    if starts is not None:
        starts = np.asarray(starts, np.int64)
        if not len(starts):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        first = np.full(int(starts.max()) + 1, -1, np.int64)
        first[starts[::-1]] = np.arange(len(starts) - 1, -1, -1)
        used = np.flatnonzero(first >= 0)
        slot = np.zeros(len(first), np.int64)
        slot[used] = np.arange(len(used))
        return first[used], slot[starts]
    n = len(origins)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    new = np.ones(n, bool)
    new[1:] = np.any(origins[1:] != origins[:-1], axis=1)
    starts = np.flatnonzero(new)
    return starts, np.cumsum(new) - 1


def near_points(exact: VisibilityBackend, points: np.ndarray, normals: np.ndarray, reach: float) -> np.ndarray:
    """``(P,) bool``: whether other geometry lies within ``reach`` of each point on its normal's side (the blind
    zone, module doc): :data:`PROBES` short exact rays over the hemisphere, stopped at the first hit."""
    points = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    has = length[:, 0] > 0
    nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
    u, v = _across(np.where(has[:, None], nrm, np.array([[0.0, 0.0, 1.0]])))
    near = np.zeros(len(points), bool)
    for dx, dy, dz in _hemisphere(PROBES):
        live = np.flatnonzero(has & ~near)
        if not len(live):
            break
        direction = u[live] * dx + v[live] * dy + nrm[live] * dz
        near[live] = exact.occluded(points[live], points[live] + direction * reach, normals=nrm[live])
    return near


def _short(origins: np.ndarray, targets: np.ndarray, distant: np.ndarray, reach: float) -> np.ndarray:
    """The ends of the segments' first ``reach`` (the whole segment where it is shorter)."""
    d = np.where(distant[:, None], targets, targets - origins)
    span = np.linalg.norm(d, axis=1, keepdims=True)
    return origins + d / np.maximum(span, 1e-30) * np.where(distant[:, None], reach, np.minimum(reach, span))


class Refined(VisibilityBackend):
    """``approx``'s answers with the uncertain ones re-asked of ``exact`` at :attr:`level` (module doc).

    Neither backend is owned: the renderer updates and closes them. ``counts`` holds the queries answered
    since :meth:`reset`, those re-asked of the exact backend (``refined``) and the rays traced over the
    blind zone (``near``).
    """

    def __init__(self, approx: VisibilityBackend, exact: VisibilityBackend, level: int = 0):
        if not approx.supports(REFINE):
            raise ValueError(f"the {approx.name} backend does not say which answers are uncertain")
        self.approx, self.exact, self.level = approx, exact, int(level)
        self.name = approx.name
        self.summary = approx.summary
        # SHADE_DIRECT: shade_direct picks the backend's fused kernel with refinement where it has one
        self.capabilities = (frozenset({LIGHT_MAJOR}) & approx.capabilities) | {SHADE_DIRECT}
        self.counts = {"queries": 0, "refined": 0, "near": 0}
        self._lock = threading.Lock()
        if LIGHT_MAJOR in self.capabilities:
            # a map per light, built anew for each call: few, large calls (about 200 bytes a pair)
            self.matrix_chunk_pairs = 1 << 22

    def supports(self, capability: str) -> bool:       # per instance: LIGHT_MAJOR as the wrapped backend
        return super().supports(capability) or capability in self.capabilities

    @property
    def stats(self):
        return MappingProxyType(dict(self.approx.stats))

    @property
    def emitter_offset(self) -> float:
        """The approximate backend's (its answers are the ones an emitting surface would block)."""
        return self.approx.emitter_offset

    def _count(self, key: str, n: int) -> None:
        with self._lock:       # shading asks from several threads at once
            self.counts[key] += n

    def reset(self) -> None:
        self.counts = {k: 0 for k in self.counts}

    def describe(self) -> dict:
        return self.approx.describe()

    def update(self, snapshot, changes=None) -> None:
        """Nothing: the renderer updates both backends."""

    def fractions(self) -> dict:
        """``refined`` (answers re-asked of the exact backend) and ``near`` (blind-zone rays), per query."""
        q = max(self.counts["queries"], 1)
        return {"refined_fraction": self.counts["refined"] / q, "near_fraction": self.counts["near"] / q}

    def occluded(self, origins, targets, *, normals=None, distant=None) -> np.ndarray:
        blocked, _ = self.answer(origins, targets, normals=normals, distant=distant)
        return blocked

    def answer(self, origins, targets, *, normals=None, distant=None, level: int | None = None,
               starts: np.ndarray | None = None):
        """``(blocked, refined)``: the answers at ``level`` (default :attr:`level`) and which were re-asked.
        ``starts``: each row's ray start (point index; rows of one point alike), when rows of one start are not
        consecutive."""
        level = self.level if level is None else int(level)
        origins = as_vectors(origins, "origins", dtype=None)
        n = origins.shape[0]
        targets = as_vectors(targets, "targets", n, dtype=None)
        distant = np.zeros(n, bool) if distant is None else as_flags(distant, "distant", n)
        self._count("queries", n)
        kw = dict(normals=normals, distant=distant)
        if level > self.approx.refine_levels:
            self._count("refined", n)
            return self.exact.occluded(origins, targets, **kw), np.ones(n, bool)
        if level <= 0:
            return self.approx.occluded(origins, targets, **kw), np.zeros(n, bool)
        blocked, uncertain = self.approx.occluded_uncertain(origins, targets, level=level, **kw)
        blocked = blocked.copy()
        reach = float(getattr(self.approx, "blind_reach", lambda _: 0.0)(level))
        if reach > 0 and normals is not None:
            self._blind_zone(origins, targets, normals, distant, blocked, uncertain, reach, starts)
        redo = np.flatnonzero(uncertain)
        if len(redo):
            # np.take: a row gather several times faster than fancy indexing on (N, 3) arrays
            blocked[redo] = self.exact.occluded(np.take(origins, redo, axis=0), np.take(targets, redo, axis=0),
                                                normals=None if normals is None else
                                                np.take(np.asarray(normals), redo, axis=0),
                                                distant=distant[redo])
            self._count("refined", len(redo))
        return blocked, uncertain

    def _blind_zone(self, origins, targets, normals, distant, blocked, uncertain, reach: float, starts=None) -> None:
        """Step 2 of the module doc, in place on ``blocked``: the certain free answers of ray starts with other
        geometry within ``reach`` traced exactly over their first ``reach``."""
        origins = np.asarray(origins)
        first, run = _runs(origins, starts)
        pts = origins[first].astype(np.float64)
        nrm = np.asarray(normals)[first].astype(np.float64)

        tg = np.asarray(targets[first], np.float64)
        side = np.einsum("ij,ij->i", nrm, np.where(distant[first, None], tg, tg - pts))
        nrm = nrm * np.where(side < 0, -1.0, 1.0)[:, None]
        near = near_points(self.exact, pts, nrm, reach)
        rows = np.flatnonzero(near[run] & ~blocked & ~uncertain)
        if not len(rows):
            return
        o = origins[rows].astype(np.float64)
        end = _short(o, np.asarray(targets[rows], np.float64), distant[rows], reach)
        blocked[rows] = self.exact.occluded(o, end, normals=np.asarray(normals)[rows])
        self._count("near", len(rows))

    def shade_direct(self, points, normals, albedo, lights, progress=None, meters_per_unit: float = 1.0,
                     min_distance: float = 0.0, geometric=None, material=None, *, plain):
        """Direct light with refined shadows: the backend's fused kernel with refinement (``shade_refined``: it
        hands back the uncertain and blind-zone pairs, traced here) where it has one, every answer of a
        ``LIGHT_MAJOR`` backend at once (a map per light), else :func:`usdml.lighting.direct.shade_direct` over
        :meth:`occluded`. With ``material`` rows: the backend's own fused kernel when nothing is refined, else
        :func:`usdml.lighting.direct.shade_direct` over :meth:`occluded` (no refined kernel sums the BRDF)."""
        options = dict(meters_per_unit=meters_per_unit, min_distance=min_distance, geometric=geometric)
        if material is not None:
            options["material"] = material
        level = self.level
        if level <= 0:
            if self.approx.supports(SHADE_DIRECT):
                return self.approx.shade_direct(points, normals, albedo, lights, progress, plain=plain, **options)
            return plain(points, normals, albedo, lights, self.approx.occluded, progress, **options)
        if material is not None:
            return plain(points, normals, albedo, lights, self.occluded, progress, **options)
        if level > self.approx.refine_levels:
            result = plain(points, normals, albedo, lights, self.exact.occluded, progress, **options)
            self._count("queries", result.queries)
            self._count("refined", result.queries)
            return result
        fused = getattr(self.approx, "shade_refined", None)
        if fused is not None and len(points) and len(lights):
            geo = np.asarray(normals if geometric is None else geometric)
            reach = float(getattr(self.approx, "blind_reach", lambda _: 0.0)(level))
            near = near_points(self.exact, points, geo, reach) if reach > 0 else None
            try:
                result, counts = fused(points, normals, albedo, lights, progress, level=level, near=near,
                                       resolve=self._resolver(points, geo, lights, reach), **options)
            except NotImplementedError:
                pass
            else:
                self._count("queries", counts["queries"])
                self._count("refined", counts["uncertain"])
                self._count("near", counts["near"])
                return result
        if LIGHT_MAJOR in self.capabilities:
            from usdml.scene import LightType

            answers = self.occluded_matrix(points, geometric if geometric is not None else normals, lights.position,
                                           lights.type == LightType.DISTANT, lights.axis)
            return plain(points, normals, albedo, lights, None, progress, answers=answers, **options)
        return plain(points, normals, albedo, lights, self.occluded, progress, **options)

    def _resolver(self, points: np.ndarray, normals: np.ndarray, lights, reach: float):
        """``resolve(point, light, kind) -> free`` for a fused kernel's handed-back pairs: kind 0 (uncertain) traced
        exactly, kind 1 (certain and free, from a point with geometry in its blind zone) over the blind zone."""
        from usdml.scene import LightType

        distant_light = np.asarray(lights.type == LightType.DISTANT)
        axis = np.asarray(lights.axis, np.float64)
        toward = np.where(distant_light[:, None], -axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True),
                                                                     1e-30), np.asarray(lights.position, np.float64))
        points = np.asarray(points)

        def resolve(point: np.ndarray, light: np.ndarray, kind: np.ndarray) -> np.ndarray:
            free = np.ones(len(point), bool)
            for k in (0, 1):
                rows = np.flatnonzero(kind == k)
                if not len(rows):
                    continue
                at, li = point[rows], light[rows]
                o = np.take(points, at, axis=0).astype(np.float64)
                t = np.take(toward, li, axis=0)
                d = distant_light[li]
                nrm = np.take(normals, at, axis=0)
                if k == 1:
                    t, d = _short(o, t, d, reach), np.zeros(len(rows), bool)
                free[rows] = ~self.exact.occluded(o, t, normals=nrm, distant=d)
            return free
        return resolve
