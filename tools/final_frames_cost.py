#!/usr/bin/env python
"""What motion blur and depth of field cost (docs/motion-blur.md, docs/depth-of-field.md): a frame of a stage with
the camera's shutter open and its lens stopped down, against the same frame with each turned off.

The stage (default: the sample city) is opened through an overlay layer that sublayers it and authors, on its
camera, ``shutter:open``/``shutter:close`` (default -0.25/0.25: a 180° shutter) and ``fStop``/``focusDistance``
(default f/2.8, focused on the point the camera looks at: the distance to the stage's bounds' centre). Cases,
rendered through :class:`usdml.render.frame.FrameRenderer` with the exact backend at ``--samples`` pixel samples:

* ``sharp``: ``motion_blur`` and ``depth_of_field`` off;
* ``blur``: motion blur on (every pass a time slice: the stage read, the backends updated and the lights moved
  at its time);
* ``lens``: depth of field on.

Each case is rendered ``--repeat`` times after one warm-up frame, interleaved (sharp, blur, lens, sharp, ...),
and the median ratio to ``sharp`` is reported, with where the frame's time went to reading the stage and
updating the backends (:class:`usdml.render.frame_stats.FrameStats`). With several ``--visibility`` backends
each is timed the same way, and its ``direct`` is compared with the first backend's (exact) in the same case:
the mean |difference| over the mean, the error an approximate backend brings to a blurred frame.

Usage::

    python tools/final_frames_cost.py --width 96 --samples 16 --repeat 3 --json
    python tools/final_frames_cost.py --stage stages/park.usda --visibility exact,voxel,svo --cases sharp,blur \
        --width 64 --samples 16 --repeat 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def overlay(stage_path: str, folder: Path, shutter: tuple[float, float], f_stop: float) -> tuple[str, str]:
    """An overlay layer on ``stage_path`` with the camera's shutter and lens authored; returns (its path, the
    camera's path)."""
    import numpy as np
    from pxr import Sdf, Usd, UsdGeom

    from usdml.stage import StageDelegate

    d = StageDelegate(stage_path)
    snap = d.snapshot(d.start_time)
    camera = snap.camera
    lo, hi = snap.world_bounds()
    focus = float(np.linalg.norm((np.asarray(lo) + np.asarray(hi)) / 2 - camera.xform[:3, 3]))
    layer = Sdf.Layer.CreateNew(str(folder / "final_frames.usda"))
    layer.subLayerPaths.append(str(Path(stage_path).resolve()))
    stage = Usd.Stage.Open(layer)
    cam = UsdGeom.Camera(stage.GetPrimAtPath(camera.path))
    cam.CreateShutterOpenAttr(shutter[0])
    cam.CreateShutterCloseAttr(shutter[1])
    cam.CreateFStopAttr(f_stop)
    cam.CreateFocusDistanceAttr(focus)
    layer.Save()
    return layer.identifier, camera.path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", default=str(ROOT / "stages" / "city.usda"))
    ap.add_argument("--frame", type=float, default=2.0)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--shutter", default="-0.25,0.25")
    ap.add_argument("--fstop", type=float, default=2.8)
    ap.add_argument("--visibility", default="exact", help="backends, comma-separated (exact first: the reference)")
    ap.add_argument("--cases", default="sharp,blur,lens")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a setting for every case (UsdmlSettings field), e.g. direct=lgh")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import numpy as np

    from usdml.params import check, table
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    shutter = tuple(float(v) for v in args.shutter.split(","))
    kinds = {"sharp": dict(motion_blur=False, depth_of_field=False), "blur": dict(depth_of_field=False),
             "lens": dict(motion_blur=False)}
    backends = args.visibility.split(",")
    extra = {}
    for item in args.set:       # typed as the parameter table declares the field, and checked by it
        key, value = item.split("=", 1)
        kind = table()[key].type if key in table() else str
        extra[key] = check(key, value.lower() in ("1", "true", "on") if kind is bool else kind(value))
    cases = [(b, k) for b in backends for k in args.cases.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        path, camera = overlay(args.stage, Path(tmp), shutter, args.fstop)
        renderers = {(b, k): FrameRenderer(StageDelegate(path), UsdmlSettings(
            pixel_samples=args.samples, visibility=b, **kinds[k], **extra), backend_options={"report": lambda _: None})
            for b, k in cases}
        height = StageDelegate(path).snapshot(args.frame).camera.resolution(args.width)[1]
        seconds: dict = {c: [] for c in cases}
        stats: dict = {}
        direct: dict = {}
        try:
            for run in range(args.repeat + 1):
                for case, r in renderers.items():
                    t0 = time.perf_counter()
                    result = r.render(args.frame, args.width, height, {"color", "direct"})
                    if run:
                        seconds[case].append(time.perf_counter() - t0)
                        stats[case] = result.stats.as_dict()
                        direct[case] = result.buffers["direct"].astype(np.float64)
        finally:
            for r in renderers.values():
                r.close()
    rows = []
    for b, k in cases:
        base = statistics.median(seconds[(b, "sharp")]) if (b, "sharp") in seconds else None
        ref = direct.get((backends[0], k))
        row = {"visibility": b, "case": k, "seconds": statistics.median(seconds[(b, k)]),
               "ratio_to_sharp": statistics.median(seconds[(b, k)]) / base if base else None,
               "snapshot_update_seconds": stats[(b, k)]["snapshot_seconds"] + stats[(b, k)]["update_seconds"],
               "direct_rel_error_vs_" + backends[0]: float(np.abs(direct[(b, k)] - ref).mean() / ref.mean())}
        rows.append(row)
    out = {"stage": args.stage, "camera": camera, "frame": args.frame, "width": args.width, "height": height,
           "samples": args.samples, "shutter": shutter, "fstop": args.fstop, "repeat": args.repeat, "settings": extra,
           "rows": rows}
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for r in rows:
            ratio = f"{r['ratio_to_sharp']:5.2f}x" if r["ratio_to_sharp"] else "   -  "
            print(f"{r['visibility']:6s} {r['case']:6s} {r['seconds']:8.2f} s  {ratio}  "
                  f"update {r['snapshot_update_seconds']:6.2f} s  error {list(r.values())[-1]:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
