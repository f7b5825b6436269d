"""Light linking, shadow linking, light groups and per-lobe light factors (issue 52 items 1 and 2).

Membership is checked against USD's own ``UsdCollectionAPI`` (includes, excludes, includeRoot false, nested prims,
native and PointInstancer instances); the rendered effect against a closed form (a point light over a ground:
Lambert and the inverse square); light groups against ``direct``; bad input gives one line and the frame renders.
The pixel-level comparison with an independent ray caster is tests/test_linking_reference.py.
"""

import math

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from conftest import ALBEDO, add_cube_mesh, add_quad, add_top_camera
from usdml.cli import main
from usdml.lighting.vpl import generate_vpls
from usdml.render.frame import FrameRenderer
from usdml.scene.linking import EVERY_PRIM
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate
from usdml.visibility import ExactBackend
from usdml.scene import diff

#: the point light over the ground: position, inputs:intensity (treatAsPoint, radius R: I = intensity·π·R²)
BULB, POWER, R = (0.0, 6.0, 0.0), 5000.0, 0.1


def _box(stage, path, centre, size=1.0, color=(0.5, 0.5, 0.5)):
    """conftest's cube of edge ``size``, moved to ``centre``, of albedo ``color``."""
    m = add_cube_mesh(stage, path, size)
    m.AddTranslateOp().Set(tuple(map(float, centre)))
    m.CreateDisplayColorPrimvar().Set([color])
    return m


def _bulb(stage, path, position=BULB, power=POWER, group=None):
    s = UsdLux.SphereLight.Define(stage, path)
    s.CreateTreatAsPointAttr(True)
    s.CreateRadiusAttr(R)
    s.CreateIntensityAttr(power)
    s.AddTranslateOp().Set(position)
    if group is not None:
        s.GetPrim().CreateAttribute("usdml:lightGroup", Sdf.ValueTypeNames.String).Set(group)
    return s


def _collection(light, which: str, includes=(), excludes=(), include_root=None):
    api = UsdLux.LightAPI(light.GetPrim())
    c = api.GetLightLinkCollectionAPI() if which == "light" else api.GetShadowLinkCollectionAPI()
    if include_root is not None:
        c.CreateIncludeRootAttr(include_root)
    for p in includes:
        c.GetIncludesRel().AddTarget(p)
    for p in excludes:
        c.GetExcludesRel().AddTarget(p)
    return c


def _scene(new_stage, build, name="s.usda"):
    stage = new_stage(name, start=1, end=1)
    add_quad(stage, "/World/ground", size=40).CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    add_top_camera(stage)
    build(stage)
    stage.Save()
    return stage.GetRootLayer().realPath


def _render(path, aovs=("direct", "P", "primId"), width=48, **settings):
    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, **settings))
    try:
        return r.render(d.start_time, width, width, set(aovs)).buffers
    finally:
        r.close()


def _lambert(p: np.ndarray, bulbs) -> np.ndarray:
    """albedo/π · Σ I·cosθ/d² on the ground (normal +Y) at ``(..., 3)`` points, no shadows."""
    out = 0.0
    for position, power in bulbs:
        d = np.asarray(position) - p
        d2 = (d * d).sum(-1)
        out = out + power * math.pi * R * R * np.maximum(d[..., 1], 0) / d2 ** 1.5
    return ALBEDO / math.pi * out


def test_membership_is_usd_collection_membership(new_stage):
    """Every rule of UsdCollectionAPI, as USD's own membership query answers it for each mesh and instance."""
    def build(stage):
        UsdGeom.Xform.Define(stage, "/World/props")
        _box(stage, "/World/props/a", (-3, 0.5, 0))
        _box(stage, "/World/props/b", (3, 0.5, 0))
        _box(stage, "/World/c", (0, 0.5, 3))
        stage.CreateClassPrim("/_asset")
        _box(stage, "/_asset/geo", (0, 0.5, 0), 0.5)
        for i, x in enumerate((-6.0, 6.0)):
            inst = UsdGeom.Xform.Define(stage, f"/World/inst{i}")
            inst.GetPrim().GetReferences().AddInternalReference("/_asset")
            inst.GetPrim().SetInstanceable(True)
            inst.AddTranslateOp().Set((x, 0, -5))
        pi = UsdGeom.PointInstancer.Define(stage, "/World/pi")
        _box(stage, "/World/pi/protos/cube", (0, 0.25, 0), 0.5)
        pi.CreatePrototypesRel().AddTarget("/World/pi/protos/cube")
        pi.CreatePositionsAttr([(-2.0, 0.0, 6.0), (2.0, 0.0, 6.0)])
        pi.CreateProtoIndicesAttr([0, 0])
        rules = {
            "only_props_but_b": dict(include_root=False, includes=["/World/props"], excludes=["/World/props/b"]),
            "all_but_c": dict(excludes=["/World/c"]),
            "one_instance": dict(include_root=False, includes=["/World/inst1"]),
            "instancer": dict(include_root=False, includes=["/World/pi"]),
        }
        for i, (name, rule) in enumerate(rules.items()):
            _collection(_bulb(stage, f"/World/{name}", (i, 6, 0)), "light", **rule)
        _collection(_bulb(stage, "/World/shade_c", (0, 7, 0)), "shadow", include_root=False, includes=["/World/c"])

    path = _scene(new_stage, build)
    d = StageDelegate(path)
    snap = d.snapshot(d.start_time)
    links = snap.links
    stage = Usd.Stage.Open(path)
    checked = 0
    for light_path, link in zip(snap.lights.paths, snap.lights.light_link):
        which = "shadowLink" if light_path.endswith("shade_c") else "lightLink"
        if which == "shadowLink":
            link = snap.lights.shadow_link[snap.lights.paths.index(light_path)]
        assert link != EVERY_PRIM
        query = Usd.CollectionAPI(stage.GetPrimAtPath(light_path), which).ComputeMembershipQuery()
        for m in snap.meshes:
            got = links.members(int(link), np.array([m.id]), np.array([-1]))[0]
            assert got == query.IsPathIncluded(Sdf.Path(m.path)), (light_path, m.path)
            checked += 1
        for p in snap.prototypes:
            for m in p.meshes:
                for inst, instancer in zip(p.instance_ids, p.instancers):
                    asked = (instancer + m.path[len(p.path):] if p.kind == "native" else m.path)
                    got = links.members(int(link), np.array([m.id]), np.array([inst]))[0]
                    assert got == query.IsPathIncluded(Sdf.Path(asked)), (light_path, asked)
                    checked += 1
    assert checked >= 5 * 7
    from usdml.info import stage_info

    info = stage_info(d)
    assert info["linkSets"] == len(links) >= 5 and info["lightGroups"] == ["default"]
    # two instances of one prototype, one in the collection: they differ
    one = snap.lights.light_link[snap.lights.paths.index("/World/one_instance")]
    native = next(p for p in snap.prototypes if p.kind == "native")
    answers = links.members(int(one), np.full(2, native.meshes[0].id), native.instance_ids)
    assert answers.tolist().count(True) == 1


def test_light_link_lights_only_its_prims_and_shadow_link_drops_shadows(new_stage):
    """A light linked to a box does not light the ground; a light whose shadow link leaves the box out is not
    shadowed by it: the ground is the closed form with no occluder."""
    def build(stage):
        _box(stage, "/World/box", (0, 2.0, 0), 2.0)
        linked = _bulb(stage, "/World/linked", (5.0, 6.0, 0.0))
        _collection(linked, "light", include_root=False, includes=["/World/box"])
        free = _bulb(stage, "/World/free")
        _collection(free, "shadow", excludes=["/World/box"])

    b = _render(_scene(new_stage, build))
    ids = b["primId"]
    p = b["P"].astype(np.float64)
    on_ground = np.abs(p[..., 1]) < 1e-4
    assert on_ground.sum() > 500
    want = _lambert(p[on_ground], [(BULB, POWER)])       # the free light only, unshadowed under the box
    got = b["direct"][on_ground][:, 0].astype(np.float64)
    rel = np.abs(got - want) / want
    assert rel.max() < 2e-3, rel.max()
    # the box is lit by both
    on_box = ~on_ground & (ids >= 0)
    assert b["direct"][on_box].max() > 0


def test_light_groups_add_up_to_direct_and_star_writes_each(new_stage, tmp_path):
    """``--aovs 'lightgroup:*'`` writes one layer per group the lights name (and ``default`` for the others); the
    groups add up to ``direct``; a group's layer is the closed form of its own light."""
    from usdml.aov.exr import read_exr

    bulbs = [((3.0, 5.0, 0.0), 3000.0, "key"), ((-3.0, 4.0, 1.0), 2000.0, "fill"), ((0.0, 7.0, -3.0), 4000.0, None)]

    def build(stage):
        for i, (pos, power, group) in enumerate(bulbs):
            _bulb(stage, f"/World/b{i}", pos, power, group)

    path = _scene(new_stage, build)
    out = tmp_path / "g.exr"
    assert main(["render", path, str(out), "--aovs", "direct,P,lightgroup:*", "--imageWidth", "32", "--pixel-samples", "1"]) == 0
    layers = read_exr(str(out))[0]
    groups = sorted(k for k in layers if k.startswith("lightgroup:"))
    assert groups == ["lightgroup:default", "lightgroup:fill", "lightgroup:key"]
    total = sum(layers[g].astype(np.float64) for g in groups)
    direct = layers["direct"].astype(np.float64)
    assert np.abs(total - direct).max() <= 2e-3 * direct.max()
    p = layers["P"].astype(np.float64)
    for pos, power, group in bulbs:
        want = _lambert(p, [(pos, power)])
        got = layers[f"lightgroup:{group or 'default'}"][..., 0].astype(np.float64)
        assert np.abs(got - want).max() <= 2e-3 * want.max()      # half-float layers


def test_render_var_light_group_and_bad_group_name(new_stage, tmp_path, capsys):
    """A RenderVar ``sourceName "lightgroup:key"`` writes that group; a group name that is not an AOV name is
    said once and made one."""
    from pxr import UsdRender

    from usdml.aov.exr import read_exr

    out = tmp_path / "rv.exr"

    def build(stage):
        _bulb(stage, "/World/key", (2.0, 5.0, 0.0), 3000.0, "key")
        _bulb(stage, "/World/odd", (-2.0, 5.0, 0.0), 3000.0, "rim light!")
        settings = UsdRender.Settings.Define(stage, "/Render/settings")
        product = UsdRender.Product.Define(stage, "/Render/product")
        product.CreateProductNameAttr(str(out))
        for name, source in (("key_light", "lightgroup:key"), ("rim", "lightgroup:rim_light_"), ("direct", "direct")):
            var = UsdRender.Var.Define(stage, f"/Render/vars/{name}")
            var.CreateSourceNameAttr(source)
            var.CreateDataTypeAttr("color3f")
            product.CreateOrderedVarsRel().AddTarget(var.GetPath())
        settings.CreateProductsRel().AddTarget(product.GetPath())
        settings.CreateResolutionAttr(Gf.Vec2i(24, 24))
        stage.SetMetadata("renderSettingsPrimPath", "/Render/settings")

    assert main(["render", _scene(new_stage, build)]) == 0
    err = capsys.readouterr().err
    assert err.count("'rim light!' is not a valid AOV name") == 1
    layers = read_exr(str(out))[0]
    assert set(layers) == {"key_light", "rim", "direct"}
    total = layers["key_light"].astype(np.float64) + layers["rim"].astype(np.float64)
    assert np.abs(total - layers["direct"]).max() <= 2e-3 * layers["direct"].max()
    assert layers["rim"].max() > 0 and layers["key_light"].max() > 0


def test_collection_naming_a_missing_prim_is_one_line(new_stage, tmp_path, capsys):
    def build(stage):
        _collection(_bulb(stage, "/World/bulb"), "light", include_root=False, includes=["/World/nothing"])

    path = _scene(new_stage, build)
    assert main(["render", path, str(tmp_path / "m.exr"), "--imageWidth", "16"]) == 0
    err = capsys.readouterr().err
    assert err.count("/World/nothing does not exist") == 1
    assert "Traceback" not in err


def test_point_instanced_lights_take_their_prototype_light_collections(new_stage):
    """1,000 lights of two prototypes with different light links: each instance lights its prototype's prims
    only (the closed form of the instances of one prototype on the ground, none of the other's)."""
    rng = np.random.default_rng(3)
    positions = np.c_[rng.uniform(-15, 15, 1000), rng.uniform(3, 8, 1000), rng.uniform(-15, 15, 1000)]
    index = rng.integers(0, 2, 1000)

    def build(stage):
        UsdGeom.Xform.Define(stage, "/World/elsewhere")
        _box(stage, "/World/elsewhere/box", (30, 0.5, 30))     # out of view
        pi = UsdGeom.PointInstancer.Define(stage, "/World/lights")
        a = _bulb(stage, "/World/lights/protos/ground_light", (0, 0, 0), 40.0, "ground")
        b = _bulb(stage, "/World/lights/protos/box_light", (0, 0, 0), 40.0, "box")
        _collection(a, "light", include_root=False, includes=["/World/ground"])
        _collection(b, "light", include_root=False, includes=["/World/elsewhere"])
        pi.CreatePrototypesRel().SetTargets([a.GetPath(), b.GetPath()])
        pi.CreatePositionsAttr([tuple(p) for p in positions])
        pi.CreateProtoIndicesAttr(index.tolist())

    b = _render(_scene(new_stage, build), aovs=("direct", "P", "lightgroup:ground", "lightgroup:box"), width=24)
    p = b["P"].astype(np.float64)
    mask = np.abs(p[..., 1]) < 1e-4
    bulbs = [(tuple(pos), 40.0) for pos, k in zip(positions, index) if k == 0]
    want = _lambert(p[mask], bulbs)
    got = b["direct"][mask][:, 0].astype(np.float64)
    assert np.abs(got - want).max() <= 2e-3 * want.max()
    assert b["lightgroup:box"].max() == 0


@pytest.mark.parametrize("diffuse, specular", [(0.0, 1.0), (1.0, 0.0), (0.5, 2.0)])
def test_light_diffuse_and_specular_scale_their_lobes(new_stage, diffuse, specular):
    """``inputs:diffuse`` and ``inputs:specular`` scale the diffuse and specular AOVs of a glossy ground apart:
    against the same light at (1, 1)."""
    from pxr import UsdShade

    def build_with(d, s):
        def build(stage):
            material = UsdShade.Material.Define(stage, "/World/mat")
            shader = UsdShade.Shader.Define(stage, "/World/mat/surface")
            shader.CreateIdAttr("UsdPreviewSurface")
            shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
            shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.3)
            material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
            ground = stage.GetPrimAtPath("/World/ground")
            UsdShade.MaterialBindingAPI.Apply(ground).Bind(material)
            light = _bulb(stage, "/World/bulb", (2.0, 6.0, 1.0))
            light.CreateDiffuseAttr(d)
            light.CreateSpecularAttr(s)
        return build

    aovs = ("diffuse", "specular", "direct")
    plain = _render(_scene(new_stage, build_with(1.0, 1.0), "plain.usda"), aovs=aovs, width=24)
    scaled = _render(_scene(new_stage, build_with(diffuse, specular), "scaled.usda"), aovs=aovs, width=24)
    for lobe, factor in (("diffuse", diffuse), ("specular", specular)):
        want = plain[lobe].astype(np.float64) * factor
        assert np.abs(scaled[lobe] - want).max() <= 1e-4 * max(plain[lobe].max(), 1e-6) * max(factor, 1), lobe
    assert plain["specular"].max() > 0.05 * plain["diffuse"].max()


def test_vpls_land_only_on_the_prims_a_light_lights(new_stage):
    """``--gi``: a light linked to a box leaves its first VPLs on the box only (they light the rest as indirect
    light, as Cycles' receivers pass light on)."""
    def build(stage):
        _box(stage, "/World/box", (0, 1.0, 0), 2.0)
        _collection(_bulb(stage, "/World/bulb", (4.0, 1.5, 0.0)), "light", include_root=False,
                    includes=["/World/box"])

    d = StageDelegate(_scene(new_stage, build))
    snap = d.snapshot(d.start_time)
    exact = ExactBackend()
    exact.update(snap, diff(None, snap))
    vpls = generate_vpls(snap, exact, snap.lights, count=2000, bounces=2, seed=1)
    first = vpls.position[vpls.bounce == 1]
    assert len(first) > 100
    assert np.all(np.abs(first[:, [0, 2]]) <= 1 + 1e-5)     # all on the box (x, z in -1..1), none on the ground
    second = vpls.position[vpls.bounce == 2]
    assert np.any(np.abs(second[:, [0, 2]]).max(axis=1) > 1.5)     # the box's bounce reaches the ground
    exact.close()


def test_a_light_is_seen_with_its_own_radiance_whatever_its_lobe_factors(new_stage):
    """``inputs:diffuse`` scales what a light lights, not what the camera sees (Karma): a rect light facing the
    camera shows its L = intensity in ``emission``, and a dome its own radiance in ``background``."""
    from usdml.render.visible_lights import dome_seen
    from usdml.scene.dome import Dome

    def build(stage):
        rect = UsdLux.RectLight.Define(stage, "/World/panel")
        rect.CreateIntensityAttr(3.0)
        rect.CreateDiffuseAttr(0.5)
        rect.AddTranslateOp().Set((0.0, 5.0, 0.0))
        rect.AddRotateXOp().Set(90.0)        # its -Z (the emitting side) up, toward the camera
        dome = UsdLux.DomeLight.Define(stage, "/World/dome")
        dome.CreateIntensityAttr(0.7)
        dome.CreateDiffuseAttr(0.25)

    path = _scene(new_stage, build)
    b = _render(path, aovs=("emission", "direct"), width=32, visible_lights=True)
    seen = b["emission"][..., 0]
    assert (np.abs(seen - 3.0) < 1e-3).sum() >= 4          # the panel's pixels: L, not 0.5·L
    d = StageDelegate(path)
    snap = d.snapshot(d.start_time)
    dome = snap.domes[0]
    assert isinstance(dome, Dome)
    sky = dome_seen(snap.domes, np.array([[0.0, 1.0, 0.0]]), snap.links)
    np.testing.assert_allclose(sky, [[0.7, 0.7, 0.7]], rtol=1e-5)
