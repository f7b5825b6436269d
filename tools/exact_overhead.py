#!/usr/bin/env python
"""The exact backend's overhead over bare embreex on the same rays, in rounds (issue 19, deliverable 4).

``usdml bench`` times the exact backend and bare embreex (:class:`usdml.bench.BareEmbree`: one merged
scene, the very rays the backend traces, its chunks and thread pool) once each. On a shared machine one
pass is noisy, so this times them in turn for ``--rounds`` rounds in one process, in wall seconds and in
the process's CPU seconds (``time.process_time``: less disturbed by other load), and reports the medians
and each round's ratio exact / bare. The answers are checked: the two must agree on every query.

Usage::

    python tools/exact_overhead.py stages/city.usda --imageWidth 128 --rounds 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--imageWidth", type=int, default=128)
    p.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    p.add_argument("--rounds", type=int, default=5, help="exact, then bare, this many times (default: %(default)s)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    from usdml.bench import WARMUP, BareEmbree, exact_queries
    from usdml.stage import StageDelegate

    delegate = StageDelegate(args.stage)
    frame = delegate.start_time if args.frame is None else args.frame
    snap, exact, _, resolution, _, queries = exact_queries(delegate, args.imageWidth, frame, "time")
    origins, targets, normals, distant, _ = queries
    bare = BareEmbree(snap, exact, *queries[:4])
    exact.occluded(origins[:WARMUP], targets[:WARMUP], normals=normals[:WARMUP], distant=distant[:WARMUP])
    times = {"exact": [], "bare": []}
    cpu = {"exact": [], "bare": []}
    disagreements = 0
    for _ in range(max(1, args.rounds)):
        c0, t0 = time.process_time(), time.perf_counter()
        blocked = exact.occluded(origins, targets, normals=normals, distant=distant)
        times["exact"].append(time.perf_counter() - t0)
        cpu["exact"].append(time.process_time() - c0)
        c0 = time.process_time()
        seconds, bare_blocked = bare.run()
        times["bare"].append(seconds)
        cpu["bare"].append(time.process_time() - c0)
        disagreements = max(disagreements, int((blocked != bare_blocked).sum()))
    exact.close()

    def ratios(d):
        return [a / b for a, b in zip(d["exact"], d["bare"]) if b > 0]

    result = {
        "stage": args.stage, "frame": frame, "resolution": list(resolution), "queries": int(len(origins)),
        "rounds": len(times["exact"]), "exact_seconds": times["exact"], "bare_embree_seconds": times["bare"],
        "exact_cpu_seconds": cpu["exact"], "bare_embree_cpu_seconds": cpu["bare"],
        "overhead_wall": ratios(times), "overhead_cpu": ratios(cpu),
        "median_overhead_wall": statistics.median(ratios(times)) if ratios(times) else None,
        "median_overhead_cpu": statistics.median(ratios(cpu)) if ratios(cpu) else None,
        "disagreements": disagreements,
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    fmt = lambda xs: ", ".join(f"{x:.3f}" for x in xs)     # noqa: E731
    print(f"{args.stage}: {result['queries']:,} queries at {resolution[0]} x {resolution[1]}, "
          f"{result['rounds']} rounds, {disagreements} disagreements")
    print(f"  wall s  exact {fmt(times['exact'])}  bare {fmt(times['bare'])}")
    print(f"  cpu s   exact {fmt(cpu['exact'])}  bare {fmt(cpu['bare'])}")
    print(f"  exact / bare: wall {fmt(result['overhead_wall'])} (median {result['median_overhead_wall']:.3f}), "
          f"cpu {fmt(result['overhead_cpu'])} (median {result['median_overhead_cpu']:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
