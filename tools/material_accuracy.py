#!/usr/bin/env python
"""The preview surface's shading against the BRDF evaluated independently (issue 51's "Shading" target).

Seeded stages of spheres over a ground, each sphere a random material of one family (metallic workflow metal or
dielectric, specular workflow, clearcoat, emission, ior), lit by a point light and a distant light. For each
stage and visibility backend:

1. one light at a time, a white Lambertian render (no materials: its ``direct`` is E_i/π per pixel, E_i the
   light's shadowed irradiance) and a render with the materials;
2. the materials under both lights.

Each pixel's expected colour is ``Σ_i E_i·f(e, l_i) + emission`` with ``f`` the BRDF written out by hand here
(:func:`hand_brdf`, float64, no usdml code) at the frame's own P and shading normal (its ``P`` and ``normal``
AOVs), e toward the camera and l_i toward light i. Reported: the median and 95th percentile of the per-pixel
relative error of ``color`` over the spheres' lit pixels, per backend (the issue's targets: 1 % and 5 %).

Usage::

    .venv/bin/python tools/material_accuracy.py --seeds 0:4 --visibility exact,voxel --width 96
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

FAMILIES = ("metal", "dielectric", "specular workflow", "clearcoat", "emissive")


def hand_brdf(n, e, l, diffuseColor=(0.18, 0.18, 0.18), metallic=0.0, roughness=0.5, ior=1.5, clearcoat=0.0,
              clearcoatRoughness=0.01, useSpecularWorkflow=0, specularColor=(0.0, 0.0, 0.0), **_):
    """f(e, l) (K, 3) of UsdPreviewSurface (usdImaging's previewSurface.glslfx as issue 51 writes it, float64):
    radiance = E · f with E the irradiance (its cos θ included). ``n``, ``e``, ``l``: (K, 3) unit vectors."""
    diffuse, spec_in = np.asarray(diffuseColor, float), np.asarray(specularColor, float)
    r = (1 - ior) / (1 + ior)
    if useSpecularWorkflow:
        f0, f90, rho = spec_in, np.ones(3), diffuse
    else:
        sc = (1 - metallic) * np.ones(3) + metallic * diffuse
        f0, f90, rho = (1 - metallic) * r * r * sc + metallic * sc, sc, diffuse * (1 - metallic)
    h = e + l
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    nl, ne = (n * l).sum(1), (n * e).sum(1)
    nh, eh = (n * h).sum(1), (e * h).sum(1)
    schlick = (1 - eh) ** 5

    def lobe(alpha):
        d = alpha ** 2 / (math.pi * (nh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
        k = alpha / 2
        g = nl / (nl * (1 - k) + k) * ne / (ne * (1 - k) + k)
        return d * g / (4 * nl * ne)

    fresnel = f0 + (f90 - f0) * schlick[:, None]
    spec = fresnel * lobe(max(roughness, 0.001) ** 2)[:, None]
    coat = clearcoat * (r * r + (1 - r * r) * schlick) * lobe(max(clearcoatRoughness, 0.001) ** 2)
    out = rho / math.pi * (1 - fresnel) + spec + coat[:, None]
    return np.where(((nl > 0) & (ne > 0))[:, None], out, 0.0)


def random_material(rng: np.random.Generator, family: str) -> dict:
    m = {"diffuseColor": tuple(rng.uniform(0.05, 0.95, 3)), "roughness": float(rng.uniform(0.15, 0.9))}
    if family == "metal":
        m["metallic"] = float(rng.choice([1.0, rng.uniform(0.3, 1.0)]))
    elif family == "dielectric":
        m["ior"] = float(rng.uniform(1.3, 2.5))
    elif family == "specular workflow":
        m.update(useSpecularWorkflow=1, specularColor=tuple(rng.uniform(0.02, 0.9, 3)))
    elif family == "clearcoat":
        m.update(clearcoat=float(rng.uniform(0.5, 1.0)), clearcoatRoughness=float(rng.uniform(0.05, 0.4)))
    else:
        m["emissiveColor"] = tuple(rng.uniform(0.0, 2.0, 3))
    return m


def build(folder: Path, seed: int, materials: bool, lights: tuple[str, ...]) -> tuple[str, list, dict]:
    """A stage of 3 × 3 spheres (one material family each, by seed) over a ground; returns (path, per-sphere
    materials, light geometry)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

    rng = np.random.default_rng(seed)
    name = f"s{seed}_{int(materials)}_{'_'.join(lights)}.usda"
    stage = Usd.Stage.CreateNew(str(folder / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    ground = UsdGeom.Mesh.Define(stage, "/World/ground")
    ground.CreatePointsAttr([(-8, 0, -8), (-8, 0, 8), (8, 0, 8), (8, 0, -8)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    ground.CreateDisplayColorPrimvar().Set([(1.0, 1.0, 1.0)])
    spheres = []
    for k in range(9):
        family = FAMILIES[(k + seed) % len(FAMILIES)]
        inputs = random_material(rng, family)
        s = UsdGeom.Sphere.Define(stage, f"/World/s{k}")
        s.CreateRadiusAttr(0.8)
        s.AddTranslateOp().Set(Gf.Vec3d(2.2 * (k % 3 - 1), 0.8, 2.2 * (k // 3 - 1)))
        s.CreateDisplayColorPrimvar().Set([(1.0, 1.0, 1.0)])
        if materials:
            mat = UsdShade.Material.Define(stage, f"/World/Looks/m{k}")
            pbr = UsdShade.Shader.Define(stage, f"/World/Looks/m{k}/pbr")
            pbr.CreateIdAttr("UsdPreviewSurface")
            for key, value in inputs.items():
                if key == "useSpecularWorkflow":
                    pbr.CreateInput(key, Sdf.ValueTypeNames.Int).Set(int(value))
                elif isinstance(value, tuple):
                    pbr.CreateInput(key, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*value))
                else:
                    pbr.CreateInput(key, Sdf.ValueTypeNames.Float).Set(float(value))
            mat.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
            UsdShade.MaterialBindingAPI.Apply(s.GetPrim()).Bind(mat)
        spheres.append(inputs)
    point = np.array([rng.uniform(-3, 3), rng.uniform(3, 5), rng.uniform(-3, 3)])
    tilt, turn = float(rng.uniform(-70, -35)), float(rng.uniform(0, 360))
    if "point" in lights:
        light = UsdLux.SphereLight.Define(stage, "/World/point")
        light.CreateTreatAsPointAttr(True)
        light.CreateIntensityAttr(40.0)
        light.AddTranslateOp().Set(Gf.Vec3d(*point))
    if "distant" in lights:
        sun = UsdLux.DistantLight.Define(stage, "/World/sun")
        sun.CreateIntensityAttr(1.5)
        sun.AddRotateYOp().Set(turn)
        sun.AddRotateXOp().Set(tilt)
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(30)
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 7, 9))
    cam.AddRotateXOp().Set(-38)
    stage.Save()
    # the distant light's direction toward the light: ops apply last first (row vectors: v · R_x · R_y)
    m = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), tilt)) * \
        Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 1, 0), turn))
    axis = np.array(m.TransformDir(Gf.Vec3d(0, 0, -1)))
    camera = np.array(cam.ComputeLocalToWorldTransform(1).ExtractTranslation())
    return str(folder / name), spheres, {"point": point, "distant": -axis / np.linalg.norm(axis), "camera": camera}


def render(path: str, visibility: str, width: int, aovs=("color", "direct", "P", "normal", "primId")) -> dict:
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, visibility=visibility, voxel_resolution=96))
    try:
        return r.render(d.start_time, width, width, set(aovs)).buffers
    finally:
        r.close()


def measure(seed: int, visibility: str, width: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        full_path, spheres, geo = build(folder, seed, True, ("point", "distant"))
        full = render(full_path, visibility, width)
        p = full["P"].reshape(-1, 3).astype(np.float64)
        n = full["normal"].reshape(-1, 3).astype(np.float64)
        prim = full["primId"].reshape(-1)
        e = geo["camera"] - p
        e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-30)
        want = np.zeros_like(p)
        lit = np.zeros(len(p), bool)
        from usdml.stage import StageDelegate

        names = StageDelegate(full_path).snapshot(1).mesh_paths
        for light in ("point", "distant"):
            white = render(build(folder, seed, False, (light,))[0], visibility, width, ("direct", "P"))
            assert np.allclose(white["P"], full["P"], atol=1e-5)
            irradiance = math.pi * white["direct"].reshape(-1, 3)[:, 0].astype(np.float64)
            l = geo[light] - p if light == "point" else np.broadcast_to(geo[light], p.shape)
            l = l / np.maximum(np.linalg.norm(l, axis=1, keepdims=True), 1e-30)
            lit |= irradiance > 1e-4 * irradiance.max()
            for k, inputs in enumerate(spheres):
                rows = np.flatnonzero(prim == names.index(f"/World/s{k}")) if f"/World/s{k}" in names else []
                if len(rows):
                    want[rows] += irradiance[rows, None] * hand_brdf(n[rows], e[rows], l[rows], **inputs)
            ground = np.flatnonzero(prim == names.index("/World/ground"))
            want[ground] += irradiance[ground, None] / math.pi
        for k, inputs in enumerate(spheres):
            rows = np.flatnonzero(prim == names.index(f"/World/s{k}"))
            want[rows] += np.asarray(inputs.get("emissiveColor", (0.0, 0.0, 0.0)))
            lit[rows] |= "emissiveColor" in inputs
        got = full["color"][..., :3].reshape(-1, 3).astype(np.float64)
        on_spheres = np.isin(prim, [names.index(f"/World/s{k}") for k in range(len(spheres))])
        sel = lit & on_spheres & (np.abs(want).max(1) > 1e-3)      # the materials' pixels, not the ground's
        rel = (np.abs(got[sel] - want[sel]) / np.maximum(want[sel], 1e-3 * want[sel].max())).ravel()
        return {"seed": seed, "visibility": visibility, "pixels": int(sel.sum()),
                "median": float(np.median(rel)), "p95": float(np.percentile(rel, 95))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--seeds", default="0:4", help="first:last (exclusive) stage seeds")
    ap.add_argument("--visibility", default="exact,voxel")
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    lo, hi = (int(x) for x in args.seeds.split(":"))
    rows = []
    for vis in args.visibility.split(","):
        for seed in range(lo, hi):
            row = measure(seed, vis, args.width)
            rows.append(row)
            print(f"{vis:6s} seed {seed}: {row['pixels']} px, median {100 * row['median']:.4f} %, "
                  f"p95 {100 * row['p95']:.4f} %", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
