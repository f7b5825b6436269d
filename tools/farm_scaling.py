#!/usr/bin/env python
"""Frames per second on Dask: one local worker of one thread against two of one thread each, the same
sequence, the cluster's start-up reported (issue: two workers >= 1.7x one on this 2-core machine).

Usage::

    python tools/farm_scaling.py stages/park.usda --frames 1:12 --imageWidth 96 --json

Each run renders into a fresh folder (nothing resumed); runs go one worker, two workers, one, two, and
each setting's best is kept (the machine's speed drifts).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--frames", default="1:12")
    p.add_argument("--imageWidth", type=int, default=96)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    import usdml

    runs = {1: [], 2: []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for workers in (1, 2):
                rec = usdml.Recorder(image_width=args.imageWidth, aovs=["color"], pixel_samples=1, workers=workers,
                                     nthreads=1, chunk_size=1)
                res = rec.record_sequence(args.stage, args.frames, f"{tmp}/r{r}w{workers}/f.####.exr")
                s = res.summary
                runs[workers].append({"seconds": s["seconds"], "startup_seconds": s["startupSeconds"],
                                      "frames": len(s["frames"]), "failed": len(s["failed"]),
                                      "frames_per_second": len(s["frames"]) / (s["seconds"] - s["startupSeconds"])})
    best = {w: max(v, key=lambda x: x["frames_per_second"]) for w, v in runs.items()}
    out = {"stage": args.stage, "frames": args.frames, "imageWidth": args.imageWidth, "runs": runs,
           "one_worker_fps": best[1]["frames_per_second"], "two_workers_fps": best[2]["frames_per_second"],
           "speedup": best[2]["frames_per_second"] / best[1]["frames_per_second"],
           "startup_seconds": [x["startup_seconds"] for v in runs.values() for x in v]}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"1 worker {out['one_worker_fps']:.2f} frames/s, 2 workers {out['two_workers_fps']:.2f}: "
              f"{out['speedup']:.2f}x; cluster start-up {min(out['startup_seconds']):.1f}-"
              f"{max(out['startup_seconds']):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
