"""Cryptomatte AOVs, read back by a decoder written here from the specification (Psyop, version 1.1.0), sharing no
usdml code: its own MurmurHash3_x86_32, its own uint32 -> float32 conversion, the EXR read with OpenEXR, the
manifest parsed from the header, a matte built by summing the coverage of the ranks whose id matches."""

from __future__ import annotations

import json
import re
import struct
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, Vt

from usdml.cli import main

# --- the decoder (the specification, no usdml code) ---------------------------------------------------------

_M = 0xFFFFFFFF


def _rotl(x: int, r: int) -> int:
    return ((x << r) | (x >> (32 - r))) & _M


def murmur3_32(data: bytes, seed: int = 0) -> int:
    """MurmurHash3_x86_32 (Austin Appleby's smhasher), written out."""
    c1, c2 = 0xCC9E2D51, 0x1B873593
    h = seed
    nblocks = len(data) // 4
    for i in range(nblocks):
        k = int.from_bytes(data[4 * i:4 * i + 4], "little")
        k = _rotl((k * c1) & _M, 15) * c2 & _M
        h = _rotl(h ^ k, 13)
        h = (h * 5 + 0xE6546B64) & _M
    tail = data[4 * nblocks:]
    k = 0
    if len(tail) >= 3:
        k ^= tail[2] << 16
    if len(tail) >= 2:
        k ^= tail[1] << 8
    if len(tail) >= 1:
        k ^= tail[0]
        h ^= _rotl((k * c1) & _M, 15) * c2 & _M
    h ^= len(data)
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & _M
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & _M
    return h ^ (h >> 16)


def spec_id(name: str) -> float:
    """The specification's ``uint32_to_float32`` of the name's hash: exponent clamped to [1, 254]."""
    h = murmur3_32(name.encode("utf-8"))
    exponent = min(max((h >> 23) & 0xFF, 1), 254)
    bits = (h & 0x80000000) | (exponent << 23) | (h & 0x7FFFFF)
    return struct.unpack("<f", struct.pack("<I", bits))[0]


class Cryptomatte:
    """One Cryptomatte layer of an EXR file, found by the name in its header."""

    def __init__(self, path, name: str):
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = dict(f.header())
            channels = {n: np.array(c.pixels) for n, c in f.channels().items()}
        keys = [k.split("/")[1] for k, v in header.items() if re.fullmatch(r"cryptomatte/[0-9a-f]{1,7}/name", k)
                and v == name]
        assert len(keys) == 1, (name, [k for k in header if k.startswith("cryptomatte/")])
        meta = {k.split("/")[2]: v for k, v in header.items() if k.startswith(f"cryptomatte/{keys[0]}/")}
        assert meta["hash"] == "MurmurHash3_32" and meta["conversion"] == "uint32_to_float32"
        # the key: the first 7 hex digits of the layer name's hash (the specification's suggestion)
        assert keys[0] == f"{murmur3_32(name.encode()):08x}"[:7]
        self.manifest = {n: struct.unpack(">f", bytes.fromhex(h))[0] for n, h in json.loads(meta["manifest"]).items()}
        self.hex = json.loads(meta["manifest"])
        layers = sorted({n[:-2] for n in channels if re.fullmatch(re.escape(name) + r"\d\d\.[RGBA]", n)})
        assert layers == [f"{name}{k:02d}" for k in range(len(layers))] and layers
        for n in channels:
            if n.startswith(name):
                assert channels[n].dtype == np.float32, n        # ids are bit patterns: never half
        ranks = []
        for layer in layers:
            ranks += [(channels[f"{layer}.R"], channels[f"{layer}.G"]), (channels[f"{layer}.B"], channels[f"{layer}.A"])]
        self.ids = np.stack([r[0] for r in ranks], -1)          # (H, W, ranks)
        self.coverage = np.stack([r[1] for r in ranks], -1)

    def matte(self, name: str) -> np.ndarray:
        return np.where(self.ids == np.float32(spec_id(name)), self.coverage, 0.0).sum(-1)

    def first(self) -> np.ndarray:
        """(H, W) object name of rank 0 ("" where none)."""
        by_id = {np.float32(v).tobytes(): n for n, v in self.manifest.items()}
        return np.vectorize(lambda v: by_id.get(np.float32(v).tobytes(), ""), otypes=[object])(self.ids[..., 0])


def test_decoder_hash_matches_specification_example():
    # the specification's manifest example: {"bunny": "13851a76"}
    assert f"{murmur3_32(b'bunny'):08x}" == "13851a76"
    assert struct.pack(">f", spec_id("bunny")).hex() == "13851a76"


# --- stages -----------------------------------------------------------------------------------------------

#: the edge stage: 16 x 4 pixels of 1 unit; Left covers x < XE, Right XE < x < XR, nothing beyond
XE, XR = -1.7, 3.55


def _ortho_camera(stage, width_units: float, height_units: float):
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    cam.CreateHorizontalApertureAttr(width_units * 10)          # tenths of a scene unit
    cam.CreateVerticalApertureAttr(height_units * 10)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100))
    cam.AddTranslateOp().Set((0, 0, 10))
    light = UsdLux.DistantLight.Define(stage, "/World/sun")
    light.CreateIntensityAttr(1.0)


def _rect(stage, path: str, xs: list[float], y0=-3.0, y1=3.0, z=0.0):
    """A mesh of quads side by side in x (one face per interval of ``xs``), facing +Z."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    pts = [(x, y, z) for x in xs for y in (y0, y1)]
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr([4] * (len(xs) - 1))
    mesh.CreateFaceVertexIndicesAttr([i for k in range(len(xs) - 1) for i in (2 * k, 2 * k + 2, 2 * k + 3, 2 * k + 1)])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def _material(stage, path: str):
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, path + "/surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return mat


def _edge_stage(new_stage):
    stage = new_stage("edge.usda", start=1)
    _ortho_camera(stage, 16, 4)
    asset = UsdGeom.Xform.Define(stage, "/World/AssetA")
    Usd.ModelAPI(asset.GetPrim()).SetKind(Kind.Tokens.component)
    left = _rect(stage, "/World/AssetA/Left", [-8.5, -5.0, XE])
    _rect(stage, "/World/Loose/Right", [XE, XR])
    mat_a, mat_b = _material(stage, "/World/Looks/MatA"), _material(stage, "/World/Looks/MatB")
    UsdShade.MaterialBindingAPI.Apply(left.GetPrim()).Bind(mat_b)
    subset = UsdShade.MaterialBindingAPI(left).CreateMaterialBindSubset("first", Vt.IntArray([0]), UsdGeom.Tokens.face)
    UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(mat_a)
    stage.Save()
    return stage.GetRootLayer().realPath


def _render(stage_path, out, aovs="CryptoObject,CryptoMaterial,CryptoAsset", width=16, samples=16, extra=()):
    assert main(["render", str(stage_path), str(out), "--aovs", aovs, "--imageWidth", str(width),
                 "--pixel-samples", str(samples), *extra]) == 0
    return out


@pytest.fixture(scope="module")
def edge_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("edge")

    def new_stage(name, start=None):
        stage = Usd.Stage.CreateNew(str(folder / name))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(start)
        return stage

    return _render(_edge_stage(new_stage), folder / "edge.exr")


def _coverage_truth(x0: float, x1: float) -> np.ndarray:
    """(16,) fraction of each pixel column (x in [-8 + c, -7 + c]) inside [x0, x1]."""
    lo = np.arange(16) - 8.0
    return np.clip(np.minimum(lo + 1, x1) - np.maximum(lo, x0), 0, 1)


def test_every_id_is_its_names_hash(edge_file):
    for layer in ("CryptoObject", "CryptoMaterial", "CryptoAsset"):
        c = Cryptomatte(edge_file, layer)
        for name, hexid in c.hex.items():
            assert hexid == struct.pack(">f", spec_id(name)).hex(), name
        ids = {np.float32(v).tobytes() for v in c.ids[c.coverage > 0]}
        assert ids == {np.float32(spec_id(n)).tobytes() for n in c.manifest}, layer
        assert np.all(c.ids[c.coverage == 0] == 0)              # no object: id 0


def test_object_coverage_at_an_edge_is_the_area_fraction(edge_file):
    c = Cryptomatte(edge_file, "CryptoObject")
    assert set(c.manifest) == {"/World/AssetA/Left", "/World/Loose/Right"}
    left, right = c.matte("/World/AssetA/Left"), c.matte("/World/Loose/Right")
    # 16 correlated multi-jittered rays: x in one of 16 thin columns each, so an edge is known to 1/16
    for got, truth in ((left, _coverage_truth(-9, XE)), (right, _coverage_truth(XE, XR))):
        assert np.abs(got - truth[None, :]).max() <= 1 / 16 + 1e-6, (got[0], truth)
    total = c.coverage.sum(-1)
    assert np.all(total <= 1 + 1e-6)
    hit = _coverage_truth(-9, XR)
    assert np.abs(total - hit[None, :]).max() <= 1 / 16 + 1e-6      # ranks sum to the fraction that hit
    # the first rank names what covers most of the pixel; exactly on every interior pixel
    first = c.first()
    want = np.where(_coverage_truth(-9, XE) > 0.5, "/World/AssetA/Left",
                    np.where(_coverage_truth(XE, XR) > 0.5, "/World/Loose/Right", ""))
    assert (first == want[None, :]).all(), first[0]


def test_material_follows_geomsubset_binding(edge_file):
    c = Cryptomatte(edge_file, "CryptoMaterial")
    assert set(c.manifest) == {"/World/Looks/MatA", "/World/Looks/MatB"}    # Right has no material: no id
    assert np.allclose(c.matte("/World/Looks/MatA"), _coverage_truth(-9, -5)[None, :], atol=1 / 16)
    assert np.allclose(c.matte("/World/Looks/MatB"), _coverage_truth(-5, XE)[None, :], atol=1 / 16)
    assert np.all(c.coverage[:, 8:].sum(-1) == 0)


def test_asset_by_kind(edge_file):
    c = Cryptomatte(edge_file, "CryptoAsset")
    assert set(c.manifest) == {"/World/AssetA"}                         # Right is in no component
    assert np.allclose(c.matte("/World/AssetA"), _coverage_truth(-9, XE)[None, :], atol=1 / 16)


def test_info_counts_the_names(edge_file, capsys):
    assert main(["info", str(edge_file.parent / "edge.usda"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cryptomatteNames"] == {"CryptoObject": 2, "CryptoMaterial": 2, "CryptoAsset": 1}


def test_instances_native_and_point_instancer(new_stage, tmp_path):
    stage = new_stage("inst.usda", start=1)
    _ortho_camera(stage, 16, 4)
    proto = UsdGeom.Xform.Define(stage, "/Asset")
    _rect(stage, "/Asset/geo", [-1.0, 1.0], -1.0, 0.0)
    _rect(stage, "/Leaf/geo", [-1.0, 1.0], 0.0, 1.0)            # nested: an instance inside the asset
    stage.GetPrimAtPath("/Leaf").SetSpecifier(Sdf.SpecifierClass)
    leaf = stage.DefinePrim("/Asset/leaf", "Xform")
    leaf.GetReferences().AddInternalReference("/Leaf")
    leaf.SetInstanceable(True)
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Asset/geo")).Bind(_material(stage, "/Asset/Mat"))
    stage.GetPrimAtPath("/Asset").SetSpecifier(Sdf.SpecifierClass)
    for i, x in enumerate((-6.0, -2.0)):
        inst = UsdGeom.Xform.Define(stage, f"/World/Inst_{i}")
        inst.GetPrim().GetReferences().AddInternalReference("/Asset")
        inst.GetPrim().SetInstanceable(True)
        Usd.ModelAPI(inst.GetPrim()).SetKind(Kind.Tokens.component)
        inst.AddTranslateOp().Set((x, 0, 0))
    pi = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    UsdGeom.Scope.Define(stage, "/World/PI/Protos")
    _rect(stage, "/World/PI/Protos/rock/geo", [-1.0, 1.0], -1.0, 1.0)
    pi.CreatePrototypesRel().SetTargets(["/World/PI/Protos/rock"])
    pi.CreateProtoIndicesAttr([0, 0])
    pi.CreatePositionsAttr([(2.0, 0, 0), (6.0, 0, 0)])
    stage.Save()
    out = _render(stage.GetRootLayer().realPath, tmp_path / "inst.exr", "CryptoObject,CryptoMaterial,CryptoAsset")
    obj = Cryptomatte(out, "CryptoObject")
    centres = obj.first()[:, [2, 6, 10, 14]]         # pixel columns at x = -6, -2, 2, 6; rows y = 1.5 .. -1.5
    # native instances: each its instance proxy path; PointInstancer instances share their prototype mesh's;
    # instances nested in an instanced asset share the path through the first instances
    assert list(centres[2]) == ["/World/Inst_0/geo", "/World/Inst_1/geo", "/World/PI/Protos/rock/geo",
                                "/World/PI/Protos/rock/geo"]
    assert list(centres[1, :2]) == ["/World/Inst_0/leaf/geo"] * 2
    assert not [n for n in obj.manifest if "__Prototype" in n]
    # instances share the material bound inside their prototype, named through the first instance
    assert set(Cryptomatte(out, "CryptoMaterial").manifest) == {"/World/Inst_0/Mat"}
    asset = Cryptomatte(out, "CryptoAsset")
    assert set(asset.manifest) == {"/World/Inst_0", "/World/Inst_1"}
    assert asset.matte("/World/Inst_1")[2, 6] == 1.0 and asset.matte("/World/Inst_0")[2, 6] == 0.0


@pytest.mark.slow          # a LocalCluster of two processes: some 10 s here
def test_workers_name_and_rank_as_one_process(tmp_path, capsys):
    """Frames on a Dask LocalCluster (other processes: USD numbers native prototypes its own way in each) write the
    same Cryptomatte layers and manifests as one process."""
    pytest.importorskip("distributed")
    stage = Usd.Stage.CreateNew(str(tmp_path / "many.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(2)
    _ortho_camera(stage, 16, 4)
    for k in range(4):                  # four assets: four prototypes whose numbering USD may change
        _rect(stage, f"/A{k}/geo", [-1.0, 1.0], -1.0, 1.0)
        UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath(f"/A{k}/geo")).Bind(_material(stage, f"/A{k}/Mat"))
        stage.GetPrimAtPath(f"/A{k}").SetSpecifier(Sdf.SpecifierClass)
        for i in range(2):
            inst = UsdGeom.Xform.Define(stage, f"/World/I{k}_{i}")
            inst.GetPrim().GetReferences().AddInternalReference(f"/A{k}")
            inst.GetPrim().SetInstanceable(True)
            inst.AddTranslateOp().Set((-7.0 + 2 * (2 * k + i), 0.0, 0.0))
    stage.Save()
    args = ["--frames", "1:2", "--aovs", "CryptoObject,CryptoMaterial", "--imageWidth", "16", "--pixel-samples", "4"]
    assert main(["render", stage.GetRootLayer().realPath, str(tmp_path / "one" / "m.#.exr"), *args]) == 0
    assert main(["render", stage.GetRootLayer().realPath, str(tmp_path / "farm" / "m.#.exr"), *args,
                 "--workers", "2", "--chunk-size", "1", "--nthreads", "1"]) == 0
    for f in (1, 2):
        for layer in ("CryptoObject", "CryptoMaterial"):
            one = Cryptomatte(tmp_path / "one" / f"m.{f}.exr", layer)
            farm = Cryptomatte(tmp_path / "farm" / f"m.{f}.exr", layer)
            assert one.hex == farm.hex and one.ids.tobytes() == farm.ids.tobytes()
            assert one.coverage.tobytes() == farm.coverage.tobytes()
    assert len(one.manifest) == 4 and "/World/I0_0/Mat" in one.manifest       # CryptoMaterial: one per asset


def test_render_var_route_and_determinism(tmp_path, edge_file):
    stage = Usd.Stage.CreateNew(str(tmp_path / "rv.usda"))
    stage.GetRootLayer().subLayerPaths.append(str(edge_file.parent / "edge.usda"))
    settings = UsdRender.Settings.Define(stage, "/Render/settings")
    settings.CreateResolutionAttr(Gf.Vec2i(16, 4))
    product = UsdRender.Product.Define(stage, "/Render/product")
    product.CreateProductNameAttr(str(tmp_path / "rv.exr"))
    var = UsdRender.Var.Define(stage, "/Render/Vars/crypto_object")     # Arnold's AOV name
    var.CreateSourceNameAttr("crypto_object")
    var.CreateDataTypeAttr("color4f")
    product.CreateOrderedVarsRel().SetTargets([var.GetPath()])
    settings.CreateProductsRel().SetTargets([product.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/settings")
    stage.Save()
    assert main(["render", stage.GetRootLayer().realPath, "--pixel-samples", "16"]) == 0
    ours, theirs = Cryptomatte(tmp_path / "rv.exr", "crypto_object"), Cryptomatte(edge_file, "CryptoObject")
    # the same seed: the same ranks, bit for bit
    assert ours.ids.tobytes() == theirs.ids.tobytes() and ours.coverage.tobytes() == theirs.coverage.tobytes()


def test_unknown_crypto_layer_is_one_line(new_stage, tmp_path, capsys, edge_file):
    code = main(["render", str(edge_file.parent / "edge.usda"), str(tmp_path / "x.exr"), "--aovs", "CryptoShape"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    (line,) = [x for x in err.splitlines() if x.startswith("usdml: error:")]
    assert "CryptoShape" in line
    assert not (tmp_path / "x.exr").exists()


def test_ranking_filter_against_counting():
    """Ranks of random passes (more than six ids a pixel, ties) against counting them one pixel at a time."""
    from usdml.aov.cryptomatte import RankFilter

    rng = np.random.default_rng(5)
    pixels, samples = 300, 16
    choices = np.array([0, 3, 5, 7, 11, 13, 17, 19, 23], np.uint32)
    passes = [rng.choice(choices, pixels, p=[0.2, 0.3, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05, 0.05]) for _ in range(samples)]
    f = RankFilter(pixels)
    for ids in passes:
        f.add(ids)
    pixels_out, written = f.result()
    every = np.stack(passes, 1)
    for p in range(pixels):
        seen, count = np.unique(every[p][every[p] != 0], return_counts=True)
        best = sorted(zip(-count, seen))[:6]           # coverage down, then the smaller id
        ids = [int(i) for _, i in best] + [0] * (6 - len(best))
        coverage = [-c / samples for c, _ in best] + [0.0] * (6 - len(best))
        assert list(pixels_out[p, 0::2].view(np.uint32)) == ids, p
        assert np.allclose(pixels_out[p, 1::2], coverage), p
    assert set(written.tolist()) == set(pixels_out[:, 0::2].view(np.uint32).ravel().tolist()) - {0}


def test_name_that_cannot_be_encoded_is_said_and_has_no_id():
    from usdml.render.mattes import MatteIds

    said = []
    ids = MatteIds(said.append)(["/World/ok", "/World/bad\ud800", "/World/bad\ud800"])
    assert ids[0] == struct.unpack("<I", struct.pack("<f", spec_id("/World/ok")))[0]
    assert list(ids[1:]) == [0, 0, 0]
    assert len(said) == 1 and "/World/bad" in said[0]


def test_no_component_and_no_material_are_said_once(new_stage, tmp_path, capsys):
    stage = new_stage("plain.usda", start=1)
    _ortho_camera(stage, 16, 4)
    _rect(stage, "/World/Right", [XE, XR])
    stage.Save()
    out = _render(stage.GetRootLayer().realPath, tmp_path / "plain.#.exr", "CryptoAsset,CryptoMaterial",
                  extra=("--frames", "1,2"))
    said = capsys.readouterr().err.splitlines()
    assert sum("CryptoAsset has no ids" in m for m in said) == 1 and sum("CryptoMaterial has no ids" in m for m in said) == 1
    for frame in (1, 2):
        assert Cryptomatte(str(out).replace("#", str(frame)), "CryptoAsset").manifest == {}


def test_a_moving_object_matte_is_its_motion_blurred_coverage(tmp_path):
    """Motion blur: each pass ranks what its ray hit at its time, so a quad sweeping across the shutter has a
    matte equal to its blurred alpha, and to the sweep's own coverage (tools/final_frames_accuracy.py)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
    from final_frames_accuracy import blur_stage, swept

    path = blur_stage(tmp_path / "sweep.usda", "xform", 8.0, 1.0, (-0.25, 0.25))
    _render(path, tmp_path / "sweep.####.exr", "CryptoObject,color", width=48, samples=64, extra=("--frames", "2"))
    out = tmp_path / "sweep.0002.exr"
    c = Cryptomatte(out, "CryptoObject")
    assert set(c.manifest) == {"/box/quad"}
    with OpenEXR.File(str(out), separate_channels=True) as f:
        alpha = np.array(f.channels()["A"].pixels, np.float64)
    matte = c.matte("/box/quad")
    assert np.abs(matte - alpha).max() < 1e-6
    band = slice(alpha.shape[0] // 2 - 2, alpha.shape[0] // 2 + 2)      # rows inside the quad
    assert np.abs(matte[band] - swept(48, 8.0, 1.0, (-0.25, 0.25))[None, :]).mean() < 0.03
