"""Lights the camera sees (issue 52, item 5; docs/visible-lights.md): the dome behind the geometry at each pixel's
direction, rect / disk / sphere / cylinder lights in front of it showing their radiance (one-sided ones from the
front only), PointInstancer-instanced lights, alpha, and ``--no-visible-lights`` giving the frame without them.

The references share no usdml code: each pixel centre's ray is computed here from the camera's USD attributes,
the dome's texel is looked up here from USD's own transform of the dome, and the light shapes are intersected
here.
"""

import math

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux

from conftest import add_cube_mesh
from usdml.aov.names import aov_for_render_var
from usdml.cli import main
from usdml.render.frame import blank_frame
from usdml.scene import Camera

pytest.importorskip("embreex")

W, H = 96, 64           # the camera's 36 x 24 aperture: no conforming


def _camera(stage, position=(0.0, 0.0, 10.0), rotate_y=0.0):
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(20)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(24)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000))
    cam.AddTranslateOp().Set(position)
    cam.AddRotateYOp().Set(rotate_y)
    return cam


def _rays(stage) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre rays ``(eye (3,), unit directions (H, W, 3))`` from the camera's USD attributes."""
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/main_cam"))
    m = np.array(cam.ComputeLocalToWorldTransform(1), np.float64)          # row vectors
    focal = cam.GetFocalLengthAttr().Get()
    x = ((np.arange(W) + 0.5) / W - 0.5) * cam.GetHorizontalApertureAttr().Get()
    y = (0.5 - (np.arange(H) + 0.5) / H) * cam.GetVerticalApertureAttr().Get()
    d = np.stack(np.broadcast_arrays(x[None, :], y[:, None], -focal), axis=-1)
    d = d @ m[:3, :3]
    return m[3, :3], d / np.linalg.norm(d, axis=-1, keepdims=True)


def _render(path, tmp_path, *flags, aovs="color,emission,background,depth") -> dict[str, np.ndarray]:
    """Render the stage's frame 1 to an EXR and read it back with OpenImageIO: layer -> (H, W, C) float64."""
    import OpenImageIO as oiio

    out = tmp_path / f"frame{len(list(tmp_path.glob('*.exr')))}.exr"
    assert main(["render", str(path), str(out), "--imageWidth", str(W), "--pixel-samples", "1",
                 "--aovs", aovs, *flags]) == 0
    image = oiio.ImageInput.open(str(out))
    names = list(image.spec().channelnames)
    pixels = image.read_image(0, 0, 0, len(names), oiio.FLOAT)
    image.close()
    layers = {}
    for i, name in enumerate(names):
        layer = name.split(".")[0] if "." in name else ("color" if name in "RGBA" else name)
        layers.setdefault(layer, []).append(pixels[..., i])
    return {k: np.stack(v, axis=-1).astype(np.float64) for k, v in layers.items()}


def _surface(b) -> np.ndarray:
    """(H, W) bool: the pixel's ray hit a surface (a finite depth)."""
    return np.isfinite(b["Z"][..., 0])


def _write_map(path, texels: np.ndarray) -> str:
    import OpenImageIO as oiio

    h, w, c = texels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, oiio.FLOAT))
    assert out.write_image(texels.astype(np.float32))
    out.close()
    return str(path)


# ------------------------------------------------------------------------------------------------ the dome

def test_dome_seen_behind_geometry_at_each_pixels_direction(new_stage, tmp_path):
    """Each background pixel shows the dome's texel in its direction (USD's dome transform, the lat-long map of
    UsdLux: top row +Y, centre column +Z, quarter column +X), times the dome's intensity; alpha 1 everywhere; a
    rect light in front of the cube shows its radiance, over both."""
    rng = np.random.default_rng(7)
    tw, th = 16, 8
    texels = rng.uniform(0.1, 1.0, (th, tw, 3))
    stage = new_stage(start=1, end=1)
    add_cube_mesh(stage, "/World/box", size=2.0)
    _camera(stage, position=(1.0, 0.5, 8.0), rotate_y=25.0)
    dome = UsdLux.DomeLight.Define(stage, "/World/sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath(_write_map(tmp_path / "sky.exr", texels)))
    dome.CreateIntensityAttr(2.0)
    UsdGeom.Xformable(dome).AddRotateYOp().Set(70.0)
    UsdGeom.Xformable(dome).AddRotateXOp().Set(15.0)
    rect = UsdLux.RectLight.Define(stage, "/World/panel")
    rect.CreateWidthAttr(0.6)
    rect.CreateHeightAttr(0.6)
    rect.CreateIntensityAttr(5.0)
    rect.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    rect.AddTranslateOp().Set((0.0, 0.0, 2.0))          # in front of the box's +Z face
    rect.AddRotateYOp().Set(180.0)                      # its -Z axis (the emitting side) toward +Z, the camera
    stage.Save()

    b = _render(stage.GetRootLayer().realPath, tmp_path)
    eye, d = _rays(stage)
    m = np.array(UsdGeom.Xformable(dome).ComputeLocalToWorldTransform(1), np.float64)[:3, :3]
    local = d @ np.linalg.inv(m)                        # row vectors: world = local @ m
    phi = np.arctan2(local[..., 0], local[..., 2])      # longitude, 0 at +Z, +π/2 at +X
    u = (1.0 - phi / np.pi) / 2.0 * tw
    v = np.arccos(np.clip(local[..., 1], -1, 1)) / np.pi * th
    want = 2.0 * texels[np.clip(v.astype(int), 0, th - 1), u.astype(int) % tw]
    sky = ~_surface(b)
    clear = sky & (np.abs(u - np.round(u)) > 1e-3) & (np.abs(v - np.round(v)) > 1e-3)
    clear &= b["emission"].max(-1) == 0
    assert clear.sum() > 0.3 * W * H
    assert np.allclose(b["background"][clear], want[clear], rtol=2e-3)
    assert np.allclose(b["color"][clear][:, :3], want[clear], rtol=2e-3)
    assert (b["color"][..., 3] == 1).all()              # a visible dome: alpha 1 everywhere
    assert (b["background"][~sky] == 0).all()
    panel = b["emission"].max(-1) > 0
    assert panel.sum() > 4 and not _surface(b)[panel].any()
    assert np.allclose(b["color"][panel][:, :3], [5.0, 2.5, 1.25], rtol=1e-3)
    assert (b["background"][panel] == 0).all()

    off = _render(stage.GetRootLayer().realPath, tmp_path, "--no-visible-lights")
    assert (off["color"][sky & ~panel] == 0).all() and (off["background"] == 0).all()
    assert (off["color"][..., 3] == (_surface(off))).all()


# ------------------------------------------------------------------------------------------ area lights

#: name -> (kind, translate, rotateY, size attributes, intensity, color)
SHAPES = {
    "front_rect": ("RectLight", (-3.0, 1.5, 0.0), 155.0, {"width": 1.5, "height": 1.0}, 3.0, (1.0, 0.5, 0.25)),
    "back_rect": ("RectLight", (3.0, 1.5, 0.0), 0.0, {"width": 1.5, "height": 1.0}, 7.0, (1.0, 1.0, 1.0)),
    "disk": ("DiskLight", (-3.0, -1.5, 0.0), 200.0, {"radius": 0.6}, 4.0, (0.25, 1.0, 0.5)),
    "sphere": ("SphereLight", (0.0, 0.0, 0.0), 0.0, {"radius": 0.8}, 2.0, (0.5, 0.5, 1.0)),
    "tube": ("CylinderLight", (3.0, -1.5, 0.0), 30.0, {"radius": 0.3, "length": 2.0}, 6.0, (1.0, 0.8, 0.6)),
}


def _shape_distance(kind, centre, rot_y, size, eye, d, grow):
    """(H, W) distance along the pixel rays to the emitting side of one light (inf: missed), its size times
    ``grow`` (the rays' own maths, not usdml's)."""
    a = math.radians(rot_y)
    ex = np.array([math.cos(a), 0.0, -math.sin(a)])    # the light's X and Z after rotateY
    ez = np.array([math.sin(a), 0.0, math.cos(a)])
    ey = np.array([0.0, 1.0, 0.0])
    oc = eye - np.asarray(centre)
    if kind in ("RectLight", "DiskLight"):
        facing = d @ ez                                 # the ray must run against the emitting -Z axis
        t = -(oc @ ez) / np.where(facing > 0, facing, 1)
        p = oc + t[..., None] * d
        x, y = p @ ex, p @ ey
        if kind == "RectLight":
            inside = (abs(x) <= grow * size["width"] / 2) & (abs(y) <= grow * size["height"] / 2)
        else:
            inside = x * x + y * y <= (grow * size["radius"]) ** 2
        return np.where((facing > 0) & inside, t, np.inf)
    r = grow * size["radius"]
    if kind == "SphereLight":
        b = d @ oc
        disc = b * b - (oc @ oc - r * r)
        return np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    # cylinder along X: solve |(oc + t d) - ((oc + t d)·ex) ex| = r, then |x| <= length / 2
    dp = d - (d @ ex)[..., None] * ex
    op = oc - (oc @ ex) * ex
    a2, b, c = (dp * dp).sum(-1), dp @ op, op @ op - r * r
    disc = b * b - a2 * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a2
    along = oc @ ex + t * (d @ ex)
    return np.where((disc >= 0) & (abs(along) <= grow * size["length"] / 2), t, np.inf)


def _area_stage(new_stage, instanced=False):
    stage = new_stage(start=1, end=1)
    wall = UsdGeom.Mesh.Define(stage, "/World/wall")      # behind the right half only
    wall.CreatePointsAttr([(1, -4, -3), (8, -4, -3), (8, 4, -3), (1, 4, -3)])
    wall.CreateFaceVertexCountsAttr([4])
    wall.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    _camera(stage, position=(0.0, 0.0, 6.0))
    for name, (kind, at, rot, size, intensity, color) in SHAPES.items():
        light = getattr(UsdLux, kind).Define(stage, f"/World/{name}")
        for attr, value in size.items():
            light.GetPrim().CreateAttribute(f"inputs:{attr}", Sdf.ValueTypeNames.Float).Set(value)
        light.CreateIntensityAttr(intensity)
        light.CreateColorAttr(Gf.Vec3f(*color))
        UsdGeom.Xformable(light).AddTranslateOp().Set(at)
        UsdGeom.Xformable(light).AddRotateYOp().Set(rot)
    stage.Save()
    return stage


def test_area_lights_seen_with_their_radiance_one_sided_from_the_front(new_stage, tmp_path):
    """Rect, disk, sphere and cylinder lights show L = intensity · color where the pixel's ray meets them first;
    a rect seen from behind is not there (the wall behind it shows); no surface on a light's pixels
    (depth inf); alpha 1 on the lights, 0 on the empty pixels; flag off: today's frame (alpha = a surface, no
    emission), the surfaces' colour unchanged."""
    stage = _area_stage(new_stage)
    b = _render(stage.GetRootLayer().realPath, tmp_path)
    eye, d = _rays(stage)
    want = np.zeros((H, W, 3))
    sure = np.ones((H, W), bool)            # pixels whose centre is not within 0.1 % of a shape's edge
    nearest = np.full((H, W), np.inf)
    for name, (kind, at, rot, size, intensity, color) in SHAPES.items():
        t = _shape_distance(kind, at, rot, size, eye, d, 1.0)
        sure &= np.isfinite(_shape_distance(kind, at, rot, size, eye, d, 0.999)) == \
            np.isfinite(_shape_distance(kind, at, rot, size, eye, d, 1.001))
        closer = t < nearest
        want[closer] = intensity * np.asarray(color)
        nearest = np.minimum(nearest, t)
    on = np.isfinite(nearest)
    assert on[sure].sum() > 60
    assert np.allclose(b["emission"][sure], want[sure], rtol=1e-3)
    assert np.allclose(b["color"][sure & on][:, :3], want[sure & on], rtol=1e-3)
    assert (b["color"][sure & on][:, 3] == 1).all()
    assert not _surface(b)[sure & on].any()
    wall = _surface(b)
    assert (b["color"][sure & ~on & ~wall] == 0).all()             # nothing there, no dome: alpha 0
    # the back of the rect at (3, 1.5): the wall shows through
    back = _shape_distance("RectLight", (3.0, 1.5, 0.0), 180.0, SHAPES["back_rect"][3], eye, d, 0.9)
    assert np.isfinite(back).sum() > 4 and wall[np.isfinite(back)].all()

    off = _render(stage.GetRootLayer().realPath, tmp_path, "--no-visible-lights")
    surface = _surface(off)
    assert (off["emission"] == 0).all() and (off["color"][..., 3] == surface).all()
    assert (off["color"][~surface] == 0).all() and surface[np.isfinite(back)].all()
    assert np.array_equal(off["color"][wall & ~on], b["color"][wall & ~on])


def test_point_instanced_rect_lights_are_seen(new_stage, tmp_path):
    """A PointInstancer of a rect light facing the camera: every instance shows L at its place, scaled."""
    stage = new_stage(start=1, end=1)
    add_cube_mesh(stage, "/World/box", size=0.5)
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/box")).AddTranslateOp().Set((0, -2.5, -2))
    _camera(stage)
    pi = UsdGeom.PointInstancer.Define(stage, "/World/panels")
    proto = UsdLux.RectLight.Define(stage, "/World/panels/proto/panel")
    proto.CreateWidthAttr(0.5)
    proto.CreateHeightAttr(0.5)
    proto.CreateIntensityAttr(3.0)
    proto.AddRotateYOp().Set(180.0)
    pi.CreatePrototypesRel().SetTargets([Sdf.Path("/World/panels/proto")])
    at = [(-3.0, 0.0, 0.0), (0.0, 1.0, 0.0), (3.0, 0.0, 0.0)]
    pi.CreatePositionsAttr(at)
    pi.CreateScalesAttr([(1, 1, 1), (2, 2, 1), (1, 1, 1)])
    pi.CreateProtoIndicesAttr([0, 0, 0])
    stage.Save()
    b = _render(stage.GetRootLayer().realPath, tmp_path)
    eye, d = _rays(stage)
    lit = b["emission"][..., 0] > 0
    for (x, y, z), s in zip(at, (1, 2, 1)):
        t = _shape_distance("RectLight", (x, y, z), 180.0, {"width": 0.5 * s, "height": 0.5 * s}, eye, d, 0.98)
        assert np.isfinite(t).sum() > 2 and np.allclose(b["emission"][np.isfinite(t)], 3.0, rtol=1e-3)
    grown = [np.isfinite(_shape_distance("RectLight", p, 180.0, {"width": 0.5 * s, "height": 0.5 * s}, eye, d, 1.1))
             for p, s in zip(at, (1, 2, 1))]
    assert not (lit & ~np.logical_or.reduce(grown)).any()


# ---------------------------------------------------------------------------------------- names, words

def test_render_vars_and_blank_frame_name_what_is_seen():
    assert aov_for_render_var("background").name == "background"
    assert aov_for_render_var("CB", "lpe").name == "background"
    assert aov_for_render_var("C[LO]", "lpe").name == "emission"
    cam = Camera("/cam", np.eye(4), 20.0, 36.0, 24.0)
    assert blank_frame(False, True, False, 1, cam, seen=True).startswith("shows no geometry, only lights")
    assert blank_frame(False, False, False, 1, cam).startswith("is empty (alpha 0 everywhere)")
