"""Light linking, shadow linking, light groups and per-lobe light factors in every direct-light path, by classes.

A frame's lights fall into *classes*: the lights that share a light-link set, a shadow-link set, a light group
(when ``lightgroup:`` AOVs are asked for) and lobe factors (:class:`usdml.scene.Lights`). Classes that differ in
their light-link set only form a *bundle*, and a bundle's points are split by which of its classes reach them
(:func:`shading_units`): each such part is shaded once, by the union of those classes' lights, with the
integrator's own method (every light with any backend's fused kernel, or a hierarchy over that union), with the
shadows of the geometry the bundle's shadow set includes (:class:`LinkedShadows`: the frame's backends built again
over that geometry); the parts' direct light is summed. Direct light is a sum over lights, so this is the frame's
light exactly. A point that every light set reaches is shaded in one call over all the lights, as if nothing were
linked: two light-link sets over the same pixels cost one gather, not two (``tools/linking_cost.py``).

A frame whose lights are all one class of every prim, no group asked and factors (1, 1) — every stage that
authors none of it — is shaded in one call, as before.

Lobe factors: a class whose factors are not (1, 1) is shaded once and its result's diffuse part
(``radiance − specular``) and specular part scaled apart (``inputs:diffuse`` / ``inputs:specular``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from usdml.scene import Lights, Snapshot, diff
from usdml.scene.linking import EVERY_PRIM, LinkSets, group_of
from usdml.visibility.base import DirectResult

__all__ = ["LightClass", "LinkedShadows", "light_classes", "shade_classes", "shading_units"]


@dataclass
class LightClass:
    """Lights shaded together (module doc): their indices in the frame's lights, and what they share."""

    index: np.ndarray
    light_link: int = EVERY_PRIM
    shadow_link: int = EVERY_PRIM
    group: str = ""
    diffuse: float = 1.0
    specular: float = 1.0

    @property
    def plain(self) -> bool:
        """Shaded as every light used to be: every prim, both lobes at the stored radiance."""
        return (self.light_link == EVERY_PRIM and self.shadow_link == EVERY_PRIM
                and self.diffuse == 1.0 and self.specular == 1.0)


def light_classes(lights: Lights, groups: bool) -> list[LightClass]:
    """The classes of ``lights`` in order of first appearance; ``groups``: split by light group too (every
    light's group is then named, :func:`usdml.scene.linking.group_of`)."""
    n = len(lights)
    if n == 0:
        return []
    names: list[str] = [""]
    code = np.zeros(n, np.float64)
    if groups:
        index: dict[str, int] = {}
        code = np.fromiter((index.setdefault(group_of(g), len(index)) for g in lights.group), np.float64, n)
        names = list(index)
    keys = np.stack([lights.light_link, lights.shadow_link, code, lights.diffuse, lights.specular], axis=1)
    if (keys == keys[0]).all():
        rows, inverse = keys[:1], np.zeros(n, np.int64)
    else:
        rows, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rows, inverse = rows[order], np.argsort(order)[inverse.ravel()]
    members = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[members], np.arange(len(rows) + 1))
    return [LightClass(members[bounds[k]:bounds[k + 1]], int(r[0]), int(r[1]), names[int(r[2])], float(r[3]),
                       float(r[4])) for k, r in enumerate(rows)]


class LinkedShadows:
    """The shadow backends of a frame's shadow-link sets: one :class:`usdml.render.backends.Backends` (its own exact
    and configured backends, refined under ``--error-budget``) per set, over the geometry the set includes, made
    the first time a set appears (keyed by its collection's name) and updated every frame with what changed."""

    def __init__(self, make: Callable[[], object]):
        self._make = make
        self._sets: dict[str, list] = {}     # name -> [Backends, the filtered snapshot it was last updated to]
        self._current: dict[int, object] = {}

    def update(self, snap: Snapshot, lights: Lights) -> float:
        """Bring the backends of the shadow sets ``lights`` use to ``snap``; returns the seconds spent."""
        import time as _time

        t0 = _time.perf_counter()
        self._current = {}
        links: LinkSets | None = snap.links
        for link in sorted(set(lights.shadow_link.tolist()) - {EVERY_PRIM}):
            name = links.names[link]
            if name not in self._sets:
                self._sets[name] = [self._make(), None]
            entry = self._sets[name]
            filtered = links.filtered(snap, link)
            entry[0].update(filtered, diff(entry[1], filtered))
            entry[1] = filtered
            self._current[link] = entry[0]
        return _time.perf_counter() - t0

    def backends(self, link: int, every_prim):
        """The :class:`Backends` of shadow set ``link`` this frame; ``every_prim`` (the frame's own) for -1."""
        return every_prim if link == EVERY_PRIM else self._current[link]

    def refine_like(self, refined) -> None:
        """``--error-budget``: every shadow set's refined backend at the level chosen for the frame's own
        (:func:`usdml.render.budget.choose_level` measures the frame's lights against every prim's shadows)."""
        for backends in self._current.values():
            if backends.refined is not None:
                backends.refined.level = refined.level

    def close(self) -> None:
        for backends, _ in self._sets.values():
            backends.close()
        self._sets.clear()
        self._current = {}


def shading_units(classes: list[LightClass], members: Callable[[int], np.ndarray]) -> list[tuple[tuple[int, ...], np.ndarray]]:
    """How a frame's points are shaded (module doc): ``(class indices, points)`` pairs, each the points (a boolean
    mask) reached by exactly those classes of a bundle (classes that differ in their light-link set only: one
    shadow set, group and lobe factors), shaded together by the union of their lights. A point every class of a
    bundle reaches is one call over all of them, as if nothing were linked."""
    bundles: dict[tuple, list[int]] = {}
    for k, c in enumerate(classes):
        bundles.setdefault((c.shadow_link, c.group, c.diffuse, c.specular), []).append(k)
    reach: dict[int, np.ndarray] = {}
    units = []
    for ks in bundles.values():
        rows = np.stack([reach.setdefault(classes[k].light_link, members(classes[k].light_link)) for k in ks])
        signature = np.packbits(rows, axis=0, bitorder="little")      # (ceil(B/8), n)
        keys, inverse = np.unique(signature, axis=1, return_inverse=True)
        inverse = inverse.ravel()
        for j in range(keys.shape[1]):
            bits = np.unpackbits(keys[:, j], bitorder="little")[:len(ks)].astype(bool)
            if bits.any():
                units.append((tuple(k for k, b in zip(ks, bits) if b), inverse == j))
    return units


def shade_classes(classes: list[LightClass], n_points: int, members: Callable[[int], np.ndarray],
                  shade: Callable[[tuple[int, ...], np.ndarray], DirectResult], groups: bool) -> DirectResult:
    """The direct light of ``n_points`` points by ``classes``: ``shade(ks, points)`` for each of
    :func:`shading_units` (classes ``ks``; the points, a boolean mask, they reach), lobe factors applied, summed;
    ``groups``: the result's :attr:`DirectResult.groups` holds each group's radiance."""
    radiance = np.zeros((n_points, 3), np.float32)
    specular = None
    blocked = np.zeros(n_points, np.float64)
    facing = np.zeros(n_points, np.float64)
    kind = np.int32        # facing's type: counts, or the hierarchy's fractional ones
    queries = 0
    by_group: dict[str, np.ndarray] = {}
    variance = None
    for ks, sel in shading_units(classes, members):
        cls = classes[ks[0]]
        r = shade(ks, sel)
        part, spec = _lobes(r, cls)
        if r.variance is not None:      # independent samples: variances add (a lobe factor scales its part's)
            variance = np.zeros(n_points, np.float32) if variance is None else variance
            variance[sel] += r.variance * np.float32(max(cls.diffuse, cls.specular) ** 2)
        radiance[sel] += part
        if spec is not None:
            specular = np.zeros((n_points, 3), np.float32) if specular is None else specular
            specular[sel] += spec
        blocked[sel] += r.shadow * r.facing
        facing[sel] += r.facing
        kind = np.result_type(kind, r.facing.dtype)
        queries += r.queries
        if groups:
            g = by_group.setdefault(cls.group, np.zeros((n_points, 3), np.float32))
            g[sel] += part
    shadow = np.where(facing > 0, blocked / np.maximum(facing, 1), 0.0).astype(np.float32)
    return DirectResult(radiance, shadow, facing.astype(kind), queries, specular,
                        groups=by_group if groups else None, variance=variance)


def _lobes(r: DirectResult, cls: LightClass) -> tuple[np.ndarray, np.ndarray | None]:
    """``(radiance, specular)`` of a class's result with its lobe factors applied."""
    if cls.diffuse == 1.0 and cls.specular == 1.0:
        return r.radiance, r.specular
    if r.specular is None:
        return r.radiance * np.float32(cls.diffuse), None
    spec = r.specular * np.float32(cls.specular)
    return (r.radiance - r.specular) * np.float32(cls.diffuse) + spec, spec
