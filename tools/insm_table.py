#!/usr/bin/env python
"""Paper 001's Tables 2-4 on usdml's stages: the insm backend's error against exact as the depth
images' resolution ``w``, the per-light maps' resolution ``S`` and the number of depth images ``K``
change (the others at the paper's 128, 512, 10), with each setting's cost per frame.

Usage::

    python tools/insm_table.py stages/dragon.usda stages/city.usda --imageWidth 128 --json
    python tools/insm_table.py stages/park.usda --dynamic --imageWidth 256 --json

Per row: ε_v, ε_s (``usdml compare``'s, paper 001's "average pixel shadow value error" is ε_s), the
reconstructed triangles, and the frame's insm seconds: depth images + triangulation + the maps,
receiver tiles and lookups of every light (one run; exact's query seconds on the same pairs beside).

``--dynamic``: a moving stage's frame (geometry changed: depth images cast again) against the same
frame rendered again (nothing moved: the triangles kept), one renderer, each timed twice.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

SWEEPS = {"insm_resolution": (32, 64, 128, 256), "insm_light_resolution": (128, 256, 512, 1024),
          "insm_count": (2, 6, 10, 14, 20)}
PAPER = {"insm_resolution": 128, "insm_light_resolution": 512, "insm_count": 10}


def sweep(stage: str, width: int) -> list[dict]:
    from usdml.compare import compare_visibility
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    rows, done = [], {}
    for field, values in SWEEPS.items():
        for v in values:
            setting = dict(PAPER, **{field: v})
            key = tuple(sorted(setting.items()))
            if key not in done:
                r = compare_visibility(delegate, "insm", image_width=width, overrides=setting)
                frame = r["seconds"]["insm"] + r["depth_seconds"] + r["triangulate_seconds"]
                done[key] = {"stage": stage, **setting, "eps_v": r["eps_v"], "eps_s": r["eps_s"],
                             "wrongly_hidden": r["wrongly_hidden"], "wrongly_visible": r["wrongly_visible"],
                             "triangles": r["reconstructed_triangles"], "frame_seconds": frame,
                             "depth_seconds": r["depth_seconds"], "triangulate_seconds": r["triangulate_seconds"],
                             "receiver_seconds": r["receiver_seconds"], "map_seconds": r["map_seconds"],
                             "lookup_seconds": r["lookup_seconds"], "exact_seconds": r["seconds"]["exact"],
                             "pixels": r["pixels"], "lights": r["lights"], "resolution": r["resolution"],
                             "cpu_kernel": r["cpu_kernel"]}
                print(f"{stage} {setting}: eps_s {100 * r['eps_s']:.2f} %, {frame:.1f} s", file=sys.stderr)
            rows.append(dict(done[key], sweep=field))
    return rows


def dynamic(stage: str, width: int) -> dict:
    from usdml.bench import next_frame
    from usdml.render.frame import FrameRenderer
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    settings = delegate.usdml_settings.updated(visibility="insm", pixel_samples=1)
    r = FrameRenderer(delegate, settings, backend_options={"report": lambda s: None})
    f0 = delegate.start_time
    f1 = next_frame(delegate, f0)
    w, h = delegate.snapshot(f0).camera.resolution(width)
    out = {"stage": stage, "resolution": [w, h], "moving": [], "still": []}
    try:
        r.render(f0, w, h, {"color"})
        for _ in range(2):
            for label, frame in (("moving", f1), ("moving", f0), ("still", f0)):
                t0 = time.perf_counter()
                res = r.render(frame, w, h, {"color"})
                seconds = time.perf_counter() - t0
                out[label].append({"frame": frame, "seconds": seconds,
                                   "depth_seconds": r.backends.shadow.stats["depth_seconds"],
                                   "triangulate_seconds": r.backends.shadow.stats["triangulate_seconds"],
                                   "update_seconds": res.stats.update_seconds, "lights": res.stats.lights})
    finally:
        r.close()
    out["triangles"] = r.backends.shadow.triangles
    for label in ("moving", "still"):
        out[f"{label}_seconds"] = min(x["seconds"] for x in out[label])
    out["moving_over_still"] = out["moving_seconds"] / out["still_seconds"]
    return out


def chart(rows: list, path: str) -> None:
    """The sweeps as charts at ``path`` (``--plot``): ε_s against w, S and K (paper 001 Tables 2-4)."""
    from usdml.plots import panels, series

    stage = lambda r: r["stage"].rsplit("/", 1)[-1].removesuffix(".usda")
    panels(path, [dict(title=f"paper 001 Table {t}", xlabel=label, ylabel="ε_s against exact (%)",
                       logx=field != "insm_count",
                       series=series([r for r in rows if r["sweep"] == field], field, lambda r: 100 * r["eps_s"], stage))
                  for t, field, label in ((2, "insm_resolution", "depth-image resolution w (pixels)"),
                                          (3, "insm_light_resolution", "light-map resolution S (texels)"),
                                          (4, "insm_count", "depth images K"))])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stages", nargs="+")
    p.add_argument("--imageWidth", type=int, default=128)
    p.add_argument("--dynamic", action="store_true", help="a moving frame against a still one (module doc)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    args = p.parse_args(argv)
    if args.dynamic:
        result = {"dynamic": [dynamic(s, args.imageWidth) for s in args.stages]}
    else:
        result = {"rows": [row for s in args.stages for row in sweep(s, args.imageWidth)]}
    if args.plot and "rows" in result:
        chart(result["rows"], args.plot)
    print(json.dumps(result, indent=2) if args.json else result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
