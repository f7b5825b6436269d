"""The one interface every visibility backend implements: "is the segment P → L blocked?".

A backend owns its acceleration structures and rebuilds them per frame from a
:class:`usdml.scene.Snapshot` (``update``), then answers batches of shadow-ray queries
(``occluded`` for arbitrary pairs, ``occluded_matrix`` for all points × all lights, the loop of
paper 000, Alg. 3, lines 2-9).

Conventions shared by all backends:

* Positions are world space, scene units; ``(N, 3)`` float32 or float64 in, float64 math inside.
* A point light ``L`` is a segment end: geometry beyond ``L`` never blocks it.
* A distant light is a direction: for a ``distant`` row the target is the unit direction *toward*
  the light and the ray runs to infinity. In ``occluded_matrix`` distant lights are given by
  ``light_directions``, the direction the light *travels* (``Lights.axis``), so the shadow ray goes
  along ``-light_directions``.
* Answers are deterministic: the same snapshot and queries give the same booleans.

Building a backend
    ``cls.from_settings(settings, device, **options)`` (what :func:`usdml.visibility.make_backend`
    calls) builds a backend from a :class:`usdml.settings.UsdmlSettings` (``None``: the backend's
    defaults), reading only the fields it has; keyword ``options`` override them. Every backend's
    ``from_settings`` accepts ``report`` (``report(line)``: one line before something costly is
    built) and ``progress`` (``progress(done, total, label, unit)`` while building), and may ignore
    them. The default builds ``cls(**options)``: settings and device ignored.

Optional capabilities
    A backend declares what it implements beyond the queries in ``capabilities`` (a frozenset of the
    names below); callers ask :meth:`VisibilityBackend.supports` instead of probing attributes. Each
    capability's method exists on every backend, with the documented default for those that do
    not declare it:

    ``SHADE_DIRECT`` ("shade_direct")
        :meth:`~VisibilityBackend.shade_direct` is the backend's own one-kernel Alg. 3 (paper 000),
        equal to :func:`usdml.lighting.direct.shade_direct` over :meth:`~VisibilityBackend.occluded`
        within float32 rounding, returning a :class:`DirectResult`. The lighting layer chooses:
        :func:`usdml.lighting.direct.shade_with` calls this kernel hook where the backend declares it,
        handing it the plain shading (``plain``) for what the kernel does not fuse, and shades over
        ``occluded`` otherwise. It takes the preview surface's material rows (``material=``), summing both
        lobes in the kernel or handing them to ``plain``. Default: ``NotImplementedError``.
    ``HIT_DISTANCES`` ("hit_distances")
        :meth:`~VisibilityBackend.hit_distances`: per query, the distance from the ray's start to its
        first hit in the backend's own units (``-1``: free; ``>= 0`` exactly where ``occluded``), for
        ``usdml compare``'s near/far split. Default: ``NotImplementedError``.
    ``STATS`` ("stats")
        ``stats``: a dict of counters of the last :meth:`~VisibilityBackend.update` (builds, bytes,
        seconds), :meth:`~VisibilityBackend.describe`: the backend-specific fields ``usdml bench`` and
        ``usdml compare`` add to their results, and :meth:`~VisibilityBackend.per_frame_rebuild_seconds`
        (``usdml bench``). Default: an empty ``stats``, ``{}``, ``{}``.
    ``MEMORY_ESTIMATE`` ("memory_estimate")
        classmethods :meth:`~VisibilityBackend.memory_estimate` (what a snapshot would cost at some
        settings, a JSON-able dict with ``totalBytes``, before anything is built; with
        ``upperBound: true`` where the size depends on what is built and the figure is a bound) and
        :meth:`~VisibilityBackend.memory_line` (it as the one line ``usdml info`` prints).
        Default: ``None`` and ``""``.
    ``LIGHT_MAJOR`` ("light_major")
        The backend's structures are per light (paper 001's shadow maps): its
        :meth:`~VisibilityBackend.occluded_matrix` answers every point against every light far faster
        than :meth:`~VisibilityBackend.occluded` over the same pairs cut into blocks of points, so a
        caller holding a point set and a light set (``usdml compare``) asks it for the whole matrix.
        Default: ``occluded_matrix`` over ``occluded``, no faster.
    ``BAKE`` ("bake")
        ``usdml bake --backend NAME`` (whose choices are the backends declaring it): the backend caches what
        it builds from the stage. Classmethod :meth:`~VisibilityBackend.bake_skip` says why some settings
        leave nothing to cache, and :meth:`~VisibilityBackend.baked`, after the updates over the frames,
        what was built or loaded. Default: ``None``; ``NotImplementedError``.
    ``REFINE`` ("refine")
        :meth:`~VisibilityBackend.occluded_uncertain`: each answer and whether it is *certain*, by a rule of
        the method's own geometry, widened by ``level`` (1: the narrowest, up to ``refine_levels``);
        :class:`usdml.visibility.refine.Refined` re-asks the uncertain ones of the exact backend
        (``--error-budget``). Default: ``NotImplementedError``.

Adding a backend
    One module with a :class:`VisibilityBackend` subclass (``name``, ``summary``, ``capabilities``, and
    ``from_settings`` when it reads settings or runs on a device), one line in
    :data:`usdml.visibility.registry.BACKENDS`, and its mismatch bound against ``exact`` in
    ``tests/test_backends.py``, which runs every registered backend on the same scenes.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from types import MappingProxyType
from typing import Callable, Mapping

import numpy as np

from usdml.scene import Changes, Snapshot
from usdml.settings import UsdmlSettings

__all__ = ["VisibilityBackend", "baked_entry", "baked_line", "settings_with", "CAPABILITIES", "SHADE_DIRECT", "HIT_DISTANCES", "STATS", "MEMORY_ESTIMATE",
           "LIGHT_MAJOR", "REFINE", "DirectResult"]

#: optional capabilities (module doc, "Optional capabilities")
SHADE_DIRECT = "shade_direct"
HIT_DISTANCES = "hit_distances"
STATS = "stats"
MEMORY_ESTIMATE = "memory_estimate"
LIGHT_MAJOR = "light_major"
BAKE = "bake"
REFINE = "refine"
CAPABILITIES = (SHADE_DIRECT, HIT_DISTANCES, STATS, MEMORY_ESTIMATE, LIGHT_MAJOR, BAKE, REFINE)


@dataclass
class DirectResult:
    """Direct light of ``P`` points (paper 000 Alg. 3): what :func:`usdml.lighting.direct.shade_direct` and
    a ``SHADE_DIRECT`` backend's fused kernel return."""

    radiance: np.ndarray    #: (P, 3) float32 outgoing radiance ρ/π·ΣE over visible lights (+ specular)
    shadow: np.ndarray      #: (P,) float32 blocked / facing, 0 where no light faces
    facing: np.ndarray      #: (P,) int32 number of lights facing each point
    queries: int            #: shadow queries asked of the backend
    #: (P, 3) float32 the specular part of ``radiance`` (ΣE·ks, ``kernels/brdf``) when shaded with material
    #: rows, else None (Lambertian: all of ``radiance`` is diffuse)
    specular: np.ndarray | None = None
    #: (P,) float32 variance of the luminance of ``radiance`` from sampling lights with area
    #: (:func:`usdml.lighting.area.shading.shade_area`), None where no light was sampled
    variance: np.ndarray | None = None
    #: light group -> (P, 3) float32 the part of ``radiance`` its lights give (``lightgroup:`` AOVs), or None
    groups: dict[str, np.ndarray] | None = None


def as_vectors(a, name: str, n: int | None = None, dtype=np.float64) -> np.ndarray:
    """``a`` as an ``(n, 3)`` array of ``dtype`` (``None``: keep float32/float64, else float64);
    ``ValueError`` naming ``name`` when the shape is wrong."""
    a = np.asarray(a)
    if dtype is not None or a.dtype not in (np.float32, np.float64):
        a = a.astype(dtype or np.float64, copy=False)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and a.shape[0] != n):
        want = f"({n}, 3)" if n is not None else "(N, 3)"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    return a


def as_flags(a, name: str, n: int) -> np.ndarray:
    """``a`` as an ``(n,)`` bool array."""
    a = np.asarray(a, dtype=bool)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    return a


def static_members(snapshot: Snapshot) -> tuple:
    """``("mesh" | "proto", path)`` of the geometry that never changes over the shot: meshes that do not
    deform and prototypes whose instances neither move nor deform (built once, in world space)."""
    return tuple([("mesh", m.path) for m in snapshot.meshes if not m.deforming]
                 + [("proto", p.path) for p in snapshot.prototypes if not (p.animated or p.deforming)])


def all_members(snapshot: Snapshot) -> tuple:
    """``("mesh" | "proto", path)`` of every mesh and prototype of ``snapshot``, for
    :func:`usdml.scene.world_geometry`: the whole scene flattened."""
    return tuple([("mesh", m.path) for m in snapshot.meshes] + [("proto", p.path) for p in snapshot.prototypes])


def members_changed(before, members: tuple, changes: Changes | None, mesh_changed) -> bool:
    """Whether a structure built from ``before`` (``("mesh" | "proto", path)`` members, None: not
    built) must be rebuilt for ``members``: no ``changes`` given, other members, a member prototype
    that ``changes`` names, or a member mesh for which ``mesh_changed(path)`` says so."""
    if before is None or changes is None or before != members:
        return True
    if any(changes.prototypes.get(path) for kind, path in members if kind == "proto"):
        return True
    return any(mesh_changed(path) for kind, path in members if kind == "mesh")


def scene_sphere(snapshot: Snapshot) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere around ``snapshot``'s world box: where a backend's distant
    rays end (``(0, 0, 0), 1`` for an empty scene)."""
    bounds = snapshot.world_bounds()
    if bounds is None:
        return np.zeros(3), 1.0
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def settings_with(settings, values: dict):
    """What a backend reads: ``settings`` (a :class:`usdml.settings.UsdmlSettings`; None: the parameter
    table's defaults) with ``values`` (settings fields by name) set, each checked by the table."""
    return (UsdmlSettings() if settings is None else settings).updated(**values)


def baked_entry(backend, kind: str, item, **fields) -> dict:
    """One structure ``usdml bake`` reports (``BAKE``): ``item`` (``source``, ``key``, ``nbytes``,
    ``build_seconds``, ``cached``) with the backend's ``fields``, and its file in the backend's cache under
    ``kind`` (None: not cached)."""
    return {"source": item.source, "key": item.key, "bytes": item.nbytes, **fields, "build_seconds": item.build_seconds,
            "loaded_from_cache": item.cached,
            "path": str(backend.cache.path(kind, item.key)) if backend.cache and item.key else None}


def baked_line(entry: dict, what: str, uncached: str) -> str:
    """``usdml bake``'s line for ``entry`` (:func:`baked_entry`): its source, ``what`` it is, built or found,
    and where it lies, else why not (``uncached``)."""
    how = "in cache" if entry["loaded_from_cache"] else f"built in {entry['build_seconds']:.1f} s"
    return f"{entry['source']}: {what}, {how}" + (f" -> {entry['path']}" if entry["path"] else f" ({uncached})")


class VisibilityBackend(abc.ABC):
    """Answers shadow-ray queries against the geometry of the last snapshot given to :meth:`update`."""

    #: registry name (``make_backend(name)``)
    name: str = ""
    #: how far (world units) a shadow ray's end on an emitting surface the backend holds (a mesh light's triangle)
    #: must be off it not to be blocked by that surface (:mod:`usdml.visibility.emitter_ends`); 0: exactly on it
    emitter_offset: float = 0.0
    #: optional capabilities it implements (module doc): a subset of ``CAPABILITIES``
    capabilities: frozenset[str] = frozenset()
    #: its constructor takes ``(settings, *, device, report, progress, **values)``: the settings it reads, those
    #: fields by name over them (:func:`settings_with`), and no defaults of its own
    reads_settings: bool = False
    #: one line saying what the backend is (``usdml info`` lists every registered backend with it)
    summary: str = ""
    #: counters of the last update (``STATS``); backends that declare it set their own dict
    stats: Mapping = MappingProxyType({})
    #: ``REFINE``: how many times :meth:`occluded_uncertain`'s rule can be widened (levels 1 .. this)
    refine_levels: int = 0
    #: ``REFINE``: per level (1, 2, ...), a lower bound on what one query costs by the level's rule alone, in
    #: exact shadow rays, where the backend has one that held on every stage measured (empty: none). Under
    #: ``--error-budget`` a level costing an exact ray or more is not used: exact alone is faster
    #: (:mod:`usdml.render.budget`)
    refine_costs: tuple[float, ...] = ()
    #: point-light pairs handed to one :meth:`occluded` call by :meth:`occluded_matrix`; bounds its
    #: temporary memory (about 200 bytes per pair, so ~200 MB at 2^20)
    matrix_chunk_pairs: int = 1 << 20

    @classmethod
    def from_settings(cls, settings=None, device: str = "cpu", *, report: Callable[[str], None] | None = None,
                      progress: Callable[..., None] | None = None, **options) -> "VisibilityBackend":
        """A backend configured from ``settings`` (a :class:`usdml.settings.UsdmlSettings`, or ``None``
        for defaults) on Warp ``device``, keyword ``options`` overriding them (module doc). The default:
        ``cls(settings, device=device, report=report, progress=progress, **options)`` for a backend that
        ``reads_settings``, else ``cls(**options)`` (no settings of its own, nothing to report, one device)."""
        if cls.reads_settings:
            return cls(settings, device=device, report=report, progress=progress, **options)
        return cls(**options)

    @classmethod
    def supports(cls, capability: str) -> bool:
        """Whether the backend declares optional ``capability`` (one of ``CAPABILITIES``)."""
        if capability not in CAPABILITIES:
            raise ValueError(f"unknown backend capability {capability!r}; one of {', '.join(CAPABILITIES)}")
        return capability in cls.capabilities

    @classmethod
    def bake_skip(cls, settings) -> tuple[str, dict] | None:
        """``BAKE``: why ``settings`` leave nothing to cache (a line for stderr, the fields ``--json`` adds),
        or None."""
        return None

    def baked(self) -> tuple[dict, list[str], str]:
        """``BAKE``: what the updates so far built or loaded, before :meth:`close`: the fields ``usdml bake
        --json`` prints, a line per structure and the summary line (``... in N s`` follows)."""
        raise NotImplementedError(f"the {self.name} backend bakes nothing")

    @classmethod
    def memory_estimate(cls, snapshot: Snapshot, settings) -> dict | None:
        """``MEMORY_ESTIMATE``: what the structures for ``snapshot`` at ``settings`` would take, as a
        JSON-able dict holding ``totalBytes`` (bytes), said before anything is built; ``None`` when the
        backend does not estimate it."""
        return None

    @classmethod
    def memory_line(cls, estimate: dict) -> str:
        """``MEMORY_ESTIMATE``: :meth:`memory_estimate`'s result as one line of ``usdml info``."""
        return ""

    @classmethod
    def cpu_path(cls) -> str:
        """How this backend runs on this machine's CPU, one line of ``usdml info`` (which kernels, which
        instruction set); ``""`` when there is nothing to say."""
        return ""

    def describe(self) -> dict:
        """``STATS``: backend-specific fields for ``usdml bench`` / ``usdml compare`` results (JSON-able),
        after :meth:`update`; ``{}`` by default."""
        return {}

    def per_frame_rebuild_seconds(self, snapshot: Snapshot, repeats: int = 3) -> dict:
        """``STATS``: timings of rebuilding what the backend rebuilds every frame of ``snapshot``
        (``usdml bench``), after :meth:`update`; ``{}`` when it rebuilds nothing per frame."""
        return {}

    @abc.abstractmethod
    def update(self, snapshot: Snapshot, changes: Changes | None = None) -> None:
        """Bring the acceleration structures to ``snapshot``.

        ``changes`` is ``usdml.scene.diff(previous, snapshot)``; ``None`` means rebuild everything.
        Implementations rebuild only what ``changes`` names.
        """

    @abc.abstractmethod
    def occluded(self, origins: np.ndarray, targets: np.ndarray, *,
                 normals: np.ndarray | None = None, distant: np.ndarray | None = None) -> np.ndarray:
        """Whether each segment ``origins[i] → targets[i]`` is blocked.

        Parameters
        ----------
        origins : (N, 3) float32 or float64
            Surface points P, world space.
        targets : (N, 3) float64
            Light positions L; for rows where ``distant[i]`` the unit direction toward the light.
        normals : (N, 3) float, optional
            Surface normals at P (either orientation; zero rows mean "no normal"). Backends use them
            to leave the surface without self-occlusion.
        distant : (N,) bool, optional
            Rows whose target is a direction to infinity.

        Returns
        -------
        (N,) bool
            True where the segment is blocked.
        """

    def occluded_matrix(self, points: np.ndarray, normals: np.ndarray | None, light_positions: np.ndarray,
                        light_distant: np.ndarray | None = None,
                        light_directions: np.ndarray | None = None) -> np.ndarray:
        """Visibility of every light from every point (paper 000, Alg. 3, lines 2-9).

        Parameters
        ----------
        points : (P, 3) float
            Surface points, world space.
        normals : (P, 3) float or None
            Normals at ``points``.
        light_positions : (L, 3) float
            Light positions (ignored for distant lights).
        light_distant : (L,) bool, optional
            Lights that are directions (``LightType.DISTANT``).
        light_directions : (L, 3) float, optional
            Direction each light travels (``Lights.axis``); required where ``light_distant``.

        Returns
        -------
        (P, L) bool
            True where light ``j`` is blocked from point ``i``.

        Calls :meth:`occluded` on row blocks of at most ``matrix_chunk_pairs`` pairs, so memory
        stays bounded whatever P × L is.
        """
        points = as_vectors(points, "points")
        n_p = points.shape[0]
        normals = None if normals is None else as_vectors(normals, "normals", n_p)
        targets = as_vectors(light_positions, "light_positions").copy()
        n_l = targets.shape[0]
        out = np.zeros((n_p, n_l), bool)
        if n_p == 0 or n_l == 0:
            return out
        distant = np.zeros(n_l, bool) if light_distant is None else as_flags(light_distant, "light_distant", n_l)
        if distant.any():
            if light_directions is None:
                raise ValueError("light_directions is required for distant lights")
            axis = as_vectors(light_directions, "light_directions", n_l)[distant]
            targets[distant] = -axis / np.linalg.norm(axis, axis=1, keepdims=True)
        cols = min(n_l, self.matrix_chunk_pairs)
        rows = max(1, self.matrix_chunk_pairs // cols)
        for p0 in range(0, n_p, rows):
            p1 = min(n_p, p0 + rows)
            for l0 in range(0, n_l, cols):
                l1 = min(n_l, l0 + cols)
                k, m = p1 - p0, l1 - l0
                out[p0:p1, l0:l1] = self.occluded(
                    np.repeat(points[p0:p1], m, axis=0),
                    np.tile(targets[l0:l1], (k, 1)),
                    normals=None if normals is None else np.repeat(normals[p0:p1], m, axis=0),
                    distant=np.tile(distant[l0:l1], k),
                ).reshape(k, m)
        return out

    def hit_distances(self, origins: np.ndarray, targets: np.ndarray, *, normals: np.ndarray | None = None,
                      distant: np.ndarray | None = None) -> np.ndarray:
        """``HIT_DISTANCES``: ``(N,) float`` distance from each ray's start to its first hit (the
        backend's units; ``-1``: free), ``>= 0`` exactly where :meth:`occluded` is True. Arguments as
        :meth:`occluded`. Backends that do not declare it raise ``NotImplementedError``."""
        raise NotImplementedError(f"the {self.name or type(self).__name__} backend does not report hit distances")

    def occluded_uncertain(self, origins: np.ndarray, targets: np.ndarray, *, normals: np.ndarray | None = None,
                           distant: np.ndarray | None = None, level: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``REFINE``: ``(blocked, uncertain)``, two ``(N,) bool``: :meth:`occluded`'s answers (the same
        booleans) and where each may be wrong by the backend's own rule at ``level`` (1 the narrowest, up to
        ``refine_levels``; a higher level flags a superset). Arguments as :meth:`occluded`. Backends that do
        not declare it raise ``NotImplementedError``."""
        raise NotImplementedError(f"the {self.name or type(self).__name__} backend does not say which answers are uncertain")

    def refine_cost(self, level: int) -> float:
        """``REFINE``: :attr:`refine_costs` at ``level`` (the last one beyond them; 0 where none is declared)."""
        if level < 1 or not self.refine_costs:
            return 0.0
        return float(self.refine_costs[min(level, len(self.refine_costs)) - 1])

    def shade_direct(self, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray, lights,
                     progress: Callable[[int], None] | None = None, meters_per_unit: float = 1.0,
                     min_distance: float = 0.0, geometric: np.ndarray | None = None,
                     material: np.ndarray | None = None, *, plain: Callable[..., DirectResult]) -> DirectResult:
        """``SHADE_DIRECT``: direct lighting of ``points`` by every light (paper 000 Alg. 3) in the backend's
        own fused kernel, arguments as :func:`usdml.lighting.direct.shade_direct` (``material``: the preview
        surface's rows, None: Lambertian); ``plain`` is that function, for what the kernel does not fuse (a
        backend whose kernel does not sum the BRDF hands material rows to ``plain`` over its ``occluded``). Callers go through
        :func:`usdml.lighting.direct.shade_with`, which shades over :meth:`occluded` where the backend does
        not declare it; backends that do not raise ``NotImplementedError``."""
        raise NotImplementedError(f"the {self.name or type(self).__name__} backend has no fused direct shading")

    def close(self) -> None:
        """Release threads and native memory; the backend needs :meth:`update` again afterwards."""

    def __enter__(self) -> "VisibilityBackend":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
