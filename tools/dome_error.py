#!/usr/bin/env python
"""Error of K-sample dome lighting against the same dome with many more samples, exact visibility both.

Usage::

    python tools/dome_error.py [STAGE] [--imageWidth 96] [--dome-samples 64,256,1024] [--reference 8192] [--json]

Without a stage it builds a small test stage (a box on a ground slab under a constant
DomeLight, seen by a camera at 3/4 view) in a temporary folder. Prints, per K, the RMSE of the
``direct`` AOV against the reference render, relative to the reference mean, and seconds per frame
(``--json``: one object with the reference and a row per K).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

TEST_STAGE = """#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
)

def Xform "World"
{
    def Cube "box"
    {
        double size = 2
        double3 xformOp:translate = (0, 1, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }

    def Cube "ground"
    {
        double size = 1
        double3 xformOp:scale = (30, 0.01, 30)
        uniform token[] xformOpOrder = ["xformOp:scale"]
    }

    def DomeLight "sky"
    {
        float inputs:intensity = 1
    }

    def Camera "main_cam"
    {
        double3 xformOp:translate = (6, 5, 8)
        float3 xformOp:rotateXYZ = (-25, 35, 0)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
    }
}
"""


def render_direct(stage: str, width: int, samples: int) -> tuple[np.ndarray, float]:
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    renderer = FrameRenderer(delegate, UsdmlSettings(dome_samples=samples))
    snap = delegate.snapshot(delegate.start_time)
    w, h = snap.camera.resolution(width)
    t0 = time.perf_counter()
    try:
        direct = renderer.render(delegate.start_time, w, h, {"direct"}).buffers["direct"]
    finally:
        renderer.close()
    return direct.astype(np.float64), time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("stage", nargs="?", help="a dome-lit stage (default: a built-in test stage)")
    parser.add_argument("--imageWidth", type=int, default=96, metavar="W",
                        help="image width in pixels (default: %(default)s)")
    parser.add_argument("--dome-samples", default="64,256,1024", metavar="K[,K...]",
                        help="dome samples K to measure, comma-separated (default: %(default)s)")
    parser.add_argument("--reference", type=int, default=8192, metavar="K",
                        help="dome samples of the reference render (default: %(default)s)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    args = parser.parse_args(argv)
    say = (lambda line: None) if args.json else print
    result: dict = {"stage": args.stage, "width": args.imageWidth, "reference_samples": args.reference, "rows": []}
    with tempfile.TemporaryDirectory() as tmp:
        stage = args.stage
        if stage is None:
            stage = str(Path(tmp) / "dome.usda")
            Path(stage).write_text(TEST_STAGE)
        ref, ref_s = render_direct(stage, args.imageWidth, args.reference)
        result.update(reference_seconds=ref_s, reference_mean=float(ref.mean()))
        say(f"reference K={args.reference}: {ref_s:.2f} s/frame, mean {ref.mean():.5f}")
        for k in (int(v) for v in args.dome_samples.split(",")):
            img, s = render_direct(stage, args.imageWidth, k)
            rmse = float(np.sqrt(((img - ref) ** 2).mean()))
            result["rows"].append({"samples": k, "rmse": rmse, "rel_rmse": rmse / float(ref.mean()), "seconds": s})
            say(f"K={k:>6}: RMSE {rmse:.5f} ({100 * rmse / ref.mean():.2f} % of the mean), {s:.2f} s/frame")
    if args.json:
        print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
