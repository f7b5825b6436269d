"""``usdml bench``: time the visibility queries of one frame, every backend on the same query set.

The query set is every (pixel, light) pair of one frame where the light faces the pixel's surface
(the pairs direct lighting asks about), from the G-buffer of the exact backend, in the order the
voxel shading kernel asks them on CPU (:func:`shading_order`: paper 000 Alg. 3 over tiles of
neighbouring pixels, light by light). Every backend is timed on the same queries in the same order.
"""

from __future__ import annotations

import time as _time
from contextlib import contextmanager

import numpy as np

from usdml.lighting.direct import facing_pairs
from usdml.render.backends import QUERY_ROLES, Backends
from usdml.render.budget import choose_level
from usdml.render.frame import FrameRenderer, centre_gbuffer
from usdml.scene import diff, world_geometry
from usdml.stage import StageDelegate
from usdml.stage.delegate import require_geometry, require_lights
from usdml.visibility import ExactBackend
from usdml.visibility.base import all_members
from usdml.visibility.refine import Refined
from usdml.visibility.voxel.backend import SHADE_TILE
from usdml.zorder import morton_order


#: queries each backend answers before anything is timed (kernel modules load, scenes commit)
WARMUP = 1024
#: timed passes over the whole query set after one untimed pass, backends in turn, the median
#: reported: the steady state of a sequence, whose frames find the structures in memory and cache.
#: (Measured on the city at 128 px, 2 shared cores: one pass right after other work ran the voxel
#: backend at 33-38 M queries/s, the same after 2 s idle at 48 M/s: the machine's speed drifts, so
#: backends are timed in turn rather than one after the other.)
PASSES = 3


def interleaved_passes(runs: dict) -> dict:
    """Each of ``runs`` (name -> a callable making one pass) once untimed, then :data:`PASSES` rounds
    taking them in turn: name -> (median seconds, the last pass's result, every pass's seconds)."""
    last = {name: run() for name, run in runs.items()}
    seconds = {name: [] for name in runs}
    for _ in range(PASSES):
        for name, run in runs.items():
            t0 = _time.perf_counter()
            last[name] = run()
            seconds[name].append(_time.perf_counter() - t0)
    return {name: (float(np.median(seconds[name])), last[name], seconds[name]) for name in runs}


def query_set(snap, gb) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origins, targets, normals, distant flags and hit-pixel index of every facing (pixel, light)
    pair: the shadow queries direct lighting asks on the G-buffer ``gb``, in :func:`shading_order`."""
    hit = gb.hit.ravel()
    points = gb.position.reshape(-1, 3)[hit]
    blocks = list(facing_pairs(points, gb.normal.reshape(-1, 3)[hit], snap.lights, gb.geometric.reshape(-1, 3)[hit]))
    if not blocks:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, np.int64)
    columns = [np.concatenate([b[k] for b in blocks]) for k in range(6)]
    order = shading_order(points, columns[4], columns[5])
    return tuple(c[order] for c in columns[:5])


def shading_order(points: np.ndarray, point_index: np.ndarray, light_index: np.ndarray,
                  tile: int = SHADE_TILE) -> np.ndarray:
    """The permutation putting (point, light) queries in the order ``kernels.voxel.shading.shade_tiles`` asks
    them on CPU: ``points`` along a Z-order curve in tiles of ``tile``, each tile light by light.
    (Rays from neighbouring points to one light share direction bins and rows; measured on the city
    at 160 px, 128³ / 2°: voxel 7.1 M queries/s in pixel-by-pixel order, 12.0 M/s in this one;
    exact 9.0 and 9.6 M/s.)"""
    rank = np.empty(len(points), np.int64)
    rank[morton_order(np.asarray(points, np.float32))] = np.arange(len(points))
    r = rank[point_index]
    return np.lexsort((r, light_index, r // max(int(tile), 1)))


def resample_lights(lights, n: int, seed: int = 0):
    """``lights`` resampled to ``n`` for timing against the light count (paper 000 Table VI): the first
    ``n`` when there are enough, else all of them plus copies of randomly drawn ones, each moved by
    a random offset of up to half the lights' mean spacing (so copies do not coincide). Radiometry is
    kept per light: images get brighter with more lights; only the timing is meant."""
    count = len(lights)
    if n <= count or count == 0:
        idx = np.arange(min(n, count))
        offset = np.zeros((len(idx), 3))
    else:
        rng = np.random.default_rng(seed)
        extra = rng.integers(0, count, n - count)
        idx = np.concatenate([np.arange(count), extra])
        ext = np.ptp(lights.position, axis=0)
        ext = np.maximum(ext, 1e-3 * max(float(ext.max()), 1e-9))
        spacing = float(np.prod(ext) / count) ** (1.0 / 3.0)
        offset = np.zeros((n, 3))
        offset[count:] = rng.uniform(-0.5, 0.5, (n - count, 3)) * spacing
    out = lights.subset(idx)
    out.position = out.position + offset
    out.xform = out.xform.copy()
    out.xform[:, :3, 3] += offset
    return out


class BareEmbree:
    """Bare ``embreex`` on the very rays ``exact`` traces for a query set: one merged scene of every
    world triangle of ``snap`` (:func:`usdml.scene.world_geometry`), ``run(o, d, query='OCCLUDED',
    dists=tfar)`` on :meth:`ExactBackend.shadow_rays`'s rays (the rows with ``tfar > 0``, the ones the
    backend sends), chunked and threaded by ``exact``'s own pool (:meth:`ExactBackend.map_chunks`).
    What the backend adds to Embree (its ray set-up, gathers, the scene split) is the difference.

    The scene is built and committed, and the rays made, here; :meth:`run` is the timed part."""

    def __init__(self, snap, exact: ExactBackend, origins: np.ndarray, targets: np.ndarray, normals: np.ndarray,
                 distant: np.ndarray) -> None:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        members = all_members(snap)
        points, triangles = world_geometry(snap, members)
        self.exact, self.n = exact, len(origins)
        o, d, tfar = (np.empty((self.n, 3), np.float32), np.empty((self.n, 3), np.float32),
                      np.empty(self.n, np.float32))
        for lo in range(0, self.n, 1 << 20):     # in blocks: the NumPy rule's temporaries stay small
            hi = min(self.n, lo + (1 << 20))
            o[lo:hi], d[lo:hi], tfar[lo:hi] = exact.shadow_rays(origins[lo:hi], targets[lo:hi], normals[lo:hi],
                                                                distant[lo:hi])
        self.live = np.flatnonzero(tfar > 0)
        self.rays = o[self.live], d[self.live], tfar[self.live]
        self.scene = None
        if triangles.shape[0] and self.live.size:
            self.scene = rtcs.EmbreeScene()
            TriangleMesh(self.scene, points, triangles)
            self._run(np.zeros(len(self.live), bool), 0, min(WARMUP, len(self.live)))  # commits the scene

    def _run(self, hit: np.ndarray, lo: int, hi: int) -> None:
        o, d, tfar = self.rays
        hit[lo:hi] = self.scene.run(o[lo:hi], d[lo:hi], query="OCCLUDED", dists=tfar[lo:hi]) != -1

    def timed_run(self) -> np.ndarray:
        """``(N,) bool`` answers of one pass over the query set (what :func:`interleaved_passes` times)."""
        blocked = np.zeros(self.n, bool)
        if self.scene is None:
            return blocked
        hit = np.zeros(len(self.live), bool)
        self.exact.map_chunks(len(self.live), lambda lo, hi: self._run(hit, lo, hi))
        blocked[self.live] = hit
        return blocked

    def run(self) -> tuple[float, np.ndarray]:
        """Seconds (the median of :data:`PASSES` passes after an untimed one) and answers."""
        seconds, blocked, _ = interleaved_passes({"bare": self.timed_run})["bare"]
        return seconds, blocked


def exact_queries(delegate: StageDelegate, image_width: int, frame: float, command: str = "bench", settings=None):
    """What ``usdml bench`` times, from the exact backend: ``(snapshot, exact backend (updated; the
    caller closes it), its build seconds, (width, height), G-buffer, (origins, targets, normals,
    distant, point index))``, the queries as :func:`query_set` gives them. ``command`` names the caller in errors;
    ``settings``: the run's (default the stage's), of which the exact backend reads none.

    The exact backend is the ``primary`` of a :class:`usdml.render.backends.Backends` set up as a render's, and
    the G-buffer a render's at the pixel centres (:func:`usdml.render.frame.centre_gbuffer`)."""
    snap = delegate.snapshot(frame)
    require_geometry(delegate, snap)
    require_lights(delegate, snap, command)
    width, height = snap.camera.resolution(image_width)
    settings = settings if settings is not None else delegate.usdml_settings
    backends = Backends(settings.updated(visibility=ExactBackend.name), roles=QUERY_ROLES)
    build = backends.update(snap, diff(None, snap))["primary"]
    _, gb = centre_gbuffer(snap, backends.primary, width, height)
    return snap, backends.primary, build, (width, height), gb, query_set(snap, gb)


def bench_visibility(delegate: StageDelegate, backends: list[str], image_width: int = 512,
                     frame: float | None = None, settings=None, backend_options: dict | None = None,
                     device: str = "cpu") -> list[dict]:
    """One result per backend: build and query seconds (the median of :data:`PASSES` passes after an untimed
    one) on the same queries, ratios to ``exact`` and to
    bare embreex on the rays ``exact`` traces (:class:`BareEmbree`, measured in the same run):
    ``bare_embree_seconds``, ``speedup_vs_bare_embree`` (bare seconds / the backend's) and, on every
    row, ``exact_overhead_vs_bare_embree`` (exact's seconds / bare; 1.0 would be no overhead).

    ``device`` is the Warp device the backends other than ``exact`` (Embree, on the CPU) run on."""
    stage = delegate.path
    frame = delegate.start_time if frame is None else frame
    base = settings if settings is not None else delegate.usdml_settings
    snap, exact, exact_build, (width, height), gb, queries = exact_queries(delegate, image_width, frame,
                                                                            settings=base)
    origins, targets, normals, distant, point_index = queries
    bare = BareEmbree(snap, exact, *queries[:4])
    built = {}
    held = {}       # name -> its Backends (usdml.render.backends), all sharing ``exact``
    for name in dict.fromkeys(["exact"] + list(backends)):
        if name == "exact":
            built[name] = (exact, exact_build)
            continue
        # --error-budget on a backend that cannot refine: timed as it is, as ever
        held[name] = Backends(base.updated(visibility=name), device, backend_options, roles=QUERY_ROLES,
                              primary=exact, unrefinable="ignore")
        built[name] = (held[name].configured, held[name].update(snap, diff(None, snap))["shadow"])
    # passes taken in turn (bare embreex, exact, the others, again ...), so that a machine whose speed
    # drifts (shared cores, a CPU quota) slows every backend alike; each backend's median is reported
    runs = {"bare": bare.timed_run}
    refined = {name: b.refined for name, b in held.items() if b.refined is not None}
    for name, (backend, _) in built.items():
        # a few queries first: kernel modules load and caches fill outside the timing
        backend.occluded(origins[:WARMUP], targets[:WARMUP], normals=normals[:WARMUP], distant=distant[:WARMUP])
        runs[name] = (lambda b: lambda: b.occluded(origins, targets, normals=normals, distant=distant))(backend)
        if name in refined:
            # --error-budget: each pass chooses the frame's level from its sample as a render does, then answers
            # every query refined (usdml.render.budget): both timed
            runs[name] = _budgeted(refined[name], gb, snap, base.error_budget, delegate, frame, origins, targets,
                                   normals, distant, point_index)
    timed = interleaved_passes(runs)
    bare_seconds, bare_blocked, _ = timed["bare"]
    results = []
    reference = None
    for name, (backend, build) in built.items():
        seconds, blocked, passes = timed[name]
        if reference is None:
            reference = (seconds, blocked)
        results.append({
            "backend": name, "stage": stage, "frame": frame, "resolution": [width, height],
            "pixels": int(gb.hit.sum()), "lights": len(snap.lights), "queries": int(len(origins)),
            "seconds": seconds, "pass_seconds": passes, "queries_per_second": len(origins) / seconds if seconds > 0 else float("inf"),
            "build_seconds": build, "blocked_fraction": float(blocked.mean()) if len(blocked) else 0.0,
            "speedup_vs_exact": reference[0] / seconds if seconds > 0 else float("inf"),
            "disagreement_vs_exact": float((blocked != reference[1]).mean()) if len(blocked) else 0.0,
            "bare_embree_seconds": bare_seconds,
            "speedup_vs_bare_embree": bare_seconds / seconds if seconds > 0 else float("inf"),
            "exact_overhead_vs_bare_embree": reference[0] / bare_seconds if bare_seconds > 0 else float("inf"),
            "disagreement_vs_bare_embree": float((blocked != bare_blocked).mean()) if len(blocked) else 0.0,
            "triangles": snap.triangle_count(),
            "bytes": 0,
        })
        # the backend's own fields (voxel: resolution, directions, arrays, bytes, ...) and what
        # rebuilding its per-frame structures costs (voxel: Alg. 5 and Alg. 1 rebuilds of this
        # frame's per-frame array, in place as a sequence render does)
        if name in refined:
            r = refined[name]
            results[-1].update(error_budget=r.budget.budget, refine_level=r.budget.level,
                               estimated_eps_v=r.budget.eps_v,
                               estimated_eps_v_interval=[r.budget.eps_v_lo, r.budget.eps_v_hi], **r.fractions())
        results[-1].update(backend.describe())
        results[-1].update(backend.per_frame_rebuild_seconds(snap))
        if name in held:
            held[name].close()
    exact.close()
    if "exact" not in backends:
        results = [r for r in results if r["backend"] != "exact"] or results
    return results


def _budgeted(refined: Refined, gb, snap, budget: float, delegate: StageDelegate, frame: float, origins, targets,
              normals, distant, point_index):
    """A timed pass of ``refined`` under ``budget``: the level chosen on the frame's sample, then every query."""
    hit = gb.hit.ravel()
    seed = delegate.usdml_settings.seed

    def run():
        refined.budget = choose_level(refined, gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit],
                                      gb.geometric.reshape(-1, 3)[hit], snap.lights, budget, seed, frame, delegate.path)
        return refined.answer(origins, targets, normals=normals, distant=distant, starts=point_index)[0]
    return run


def format_bench(results: list[dict]) -> str:
    lines = []
    for r in results:
        lines.append(f"{r['backend']:>8}: {r['queries']:,} shadow queries ({r['pixels']:,} pixels x {r['lights']:,} "
                     f"lights, facing pairs) in {r['seconds']:.2f} s = {r['queries_per_second'] / 1e6:.2f} M/s; "
                     f"build {r['build_seconds']:.2f} s; {100 * r['blocked_fraction']:.1f} % blocked"
                     + (f"; {r['bytes'] / 2**20:.0f} MiB" if r.get("bytes") else "")
                     + (f"; {r['cpu_kernel']} kernel" if r.get("cpu_kernel") else "")
                     + (f"; bare embreex on the same rays {r['bare_embree_seconds']:.2f} s (exact "
                        f"{r['exact_overhead_vs_bare_embree']:.2f}x)"
                        if r["backend"] == "exact" and "bare_embree_seconds" in r else "")
                     + (f"; --error-budget {r['error_budget']:g}: level {r['refine_level']}, "
                        f"{100 * r['refined_fraction']:.1f} % re-asked of exact, disagreeing with exact on "
                        f"{100 * r['disagreement_vs_exact']:.2f} % of queries" if "error_budget" in r else "")
                     + ("" if r["backend"] == "exact" else f"; {r['speedup_vs_exact']:.1f}x exact"
                        + (f", {r['speedup_vs_bare_embree']:.1f}x bare embreex" if "speedup_vs_bare_embree" in r else ""))
                     + (f"\n          per-frame array: Alg. 5 ({r['mapping']}) {r['rebuild_seconds']:.2f} s, Alg. 1 "
                        f"{r['full_rebuild_seconds']:.2f} s = {r['rebuild_speedup']:.1f}x"
                        if "rebuild_seconds" in r and "mapping" in r else "")
                     + (f"\n          per frame: depth images {r['depth_image_seconds']:.2f} s, triangulation "
                        f"{r['triangulate_seconds']:.2f} s ({r['reconstructed_triangles']:,} triangles); the last pass's "
                        f"{r['last_maps']:,} lights, summed over threads: receiver tiles {r['last_receiver_seconds']:.2f} s, "
                        f"maps {r['last_map_seconds']:.2f} s, lookups {r['last_lookup_seconds']:.2f} s; "
                        f"{r['exact_queries']:,} queries sent to exact"
                        if "depth_image_seconds" in r else ""))
    return "\n".join(lines)


def next_frame(delegate: StageDelegate, frame: float) -> float:
    """The timecode after ``frame`` (``frame`` itself at the stage's end)."""
    return min(frame + 1, delegate.end_time) if delegate.end_time > frame else frame


@contextmanager
def steady_frame(delegate: StageDelegate, settings, frame: float, width: int, height: int,
                 aovs: frozenset = frozenset({"color"}), backend_options: dict | None = None):
    """Render ``frame`` and then :func:`next_frame` with one renderer and time the second: the steady
    state of a sequence (per-frame arrays rebuilt, static ones kept). Yields ``(result, seconds,
    renderer)``; the renderer is closed on leaving. ``backend_options``: keyword options of the backends
    (:class:`usdml.render.frame.FrameRenderer`'s), default none but a silent ``report``."""
    r = FrameRenderer(delegate, settings, backend_options=backend_options or {"report": lambda s: None})
    try:
        r.render(frame, width, height, set(aovs))
        t0 = _time.perf_counter()
        result = r.render(next_frame(delegate, frame), width, height, set(aovs))
        yield result, _time.perf_counter() - t0, r
    finally:
        r.close()
