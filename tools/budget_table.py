#!/usr/bin/env python
"""Approximations under ``--error-budget`` (issue 36): for each stage, backend and budget, what a frame gets.

Per (stage, backend, budget), ``usdml compare`` on the stage's start frame (``usdml.compare.compare_visibility``):
the measured ε_v and ε_s against ``exact`` over every facing pixel-light pair, the speed-up over ``exact``
on those pairs in the same run (the budget's level choice and every refinement included), the level chosen,
the fraction of queries re-asked of ``exact`` (``refined``) and traced over the blind zone (``near``), and the
frame's own estimate of ε_v with its 95 % interval beside the measurement. A budget of 1 is no budget (the
backend as it is), 0 every answer exact.

With ``--bench``, also ``usdml bench`` (median of passes; refinement included) per (backend, budget); with
``--frame-width W``, the seconds of whole frames rendered at W pixels wide, each budget against ``exact``
(``usdml.bench.steady_frame``: frames 2-4 after frame 1, one primary ray per pixel, by exact's renderer and the
budget's: frames 1-2 by exact's and then by the budget's, frames 3-4 by the budget's and then by exact's in
turn; the medians of the seconds and of the pairs' ratios; the shadow AOV and the estimate's seconds of
frame 2).

Usage (``--from docs/data/budget.json --plot docs/images/budget`` redraws the docs' chart from its data)::

    python tools/budget_table.py /tmp/uc/unseen_city_1.usda --backends voxel,svo,insm \\
        --budgets 1,0.01,0.003,0.001,0 --imageWidth 128 --json --plot docs/images/budget
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def _numbers(text: str, kind=float) -> list:
    return [kind(x) for x in text.split(",") if x.strip()]


def _frames(delegate, settings, exact_settings, width: int, height: int, frames: int = 3) -> dict:
    """A steady frame of ``settings`` against ``exact_settings``'s, pair by pair (the machine's speed drifts by a
    tenth between runs): frames 1 and 2 by exact's renderer and then by the other (``steady_frame`` each), then
    the next ``frames - 1`` frames by the other and then by exact's, in turn. The medians of each side's
    seconds and of the pairs' ratios, frame 2's ``shadow`` AOVs and the seconds of its estimate (with a budget:
    the level's choice, sample and sweep)."""
    import time

    from usdml.bench import next_frame, steady_frame

    aovs = frozenset({"color", "shadow"})
    with steady_frame(delegate, exact_settings.updated(pixel_samples=1), delegate.start_time, width, height,
                      aovs) as (exact_result, exact_s, er), \
            steady_frame(delegate, settings.updated(pixel_samples=1), delegate.start_time, width, height,
                         aovs) as (result, seconds, r):
        estimate = result.stats.estimate
        pairs, time_code = [(seconds, exact_s)], next_frame(delegate, delegate.start_time)
        for _ in range(frames - 1):
            time_code = next_frame(delegate, time_code)
            pair = []
            for renderer in (r, er):
                t0 = time.perf_counter()
                renderer.render(time_code, width, height, set(aovs))
                pair.append(time.perf_counter() - t0)
            pairs.append(tuple(pair))
        got, ref = np.array(pairs).T
        return {"frame_seconds": float(np.median(got)), "exact_frame_seconds": float(np.median(ref)),
                "frame_speedup": float(np.median(ref / got)), "frame_estimate_seconds": estimate.seconds if estimate is not None else 0.0,
                "shadow": result.buffers["shadow"], "exact_shadow": exact_result.buffers["shadow"]}


def cold_render(stage: str, width: int, frames: str, flags: list[str]) -> float:
    """Seconds of a whole ``usdml render`` of ``frames`` as a user runs it, with an empty cache (the voxel arrays
    built first), one primary ray per pixel."""
    import os
    import subprocess
    import tempfile
    import time
    from pathlib import Path

    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as folder:
        argv = [sys.executable, "-m", "usdml.cli", "render", stage, str(Path(folder) / "f.####.exr"), "--frames", frames,
                "--imageWidth", str(width), "--pixel-samples", "1", "-q", *flags]
        t0 = time.perf_counter()
        subprocess.run(argv, check=True, env={**os.environ, "USDML_CACHE_DIR": cache}, stdout=subprocess.DEVNULL)
        return time.perf_counter() - t0


def measure(stage: str, backends: list[str], budgets: list[float], width: int, bench: bool,
            frame_width: int | None, cold: str | None = None) -> list[dict]:
    from usdml.bench import bench_visibility
    from usdml.compare import compare_visibility
    from usdml.stage import StageDelegate

    d = StageDelegate(stage)
    rows = []
    if frame_width:
        w, h = d.snapshot(d.start_time).camera.resolution(frame_width)
    exact_cold = cold_render(stage, frame_width, cold, ["--visibility", "exact"]) if cold and frame_width else None
    for backend in backends:
        for budget in budgets:
            r = compare_visibility(d, backend, image_width=width, overrides=dict(error_budget=budget))
            est = r["estimate"]
            row = {k: r.get(k) for k in ("stage", "frame", "resolution", "pixels", "lights", "queries", "visibility",
                                         "eps_v", "eps_s", "speedup", "seconds", "refined_fraction", "near_fraction",
                                         "refine_level", "estimated_eps_v", "estimated_eps_v_interval",
                                         "build_seconds")}
            row["budget"] = budget
            lo, hi = r["estimated_eps_v_interval"]
            row["interval_holds"] = bool(lo <= r["eps_v"] <= hi)
            row["estimate_seconds"] = est.get("seconds", 0.0)
            row["estimate_share"] = est.get("seconds", 0.0) / max(r["seconds"][backend], 1e-9)
            if bench:
                b = bench_visibility(d, [backend], image_width=width,
                                     settings=d.usdml_settings.updated(visibility=backend, error_budget=budget))[0]
                row["bench_speedup"] = b["speedup_vs_exact"]
                row["bench_disagreement"] = b["disagreement_vs_exact"]
            if frame_width:
                f = _frames(d, d.usdml_settings.updated(visibility=backend, error_budget=budget),
                            d.usdml_settings.updated(visibility="exact"), w, h)
                shadow, exact_shadow = f.pop("shadow"), f.pop("exact_shadow")
                row.update(f)
                row["frame_estimate_share"] = row["frame_estimate_seconds"] / max(row["frame_seconds"], 1e-9)
                # the shadow AOV against the exact backend's, over the frame's pixels (0 where nothing is hit)
                row["shadow_mean_abs"] = float(abs(shadow - exact_shadow).mean())
                row["shadow_bias"] = float((shadow - exact_shadow).mean())
                row["frame_width"] = [w, h]
            if exact_cold is not None:
                # a user's first render: arrays built, every frame of ``cold`` (--frames)
                row["cold_frames"] = cold
                row["cold_seconds"] = cold_render(stage, frame_width, cold, ["--visibility", backend,
                                                                             "--error-budget", f"{budget:g}"])
                row["exact_cold_seconds"] = exact_cold
                row["cold_speedup"] = exact_cold / row["cold_seconds"]
            rows.append(row)
            print(f"{stage} {backend} budget {budget:g}: eps_v {100 * r['eps_v']:.3f} % (estimate "
                  f"{100 * r['estimated_eps_v']:.3f} % [{100 * lo:.3f}, {100 * hi:.3f}]), {r['speedup']:.2f}x exact, "
                  f"level {r['refine_level']}, refined {100 * r['refined_fraction']:.1f} %"
                  + (f", bench {row['bench_speedup']:.2f}x" if bench else "")
                  + (f", frame {row['frame_seconds']:.1f} s vs {row['exact_frame_seconds']:.1f} s "
                     f"({row['frame_speedup']:.2f}x), shadow AOV off by "
                     f"{row['shadow_mean_abs']:.4f}" if frame_width else ""),
                  file=sys.stderr)
    return rows


def chart(rows: list, path: str) -> None:
    """ε_v and speed-up against the budget (``--plot``); budget 1 (none) drawn at 0.1, 0 at 1e-4."""
    from usdml.plots import panels, series

    def at(r):
        return 0.1 if r["budget"] >= 1 else (1e-4 if r["budget"] <= 0 else r["budget"])

    group = lambda r: f"{r['stage'].rsplit('/', 1)[-1].removesuffix('.usda')} {r['visibility']}"
    panels(path, [
        dict(title="measured ε_v", xlabel="--error-budget (none at 0.1, 0 at 1e-4)",
             ylabel="ε_v (%; 0 at 1e-4)", series=series(rows, at, lambda r: max(100 * r["eps_v"], 1e-4), group),
             logx=True, logy=True),
        dict(title="speed-up over exact", xlabel="--error-budget", ylabel="× exact (compare's pairs)",
             series=series(rows, at, "speedup", group), logx=True),
        dict(title="queries re-asked of exact", xlabel="--error-budget", ylabel="refined (%)",
             series=series(rows, at, lambda r: 100 * r["refined_fraction"], group), logx=True)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stages", nargs="*")
    p.add_argument("--backends", default="voxel,svo,insm")
    p.add_argument("--budgets", default="1,0.01,0.003,0.001,0")
    p.add_argument("--imageWidth", type=int, default=128)
    p.add_argument("--bench", action="store_true", help="also usdml bench per backend and budget")
    p.add_argument("--frame-width", type=int, default=None, help="also time whole frames this wide")
    p.add_argument("--cold", default=None, metavar="FRAMES",
                   help="with --frame-width: also time whole `usdml render --frames FRAMES` runs with an empty cache")
    p.add_argument("--plot", default=None, metavar="PREFIX", help="write PREFIX.png: ε_v and speed against the budget")
    p.add_argument("--json", action="store_true")
    p.add_argument("--from", dest="saved", action="append", default=[], metavar="JSON",
                   help="rows of an earlier --json run (a list, or a docs/data file's runs) to plot with these")
    args = p.parse_args(argv)
    rows = []
    for path in args.saved:
        data = json.load(open(path))
        rows += data if isinstance(data, list) else [r for run in data["runs"] for r in run["output"]]
    for stage in args.stages:
        rows += measure(stage, args.backends.split(","), _numbers(args.budgets), args.imageWidth, args.bench,
                        args.frame_width, args.cold)
    if args.plot:
        seen = {}
        for r in rows:      # one point per stage, backend and budget: the first run's
            seen.setdefault((r["stage"], r["visibility"], r["budget"]), r)
        chart(list(seen.values()), args.plot + ".png")
    if args.json:
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
