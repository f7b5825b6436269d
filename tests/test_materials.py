"""Bound UsdPreviewSurface diffuse colour -> per-corner albedo (usdml.stage.materials)."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils

from conftest import add_cube_mesh, add_quad, add_top_camera
from usdml.stage import materials
from usdml.stage.materials import MaterialResolver, read_texture, srgb_to_linear
from usdml.stage.mesh import Topology

T0 = Usd.TimeCode.Default()

#: 4x4 RGBA 8-bit texture, rows top to bottom as stored in the file; every texel distinct
TEXELS = np.array([[[(17 * (4 * r + c) + 5) % 256, (40 + 13 * r) % 256, (200 - 37 * c) % 256, 255]
                    for c in range(4)] for r in range(4)], np.uint8)


def srgb_ref(v8: np.ndarray) -> np.ndarray:
    """sRGB decoding computed independently of the module (float64, the IEC formula)."""
    x = np.asarray(v8, np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def texel(col: int, row_from_bottom: int) -> np.ndarray:
    return TEXELS[3 - row_from_bottom, col]


def st_center(col: int, row_from_bottom: int) -> tuple[float, float]:
    return ((col + 0.5) / 4, (row_from_bottom + 0.5) / 4)


def write_png(path, pixels: np.ndarray = TEXELS) -> str:
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8))
    assert out.write_image(pixels)
    out.close()
    back = oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)
    assert np.array_equal(back, pixels)          # the file holds exactly these texels
    return str(path)


class Log(list):
    """Records every warning call (no de-duplication) so 'once' can be checked."""

    def __call__(self, message: str) -> None:
        self.append(message)


def topo_of(prim: Usd.Prim) -> tuple[Topology, int]:
    m = UsdGeom.Mesh(prim)
    pts = m.GetPointsAttr().Get()
    topo = Topology(np.asarray(m.GetFaceVertexCountsAttr().Get()), np.asarray(m.GetFaceVertexIndicesAttr().Get()),
                    len(pts), np.zeros(0, np.int64), False, str(prim.GetPath()), lambda _m: None)
    return topo, len(pts)


def albedo(resolver: MaterialResolver, prim: Usd.Prim, **kw):
    topo, n = topo_of(prim)
    return resolver.albedo(prim, T0, topo, n, **kw)


def preview_material(stage: Usd.Stage, path: str, color=None) -> tuple[UsdShade.Material, UsdShade.Shader]:
    mat = UsdShade.Material.Define(stage, path)
    pbr = UsdShade.Shader.Define(stage, f"{path}/pbr")
    pbr.CreateIdAttr("UsdPreviewSurface")
    if color is not None:
        pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
    mat.CreateSurfaceOutput().ConnectToSource(pbr.ConnectableAPI(), "surface")
    return mat, pbr


def bind(prim: Usd.Prim, mat: UsdShade.Material, purpose=UsdShade.Tokens.allPurpose, strength=None):
    api = UsdShade.MaterialBindingAPI.Apply(prim)
    if strength is None:
        api.Bind(mat, materialPurpose=purpose)
    else:
        api.Bind(mat, bindingStrength=strength, materialPurpose=purpose)


def textured_material(stage, path, file, *, st_input=None, varname="st", **tex_inputs):
    """Material whose diffuseColor is a UsdUVTexture's output (``output=``, default rgb) read at primvar st."""
    output = tex_inputs.pop("output", "rgb")
    mat, pbr = preview_material(stage, path)
    tex = UsdShade.Shader.Define(stage, f"{path}/tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    types = {"wrapS": Sdf.ValueTypeNames.Token, "wrapT": Sdf.ValueTypeNames.Token,
             "sourceColorSpace": Sdf.ValueTypeNames.Token, "scale": Sdf.ValueTypeNames.Float4,
             "bias": Sdf.ValueTypeNames.Float4, "fallback": Sdf.ValueTypeNames.Float4}
    for name, value in tex_inputs.items():
        tex.CreateInput(name, types[name]).Set(Gf.Vec4f(*value) if types[name] == Sdf.ValueTypeNames.Float4 else value)
    reader = UsdShade.Shader.Define(stage, f"{path}/uv")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    vn = reader.CreateInput("varname", Sdf.ValueTypeNames.String)
    if st_input is not None:        # varname from a material interface input
        vn.ConnectToSource(st_input)
    else:
        vn.Set(varname)
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    out_type = Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float
    tex.CreateOutput(output, out_type)
    pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), output)
    return mat, tex


def quad_with_st(stage, path, st) -> Usd.Prim:
    q = add_quad(stage, path)
    pv = UsdGeom.PrimvarsAPI(q).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    pv.Set([Gf.Vec2f(*x) for x in st])
    return q.GetPrim()


def corner_expected(prim: Usd.Prim, per_vertex: np.ndarray) -> np.ndarray:
    topo, _ = topo_of(prim)
    return per_vertex[topo.vertex]


# --------------------------------------------------------------------------------------------------
def test_constant_diffuse_color_on_every_corner(new_stage):
    stage = new_stage()
    cube = add_cube_mesh(stage, "/World/cube").GetPrim()
    mat, _ = preview_material(stage, "/World/Looks/red", (0.8, 0.1, 0.05))
    bind(cube, mat)
    a = albedo(MaterialResolver(Log()), cube)
    assert a.shape == (12, 3, 3) and a.dtype == np.float32
    assert np.allclose(a, [0.8, 0.1, 0.05])


def test_unauthored_diffuse_is_the_spec_fallback_and_values_are_clipped(new_stage):
    stage = new_stage()
    q1, q2, q3 = (add_quad(stage, f"/World/q{i}").GetPrim() for i in range(3))
    bind(q1, preview_material(stage, "/World/Looks/plain")[0])
    bind(q2, preview_material(stage, "/World/Looks/hot", (2.0, -0.5, 0.5))[0])
    r = MaterialResolver(Log())
    assert np.allclose(albedo(r, q1), 0.18)
    assert np.allclose(albedo(r, q2), [1.0, 0.0, 0.5])
    assert albedo(r, q3) is None                 # nothing bound: caller uses displayColor


def test_diffuse_from_a_material_interface_input(new_stage):
    stage = new_stage()
    quad = add_quad(stage, "/World/q").GetPrim()
    mat, pbr = preview_material(stage, "/World/Looks/m")
    iface = mat.CreateInput("tint", Sdf.ValueTypeNames.Color3f)
    iface.Set(Gf.Vec3f(0.4, 0.5, 0.6))
    pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(iface)
    bind(quad, mat)
    assert np.allclose(albedo(MaterialResolver(Log()), quad), [0.4, 0.5, 0.6])


def test_inherited_binding_from_an_ancestor(new_stage):
    stage = new_stage()
    UsdGeom.Xform.Define(stage, "/World/group")
    quad = add_quad(stage, "/World/group/sub/quad").GetPrim()
    mat, _ = preview_material(stage, "/World/Looks/blue", (0.1, 0.2, 0.9))
    bind(stage.GetPrimAtPath("/World/group"), mat)
    assert np.allclose(albedo(MaterialResolver(Log()), quad), [0.1, 0.2, 0.9])


def test_collection_based_binding(new_stage):
    stage = new_stage()
    world = UsdGeom.Xform.Define(stage, "/World").GetPrim()
    a = add_quad(stage, "/World/a").GetPrim()
    b = add_quad(stage, "/World/b").GetPrim()
    coll = Usd.CollectionAPI.Apply(world, "shiny")
    coll.CreateIncludesRel().AddTarget(a.GetPath())
    mat, _ = preview_material(stage, "/World/Looks/gold", (1.0, 0.7, 0.2))
    UsdShade.MaterialBindingAPI.Apply(world).Bind(coll, mat)
    r = MaterialResolver(Log())
    assert np.allclose(albedo(r, a), [1.0, 0.7, 0.2])
    assert albedo(r, b) is None


def test_preview_purpose_used_without_full_and_full_preferred(new_stage):
    stage = new_stage()
    only_preview = add_quad(stage, "/World/p").GetPrim()
    both = add_quad(stage, "/World/b").GetPrim()
    prev, _ = preview_material(stage, "/World/Looks/prev", (0.0, 1.0, 0.0))
    full, _ = preview_material(stage, "/World/Looks/full", (0.0, 0.0, 1.0))
    bind(only_preview, prev, UsdShade.Tokens.preview)
    bind(both, prev, UsdShade.Tokens.preview)
    bind(both, full, UsdShade.Tokens.full)
    r = MaterialResolver(Log())
    assert np.allclose(albedo(r, only_preview), [0, 1, 0])
    assert np.allclose(albedo(r, both), [0, 0, 1])


def test_textured_quad_gets_linearized_texels_at_texel_centres(new_stage, tmp_path):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    cells = [(0, 0), (3, 0), (2, 3), (1, 2)]          # (col, row from bottom) per quad vertex
    quad = quad_with_st(stage, "/World/quad", [st_center(*c) for c in cells])
    mat, _ = textured_material(stage, "/World/Looks/tex", "./tex.png")   # relative to the layer
    bind(quad, mat)
    stage.Save()
    log = Log()
    a = albedo(MaterialResolver(log), quad)
    per_vertex = np.array([srgb_ref(texel(*c)[:3]) for c in cells])   # PNG 8-bit RGBA: auto -> sRGB
    assert np.allclose(a, corner_expected(quad, per_vertex), atol=1e-6)
    assert not log


def test_texture_raw_single_channel_outputs_and_interface_varname(new_stage, tmp_path, monkeypatch):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    cells = [(0, 0), (3, 0), (2, 3), (1, 2)]
    q_raw = quad_with_st(stage, "/World/raw", [st_center(*c) for c in cells])
    q_g = add_quad(stage, "/World/g").GetPrim()
    pv = UsdGeom.PrimvarsAPI(q_g).CreatePrimvar("uvMap", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    pv.Set([Gf.Vec2f(*st_center(*c)) for c in cells])
    raw, _ = textured_material(stage, "/World/Looks/raw", str(tmp_path / "tex.png"), sourceColorSpace="raw")
    mat = UsdShade.Material.Define(stage, "/World/Looks/g")
    iface = mat.CreateInput("uvName", Sdf.ValueTypeNames.Token)
    iface.Set("uvMap")
    g, _ = textured_material(stage, "/World/Looks/g", str(tmp_path / "tex.png"), st_input=iface, output="g")
    bind(q_raw, raw)
    bind(q_g, g)
    reads = []
    monkeypatch.setattr(materials, "read_texture", lambda path: reads.append(path) or read_texture(path))
    r = MaterialResolver(Log())
    per_vertex = np.array([texel(*c)[:3] / 255.0 for c in cells])
    assert np.allclose(albedo(r, q_raw), corner_expected(q_raw, per_vertex), atol=1e-6)
    green = np.array([srgb_ref(texel(*c)[1]) for c in cells])
    topo, _ = topo_of(q_g)
    assert np.allclose(albedo(r, q_g), np.repeat(green[topo.corner][..., None], 3, axis=2), atol=1e-6)
    assert len(reads) == 1                       # one read for both materials


@pytest.mark.parametrize("wrap,col", [("repeat", 0), ("useMetadata", 0), ("clamp", 3), ("mirror", 3), ("black", None)])
def test_wrap_modes_outside_unit_square(new_stage, tmp_path, wrap, col):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    # s = 1 + half a texel: the first texel again (repeat), the last (clamp/mirror) or outside (black)
    st = [(1 + 0.5 / 4, st_center(0, 1)[1])] * 4
    quad = quad_with_st(stage, "/World/q", st)
    mat, _ = textured_material(stage, "/World/Looks/m", str(tmp_path / "tex.png"), wrapS=wrap, wrapT="clamp",
                               sourceColorSpace="raw")
    bind(quad, mat)
    a = albedo(MaterialResolver(Log()), quad)
    expected = np.zeros(3) if col is None else texel(col, 1)[:3] / 255.0
    assert np.allclose(a, expected, atol=1e-6)


def test_wrap_t_mirror_and_bilinear_between_texels(new_stage, tmp_path):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    # t = -0.5 texel -> mirrored back onto the bottom row; s on the edge between columns 1 and 2
    st = [(0.5, -0.5 / 4)] * 4
    quad = quad_with_st(stage, "/World/q", st)
    mat, _ = textured_material(stage, "/World/Looks/m", str(tmp_path / "tex.png"), wrapT="mirror")
    bind(quad, mat)
    a = albedo(MaterialResolver(Log()), quad)
    expected = 0.5 * (srgb_ref(texel(1, 0)[:3]) + srgb_ref(texel(2, 0)[:3]))    # linearized, then filtered
    assert np.allclose(a, expected, atol=1e-6)


def test_scale_and_bias_then_clipped(new_stage, tmp_path):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    cells = [(0, 0), (3, 0), (2, 3), (1, 2)]
    quad = quad_with_st(stage, "/World/q", [st_center(*c) for c in cells])
    scale, bias = (0.5, 2.0, 1.0, 1.0), (0.1, 0.0, -0.3, 0.0)
    mat, _ = textured_material(stage, "/World/Looks/m", str(tmp_path / "tex.png"), sourceColorSpace="sRGB",
                               scale=scale, bias=bias)
    bind(quad, mat)
    per_vertex = np.clip(np.array([srgb_ref(texel(*c)[:3]) for c in cells]) * scale[:3] + bias[:3], 0, 1)
    assert np.allclose(albedo(MaterialResolver(Log()), quad), corner_expected(quad, per_vertex), atol=1e-6)


def test_float_exr_auto_is_raw(new_stage, tmp_path):
    stage = new_stage()
    pix = np.random.default_rng(1).uniform(0, 1, (4, 4, 3)).astype(np.float32)
    path = str(tmp_path / "tex.exr")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(4, 4, 3, oiio.FLOAT))
    out.write_image(pix)
    out.close()
    cells = [(0, 0), (3, 0), (2, 3), (1, 2)]
    quad = quad_with_st(stage, "/World/q", [st_center(*c) for c in cells])
    bind(quad, textured_material(stage, "/World/Looks/m", path)[0])
    per_vertex = np.array([pix[3 - r, c] for c, r in cells])
    assert np.allclose(albedo(MaterialResolver(Log()), quad), corner_expected(quad, per_vertex), atol=1e-6)


def _two_quads_with_mtlx_surface(new_stage, sid: str):
    """(stage, quad, quad) bound to one material whose only surface is a MaterialX shader ``sid``, base_color red."""
    stage = new_stage()
    q1, q2 = add_quad(stage, "/World/a").GetPrim(), add_quad(stage, "/World/b").GetPrim()
    mat = UsdShade.Material.Define(stage, "/World/Looks/mx")
    ss = UsdShade.Shader.Define(stage, "/World/Looks/mx/ss")
    ss.CreateIdAttr(sid)
    ss.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(1, 0, 0))
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(ss.ConnectableAPI(), "out")
    bind(q1, mat)
    bind(q2, mat)
    return stage, q1, q2


def test_materialx_standard_surface_renders_its_base_color(new_stage):
    """MaterialX's standard_surface without a preview surface: base · base_color (usdml.stage.materialx)."""
    _stage, q1, q2 = _two_quads_with_mtlx_surface(new_stage, "ND_standard_surface_surfaceshader")
    log = Log()
    r = MaterialResolver(log)
    assert np.allclose(albedo(r, q1), (1, 0, 0)) and np.allclose(albedo(r, q2), (1, 0, 0)) and not log


def test_surface_usdml_does_not_map_gives_none_and_warns_once(new_stage):
    _stage, q1, q2 = _two_quads_with_mtlx_surface(new_stage, "ND_gltf_pbr_surfaceshader")
    log = Log()
    r = MaterialResolver(log)
    assert albedo(r, q1) is None and albedo(r, q2) is None and albedo(r, q1) is None
    assert len(log) == 1
    assert log[0].startswith("/World/Looks/mx: no UsdPreviewSurface (MaterialX/other only); using displayColor")


def test_preview_surface_found_beside_materialx(new_stage):
    stage = new_stage()
    quad = add_quad(stage, "/World/q").GetPrim()
    mat, _ = preview_material(stage, "/World/Looks/both", (0.3, 0.6, 0.9))
    ss = UsdShade.Shader.Define(stage, "/World/Looks/both/ss")
    ss.CreateIdAttr("ND_open_pbr_surface_surfaceshader")
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(ss.ConnectableAPI(), "out")
    bind(quad, mat)
    log = Log()
    assert np.allclose(albedo(MaterialResolver(log), quad), [0.3, 0.6, 0.9]) and not log


def _instanced_stage(new_stage, tmp_path):
    asset = Usd.Stage.CreateNew(str(tmp_path / "asset.usda"))
    root = UsdGeom.Xform.Define(asset, "/Asset").GetPrim()
    asset.SetDefaultPrim(root)
    mesh = add_quad(asset, "/Asset/Geom/mesh").GetPrim()
    mat, _ = preview_material(asset, "/Asset/Looks/green", (0.1, 0.9, 0.2))
    bind(mesh, mat)
    asset.Save()
    stage = new_stage()
    for name in ("inst1", "inst2"):
        p = UsdGeom.Xform.Define(stage, f"/World/{name}").GetPrim()
        p.GetReferences().AddReference("./asset.usda")
        p.SetInstanceable(True)
    return stage


def test_material_inside_an_instanceable_asset_resolves_on_the_prototype(new_stage, tmp_path):
    stage = _instanced_stage(new_stage, tmp_path)
    (proto,) = stage.GetPrototypes()
    mesh = stage.GetPrimAtPath(proto.GetPath().AppendPath("Geom/mesh"))
    assert mesh and mesh.IsInPrototype()
    r = MaterialResolver(Log())
    assert np.allclose(albedo(r, mesh), [0.1, 0.9, 0.2])
    proxy = stage.GetPrimAtPath("/World/inst2/Geom/mesh")
    assert proxy.IsInstanceProxy()
    assert np.allclose(albedo(r, proxy), [0.1, 0.9, 0.2])


def test_binding_on_the_instance_applies_through_instance_argument(new_stage, tmp_path):
    stage = _instanced_stage(new_stage, tmp_path)
    red, _ = preview_material(stage, "/World/Looks/red", (0.9, 0.0, 0.0))
    inst1 = stage.GetPrimAtPath("/World/inst1")
    inst2 = stage.GetPrimAtPath("/World/inst2")
    bind(inst1, red, strength=UsdShade.Tokens.strongerThanDescendants)
    bind(inst2, red)                                       # weaker than the asset's own binding
    (proto,) = {i.GetPrototype() for i in (inst1, inst2)}
    mesh = stage.GetPrimAtPath(proto.GetPath().AppendPath("Geom/mesh"))
    r = MaterialResolver(Log())
    assert np.allclose(albedo(r, mesh, instance=inst1), [0.9, 0, 0])
    assert np.allclose(albedo(r, mesh, instance=inst2), [0.1, 0.9, 0.2])
    assert np.allclose(albedo(r, mesh), [0.1, 0.9, 0.2])


def test_missing_texture_uses_fallback_and_warns(new_stage, tmp_path):
    stage = new_stage()
    quad = quad_with_st(stage, "/World/q", [(0, 0)] * 4)
    mat, _ = textured_material(stage, "/World/Looks/m", "./nope.png", fallback=(0.2, 0.4, 0.6, 1.0))
    bind(quad, mat)
    stage.Save()
    log = Log()
    r = MaterialResolver(log)
    assert np.allclose(albedo(r, quad), [0.2, 0.4, 0.6])
    assert np.allclose(albedo(r, quad), [0.2, 0.4, 0.6])
    assert len(log) == 1 and "/World/Looks/m" in log[0] and "nope.png" in log[0]
    assert "using its inputs:fallback (0.2, 0.4, 0.6, 1) (fix the asset path)" in log[0]     # the value used


def test_unreadable_texture_and_udim_warn(new_stage, tmp_path):
    stage = new_stage()
    (tmp_path / "junk.png").write_bytes(b"not a png")
    q1 = quad_with_st(stage, "/World/a", [(0, 0)] * 4)
    q2 = quad_with_st(stage, "/World/b", [(0, 0)] * 4)
    bind(q1, textured_material(stage, "/World/Looks/junk", str(tmp_path / "junk.png"))[0])   # default fallback
    udim, _ = textured_material(stage, "/World/Looks/udim", str(tmp_path / "tex.<UDIM>.png"))
    udim.GetPrim().GetChild("pbr").GetAttribute("inputs:diffuseColor").Set(Gf.Vec3f(0.5, 0.25, 0.125))
    bind(q2, udim)
    log = Log()
    r = MaterialResolver(log)
    assert np.allclose(albedo(r, q1), [0, 0, 0])           # UsdUVTexture's spec fallback (0, 0, 0, 1)
    assert np.allclose(albedo(r, q2), [0.5, 0.25, 0.125])  # the diffuseColor's own value
    assert len(log) == 2 and "junk.png" in log[0] and "UDIM" in log[1]
    # issue 55: "using its inputs:fallback" of an unauthored fallback made a frame black without saying so
    assert "using the UsdUVTexture's inputs:fallback (0, 0, 0, 1), unauthored: the spec's default black" in log[0]


def test_missing_st_primvar_uses_reader_fallback(new_stage, tmp_path):
    stage = new_stage()
    write_png(tmp_path / "tex.png")
    quad = add_quad(stage, "/World/q").GetPrim()
    mat, _ = textured_material(stage, "/World/Looks/m", str(tmp_path / "tex.png"), sourceColorSpace="raw",
                               wrapS="clamp", wrapT="clamp")
    bind(quad, mat)
    log = Log()
    a = albedo(MaterialResolver(log), quad)
    assert np.allclose(a, texel(0, 0)[:3] / 255.0, atol=1e-6)    # st fallback (0, 0) clamps to the corner texel
    assert len(log) == 1 and "primvar 'st'" in log[0]


def test_texture_inside_usdz_package(tmp_path):
    write_png(tmp_path / "tex.png")
    stage = Usd.Stage.CreateNew(str(tmp_path / "pkg.usda"))
    root = UsdGeom.Xform.Define(stage, "/World").GetPrim()
    stage.SetDefaultPrim(root)
    cells = [(0, 0), (3, 0), (2, 3), (1, 2)]
    quad = quad_with_st(stage, "/World/q", [st_center(*c) for c in cells])
    bind(quad, textured_material(stage, "/World/Looks/m", "./tex.png")[0])
    stage.Save()
    usdz = str(tmp_path / "pkg.usdz")
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(tmp_path / "pkg.usda")), usdz)
    (tmp_path / "tex.png").unlink()                      # only the packaged copy remains
    pkg = Usd.Stage.Open(usdz)
    q = pkg.GetPrimAtPath("/World/q")
    log = Log()
    a = albedo(MaterialResolver(log), q)
    per_vertex = np.array([srgb_ref(texel(*c)[:3]) for c in cells])
    assert not log, log
    assert np.allclose(a, corner_expected(q, per_vertex), atol=1e-6)


def test_primvar_reader_drives_diffuse(new_stage):
    stage = new_stage()
    quad = add_quad(stage, "/World/q")
    UsdGeom.PrimvarsAPI(quad).CreatePrimvar("tint", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.uniform).Set(
        [Gf.Vec3f(0.25, 0.5, 0.75)])
    mat, pbr = preview_material(stage, "/World/Looks/m")
    reader = UsdShade.Shader.Define(stage, "/World/Looks/m/tint")
    reader.CreateIdAttr("UsdPrimvarReader_float3")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("tint")
    pbr.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(reader.ConnectableAPI(), "result")
    bind(quad.GetPrim(), mat)
    assert np.allclose(albedo(MaterialResolver(Log()), quad.GetPrim()), [0.25, 0.5, 0.75])


def test_srgb_curve_matches_reference():
    x = np.linspace(0, 1, 1001)
    assert np.allclose(srgb_to_linear(x), np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4), atol=1e-6)


def test_standard_shader_ball_does_not_crash(assets, capsys):
    path = assets / "usd-wg" / "StandardShaderBall" / "standard_shader_ball_scene.usda"
    if not path.exists():
        pytest.skip(f"{path} not found")
    stage = Usd.Stage.Open(str(path))
    log = Log()
    r = MaterialResolver(log)
    rows = []
    for prim in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies()):
        if not prim.IsA(UsdGeom.Mesh):
            continue
        topo, n = topo_of(prim)
        a = r.albedo(prim, Usd.TimeCode(3), topo, n)
        mat = r.bound_material(prim)
        if a is not None:
            assert a.shape == (len(topo.face), 3, 3) and np.isfinite(a).all() and (a >= 0).all() and (a <= 1).all()
        rows.append((str(prim.GetPath()), str(mat.GetPath()) if mat else None,
                     None if a is None else np.round(a.reshape(-1, 3).mean(0), 3).tolist()))
    with capsys.disabled():
        for row in rows:
            print("shaderball:", *row)
        for m in log:
            print("shaderball warning:", m)
    assert rows


def test_delegate_uses_the_bound_material_as_albedo(tmp_path):
    """End to end: the albedo AOV of a rendered mesh shows its UsdPreviewSurface diffuseColor."""
    from pxr import Usd, UsdGeom, UsdShade, Sdf
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    stage = Usd.Stage.CreateNew(str(tmp_path / "m.usda"))
    mesh = UsdGeom.Mesh.Define(stage, "/World/quad")
    mesh.CreatePointsAttr([(-1, 0, -1), (-1, 0, 1), (1, 0, 1), (1, 0, -1)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateDisplayColorPrimvar().Set([(0, 0, 1)])
    material = UsdShade.Material.Define(stage, "/World/mat")
    shader = UsdShade.Shader.Define(stage, "/World/mat/surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.8, 0.4, 0.1))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.AddTranslateOp().Set((0, 5, 0))
    cam.AddRotateXOp().Set(-90)
    stage.Save()
    d = StageDelegate(str(tmp_path / "m.usda"))
    assert np.allclose(d.snapshot(0).meshes[0].albedo, (0.8, 0.4, 0.1))
    r = FrameRenderer(d, UsdmlSettings())
    albedo = r.render(0, 16, 16, {"albedo"}).buffers["albedo"]
    assert np.allclose(albedo[8, 8], (0.8, 0.4, 0.1))


def test_textures_are_sampled_per_pixel(tmp_path):
    """A 4x4 texture on a quad filling the view: every texel shows in the albedo AOV, not a corner blend."""
    from pxr import Usd, UsdGeom, UsdShade, Sdf
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    texels = (np.arange(48, dtype=np.float32).reshape(4, 4, 3) * 5 + 10) / 255.0
    out = oiio.ImageOutput.create(str(tmp_path / "t.exr"))
    out.open(str(tmp_path / "t.exr"), oiio.ImageSpec(4, 4, 3, oiio.FLOAT))
    out.write_image(texels)
    out.close()
    stage = Usd.Stage.CreateNew(str(tmp_path / "q.usda"))
    quad = UsdGeom.Mesh.Define(stage, "/quad")
    quad.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.PrimvarsAPI(quad).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    mat = UsdShade.Material.Define(stage, "/mat")
    surf = UsdShade.Shader.Define(stage, "/mat/surf")
    surf.CreateIdAttr("UsdPreviewSurface")
    reader = UsdShade.Shader.Define(stage, "/mat/st")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    tex = UsdShade.Shader.Define(stage, "/mat/tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("t.exr")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(quad.GetPrim()).Bind(mat)
    cam = UsdGeom.Camera.Define(stage, "/cam")
    cam.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    cam.CreateHorizontalApertureAttr(20)      # tenths of a scene unit: the view is exactly 2 x 2
    cam.CreateVerticalApertureAttr(20)
    cam.AddTranslateOp().Set((0, 0, 5))
    stage.Save()
    r = FrameRenderer(StageDelegate(str(tmp_path / "q.usda")), UsdmlSettings(pixel_samples=1))   # texel centres: no blend across texels
    albedo = r.render(0, 8, 8, {"albedo"}).buffers["albedo"]
    # independent bilinear lookup with repeat wrap: texel centres at (i + 0.5) / 4, t = 0 at the image bottom
    s = (np.arange(8) + 0.5) / 8
    x = s * 4 - 0.5
    y = s * 4 - 0.5                             # pixel row i sees t = 1 - s_i: image row (1 - t) * 4 - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    expected = np.zeros((8, 8, 3))
    for i in range(8):
        for j in range(8):
            a, b = y0[i] % 4, (y0[i] + 1) % 4
            c, d = x0[j] % 4, (x0[j] + 1) % 4
            expected[i, j] = ((1 - fy[i]) * ((1 - fx[j]) * texels[a, c] + fx[j] * texels[a, d])
                              + fy[i] * ((1 - fx[j]) * texels[b, c] + fx[j] * texels[b, d]))
    np.testing.assert_allclose(albedo, expected, atol=1e-5)
    assert len(np.unique(albedo.reshape(-1, 3).round(4), axis=0)) > 16    # not a blend of 4 corners


def test_a_missing_texture_that_blacks_out_the_frame_says_so(new_stage, tmp_path):
    """Issue 55: a missing texture with an unauthored fallback made a whole frame black while the warning said
    only "using its inputs:fallback"; now it names the value, and the black frame is a warning of its own."""
    import subprocess
    import sys

    from pxr import UsdLux

    stage = new_stage(start=1, end=1)
    quad = quad_with_st(stage, "/World/q", [(0, 0), (0, 1), (1, 1), (1, 0)])
    mat = textured_material(stage, "/World/Looks/wood", "./wood.png")[0]
    # a metal (its specular colour is its diffuseColor): with the texture's black fallback nothing reflects at all
    UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/wood/pbr")).CreateInput(
        "metallic", Sdf.ValueTypeNames.Float).Set(1.0)
    bind(quad, mat)
    add_top_camera(stage, 2.0)
    UsdLux.DistantLight.Define(stage, "/World/sun").AddRotateXOp().Set(-60)
    stage.Save()
    path = stage.GetRootLayer().realPath
    r = subprocess.run([sys.executable, "-m", "usdml.cli", "render", path, str(tmp_path / "o.exr"), "--imageWidth",
                        "16", "--pixel-samples", "1"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stderr.splitlines() == [
        "usdml: warning: /World/Looks/wood: /World/Looks/wood/tex.inputs:file @./wood.png@ does not resolve (missing "
        "file?); using its inputs:fallback (0, 0, 0, 1), unauthored: the spec's default black (fix the asset path)",
        f"usdml: warning: {path}: frame 1 is black (color 0 everywhere): every surface in view has a black albedo; "
        "check the materials (a diffuseColor of 0, a texture that does not load and whose inputs:fallback is the "
        "spec's black)"]
