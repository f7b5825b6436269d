#!/usr/bin/env python
"""Lighting grid hierarchy construction time against the number of VPLs (paper 004 Tables 1–2).

Usage::

    python tools/lgh_build_times.py stages/cornell.usda [--vpls 1000,10000,100000,1000000] [--repeat 5]
        [--frame F] [--device cpu] [--json]

For each count the stage's VPLs are generated (3 bounces, seed 0, as ``--gi lgh`` does) and the
hierarchy is built ``--repeat`` times after Warp's kernels are loaded; the median build and its split
(bounds, automatic level count, S1 scatter, gather of the higher levels, compaction, merge) are
printed, with the levels, the non-empty S1 grid lights and the VPL generation time.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

STEPS = ("bounds", "auto_levels", "s1", "gather", "compaction", "merge")


def chart(rows: list, path: str) -> None:
    """The table as a chart at ``path`` (``--plot``): build seconds, and each step's, against VPLs."""
    from usdml.plots import panels

    xs = [r["vpls"] for r in rows]
    panels(path, [dict(title="LGH build (paper 004 Table 1)", xlabel="VPLs", ylabel="seconds", logx=True, logy=True,
                       series=[("build", xs, [r["seconds"] for r in rows])]
                       + [(k, xs, [max(r[f"{k}_seconds"], 1e-6) for r in rows]) for k in STEPS])])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--vpls", default="1000,10000,100000,1000000")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--frame", type=float)
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    args = p.parse_args(argv)

    from gi_frame import open_frame
    from usdml.lighting.gi import warm_up
    from usdml.lighting.lgh.build import build_lgh
    from usdml.lighting.vpl import generate_vpls

    _, frame, snap, renderer, lights = open_frame(args.stage, args.frame)
    warm_up(args.device)
    rows = []
    for count in (int(x) for x in args.vpls.split(",") if x):
        t0 = time.perf_counter()
        vpls = generate_vpls(snap, renderer.backends.primary, lights, count, 3, 0)
        intensity = vpls.flux / np.float32(4.0 * np.pi)     # as usdml.lighting.gi builds it, normals included
        vpl_seconds = time.perf_counter() - t0
        builds = []
        for _ in range(max(1, args.repeat)):
            t0 = time.perf_counter()
            lgh = build_lgh(vpls.position, intensity, device=args.device, normal=vpls.normal)
            builds.append((time.perf_counter() - t0, lgh.stats))
        builds.sort(key=lambda b: b[0])
        seconds, stats = builds[len(builds) // 2]
        rows.append({"vpls": len(vpls.position), "seconds": seconds, "vpl_seconds": vpl_seconds,
                     "levels": stats["levels"], "lights_per_level": stats["lights_per_level"],
                     **{f"{k}_seconds": stats[k] for k in STEPS}})
    renderer.close()
    if args.plot:
        chart(rows, args.plot)
    if args.json:
        print(json.dumps({"stage": args.stage, "frame": frame, "device": args.device, "rows": rows}, indent=2))
        return 0
    print(f"{args.stage} frame {frame:g}, device {args.device}, median of {args.repeat} builds (ms)")
    print("| VPLs | build | " + " | ".join(STEPS) + " | levels | S1 lights | VPL generation |")
    print("|---" * (len(STEPS) + 5) + "|")
    for r in rows:
        print(f"| {r['vpls']:,} | **{1e3 * r['seconds']:.1f}** | "
              + " | ".join(f"{1e3 * r[f'{k}_seconds']:.1f}" for k in STEPS)
              + f" | {r['levels']} | {r['lights_per_level'][0]:,} | {1e3 * r['vpl_seconds']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
