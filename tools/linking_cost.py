#!/usr/bin/env python
"""What light and shadow linking cost a frame (issue 52, "Cost"): a frame with linking against the same frame
without it.

The stage is :func:`linking_reference.instanced_stage`: ``--lights`` point lights instanced by a PointInstancer
from two prototype lights whose collections differ (two light-link sets and a shadow-link set) over a ground and
``--boxes`` boxes, a third of them instanced by a second PointInstancer. ``--rules``: ``scene``, the accuracy
stage's rules (``warm`` lights only the PointInstancer's boxes and one box, ``cool`` everything but those boxes,
shadowed by all but one box: the linked lights reach fewer pixels, so the linked frame does less work), and
``one box``, each prototype light unlinked from one box and ``cool`` unshadowed by a third (nearly the same pairs
as without links: what the machinery itself costs). The lights drift frame to frame, so frame 2 is a new frame:
its lights and their link sets are read again. The frame without linking is the same stage written without the
collections (same lights, same groups).

For each case (``lights:mode``; mode ``exact`` and ``voxel``: ``--direct all`` with that visibility; ``lgh``:
``--direct lgh``) both stages render frames 1 and 2 with one renderer, one ray per pixel, each timed (frame 2: a
sequence's steady state, the issue's figure; frame 1 also builds what a link set needs). The two stages are
interleaved (without, with, without, with ... for ``--repeat`` pairs), so a load that comes and goes on a shared
machine falls on both, and each pair gives a ratio (with / without). Reported, for frame 2 and for frame 1: each
pair's seconds and ratio, the median ratio and the ratio of the best times. The issue's targets: ≤ 1.2× at 1,024
lights (exact, voxel, lgh), ≤ 1.5× at 100,000 lights with two link sets (lgh).

Usage::

    .venv/bin/python tools/linking_cost.py                                  # the issue's four cases
    .venv/bin/python tools/linking_cost.py --cases 1024:exact --repeat 5 --imageWidth 96
    .venv/bin/python tools/linking_cost.py --json > cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: mode -> usdml settings
MODES = {"exact": {"visibility": "exact", "direct": "all"},
         "voxel": {"visibility": "voxel", "direct": "all"},
         "lgh": {"visibility": "exact", "direct": "lgh"}}
#: lights -> the issue's bound on the ratio
TARGETS = {1024: 1.2, 100_000: 1.5}


def timed_frames(stage: str, mode: str, width: int) -> dict:
    """Frames 1 and 2 of ``stage`` with one renderer, ``mode``'s settings, one ray per pixel: the seconds of each
    (frame 1 builds what the frame's link sets need; frame 2 is a sequence's steady state)."""
    from usdml.bench import next_frame
    from usdml.render.frame import FrameRenderer
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    settings = delegate.usdml_settings.updated(pixel_samples=1, gi="none", **MODES[mode])
    f0 = delegate.start_time
    w, h = delegate.snapshot(f0).camera.resolution(width)
    r = FrameRenderer(delegate, settings, backend_options={"report": lambda s: None})
    try:
        seconds = []
        for frame in (f0, next_frame(delegate, f0)):
            t0 = time.perf_counter()
            res = r.render(frame, w, h, {"color"})
            seconds.append(time.perf_counter() - t0)
    finally:
        r.close()
    st = res.stats
    return {"seconds": seconds[1], "first_seconds": seconds[0], "snapshot_seconds": st.snapshot_seconds,
            "shading_seconds": st.shading_seconds, "resolution": [w, h]}


def measure(lights: int, mode: str, width: int, repeat: int, seed: int, boxes: int, rules: str,
            folder: Path) -> dict:
    from linking_reference import instanced_stage

    tag = rules.replace(" ", "_")
    stages = {linked: str(folder / f"cost_{lights}_{tag if linked else 'none'}_{seed}_{boxes}.usda")
              for linked in (False, True)}
    for linked, path in stages.items():
        if not Path(path).exists():
            instanced_stage(path, seed, lights, linked, boxes=boxes - boxes // 3, scattered=boxes // 3, frames=2,
                            rules=rules)
    pairs = []
    for _ in range(max(1, repeat)):
        without = timed_frames(stages[False], mode, width)
        with_ = timed_frames(stages[True], mode, width)
        pairs.append({"without": without, "with": with_, "ratio": with_["seconds"] / without["seconds"],
                      "first_ratio": with_["first_seconds"] / without["first_seconds"]})

    def best(key):
        return min(p["with"][key] for p in pairs) / min(p["without"][key] for p in pairs)
    return {"lights": lights, "mode": mode, "rules": rules, "resolution": pairs[0]["with"]["resolution"],
            "pairs": pairs, "median_ratio": statistics.median(p["ratio"] for p in pairs), "best_ratio": best("seconds"),
            "first_median_ratio": statistics.median(p["first_ratio"] for p in pairs),
            "first_best_ratio": best("first_seconds"), "target": TARGETS.get(lights)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--cases", default="1024:exact,1024:voxel,1024:lgh,100000:lgh",
                   help="lights:mode, comma-separated (modes: exact, voxel, lgh; default: %(default)s)")
    p.add_argument("--imageWidth", type=int, default=128, help="frame width in pixels (default: %(default)s)")
    p.add_argument("--repeat", type=int, default=3, help="interleaved pairs per case (default: %(default)s)")
    p.add_argument("--boxes", type=int, default=24, help="boxes on the stage (default: %(default)s)")
    p.add_argument("--rules", default="scene,one box", help="the stage's link rules, comma-separated "
                   "(linking_reference.INSTANCED_RULES; default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="stage seed (odd: reporting; default: %(default)s)")
    p.add_argument("--out", help="folder for the stages (default: a temporary one)")
    p.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = p.parse_args(argv)

    from command_timing import machine

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.out or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for case in args.cases.split(","):
            for rules in args.rules.split(","):
                lights, mode = case.split(":")
                row = measure(int(lights), mode, args.imageWidth, args.repeat, args.seed, args.boxes, rules, folder)
                rows.append(row)
                if not args.json:
                    w, h = row["resolution"]
                    each = ", ".join(f"{q['without']['seconds']:.2f}/{q['with']['seconds']:.2f}" for q in row["pairs"])
                    target = f" (target {row['target']}x)" if row["target"] else ""
                    print(f"{int(lights):>7d} lights {mode:5s} {rules!r:9s} {w}x{h}: frame 2 without/with {each} s; "
                          f"median ratio {row['median_ratio']:.3f}x, best {row['best_ratio']:.3f}x{target}; frame 1: "
                          f"median {row['first_median_ratio']:.3f}x, best {row['first_best_ratio']:.3f}x", flush=True)
    if args.json:
        print(json.dumps({"argv": sys.argv[1:] if argv is None else argv, "seed": args.seed, "boxes": args.boxes,
                          "image_width": args.imageWidth,
                          "machine": machine() | {"load_average": list(os.getloadavg())},
                          "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
