#!/usr/bin/env python
"""Seconds per frame against the number of lights (the shape of paper 000 Table VI).

For each light count N, the stage's lights are resampled to N (:func:`usdml.bench.resample_lights`:
the first N, or all of them plus jittered copies), and each backend renders two consecutive frames
through the renderer; the second frame is timed (the steady state of a sequence: per-frame arrays
rebuilt, static ones kept). Reported per backend and N: frame seconds and its split (scene update,
of which the voxel per-frame rebuild; G-buffer; shading), and the voxel/exact ratio of the same run.

Usage::

    python tools/light_scaling.py stages/creature.usda --lights 512,1024,2048,4096,10000 --imageWidth 192
    python tools/light_scaling.py stages/park.usda --fully-dynamic --json

Voxel settings come from the stage (``usdml:voxel:*``) and the flags below.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
import sys


def chart(rows: list, path: str) -> None:
    """The table as a chart at ``path`` (``--plot``): seconds per frame against lights, per backend."""
    from usdml.plots import panels

    names = [k for k in rows[0] if isinstance(rows[0][k], dict)] if rows else []
    stage = rows[0]["stage"].rsplit("/", 1)[-1] if rows else ""
    panels(path, [dict(title=f"seconds per frame ({stage})", xlabel="lights", ylabel="frame (s)", logx=True, logy=True,
                       series=[(n, [r["lights"] for r in rows], [r[n]["seconds"] for r in rows]) for n in names])])


def main(argv: list[str] | None = None) -> int:
    from usdml.params import add_cmdline_args, overrides_from_args

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--lights", default="512,1024,2048,4096,10000", help="comma-separated light counts")
    p.add_argument("--imageWidth", type=int, default=192)
    p.add_argument("--frame", type=float, help="first of the two frames (default: the stage's start)")
    p.add_argument("--visibility", default="voxel,exact", metavar="NAME[,NAME...]",
                   help="visibility backends to time, comma-separated (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the resampled lights (default: %(default)s)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    add_cmdline_args(p, "bench")      # the voxel settings, as usdml bench takes them
    args = p.parse_args(argv)

    from usdml.bench import next_frame, resample_lights, steady_frame
    from usdml.stage import StageDelegate
    from usdml.visibility.base import STATS

    delegate = StageDelegate(args.stage)
    settings = delegate.usdml_settings.updated(
        **overrides_from_args(args),
        pixel_samples=1)     # one primary ray per pixel: the visibility backends' cost, not anti-aliasing's
    f0 = delegate.start_time if args.frame is None else args.frame
    f1 = next_frame(delegate, f0)
    rows = []
    for n in [int(x) for x in args.lights.split(",")]:
        original = delegate.snapshot

        def snapshot(t, _n=n, _orig=original):
            s = _orig(t)
            return replace(s, lights=resample_lights(s.lights, _n, args.seed))

        delegate.snapshot = snapshot
        try:
            row = {"stage": args.stage, "lights": n, "frame": f1}
            for name in args.visibility.split(","):
                w, h = delegate.snapshot(f0).camera.resolution(args.imageWidth)
                with steady_frame(delegate, settings.updated(visibility=name), f0, w, h) as (res, seconds, r):
                    st = res.stats
                    row[name] = {"seconds": seconds, "update_seconds": st.update_seconds,
                                 "gbuffer_seconds": st.gbuffer_seconds, "shading_seconds": st.shading_seconds,
                                 "resolution": [w, h]}
                    if name == "voxel":
                        b = r.backends.shadow
                        row[name].update(rebuilt=b.built, rebuild_seconds=b.stats["dynamic_seconds"] if b.built else 0.0,
                                         voxel_resolution=b.resolution, direction_step=b.step,
                                         fully_dynamic=b.fully_dynamic, mapping=b.mapping)
                    elif r.backends.shadow.supports(STATS) and name != "exact":
                        row[name].update(r.backends.shadow.describe())     # e.g. insm: its per-frame timings
            for name in args.visibility.split(","):
                if name != "exact" and "exact" in row:
                    row[f"{name}_speedup_vs_exact"] = row["exact"]["seconds"] / row[name]["seconds"]
            rows.append(row)
            if not args.json:
                parts = [f"{n:>6} lights"]
                for name in args.visibility.split(","):
                    b = row[name]
                    extra = f", rebuild {b['rebuild_seconds']:.2f}" if name == "voxel" else ""
                    parts.append(f"{name} {b['seconds']:.2f} s (update {b['update_seconds']:.2f}{extra}, "
                                 f"shading {b['shading_seconds']:.2f})")
                parts += [f"{name} {row[f'{name}_speedup_vs_exact']:.2f}x exact" for name in args.visibility.split(",")
                          if f"{name}_speedup_vs_exact" in row]
                print("; ".join(parts), flush=True)
        finally:
            delegate.snapshot = original
    if args.plot:
        chart(rows, args.plot)
    if args.json:
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
