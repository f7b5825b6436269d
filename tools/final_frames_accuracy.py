#!/usr/bin/env python
"""Motion blur and depth of field against their own geometry (docs/motion-blur.md, docs/depth-of-field.md), on
seeded families of stages: the issue's figures.

Motion blur: a quad (width ``w``) 10 m in front of a camera moves ``v`` m per frame along X, by each of the ways a
stage moves things (``xform``: an animated translate; ``points``: points time samples; ``velocities``: one points
sample and its velocities; ``instancer``: a PointInstancer's position and velocity; ``skel``: a joint's
translation skinning the quad; ``camera``: the camera moving the other way past a still quad), seen through a
shutter ``(open, close)`` around frame 2. The reference is the sweep's own kinematics: a pixel's coverage is the
fraction of the shutter the quad covers it, averaged over the pixel (512 times × 64 points across the pixel),
computed here. Figure: the mean |alpha − coverage| over the pixels the sweep touches (the issue: ≤ 0.03 at 64
samples).

Depth of field: a half-plane at depth ``D`` (a centimetre stage) seen through a thin lens ``focal`` mm, f/``N``,
focused at ``F``: a point of the plane spreads over a disk of radius ``r |D/F − 1|`` (``r`` = focal × 0.1 / N / 2
scene units) around where the pinhole ray meets it, so the edge's profile is the disk's area fraction beyond the
edge (a circular segment), averaged over the pixel. Figure: the largest |profile − disk blur| over the columns,
the profile being the rows' mean (the issue: ≤ 0.05), and the per-pixel mean error.

Each seed draws its own speeds, widths, shutters, lenses and depths; ``--seeds`` picks the ones to report (the
tests' and the defaults' were chosen on even seeds; report odd ones).

Usage::

    python tools/final_frames_accuracy.py --seeds 1,3,5,7 --samples 64 --json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

KINDS = ("xform", "points", "velocities", "instancer", "skel", "camera")
DEPTH, APERTURE, FOCAL, FPS = 10.0, 20.0, 25.0, 24.0


def quad(stage, path: str, points):
    """A UsdGeom.Mesh at ``path``: one four-cornered face ``points`` (a default value)."""
    from pxr import UsdGeom

    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr(points)
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return m


def blur_stage(path: Path, kind: str, speed: float, width: float, shutter: tuple[float, float]) -> str:
    from pxr import Gf, Usd, UsdGeom, UsdLux, UsdSkel, Vt

    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(s, 1.0)
    s.SetTimeCodesPerSecond(FPS)
    s.SetStartTimeCode(1)
    s.SetEndTimeCode(3)
    cam = UsdGeom.Camera.Define(s, "/cam")
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(APERTURE)
    cam.CreateVerticalApertureAttr(APERTURE / 2)
    cam.CreateShutterOpenAttr(shutter[0])
    cam.CreateShutterCloseAttr(shutter[1])
    UsdLux.DistantLight.Define(s, "/sun")
    h = width / 2
    local = [(-h, -0.5, 0.0), (h, -0.5, 0.0), (h, 0.5, 0.0), (-h, 0.5, 0.0)]
    at_depth = [(x, y, -DEPTH) for x, y, _ in local]

    frames = (1, 2, 3)
    if kind == "xform":
        quad(s, "/box/quad", at_depth)
        op = UsdGeom.Xform.Define(s, "/box").AddTranslateOp()
        for t in frames:
            op.Set(Gf.Vec3d(speed * (t - 2), 0, 0), t)
    elif kind == "points":
        m = quad(s, "/quad", at_depth)
        for t in frames:
            m.GetPointsAttr().Set([(x + speed * (t - 2), y, z) for x, y, z in at_depth], t)
    elif kind == "velocities":
        m = UsdGeom.Mesh.Define(s, "/quad")       # one sample, at frame 1, and its velocities (units per second)
        m.CreateFaceVertexCountsAttr([4])
        m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        m.CreatePointsAttr().Set([(x - speed, y, z) for x, y, z in at_depth], 1)
        m.CreateVelocitiesAttr().Set([(speed * FPS, 0, 0)] * 4, 1)
    elif kind == "instancer":
        pi = UsdGeom.PointInstancer.Define(s, "/pi")
        quad(s, "/pi/protos/quad", local)
        pi.CreatePrototypesRel().SetTargets(["/pi/protos/quad"])
        pi.CreateProtoIndicesAttr([0])
        pi.CreatePositionsAttr().Set([(-speed, 0, -DEPTH)], 1)
        pi.CreateVelocitiesAttr().Set([(speed * FPS, 0, 0)], 1)
    elif kind == "skel":
        UsdSkel.Root.Define(s, "/rig")
        skel = UsdSkel.Skeleton.Define(s, "/rig/skel")
        skel.CreateJointsAttr(["root"])
        skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
        skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
        anim = UsdSkel.Animation.Define(s, "/rig/skel/anim")
        anim.CreateJointsAttr(["root"])
        anim.CreateRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1)]))
        anim.CreateScalesAttr().Set(Vt.Vec3hArray([(1, 1, 1)]))
        for t in frames:
            anim.CreateTranslationsAttr().Set(Vt.Vec3fArray([(speed * (t - 2), 0, 0)]), t)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        binding = UsdSkel.BindingAPI.Apply(quad(s, "/rig/quad", at_depth).GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(True, 1).Set([0])
        binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    elif kind == "camera":
        quad(s, "/quad", at_depth)
        op = cam.AddTranslateOp()
        for t in frames:
            op.Set(Gf.Vec3d(-speed * (t - 2), 0, 0), t)
    s.Save()
    return str(path)


def swept(width_px: int, speed: float, width: float, shutter: tuple[float, float]) -> np.ndarray:
    """Each pixel column's coverage by the quad over the shutter (module doc)."""
    half = DEPTH * APERTURE / 2 / FOCAL
    times = shutter[0] + (shutter[1] - shutter[0]) * (np.arange(512) + 0.5) / 512
    centre = speed * times
    across = (np.arange(64) + 0.5) / 64
    return np.array([np.mean(np.abs(-half + (x + across[:, None]) / width_px * 2 * half - centre[None]) < width / 2)
                     for x in range(width_px)])


def edge_stage(path: Path, focal: float, f_stop: float, focus: float, depth: float, aperture: float) -> str:
    from pxr import Usd, UsdGeom, UsdLux

    s = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(s, 0.01)
    cam = UsdGeom.Camera.Define(s, "/cam")
    cam.CreateFocalLengthAttr(focal)
    cam.CreateHorizontalApertureAttr(aperture)
    cam.CreateVerticalApertureAttr(aperture / 2)
    cam.CreateFStopAttr(f_stop)
    cam.CreateFocusDistanceAttr(focus)
    big = 1e5
    quad(s, "/plane", [(-big, -big, -depth), (0, -big, -depth), (0, big, -depth), (-big, big, -depth)])
    UsdLux.DistantLight.Define(s, "/sun")
    s.Save()
    return str(path)


def disk_blur(width_px: int, focal: float, f_stop: float, focus: float, depth: float, aperture: float) -> np.ndarray:
    radius = focal * 0.1 / f_stop / 2 * abs(depth / focus - 1)
    half = depth * aperture / 2 / focal
    across = (np.arange(64) + 0.5) / 64
    out = []
    for x in range(width_px):
        d = np.clip((-half + (x + across) / width_px * 2 * half) / radius, -1.0, 1.0)
        out.append(np.mean((np.arccos(d) - d * np.sqrt(1 - d * d)) / math.pi))
    return np.array(out)


def alpha(path: str, time: float, width: int, samples: int, seed: int) -> np.ndarray:
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=samples, seed=seed))
    try:
        return r.render(time, width, width // 2, {"color"}).buffers["color"][..., 3].astype(np.float64)
    finally:
        r.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1,3,5,7")
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            rng = np.random.default_rng([seed, 53])
            speed, width = rng.uniform(2.0, 12.0), rng.uniform(0.5, 2.0)
            opening = rng.uniform(-0.5, 0.0)
            shutter = (opening, opening + rng.uniform(0.25, 1.0))
            want = swept(args.width, speed, width, shutter)
            for kind in args.kinds.split(","):
                a = alpha(blur_stage(Path(tmp) / f"{kind}{seed}.usda", kind, speed, width, shutter), 2.0,
                          args.width, args.samples, seed)
                band = np.abs(np.arange(a.shape[0]) - a.shape[0] / 2 + 0.5) < a.shape[0] * 0.1  # inside the quad
                touched = ((want[None, :] > 0) | (a > 0)) & band[:, None]
                err = np.abs(a - want[None, :])[touched]
                rows.append({"case": "motion blur", "kind": kind, "seed": seed, "speed": round(speed, 3),
                             "width": round(width, 3), "shutter": [round(v, 3) for v in shutter],
                             "mean_error": float(err.mean()), "target": 0.03})
            focal, f_stop = rng.uniform(35.0, 135.0), rng.uniform(0.7, 4.0)
            focus, depth = rng.uniform(100.0, 800.0), rng.uniform(900.0, 3000.0)
            radius = focal * 0.1 / f_stop / 2 * abs(depth / focus - 1)
            aperture = 2 * focal * 12 * radius / depth           # the view spans 12 blur radii at the plane
            a = alpha(edge_stage(Path(tmp) / f"edge{seed}.usda", focal, f_stop, focus, depth, aperture), 0.0,
                      args.width, args.samples, seed)
            want = disk_blur(args.width, focal, f_stop, focus, depth, aperture)
            rows.append({"case": "depth of field", "seed": seed, "focal": round(focal, 2), "fStop": round(f_stop, 2),
                         "focus": round(focus, 1), "depth": round(depth, 1),
                         "profile_error": float(np.abs(a.mean(axis=0) - want).max()),
                         "pixel_mean_error": float(np.abs(a - want[None, :]).mean()), "target": 0.05})
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for r in rows:
            figure = r.get("mean_error", r.get("profile_error"))
            print(f"{r['case']:15s} {r.get('kind', ''):10s} seed {r['seed']:3d}  {figure:.4f} (target {r['target']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
