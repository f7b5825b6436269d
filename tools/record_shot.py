#!/usr/bin/env python
"""A pipeline script with usdml's Python API (``usdml.Recorder``): render a shot with an override
made in the stage's session layer, the way a TD would relight a shot without touching its files.

Usage::

    python tools/record_shot.py stages/city.usda out/city.####.exr --frames 1:3 --light-scale 2

``--light-scale`` multiplies every UsdLux light's intensity in the session layer (nothing on disk
changes); the frames go to OUTPUT with usdrecord's ``#`` placeholders. Prints one line per frame
and the files written.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("output")
    p.add_argument("--frames", default=None, help="a FrameSpec (default: the stage's start frame)")
    p.add_argument("--light-scale", type=float, default=1.0)
    p.add_argument("--imageWidth", type=int, default=256)
    p.add_argument("--visibility", default=None)
    args = p.parse_args(argv)

    from pxr import Usd, UsdLux

    import usdml

    stage = Usd.Stage.Open(args.stage)
    if args.light_scale != 1.0:
        with Usd.EditContext(stage, stage.GetSessionLayer()):
            for prim in stage.Traverse():
                if prim.HasAPI(UsdLux.LightAPI):
                    attr = UsdLux.LightAPI(prim).GetIntensityAttr()
                    attr.Set(attr.Get() * args.light_scale)
    settings = {"image_width": args.imageWidth, "aovs": ["color", "direct", "shadow"]}
    if args.visibility:
        settings["visibility"] = args.visibility
    try:
        result = usdml.Recorder(**settings).record_sequence(stage, args.frames, args.output)
    except usdml.UsdmlError as e:
        print(f"record_shot: {e}", file=sys.stderr)
        return 1
    for f in result.frames:
        print(f"frame {f:g}: {result.seconds_per_frame:.2f} s")
    for path in result.files:
        print(path)
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
