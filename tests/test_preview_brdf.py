"""The whole UsdPreviewSurface rendered (issue 51): the BRDF against values worked out by hand, energy, bindings
through GeomSubsets, emission and the diffuse/specular/emission AOVs, every visibility backend, and what is not
rendered said once.

The hand reference (:func:`hand_brdf`) is written here from the issue's text of usdImaging's
``previewSurface.glslfx`` in float64, sharing no code with ``kernels/brdf`` nor ``usdml.scene.shading``. The
light's irradiance E comes from a second render of the same view with a white Lambertian ground (no material):
its ``direct`` is E/π per pixel, so the comparison does not depend on the light's units.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade

from conftest import add_quad, add_top_camera

CAMERA = np.array([0.0, 3.0, 0.0])
LIGHT = np.array([1.0, 2.0, 0.5])
N = np.array([0.0, 1.0, 0.0])

CASES = {
    "gold": dict(diffuseColor=(1.0, 0.77, 0.34), metallic=1.0, roughness=0.3),
    "dielectric": dict(diffuseColor=(0.2, 0.4, 0.8), roughness=0.25, ior=1.5),
    "spec defaults": dict(),        # the spec's defaults: 0.18 grey, roughness 0.5, ior 1.5 (a 4 % GGX lobe)
    "clearcoat": dict(diffuseColor=(0.5, 0.1, 0.1), roughness=0.6, clearcoat=1.0, clearcoatRoughness=0.1),
    "specular workflow": dict(useSpecularWorkflow=1, diffuseColor=(0.3, 0.3, 0.3), specularColor=(0.9, 0.9, 0.2),
                              roughness=0.35),
    "half metal, ior 2": dict(diffuseColor=(0.6, 0.6, 0.9), metallic=0.5, roughness=0.45, ior=2.0),
}

_TYPES = {"useSpecularWorkflow": Sdf.ValueTypeNames.Int}


def hand_brdf(n, e, l, diffuseColor=(0.18, 0.18, 0.18), metallic=0.0, roughness=0.5, ior=1.5, clearcoat=0.0,
              clearcoatRoughness=0.01, useSpecularWorkflow=0, specularColor=(0.0, 0.0, 0.0), **_):
    """f(e, l) (K, 3) of the preview surface, times π-free: radiance = E · f (E with its cos θ)."""
    diffuse, spec_in = np.asarray(diffuseColor, float), np.asarray(specularColor, float)
    r = (1 - ior) / (1 + ior)
    if useSpecularWorkflow:
        f0, f90, rho = spec_in, np.ones(3), diffuse
    else:
        sc = (1 - metallic) * np.ones(3) + metallic * diffuse
        f0, f90, rho = (1 - metallic) * r * r * sc + metallic * sc, sc, diffuse * (1 - metallic)
    h = e + l
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nl, ne = (n * l).sum(1), (n * e).sum(1)
    nh, eh = (n * h).sum(1), (e * h).sum(1)
    schlick = (1 - eh) ** 5

    def lobe(alpha):
        d = alpha ** 2 / (math.pi * (nh ** 2 * (alpha ** 2 - 1) + 1) ** 2)
        k = alpha / 2
        g = nl / (nl * (1 - k) + k) * ne / (ne * (1 - k) + k)
        return d * g / (4 * nl * ne)

    fresnel = f0 + (f90 - f0) * schlick[:, None]
    spec = fresnel * lobe(roughness ** 2)[:, None]
    coat = clearcoat * (r * r + (1 - r * r) * schlick) * lobe(clearcoatRoughness ** 2)
    return rho / math.pi * (1 - fresnel) + spec + coat[:, None]


def material(stage, path: str, **inputs) -> UsdShade.Material:
    mat = UsdShade.Material.Define(stage, path)
    pbr = UsdShade.Shader.Define(stage, f"{path}/pbr")
    pbr.CreateIdAttr("UsdPreviewSurface")
    for name, value in inputs.items():
        if name in _TYPES:
            pbr.CreateInput(name, _TYPES[name]).Set(value)
        elif isinstance(value, tuple):
            pbr.CreateInput(name, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*value))
        else:
            pbr.CreateInput(name, Sdf.ValueTypeNames.Float).Set(float(value))
    mat.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
    return mat


def bind(prim, mat) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)


def ground(new_stage, name: str, inputs: dict | None, light: str = "point"):
    """A 10 × 10 ground seen from straight above at CAMERA, lit by one point light at LIGHT (or a distant light);
    ``inputs``: its preview surface, None: a white Lambertian ground (displayColor, no material)."""
    stage = new_stage(name, start=1, end=1)
    quad = add_quad(stage, "/World/ground", size=10)
    if inputs is None:
        quad.CreateDisplayColorPrimvar().Set([(1.0, 1.0, 1.0)])
    else:
        bind(quad.GetPrim(), material(stage, "/World/Looks/m", **inputs))
    add_top_camera(stage, CAMERA[1])
    if light == "point":
        sphere = UsdLux.SphereLight.Define(stage, "/World/light")
        sphere.CreateTreatAsPointAttr(True)
        sphere.CreateIntensityAttr(30.0)
        sphere.AddTranslateOp().Set(Gf.Vec3d(*LIGHT))
    else:
        sun = UsdLux.DistantLight.Define(stage, "/World/sun")
        sun.CreateIntensityAttr(2.0)
        sun.AddRotateXOp().Set(-50.0)
        sun.AddRotateYOp().Set(20.0)
    stage.Save()
    return stage.GetRootLayer().realPath


def render(path, aovs=("direct", "P", "color", "specular", "diffuse", "emission", "albedo"), width=48, **settings):
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, **settings))
    try:
        return r.render(d.start_time, width, width, set(aovs)).buffers
    finally:
        r.close()


def light_direction(p: np.ndarray, light: str) -> np.ndarray:
    if light == "point":
        l = LIGHT - p
        return l / np.linalg.norm(l, axis=1, keepdims=True)
    # xformOpOrder [rotateX, rotateY]: the last op applies first (row vectors: v · R_y · R_x)
    m = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 1, 0), 20.0)) * \
        Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), -50.0))
    axis = np.array(m.TransformDir(Gf.Vec3d(0, 0, -1)))
    return np.broadcast_to(-axis / np.linalg.norm(axis), p.shape)


def expected(lambert: dict, shaded: dict, inputs: dict, light: str):
    """(rendered, hand) (K, 3) over the pixels where the ground is lit."""
    p = shaded["P"].reshape(-1, 3).astype(np.float64)
    assert np.allclose(p, lambert["P"].reshape(-1, 3), atol=1e-5)      # the same view: the same points
    e_irr = math.pi * lambert["direct"].reshape(-1, 3)[:, 0].astype(np.float64)   # E of a white Lambertian
    lit = e_irr > 1e-3 * e_irr.max()
    e = CAMERA - p[lit]
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    f = hand_brdf(np.broadcast_to(N, e.shape), e, np.array(light_direction(p[lit], light)), **inputs)
    return shaded["direct"].reshape(-1, 3)[lit].astype(np.float64), e_irr[lit, None] * f


@pytest.mark.parametrize("case", list(CASES))
def test_point_light_over_a_plane_matches_the_brdf_by_hand(new_stage, case):
    inputs = CASES[case]
    lambert = render(ground(new_stage, "white.usda", None))
    shaded = render(ground(new_stage, "m.usda", inputs))
    got, want = expected(lambert, shaded, inputs, "point")
    rel = np.abs(got - want) / np.maximum(want, 1e-3 * want.max())
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05 and rel.max() < 0.05, (np.median(rel), rel.max())
    assert shaded["specular"].max() > 0


def test_distant_light_and_the_aovs(new_stage):
    """Under a distant light; direct = diffuse + specular; albedo is the diffuse reflectance diffuseColor·(1 − m)."""
    inputs = CASES["half metal, ior 2"]
    lambert = render(ground(new_stage, "white.usda", None, light="distant"))
    shaded = render(ground(new_stage, "m.usda", inputs, light="distant"))
    got, want = expected(lambert, shaded, inputs, "distant")
    rel = np.abs(got - want) / np.maximum(want, 1e-3 * want.max())
    assert np.median(rel) < 0.01 and rel.max() < 0.05
    assert np.allclose(shaded["diffuse"] + shaded["specular"], shaded["direct"], atol=1e-3)
    assert shaded["specular"].max() > 0.05 * shaded["direct"].max()
    assert np.allclose(shaded["albedo"][24, 24], np.array(inputs["diffuseColor"]) * 0.5, atol=1e-3)
    assert not shaded["emission"].any()


@pytest.mark.parametrize("visibility", ["voxel", "svo", "insm"])
def test_every_backend_shades_the_same_brdf(new_stage, visibility):
    """The approximate backends (whose fused kernels sum Lambert's terms) shade the preview surface too: with nothing
    to cast a shadow they give exact's pixels."""
    path = ground(new_stage, "m.usda", CASES["gold"])
    exact = render(path)
    other = render(path, visibility=visibility, voxel_resolution=32)
    assert other["specular"].max() > 0
    assert np.allclose(other["direct"], exact["direct"], rtol=1e-3, atol=1e-4)


def test_white_furnace_never_reflects_more_than_it_receives():
    """F0 = F90 = 1 (a white metal): the directional albedo ∫ f·cos θ_l dω_l over the hemisphere stays ≤ 1 at every
    roughness and view angle, and near 1 for a sharp lobe seen head-on (kernels/brdf integrated numerically
    over half vectors, dω_l = 4 (e·h) dω_h, on a grid dense near the normal where sharp lobes peak)."""
    from usdml.kernels.brdf import ALPHA, CLEARCOAT_ALPHA, EYE, F0, F90, OCCLUSION, WIDTH, brdf_terms

    nx, nphi = 3000, 200
    x = (np.arange(nx) + 0.5) / nx
    t, p = np.meshgrid((math.pi / 2) * x ** 4, (np.arange(nphi) + 0.5) / nphi * 2 * math.pi, indexing="ij")
    h = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    dwh = (np.sin(t) * ((math.pi / 2) * 4 * x ** 3 / nx)[:, None] * (2 * math.pi / nphi)).reshape(-1)
    for roughness in (0.05, 0.2, 0.5, 1.0):
        for view in (0.0, 45.0, 80.0):
            e = np.array([math.sin(math.radians(view)), math.cos(math.radians(view)), 0.0])
            eh = h @ e
            l = 2 * eh[:, None] * h - e
            ok = (eh > 0) & (l[:, 1] > 0)
            rows = np.zeros((ok.sum(), WIDTH), np.float32)
            rows[:, EYE:EYE + 3] = e
            rows[:, F0:F0 + 3] = rows[:, F90:F90 + 3] = 1.0
            rows[:, ALPHA], rows[:, CLEARCOAT_ALPHA], rows[:, OCCLUSION] = roughness ** 2, 1.0, 1.0
            kd, ks = brdf_terms(rows, np.broadcast_to(N, (ok.sum(), 3)), l[ok])
            albedo = (ks[:, 0] * l[ok, 1] * 4 * eh[ok] * dwh[ok]).sum()
            assert albedo <= 1.0 + 2e-3, (roughness, view, albedo)
            if roughness == 0.05 and view == 0.0:
                assert albedo > 0.99, albedo
            assert np.all(kd <= 1e-6)        # F = 1: nothing left for a diffuse lobe


def test_geomsubsets_show_their_materials(new_stage):
    """Every face shows its subset's material; faces in no subset show the prim's own; bindings as
    ComputeBoundMaterial resolves them."""
    stage = new_stage("s.usda", start=1, end=1)
    mesh = UsdGeom.Mesh.Define(stage, "/World/strip")
    mesh.CreatePointsAttr([(x, 0, z) for x in (-3, -1, 1, 3) for z in (-1, 1)])
    mesh.CreateFaceVertexCountsAttr([4, 4, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 3, 2, 2, 3, 5, 4, 4, 5, 7, 6])
    red = material(stage, "/World/Looks/red", diffuseColor=(0.8, 0.1, 0.1))
    green = material(stage, "/World/Looks/green", diffuseColor=(0.1, 0.8, 0.1), metallic=1.0)
    blue = material(stage, "/World/Looks/blue", diffuseColor=(0.1, 0.1, 0.8))
    bind(mesh.GetPrim(), blue)
    for name, faces, mat in (("left", [0], red), ("right", [2], green)):
        subset = UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, faces, "materialBind")
        bind(subset.GetPrim(), mat)
    add_top_camera(stage, 4.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    for subset, mat in (("left", red), ("right", green)):
        prim = stage.GetPrimAtPath(f"/World/strip/{subset}")
        assert UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0].GetPath() == mat.GetPath()
    b = render(stage.GetRootLayer().realPath, width=40)
    row = b["albedo"][20]
    assert np.allclose(row[8], (0.8, 0.1, 0.1), atol=1e-3)      # x = -2: the red subset
    assert np.allclose(row[20], (0.1, 0.1, 0.8), atol=1e-3)     # x = 0: the prim's blue
    assert np.allclose(row[32], (0.0, 0.0, 0.0), atol=1e-3)     # x = 2: green metal, no diffuse
    assert b["specular"][20, 32].sum() > b["specular"][20, 8].sum()   # ... a coloured mirror-like lobe instead


def test_emission_adds_to_color(new_stage):
    path = ground(new_stage, "m.usda", dict(diffuseColor=(0.5, 0.5, 0.5), emissiveColor=(2.0, 0.5, 0.0)))
    b = render(path)
    assert np.allclose(b["emission"][24, 24], (2.0, 0.5, 0.0))
    assert np.allclose(b["color"][..., :3], b["direct"] + b["emission"], atol=2e-3)


def test_what_is_not_rendered_is_said_once_and_listed_by_info(new_stage, tmp_path):
    stage = new_stage("s.usda", start=1, end=3)
    for i in range(3):
        quad = add_quad(stage, f"/World/q{i}", size=1.0, y=0.1 * i)
        bind(quad.GetPrim(), material(stage, "/World/Looks/card", opacity=0.5, opacityThreshold=0.3))
    add_top_camera(stage, 3.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    path = stage.GetRootLayer().realPath
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", path, str(tmp_path / "o.####.exr"),
                        "--imageWidth", "16", "--pixel-samples", "1", "--frames", "1:3"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "opacityThreshold" in line]
    assert said == ["usdml: warning: /World/Looks/card: inputs:opacityThreshold (a cutout) is not rendered: the "
                    "surface and its shadow are opaque"]
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "info", path, "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["unsupportedMaterials"] == {"/World/Looks/card": [
        "inputs:opacityThreshold (a cutout) is not rendered: the surface and its shadow are opaque"]}
    assert info["unsupported"]["material inputs"] == 1
