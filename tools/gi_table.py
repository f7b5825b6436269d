#!/usr/bin/env python
"""Paper 004's figures for one stage: LGH indirect light against VPL brute force, many settings, one run.

Usage::

    python tools/gi_table.py stages/cornell.usda [--vpls 10000] [--imageWidth 96] [--alphas 1,2]
        [--samples 1,4] [--start-levels 1,0] [--filter-iterations -1] [--frame F] [--json]

The G-buffer and the VPLs (same seed) are made once; ``vpl-bruteforce`` (every VPL, exact
visibility) runs once and every LGH setting is timed against it, so the table costs one brute-force
pass instead of one per row. Each row is what ``usdml compare STAGE --gi lgh --against
vpl-bruteforce`` reports for that setting: ``rel_rmse`` of ``indirect`` radiance over the pixels that
see geometry (divided by the reference mean), the seconds of the whole indirect pass (VPLs, LGH
construction, lighting, shadow rays, filter) and their split, and the speed-up. Warp's kernels are
loaded before anything is timed.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("stage")
    p.add_argument("--vpls", type=int, default=10_000)
    p.add_argument("--imageWidth", type=int, default=96)
    p.add_argument("--alphas", default="1,2")
    p.add_argument("--samples", default="1,4")
    p.add_argument("--start-levels", default="1,0")
    p.add_argument("--filter-iterations", default="-1", help="à-trous iterations to try (-1: by samples)")
    p.add_argument("--frame", type=float)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    from gi_frame import open_frame
    from usdml.lighting.gi import indirect_lighting, warm_up
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer

    delegate, frame, snap, renderer, lights = open_frame(args.stage, args.frame)
    width, height = snap.camera.resolution(args.imageWidth)
    base = delegate.usdml_settings.updated(vpl_count=args.vpls)
    snap = replace(snap, camera=conform_camera(snap.camera, width, height))
    gb = build_gbuffer(snap, renderer.exact, width, height)
    hit = gb.hit.ravel()
    points, normals, albedo = (a.reshape(-1, 3)[hit] for a in (gb.position, gb.normal, gb.albedo))
    warm = warm_up()

    def run(settings):
        t0 = time.perf_counter()
        r = indirect_lighting(snap, renderer.exact, renderer.exact.occluded, lights, points, normals, albedo,
                              settings, image=(gb.hit, gb.position))
        return r, time.perf_counter() - t0

    ref, ref_s = run(base.updated(gi="vpl-bruteforce"))
    b = ref.radiance.astype(np.float64)
    mean = float(b.mean())
    rows = []
    for alpha in map(float, args.alphas.split(",")):
        for k in _ints(args.samples):
            for start, iterations in ((s, i) for s in _ints(args.start_levels) for i in _ints(args.filter_iterations)):
                r, s = run(base.updated(gi="lgh", lgh_alpha=alpha, shadow_samples=k, lgh_start_level=start,
                                        shadow_filter_iterations=iterations))
                rmse = float(np.sqrt(np.mean((r.radiance.astype(np.float64) - b) ** 2)))
                split = {key: r.stats.get(key, 0.0) for key in
                         ("vpl_seconds", "lgh_seconds", "lighting_seconds", "shadow_seconds", "filter_seconds")}
                rows.append({"alpha": alpha, "shadow_samples": k, "start_level": start,
                             "filter_iterations": r.stats.get("filter_iterations"),
                             "rel_rmse": rmse / mean if mean > 0 else 0.0, "seconds": s,
                             "speedup": ref_s / s if s > 0 else float("inf"), **split,
                             "lgh_levels": r.stats.get("lgh_levels"), "shadow_rays": r.stats.get("shadow_rays")})
    renderer.close()
    result = {"stage": args.stage, "frame": frame, "resolution": [width, height], "pixels": int(hit.sum()),
              "vpls": ref.stats.get("vpls", 0), "bruteforce_seconds": ref_s, "warmup_seconds": warm, "rows": rows}
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{args.stage} frame {frame:g}, {width}x{height} ({result['pixels']:,} pixels), {result['vpls']:,} VPLs; "
          f"vpl-bruteforce {ref_s:.2f} s")
    print("| α | k | start | filter it. | rel. RMSE | seconds | speed-up | VPLs | LGH | lighting | shadow rays "
          "| filter |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['alpha']:g} | {r['shadow_samples']} | S{r['start_level']} | {r['filter_iterations']} | "
              f"{100 * r['rel_rmse']:.1f} % | "
              f"{r['seconds']:.3f} | {r['speedup']:.0f}× | {r['vpl_seconds']:.3f} | {r['lgh_seconds']:.3f} | "
              f"{r['lighting_seconds']:.3f} | {r['shadow_seconds']:.3f} | {r['filter_seconds']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
