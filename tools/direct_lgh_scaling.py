#!/usr/bin/env python
"""Frame time and error against the number of lights: ``--direct all`` against ``--direct lgh`` on the city.

For each light count N the city at night is written as a real stage (``tools/make_stages.py``'s
``make_city_night``: the city's bulbs off, N static street lamps, a PointInstancer of point-like
SphereLights, their total power the same at every N) into ``--stages`` (kept between runs), and
``usdml compare --direct lgh --against all`` measures it (:func:`usdml.compare.compare_direct`: one
primary ray per pixel, the same G-buffer both ways): the frame's seconds each way, the speed-up, and
the relative RMSE of ``direct``. Above ``--full-reference`` lights the every-light reference shades
``--reference-pixels`` random pixels only and its seconds are extrapolated to the whole frame (at
100,000 lights and 256 px it would take minutes; the error of the subset is an estimate of the
frame's). The LGH frame's growth per 10x lights is reported beside.

Usage::

    python tools/direct_lgh_scaling.py --lights 1000,10000,100000,1000000 --imageWidth 256 --json
    python tools/direct_lgh_scaling.py --lights 1024 --imageWidth 256 --full-reference 2000
    python tools/direct_lgh_scaling.py --json > rows.json; python tools/direct_lgh_scaling.py --rows rows.json --plot p.png
    python tools/direct_lgh_scaling.py --lights 1000000 --frame-size 512   # usdml render of a 512 x 512 frame

``--frame-size SIZE`` times instead what a user waits for: ``usdml render`` (:class:`usdml.Recorder`) of one
SIZE x SIZE frame with ``--direct lgh`` (a layer over the stage sets its RenderSettings resolution),
the stage's default pixel samples and AOVs, stage load and EXR included.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def night_stage(n: int, folder: str) -> str:
    """The city with ``n`` street lamps (written once into ``folder``)."""
    path = os.path.join(folder, f"city_lights_{n}.usda")
    if not os.path.exists(path):
        sys.path.insert(0, HERE)
        from make_stages import make_city_night

        os.makedirs(os.path.join(folder, "anim"), exist_ok=True)
        make_city_night(folder, n, f"city_lights_{n}", city=os.path.join(ROOT, "stages", "city.usda"))
    return path


def square_stage(n: int, size: int, folder: str) -> str:
    """``night_stage(n)`` with its RenderSettings resolution ``size`` × ``size`` (a layer over it)."""
    base = night_stage(n, folder)
    path = os.path.join(folder, f"city_lights_{n}_{size}sq.usda")
    if not os.path.exists(path):
        from pxr import Gf, Sdf, Usd

        below = Usd.Stage.Open(base)
        stage = Usd.Stage.CreateNew(path)
        stage.GetRootLayer().subLayerPaths.append(os.path.basename(base))
        for key in ("startTimeCode", "endTimeCode", "metersPerUnit", "upAxis", "renderSettingsPrimPath",
                    "defaultPrim", "timeCodesPerSecond", "framesPerSecond"):
            value = below.GetMetadata(key)
            if value is not None:
                stage.SetMetadata(key, value)
        settings = stage.OverridePrim("/Render/Settings")
        settings.CreateAttribute("resolution", Sdf.ValueTypeNames.Int2, variability=Sdf.VariabilityUniform).Set(
            Gf.Vec2i(size, size))
        stage.Save()
    return path


def time_frame(n: int, size: int, args) -> dict:
    """What a user waits for: ``usdml render`` (through :class:`usdml.Recorder`) of one ``size`` ×
    ``size`` frame of ``n`` lamps with ``--direct lgh``, the default pixel samples, every AOV of the
    stage's product: stage load, BVH, hierarchy, shading and the EXR, in one fresh process's time."""
    import usdml
    from usdml.stage import StageDelegate

    path = square_stage(n, size, args.stages)
    rec = usdml.Recorder(direct="lgh", visibility=args.visibility,
                         **({"direct_shadow_samples": args.direct_shadow_samples}
                            if args.direct_shadow_samples else {}))
    here = os.getcwd()
    os.chdir(args.stages)          # the stage's product (out/...exr, at its RenderSettings resolution) lands here
    try:
        t0 = time.perf_counter()
        r = rec.record(path, 1, None)
        seconds = time.perf_counter() - t0
    finally:
        os.chdir(here)
    return {"lights": n, "resolution": r.resolution, "seconds": seconds,
            "seconds_per_frame": r.seconds_per_frame,
            "pixel_samples": StageDelegate(path).usdml_settings.pixel_samples, "visibility": args.visibility}


def measure(n: int, args) -> dict:
    from usdml.compare import compare_direct
    from usdml.stage import StageDelegate

    path = night_stage(n, args.stages)
    overrides = {"visibility": args.visibility}
    if args.direct_shadow_samples:
        overrides["direct_shadow_samples"] = args.direct_shadow_samples
    subset = 0 if n <= args.full_reference else args.reference_pixels
    r = compare_direct(StageDelegate(path), "lgh", "all", image_width=args.imageWidth, overrides=overrides,
                       reference_pixels=subset)
    return {"lights": n, "stage": os.path.basename(path), "resolution": r["resolution"], "pixels": r["pixels"],
            "visibility": args.visibility, "direct_shadow_samples": r["direct_shadow_samples"],
            "alpha": r["direct_alpha"], "rel_rmse": r["rel_rmse"], "lgh_seconds": r["seconds"]["lgh"],
            "all_seconds": r["seconds"]["all"], "speedup": r["speedup"],
            "reference": f"{r['compared_pixels']} pixels, extrapolated" if r["reference_extrapolated"] else "full frame",
            "lgh_levels": r["breakdown"]["lgh"].get("lgh_levels"), "lgh_build_seconds": r["breakdown"]["lgh"].get(
                "lgh_seconds")}


def chart(rows: list, path: str) -> None:
    """``--plot``: seconds per frame and relative RMSE against lights."""
    from usdml.plots import panels

    n = [r["lights"] for r in rows]
    panels(path, [
        dict(title="seconds per frame (city at night)", xlabel="lights", ylabel="frame (s)", logx=True, logy=True,
             series=[("--direct all (exact)", n, [r["all_seconds"] for r in rows]),
                     ("--direct lgh", n, [r["lgh_seconds"] for r in rows])]),
        dict(title="direct: rel. RMSE of lgh against all", xlabel="lights", ylabel="rel. RMSE (%)", logx=True,
             series=[("--direct lgh", n, [100 * r["rel_rmse"] for r in rows])]),
    ])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--lights", default="1000,10000,100000,1000000", help="comma-separated light counts")
    p.add_argument("--imageWidth", type=int, default=256)
    p.add_argument("--visibility", default="exact", help="shadow rays of both (default: %(default)s)")
    p.add_argument("--direct-shadow-samples", type=int, metavar="N", help="shadow rays per pixel of --direct lgh "
                   "(default: the stage's)")
    p.add_argument("--full-reference", type=int, default=10_000, metavar="N",
                   help="up to N lights the reference shades the whole frame (default: %(default)s)")
    p.add_argument("--reference-pixels", type=int, default=4096, help="above that, the pixels it shades")
    p.add_argument("--stages", default=os.path.join(tempfile.gettempdir(), "usdml-city-lights"),
                   help="where the stages are written (default: %(default)s)")
    p.add_argument("--frame-size", type=int, metavar="SIZE",
                   help="instead: time usdml render of one SIZE x SIZE frame with --direct lgh per light count")
    p.add_argument("--rows", help="chart rows from an earlier --json run instead of measuring")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", metavar="PNG", help="also write the chart as a PNG")
    args = p.parse_args(argv)
    if args.frame_size:
        rows = [time_frame(int(x), args.frame_size, args) for x in args.lights.split(",")]
        print(json.dumps(rows, indent=2) if args.json else "\n".join(
            f"{r['lights']:>9,} lamps, {r['resolution'][0]}x{r['resolution'][1]}: {r['seconds']:.1f} s" for r in rows))
        return 0
    if args.rows:
        rows = json.load(open(args.rows))
    else:
        rows = []
        for n in [int(x) for x in args.lights.split(",")]:
            rows.append(measure(n, args))
            if not args.json:
                r = rows[-1]
                print(f"{n:>9,} lights: lgh {r['lgh_seconds']:7.2f} s, all {r['all_seconds']:8.1f} s "
                      f"({r['speedup']:.1f}x, {r['reference']}), rel. RMSE {100 * r['rel_rmse']:.2f} %", flush=True)
        for a, b in zip(rows, rows[1:]):
            b["growth_per_10x"] = (b["lgh_seconds"] / a["lgh_seconds"]) ** (1.0 / max(
                math.log10(b["lights"] / a["lights"]), 1e-9))
    if args.json:
        print(json.dumps(rows, indent=2))
    if args.plot:
        chart(rows, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
