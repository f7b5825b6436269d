"""VPL indirect light against references that share none of usdml's VPL code.

* **Path tracing**: Mitsuba 3 (``pip install -e ".[reference]"``, ``scalar_rgb`` variant) renders the same
  USD stage (read by :mod:`usdml.reference` with pxr alone) with ``max_depth = bounces + 2``
  and ``max_depth = 2``; their difference (same seed, so the direct parts cancel sample by sample) is
  the indirect light of ``bounces`` diffuse bounces, which usdml's ``indirect`` AOV with
  ``usdml:vpl:bounces = bounces`` should match.
* **Furnace**: a closed diffuse sphere of albedo ρ with a point light at its centre. Any two points of a
  sphere see each other with the same geometry term ``cos θ cos θ' / d² = 1 / 4R²``, so after the first
  bounce the radiance is uniform and every bounce multiplies it by ρ: ``indirect = direct · (ρ + … + ρ^B)``.

``python tools/gi_reference.py [--vpls N] [--vpl-bounces B] [--imageWidth W] [--spp S] [--json]`` prints, for
``--gi vpl-bruteforce``, ``--gi lgh`` and ``--gi svo``, the ``indirect`` energy ratio against Mitsuba on a closed
Cornell-style box (two point lights, camera inside), the median 16×16-block relative error, and the
furnace ratio against the analytic series.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])
METHODS = ("vpl-bruteforce", "lgh", "svo")

#: closed box (Cornell-box proportions, scene units = metres): walls (name, corners, albedo)
BOX = (5.56, 5.488, 5.592)
_WHITE, _RED, _GREEN = (0.73, 0.73, 0.73), (0.63, 0.065, 0.05), (0.14, 0.45, 0.091)
#: the two point lights: (position, radiance L, radius r, colour); I = L·π·r² (treatAsPoint, normalize off)
BOX_LIGHTS = (((1.9, 4.9, -2.4), 1200.0, 0.1, (1.0, 0.9, 0.8)), ((3.9, 4.6, -3.4), 900.0, 0.1, (0.8, 0.9, 1.0)))


def _quad(stage, path: str, corners, albedo) -> None:
    from pxr import UsdGeom

    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr([tuple(map(float, c)) for c in corners])
    m.CreateFaceVertexCountsAttr([4] * (len(corners) // 4))
    m.CreateFaceVertexIndicesAttr(list(range(len(corners))))
    m.CreateSubdivisionSchemeAttr("none")
    m.CreateDisplayColorAttr([tuple(albedo)])


def _point_light(stage, path: str, position, radiance: float, radius: float, color) -> None:
    from pxr import Gf, UsdGeom, UsdLux

    light = UsdLux.SphereLight.Define(stage, path)
    light.CreateIntensityAttr(radiance)
    light.CreateRadiusAttr(radius)
    light.CreateColorAttr(Gf.Vec3f(*color))
    light.CreateTreatAsPointAttr(True)
    UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*position))


def _camera(stage, position, target, focal: float = 14.0, aperture: float = 36.0) -> None:
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(focal)
    cam.CreateHorizontalApertureAttr(aperture)
    cam.CreateVerticalApertureAttr(aperture)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    look = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*position), Gf.Vec3d(*target), Gf.Vec3d(0, 1, 0))
    cam.AddTransformOp().Set(look.GetInverse())


def _new_stage(path: str):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    return stage


def closed_box(path: str | Path) -> str:
    """A closed Cornell-style box (six walls, a short block), two point lights, a camera inside; saved to ``path``."""
    x, y, z = BOX
    z = -z
    walls = {
        "Floor": ([(0, 0, 0), (x, 0, 0), (x, 0, z), (0, 0, z)], _WHITE),
        "Ceiling": ([(0, y, 0), (0, y, z), (x, y, z), (x, y, 0)], _WHITE),
        "BackWall": ([(0, 0, z), (x, 0, z), (x, y, z), (0, y, z)], _WHITE),
        "FrontWall": ([(0, 0, 0), (0, y, 0), (x, y, 0), (x, 0, 0)], _WHITE),
        "GreenWall": ([(x, 0, z), (x, 0, 0), (x, y, 0), (x, y, z)], _GREEN),
        "RedWall": ([(0, 0, 0), (0, 0, z), (0, y, z), (0, y, 0)], _RED),
    }
    stage = _new_stage(path)
    for name, (corners, albedo) in walls.items():
        _quad(stage, f"/World/Box/{name}", corners, albedo)
    # an axis-aligned block on the floor: shadows and contact corners
    lo, hi = np.array([3.0, 0.0, -3.4]), np.array([4.4, 1.6, -2.0])
    c = [np.where([(i >> k) & 1 for k in range(3)], hi, lo) for i in range(8)]
    faces = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (4, 6, 7, 5)]   # no bottom face
    _quad(stage, "/World/Box/Block", [c[i] for f in faces for i in f], _WHITE)
    for i, (p, radiance, radius, color) in enumerate(BOX_LIGHTS):
        _point_light(stage, f"/World/Lights/Light_{i}", p, radiance, radius, color)
    _camera(stage, (2.78, 2.6, -0.15), (2.78, 2.2, -5.592))
    stage.Save()
    return str(path)


def furnace_sphere(path: str | Path, albedo: float, radius: float = 2.0, intensity: float = 10.0,
                   segments: int = 48) -> str:
    """A closed diffuse sphere (a faceted Mesh of ``segments`` × ``segments / 2`` quads, grey ``albedo``), a
    point light of intensity ``intensity`` (nit·m²: SphereLight treatAsPoint, L·π·r²) at its centre and a
    camera inside; saved to ``path``."""
    from pxr import UsdGeom

    stage = _new_stage(path)
    rings = segments // 2
    lat = np.linspace(-np.pi / 2, np.pi / 2, rings + 1)[:, None]
    lon = np.linspace(0.0, 2.0 * np.pi, segments + 1)[None, :-1]
    pts = radius * np.stack(np.broadcast_arrays(np.cos(lat) * np.cos(lon), np.sin(lat), np.cos(lat) * np.sin(lon)),
                            axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    quads = np.stack([a, b, b + segments, a + segments], axis=-1).reshape(-1, 4)
    m = UsdGeom.Mesh.Define(stage, "/World/Shell")
    m.CreatePointsAttr([tuple(map(float, q)) for q in pts])
    m.CreateFaceVertexCountsAttr([4] * len(quads))
    m.CreateFaceVertexIndicesAttr(quads.ravel().tolist())
    m.CreateSubdivisionSchemeAttr("none")
    m.CreateDisplayColorAttr([(albedo, albedo, albedo)])
    r = 0.01
    _point_light(stage, "/World/Light", (0.0, 0.0, 0.0), intensity / (math.pi * r * r), r, (1.0, 1.0, 1.0))
    _camera(stage, (0.0, 0.3 * radius, 0.5 * radius), (0.0, -0.2 * radius, -radius), focal=10.0)
    stage.Save()
    return str(path)


def furnace_expected(albedo: float, bounces: int) -> float:
    """Analytic ``indirect / direct`` in the furnace sphere: ρ + ρ² + … + ρ^bounces."""
    return float(sum(albedo ** b for b in range(1, bounces + 1)))


# ---------------------------------------------------------------------------------------------- renders


def render_usdml(stage: str, method: str, vpls: int, bounces: int, width: int, seed: int = 0, **settings) -> dict:
    """``{"direct", "indirect"}`` (H, W, 3) float32 of usdml's frame with ``--gi method``, ``bounces`` VPL bounces."""
    from dataclasses import replace

    from usdml.render.frame import FrameRenderer
    from usdml.stage import StageDelegate

    d = StageDelegate(stage)
    s = replace(d.usdml_settings, gi=method, vpl_count=int(vpls), vpl_bounces=int(bounces), seed=int(seed), **settings)
    snap = d.snapshot(d.start_time)
    w, h = snap.camera.resolution(width)
    b = FrameRenderer(d, s).render(d.start_time, w, h, {"direct", "indirect"}).buffers
    return {k: np.asarray(b[k], np.float32) for k in ("direct", "indirect")}


def render_mitsuba(stage: str, width: int, bounces: int, spp: int, seed: int = 0) -> dict:
    """``{"direct", "indirect"}`` (H, W, 3) float32 path traced by Mitsuba 3 (``scalar_rgb``) from the
    stage as :mod:`usdml.reference` reads it with pxr alone (none of usdml's stage code)."""
    from usdml import reference

    scene = reference.load(stage, None, width)
    direct, total = (reference.render(scene, spp, b, seed, by_light=False) for b in (0, bounces))
    return {"direct": direct, "indirect": total - direct}


# ---------------------------------------------------------------------------------------------- measures


def energy_ratio(image: np.ndarray, reference: np.ndarray) -> float:
    """Σ luminance(image) / Σ luminance(reference) over all pixels."""
    return float((np.asarray(image, np.float64) @ LUMA).sum() / (np.asarray(reference, np.float64) @ LUMA).sum())


def block_error(image: np.ndarray, reference: np.ndarray, block: int = 16) -> float:
    """Median over ``block`` × ``block`` pixel blocks of |mean lum(image) − mean lum(ref)| / mean lum(ref)."""
    a, r = (np.asarray(x, np.float64) @ LUMA for x in (image, reference))
    h, w = (s // block * block for s in r.shape)
    fold = lambda x: x[:h, :w].reshape(h // block, block, w // block, block).mean(axis=(1, 3))  # noqa: E731
    ma, mr = fold(a), fold(r)
    ok = mr > 0
    return float(np.median(np.abs(ma[ok] - mr[ok]) / mr[ok]))


def measure(vpls: int = 20_000, bounces: int = 3, width: int = 64, spp: int = 256, seed: int = 0,
            albedo: float = 0.5, methods=METHODS, mitsuba: bool = True, **settings) -> dict:
    """Energy ratio and median block error of ``indirect`` against Mitsuba (closed box), and the
    furnace ratio against the analytic series, for every method."""
    out: dict = {"vpls": vpls, "bounces": bounces, "width": width, "spp": spp, "furnace_albedo": albedo,
                 "methods": {}}
    with tempfile.TemporaryDirectory() as tmp:
        box = closed_box(Path(tmp) / "box.usda")
        sphere = furnace_sphere(Path(tmp) / "sphere.usda", albedo)
        ref = render_mitsuba(box, width, bounces, spp, seed) if mitsuba else None
        expected = furnace_expected(albedo, bounces)
        for method in methods:
            row: dict = {}
            if ref is not None:
                got = render_usdml(box, method, vpls, bounces, width, seed, **settings)
                row["direct_ratio"] = energy_ratio(got["direct"], ref["direct"])
                row["indirect_ratio"] = energy_ratio(got["indirect"], ref["indirect"])
                row["block_error"] = block_error(got["indirect"], ref["indirect"])
            f = render_usdml(sphere, method, vpls, bounces, width, seed, **settings)
            row["furnace_ratio"] = float((f["indirect"] @ LUMA).sum() / (f["direct"] @ LUMA).sum() / expected)
            out["methods"][method] = row
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter, allow_abbrev=False)
    ap.add_argument("--vpls", type=int, default=20_000)
    ap.add_argument("--vpl-bounces", type=int, default=3, help="diffuse bounces of the indirect light")
    ap.add_argument("--imageWidth", type=int, default=64)
    ap.add_argument("--spp", type=int, default=256, help="Mitsuba samples per pixel")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--albedo", type=float, default=0.5, help="furnace sphere albedo")
    ap.add_argument("--gi", default=",".join(METHODS), help="--gi methods to measure, comma-separated")
    ap.add_argument("--no-mitsuba", action="store_true", help="furnace only")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    r = measure(a.vpls, a.vpl_bounces, a.imageWidth, a.spp, a.seed, a.albedo, a.gi.split(","), not a.no_mitsuba)
    if a.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"{a.vpls} VPLs, {a.vpl_bounces} bounces, {a.imageWidth} px, Mitsuba {a.spp} spp; furnace rho {a.albedo}")
    for method, row in r["methods"].items():
        print(f"{method:>15}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
