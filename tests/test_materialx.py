"""MaterialX's standard_surface and open_pbr_surface mapped onto the preview surface (usdml.stage.materialx): inline
``ND_`` nodes, referenced ``.mtlx`` documents, and what the resolver and a frame make of them."""

from __future__ import annotations

import math

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

from conftest import add_quad
from usdml.stage.materials import MaterialResolver
from usdml.stage.materialx import read_materialx, read_materialx_path
from usdml.stage.network import Image, Primvar

pytest.importorskip("MaterialX")

T0 = Usd.TimeCode.Default()


class Log(list):
    def __call__(self, message: str) -> None:
        self.append(message)


def ior_for(f0: float) -> float:
    """The ior whose normal-incidence reflectance ((n − 1)/(n + 1))² is ``f0``."""
    r = math.sqrt(f0)
    return (1 + r) / (1 - r)


def write_exr(path, pixels: np.ndarray) -> None:
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, oiio.FLOAT))
    assert out.write_image(np.ascontiguousarray(pixels, np.float32))
    out.close()


def mx_shader(stage, path: str, sid: str, **inputs) -> UsdShade.Shader:
    shader = UsdShade.Shader.Define(stage, path)
    shader.CreateIdAttr(sid)
    for name, (type_name, value) in inputs.items():
        shader.CreateInput(name, type_name).Set(value)
    return shader


def inline_standard_surface(stage, root: str = "/World/Looks/ss", image: str | None = None) -> UsdShade.Material:
    """A material with MaterialX nodes in the file: constants, and an image (with normal map) when given."""
    f, c3 = Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Color3f
    material = UsdShade.Material.Define(stage, root)
    ss = mx_shader(stage, f"{root}/surface", "ND_standard_surface_surfaceshader",
                   base=(f, 0.5), base_color=(c3, Gf.Vec3f(0.8, 0.4, 0.2)), metalness=(f, 0.25),
                   specular=(f, 0.5), specular_color=(c3, Gf.Vec3f(1.0, 0.5, 0.0)), specular_roughness=(f, 0.3),
                   specular_IOR=(f, 2.0), coat=(f, 0.6), coat_roughness=(f, 0.05), coat_IOR=(f, 1.4),
                   emission=(f, 2.0), emission_color=(c3, Gf.Vec3f(0.1, 0.2, 0.3)),
                   opacity=(c3, Gf.Vec3f(1.0, 0.5, 0.9)), sheen=(f, 0.7), transmission_color=(c3, Gf.Vec3f(0, 1, 0)))
    if image is not None:
        uv = mx_shader(stage, f"{root}/uv", "ND_geompropvalue_vector2",
                       geomprop=(Sdf.ValueTypeNames.String, "uvs"))
        uv.CreateOutput("out", Sdf.ValueTypeNames.Float2)
        img = mx_shader(stage, f"{root}/img", "ND_image_color3",
                        file=(Sdf.ValueTypeNames.Asset, image), default=(c3, Gf.Vec3f(0.3, 0.3, 0.3)),
                        uaddressmode=(Sdf.ValueTypeNames.String, "clamp"),
                        vaddressmode=(Sdf.ValueTypeNames.String, "mirror"))
        img.CreateInput("texcoord", Sdf.ValueTypeNames.Float2).ConnectToSource(uv.ConnectableAPI(), "out")
        img.CreateOutput("out", c3)
        ss.GetInput("base_color").ConnectToSource(img.ConnectableAPI(), "out")
        nimg = mx_shader(stage, f"{root}/nimg", "ND_image_vector3", file=(Sdf.ValueTypeNames.Asset, image))
        nimg.CreateOutput("out", Sdf.ValueTypeNames.Vector3f)
        nmap = mx_shader(stage, f"{root}/nmap", "ND_normalmap_float", scale=(f, 0.5))
        nmap.CreateInput("in", Sdf.ValueTypeNames.Vector3f).ConnectToSource(nimg.ConnectableAPI(), "out")
        nmap.CreateOutput("out", Sdf.ValueTypeNames.Vector3f)
        ss.CreateInput("normal", Sdf.ValueTypeNames.Vector3f).ConnectToSource(nmap.ConnectableAPI(), "out")
    material.CreateSurfaceOutput("mtlx").ConnectToSource(ss.ConnectableAPI(), "out")
    return material


def test_inline_standard_surface_constants(new_stage):
    stage = new_stage()
    net = read_materialx(inline_standard_surface(stage), T0)
    assert net.origin.startswith("MaterialX ND_standard_surface_surfaceshader")
    i = net.inputs
    # diffuseColor = base · base_color = 0.5 · (0.8, 0.4, 0.2)
    assert np.allclose(i["diffuseColor"].value, (0.4, 0.2, 0.1))
    assert np.allclose(i["metallic"].value, 0.25) and np.allclose(i["roughness"].value, 0.3)
    # F0 = specular · mean(specular_color) · ((2 − 1)/(2 + 1))² = 0.5 · 0.5 · 1/9 = 1/36
    # -> ior (1 + 1/6)/(1 − 1/6) = 1.4
    assert np.allclose(i["ior"].value, 1.4) and np.isclose(ior_for(1 / 36), 1.4)
    assert np.allclose(i["clearcoat"].value, 0.6) and np.allclose(i["clearcoatRoughness"].value, 0.05)
    # emissiveColor = emission · emission_color; opacity = mean(1, 0.5, 0.9) = 0.8
    assert np.allclose(i["emissiveColor"].value, (0.2, 0.4, 0.6)) and np.allclose(i["opacity"].value, 0.8)
    assert "normal" not in i
    # coat_IOR 1.4 equals the folded ior: nothing said; sheen is; transmission_color with transmission 0 is not
    assert net.unsupported == ["sheen is not rendered (sheen 0.7)"]


def test_unauthored_inputs_take_standard_surface_defaults(new_stage):
    stage = new_stage()
    material = UsdShade.Material.Define(stage, "/M")
    ss = mx_shader(stage, "/M/ss", "ND_standard_surface_surfaceshader")
    material.CreateSurfaceOutput("mtlx").ConnectToSource(ss.ConnectableAPI(), "out")
    i = read_materialx(material, T0).inputs
    # standard_surface: base 1, base_color 0.8, specular_roughness 0.2, specular 1 · white · F0(1.5) = 0.04 -> 1.5
    assert np.allclose(i["diffuseColor"].value, 0.8) and np.allclose(i["roughness"].value, 0.2)
    assert np.allclose(i["ior"].value, 1.5) and np.allclose(i["clearcoatRoughness"].value, 0.1)
    assert np.allclose(i["emissiveColor"].value, 0.0) and np.allclose(i["opacity"].value, 1.0)


def test_inline_image_and_normal_map(new_stage, tmp_path):
    write_exr(tmp_path / "t.exr", np.full((2, 2, 3), 0.5, np.float32))
    stage = new_stage()
    net = read_materialx(inline_standard_surface(stage, image="t.exr"), T0)
    base = net.inputs["diffuseColor"]
    assert isinstance(base, Image) and base.file == str(tmp_path / "t.exr") and base.authored == "t.exr"
    assert base.st == Primvar("uvs", 2, (0.0, 0.0), "/World/Looks/ss/uv")
    assert (base.wrap_s, base.wrap_t, base.color_space, base.output) == ("clamp", "mirror", "auto", "rgb")
    # base 0.5 folds into the image's scale; default (0.3, 0.3, 0.3) is the fallback
    assert np.allclose(base.scale, (0.5, 0.5, 0.5, 1.0)) and np.allclose(base.fallback, (0.3, 0.3, 0.3, 1.0))
    normal = net.inputs["normal"]
    # normalmap scale 0.5: n = (2·in − 1)·(0.5, 0.5, 1) -> scale (1, 1, 2, 1), bias (−0.5, −0.5, −1, 0);
    # a vector image is data: raw
    assert isinstance(normal, Image) and normal.color_space == "raw"
    assert np.allclose(normal.scale, (1, 1, 2, 1)) and np.allclose(normal.bias, (-0.5, -0.5, -1, 0))
    assert normal.st == Primvar("st", 2, (0.0, 0.0), "/World/Looks/ss/nimg")


def test_open_pbr_inline(new_stage):
    stage = new_stage()
    f, c3 = Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Color3f
    material = UsdShade.Material.Define(stage, "/M")
    ss = mx_shader(stage, "/M/pbr", "ND_open_pbr_surface_surfaceshader",
                   base_weight=(f, 0.5), base_color=(c3, Gf.Vec3f(0.2, 0.4, 0.6)), base_metalness=(f, 1.0),
                   specular_weight=(f, 0.0), emission_luminance=(f, 10.0), geometry_opacity=(f, 0.25),
                   fuzz_weight=(f, 0.0), fuzz_color=(c3, Gf.Vec3f(1, 0, 0)))
    material.CreateSurfaceOutput("mtlx").ConnectToSource(ss.ConnectableAPI(), "out")
    net = read_materialx(material, T0)
    i = net.inputs
    assert np.allclose(i["diffuseColor"].value, (0.1, 0.2, 0.3)) and np.allclose(i["metallic"].value, 1.0)
    # specular_weight 0: no reflection at normal incidence -> ior 1; open_pbr's specular_roughness default 0.3
    assert np.allclose(i["ior"].value, 1.0) and np.allclose(i["roughness"].value, 0.3)
    assert np.allclose(i["emissiveColor"].value, 10.0) and np.allclose(i["opacity"].value, 0.25)
    assert net.unsupported == []        # fuzz_color under fuzz_weight 0 changes nothing


MTLX = """<?xml version="1.0"?>
<materialx version="1.39" colorspace="lin_rec709">
  <nodegraph name="NG_red">
    <tiledimage name="tex" type="color3">
      <input name="file" type="filename" value="maps/red.exr" />
      <input name="uvtiling" type="vector2" value="2, 3" />
      <input name="uvoffset" type="vector2" value="0.5, 0.25" />
    </tiledimage>
    <output name="out" type="color3" nodename="tex" />
  </nodegraph>
  <standard_surface name="SR_red" type="surfaceshader">
    <input name="base_color" type="color3" nodegraph="NG_red" output="out" />
    <input name="specular_roughness" type="float" value="0.4" />
    <input name="metalness" type="float" value="0.1" />
    <input name="subsurface" type="float" value="0.5" />
    <input name="subsurface_color" type="color3" value="1, 0, 0" />
  </standard_surface>
  <surfacematerial name="red" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_red" />
  </surfacematerial>
  <open_pbr_surface name="SR_blue" type="surfaceshader">
    <input name="base_color" type="color3" value="0.1, 0.2, 0.9" />
    <input name="subsurface_weight" type="float" value="0.5" />
    <input name="subsurface_color" type="color3" value="0.3, 0.2, 0.1" />
  </open_pbr_surface>
  <surfacematerial name="blue" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_blue" />
  </surfacematerial>
</materialx>
"""


def mtlx_stage(new_stage, tmp_path, text: str = MTLX):
    """A stage whose /World/Looks scope references a .mtlx document (as the Standard Shader Ball does), a quad
    bound to its material ``blue`` (a prim usd-core leaves missing) and one to a Material referencing ``red``."""
    (tmp_path / "looks.mtlx").write_text(text)
    (tmp_path / "maps").mkdir(exist_ok=True)
    write_exr(tmp_path / "maps" / "red.exr", np.array([[[0.9, 0.1, 0.1]]], np.float32))
    stage = new_stage()
    looks = UsdGeom.Scope.Define(stage, "/World/Looks").GetPrim()
    looks.GetReferences().AddReference("./looks.mtlx", "/MaterialX/Materials")
    red = UsdShade.Material.Define(stage, "/World/Red")
    red.GetPrim().GetReferences().AddReference("./looks.mtlx", "/MaterialX/Materials/red")
    a, b = add_quad(stage, "/World/a").GetPrim(), add_quad(stage, "/World/b", y=1).GetPrim()
    UsdShade.MaterialBindingAPI.Apply(a).GetDirectBindingRel().SetTargets([Sdf.Path("/World/Looks/blue")])
    UsdShade.MaterialBindingAPI.Apply(b).Bind(red)
    for prim in (a, b):
        UsdGeom.PrimvarsAPI(prim).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                UsdGeom.Tokens.vertex).Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    stage.Save()
    return stage


def test_referenced_mtlx_document(new_stage, tmp_path):
    stage = mtlx_stage(new_stage, tmp_path)
    assert not stage.GetPrimAtPath("/World/Looks/blue")          # usd-core cannot compose .mtlx
    log = Log()
    blue = read_materialx_path(stage, "/World/Looks/blue", T0, log)
    assert blue.origin == "MaterialX ND_open_pbr_surface_surfaceshader (looks.mtlx:SR_blue)" and not log
    # subsurface_weight 0.5 mixes subsurface_color into the diffuse: 0.5·(0.1, 0.2, 0.9) + 0.5·(0.3, 0.2, 0.1)
    assert np.allclose(blue.inputs["diffuseColor"].value, (0.2, 0.2, 0.5))
    assert blue.unsupported == ["subsurface is not rendered (subsurface_weight 0.5, subsurface_color (0.3, 0.2, 0.1)): "
                                "its colour is mixed into the diffuse"]
    red = read_materialx(UsdShade.Material(stage.GetPrimAtPath("/World/Red")), T0, log)
    assert not log and np.allclose(red.inputs["roughness"].value, 0.4)
    assert np.allclose(red.inputs["metallic"].value, 0.1)
    image = red.inputs["diffuseColor"]
    assert isinstance(image, Image) and image.file == str(tmp_path / "maps" / "red.exr")
    # the document's colorspace lin_rec709: raw; tiledimage: st·(2, 3) − (0.5, 0.25), repeating
    assert (image.color_space, image.wrap_s, image.wrap_t) == ("raw", "repeat", "repeat")
    assert len(image.transforms) == 1 and image.transforms[0].scale == (2.0, 3.0)
    assert image.transforms[0].translation == (-0.5, -0.25)


def test_resolver_renders_missing_material_prims_from_their_mtlx(new_stage, tmp_path):
    from test_materials import albedo

    stage = mtlx_stage(new_stage, tmp_path)
    log = Log()
    r = MaterialResolver(log)
    a, b = stage.GetPrimAtPath("/World/a"), stage.GetPrimAtPath("/World/b")
    assert r.bound_material(a) is None and r.bound_path(a) == "/World/Looks/blue"
    assert np.allclose(albedo(r, a), (0.2, 0.2, 0.5))
    # red: the texel 0.9, 0.1, 0.1 (raw) · (1 − metalness 0.1); its subsurface mixes only into a constant colour
    assert np.allclose(albedo(r, b), np.array([0.9, 0.1, 0.1]) * 0.9, atol=1e-6)
    assert sorted(log) == [
        "/World/Looks/blue: subsurface is not rendered (subsurface_weight 0.5, subsurface_color (0.3, 0.2, 0.1)): "
        "its colour is mixed into the diffuse",
        "/World/Red: subsurface is not rendered (subsurface 0.5, subsurface_color (1, 0, 0)): its colour is mixed "
        "into the diffuse"]


def test_preview_surface_wins_over_materialx(new_stage, tmp_path):
    """Storm's choice: a material with both surfaces renders its UsdPreviewSurface."""
    from test_materials import albedo

    stage = new_stage()
    quad = add_quad(stage, "/World/q").GetPrim()
    material = inline_standard_surface(stage, "/World/Looks/both")
    preview = UsdShade.Shader.Define(stage, "/World/Looks/both/preview")
    preview.CreateIdAttr("UsdPreviewSurface")
    preview.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.3, 0.6, 0.9))
    material.CreateSurfaceOutput().ConnectToSource(preview.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(quad).Bind(material)
    log = Log()
    r = MaterialResolver(log)
    assert np.allclose(albedo(r, quad), (0.3, 0.6, 0.9)) and not log
    assert r.network(material, T0).origin == "UsdPreviewSurface"


def _frame_stage(tmp_path, mtlx_text: str):
    stage = Usd.Stage.CreateNew(str(tmp_path / "f.usda"))
    (tmp_path / "look.mtlx").write_text(mtlx_text)
    mesh = UsdGeom.Mesh.Define(stage, "/World/quad")
    mesh.CreatePointsAttr([(-1, 0, -1), (-1, 0, 1), (1, 0, 1), (1, 0, -1)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateDisplayColorPrimvar().Set([(0, 0, 1)])
    looks = UsdGeom.Scope.Define(stage, "/World/Looks").GetPrim()
    looks.GetReferences().AddReference("./look.mtlx", "/MaterialX/Materials")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).GetDirectBindingRel().SetTargets(
        [Sdf.Path("/World/Looks/blue")])
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.AddTranslateOp().Set((0, 5, 0))
    cam.AddRotateXOp().Set(-90)
    stage.Save()
    return str(tmp_path / "f.usda")


def _render_albedo(path: str):
    """The albedo AOV of a 16x16 frame and every warning the stage and the frame gave."""
    from usdml.errors import Warnings
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    warn = Warnings()
    d = StageDelegate(path, warn=warn)
    albedo = FrameRenderer(d, UsdmlSettings()).render(0, 16, 16, {"albedo"}).buffers["albedo"]
    return albedo, warn.messages


def test_frame_renders_a_referenced_mtlx_material(tmp_path):
    albedo, messages = _render_albedo(_frame_stage(tmp_path, MTLX))
    assert np.allclose(albedo[8, 8], (0.2, 0.2, 0.5), atol=1e-3)      # not displayColor (0, 0, 1)
    assert [m for m in messages if "composition error" not in m] == [
        "/World/Looks/blue: subsurface is not rendered (subsurface_weight 0.5, subsurface_color (0.3, 0.2, 0.1)): "
        "its colour is mixed into the diffuse"]


def test_mtlx_that_does_not_parse_warns_once_and_the_frame_renders(tmp_path):
    albedo, messages = _render_albedo(_frame_stage(tmp_path, "<materialx version='1.39'><standard_surface"))
    assert np.allclose(albedo[8, 8], (0, 0, 1))                        # displayColor
    ours = [m for m in messages if "composition error" not in m]
    assert len(ours) == 1 and ours[0].startswith("/World/Looks/blue: look.mtlx does not parse as MaterialX (")
    assert ours[0].endswith("; using displayColor")


def test_unsupported_nodes_and_missing_names_are_said_not_raised(new_stage, tmp_path):
    text = MTLX.replace('<input name="base_color" type="color3" value="0.1, 0.2, 0.9" />',
                        '<input name="base_color" type="color3" nodename="noise" />').replace(
        '<open_pbr_surface name="SR_blue"',
        '<noise3d name="noise" type="color3" />\n  <open_pbr_surface name="SR_blue"')
    stage = mtlx_stage(new_stage, tmp_path, text)
    log = Log()
    blue = read_materialx_path(stage, "/World/Looks/blue", T0, log)
    assert not log and np.allclose(blue.inputs["diffuseColor"].value, 0.5 * 0.8 + 0.5 * np.array([0.3, 0.2, 0.1]))
    assert blue.unsupported[0] == ("looks.mtlx:SR_blue.base_color comes from looks.mtlx:noise (ND_noise3d_color3), "
                                   "which usdml does not evaluate: using the default")
    assert read_materialx_path(stage, "/World/Looks/green", T0, log) is None
    assert log == ["/World/Looks/green: no surfacematerial green in looks.mtlx; using displayColor"]


def test_standard_shader_ball_binds_its_mtlx_plastic(assets, tmp_path):
    """End to end on the usd-wg Standard Shader Ball: the ball bound to the referenced plastic_openpbr.mtlx renders
    its base colour, not its displayColor (usd-core cannot compose the .mtlx)."""
    path = assets / "usd-wg" / "StandardShaderBall" / "standard_shader_ball_scene.usda"
    if not path.exists():
        pytest.skip(f"{path} not found")
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    stage = Usd.Stage.Open(str(path))
    ball = stage.GetPrimAtPath("/standard_shader_ball_scene")
    ball.GetVariantSet("example_material").SetVariantSelection("mtlx_plastic")
    d = StageDelegate(stage)
    snap = d.snapshot(3)
    surface = [m for m in snap.meshes if m.path.endswith("/material_surface")]
    assert surface and np.allclose(surface[0].albedo, (0.209884, 0.562091, 0.766), atol=1e-5)
    albedo = FrameRenderer(d, UsdmlSettings()).render(3, 48, 48, {"albedo"}).buffers["albedo"]
    pixels = albedo.reshape(-1, 3)
    plastic = np.isclose(pixels, (0.209884, 0.562091, 0.766), atol=2e-3).all(axis=1)
    display = np.isclose(pixels, (0.325, 0.7075, 1.0), atol=2e-3).all(axis=1)
    assert plastic.sum() > 20 and not display.any()
