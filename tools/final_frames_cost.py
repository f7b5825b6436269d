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
and the median ratio to ``sharp`` is reported, with where the blurred frame's extra time went (snapshots and
backend updates, from :class:`usdml.render.frame_stats.FrameStats`).

Usage::

    python tools/final_frames_cost.py --width 96 --samples 16 --repeat 3 --json
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
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    shutter = tuple(float(v) for v in args.shutter.split(","))
    cases = {"sharp": dict(motion_blur=False, depth_of_field=False), "blur": dict(depth_of_field=False),
             "lens": dict(motion_blur=False)}
    with tempfile.TemporaryDirectory() as tmp:
        path, camera = overlay(args.stage, Path(tmp), shutter, args.fstop)
        renderers = {name: FrameRenderer(StageDelegate(path), UsdmlSettings(pixel_samples=args.samples, **kw))
                     for name, kw in cases.items()}
        height = None
        seconds: dict[str, list[float]] = {name: [] for name in cases}
        stats: dict[str, dict] = {}
        try:
            for run in range(args.repeat + 1):
                for name, r in renderers.items():
                    if height is None:
                        height = r.delegate.snapshot(args.frame).camera.resolution(args.width)[1]
                    t0 = time.perf_counter()
                    result = r.render(args.frame, args.width, height, {"color"})
                    if run:
                        seconds[name].append(time.perf_counter() - t0)
                        stats[name] = result.stats.as_dict()
        finally:
            for r in renderers.values():
                r.close()
    base = statistics.median(seconds["sharp"])
    out = {"stage": args.stage, "camera": camera, "frame": args.frame, "width": args.width, "height": height,
           "samples": args.samples, "shutter": shutter, "fstop": args.fstop,
           "seconds": {k: statistics.median(v) for k, v in seconds.items()},
           "ratio": {k: statistics.median(v) / base for k, v in seconds.items()},
           "blur_snapshot_update_seconds": stats["blur"]["snapshot_seconds"] + stats["blur"]["update_seconds"],
           "sharp_snapshot_update_seconds": stats["sharp"]["snapshot_seconds"] + stats["sharp"]["update_seconds"]}
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k in cases:
            print(f"{k:6s} {out['seconds'][k]:8.2f} s  {out['ratio'][k]:5.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
