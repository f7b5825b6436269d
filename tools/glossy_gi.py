#!/usr/bin/env python
"""What usdml's diffuse-only indirect light misses on glossy surfaces, against a path tracer (issue 51).

usdml's VPLs leave a surface with its diffuse reflectance and receivers gather with theirs
(docs/materials.md): a metal's specular bounce is not in ``indirect``. This measures that choice. The closed
Cornell-style box of ``tools/gi_reference.py`` (two point lights, camera inside) with its floor made
(a) white diffuse, (b) a rough metal (UsdPreviewSurface metallic 1, roughness R, colour C) and (c) a glossy
dielectric (diffuse 0.5 grey, roughness R, ior 1.5): usdml's ``indirect`` (``--gi vpl-bruteforce``, B bounces)
against Mitsuba 3's path tracer (``scalar_rgb``; the floor a ``roughconductor`` GGX of α = R² with
``specular_reflectance`` C, ``material`` none, or a ``roughplastic`` GGX of the same α over the same grey), as
the energy ratio of ``indirect`` over the image (1 = all indirect light there) and the same over the floor's
pixels alone and the walls' alone, and the floor's direct light against Mitsuba's (the two models' own gap:
Mitsuba's ``roughplastic`` dims its diffuse base by the coating's internal reflection, which the preview surface
does not model, so (c) is a plausibility check only). (a) separates the VPL method's own error from what
glossiness costs.

    .venv/bin/python tools/glossy_gi.py --roughness 0.3 --bounces 2 --width 64 --spp 256
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gi_reference as gr  # noqa: E402

FLOOR_GREY = (0.5, 0.5, 0.5)    # the floor's own albedo: its own shape in the Mitsuba scene (faces grouped by albedo)


def box_with_floor(path: Path, floor: str, roughness: float, colour) -> str:
    """gi_reference's closed box whose floor is ``floor`` (diffuse, metal or plastic) in USD."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

    gr.closed_box(path)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/Box/Floor")
    UsdGeom.Mesh(prim).GetDisplayColorPrimvar().Set([FLOOR_GREY])
    if floor != "diffuse":
        mat = UsdShade.Material.Define(stage, "/World/Looks/floor")
        pbr = UsdShade.Shader.Define(stage, "/World/Looks/floor/pbr")
        pbr.CreateIdAttr("UsdPreviewSurface")
        pbr.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
        if floor == "metal":
            pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
            pbr.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(1.0)
        else:
            pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*FLOOR_GREY))
        mat.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)
    stage.Save()
    return str(path)


def mitsuba_indirect(stage: str, floor: str, roughness: float, colour, width: int, bounces: int, spp: int):
    """``(direct, indirect)`` path traced by Mitsuba with the floor's BSDF swapped in."""
    from usdml import reference

    scene = reference.load(stage, None, width)
    for shape in scene.definition.values():
        if isinstance(shape, dict) and shape.get("type") == "obj":
            value = shape["bsdf"]["material"].get("reflectance", {}).get("value")
            if value is not None and np.allclose(value, FLOOR_GREY):
                if floor == "metal":
                    shape["bsdf"]["material"] = {"type": "roughconductor", "distribution": "ggx",
                                                 "alpha": roughness ** 2, "material": "none",
                                                 "specular_reflectance": {"type": "rgb", "value": list(colour)}}
                elif floor == "plastic":
                    shape["bsdf"]["material"] = {"type": "roughplastic", "distribution": "ggx", "alpha": roughness ** 2,
                                                 "int_ior": 1.5, "ext_ior": 1.0, "nonlinear": False,
                                                 "diffuse_reflectance": {"type": "rgb", "value": list(FLOOR_GREY)}}
    direct, total = (reference.render(scene, spp, b, 0, by_light=False) for b in (0, bounces))
    return direct, total - direct


def measure(floor: str, roughness: float, colour, width: int, bounces: int, spp: int, vpls: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        stage = box_with_floor(Path(tmp) / "box.usda", floor, roughness, colour)
        ref_direct, ref = mitsuba_indirect(stage, floor, roughness, colour, width, bounces, spp)
        frame = gr.render_usdml(stage, "vpl-bruteforce", vpls, bounces, width)
        got = frame["indirect"]
        from usdml.render.frame import FrameRenderer
        from usdml.stage import StageDelegate

        d = StageDelegate(stage)
        names = d.snapshot(d.start_time).mesh_paths
        h, w = got.shape[:2]
        ids = FrameRenderer(d, d.usdml_settings).render(d.start_time, w, h, {"primId"}).buffers["primId"]
        on_floor = ids == names.index("/World/Box/Floor")
    return {"floor": floor, "roughness": roughness, "bounces": bounces,
            "ratio": gr.energy_ratio(got, ref),
            "ratio_floor": gr.energy_ratio(got[on_floor], ref[on_floor]),
            "ratio_walls": gr.energy_ratio(got[~on_floor], ref[~on_floor]),
            "direct_floor": gr.energy_ratio(frame["direct"][on_floor], ref_direct[on_floor])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--roughness", type=float, default=0.3)
    ap.add_argument("--colour", default="0.95,0.64,0.54", help="the metal floor's colour (F0 = F90)")
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--vpls", type=int, default=20_000)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    colour = tuple(float(x) for x in args.colour.split(","))
    rows = [measure(f, args.roughness, colour, args.width, args.bounces, args.spp, args.vpls)
            for f in ("diffuse", "metal", "plastic")]
    for r in rows:
        print(f"{r['floor']:8s} floor: indirect / path traced {r['ratio']:.3f} (floor pixels {r['ratio_floor']:.3f}, "
              f"walls {r['ratio_walls']:.3f}); direct on the floor {r['direct_floor']:.3f}")
    if args.json:
        print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
