"""Soft shadows of area lights against Mitsuba 3's area emitters, and what sampling them costs (issue 52 item 3).

One stage per shape: a 24 x 24 ground (albedo 0.5) and a box on it, seen from straight above (90 degrees of view),
lit by one UsdLux RectLight (2 x 1), DiskLight (radius 0.75) or SphereLight (radius 0.5) 3 units up beside the
box, radiance L = 10 (normalize off), metersPerUnit 1. usdml renders its ``direct`` AOV (``--visibility exact`` and
others, 16 primary rays per pixel unless ``--pixel-samples`` says, box filter); Mitsuba 3 (``scalar_rgb``, path tracer, ``max_depth`` 2, box filter,
its own ``rectangle`` / ``disk`` / ``sphere`` shapes with an ``area`` emitter of the same radiance) renders the same
scene from a scene dictionary written here from the same numbers (nothing of usdml's code), twice with other seeds:
the reference is their mean, its noise ``RMS(a - b) / 2``. A third Mitsuba render without the box gives the
unshadowed light; the penumbra is where the reference is between 5 % and 95 % of it.

Prints, per shape and visibility backend: the median relative error over the penumbra pixels, the frame's relative
RMSE (over the ground's mean), Mitsuba's own noise on the same terms, and the shading seconds of the frame's
lights as area lights and as points of the same intensity (size 0); ``--json`` writes them.

    .venv/bin/python tools/area_lights.py --width 96 --spp 1024
    .venv/bin/python tools/area_lights.py --city 500

(Mitsuba's stratified sampler takes a square sample count: 256, 1024.)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

#: the shapes, their USD and Mitsuba descriptions: (USD type, {attribute: value}, Mitsuba shape, its scale)
SHAPES = {
    "rect": ("RectLight", {"inputs:width": 2.0, "inputs:height": 1.0}, "rectangle", (1.0, 0.5, 1.0)),
    "disk": ("DiskLight", {"inputs:radius": 0.75}, "disk", (0.75, 0.75, 1.0)),
    "sphere": ("SphereLight", {"inputs:radius": 0.5}, "sphere", (0.5, 0.5, 0.5)),
}
LIGHT_AT = (-1.0, 3.0, -0.5)
RADIANCE = 10.0
BOX_AT, BOX_SIZE = (0.5, 0.75, 0.5), 1.5
GROUND = 24.0
CAMERA_HEIGHT = 8.0
ALBEDO = 0.5


def write_stage(path: str, shape: str) -> None:
    """The USD stage of ``shape`` (module doc)."""
    from pxr import Gf, Sdf, Usd, UsdGeom

    kind, attrs, _, _ = SHAPES[shape]
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    s = GROUND / 2
    ground = UsdGeom.Mesh.Define(stage, "/World/ground")
    ground.CreatePointsAttr([(-s, 0, -s), (-s, 0, s), (s, 0, s), (s, 0, -s)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    ground.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    box = UsdGeom.Mesh.Define(stage, "/World/box")
    h = BOX_SIZE / 2
    box.CreatePointsAttr([(BOX_AT[0] + x, BOX_AT[1] + y, BOX_AT[2] + z) for x in (-h, h) for y in (-h, h)
                          for z in (-h, h)])
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    box.CreateFaceVertexCountsAttr([4] * 6)
    box.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    box.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    for mesh in (ground, box):          # faceted, as Mitsuba's
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")      # 90 degrees of view, looking down
    for name, value in (("focalLength", 18.0), ("horizontalAperture", 36.0), ("verticalAperture", 36.0),
                        ("clippingRange", Gf.Vec2f(0.1, 100))):
        cam.GetPrim().GetAttribute(name).Set(value)
    cam.AddTranslateOp().Set((0, CAMERA_HEIGHT, 0))
    cam.AddRotateXOp().Set(-90)
    light = stage.DefinePrim("/World/light", kind)
    for name, value in attrs.items():
        light.CreateAttribute(name, Sdf.ValueTypeNames.Float).Set(value)
    light.CreateAttribute("inputs:intensity", Sdf.ValueTypeNames.Float).Set(RADIANCE)
    xf = UsdGeom.Xformable(light)
    xf.AddTranslateOp().Set(LIGHT_AT)
    xf.AddRotateXOp().Set(-90)          # the light's -Z (its emission) down
    stage.Save()


def mitsuba_scene(shape: str, width: int, spp: int, box: bool = True):
    """The same scene as a Mitsuba 3 dictionary (module doc)."""
    import mitsuba as mi

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    T = mi.ScalarTransform4f
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [ALBEDO] * 3}}
    _, _, kind, scale = SHAPES[shape]
    light = {"type": kind, "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [RADIANCE] * 3}},
             "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}}}
    if kind == "sphere":
        light.update(center=list(LIGHT_AT), radius=scale[0])
    else:       # rectangle and disk face +Z: turned to face -Y
        light["to_world"] = T().translate(list(LIGHT_AT)).rotate([1, 0, 0], 90).scale(list(scale))
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sensor": {"type": "perspective", "fov": 90.0, "fov_axis": "x",
                   "to_world": T().look_at(origin=[0, CAMERA_HEIGHT, 0], target=[0, 0, 0], up=[0, 0, -1]),
                   "film": {"type": "hdrfilm", "width": width, "height": width, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "stratified", "sample_count": spp}},
        "ground": {"type": "rectangle", "bsdf": white,
                   "to_world": T().rotate([1, 0, 0], -90).scale([GROUND / 2, GROUND / 2, 1])},
        "light": light,
    }
    if box:
        scene["box"] = {"type": "cube", "bsdf": white,
                        "to_world": T().translate(list(BOX_AT)).scale([BOX_SIZE / 2] * 3)}
    return mi, mi.load_dict(scene)


def mitsuba_render(shape: str, width: int, spp: int, seed: int, box: bool = True) -> np.ndarray:
    mi, scene = mitsuba_scene(shape, width, spp, box)
    return np.array(mi.render(scene, spp=spp, seed=seed), np.float64)[..., :3]


def usdml_render(path: str, width: int, visibility: str, light_samples: int | None = None, pixel_samples: int = 16):
    """``(FrameResult, FrameRenderer)`` of the stage: ``direct``, ``P``, ``normal`` (the renderer left open)."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    options = {} if light_samples is None else {"light_samples": light_samples}
    if visibility == "lgh":         # --direct lgh with exact shadow rays
        visibility, options["direct"] = "exact", "lgh"
    d = StageDelegate(path)
    # the light on surfaces, as Mitsuba renders it with its emitters hidden: the lights unseen
    r = FrameRenderer(d, UsdmlSettings(visibility=visibility, pixel_samples=pixel_samples, visible_lights=False,
                                       **options))
    result = r.render(d.start_time, width, width, {"direct", "P", "normal"})
    return result, r


def shading_seconds(renderer, result, repeat: int = 3) -> dict:
    """Seconds :func:`usdml.lighting.direct.shade_with` takes for the frame's centre points, its lights with area
    and the same lights as points (size 0, the same intensity): the best of ``repeat``."""
    from usdml.lighting.direct import shade_with

    snap = result.snapshot
    p = result.buffers["P"].reshape(-1, 3).astype(np.float64)
    n = result.buffers["normal"].reshape(-1, 3).astype(np.float64)
    keep = np.linalg.norm(n, axis=1) > 0.5
    p, n = p[keep], n[keep]
    albedo = np.full_like(p, ALBEDO)
    lights = renderer.frame_lights(snap)
    points = lights.subset(np.arange(len(lights)))
    points.radius[:], points.width[:], points.height[:] = 0.0, 0.0, 0.0
    out = {}
    for name, ls in (("area", lights), ("points", points)):
        best = math.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            shade_with(renderer.backends.shadow, p, n, albedo, ls, meters_per_unit=snap.meters_per_unit,
                       geometric=n, seed=1)
            best = min(best, time.perf_counter() - t0)
        out[name] = best
    out["ratio"] = out["area"] / out["points"]
    return out


def compare(shape: str, width: int, spp: int, backends: list[str], folder: str, light_samples=None,
            pixel_samples: int = 16) -> dict:
    path = os.path.join(folder, f"{shape}.usda")
    write_stage(path, shape)
    t0 = time.perf_counter()
    a, b = mitsuba_render(shape, width, spp, 0), mitsuba_render(shape, width, spp, 1)
    open_sky = mitsuba_render(shape, width, spp, 2, box=False)
    mitsuba_seconds = time.perf_counter() - t0
    ref = (a + b) / 2
    lum = ref.mean(axis=2)
    ratio = lum / np.maximum(open_sky.mean(axis=2), 1e-12)
    penumbra = (ratio > 0.05) & (ratio < 0.95) & (open_sky.mean(axis=2) > 1e-3 * open_sky.mean())
    mean = ref.mean()
    noise = float(np.sqrt(np.mean((a - b) ** 2)) / 2 / mean)
    noise_pen = float(np.median(np.abs(a - b).mean(axis=2)[penumbra] / 2 / np.maximum(lum[penumbra], 1e-12)))
    out = {"shape": shape, "width": width, "spp": spp, "pixel_samples": pixel_samples,
           "penumbra_pixels": int(penumbra.sum()),
           "mitsuba_noise_rel_rmse": noise, "mitsuba_noise_penumbra_median": noise_pen,
           "mitsuba_seconds": mitsuba_seconds, "backends": {}}
    for backend in backends:
        result, renderer = usdml_render(path, width, backend, light_samples, pixel_samples)
        try:
            got = result.buffers["direct"][..., :3].astype(np.float64)
            rel = np.abs(got.mean(axis=2)[penumbra] / lum[penumbra] - 1)
            out["backends"][backend] = {
                "penumbra_median": float(np.median(rel)), "penumbra_p95": float(np.percentile(rel, 95)),
                "rel_rmse": float(np.sqrt(np.mean((got - ref) ** 2)) / mean),
                "mean_ratio": float(got.mean() / mean),
                "estimate_area": result.stats.estimate_area,
                "frame_seconds": result.stats.seconds,
                "shading": shading_seconds(renderer, result),
            }
        finally:
            renderer.close()
    return out


def city_cost(points: int, backends: list[str], stage: str = "stages/city.usda", width: int = 128) -> dict:
    """The cost at many lights: ``points`` pixels of the city (1,024 SphereLights of radius 0.1 made points by
    ``treatAsPoint``) shaded by :func:`usdml.lighting.direct.shade_with` with its lights as authored and with
    ``treatAsPoint`` off (1,024 sphere area lights, the same intensity), per backend: seconds and shadow rays."""
    from usdml.lighting.direct import shade_with
    from usdml.render.frame import FrameRenderer, centre_gbuffer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    out = {"stage": stage, "points": points, "backends": {}}
    for backend in backends:
        d = StageDelegate(os.path.abspath(stage))
        r = FrameRenderer(d, UsdmlSettings(visibility=backend, pixel_samples=1))
        try:
            snap, lights, _ = r.advance(d.start_time, width, width * 9 // 16)
            _, gb = centre_gbuffer(snap, r.backends.primary, width, width * 9 // 16)
            hit = np.flatnonzero(gb.hit.ravel())
            pick = hit[np.linspace(0, len(hit) - 1, points).astype(int)]
            p, n = gb.position.reshape(-1, 3)[pick], gb.normal.reshape(-1, 3)[pick]
            g, a = gb.geometric.reshape(-1, 3)[pick], gb.albedo.reshape(-1, 3)[pick]
            area = lights.subset(np.arange(len(lights)))
            area.type[area.type == 0] = 1               # POINT -> SPHERE: treatAsPoint off, radius as authored
            row = {"lights": len(lights)}
            for name, ls in (("points", lights), ("area", area)):
                t0 = time.perf_counter()
                res = shade_with(r.backends.shadow, p, n, a, ls, meters_per_unit=snap.meters_per_unit, geometric=g)
                row[name] = {"seconds": time.perf_counter() - t0, "rays": int(res.queries)}
            row["ratio"] = row["area"]["seconds"] / row["points"]["seconds"]
            out["backends"][backend] = row
        finally:
            r.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--spp", type=int, default=1024, help="Mitsuba samples per pixel (each of two renders)")
    ap.add_argument("--shapes", default="rect,disk,sphere")
    ap.add_argument("--backends", default="exact,voxel,lgh", help="visibility backends; lgh: --direct lgh, exact")
    ap.add_argument("--light-samples", type=int, default=None, help="usdml's light_samples (default: its default)")
    ap.add_argument("--pixel-samples", type=int, default=16, help="usdml's primary rays per pixel (box filter)")
    ap.add_argument("--json", default=None, help="write the figures here")
    ap.add_argument("--city", type=int, default=0, metavar="N",
                    help="instead: the cost at 1,024 lights, N pixels of stages/city.usda (city_cost)")
    args = ap.parse_args(argv)
    if args.city:
        cost = city_cost(args.city, args.backends.split(","))
        for name, row in cost["backends"].items():
            print(f"city {name:6s} {row['lights']} lights, {args.city} px: points {row['points']['seconds']:.2f} s "
                  f"({row['points']['rays']} rays), area {row['area']['seconds']:.2f} s ({row['area']['rays']} rays): "
                  f"{row['ratio']:.1f}x", flush=True)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(cost, f, indent=1)
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for shape in args.shapes.split(","):
            row = compare(shape, args.width, args.spp, args.backends.split(","), folder, args.light_samples,
                          args.pixel_samples)
            rows.append(row)
            for name, b in row["backends"].items():
                noise = (b["estimate_area"] or {}).get("rel_rmse", float("nan"))      # lgh: its own estimate
                print(f"{shape:7s} {name:6s} penumbra median {100 * b['penumbra_median']:.2f} % "
                      f"(p95 {100 * b['penumbra_p95']:.1f} %, {row['penumbra_pixels']} px), rel RMSE "
                      f"{100 * b['rel_rmse']:.2f} % (estimated {100 * noise:.2f} %), "
                      f"mean {b['mean_ratio']:.4f}; Mitsuba noise {100 * row['mitsuba_noise_rel_rmse']:.2f} % "
                      f"(penumbra {100 * row['mitsuba_noise_penumbra_median']:.2f} %); shading area "
                      f"{b['shading']['area']:.3f} s, points {b['shading']['points']:.3f} s "
                      f"({b['shading']['ratio']:.1f}x)", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"light_samples": args.light_samples, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
