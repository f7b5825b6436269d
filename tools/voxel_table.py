#!/usr/bin/env python
"""Paper 000's figures over voxel resolutions and direction steps (its Tables I, III, IV).

For each stage, resolution N and step K: error against ``exact`` (``usdml.compare.compare_visibility``:
ε_v, ε_s, wrongly hidden / visible pairs), array build seconds and bytes, shadow queries per second
and the speed-up over ``exact`` on the same query set in the same run (``usdml.bench``), and the
seconds of a whole voxel frame at ``--frameWidth`` × ``--frameHeight`` (steady state: a frame
rendered first, the next one timed) beside ``exact``'s, measured once per stage.

The compare builds its arrays without the cache (its build seconds are a build's); the bench and
frame runs read them from the cache (``$USDML_CACHE_DIR``: 939 MiB per array at 128³ / 2°),
building them once when it has none.

Usage::

    python tools/voxel_table.py stages/city.usda stages/planes.usda --voxel-resolution 32,64,128 --direction-step 6,3,2
"""

from __future__ import annotations

import argparse
import json
import sys


def _frame_seconds(delegate, settings, width: int, height: int) -> float:
    """Seconds of the second of two consecutive frames from the stage's start (color only), one
    primary ray per pixel: the visibility backends' cost, not the anti-aliasing's."""
    from usdml.bench import steady_frame

    with steady_frame(delegate, settings.updated(pixel_samples=1), delegate.start_time, width, height) \
            as (_, seconds, _r):
        return seconds


def chart(rows: list, path: str) -> None:
    """The table as charts at ``path`` (``--plot``): ε_s, speed-up over exact and memory per resolution."""
    from usdml.plots import panels, series

    group = lambda r: f"{r['stage'].rsplit('/', 1)[-1].removesuffix('.usda')} {r['direction_step']:g}°"
    panels(path, [
        dict(title="shadow error against exact", xlabel="voxel resolution (voxels per axis)", ylabel="ε_s (%)",
             series=series(rows, "voxel_resolution", lambda r: 100 * r["eps_s"], group), logx=True),
        dict(title="queries against exact", xlabel="voxel resolution (voxels per axis)",
             ylabel="speed-up over exact (×)", series=series(rows, "voxel_resolution", "speedup_vs_exact", group),
             logx=True),
        dict(title="memory", xlabel="voxel resolution (voxels per axis)", ylabel="voxel arrays (MiB)",
             series=series(rows, "voxel_resolution", lambda r: r["bytes"] / 2**20, group), logx=True, logy=True)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stages", nargs="+")
    p.add_argument("--voxel-resolution", default="32,64,128", metavar="N[,N...]",
                   help="voxel resolutions to measure, comma-separated (default: %(default)s)")
    p.add_argument("--direction-step", default="6,3,2", metavar="DEG[,DEG...]",
                   help="direction steps in degrees to measure, comma-separated (default: %(default)s)")
    p.add_argument("--imageWidth", type=int, default=128, help="width of the compare and bench images")
    p.add_argument("--frameWidth", type=int, default=512)
    p.add_argument("--frameHeight", type=int, default=512)
    p.add_argument("--no-frames", action="store_true", help="skip the whole-frame timings")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the table's chart as a PNG")
    args = p.parse_args(argv)

    from usdml.bench import bench_visibility
    from usdml.compare import compare_visibility
    from usdml.stage import StageDelegate

    rows = []
    if not args.json:
        print("| stage | grid | ε_v | ε_s | hidden / visible (% pairs) | build s | bytes | queries/s | vs exact "
              "| frame s (exact) |")
        print("|---|---|---|---|---|---|---|---|---|---|")
    for stage in args.stages:
        delegate = StageDelegate(stage)
        exact_frame = None
        if not args.no_frames:
            exact_frame = _frame_seconds(delegate, delegate.usdml_settings.updated(visibility="exact"),
                                         args.frameWidth, args.frameHeight)
        for n in (int(x) for x in args.voxel_resolution.split(",")):
            for k in (float(x) for x in args.direction_step.split(",")):
                over = {"voxel_resolution": n, "direction_step": k}
                quiet = {"report": lambda s: None}
                c = compare_visibility(delegate, "voxel", image_width=args.imageWidth, overrides=over,
                                       backend_options={**quiet, "cache": False})
                settings = delegate.usdml_settings.updated(**over)
                b = next(r for r in bench_visibility(delegate, ["voxel"], image_width=args.imageWidth,
                                                     settings=settings, backend_options=quiet)
                         if r["backend"] == "voxel")
                row = {"stage": stage, "voxel_resolution": n, "direction_step": k, "eps_v": c["eps_v"],
                       "eps_s": c["eps_s"], "wrongly_hidden": c["wrongly_hidden"],
                       "wrongly_visible": c["wrongly_visible"], "build_seconds": c["build_seconds"],
                       "bytes": b["bytes"], "queries_per_second": b["queries_per_second"],
                       "speedup_vs_exact": b["speedup_vs_exact"], "queries": b["queries"]}
                if not args.no_frames:
                    row["frame_seconds"] = _frame_seconds(delegate, settings.updated(visibility="voxel"),
                                                          args.frameWidth, args.frameHeight)
                    row["exact_frame_seconds"] = exact_frame
                rows.append(row)
                if not args.json:
                    frame = (f"{row['frame_seconds']:.1f} ({exact_frame:.1f})" if not args.no_frames else "–")
                    print(f"| {stage.rsplit('/', 1)[-1].removesuffix('.usda')} | {n}³ / {k:g}° "
                          f"| {100 * row['eps_v']:.2f} % | {100 * row['eps_s']:.2f} % "
                          f"| {100 * row['wrongly_hidden']:.2f} / {100 * row['wrongly_visible']:.2f} "
                          f"| {row['build_seconds']:.1f} | {row['bytes'] / 2 ** 20:.0f} MiB "
                          f"| {row['queries_per_second'] / 1e6:.1f} M | {row['speedup_vs_exact']:.2f}× | {frame} |",
                          flush=True)
    if args.plot:
        chart(rows, args.plot)
    if args.json:
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
