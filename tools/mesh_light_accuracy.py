#!/usr/bin/env python
"""Mesh lights (``MeshLightAPI``) against Lambert's closed form, and through every visibility backend and
``--direct lgh``.

Usage::

    python tools/mesh_light_accuracy.py [--imageWidth 96] [--quads 8] [--lgh-quads 48] [--json]

Builds a stage in a temporary folder: a 40 × 40 ground (albedo 0.5) seen from straight above, under a 2 × 2
panel 2 units up whose faces (``--quads`` × ``--quads`` quads, two triangles each) carry a ``MeshLightAPI``
(intensity 10, emitting down). Prints:

* **lambert**: the ground's irradiance ``E = π · direct / albedo`` at every ground pixel (``P`` AOV) against
  Lambert's formula for a polygon of uniform radiance L,
  ``E = L/2 · |Σ_i θ_i n · (r_i × r_{i+1}) / |r_i × r_{i+1}||`` (r_i the unit vectors to the panel's corners, θ_i the angle between r_i and r_{i+1}): median, 95th percentile
  and maximum relative error over the pixels with E above 1e-3 of its maximum (no usdml code in the reference);
* **backends**: the frame with a unit cube on the ground under the panel's edge, with ``--visibility voxel, svo,
  insm`` against ``exact`` (median, 95th percentile), and ``--direct lgh`` with voxel shadows against it;
* **lgh**: the panel cut into ``--lgh-quads``² quads (``2 · lgh-quads²`` triangle lights) with ``--direct lgh``
  against ``--direct all`` (relative RMSE of ``direct``, median and 95th percentile of the per-pixel error), and
  the seconds of each.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from stage_build import define_ground

ALBEDO = 0.5
PANEL = 1.0        #: half size
HEIGHT = 2.0
INTENSITY = 10.0


def emitting_panel(stage: Usd.Stage, path: str, quads: int, half: float = PANEL, height: float = HEIGHT,
                   intensity: float = INTENSITY, down: bool = True) -> UsdGeom.Mesh:
    """A ``2·half`` square of ``quads``² faces at ``height`` (Y up) with a ``MeshLightAPI`` of ``intensity``,
    emitting down (its faces wound so the normal is -Y) or up."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    xs = np.linspace(-half, half, quads + 1)
    mesh.CreatePointsAttr([(float(x), height, float(z)) for z in xs for x in xs])
    faces = []
    for j in range(quads):
        for i in range(quads):
            a = j * (quads + 1) + i
            quad = [a, a + 1, a + quads + 2, a + quads + 1]
            faces += quad if down else quad[::-1]
    mesh.CreateFaceVertexCountsAttr([4] * quads * quads)
    mesh.CreateFaceVertexIndicesAttr(faces)
    UsdLux.MeshLightAPI.Apply(mesh.GetPrim())
    mesh.GetPrim().CreateAttribute("inputs:intensity", Sdf.ValueTypeNames.Float).Set(intensity)
    return mesh


def panel_stage(path: Path, quads: int, box: bool = False) -> str:
    """The ground, the camera and the emitting panel of ``quads`` × ``quads`` faces (and a unit cube on the ground
    under its edge casting a penumbra, where ``box``); returns the file."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    define_ground(stage, 20, ALBEDO)
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(18)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(36)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000))
    cam.AddTranslateOp().Set((0, 15, 0))
    cam.AddRotateXOp().Set(-90)
    emitting_panel(stage, "/World/panel", quads)
    if box:
        cube = UsdGeom.Cube.Define(stage, "/World/box")
        cube.AddTranslateOp().Set((1.0, 0.5, 0.0))
    stage.Save()
    return str(path)


def lambert_irradiance(points: np.ndarray, corners: np.ndarray, radiance: float) -> np.ndarray:
    """Irradiance at ``points`` (P, 3) on an upward (+Y) surface from a polygon of ``corners`` (K, 3) of uniform
    radiance: Lambert's formula (the polygon's vector irradiance, dotted with the normal)."""
    r = corners[None] - points[:, None]
    r /= np.linalg.norm(r, axis=2, keepdims=True)
    total = np.zeros(len(points))
    for i in range(len(corners)):
        a, b = r[:, i], r[:, (i + 1) % len(corners)]
        theta = np.arccos(np.clip((a * b).sum(axis=1), -1.0, 1.0))
        c = np.cross(a, b)
        total += theta * c[:, 1] / np.linalg.norm(c, axis=1)
    return radiance / 2.0 * np.abs(total)


def render(path: str, width: int, **settings) -> tuple[dict, float]:
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    delegate = StageDelegate(path)
    renderer = FrameRenderer(delegate, UsdmlSettings(pixel_samples=1, **settings))
    try:
        t0 = time.perf_counter()
        buffers = renderer.render(delegate.start_time, width, width, {"direct", "P"}).buffers
        return buffers, time.perf_counter() - t0
    finally:
        renderer.close()


def errors(got: np.ndarray, want: np.ndarray) -> dict:
    mask = want > 1e-3 * want.max()
    rel = np.abs(got[mask] - want[mask]) / want[mask]
    return {"median": float(np.median(rel)), "p95": float(np.percentile(rel, 95)), "max": float(rel.max()),
            "relRmse": float(np.sqrt(np.mean((got[mask] - want[mask]) ** 2)) / want[mask].mean()),
            "pixels": int(mask.sum())}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--imageWidth", type=int, default=96)
    ap.add_argument("--quads", type=int, default=8)
    ap.add_argument("--lgh-quads", type=int, default=48)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out: dict = {"imageWidth": args.imageWidth, "quads": args.quads, "lghQuads": args.lgh_quads}
    with tempfile.TemporaryDirectory() as tmp:
        path = panel_stage(Path(tmp) / "panel.usda", args.quads)
        exact, seconds = render(path, args.imageWidth)
        p = exact["P"].reshape(-1, 3).astype(np.float64)
        ground = np.abs(p[:, 1]) < 1e-4
        corners = np.array([(-PANEL, HEIGHT, -PANEL), (PANEL, HEIGHT, -PANEL), (PANEL, HEIGHT, PANEL),
                            (-PANEL, HEIGHT, PANEL)])
        e_ref = lambert_irradiance(p[ground], corners, INTENSITY)
        e_got = exact["direct"].reshape(-1, 3)[ground, 0].astype(np.float64) * math.pi / ALBEDO
        out["lambert"] = {**errors(e_got, e_ref), "triangles": 2 * args.quads ** 2, "seconds": seconds}
        boxed = panel_stage(Path(tmp) / "box.usda", args.quads, box=True)
        exact_box, s_exact = render(boxed, args.imageWidth)
        ref = exact_box["direct"][..., 0].astype(np.float64)
        out["backends"] = {"exact": {"seconds": s_exact}}
        for name, settings in (("voxel", {}), ("svo", {}), ("insm", {}), ("voxel lgh", {"direct": "lgh"})):
            b, s = render(boxed, args.imageWidth, visibility=name.split()[0], **settings)
            out["backends"][name] = {**errors(b["direct"][..., 0].astype(np.float64), ref), "seconds": s}
        fine = panel_stage(Path(tmp) / "fine.usda", args.lgh_quads)
        every, s_all = render(fine, args.imageWidth)
        lgh, s_lgh = render(fine, args.imageWidth, direct="lgh")
        out["lgh"] = {**errors(lgh["direct"][..., 0].astype(np.float64), every["direct"][..., 0].astype(np.float64)),
                      "triangles": 2 * args.lgh_quads ** 2, "secondsAll": s_all, "secondsLgh": s_lgh}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        lam = out["lambert"]
        print(f"lambert  {lam['triangles']} triangles: median {lam['median']:.3%}, p95 {lam['p95']:.3%}, "
              f"max {lam['max']:.3%} over {lam['pixels']} ground pixels")
        for name, row in out["backends"].items():
            if name != "exact":
                print(f"{name:9s} vs exact, with a box: median {row['median']:.2%}, p95 {row['p95']:.2%}, max "
                      f"{row['max']:.2%}; {row['seconds']:.2f} s (exact {out['backends']['exact']['seconds']:.2f} s)")
        row = out["lgh"]
        print(f"lgh      {row['triangles']} triangles vs --direct all: rel. RMSE {row['relRmse']:.2%}, median "
              f"{row['median']:.2%}, p95 {row['p95']:.2%}; {row['secondsLgh']:.2f} s vs {row['secondsAll']:.2f} s")
    return out


if __name__ == "__main__":
    main()
