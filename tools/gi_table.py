#!/usr/bin/env python
"""Paper 004's figures for one stage: LGH indirect light against VPL brute force, many settings, one run.

Usage::

    python tools/gi_table.py stages/cornell.usda [--vpls 10000] [--imageWidth 96] [--lgh-alpha 1,2]
        [--shadow-samples 1,4] [--lgh-start-level 1,0] [--shadow-filter-iterations -1] [--frame F]
        [--lgh-split none,normal] [--visibility exact] [--reference-visibility exact] [--reference FILE.npz]
        [--hierarchy] [--json]

The G-buffer and the VPLs (same seed) are made once; ``vpl-bruteforce`` (every VPL, exact
visibility) runs once and every LGH setting is timed against it, so the table costs one brute-force
pass instead of one per row. Each row is what ``usdml compare STAGE --gi lgh --against
vpl-bruteforce`` reports for that setting: ``rel_rmse`` of ``indirect`` radiance over the pixels that
see geometry (divided by the reference mean), the seconds of the whole indirect pass (VPLs, LGH
construction, lighting, shadow rays, filter) and their split, and the speed-up. Warp's kernels are
loaded before anything is timed.

``--visibility`` is the backend of the LGH's shadow rays (voxel arrays are built, or read from the
cache, before anything is timed), ``--reference-visibility`` that of brute force (exact, the
reference). ``--reference FILE.npz`` keeps the brute-force radiance and its seconds: written on the
first run, read on later runs with the same stage, frame, VPLs, width and visibility (checked), so
that trying LGH settings does not repeat an expensive brute-force pass.

``--hierarchy`` splits each row's error: the same LGH setting and brute force both without shadows
(``hierarchy_rel_rmse``: the grid lights, their blending and lobes, against every VPL), one more
brute-force pass without rays. An ``--lgh-alpha`` or ``--shadow-samples`` of 0 is usdml's automatic
choice; the rows give what the frame chose.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

import numpy as np


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def chart(rows: list, path: str) -> None:
    """The table as charts at ``path`` (``--plot``): error and speed-up against shadow samples per setting."""
    from usdml.plots import panels, series

    group = lambda r: f"α {r['alpha']:g}, S{r['start_level']}, {r['shadow_targets']}"
    panels(path, [
        dict(title="LGH against VPL brute force", xlabel="stochastic shadow samples per pixel",
             ylabel="rel. RMSE of indirect (%)", series=series(rows, "shadow_samples", lambda r: 100 * r["rel_rmse"],
                                                                group)),
        dict(title="speed", xlabel="stochastic shadow samples per pixel", ylabel="speed-up over brute force (×)",
             series=series(rows, "shadow_samples", "speedup", group))])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--vpls", type=int, default=10_000)
    p.add_argument("--imageWidth", type=int, default=96)
    p.add_argument("--lgh-alpha", default="1,2", metavar="A[,A...]", help="LGH alphas to try (%(default)s)")
    p.add_argument("--shadow-samples", default="1,4", metavar="N[,N...]",
                   help="stochastic shadow samples per pixel to try (%(default)s)")
    p.add_argument("--lgh-start-level", default="1,0", metavar="L[,L...]", help="LGH start levels to try (%(default)s)")
    p.add_argument("--shadow-filter-iterations", default="-1", metavar="N[,N...]",
                   help="à-trous iterations to try (-1: by samples)")
    p.add_argument("--lgh-split", default=None, metavar="S[,S...]",
                   help="LGH splits to try: none, normal (default: the stage's)")
    p.add_argument("--shadow-targets", default=None, help="shadow-ray targets to try (default: the stage's)")
    p.add_argument("--frame", type=float)
    p.add_argument("--visibility", default="exact", help="backend of the LGH's shadow rays (%(default)s)")
    p.add_argument("--reference-visibility", default="exact", help="backend of brute force (%(default)s)")
    p.add_argument("--reference", help="brute-force result to read (.npz), written first if missing")
    p.add_argument("--check-rays", type=int, default=0, metavar="N",
                   help="with --visibility other than exact: test N of each row's LGH shadow rays with exact too")
    p.add_argument("--hierarchy", action="store_true",
                   help="also each row's error without shadows, against brute force without shadows")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    args = p.parse_args(argv)

    from gi_frame import open_frame
    from usdml.lighting.gi import indirect_lighting, warm_up
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer

    from usdml.scene import diff
    from usdml.visibility import make_backend

    delegate, frame, snap, renderer, lights = open_frame(args.stage, args.frame)
    width, height = snap.camera.resolution(args.imageWidth)
    base = delegate.usdml_settings.updated(vpl_count=args.vpls)
    backends = {"exact": renderer.backends.primary}
    for name in {args.visibility, args.reference_visibility} - {"exact"}:
        backends[name] = make_backend(name, base.updated(visibility=name), "cpu")
        backends[name].update(snap, diff(None, snap))      # builds (or reads) its arrays: not timed
    snap = replace(snap, camera=conform_camera(snap.camera, width, height))
    gb = build_gbuffer(snap, renderer.backends.primary, width, height)
    hit = gb.hit.ravel()
    points, normals, albedo = (a.reshape(-1, 3)[hit] for a in (gb.position, gb.normal, gb.albedo))
    warm = warm_up()

    checked = []      # (rays, backend visible where exact is blocked, backend blocked where exact is visible)

    def checking(occluded):
        def both(origins, targets, normals=None):
            got = occluded(origins, targets, normals=normals)
            pick = np.random.default_rng(0).permutation(len(got))[:args.check_rays]
            exact = renderer.backends.primary.occluded(origins[pick], targets[pick], normals=normals[pick])
            checked.append((len(pick), int((~got[pick] & exact).sum()), int((got[pick] & ~exact).sum())))
            return got
        return both

    def run(settings, visibility, check=False, shadows=True):
        occluded = backends[visibility].occluded if shadows else None
        t0 = time.perf_counter()
        r = indirect_lighting(snap, renderer.backends.primary, checking(occluded) if check and shadows else occluded,
                              lights,
                              points, normals, albedo, settings, image=(gb.hit, gb.position))
        return r, time.perf_counter() - t0

    key = np.array([args.stage, f"{frame:g}", str(args.vpls), str(args.imageWidth), args.reference_visibility])
    if args.reference and os.path.exists(args.reference):
        with np.load(args.reference) as f:
            if f["key"].tolist() != key.tolist():
                raise SystemExit(f"{args.reference} holds {f['key'].tolist()}, not {key.tolist()}")
            b, ref_s, ref_vpls = f["radiance"].astype(np.float64), float(f["seconds"]), int(f["vpls"])
    else:
        ref, ref_s = run(base.updated(gi="vpl-bruteforce"), args.reference_visibility)
        b, ref_vpls = ref.radiance.astype(np.float64), int(ref.stats.get("vpls", 0))
        if args.reference:
            np.savez(args.reference, key=key, radiance=ref.radiance, seconds=ref_s, vpls=ref_vpls,
                     shadow_rays=ref.stats.get("shadow_rays", 0))
    if len(b) != len(points):
        raise SystemExit(f"{args.reference} has {len(b)} pixels, this frame {len(points)}")
    mean = float(b.mean())
    # --hierarchy: brute force without shadows, once for every row
    unshadowed = run(base.updated(gi="vpl-bruteforce"), args.reference_visibility, shadows=False)[0].radiance \
        .astype(np.float64) if args.hierarchy else None
    rows = []
    target_choices = args.shadow_targets.split(",") if args.shadow_targets else [base.shadow_targets]
    splits = args.lgh_split.split(",") if args.lgh_split else [base.lgh_split]
    for alpha in map(float, args.lgh_alpha.split(",")):
        for k in _ints(args.shadow_samples):
            for start, iterations, targets, split_by in ((s, i, t, g) for s in _ints(args.lgh_start_level)
                                                         for i in _ints(args.shadow_filter_iterations)
                                                         for t in target_choices for g in splits):
                lgh = base.updated(gi="lgh", lgh_alpha=alpha, shadow_samples=k, lgh_start_level=start,
                                   lgh_split=split_by)
                row_settings = lgh.updated(shadow_filter_iterations=iterations, shadow_targets=targets)
                r, s = run(row_settings, args.visibility)
                extra = {}
                if args.check_rays > 0 and args.visibility != "exact":     # after the timed run, on its rays
                    checked.clear()
                    run(row_settings, args.visibility, check=True)
                    n_rays, wrongly_visible, wrongly_blocked = map(sum, zip(*checked))
                    extra = {"checked_rays": n_rays, "wrongly_visible": wrongly_visible / max(n_rays, 1),
                             "wrongly_blocked": wrongly_blocked / max(n_rays, 1)}
                if unshadowed is not None:
                    got = run(lgh, args.visibility, shadows=False)[0].radiance.astype(np.float64)
                    extra["hierarchy_rel_rmse"] = float(np.sqrt(np.mean((got - unshadowed) ** 2)) / unshadowed.mean())
                rmse = float(np.sqrt(np.mean((r.radiance.astype(np.float64) - b) ** 2)))
                split = {key: r.stats.get(key, 0.0) for key in
                         ("vpl_seconds", "lgh_seconds", "lighting_seconds", "shadow_seconds", "filter_seconds")}
                rows.append({"alpha": r.stats.get("lgh_alpha", alpha),
                             "shadow_samples": r.stats.get("shadow_samples", k),
                             "start_level": start, "shadow_targets": targets, "lgh_split": r.stats.get("lgh_split", split_by),
                             "filter_iterations": r.stats.get("filter_iterations"),
                             "rel_rmse": rmse / mean if mean > 0 else 0.0,
                             "mean_ratio": float(r.radiance.mean()) / mean if mean > 0 else 0.0, "seconds": s,
                             "speedup": ref_s / s if s > 0 else float("inf"), **split,
                             "lgh_levels": r.stats.get("lgh_levels"), "shadow_rays": r.stats.get("shadow_rays"),
                             **extra})
    for name, backend in backends.items():
        if name != "exact":
            backend.close()
    renderer.close()
    result = {"stage": args.stage, "frame": frame, "resolution": [width, height], "pixels": int(hit.sum()),
              "vpls": ref_vpls, "visibility": args.visibility, "reference_visibility": args.reference_visibility,
              "bruteforce_seconds": ref_s, "warmup_seconds": warm, "rows": rows}
    if args.plot:
        chart(rows, args.plot)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{args.stage} frame {frame:g}, {width}x{height} ({result['pixels']:,} pixels), {result['vpls']:,} VPLs; "
          f"vpl-bruteforce ({args.reference_visibility}) {ref_s:.2f} s, LGH shadow rays {args.visibility}")
    print("| α | k | start | targets | split | filter it. | rel. RMSE | seconds | speed-up | VPLs | LGH | lighting | shadow rays "
          "| filter |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['alpha']:g} | {r['shadow_samples']} | S{r['start_level']} | {r['shadow_targets']} | "
              f"{r['lgh_split']} | "
              f"{r['filter_iterations']} | "
              f"{100 * r['rel_rmse']:.1f} % ({r['mean_ratio']:.2f}) | "
              f"{r['seconds']:.3f} | {r['speedup']:.0f}× | {r['vpl_seconds']:.3f} | {r['lgh_seconds']:.3f} | "
              f"{r['lighting_seconds']:.3f} | {r['shadow_seconds']:.3f} | {r['filter_seconds']:.3f} |"
              + (f" without shadows {100 * r['hierarchy_rel_rmse']:.1f} %" if "hierarchy_rel_rmse" in r else "")
              + (f" rays against exact: {100 * r['wrongly_visible']:.1f} % wrongly visible, "
                 f"{100 * r['wrongly_blocked']:.1f} % wrongly blocked of {r['checked_rays']:,}" if "checked_rays" in r
                 else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
