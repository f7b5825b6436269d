#!/usr/bin/env python
"""``--gi svo`` (paper 003) against ``vpl-bruteforce`` at several VPL counts, and paper 003 Table 1's
stage timings beside usdml's.

Usage::

    python tools/svo_gi_table.py stages/cornell.usda --vpls 512,1024,2048 --imageWidth 256 --stage-width 768 --json

Per VPL count (first-bounce VPLs, ``--vpl-bounces 1``, as paper 003):

* **accuracy and speed** at ``--imageWidth`` (the primary rays per pixel of ``usdml compare``): brute
  force (every VPL, exact rays) once, then ``svo`` with its (pixel, VPL) rays through each backend of
  ``--ray-backends`` (default ``exact`` and, once registered, ``svo``): relative RMSE of ``indirect``
  as ``usdml compare`` computes it, the indirect pass's seconds and the speed-up. The two sources of
  the speed-up come apart: ``svo`` with exact rays against brute force is the sixteenth of the pairs
  (and the pairs with G = 0 skipped); ``svo`` rays against exact rays in the same pass is the cheaper
  ray (``visibility_seconds``: thread-seconds inside the backend's ``occluded``).
* **stage timings** at ``--stage-width``, one primary ray per pixel (paper 003's "no MSAA"), with the
  last backend of ``--ray-backends``: VPL generation, the rays' backend's update for the frame (for
  ``svo`` a static stage's tree comes from the cache) and, for ``svo``, a build from scratch without
  the cache (voxelization and octree, the median of 3: what every frame of a fully dynamic stage
  pays, paper 003's "scene voxelization and SVO generation"), gather (of which visibility), filter,
  and direct lighting (the stage's own lights, exact shadows).

Paper 003's figures (768×768, 128³ SVO, Titan X, Table 1) are in :data:`PAPER` for the table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: paper 003, Table 1, Cornell box (ms at 512 / 1,024 / 2,048 VPLs)
PAPER = {"resolution": [768, 768], "svo": "128³", "gpu": "NVIDIA GeForce Titan X",
         "voxelization_svo_ms": [0.57, 0.57, 0.58], "rsm_ms": [0.46, 0.46, 0.46], "vpl_generation_ms": [0.02] * 3,
         "direct_ms": [0.17, 0.17, 0.18], "indirect_ms": [16.0, 33.0, 69.0]}


def _render(delegate, settings, width: int, height: int, device: str, gi_visibility: str | None = None):
    from usdml.render.frame import FrameRenderer

    r = FrameRenderer(delegate, settings, device, gi_visibility=gi_visibility)
    try:
        return r.render(delegate.start_time, width, height, {"indirect", "direct", "depth"})
    finally:
        r.close()


def svo_build_seconds(snapshot, settings, device: str, repeats: int = 3) -> float:
    """Median seconds of building the ``svo`` backend's trees for ``snapshot`` without the cache."""
    from usdml.scene import diff
    from usdml.visibility import make_backend

    seconds = []
    for _ in range(repeats):
        b = make_backend("svo", settings, device, cache=False)
        try:
            t0 = time.perf_counter()
            b.update(snapshot, diff(None, snapshot))
            seconds.append(time.perf_counter() - t0)
        finally:
            b.close()
    return sorted(seconds)[len(seconds) // 2]


def measure(stage: str, vpls: list[int], image_width: int, stage_width: int, ray_backends: list[str],
            device: str = "cpu") -> dict:
    from usdml.compare import indirect_error
    from usdml.lighting.gi import warm_up
    from usdml.stage import StageDelegate

    d = StageDelegate(stage)
    snap = d.snapshot(d.start_time)
    width, height = snap.camera.resolution(image_width)
    sw, sh = snap.camera.resolution(stage_width)
    warm_up(device)
    base = d.usdml_settings.updated(vpl_bounces=1)
    for name in ray_backends:        # load every backend's kernels before anything is timed
        _render(d, base.updated(gi="svo", vpl_count=64), 16, 9, device, name)
    rows = []
    for n in vpls:
        s = base.updated(vpl_count=n)
        ref = _render(d, s.updated(gi="vpl-bruteforce"), width, height, device)
        ref_s = ref.stats.gi_seconds
        row = {"vpls": n, "bruteforce_seconds": ref_s, "bruteforce_rays": ref.stats.gi["shadow_rays"],
               "rays": {}}
        for name in ray_backends:
            got = _render(d, s.updated(gi="svo"), width, height, device, name)
            rmse, mean = indirect_error(got.buffers, ref.buffers)
            gi = got.stats.gi
            row["rays"][name] = {"rel_rmse": rmse / mean if mean > 0 else 0.0, "seconds": got.stats.gi_seconds,
                                 "speedup": ref_s / got.stats.gi_seconds, "shadow_rays": gi["shadow_rays"],
                                 "visibility_seconds": gi["visibility_seconds"],
                                 "update_seconds": got.stats.gi_update_seconds or 0.0}
        t0 = time.perf_counter()
        frame = _render(d, s.updated(gi="svo", pixel_samples=1), sw, sh, device, ray_backends[-1])
        total = time.perf_counter() - t0
        gi = frame.stats.gi
        row["stages"] = {"backend": ray_backends[-1], "vpl_generation": gi["vpl_seconds"] + gi["lgh_seconds"],
                         "backend_update": frame.stats.gi_update_seconds or 0.0,
                         "backend_build": (svo_build_seconds(snap, s, device) if ray_backends[-1] == "svo"
                                           else None),
                         "gather": gi["gather_seconds"], "visibility": gi["visibility_seconds"],
                         "filter": gi["filter_seconds"], "direct": frame.stats.shading_seconds,
                         "gbuffer": frame.stats.gbuffer_seconds, "frame": total,
                         "shadow_rays": gi["shadow_rays"]}
        rows.append(row)
        print(f"{n} VPLs: brute force {ref_s:.2f} s; " + "; ".join(
            f"svo with {k} rays {100 * v['rel_rmse']:.1f} %, {v['seconds']:.2f} s ({v['speedup']:.1f}x)"
            for k, v in row["rays"].items()), file=sys.stderr, flush=True)
    return {"stage": stage, "resolution": [width, height], "stage_resolution": [sw, sh], "vpl_bounces": 1,
            "device": device, "rows": rows, "paper": PAPER}


def chart(rows: list, path: str) -> None:
    """The table as charts at ``path`` (``--plot``): error and speed-up against VPLs per ray backend."""
    from usdml.plots import panels

    xs = [row["vpls"] for row in rows]
    names = list(rows[0]["rays"]) if rows else []
    panels(path, [
        dict(title="--gi svo against brute force", xlabel="VPLs", ylabel="rel. RMSE of indirect (%)", logx=True,
             series=[(n, xs, [100 * row["rays"][n]["rel_rmse"] for row in rows]) for n in names]),
        dict(title="speed", xlabel="VPLs", ylabel="speed-up over brute force (×)", logx=True,
             series=[(n, xs, [row["rays"][n]["speedup"] for row in rows]) for n in names])])


def main(argv=None) -> int:
    from usdml.visibility import backend_names

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("stage")
    ap.add_argument("--vpls", default="512,1024,2048", help="VPL counts (default: %(default)s, paper 003's)")
    ap.add_argument("--imageWidth", type=int, default=256, help="width of the accuracy renders (%(default)s)")
    ap.add_argument("--stage-width", type=int, default=768, help="width of the stage-timing frame (%(default)s)")
    default_rays = ",".join(n for n in ("exact", "svo") if n in backend_names())
    ap.add_argument("--ray-backends", default=default_rays,
                    help="backends of svo's (pixel, VPL) rays, in turn (default: %(default)s)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    args = ap.parse_args(argv)
    r = measure(args.stage, [int(v) for v in args.vpls.split(",")], args.imageWidth, args.stage_width,
                args.ray_backends.split(","), args.device)
    if args.plot:
        chart(r["rows"], args.plot)
    print(json.dumps(r, indent=2) if args.json else json.dumps(r["rows"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
