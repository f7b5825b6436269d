"""The whole UsdPreviewSurface rendered (issue 51): the BRDF against values worked out by hand, energy, bindings
through GeomSubsets, emission and the diffuse/specular/emission AOVs, every visibility backend, and what is not
rendered said once.

The hand reference (``tools/material_accuracy.py``'s ``hand_brdf``) is written from the issue's text of usdImaging's
``previewSurface.glslfx`` in float64, sharing no code with ``kernels/brdf`` nor ``usdml.scene.shading``. The
light's irradiance E comes from a second render of the same view with a white Lambertian ground (no material):
its ``direct`` is E/π per pixel, so the comparison does not depend on the light's units.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade

from conftest import add_quad, add_top_camera

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from material_accuracy import hand_brdf  # noqa: E402  (the BRDF by hand: no usdml code)

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


def image_input(stage, quad, look: str, name: str, file: str, output: str = "rgb", st=((0, 0), (0, 1), (1, 1), (1, 0)),
                **float4_inputs) -> None:
    """The preview surface ``look``'s input ``name`` from a UsdUVTexture of ``file`` (its ``output``) read at the
    quad's ``st`` primvar (per corner), with float4 ``scale``, ``bias`` or ``fallback`` given."""
    pv = UsdGeom.PrimvarsAPI(quad).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    pv.Set([Gf.Vec2f(*x) for x in st])
    tex = UsdShade.Shader.Define(stage, f"{look}/{name}Tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    for key, value in float4_inputs.items():
        tex.CreateInput(key, Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*value))
    reader = UsdShade.Shader.Define(stage, f"{look}/{name}Uv")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    kind = Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float
    tex.CreateOutput(output, kind)
    types = {"normal": Sdf.ValueTypeNames.Normal3f, "diffuseColor": Sdf.ValueTypeNames.Color3f}
    UsdShade.Shader(stage.GetPrimAtPath(f"{look}/pbr")).CreateInput(
        name, types.get(name, Sdf.ValueTypeNames.Float)).ConnectToSource(tex.ConnectableAPI(), output)


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
    r = FrameRenderer(d, UsdmlSettings(**{"pixel_samples": 1, **settings}))
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
        bind(quad.GetPrim(), material(stage, "/World/Looks/veil", opacity=0.5, displacement=0.2))
    add_top_camera(stage, 3.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    path = stage.GetRootLayer().realPath
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", path, str(tmp_path / "o.####.exr"),
                        "--imageWidth", "16", "--pixel-samples", "1", "--frames", "1:3"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    items = ["inputs:displacement (not rendered)"]
    said = [line for line in r.stderr.splitlines() if "/World/Looks/veil" in line]
    assert said == [f"usdml: warning: /World/Looks/veil: {item}" for item in items]
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "info", path, "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["unsupportedMaterials"] == {"/World/Looks/veil": items}
    assert info["unsupported"]["material inputs"] == 1


def checker_card(new_stage, tmp_path, n=8):
    """A 2 × 2 card at height 1 over a 10 × 10 ground, its opacity an n × n checker (the texture's alpha, cut at
    0.5), seen from straight above at height 3 and lit straight down; returns (path, opaque(x, z) by hand)."""
    import OpenImageIO as oiio

    j, i = np.mgrid[0:n, 0:n]                   # j: t texel (upward in st), i: s texel
    opaque = (i + j) % 2 == 0
    rgba = np.zeros((n, n, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[..., 3] = np.where(opaque, 255, 0)[::-1]   # image rows run top down; st (0, 0) is the lower left
    out = oiio.ImageOutput.create(str(tmp_path / "checker.png"))
    out.open(str(tmp_path / "checker.png"), oiio.ImageSpec(n, n, 4, oiio.UINT8))
    out.write_image(rgba)
    out.close()
    stage = new_stage("card.usda", start=1, end=1)
    g = add_quad(stage, "/World/ground", size=10)
    g.CreateDisplayColorPrimvar().Set([(0.5, 0.5, 0.5)])
    card = add_quad(stage, "/World/card", size=2.0, y=1.0)
    mat = material(stage, "/World/Looks/leaf", diffuseColor=(0.2, 0.6, 0.2), opacityThreshold=0.5)
    image_input(stage, card, "/World/Looks/leaf", "opacity", "./checker.png", output="a")
    bind(card.GetPrim(), mat)
    add_top_camera(stage, 3.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()

    def kept(x, z):
        inside = (np.abs(x) < 1) & (np.abs(z) < 1)
        si = np.clip(((x + 1) / 2 * n).astype(int), 0, n - 1)
        tj = np.clip(((z + 1) / 2 * n).astype(int), 0, n - 1)
        return inside & opaque[tj, si]
    return stage.GetRootLayer().realPath, kept


def test_cutout_holes_for_camera_and_shadow_rays(new_stage, tmp_path):
    """A checker cutout (exact): where the card is seen its texel is kept; where the ground is seen through the
    card's plane the texel there is a hole; the ground is in shadow exactly under kept texels (light straight down)."""
    path, kept = checker_card(new_stage, tmp_path)
    b = render(path, aovs=("P", "shadow", "primId"), width=64)
    p = b["P"].reshape(-1, 3).astype(np.float64)
    on_card = np.abs(p[:, 1] - 1.0) < 1e-4
    on_ground = np.abs(p[:, 1]) < 1e-4
    assert on_card.sum() > 300 and on_ground.sum() > 300
    q = CAMERA + (p - CAMERA) * (2.0 / 3.0)     # where a ground pixel's ray crossed the card's plane
    camera_ok = np.concatenate([kept(p[on_card, 0], p[on_card, 2]), ~kept(q[on_ground, 0], q[on_ground, 2])])
    assert camera_ok.mean() >= 0.97, camera_ok.mean()
    crossed = on_ground & (np.abs(q[:, 0]) < 1) & (np.abs(q[:, 2]) < 1)
    assert crossed.sum() > 100        # holes were seen through
    shadow = b["shadow"].reshape(-1)[on_ground]
    shadow_ok = (shadow > 0.5) == kept(p[on_ground, 0], p[on_ground, 2])
    assert shadow_ok.mean() >= 0.97, shadow_ok.mean()
    assert (shadow > 0.5).sum() > 50 and (shadow < 0.5).sum() > 50


@pytest.mark.parametrize("visibility", ["voxel", "svo", "insm"])
def test_approximate_backends_shadow_through_the_kept_texels(new_stage, tmp_path, visibility):
    """The approximate backends build from the triangles a cutout keeps (usdml.scene.cutout): the ground's shadow
    answers under the checker card agree with the card by hand as exact's do (the issue's target: 97 %)."""
    path, kept = checker_card(new_stage, tmp_path)
    b = render(path, aovs=("P", "shadow"), width=64, visibility=visibility, voxel_resolution=128)
    p = b["P"].reshape(-1, 3).astype(np.float64)
    on_ground = np.abs(p[:, 1]) < 1e-4
    shadow = b["shadow"].reshape(-1)[on_ground]
    agree = ((shadow > 0.5) == kept(p[on_ground, 0], p[on_ground, 2])).mean()
    assert agree >= 0.97, agree


def test_partial_opacity_covers_its_share_of_pixel_samples(new_stage):
    """opacity 0.25 without a threshold: a quarter of the camera rays stop on the veil and three quarters of the
    light reaches the ground under it (stochastic transparency, averaged over 16 pixel samples), against two
    opaque renders: the veil alone (opacity 1) and the ground alone."""
    def scene(name, opacity):
        stage = new_stage(name, start=1, end=1)
        g = add_quad(stage, "/World/ground", size=10)
        g.CreateDisplayColorPrimvar().Set([(0.5, 0.5, 0.5)])
        if opacity is not None:
            veil = add_quad(stage, "/World/veil", size=4.0, y=1.0)
            bind(veil.GetPrim(), material(stage, "/World/Looks/veil", diffuseColor=(0.9, 0.2, 0.2), opacity=opacity))
        add_top_camera(stage, 3.0)
        sun = UsdLux.DistantLight.Define(stage, "/World/sun")
        sun.AddRotateXOp().Set(-90)
        stage.Save()
        return stage.GetRootLayer().realPath

    def mean_colour(path, samples=16):
        b = render(path, aovs=("color",), width=32, pixel_samples=samples)
        return b["color"][10:22, 10:22, :3].reshape(-1, 3).astype(np.float64).mean(0)

    veil = mean_colour(scene("veil.usda", 1.0), 1)
    ground = mean_colour(scene("ground.usda", None), 1)
    got = mean_colour(scene("partial.usda", 0.25))
    want = 0.25 * veil + 0.75 * 0.75 * ground
    assert np.allclose(got, want, rtol=0.05), (got, want)
    assert np.array_equal(got, mean_colour(scene("again.usda", 0.25)))      # deterministic


@pytest.mark.parametrize("roughness", [0.05, 0.3, 0.7])
def test_a_white_dome_on_a_white_metal_reflects_the_brdf_albedo(new_stage, roughness):
    """A constant dome of radiance 1 over a ground of white metal (F0 = F90 = 1, no diffuse lobe): each pixel's
    radiance is the BRDF's directional albedo ∫ f·cos θ dω, here integrated from the hand formula by quadrature
    (the dome's specular is sampled from the GGX lobe, not from its distant lights)."""
    stage = new_stage("dome.usda", start=1, end=1)
    quad = add_quad(stage, "/World/ground", size=10)
    bind(quad.GetPrim(), material(stage, "/World/Looks/m", diffuseColor=(1.0, 1.0, 1.0), metallic=1.0,
                                  roughness=roughness))
    add_top_camera(stage, CAMERA[1])
    UsdLux.DomeLight.Define(stage, "/World/dome").CreateIntensityAttr(1.0)
    stage.Save()
    b = render(stage.GetRootLayer().realPath, aovs=("direct", "P", "specular"), width=48)
    got = b["direct"][21:27, 21:27, 0].astype(np.float64).ravel()
    p = b["P"][21:27, 21:27].reshape(-1, 3).astype(np.float64)
    theta = (np.arange(300) + 0.5) / 300 * (math.pi / 2)
    phi = (np.arange(300) + 0.5) / 300 * 2 * math.pi
    t, f = np.meshgrid(theta, phi, indexing="ij")
    l = np.stack([np.sin(t) * np.cos(f), np.cos(t), np.sin(t) * np.sin(f)], -1).reshape(-1, 3)
    dw = (np.sin(t) * (math.pi / 2 / 300) * (2 * math.pi / 300)).reshape(-1)
    want = []
    for q in p:
        e = (CAMERA - q) / np.linalg.norm(CAMERA - q)
        fr = hand_brdf(np.broadcast_to(N, l.shape), np.broadcast_to(e, l.shape), l, diffuseColor=(1, 1, 1),
                       metallic=1.0, roughness=roughness)[:, 0]
        want.append((fr * l[:, 1] * dw).sum())
    want = np.array(want)
    if roughness < 0.1:      # the quadrature cannot resolve so sharp a lobe: its albedo is 1 within 0.5 %
        want = np.ones_like(want)
    assert abs(got.mean() / want.mean() - 1) < 0.02, (got.mean(), want.mean())
    assert np.allclose(b["specular"], b["direct"], atol=1e-4)      # all of it specular


def test_spheres_of_every_family_match_the_brdf_and_a_wrong_roughness_shows(monkeypatch):
    """tools/material_accuracy.py on one seeded stage (spheres of every material family, a point and a distant
    light, exact): within the issue's targets; the same measure with the reference's roughness 10 % off fails them,
    so the measure can fail."""
    import material_accuracy as ma

    row = ma.measure(0, "exact", 40)
    assert row["pixels"] > 100 and row["median"] < 0.01 and row["p95"] < 0.05, row
    right = ma.hand_brdf
    monkeypatch.setattr(ma, "hand_brdf", lambda n, e, l, **kw: right(n, e, l, **{**kw, "roughness": kw.get(
        "roughness", 0.5) * 1.1}))
    wrong = ma.measure(0, "exact", 40)
    assert wrong["p95"] > 0.05, wrong


@pytest.mark.parametrize("roughness, median, mean", [(0.4, 0.05, 0.02), (0.7, 0.12, 0.06)])
def test_a_rough_metal_is_near_mitsuba_s_roughconductor(new_stage, roughness, median, mean):
    """Mitsuba 3 (``scalar_rgb``, its own GGX ``roughconductor`` with F = specular_reflectance, ``material`` none)
    against usdml's metal (F0 = F90 = the same colour) under one point light, as the ratio to a white diffuse plane
    in each renderer (no shared light units). The models differ in masking only: Mitsuba's exact Smith G against
    the preview surface's Smith–Schlick (k = α/2), which loses a few % more light as roughness grows (G1 ≈ 0.94
    against 0.97 at α = 0.49, 37° from the normal): the expected gap is about 1 % of the mean at roughness 0.4 and
    4 % at 0.7, per pixel up to 3 % and 8 % at the median (measured when this landed)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    width, f0 = 40, (0.95, 0.64, 0.54)
    t = mi.ScalarTransform4f

    def mitsuba(bsdf):
        return np.array(mi.render(mi.load_dict({
            "type": "scene", "integrator": {"type": "direct"},
            "sensor": {"type": "perspective", "fov": 90, "fov_axis": "x",
                       "to_world": t().look_at(origin=list(CAMERA), target=[0, 0, 0], up=[0, 0, -1]),
                       "film": {"type": "hdrfilm", "width": width, "height": width, "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 128}},
            "light": {"type": "point", "position": list(LIGHT), "intensity": {"type": "rgb", "value": [10, 10, 10]}},
            "plane": {"type": "rectangle", "to_world": t().rotate([1, 0, 0], -90).scale(5), "bsdf": bsdf}})))[..., 0]

    mw = mitsuba({"type": "diffuse", "reflectance": {"type": "rgb", "value": [1, 1, 1]}})
    mm = mitsuba({"type": "roughconductor", "distribution": "ggx", "alpha": roughness ** 2, "material": "none",
                  "specular_reflectance": {"type": "rgb", "value": list(f0)}})
    uw = render(ground(new_stage, "w.usda", None), aovs=("direct",), width=width, pixel_samples=16)["direct"][..., 0]
    um = render(ground(new_stage, "m.usda", dict(diffuseColor=f0, metallic=1.0, roughness=roughness)),
                aovs=("direct",), width=width, pixel_samples=16)["direct"][..., 0]
    ok = mw > 0.05 * mw.max()
    rm, ru = mm[ok] / mw[ok], um[ok] / uw[ok]
    rel = np.abs(ru - rm) / np.maximum(rm, 1e-2 * rm.max())
    assert np.median(rel) < median, np.median(rel)
    assert abs(um[ok].sum() / uw[ok].sum() / (mm[ok].sum() / mw[ok].sum()) - 1) < mean
    assert np.unravel_index(np.argmax(um), um.shape) == np.unravel_index(np.argmax(mm), mm.shape)   # the highlight


@pytest.mark.parametrize("roughness, view", [(0.3, 0.0), (0.3, 60.0), (0.7, 30.0)])
def test_indirect_albedo_is_the_brdf_s_directional_albedo(roughness, view):
    """What a surface bounces indirect light with (usdml.lighting.specular_albedo): for a white metal, the hand
    BRDF's directional albedo by quadrature; for a Lambertian row, its albedo unchanged."""
    from usdml.kernels.brdf import ALPHA, EYE, F0, F90, OCCLUSION, WIDTH
    from usdml.lighting.specular_albedo import indirect_albedo
    from usdml.scene.shading import lambert_rows

    e = np.array([[math.sin(math.radians(view)), math.cos(math.radians(view)), 0.0]])
    row = np.zeros((1, WIDTH), np.float32)
    row[:, EYE:EYE + 3] = e
    row[:, F0:F0 + 3] = row[:, F90:F90 + 3] = 1.0
    row[:, ALPHA], row[:, OCCLUSION] = roughness ** 2, 1.0
    got = indirect_albedo(np.zeros((1, 3)), row, N[None])[0, 0]
    theta = (np.arange(400) + 0.5) / 400 * (math.pi / 2)
    phi = (np.arange(400) + 0.5) / 400 * 2 * math.pi
    t, f = np.meshgrid(theta, phi, indexing="ij")
    l = np.stack([np.sin(t) * np.cos(f), np.cos(t), np.sin(t) * np.sin(f)], -1).reshape(-1, 3)
    dw = (np.sin(t) * (math.pi / 2 / 400) * (2 * math.pi / 400)).reshape(-1)
    fr = hand_brdf(np.broadcast_to(N, l.shape), np.broadcast_to(e[0], l.shape), l, diffuseColor=(1, 1, 1),
                   metallic=1.0, roughness=roughness)[:, 0]
    assert abs(got / (fr * l[:, 1] * dw).sum() - 1) < 0.02
    flat = lambert_rows(1, e)
    assert np.allclose(indirect_albedo(np.array([[0.3, 0.5, 0.7]]), flat, N[None]), (0.3, 0.5, 0.7))


def test_a_udim_set_reads_the_tile_under_each_st(new_stage, tmp_path):
    """``<UDIM>`` in a file name: tile 1001 holds st in [0, 1)², tile 1002 [1, 2) × [0, 1); the layer's folder
    anchors the pattern (usd-core resolves none); st on no tile gives the fallback."""
    import OpenImageIO as oiio

    (tmp_path / "tex").mkdir()
    for tile, colour in ((1001, (255, 0, 0)), (1002, (0, 255, 0))):
        out = oiio.ImageOutput.create(str(tmp_path / f"tex/wood.{tile}.png"))
        out.open(str(tmp_path / f"tex/wood.{tile}.png"), oiio.ImageSpec(4, 4, 3, oiio.UINT8))
        out.write_image(np.broadcast_to(np.array(colour, np.uint8), (4, 4, 3)).copy())
        out.close()
    stage = new_stage("s.usda", start=1, end=1)
    quad = add_quad(stage, "/World/q", size=2.0)
    mat = material(stage, "/World/Looks/wood")
    image_input(stage, quad, "/World/Looks/wood", "diffuseColor", "./tex/wood.<UDIM>.png",      # s 0..3 along +X
                st=((0, 0), (0, 1), (3, 1), (3, 0)), fallback=(0, 0, 1, 1))
    bind(quad.GetPrim(), mat)
    add_top_camera(stage, 1.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    albedo = render(stage.GetRootLayer().realPath, aovs=("albedo",), width=30)["albedo"][15]
    assert np.allclose(albedo[3], (1, 0, 0), atol=1e-3)        # s ≈ 0.3: tile 1001
    assert np.allclose(albedo[15], (0, 1, 0), atol=1e-3)       # s ≈ 1.5: tile 1002
    assert np.allclose(albedo[26], (0, 0, 1), atol=1e-3)       # s ≈ 2.7: no tile 1003, the fallback


def test_normal_map_tilts_the_shading_normal_in_tangent_space(new_stage, tmp_path):
    """A constant normal map (30° toward +s, the spec's scale 2 / bias −1 encoding, raw float texels) on a quad whose
    s runs along +X and t along +Z: the normal AOV is sin 30°·X + cos 30°·Y (the tangent frame by hand)."""
    import OpenImageIO as oiio

    tilt = math.radians(30.0)
    texel = (np.array([math.sin(tilt), 0.0, math.cos(tilt)]) + 1.0) / 2.0
    out = oiio.ImageOutput.create(str(tmp_path / "n.exr"))
    out.open(str(tmp_path / "n.exr"), oiio.ImageSpec(4, 4, 3, oiio.FLOAT))
    out.write_image(np.broadcast_to(texel.astype(np.float32), (4, 4, 3)).copy())
    out.close()
    stage = new_stage("s.usda", start=1, end=1)
    quad = add_quad(stage, "/World/q", size=2.0)
    mat = material(stage, "/World/Looks/bumpy", diffuseColor=(0.5, 0.5, 0.5))
    image_input(stage, quad, "/World/Looks/bumpy", "normal", "./n.exr", scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0))
    bind(quad.GetPrim(), mat)
    add_top_camera(stage, 1.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    b = render(stage.GetRootLayer().realPath, aovs=("normal", "direct"), width=16)
    want = np.array([math.sin(tilt), math.cos(tilt), 0.0])
    assert np.allclose(b["normal"][2:14, 2:14].reshape(-1, 3), want, atol=1e-4)


def test_bad_inputs_are_a_line_each_and_the_frame_renders(new_stage, tmp_path):
    """An input of the wrong type, a shader with no id, a connection cycle through UsdTransform2d: one warning line
    each, naming the material, and the frame renders with the defaults."""
    stage = new_stage("s.usda", start=1, end=1)
    looks = []
    for i, name in enumerate(("typed", "noid", "cycle")):
        quad = add_quad(stage, f"/World/q{i}", size=1.0, y=0.1 * i)
        look = f"/World/Looks/{name}"
        bind(quad.GetPrim(), material(stage, look))
        looks.append((quad, look))
    pbr = lambda look: UsdShade.Shader(stage.GetPrimAtPath(f"{look}/pbr"))  # noqa: E731
    pbr("/World/Looks/typed").CreateInput("roughness", Sdf.ValueTypeNames.String).Set("rough")
    anonymous = UsdShade.Shader.Define(stage, "/World/Looks/noid/mystery")
    anonymous.CreateOutput("out", Sdf.ValueTypeNames.Color3f)
    pbr("/World/Looks/noid").CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        anonymous.ConnectableAPI(), "out")
    image_input(stage, looks[2][0], "/World/Looks/cycle", "diffuseColor", "./none.png")
    spin = UsdShade.Shader.Define(stage, "/World/Looks/cycle/spin")
    spin.CreateIdAttr("UsdTransform2d")
    spin.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    spin.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(spin.ConnectableAPI(), "result")
    UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/cycle/diffuseColorTex")).GetInput("st").ConnectToSource(
        spin.ConnectableAPI(), "result")
    add_top_camera(stage, 3.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-90)
    stage.Save()
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", stage.GetRootLayer().realPath,
                        str(tmp_path / "o.exr"), "--imageWidth", "16", "--pixel-samples", "1"],
                       capture_output=True, text=True)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.splitlines()
    for look, words in (("typed", "inputs:roughness = 'rough' is not a number"),
                        ("noid", "a shader with no info:id"), ("cycle", "a connection cycle through")):
        said = [line for line in lines if line.startswith(f"usdml: warning: /World/Looks/{look}: ") and words in line]
        assert len(said) == 1, (look, lines)
