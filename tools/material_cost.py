#!/usr/bin/env python
"""What a glossy material costs a frame: a generated city shaded diffuse against the same city glossy (issue 51).

The city is tools/make_city.py's (``--seed``, ``--triangles``; 1,024 point lights); the glossy stage is a layer
over it binding one clearcoated UsdPreviewSurface to ``/World`` (so every mesh and every instance has it):
roughness 0.3, metallic 0.5, clearcoat 1, clearcoatRoughness 0.1, its diffuse colour each mesh's
``displayColor`` (a ``UsdPrimvarReader_float3``), so the two frames differ only in the BRDF. The diffuse frame is
the city as written (no material: ``displayColor``, the Lambertian path).

For each visibility backend (and, for ``voxel``, each instruction set of the compiled kernels this CPU runs:
AVX-512 where it has it, AVX2; ``--isa`` to choose), both stages render two consecutive frames with
``--direct all`` at one ray per pixel and the second is timed (``usdml.bench.steady_frame``: the steady state of a
sequence); the ratio glossy / diffuse is of the same run, frames interleaved (diffuse, glossy, diffuse, glossy
with ``--repeat 2``: the best of each), so a load that comes and goes on a shared machine falls on both.

The diffuse frame sums its lights with a matrix product (NumPy's BLAS) wherever a backend has no fused kernel
(``exact``): BLAS's own threads then compete with the shading's thread pool, and on a small machine that frame's
time swings with them; ``--blas-threads 1`` (``OPENBLAS_NUM_THREADS``, set before NumPy loads) takes them out
(the results record the variable as it was).

Usage::

    python tools/material_cost.py                                  # 200k triangles, 256 px: several minutes
    python tools/material_cost.py --triangles 20000 --imageWidth 96 # a minute
    python tools/material_cost.py --visibility voxel --isa avx2,scalar --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: the issue's glossy clearcoated preview surface
GLOSSY = {"roughness": 0.3, "metallic": 0.5, "clearcoat": 1.0, "clearcoatRoughness": 0.1}


def glossy_layer(city: Path, out: Path) -> Path:
    """``out``: a layer over ``city`` binding the :data:`GLOSSY` preview surface to ``/World`` (its diffuse colour
    each mesh's displayColor)."""
    from pxr import Sdf, Usd, UsdShade

    stage = Usd.Stage.CreateNew(str(out))
    stage.GetRootLayer().subLayerPaths.append(os.path.relpath(city, out.parent))
    world = stage.OverridePrim("/World")
    stage.SetDefaultPrim(world)
    mat = UsdShade.Material.Define(stage, "/World/Looks/Glossy")
    pbr = UsdShade.Shader.Define(stage, "/World/Looks/Glossy/pbr")
    pbr.CreateIdAttr("UsdPreviewSurface")
    for name, value in GLOSSY.items():
        pbr.CreateInput(name, Sdf.ValueTypeNames.Float).Set(value)
    color = UsdShade.Shader.Define(stage, "/World/Looks/Glossy/displayColor")
    color.CreateIdAttr("UsdPrimvarReader_float3")
    color.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
    color.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(color.ConnectableAPI(), "result")
    mat.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(world).Bind(mat)
    stage.GetRootLayer().Save()
    return out


def isas(requested: str) -> list[str]:
    """The instruction sets to time the voxel backend's compiled kernels with (``usdml.native.ISAS`` names):
    ``requested`` comma-separated, or for ``cpu`` the two SIMD ones this CPU runs (``auto`` is AVX-512 where it has
    it, else the same as ``avx2`` and left out)."""
    from usdml.visibility.voxel.native import isa_width

    if requested != "cpu":
        return requested.split(",")
    return ["auto", "avx2"] if isa_width("auto") == 16 else ["avx2"]


def label(isa: str) -> str:
    from usdml.native import kernel_label
    from usdml.visibility.voxel.native import isa_width

    return kernel_label(isa_width(isa)) if isa_width(isa) else "warp"


def timed_frame(stage: str, visibility: str, width: int, options: dict) -> dict:
    """The second of two frames of ``stage`` rendered with ``visibility`` at ``width`` px, one ray per pixel."""
    from usdml.bench import next_frame, steady_frame
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    settings = delegate.usdml_settings.updated(visibility=visibility, direct="all", gi="none", pixel_samples=1)
    f0 = delegate.start_time
    w, h = delegate.snapshot(f0).camera.resolution(width)
    with steady_frame(delegate, settings, f0, w, h, backend_options=options) as (res, seconds, r):
        st = res.stats
        return {"seconds": seconds, "shading_seconds": st.shading_seconds, "gbuffer_seconds": st.gbuffer_seconds,
                "update_seconds": st.update_seconds, "resolution": [w, h], "frame": next_frame(delegate, f0)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--triangles", type=int, default=200_000, help="the city's size (default: %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="the city's seed (odd: for reporting; default: %(default)s)")
    p.add_argument("--imageWidth", type=int, default=256, help="frame width in pixels (default: %(default)s)")
    p.add_argument("--visibility", default="exact,voxel", help="backends, comma-separated (default: %(default)s)")
    p.add_argument("--isa", default="cpu", help="the voxel backend's instruction sets, comma-separated of auto, "
                   "avx2, scalar; cpu: the SIMD ones this CPU has (default: %(default)s)")
    p.add_argument("--repeat", type=int, default=1, help="timed frames per case, the best kept (default: %(default)s)")
    p.add_argument("--blas-threads", type=int, help="OPENBLAS_NUM_THREADS for this run (default: as set)")
    p.add_argument("--out", help="folder for the stages (default: a temporary one)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if args.blas_threads is not None:
        if "numpy" in sys.modules:
            p.error("--blas-threads must be set before NumPy is loaded (run the tool as a script)")
        os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)

    from command_timing import machine
    from make_city import make_city

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        city = make_city(args.seed, str(out), args.triangles)
        diffuse = out / f"unseen_city_{args.seed}.usda"
        glossy = glossy_layer(diffuse, out / f"unseen_city_{args.seed}_glossy.usda")
        if not args.json:
            print(f"city {diffuse.name}: {city.get('triangles', args.triangles)} triangles, stages in "
                  f"{time.perf_counter() - t0:.1f} s", flush=True)
        rows = []
        for vis in args.visibility.split(","):
            for isa in isas(args.isa) if vis == "voxel" else [None]:
                options = {"report": lambda s: None} | ({"native_isa": isa} if isa else {})
                best: dict[str, dict] = {}
                for _ in range(max(1, args.repeat)):
                    for name, stage in (("diffuse", diffuse), ("glossy", glossy)):
                        t = timed_frame(str(stage), vis, args.imageWidth, options)
                        if name not in best or t["seconds"] < best[name]["seconds"]:
                            best[name] = t
                row = {"visibility": vis, "kernel": label(isa) if isa else None, **best,
                       "glossy_over_diffuse": best["glossy"]["seconds"] / best["diffuse"]["seconds"],
                       "shading_glossy_over_diffuse": (best["glossy"]["shading_seconds"]
                                                       / max(best["diffuse"]["shading_seconds"], 1e-9))}
                rows.append(row)
                if not args.json:
                    d, g = best["diffuse"], best["glossy"]
                    w, h = d["resolution"]
                    print(f"{vis:>6} {row['kernel'] or '':<14} {w}x{h}: diffuse {d['seconds']:.2f} s "
                          f"(shading {d['shading_seconds']:.2f}), glossy {g['seconds']:.2f} s "
                          f"(shading {g['shading_seconds']:.2f}): {row['glossy_over_diffuse']:.2f}x the frame, "
                          f"{row['shading_glossy_over_diffuse']:.2f}x the shading", flush=True)
    result = {"triangles": args.triangles, "seed": args.seed, "image_width": args.imageWidth,
              "lights": city.get("lights"), "material": GLOSSY,
              "machine": machine() | {"load_average": list(os.getloadavg())},
              "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "rows": rows}
    if args.json:
        print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
