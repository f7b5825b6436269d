#!/usr/bin/env python
"""The lighting grid hierarchy on the seeded suite (issue 37): ``--gi lgh`` and ``--direct lgh`` against brute force.

Usage::

    python tools/make_stages.py --suite --out /tmp/suite --seeds 0-3 --lights 64,1024,100000
    python tools/lgh_suite.py /tmp/suite [--split report] [--gi-vpls 10000] [--gi-lights 64,1024]
        [--direct-lights 100000] [--imageWidth 96] [--direct-width 128] [--direct-height 0] [--reference-pixels 2048]
        [--lgh-split none,normal] [--direct-gather hierarchy,each] [--json]

For each suite stage of the split (``report``: odd seeds, never tuned on; ``tune``; ``all``), what
``usdml compare`` reports on its start frame with the stage's and usdml's default settings:

* stages with a light count in ``--gi-lights``: ``--gi lgh --against vpl-bruteforce --vpls N`` for each N of
  ``--gi-vpls`` and each ``--lgh-split`` (default: usdml's) (relative RMSE of ``indirect`` over the reference's
  mean; the indirect passes' speed-up);
* stages with a light count in ``--direct-lights``: ``--direct lgh --against all`` for each
  ``--direct-gather`` (default: usdml's) (relative RMSE of ``direct``; the frame's speed-up, the reference on
  ``--reference-pixels`` pixels with its seconds extrapolated to the frame when that is above 0);

each with the frame's own estimate of its error, its 95 % interval and whether the interval holds the
measurement. Rows print as they finish (stderr); ``--json`` writes them all to stdout at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from stage_suite import split as seed_split  # noqa: E402


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def suite_stages(folder: str, which: str) -> list[tuple[str, dict]]:
    """``(path, {"kind", "lights", "seed", "split"})`` of the suite stages under ``folder`` in split ``which``."""
    from pxr import Sdf

    out = []
    for name in sorted(os.listdir(folder)):
        if not (name.startswith("suite_") and name.endswith(".usda")):
            continue
        path = os.path.join(folder, name)
        info = dict(Sdf.Layer.FindOrOpen(path).customLayerData.get("suite", {}))
        if not info:
            continue
        if which != "all" and seed_split(int(info["seed"])) != which:
            continue
        out.append((path, info))
    return out


def _row(kind: str, path: str, info: dict, r: dict, **extra) -> dict:
    lo, hi = r.get("estimated_rel_rmse_interval", [None, None])
    return {"stage": os.path.basename(path), "kind": info["kind"], "lights": int(info["lights"]),
            "seed": int(info["seed"]), "split": seed_split(int(info["seed"])), "scale": info.get("scale"),
            "mode": kind, "resolution": r["resolution"], "rel_rmse": r["rel_rmse"], "speedup": r["speedup"],
            "estimated_rel_rmse": r.get("estimated_rel_rmse"), "estimated_interval": [lo, hi],
            "estimate_holds": r.get("estimate_holds"), "seconds": r["seconds"], **extra}


def measure(folder: str, which: str, gi_vpls: list[int], gi_lights: list[int], direct_lights: list[int],
            width: int, direct_width: int, reference_pixels: int, splits: list[str | None] = (None,),
            gathers: list[str | None] = (None,), direct_height: int = 0) -> list[dict]:
    from usdml.compare import compare_direct, compare_gi
    from usdml.stage import StageDelegate

    rows = []
    for path, info in suite_stages(folder, which):
        lights = int(info["lights"])
        t0 = time.perf_counter()
        if lights in gi_lights:
            for n in gi_vpls:
                for split_by in splits:
                    r = compare_gi(StageDelegate(path), "lgh", "vpl-bruteforce", image_width=width,
                                   overrides={"vpl_count": n, **({} if split_by is None else {"lgh_split": split_by})})
                    rows.append(_row("gi", path, info, r, vpls=n, asked=split_by or "default", settings={
                        k: r[k] for k in ("lgh_alpha", "shadow_samples", "lgh_start_level", "shadow_targets",
                                          "lgh_split")},
                        breakdown=r["breakdown"].get("lgh", {})))
                    _tell(rows[-1], time.perf_counter() - t0)
        for gather in gathers if lights in direct_lights else ():
            r = compare_direct(StageDelegate(path), "lgh", "all", image_width=direct_width,
                               image_height=direct_height or None,
                               reference_pixels=reference_pixels,
                               overrides={} if gather is None else {"direct_gather": gather})
            rows.append(_row("direct", path, info, r, direct_speedup=r["direct_speedup"],
                             reference_extrapolated=r["reference_extrapolated"],
                             compared_pixels=r["compared_pixels"], asked=gather or "default",
                             settings={k: r[k] for k in ("direct_alpha", "direct_shadow_samples", "direct_gather")},
                             breakdown=r["breakdown"].get("lgh", {})))
            _tell(rows[-1], time.perf_counter() - t0)
    return rows


def _tell(r: dict, seconds: float) -> None:
    est = ("" if r["estimated_rel_rmse"] is None else
           f", estimated {100 * r['estimated_rel_rmse']:.1f} % [{100 * r['estimated_interval'][0]:.1f}, "
           f"{100 * r['estimated_interval'][1]:.1f}] ({'holds' if r['estimate_holds'] else 'MISSES'})")
    what = (f"{r.get('vpls', 0):,} VPLs, split {r['settings'].get('lgh_split')}" if r["mode"] == "gi"
            else f"{r['lights']:,} lights, {r['settings'].get('direct_gather')}")
    print(f"{r['stage']} --{r['mode']} lgh, {what}: {100 * r['rel_rmse']:.2f} % at {r['speedup']:.1f}x{est} "
          f"({seconds:.0f} s)", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    p.add_argument("folder", help="where tools/make_stages.py --suite wrote the stages")
    p.add_argument("--split", choices=("report", "tune", "all"), default="report")
    p.add_argument("--gi-vpls", default="10000", metavar="N[,N...]")
    p.add_argument("--gi-lights", default="64,1024", metavar="N[,N...]", help="stages measured with --gi lgh")
    p.add_argument("--direct-lights", default="100000", metavar="N[,N...]", help="stages measured with --direct lgh")
    p.add_argument("--imageWidth", type=int, default=96, help="--gi lgh width (%(default)s)")
    p.add_argument("--direct-width", type=int, default=128, help="--direct lgh width (%(default)s)")
    p.add_argument("--direct-height", type=int, default=0,
                   help="--direct lgh height, the camera conformed to it (0: the camera's aspect)")
    p.add_argument("--reference-pixels", type=int, default=2048,
                   help="--direct: pixels every-light shading runs on, its time extrapolated (0: every pixel)")
    p.add_argument("--lgh-split", default=None, metavar="S[,S...]",
                   help="--gi lgh: each of these --lgh-split values (none, normal) in turn (default: usdml's)")
    p.add_argument("--direct-gather", default=None, metavar="G[,G...]",
                   help="--direct lgh: each of these --direct-gather values (hierarchy, each) in turn (default: usdml's)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if not os.path.isdir(args.folder):
        p.error(f"{args.folder}: no such folder (write the suite with tools/make_stages.py --suite --out DIR)")
    rows = measure(args.folder, args.split, _ints(args.gi_vpls), _ints(args.gi_lights), _ints(args.direct_lights),
                   args.imageWidth, args.direct_width, args.reference_pixels,
                   args.lgh_split.split(",") if args.lgh_split else [None],
                   args.direct_gather.split(",") if args.direct_gather else [None], args.direct_height)
    if not rows:
        p.error(f"{args.folder}: no suite stage of split {args.split!r} with those light counts")
    if args.json:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
