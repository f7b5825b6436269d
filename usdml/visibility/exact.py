"""The ``exact`` visibility backend: Embree (through ``embreex``), the reference every other backend is tested against.

Geometry
    embreex has no instancing API, so prototype instances are flattened into world-space triangles.
    The snapshot is split in two Embree scenes:

    * **static**: non-deforming meshes and prototypes that are neither ``animated`` nor ``deforming``;
    * **dynamic**: deforming meshes and animated / deforming prototypes.

    Each scene holds ONE indexed Embree triangle mesh, all its sources merged (a 1000-geometry scene
    built no faster than one merged geometry here, and one geometry keeps the per-instance Python
    overhead out of the build). ``update`` rebuilds a scene only when ``changes`` names one of its
    members, so a camera fly-through or light animation never rebuilds anything and an animated
    prototype never rebuilds the static city. An embreex scene is immutable once committed
    (geometry added after the first ``run`` is silently ignored: measured), hence two scenes rather
    than one that would be rebuilt whole every frame. A query traverses the static scene first and
    sends only the rays still unblocked to the dynamic one (OCCLUDED = OR of both scenes;
    INTERSECT = the nearer hit, the static ``t`` clipping the dynamic ray).

Cost of flattening (measured on this 2-core machine, AMD EPYC, shared)
    Memory: the merged vertex + index arrays are ``V × 12 + T × 12`` bytes per scene while building
    (at most ``T × 9 floats × 4 bytes`` = 36 B per triangle, a triangle soup), freed once Embree has
    copied them (embreex copies into Embree-owned buffers: measured), plus Embree's own copy and BVH:
    max RSS grew ~100 MB for 240k flattened triangles. Every instance costs its full triangle count:
    2000 instances of a 240-triangle prototype cost what 480k unique triangles cost.
    Build time (flatten + embreex add + BVH commit): 2000 instances × 240 triangles = 480k triangles:
    0.07 + 0.23 + 0.12-0.16 s ≈ 0.45 s; a 277k-triangle city of boxes 0.45 s, 560k 1.2 s; 500k
    random overlapping triangles 0.45 s add + 0.25 s commit. Adding is embreex's per-element copy
    loop (~0.5-1 µs per triangle); the BVH build is Embree's, multi-threaded. An animated prototype
    therefore costs ~1 µs per flattened triangle per frame, and only it is rebuilt.

Robust segment ends (no shadow acne, no light leaking through the far end)
    ``eps(P) = max(epsilon, |P|_max · 2^-20)`` with ``epsilon = rel_epsilon × scene bounding-box
    diagonal`` (``rel_epsilon = 1e-5``: the float term alone already prevents acne; measured on a city, 0.48 % of unit-normal-offset rays blocked at 1e-5 and 1e-7 alike) unless given. The float term is 8 float32 ulps of the
    coordinate, what Embree's single-precision traversal can be off by.

    * With a normal: the origin moves ``eps(P)`` along the normal flipped toward the light, and the
      ray aims from there to L. A point of a closed surface lit from behind therefore starts inside
      and is blocked by the far side; an open sheet lit from behind is visible (the shading cosine,
      not visibility, darkens it).
    * Without a normal (or a zero one): the origin moves ``eps(P)`` along the ray.
    * The segment stops ``eps(L)`` short of a point light, so geometry the light sits on does not
      block it. Segments shorter than the two epsilons are reported unblocked. Distant rays end at
      infinity.

    Cost: blockers closer than ``eps`` to either end are missed. A plate hovering less than ``eps``
    above the ground casts no shadow on the ground right under it (contact shadows closer than
    ``eps`` leak); a segment that crosses a surface within ``eps`` of P or L is reported unblocked.
    Where a box stands on the ground, ground points outside the box stay correctly shadowed by its
    walls (the origin rises ``eps`` but the wall starts at the ground), and ground points under the
    box start inside it and are blocked. Measured on the city below (diagonal 216 units, |P| ≤ 140):
    rays from 400k surface points to lights 0.05 units out along their normals are blocked 0.48 %
    of the time with ``rel_epsilon`` 1e-7, 1e-6 or 1e-5 alike (the float term alone prevents acne;
    those hits are real geometry: fins and balconies cut into walls) and 0.085 % at the default
    1e-4, i.e. the default hides real occluders within 0.02 units. Lower ``rel_epsilon`` where
    contact shadows matter more than margin for error.

Parallelism
    embreex releases the GIL inside ``run``, so batches are cut into ``chunk_rays`` rays and run on a
    persistent ``ThreadPoolExecutor`` with one worker per core (``usdml.parallel.cpu_workers``; kept
    across calls, as a frame makes many); the epsilon arithmetic of a chunk runs in its worker too.
    :meth:`ExactBackend.shadow_rays` states it in NumPy (the rule, and its reference); ``occluded``
    runs the same float32 operations compiled (``usdml.kernels.shadow_rays``, one Warp CPU launch per
    chunk, which releases the GIL): the same rays bit for bit, tested. In NumPy the rule took ~60
    passes per chunk and cost 28 % on top of bare Embree on the city bench (7.3 M rays, 2 threads:
    1.30 s against 1.02 s); compiled, 4-5 % (1.07 against 1.01 s, same process, medians of 3). Chunks
    write to fixed slices of the output, so results do not depend on thread timing.
    Measured: 277k-triangle city (14 × 14 boxy buildings, facades split 9 × 9, 20 thin fins and
    balconies each, on a ground slab), 1M shadow rays from random surface points (with normals) to
    random lights 5-40 units above the roofs, 85 % blocked, chunk 65536, in windows where no other
    process used the CPU: ``occluded`` 1 worker 2.6-3.4 M rays/s, 2 workers 5.3-6.3 M rays/s
    (≈ 1.9× scaling); bare ``run`` on the same rays 3.3-3.9 (1 thread) and 6.9-8.5 (2 threads)
    M rays/s, so the epsilon arithmetic and gathers cost ~20 % (in NumPy, before the compiled
    ray set-up above). These random, incoherent rays are a
    worst case; DESIGN.md's ≈ 7 M rays/s per core was measured on another city and ray set.
    See ``ExactBackend.stats`` for per-scene triangle counts and build times.

Embree facts this module relies on (checked by experiment with embreex 4.4)
    ``run(o, d, query='OCCLUDED', dists=tfar)`` returns int32 per ray: ``-1`` unblocked, ``0`` blocked
    (not a geometry id); a negative ``tfar`` reports "blocked", so rays of no length are never sent.
    ``query='INTERSECT', output=1`` writes ``tfar`` back into the ``dists`` array and returns
    ``geomID``/``primID`` ``-1`` on a miss; ``u, v`` weight vertices 1 and 2; ``Ng`` is
    ``(v1 - v0) × (v2 - v0)`` unnormalised. Origins and directions must be float32.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple
import time

import numpy as np

from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers
from usdml.scene import Changes, Mesh, Prototype, Snapshot, world_geometry
from usdml.scene.cutout import has_see_through, see_through
from usdml.scene.hashing import GOLDEN, fold_bits, mix, unit
from usdml.visibility.base import STATS, VisibilityBackend, as_flags, as_vectors, members_changed, static_members

try:
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh
except ImportError:     # optional dependency: the other backends work without it
    rtcs = TriangleMesh = None

__all__ = ["ExactBackend", "GeometrySource", "SourceTable"]

#: relative float32 precision margin: 8 ulps of a coordinate
FLOAT_MARGIN = 2.0 ** -20
#: holes a ray passes through (cutouts, opacityThreshold) before it is taken to have missed
CUTOUT_LAYERS = 64


class GeometrySource(NamedTuple):
    """Where one ``geom`` id of :meth:`ExactBackend.intersect` comes from."""

    mesh: int           #: index into ``Snapshot.meshes``, -1 for instanced geometry
    prototype: int      #: index into ``Snapshot.prototypes``, -1 for a plain mesh
    instance: int       #: instance index within the prototype (row of ``xforms``), -1 for a plain mesh
    proto_mesh: int     #: index into ``Prototype.meshes``, -1 for a plain mesh
    prim_id: int        #: ``Mesh.id`` (the primId AOV)
    instance_id: int    #: ``Prototype.instance_ids[instance]`` (the instanceId AOV), -1 for a plain mesh

    def mesh_of(self, snapshot: Snapshot) -> Mesh:
        """The :class:`Mesh` whose ``triangles[prim]`` was hit (prototype space for instances)."""
        if self.mesh >= 0:
            return snapshot.meshes[self.mesh]
        return snapshot.prototypes[self.prototype].meshes[self.proto_mesh]


@dataclass
class SourceTable:
    """Flat description of the sources of one Embree scene, in the order their triangles were merged.

    All arrays are ``(S,)``; ``tri_offset`` is ``(S + 1,)`` int64, source ``s`` owns merged triangles
    ``tri_offset[s]:tri_offset[s + 1]``.
    """

    mesh: np.ndarray            #: int32
    prototype: np.ndarray       #: int32
    instance: np.ndarray        #: int32
    proto_mesh: np.ndarray      #: int32
    prim_id: np.ndarray         #: int32
    instance_id: np.ndarray     #: int64
    tri_offset: np.ndarray      #: int64

    @property
    def triangle_count(self) -> int:
        return int(self.tri_offset[-1])

    def __len__(self) -> int:
        return int(self.mesh.shape[0])

    @staticmethod
    def empty() -> "SourceTable":
        z = np.zeros(0, np.int32)
        return SourceTable(z, z, z, z, z, np.zeros(0, np.int64), np.zeros(1, np.int64))

    @staticmethod
    def concat(tables: list["SourceTable"]) -> "SourceTable":
        if not tables:
            return SourceTable.empty()
        cols = {k: np.concatenate([getattr(t, k) for t in tables])
                for k in ("mesh", "prototype", "instance", "proto_mesh", "prim_id", "instance_id")}
        offs, base = [np.zeros(1, np.int64)], 0
        for t in tables:
            offs.append(t.tri_offset[1:] + base)
            base += t.triangle_count
        return SourceTable(**cols, tri_offset=np.concatenate(offs))


def _source_table(snapshot: Snapshot, members: tuple[tuple[str, str], ...]) -> SourceTable:
    """Sources of ``members`` (``("mesh", path)`` / ``("proto", path)``): a mesh is one source, a
    prototype one per (mesh, instance), mesh-major, as :func:`usdml.scene.world_geometry` lays triangles out."""
    mesh_index = {m.path: i for i, m in enumerate(snapshot.meshes)}
    proto_index = {p.path: i for i, p in enumerate(snapshot.prototypes)}
    cols: dict[str, list] = {k: [] for k in ("mesh", "prototype", "instance", "proto_mesh", "prim_id",
                                             "instance_id", "tris")}
    for kind, path in members:
        if kind == "mesh":
            i = mesh_index[path]
            m = snapshot.meshes[i]
            for k, v in (("mesh", i), ("prototype", -1), ("instance", -1), ("proto_mesh", -1),
                         ("prim_id", m.id), ("instance_id", -1), ("tris", m.triangle_count)):
                cols[k].append(np.array([v], np.int64))
            continue
        pi = proto_index[path]
        p = snapshot.prototypes[pi]
        n = p.instance_count
        for k, m in enumerate(p.meshes):
            for key, v in (("mesh", np.full(n, -1)), ("prototype", np.full(n, pi)), ("instance", np.arange(n)),
                           ("proto_mesh", np.full(n, k)), ("prim_id", np.full(n, m.id)),
                           ("instance_id", np.asarray(p.instance_ids, np.int64).reshape(n)),
                           ("tris", np.full(n, m.triangle_count))):
                cols[key].append(np.asarray(v, np.int64))
    cat = {k: (np.concatenate(v) if v else np.zeros(0, np.int64)) for k, v in cols.items()}
    return SourceTable(
        mesh=cat["mesh"].astype(np.int32), prototype=cat["prototype"].astype(np.int32),
        instance=cat["instance"].astype(np.int32), proto_mesh=cat["proto_mesh"].astype(np.int32),
        prim_id=cat["prim_id"].astype(np.int32), instance_id=cat["instance_id"],
        tri_offset=np.concatenate([[0], np.cumsum(cat["tris"])]).astype(np.int64))


@dataclass
class _EmbreeGroup:
    """One committed Embree scene and what it was built from."""

    members: tuple[tuple[str, str], ...]
    scene: object | None            #: rtcs.EmbreeScene, None when there are no triangles
    table: SourceTable
    build_seconds: float = 0.0

    @property
    def triangle_count(self) -> int:
        return self.table.triangle_count


def _build_group(snapshot: Snapshot, members: tuple[tuple[str, str], ...], table: SourceTable) -> _EmbreeGroup:
    t0 = time.perf_counter()
    points, triangles = world_geometry(snapshot, members)
    scene = None
    if triangles.shape[0]:
        scene = rtcs.EmbreeScene()
        TriangleMesh(scene, points, triangles)
        # commit now, on this thread: embreex commits lazily inside the first run(), which would
        # race when several worker threads make that first call together
        scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")
    return _EmbreeGroup(members, scene, table, time.perf_counter() - t0)


def _abs_max(x: np.ndarray) -> np.ndarray:
    """``(n,)`` largest ``|coordinate|`` of ``(3, n)`` ``x``."""
    a = np.abs(x)
    return np.maximum(np.maximum(a[0], a[1]), a[2])


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(n,)`` dot products of ``(3, n)`` ``a`` and ``b``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _is_dynamic(p: Prototype) -> bool:
    return bool(p.animated or p.deforming)


class _RayKernel:
    """:meth:`ExactBackend.shadow_rays` of chunks of one batch, by the compiled kernel: inputs as the
    kernel reads them (float64 points, float32 or float64 targets as they come, float32 normals: the
    casts the rule makes) wrapped once per batch, rays written per chunk into fresh arrays (they stay in cache for Embree)."""

    def __init__(self, origins, targets, normals, distant, epsilon: float) -> None:
        from usdml.kernels import shadow_rays as kernels
        from usdml.kernels import warp

        wp = self.wp = warp()
        # float32 targets are read as they are, points as float64 (float32 -> float64 is exact, and the
        # kernel rounds back to the same float32): no float64 copy of a batch of float32 targets
        f32 = targets.dtype == np.float32
        self.kernel = kernels.shadow_rays_df if f32 else kernels.shadow_rays
        self.device = wp.get_device("cpu")
        # compile / load here, on the caller's thread, before the pool's workers launch it together
        wp.load_module(kernels, device=self.device)
        wrap = lambda a, dtype: wp.array(a, dtype=dtype, device=self.device, copy=False)  # noqa: E731
        self.inputs = [
            wrap(np.ascontiguousarray(origins, np.float64), wp.vec3d),
            wrap(np.ascontiguousarray(targets, np.float32), wp.vec3f) if f32 else
            wrap(np.ascontiguousarray(targets, np.float64), wp.vec3d),
            wrap(np.ascontiguousarray(np.zeros((1, 3), np.float32) if normals is None else normals, np.float32),
                 wp.vec3f),
            wrap(np.ascontiguousarray(np.zeros(1, bool) if distant is None or not distant.any() else distant),
                 wp.bool),
            int(normals is not None), int(distant is not None and bool(distant.any())),
            float(np.float32(epsilon)), FLOAT_MARGIN,
        ]

    def __call__(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays of rows ``lo:hi``: ``(m, 3)`` float32 origins, unit directions, ``(m,)`` float32 ``tfar``."""
        wp, m = self.wp, hi - lo
        o, d, t = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty(m, np.float32)
        outs = [wp.array(ptr=a.ctypes.data, dtype=dt, shape=m, device=self.device, copy=False)
                for a, dt in ((o, wp.vec3f), (d, wp.vec3f), (t, wp.float32))]
        wp.launch(self.kernel, dim=1, device=self.device, inputs=self.inputs + [lo, hi] + outs)
        return o, d, t


def _ray_seeds(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) uint64 per-ray seeds from the float32 bits of each ray: the same ray, the same seed (deterministic
    stochastic transparency; pixel samples and shadow rays from jittered points differ)."""
    return fold_bits(np.full(len(origins), GOLDEN, np.uint64), np.concatenate([origins, dirs], axis=1))


def _uniform(seeds: np.ndarray, layer: int) -> np.ndarray:
    """(K,) float64 in [0, 1): the ``layer``-th random number of each seed."""
    with np.errstate(over="ignore"):
        return unit(mix(seeds + np.uint64(layer + 1) * GOLDEN))


class ExactBackend(VisibilityBackend):
    """Exact shadow rays and closest hits with Embree; see the module docstring for costs.

    Parameters
    ----------
    rel_epsilon : float
        Ray-end offset as a fraction of the scene's bounding-box diagonal (default 1e-5).
    epsilon : float, optional
        Absolute ray-end offset in scene units; overrides ``rel_epsilon``.
    workers : int, optional
        Threads for large batches (default: one per core this process may use).
    chunk_rays : int
        Rays per task handed to a worker (default 65536: smaller chunks lost ~30 % to overhead here).

    Built from settings by the default ``from_settings`` (it reads none; CPU only). Declares ``STATS``
    (``stats``: build counters) and nothing else: direct light is :func:`usdml.lighting.direct.shade_direct`
    over :meth:`occluded` (:func:`usdml.lighting.direct.shade_with` chooses it).
    """

    name = "exact"
    summary = "Embree ray casts: the reference every approximation is measured against"
    capabilities = frozenset({STATS})

    def __init__(self, *, rel_epsilon: float = 1e-5, epsilon: float | None = None,
                 workers: int | None = None, chunk_rays: int = 65536) -> None:
        if rtcs is None:
            raise UsdmlError("the 'exact' visibility backend needs embreex: pip install embreex")
        self.rel_epsilon = float(rel_epsilon)
        self.fixed_epsilon = None if epsilon is None else float(epsilon)
        self.epsilon = self.fixed_epsilon if epsilon is not None else 0.0
        self.workers = cpu_workers("cpu", workers)
        self.chunk_rays = max(1, int(chunk_rays))
        self._static: _EmbreeGroup | None = None
        self._dynamic: _EmbreeGroup | None = None
        self._pool: ThreadPoolExecutor | None = None
        self.sources = SourceTable.empty()
        self._snapshot: Snapshot | None = None
        #: (sources,) bool: the geometry sources whose surface has cutouts (opacityThreshold), None when none has
        self._cutouts: np.ndarray | None = None
        #: build counters and sizes: ``static_builds``, ``dynamic_builds``, ``*_triangles``, ``*_build_s``
        self.stats: dict[str, float] = {"static_builds": 0, "dynamic_builds": 0, "static_triangles": 0,
                                        "dynamic_triangles": 0, "static_build_s": 0.0, "dynamic_build_s": 0.0}

    # ------------------------------------------------------------------ per-frame update

    def update(self, snapshot: Snapshot, changes: Changes | None = None) -> None:
        """Rebuild the static and/or dynamic Embree scene where ``changes`` says something moved.

        ``changes=None`` rebuilds both. The source table (``self.sources``) is recomputed every frame
        from the snapshot (cheap), so ``geom`` ids follow the current snapshot's mesh / prototype
        order; static sources come first, so their ids stay put while dynamic geometry changes.
        """
        static = static_members(snapshot)
        dynamic = tuple([("mesh", m.path) for m in snapshot.meshes if m.deforming]
                        + [("proto", p.path) for p in snapshot.prototypes if _is_dynamic(p)])
        deformed = set(changes.deforming) if changes is not None else set()
        tables = _source_table(snapshot, static), _source_table(snapshot, dynamic)

        def dirty(group: _EmbreeGroup | None, members, table: SourceTable, meshes_changed) -> bool:
            if members_changed(None if group is None else group.members, members, changes, meshes_changed):
                return True
            # guard against a Changes that does not describe this snapshot: same members, other sizes
            return table.triangle_count != group.triangle_count

        if dirty(self._static, static, tables[0], lambda path: changes.static):
            self._static = _build_group(snapshot, static, tables[0])
            self.stats["static_builds"] += 1
            self.stats["static_build_s"] = self._static.build_seconds
        if dirty(self._dynamic, dynamic, tables[1], lambda path: path in deformed):
            self._dynamic = _build_group(snapshot, dynamic, tables[1])
            self.stats["dynamic_builds"] += 1
            self.stats["dynamic_build_s"] = self._dynamic.build_seconds
        # the kept scenes' tables follow this snapshot's mesh / prototype order
        self._static.table, self._dynamic.table = tables
        self.stats["static_triangles"] = self._static.triangle_count
        self.stats["dynamic_triangles"] = self._dynamic.triangle_count
        self.sources = SourceTable.concat(list(tables))
        self._snapshot = snapshot
        self._cutouts = self._cutout_sources(snapshot)
        if self.fixed_epsilon is None:
            bounds = snapshot.world_bounds()
            diag = float(np.linalg.norm(bounds[1] - bounds[0])) if bounds is not None else 0.0
            self.epsilon = self.rel_epsilon * diag

    def _groups(self) -> list[_EmbreeGroup]:
        if self._static is None:
            raise RuntimeError("ExactBackend.update(snapshot) must be called before queries")
        return [g for g in (self._static, self._dynamic) if g is not None and g.scene is not None]

    # ------------------------------------------------------------------ threading

    def map_chunks(self, n: int, work) -> None:
        """Run ``work(lo, hi)`` over ``[0, n)`` in ``chunk_rays`` slices, on the backend's pool when it pays
        (``usdml bench`` times bare Embree through it, on the same chunks and threads)."""
        spans = [(lo, min(n, lo + self.chunk_rays)) for lo in range(0, n, self.chunk_rays)]
        if self.workers == 1 or len(spans) == 1:
            for lo, hi in spans:
                work(lo, hi)
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="usdml-embree")
        for f in [self._pool.submit(work, lo, hi) for lo, hi in spans]:
            f.result()      # re-raises a worker's exception here

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        self._static = self._dynamic = None

    # ------------------------------------------------------------------ shadow rays

    def shadow_rays(self, origins: np.ndarray, targets: np.ndarray, normals: np.ndarray | None,
                    distant: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rays Embree is given for segments P → L, with the epsilon rules of the module docstring.

        Parameters as :meth:`occluded`: ``(n, 3)`` float arrays, ``distant`` ``(n,)`` bool or None.

        Returns
        -------
        ray_origins : (n, 3) float32
        ray_directions : (n, 3) float32, unit
        tfar : (n,) float32
            Ray length in scene units; ``inf`` for distant rows, 0 for segments too short to test.

        The arithmetic is float32 (it was half the cost of the Embree traversal in float64): the
        offsets are at least 8 float32 ulps of the coordinates they move, so rounding cannot undo them.
        This is the rule as NumPy; :meth:`occluded` computes the same rays with the compiled
        ``usdml.kernels.shadow_rays`` (bit for bit: keep the two in step).
        """
        f32 = np.float32
        # (3, n) views: every op below is a contiguous column-wise ufunc, which releases the GIL;
        # row reductions (einsum, sum(axis=1)) hold it and stopped two workers from scaling
        P = np.asarray(origins, f32).T
        L = np.asarray(targets, f32).T
        n = P.shape[1]
        far = distant if distant is not None and distant.any() else None
        eps_p = _abs_max(P)
        eps_p *= f32(FLOAT_MARGIN)
        np.maximum(eps_p, f32(self.epsilon), out=eps_p)
        eps_l = _abs_max(L)
        eps_l *= f32(FLOAT_MARGIN)
        np.maximum(eps_l, f32(self.epsilon), out=eps_l)
        d = L - P
        if far is not None:
            d[:, far] = L[:, far]
        length = np.sqrt(_dot(d, d))
        if normals is not None:
            N = np.asarray(normals, f32).T
            nn = _dot(N, N)
            has_n = nn > 0
            # lift by eps along the normal, flipped to the light's side (sign of n · (L - P))
            lift = np.divide(eps_p, np.sqrt(nn), out=np.zeros(n, f32), where=has_n)
            np.negative(lift, out=lift, where=_dot(N, d) < 0)
            O = P + lift * N
            bare = ~has_n & (length > 0)
            if bare.any():      # zero normal: step along the ray instead
                O[:, bare] += (eps_p[bare] / length[bare]) * d[:, bare]
            # aim from the lifted origin at the light itself, so the segment still ends at L
            d2 = L - O
            if far is not None:
                d2[:, far] = d[:, far]
            length2 = np.sqrt(_dot(d2, d2))
            # a sideways lift keeps the whole segment; a step along the ray already used eps_p of it
            tfar = np.where(has_n, length2 - eps_l, length - eps_p - eps_l)
        else:
            inv = np.divide(f32(1), length, out=np.zeros(n, f32), where=length > 0)
            O = P + (eps_p * inv) * d
            d2, length2 = d, length
            tfar = length - eps_p - eps_l
        d2 *= np.divide(f32(1), length2, out=np.zeros(n, f32), where=length2 > 0)
        if far is not None:
            tfar[far] = np.inf
        tfar[~(tfar > 0) | ~(length > 0)] = 0      # too short (or NaN): never sent to Embree
        return np.ascontiguousarray(O.T), np.ascontiguousarray(d2.T), tfar

    def occluded(self, origins: np.ndarray, targets: np.ndarray, *,
                 normals: np.ndarray | None = None, distant: np.ndarray | None = None) -> np.ndarray:
        """``(N,) bool``: is each segment ``origins[i] → targets[i]`` blocked (see :class:`VisibilityBackend`).

        The rays are :meth:`shadow_rays`'s, computed chunk by chunk by the compiled
        ``usdml.kernels.shadow_rays`` (the same float32 operations: the same rays, bit for bit)."""
        origins = as_vectors(origins, "origins", dtype=None)
        n = origins.shape[0]
        targets = as_vectors(targets, "targets", n, dtype=None)
        normals = None if normals is None else as_vectors(normals, "normals", n, dtype=None)
        distant = None if distant is None else as_flags(distant, "distant", n)
        groups = self._groups()
        out = np.zeros(n, bool)
        if not groups or n == 0:
            return out
        rays = _RayKernel(origins, targets, normals, distant, self.epsilon)

        def work(lo: int, hi: int) -> None:
            o, d, tfar = rays(lo, hi)
            live = None                         # None: every ray of the chunk
            if not (tfar > 0).all():            # a zero-length ray is never blocked: do not send it
                live = np.flatnonzero(tfar > 0)
                o, d, tfar = o[live], d[live], tfar[live]
            for k, g in enumerate(groups):
                if live is not None and not live.size:
                    break
                hit = g.scene.run(o, d, query="OCCLUDED", dists=tfar) != -1
                if live is None:
                    out[lo:hi] = hit
                else:
                    out[lo + live[hit]] = True
                if k + 1 < len(groups):         # OR over scenes: the rays still unblocked go on
                    keep = ~hit
                    live = np.flatnonzero(keep) if live is None else live[keep]
                    o, d, tfar = o[keep], d[keep], tfar[keep]

        self.map_chunks(n, work)
        if self._cutouts is not None and out.any():
            # Embree's any-hit cannot tell a hole from a surface: the blocked segments are walked hit by hit
            rows = np.flatnonzero(out)
            o, d, tfar = self.shadow_rays(origins[rows], targets[rows], None if normals is None else normals[rows],
                                          None if distant is None else distant[rows])
            out[rows] = self.intersect(o.astype(np.float64), d.astype(np.float64),
                                       np.where(tfar > 0, tfar, 0.0))["geom"] >= 0
        return out

    # ------------------------------------------------------------------ closest hits

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, tmax: float | np.ndarray | None = None) -> dict:
        """Closest hit along each ray (for the G-buffer): no epsilon, rays start at ``origins``. A hit in a
        cutout's hole (``opacity < opacityThreshold``, :meth:`usdml.scene.shading.MeshShading.kept`) is passed
        through: the ray goes on from just past it (:attr:`epsilon`) to the next hit, up to :data:`CUTOUT_LAYERS`
        holes deep.

        Parameters
        ----------
        origins : (N, 3) float
        dirs : (N, 3) float
            Directions; ``t`` is measured in units of ``|dirs|`` (unit directions: scene units).
        tmax : float or (N,) float, optional
            Farthest ``t`` considered (default: infinity).

        Returns
        -------
        dict with
            ``t`` (N,) float32, ``inf`` on a miss;
            ``geom`` (N,) int32, row of ``self.sources`` (:meth:`source`), -1 on a miss;
            ``prim`` (N,) int32, triangle index into that source mesh's ``triangles``, -1 on a miss;
            ``u``, ``v`` (N,) float32 barycentrics of triangle corners 1 and 2;
            ``ng`` (N, 3) float32 unnormalised geometric normal ``(v1 - v0) × (v2 - v0)`` in world space.
        """
        origins = as_vectors(origins, "origins")
        n = origins.shape[0]
        dirs = as_vectors(dirs, "dirs", n)
        limit = np.broadcast_to(np.asarray(np.inf if tmax is None else tmax, np.float64), (n,))
        out = self._closest(origins, dirs, limit)
        if self._cutouts is None:
            return out
        base = np.zeros(n, np.float64)       # where each ray's current segment starts, along the ray
        step = max(self.epsilon, 1e-7)
        seeds = _ray_seeds(origins, dirs)
        holes = np.arange(n)                 # the rays whose latest hit is still to be judged
        for layer in range(CUTOUT_LAYERS):
            holes = self._holes(out, seeds, layer, holes)
            if not len(holes):
                break
            start = base[holes] + out["t"][holes].astype(np.float64) + step
            again = self._closest(origins[holes] + dirs[holes] * start[:, None], dirs[holes],
                                  np.maximum(limit[holes] - start, 0.0))
            base[holes] = start
            for key in ("geom", "prim", "u", "v", "ng"):
                out[key][holes] = again[key]
            out["t"][holes] = again["t"]
        else:
            holes = self._holes(out, seeds, CUTOUT_LAYERS, holes)
            out["geom"][holes], out["prim"][holes], out["t"][holes] = -1, -1, np.inf
        hit = out["geom"] >= 0
        out["t"][hit] = (out["t"][hit].astype(np.float64) + base[hit]).astype(np.float32)
        return out

    def _cutout_sources(self, snapshot: Snapshot) -> np.ndarray | None:
        """(sources,) bool of the sources whose mesh has a cutout or partial opacity, or None when none has."""
        if not has_see_through(snapshot):
            return None
        flags = np.array([see_through(self.source(i).mesh_of(snapshot)) for i in range(len(self.sources))], bool)
        return flags if flags.any() else None

    def _holes(self, out: dict, seeds: np.ndarray, layer: int, rows: np.ndarray) -> np.ndarray:
        """The ``rows`` of ``out`` (:meth:`_closest`) whose hit the ray passes through: a cutout's hole, or a partly
        opaque surface the ray's own random number (``seeds``, the ``layer``-th hit along it) lets through."""
        geom = out["geom"]
        rows = rows[geom[rows] >= 0]
        rows = rows[self._cutouts[geom[rows]]]
        if not len(rows):
            return rows
        holes = []
        order = np.argsort(geom[rows], kind="stable")
        rows = rows[order]
        bounds = np.flatnonzero(np.diff(geom[rows])) + 1
        for group in np.split(rows, bounds):
            mesh = self.source(int(geom[group[0]])).mesh_of(self._snapshot)
            u, v = out["u"][group].astype(np.float64), out["v"][group].astype(np.float64)
            w = np.stack([1.0 - u - v, u, v], axis=1)[:, :, None]
            holes.append(group[~mesh.shading.kept(out["prim"][group], w, _uniform(seeds[group], layer))])
        return np.sort(np.concatenate(holes))

    def _closest(self, origins: np.ndarray, dirs: np.ndarray, limit: np.ndarray) -> dict:
        """:meth:`intersect` without cutouts: Embree's closest hit of each ray."""
        n = origins.shape[0]
        groups = self._groups()
        out = {"t": np.full(n, np.inf, np.float32), "geom": np.full(n, -1, np.int32),
               "prim": np.full(n, -1, np.int32), "u": np.zeros(n, np.float32), "v": np.zeros(n, np.float32),
               "ng": np.zeros((n, 3), np.float32)}
        if not groups or n == 0:
            return out
        # global geom id = group's first source + source within the group
        first_source = {id(self._static): 0, id(self._dynamic): len(self._static.table)}

        def work(lo: int, hi: int) -> None:
            o = origins[lo:hi].astype(np.float32)
            d = dirs[lo:hi].astype(np.float32)
            t = limit[lo:hi].astype(np.float32)       # each run() shortens t in place: nearer hits only
            for g in groups:
                r = g.scene.run(o, d, query="INTERSECT", dists=t, output=1)
                hit = np.flatnonzero(r["geomID"] != -1)
                if not hit.size:
                    continue
                tri = r["primID"][hit].astype(np.int64)
                src = np.searchsorted(g.table.tri_offset, tri, side="right") - 1
                rows = lo + hit
                out["t"][rows] = r["tfar"][hit]
                out["geom"][rows] = first_source[id(g)] + src
                out["prim"][rows] = tri - g.table.tri_offset[src]
                out["u"][rows] = r["u"][hit]
                out["v"][rows] = r["v"][hit]
                out["ng"][rows] = r["Ng"][hit]

        self.map_chunks(n, work)
        return out

    def source(self, geom: int) -> GeometrySource:
        """Where ``geom`` (from :meth:`intersect`) comes from: plain mesh or (prototype, instance, mesh)."""
        s = self.sources
        if not 0 <= geom < len(s):
            raise IndexError(f"geom {geom} is not a source of the current snapshot ({len(s)} sources)")
        return GeometrySource(int(s.mesh[geom]), int(s.prototype[geom]), int(s.instance[geom]),
                              int(s.proto_mesh[geom]), int(s.prim_id[geom]), int(s.instance_id[geom]))

    def ids(self, geom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(N,) int32`` primId and ``(N,) int64`` instanceId of each ``geom`` (-1 for misses / plain meshes)."""
        geom = np.asarray(geom)
        hit = geom >= 0
        g = np.where(hit, geom, 0)
        if not len(self.sources):
            return np.full(geom.shape, -1, np.int32), np.full(geom.shape, -1, np.int64)
        return (np.where(hit, self.sources.prim_id[g], -1).astype(np.int32),
                np.where(hit, self.sources.instance_id[g], -1).astype(np.int64))
