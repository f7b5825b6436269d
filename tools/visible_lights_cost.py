#!/usr/bin/env python
"""What seeing the lights costs (docs/visible-lights.md): a frame with and without ``visible_lights`` on a stage of
N rect lights (a PointInstancer of one panel facing down over a ground, seen from above at an angle), and the
G-buffer alone (the primary rays, where the light shapes are intersected) at a larger size.

Each case is timed ``--repeat`` times after one warm-up run (median, the cases interleaved); the G-buffer is timed
through :func:`usdml.render.gbuffer.build_gbuffer` with the exact backend, one pass of pixel-centre rays, and the
light intersection alone (:func:`usdml.render.visible_lights.lights_seen`) on the same rays.

Usage::

    python tools/visible_lights_cost.py --lights 1000 --imageWidth 160 --gbufferWidth 960 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path


def make_stage(path: Path, lights: int) -> str:
    """A 60 x 60 ground under ``lights`` 0.8 x 0.4 rect lights 4 units up in a square grid, facing down, and a
    camera above one edge looking across them."""
    import math

    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux
    from stage_build import define_ground

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    define_ground(stage, 30)
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(18)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(20.25)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000))
    cam.AddTranslateOp().Set((0, 2, 32))
    cam.AddRotateXOp().Set(8)                   # looking slightly up: the panels' undersides and the ground
    pi = UsdGeom.PointInstancer.Define(stage, "/World/panels")
    panel = UsdLux.RectLight.Define(stage, "/World/panels/proto/panel")
    panel.CreateWidthAttr(0.8)
    panel.CreateHeightAttr(0.4)
    panel.CreateIntensityAttr(20.0)
    panel.AddRotateXOp().Set(-90)               # the light's -Z (its emitting side) down
    pi.CreatePrototypesRel().SetTargets([Sdf.Path("/World/panels/proto")])
    side = math.ceil(math.sqrt(lights))
    step = 50.0 / side
    pi.CreatePositionsAttr([(-25 + step * (i % side + 0.5), 4.0, -25 + step * (i // side + 0.5))
                            for i in range(lights)])
    pi.CreateProtoIndicesAttr([0] * lights)
    stage.Save()
    return str(path)


def medians(runs: dict, repeat: int) -> dict:
    """Median seconds of each of ``runs`` (name -> callable), after one warm-up run each, the runs interleaved and
    their order reversed every repetition (off, on, on, off ...) so that a machine's changing load and whatever
    the run before leaves behind fall on all alike."""
    times: dict = {name: [] for name in runs}
    for name, run in runs.items():
        run()                                   # warm-up: acceleration structures, caches
    for i in range(repeat):
        for name, run in (list(runs.items()) if i % 2 == 0 else list(runs.items())[::-1]):
            t0 = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def measure(stage_path: str, width: int, gbuffer_width: int, repeat: int) -> dict:
    from dataclasses import replace

    import numpy as np

    from usdml.render.frame import FrameRenderer, conform_camera
    from usdml.render.gbuffer import build_gbuffer, camera_rays
    from usdml.render.visible_lights import lights_seen
    from usdml.scene import diff
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate
    from usdml.visibility import ExactBackend

    delegate = StageDelegate(stage_path)
    snap = delegate.snapshot(delegate.start_time)
    out: dict = {"stage": "rect lights over a ground (tools/visible_lights_cost.py)", "lights": len(snap.lights),
                 "repeat": repeat}
    height = round(width * 20.25 / 36)
    renderers = {key: FrameRenderer(delegate, UsdmlSettings(pixel_samples=1, visible_lights=key == "on"))
                 for key in ("off", "on")} if width else {}
    try:
        frames, gbuffer = {}, {key: [] for key in renderers}

        def frame(key: str) -> None:
            frames[key] = renderers[key].render(delegate.start_time, width, height, {"color", "depth"})
            gbuffer[key].append(frames[key].stats.gbuffer_seconds)
        if renderers:
            out["frame"] = {"width": width, "height": height, "pixel_samples": 1,
                            **medians({key: (lambda key=key: frame(key)) for key in renderers}, repeat)}
            out["frame"]["ratio"] = out["frame"]["on"] / out["frame"]["off"]
            out["frame"]["gbuffer_seconds"] = {key: statistics.median(t) for key, t in gbuffer.items()}
            for name, count in (("alpha_pixels", lambda f: f.buffers["color"][..., 3] > 0),
                                ("surface_pixels", lambda f: np.isfinite(f.buffers["depth"]))):
                out["frame"][name] = {key: int(count(f).sum()) for key, f in frames.items()}
    finally:
        for r in renderers.values():
            r.close()

    exact = ExactBackend()
    exact.update(snap, diff(None, snap))
    gh = round(gbuffer_width * 20.25 / 36)
    snap = replace(snap, camera=conform_camera(snap.camera, gbuffer_width, gh))
    rays = camera_rays(snap.camera, gbuffer_width, gh)
    out["gbuffer"] = {"width": gbuffer_width, "height": gh, **medians({
        "off": lambda: build_gbuffer(snap, exact, gbuffer_width, gh),
        "on": lambda: build_gbuffer(snap, exact, gbuffer_width, gh, visible_lights=True),
        "lights_seen": lambda: lights_seen(snap.lights, snap.camera, gbuffer_width, gh, *rays)}, repeat)}
    t, _ = lights_seen(snap.lights, snap.camera, gbuffer_width, gh, *rays)
    out["gbuffer"]["light_pixels"] = int(np.isfinite(t).sum())
    exact.close()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--lights", type=int, default=1000, help="rect lights (default: %(default)s)")
    p.add_argument("--imageWidth", type=int, default=160, help="frame width, 0: no frame (default: %(default)s)")
    p.add_argument("--gbufferWidth", type=int, default=960, help="G-buffer width (default: %(default)s)")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per case (default: %(default)s)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = measure(make_stage(Path(tmp) / "panels.usda", args.lights), args.imageWidth, args.gbufferWidth,
                      args.repeat)
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        print()
    else:
        g = out["gbuffer"]
        f = out.get("frame")
        if f:
            print(f"{out['lights']} rect lights; frame {f['width']}x{f['height']}: {f['off']:.3f} s without "
                  f"visible lights, {f['on']:.3f} s with ({f['ratio']:.3f}x)")
        print(f"{out['lights']} rect lights; G-buffer {g['width']}x{g['height']}: "
              f"{g['off'] * 1000:.1f} ms, {g['on'] * 1000:.1f} ms with, of which {g['lights_seen'] * 1000:.1f} ms "
              f"intersecting the lights ({g['light_pixels']} light pixels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
