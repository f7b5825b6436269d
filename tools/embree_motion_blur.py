#!/usr/bin/env python
"""Embree's own motion blur against usdml's time slices, measured (docs/motion-blur.md, "Embree's motion blur,
measured").

usdml blurs motion with time slices: every pass reads the stage at its time and the exact backend rebuilds its
dynamic Embree scene there (``usdml/render/shutter.py``). The alternative is Embree's motion blur: a geometry with
several time steps (one vertex buffer per step, vertices interpolated linearly between steps) and a time in every
ray. ``embreex`` exposes neither, but its wheel bundles the whole Embree 4 library (``embreex.libs/libembree4-*``);
this tool loads that library with ctypes. The few functions and the ``RTCRay`` / ``RTCRay4/8/16`` layouts it needs
are declared here from Embree 4's public headers (``rtcore_ray.h``, ``rtcore_scene.h``, ``rtcore_geometry.h``,
``rtcore_buffer.h``, ``rtcore_common.h``, ``rtcore_device.h``): no header, no new dependency
(``tests/test_embree_motion_blur.py`` checks the declarations on a moving square).

On a moving stage (default the skinned creature, ``stages/creature.usda``, frame 2, shutter -0.25..0.25; the
bear deforms, the ground is static; ``--stage stages/park.usda``: rigidly moving rides) it measures:

1. **build**: the moving geometry's BVH with one time step (a static BVH, what a slice builds), with 2 and with
   4 time steps (Embree's motion blur over the shutter), and ``--slices`` (16) static rebuilds, as usdml's slices
   do per frame, through ctypes; and one rebuild through embreex (the exact backend's own path: embreex copies
   vertex by vertex). Also what reading the stage at a time costs (``StageDelegate.snapshot`` and flattening),
   which slices pay per slice and time steps per step.
2. **trace**: shadow rays (occluded) from the points the camera sees to the stage's lights (:class:`ShadowRays`),
   ``rtcOccluded1/8/16`` (``--widths``), on 1 and on ``--threads`` Python threads: the static BVH with no time,
   against the 2- and 4-step BVHs and a BVH of two identical steps (the motion-blur structure with nothing
   moving) with a random time per ray in [0, 1]. Each packet is either one ctypes call (its cost, about a
   microsecond, is measured with the same calls on an empty scene and subtracted: "net") or, where ``cc`` works,
   part of one call of a ten-line compiled C loop (:data:`LOOP_C`) that calls the Embree function it is handed.
   embreex's ``run`` on the static BVH (the exact backend's path) for comparison, with its answers.
3. **agreement**: rays at each time step give the answers of a static BVH of that step's pose; and what linear
   interpolation costs: the rays split among the slices' times (strata centres), each from and against the
   true pose at its time (what slices trace), against the 2- and 4-step BVHs at the same times.
4. **memory**: what Embree allocates for each BVH (``rtcSetDeviceMemoryMonitorFunction``, net bytes after the
   commit, geometry buffers included).
5. **per frame**: the sums for a ``--frame-width`` frame at ``--slices`` samples, every light of every visible
   sample traced (single rays, ``--threads`` threads): the slices' reads, rebuilds and tracing against the time
   steps' reads, build and tracing.

Usage::

    python tools/embree_motion_blur.py --json
    python tools/embree_motion_blur.py --rays 200000 --repeat 1
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

# Embree 4 enums (rtcore_geometry.h, rtcore_buffer.h, rtcore_common.h, rtcore_device.h)
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX = 0
RTC_BUFFER_TYPE_VERTEX = 1
RTC_FORMAT_UINT3 = 0x5003
RTC_FORMAT_FLOAT3 = 0x9003
RTC_ERROR_NONE = 0

#: RTCRay (rtcore_ray.h) and its packets RTCRay4/8/16: twelve 4-byte fields in this order, each an array of the
#: packet's width in a packet (``RTCRayN_*``: field k of ray i at float ``k·N + i``), aligned to 16 bytes (RTCRay,
#: RTCRay4), 32 (RTCRay8), 64 (RTCRay16); rtcOccluded* set ``tfar`` to -inf for each ray they find blocked
RAY_FIELDS = ("org_x", "org_y", "org_z", "tnear", "dir_x", "dir_y", "dir_z", "time",
              "tfar", "mask", "id", "flags")
FIELD = {name: i for i, name in enumerate(RAY_FIELDS)}
#: the packet widths Embree 4 takes: rtcOccluded1, rtcOccluded4, rtcOccluded8, rtcOccluded16
WIDTHS = (1, 4, 8, 16)

#: bool (*RTCMemoryMonitorFunction)(void* userPtr, ssize_t bytes, bool post)
MEMORY_MONITOR = ctypes.CFUNCTYPE(ctypes.c_bool, ctypes.c_void_p, ctypes.c_ssize_t, ctypes.c_bool)


def library_path() -> Path | None:
    """The Embree 4 shared library embreex's wheel bundles (``site-packages/embreex.libs/libembree4-*.so*``), or
    None where embreex is not installed or carries none."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        return None
    libs = Path(list(spec.submodule_search_locations)[0]).parent / "embreex.libs"
    found = sorted(libs.glob("libembree4*.so*"))
    return found[0] if found else None


def _aligned(nbytes: int, align: int = 64) -> np.ndarray:
    """``nbytes`` zeroed uint8 whose address is a multiple of ``align`` (Embree's packets need 64)."""
    raw = np.zeros(nbytes + align, np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off:off + nbytes]


class Embree:
    """One Embree 4 device, loaded with ctypes from ``path``; ``config`` is rtcNewDevice's string (e.g.
    ``"threads=1"``; empty: every core builds). ``monitor=True`` counts what the device allocates
    (:attr:`allocated`, net bytes)."""

    def __init__(self, path: Path, config: str = "", monitor: bool = False) -> None:
        lib = self.lib = ctypes.CDLL(str(path))
        vp, uint, size = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
        for name, restype, argtypes in (
                ("rtcNewDevice", vp, [ctypes.c_char_p]),
                ("rtcReleaseDevice", None, [vp]),
                ("rtcGetDeviceError", ctypes.c_int, [vp]),
                ("rtcSetDeviceMemoryMonitorFunction", None, [vp, MEMORY_MONITOR, vp]),
                ("rtcNewScene", vp, [vp]),
                ("rtcCommitScene", None, [vp]),
                ("rtcReleaseScene", None, [vp]),
                ("rtcNewGeometry", vp, [vp, ctypes.c_int]),
                ("rtcSetGeometryTimeStepCount", None, [vp, uint]),
                ("rtcSetNewGeometryBuffer", vp, [vp, ctypes.c_int, uint, ctypes.c_int, size, size]),
                ("rtcCommitGeometry", None, [vp]),
                ("rtcAttachGeometry", uint, [vp, vp]),
                ("rtcReleaseGeometry", None, [vp]),
                # Embree 4: ([valid,] scene, ray, args); args NULL = the default RTCOccludedArguments
                ("rtcOccluded1", None, [vp, vp, vp]),
                ("rtcOccluded4", None, [vp, vp, vp, vp]),
                ("rtcOccluded8", None, [vp, vp, vp, vp]),
                ("rtcOccluded16", None, [vp, vp, vp, vp])):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        self.device = lib.rtcNewDevice(config.encode() if config else None)
        if not self.device:
            raise RuntimeError(f"rtcNewDevice({config!r}) failed")
        self.allocated = 0
        self._monitor = None
        if monitor:
            def count(_user, nbytes, _post) -> bool:    # called once per block, from Embree's build threads
                self.allocated += nbytes
                return True
            self._monitor = MEMORY_MONITOR(count)       # kept alive as long as the device
            lib.rtcSetDeviceMemoryMonitorFunction(self.device, self._monitor, None)
        self.check("rtcNewDevice")

    def check(self, what: str) -> None:
        err = self.lib.rtcGetDeviceError(self.device)
        if err != RTC_ERROR_NONE:
            raise RuntimeError(f"Embree error {err} after {what}")

    def scene(self, geometries: list[tuple[list[np.ndarray], np.ndarray]]) -> int:
        """A committed scene of triangle meshes; each geometry is ``(steps, triangles)``: one ``(V, 3)`` float32
        vertex array per time step (one: static; k > 1: k steps spread evenly over a ray time of [0, 1]) and
        ``(T, 3)`` triangles. Returns the scene handle (release with :meth:`release`)."""
        lib = self.lib
        scene = lib.rtcNewScene(self.device)
        for steps, triangles in geometries:
            tris = np.ascontiguousarray(triangles, np.uint32)
            geom = lib.rtcNewGeometry(self.device, RTC_GEOMETRY_TYPE_TRIANGLE)
            if len(steps) > 1:
                lib.rtcSetGeometryTimeStepCount(geom, len(steps))
            ptr = lib.rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, len(tris))
            ctypes.memmove(ptr, tris.ctypes.data, tris.nbytes)
            for slot, points in enumerate(steps):
                pts = np.ascontiguousarray(points, np.float32)
                ptr = lib.rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, slot, RTC_FORMAT_FLOAT3, 12, len(pts))
                ctypes.memmove(ptr, pts.ctypes.data, pts.nbytes)
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometry(scene, geom)
            lib.rtcReleaseGeometry(geom)            # the scene holds it
        lib.rtcCommitScene(scene)
        self.check("rtcCommitScene")
        return scene

    def release(self, scene: int) -> None:
        self.lib.rtcReleaseScene(scene)

    def close(self) -> None:
        self.lib.rtcReleaseDevice(self.device)
        self.device = None

    def occluded(self, scene: int, packets: "Packets", threads: int = 1, loop: bool = False) -> float:
        """Trace every packet of ``packets`` (rtcOccluded1/4/8/16 by its width) against ``scene`` on ``threads``
        Python threads (the packets cut into contiguous runs); returns the seconds it took. Results:
        :meth:`Packets.blocked`. ``loop``: each run of packets is one call of the compiled loop
        (:func:`compiled_loop`) rather than one ctypes call a packet."""
        n, size, base = packets.count, packets.nbytes, packets.address
        full, last = packets.valid_full, packets.valid_last
        name = "rtcOccluded1" if packets.width == 1 else f"rtcOccluded{packets.width}"
        fn = getattr(self.lib, name)
        if loop:
            trace, address = compiled_loop(), ctypes.cast(fn, ctypes.c_void_p).value

            def run(valid: int, lo: int, hi: int) -> None:
                if hi > lo:
                    trace(address, packets.width, valid, scene, base + lo * size, hi - lo, size)
        elif packets.width == 1:
            def run(valid: int, lo: int, hi: int) -> None:
                for p in range(lo, hi):
                    fn(scene, base + p * size, None)
        else:
            def run(valid: int, lo: int, hi: int) -> None:
                for p in range(lo, hi):
                    fn(valid, scene, base + p * size, None)

        def work(lo: int, hi: int) -> None:
            run(full, lo, min(hi, n - 1))
            if hi == n:
                run(last, n - 1, n)

        bounds = np.linspace(0, n, threads + 1).astype(int)
        t0 = time.perf_counter()
        if threads == 1:
            work(0, n)
        else:
            with ThreadPoolExecutor(threads) as pool:
                for f in [pool.submit(work, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
                    f.result()
        seconds = time.perf_counter() - t0
        self.check(name)
        return seconds


#: a C loop over packets, so that ctypes' cost per call (about a microsecond, several single-ray traversals) is
#: paid once per run of packets; it calls the Embree function it is given, and needs no Embree header
LOOP_C = r"""
typedef void (*occluded1_fn)(void *scene, void *ray, void *args);
typedef void (*occluded_n_fn)(const int *valid, void *scene, void *ray, void *args);

void trace_packets(void *fn, int width, const int *valid, void *scene, char *rays, long count, long stride)
{
    long i;
    if (width == 1)
        for (i = 0; i < count; ++i) ((occluded1_fn)fn)(scene, rays + i * stride, 0);
    else
        for (i = 0; i < count; ++i) ((occluded_n_fn)fn)(valid, scene, rays + i * stride, 0);
}
"""


@functools.lru_cache(maxsize=1)
def compiled_loop():
    """``trace_packets(fn, width, valid, scene, rays, count, stride)`` of :data:`LOOP_C`, compiled with ``cc`` into
    a temporary folder; None where no C compiler works."""
    with tempfile.TemporaryDirectory(prefix="embree_loop_") as tmp:    # a loaded library outlives its file
        folder = Path(tmp)
        (folder / "loop.c").write_text(LOOP_C)
        try:
            subprocess.run(["cc", "-O2", "-shared", "-fPIC", "-o", str(folder / "loop.so"), str(folder / "loop.c")],
                           check=True, capture_output=True)
        except (OSError, subprocess.CalledProcessError):
            return None
        fn = ctypes.CDLL(str(folder / "loop.so")).trace_packets
    vp = ctypes.c_void_p
    fn.restype, fn.argtypes = None, [vp, ctypes.c_int, vp, vp, vp, ctypes.c_long, ctypes.c_long]
    return fn


class Packets:
    """Rays laid out as consecutive ``RTCRay`` (``width`` 1) or ``RTCRay4/8/16`` packets (64-byte aligned), with
    the valid masks rtcOccluded4/8/16 read: every lane of a full packet, the first ``n mod width`` of the last."""

    def __init__(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray, times: np.ndarray | None = None,
                 width: int = 16):
        if width not in WIDTHS:
            raise ValueError(f"packet width {width} is not one of {WIDTHS}")
        n = len(origins)
        self.n, self.width, self.count = n, width, -(-n // width)
        self.nbytes = len(RAY_FIELDS) * width * 4
        self._buf = _aligned(self.count * self.nbytes)
        self.address = self._buf.ctypes.data
        f = self.fields = self._buf.view(np.float32).reshape(self.count, len(RAY_FIELDS), width)

        def put(name: str, values) -> None:
            col = np.zeros(self.count * width, np.float32)
            col[:n] = values
            f[:, FIELD[name]] = col.reshape(self.count, width)

        for k, axis in enumerate("xyz"):
            put(f"org_{axis}", origins[:, k])
            put(f"dir_{axis}", dirs[:, k])
        put("tnear", 0.0)
        put("tfar", tfar)
        put("time", 0.0 if times is None else times)
        f.view(np.uint32)[:, FIELD["mask"]] = 0xFFFFFFFF
        self._tfar = f[:, FIELD["tfar"]].copy()
        masks = _aligned(2 * 64).view(np.int32).reshape(2, 16)
        masks[0] = -1
        masks[1, :n - (self.count - 1) * width] = -1
        self._masks = masks
        self.valid_full, self.valid_last = masks[0].ctypes.data, masks[1].ctypes.data

    def set_times(self, times: np.ndarray) -> None:
        col = np.zeros(self.count * self.width, np.float32)
        col[:self.n] = times
        self.fields[:, FIELD["time"]] = col.reshape(self.count, self.width)

    def reset(self) -> None:
        """Restore every ray's ``tfar`` (a trace overwrites the blocked ones)."""
        self.fields[:, FIELD["tfar"]] = self._tfar

    def blocked(self) -> np.ndarray:
        """``(n,)`` bool: the rays the last trace found blocked."""
        return np.isneginf(self.fields[:, FIELD["tfar"]].reshape(-1)[:self.n])


# ---------------------------------------------------------------------------------------------- the stage


def geometry_at(delegate, t: float) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], object]:
    """``((static points, triangles), (moving points, triangles), snapshot)`` of the stage at time ``t``, in world
    space, split as the exact backend splits its two scenes."""
    from usdml.scene import world_geometry
    from usdml.visibility.base import static_members

    snap = delegate.snapshot(t)
    moving = tuple([("mesh", m.path) for m in snap.meshes if m.deforming]
                   + [("proto", p.path) for p in snap.prototypes if p.animated or p.deforming])
    return world_geometry(snap, static_members(snap)), world_geometry(snap, moving), snap


class ShadowRays:
    """The frame's shadow rays, movable in time: from the points the camera sees at the frame (a G-buffer through
    the exact backend) to the snapshot's lights, ``n`` random (pixel, light) pairs. A ray's origin is a point of a
    triangle (its index into the static-then-moving triangles and its barycentrics), so it can be put on that
    triangle in any pose: a structure is traced with rays from its own surface at the ray's time, as a renderer's
    primary hits would give. The rays are the exact backend's own rule
    (:meth:`usdml.visibility.exact.ExactBackend.shadow_rays`: lifted along the geometric normal toward the light,
    stopped short of it); the lights stay where they are at the frame."""

    def __init__(self, snapshot, triangles: np.ndarray, n: int, seed: int, width: int = 256) -> None:
        from usdml.render.gbuffer import camera_rays
        from usdml.visibility.exact import ExactBackend

        self.backend = backend = ExactBackend()
        backend.update(snapshot)
        origins, dirs, tmax = camera_rays(snapshot.camera, *snapshot.camera.resolution(width))
        hit = backend.intersect(origins, dirs, tmax)
        rows = np.flatnonzero(hit["geom"] >= 0)
        self.hit_fraction = len(rows) / len(hit["geom"])        #: of the pixels, those that see a surface
        self.light_count = len(snapshot.lights.position)
        rng = np.random.default_rng(seed)
        pick = rows[rng.integers(0, len(rows), n)]
        #: (n,) index into ``triangles`` (the static triangles, then the moving ones)
        self.triangle = backend.sources.tri_offset[hit["geom"][pick]] + hit["prim"][pick]
        self.u, self.v = hit["u"][pick].astype(np.float64), hit["v"][pick].astype(np.float64)
        lights = np.asarray(snapshot.lights.position, np.float64)
        self.lights = lights[rng.integers(0, len(lights), n)]
        self.corners = np.asarray(triangles, np.int64)[self.triangle]           # (n, 3) vertex indices

    def rays(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """float32 origins, unit directions and tfar with each ray's triangle at its corners ``points``
        (``(n, 3, 3)``, or ``(V, 3)`` vertices of one pose); a ray of no length has tfar 0."""
        if points.ndim == 2:
            points = points[self.corners]
        a, b, c = points[:, 0], points[:, 1], points[:, 2]
        p = (1 - self.u - self.v)[:, None] * a + self.u[:, None] * b + self.v[:, None] * c
        return self.backend.shadow_rays(p, self.lights, np.cross(b - a, c - a), None)

    def corners_at(self, steps: list[np.ndarray], times: np.ndarray) -> np.ndarray:
        """``(n, 3, 3)`` corners of each ray's triangle where Embree puts them at the ray's time in [0, 1]: linear
        between the two time steps around it (``steps``: ``(V, 3)`` vertices per step, evenly spread)."""
        j, f = _step(times, len(steps))
        f = f[:, None, None]
        stacked = np.stack(steps)                                               # (S, V, 3)
        return stacked[j[:, None], self.corners] * (1 - f) + stacked[j[:, None] + 1, self.corners] * f


def _best(fn, repeat: int) -> float:
    """The shortest of ``repeat`` runs of ``fn`` (seconds): the machine is shared, the least disturbed run counts."""
    return min(fn() for _ in range(repeat))


def measure(stage: str, frame: float, shutter: tuple[float, float], slices: int, rays: int, threads: int,
            widths: tuple[int, ...], repeat: int, seed: int, frame_width: int = 64) -> dict:
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    from usdml.stage import StageDelegate

    path = library_path()
    if path is None:
        raise SystemExit("embree_motion_blur: embreex's bundled libembree4 not found")
    delegate = StageDelegate(stage)
    t_open, t_close = frame + shutter[0], frame + shutter[1]
    span = t_close - t_open
    slice_times = [t_open + (k + 0.5) / slices * span for k in range(slices)]       # the strata's centres
    step4_times = [t_open + j / 3 * span for j in range(4)]

    (static, moving, snap) = geometry_at(delegate, frame)
    poses, snap_s = {}, []
    for t in sorted(set(slice_times + step4_times + [t_open, t_close])):
        t0 = time.perf_counter()
        poses[t] = geometry_at(delegate, t)[1][0]
        snap_s.append(time.perf_counter() - t0)
        if poses[t].shape != moving[0].shape:
            raise SystemExit(f"embree_motion_blur: the moving geometry changes size at time {t:g}")
    tris = moving[1]
    out: dict = {"stage": stage, "frame": frame, "shutter": list(shutter), "slices": slices,
                 "library": path.name, "static_triangles": int(len(static[1])),
                 "moving_triangles": int(len(tris)), "moving_vertices": int(len(moving[0])),
                 "snapshot_s": statistics.median(snap_s), "threads": threads, "widths": list(widths),
                 "repeat": repeat}

    emb = Embree(path)
    ground = ([static[0]], static[1])
    ends = [poses[t_open], poses[t_close]]
    steps4 = [poses[t] for t in step4_times]

    # 1. build: the moving geometry alone (the exact backend's dynamic scene) --------------------------------
    def build_s(steps) -> float:
        def once() -> float:
            t0 = time.perf_counter()
            scene = emb.scene([(steps, tris)])
            seconds = time.perf_counter() - t0
            emb.release(scene)
            return seconds
        return _best(once, repeat)

    def embreex_once() -> float:
        t0 = time.perf_counter()
        sc = rtcs.EmbreeScene()
        TriangleMesh(sc, moving[0], tris)
        sc.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")     # commits
        return time.perf_counter() - t0

    def slices_once() -> float:
        t0 = time.perf_counter()
        for t in slice_times:
            emb.release(emb.scene([([poses[t]], tris)]))
        return time.perf_counter() - t0

    build = {"static": build_s([moving[0]]), "mb2": build_s(ends), "mb4": build_s(steps4),
             "slices": _best(slices_once, repeat), "embreex_static": _best(embreex_once, repeat)}
    build["embreex_slices"] = build["embreex_static"] * slices
    out["build_s"] = build

    # 2. trace ------------------------------------------------------------------------------------------------
    all_tris = np.concatenate([static[1], tris + len(static[0])])

    def whole(points: np.ndarray) -> np.ndarray:
        return np.concatenate([static[0], points])
    sr = ShadowRays(snap, all_tris, rays, seed)
    times = np.random.default_rng(seed + 1).random(rays).astype(np.float32)
    ray_sets = {"static": (sr.rays(whole(moving[0])), 0.0),
                "mb2": (sr.rays(sr.corners_at([whole(p) for p in ends], times)), times),
                "mb4": (sr.rays(sr.corners_at([whole(p) for p in steps4], times)), times)}
    ray_sets["still2"] = (ray_sets["static"][0], times)
    ray_sets["empty"] = ray_sets["static"]
    # still2: two identical steps, Embree's motion blur structure with nothing moving (its own cost, no swept bounds)
    scenes = {"static": emb.scene([ground, ([moving[0]], tris)]), "mb2": emb.scene([ground, (ends, tris)]),
              "mb4": emb.scene([ground, (steps4, tris)]), "still2": emb.scene([ground, ([moving[0]] * 2, tris)]),
              "empty": emb.scene([])}
    trace: dict = {"rays": rays}
    blocked: dict = {}
    loops = ["py", "c"] if compiled_loop() is not None else ["py"]
    for w in widths:
        packets = {name: Packets(*rs, ts, width=w) for name, (rs, ts) in ray_sets.items()}
        for nthreads, loop in ((k, lp) for k in sorted({1, threads}) for lp in loops):
            runs: dict = {name: [] for name in scenes}
            for _ in range(repeat):             # interleaved, so a busy moment of the machine hits every scene
                for name, scene in scenes.items():
                    packets[name].reset()
                    runs[name].append(emb.occluded(scene, packets[name], nthreads, loop == "c"))
                    blocked[name] = packets[name].blocked()
            key = f"w{w}_{nthreads}t_{loop}"
            overhead = trace[f"empty_{key}_s"] = min(runs["empty"])
            for name in ("static", "mb2", "mb4", "still2"):
                sec = trace[f"{name}_{key}_s"] = min(runs[name])
                trace[f"{name}_{key}_mrays"] = rays / sec / 1e6
                trace[f"{name}_{key}_net_mrays"] = rays / max(sec - overhead, 1e-9) / 1e6
    trace["loops"] = loops
    for name in ("static", "mb2", "mb4"):
        trace[f"{name}_blocked_fraction"] = float(blocked[name].mean())
    trace["still2_vs_static_disagree"] = int((blocked["still2"] != blocked["static"]).sum())
    ex = rtcs.EmbreeScene()
    TriangleMesh(ex, whole(moving[0]), all_tris)
    o, d, tfar = ray_sets["static"][0]
    live = tfar > 0                         # the exact backend never sends a ray of no length
    o, d, tfar = o[live], d[live], tfar[live]
    ex_hit = np.zeros(rays, bool)
    ex_hit[live] = ex.run(o, d, query="OCCLUDED", dists=tfar.copy()) != -1       # (commits)

    def embreex_once(nthreads: int) -> float:
        parts = np.array_split(np.arange(len(o)), nthreads)
        t0 = time.perf_counter()
        with ThreadPoolExecutor(nthreads) as pool:
            for f in [pool.submit(ex.run, o[i], d[i], tfar[i].copy(), "OCCLUDED") for i in parts]:
                f.result()
        return time.perf_counter() - t0
    for nthreads in sorted({1, threads}):
        trace[f"embreex_static_{nthreads}t_mrays"] = len(o) / _best(lambda: embreex_once(nthreads), repeat) / 1e6
    trace["ctypes_vs_embreex_disagree"] = int((ex_hit != blocked["static"]).sum())
    out["trace"] = trace
    for scene in scenes.values():
        emb.release(scene)

    # 3. agreement --------------------------------------------------------------------------------------------
    on_moving = sr.triangle >= len(static[1])

    def answers(geometries, rs, t) -> np.ndarray:
        scene = emb.scene(geometries)
        packets = Packets(*rs, t, width=8)
        emb.occluded(scene, packets, threads)
        emb.release(scene)
        return packets.blocked()

    agree: dict = {}
    for name, steps, step_times in (("mb2", ends, [t_open, t_close]), ("mb4", steps4, step4_times)):
        worst = 0
        for j, t in enumerate(step_times):
            tau = np.full(rays, j / (len(steps) - 1), np.float32)
            ref = answers([ground, ([poses[t]], tris)], sr.rays(whole(poses[t])), 0.0)
            got = answers([ground, (steps, tris)], sr.rays(sr.corners_at([whole(p) for p in steps], tau)), tau)
            worst = max(worst, int((ref != got).sum()))
        agree[f"{name}_at_steps_max_disagree"] = worst
    # what slices trace: ray i at slice i mod S, from and against the true pose at that slice's time
    which = np.arange(rays) % slices
    truth = np.zeros(rays, bool)
    for k, t in enumerate(slice_times):
        truth[which == k] = answers([ground, ([poses[t]], tris)], sr.rays(whole(poses[t])), 0.0)[which == k]
    tau = ((np.asarray(slice_times) - t_open) / span)[which].astype(np.float32)
    for name, steps in (("mb2", ends), ("mb4", steps4)):
        got = answers([ground, (steps, tris)], sr.rays(sr.corners_at([whole(p) for p in steps], tau)), tau)
        agree[f"{name}_vs_slices_fraction"] = float((got != truth).mean())
        agree[f"{name}_vs_slices_from_moving_fraction"] = float((got != truth)[on_moving].mean())
        agree[f"{name}_vs_slices_from_static_fraction"] = float((got != truth)[~on_moving].mean())
        dev = [np.linalg.norm(_lerp(steps, (t - t_open) / span) - poses[t], axis=1).max() for t in slice_times]
        agree[f"{name}_max_vertex_error"] = float(max(dev))
    agree["rays_from_moving_fraction"] = float(on_moving.mean())
    agree["max_vertex_motion"] = float(np.linalg.norm(poses[t_close] - poses[t_open], axis=1).max())
    agree["epsilon"] = float(sr.backend.epsilon)
    out["agreement"] = agree
    emb.close()
    sr.backend.close()

    # 5. a frame: what each way would spend on the creature's motion, from the figures above --------------------
    w, h = snap.camera.resolution(frame_width)
    shadow_rays = w * h * sr.hit_fraction * slices * sr.light_count       # every light of every visible sample
    key = f"w1_{threads}t_{trace['loops'][-1]}"        # single rays, the compiled loop where there is one
    speed = {name: trace[f"{name}_{key}_net_mrays"] * 1e6 for name in ("static", "mb2", "mb4")}
    per_frame = {"width": w, "height": h, "shadow_rays": shadow_rays, "throughput_key": key,
                 "slices_s": slices * (out["snapshot_s"] + build["embreex_static"]),
                 "slices_ctypes_s": slices * out["snapshot_s"] + build["slices"],
                 "mb2_s": 2 * out["snapshot_s"] + build["mb2"], "mb4_s": 4 * out["snapshot_s"] + build["mb4"]}
    for name in ("static", "mb2", "mb4"):
        per_frame[f"trace_{name}_s"] = shadow_rays / speed[name]
    out["per_frame"] = per_frame

    # 4. memory -----------------------------------------------------------------------------------------------
    mem: dict = {}
    for name, steps in (("static", [moving[0]]), ("mb2", ends), ("mb4", steps4)):
        dev = Embree(path, monitor=True)
        scene = dev.scene([(steps, tris)])
        mem[f"{name}_mib"] = dev.allocated / 2 ** 20
        dev.release(scene)
        dev.close()
    out["memory"] = mem
    return out


def _step(tau, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Embree's linear motion over ``count`` evenly spread time steps: for ray times ``tau`` in [0, 1], the step
    before each (int) and the weight of the step after it."""
    u = np.asarray(tau, np.float64) * (count - 1)
    j = np.minimum(u.astype(int), count - 2)
    return j, u - j


def _lerp(steps: list[np.ndarray], tau: float) -> np.ndarray:
    """``(V, 3)`` vertices where Embree puts them at ray time ``tau`` in [0, 1] between evenly spread ``steps``."""
    j, f = _step(tau, len(steps))
    return steps[int(j)] * (1 - float(f)) + steps[int(j) + 1] * float(f)


def report(r: dict) -> str:
    b, t, a, m, f = r["build_s"], r["trace"], r["agreement"], r["memory"], r["per_frame"]
    s, n = r["slices"], r["threads"]
    lines = [
        f"{r['stage']} frame {r['frame']:g}, shutter {r['shutter'][0]:g}..{r['shutter'][1]:g}: "
        f"{r['moving_triangles']} moving triangles ({r['moving_vertices']} vertices), {r['static_triangles']} static;"
        f" Embree {r['library']}; best of {r['repeat']} runs",
        f"stage read at a time (StageDelegate.snapshot and flattening): {r['snapshot_s']:.3f} s",
        "build of the moving geometry (s, Embree's own threads):",
        f"  1 step (static) {b['static']:.3f}   2 steps {b['mb2']:.3f}   4 steps {b['mb4']:.3f}   "
        f"{s} static rebuilds {b['slices']:.3f}   embreex (the exact backend's path) {b['embreex_static']:.3f}, "
        f"x{s} = {b['embreex_slices']:.2f}",
        f"shadow rays: {t['rays']} from the visible points to the lights (random pairs); blocked: static "
        f"{100 * t['static_blocked_fraction']:.1f} %, 2 steps {100 * t['mb2_blocked_fraction']:.1f} %, 4 steps "
        f"{100 * t['mb4_blocked_fraction']:.1f} % (a random time per ray); M rays/s as called from Python "
        f"(net: the same calls on an empty scene subtracted):",
    ]
    for w in r["widths"]:
        for k in sorted({1, n}):
            for loop in t["loops"]:
                key = f"w{w}_{k}t_{loop}"
                how = "a ctypes call a packet" if loop == "py" else "the compiled loop"
                lines.append(
                    f"  rtcOccluded{w}, {k} thread(s), {how}: static {t[f'static_{key}_mrays']:.2f} "
                    f"({t[f'static_{key}_net_mrays']:.2f})   2 steps {t[f'mb2_{key}_mrays']:.2f} "
                    f"({t[f'mb2_{key}_net_mrays']:.2f})   4 steps {t[f'mb4_{key}_mrays']:.2f} "
                    f"({t[f'mb4_{key}_net_mrays']:.2f})   2 still steps {t[f'still2_{key}_mrays']:.2f} "
                    f"({t[f'still2_{key}_net_mrays']:.2f})   empty scene {t[f'empty_{key}_s']:.3f} s")
    lines.append("  embreex static (rtcOccluded1 in its C loop): " + "   ".join(
        f"{k} thread(s) {t[f'embreex_static_{k}t_mrays']:.2f}" for k in sorted({1, n}))
        + f"; answers differing from ctypes': {t['ctypes_vs_embreex_disagree']}; 2 still steps differing from "
        f"static: {t['still2_vs_static_disagree']}")
    lines += [
        f"agreement at the time steps (most rays differing at one step): 2 steps {a['mb2_at_steps_max_disagree']}, "
        f"4 steps {a['mb4_at_steps_max_disagree']}",
        f"against the slices' true poses ({100 * a['rays_from_moving_fraction']:.0f} % of rays leave the moving "
        f"surface): 2 steps {100 * a['mb2_vs_slices_fraction']:.3f} % of rays differ (from the moving surface "
        f"{100 * a['mb2_vs_slices_from_moving_fraction']:.3f} %, from the static one "
        f"{100 * a['mb2_vs_slices_from_static_fraction']:.3f} %), 4 steps {100 * a['mb4_vs_slices_fraction']:.3f} % "
        f"({100 * a['mb4_vs_slices_from_moving_fraction']:.3f} % / {100 * a['mb4_vs_slices_from_static_fraction']:.3f} %)",
        f"  largest vertex off its true pose: 2 steps {a['mb2_max_vertex_error']:.4f}, 4 steps "
        f"{a['mb4_max_vertex_error']:.4f} (largest motion over the shutter {a['max_vertex_motion']:.3f}; ray epsilon "
        f"{a['epsilon']:.5f})",
        f"a frame of {f['width']} x {f['height']} px at {s} samples, {f['shadow_rays'] / 1e6:.1f} M shadow rays "
        f"(every light of every visible sample), single rays ({f['throughput_key']}): "
        f"slices {f['slices_s']:.2f} s of stage reads and embreex rebuilds ({f['slices_ctypes_s']:.2f} s with "
        f"bare Embree builds) + {f['trace_static_s']:.2f} s of tracing; 2 steps {f['mb2_s']:.2f} s + "
        f"{f['trace_mb2_s']:.2f} s; 4 steps {f['mb4_s']:.2f} s + {f['trace_mb4_s']:.2f} s",
        f"Embree's memory for the moving geometry (MiB, buffers + BVH): 1 step {m['static_mib']:.1f}   "
        f"2 steps {m['mb2_mib']:.1f}   4 steps {m['mb4_mib']:.1f}",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", default=str(ROOT / "stages" / "creature.usda"))
    ap.add_argument("--frame", type=float, default=2.0)
    ap.add_argument("--shutter", default="-0.25,0.25", help="open,close in frames around the frame")
    ap.add_argument("--slices", type=int, default=16, help="time slices a frame renders (pixel samples)")
    ap.add_argument("--frame-width", type=int, default=64, help="pixels across the frame the per-frame sums are for")
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--threads", type=int, default=2, help="Python threads tracing (besides 1)")
    ap.add_argument("--widths", default="1,8,16", help="ray packet widths to trace with (1, 4, 8, 16)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per timing (median)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print the figures as JSON after the report")
    args = ap.parse_args(argv)
    shutter = tuple(float(x) for x in args.shutter.split(","))
    widths = tuple(int(w) for w in args.widths.split(","))
    if 1 not in widths:
        ap.error("--widths must include 1 (single rays: what the exact backend traces)")
    r = measure(args.stage, args.frame, shutter, args.slices, args.rays, args.threads, widths, args.repeat, args.seed,
                args.frame_width)
    print(report(r))
    if args.json:
        print(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
