"""Anti-aliasing: ``--pixel-samples N`` correlated multi-jittered primary rays per pixel, box filter (issue 18, item 4).

References: pixel coverage of a straight edge integrated numerically on a fine grid (no usdml code),
and the geometry of the stage itself for the AOVs taken from the ray nearest the pixel centre.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from conftest import add_cube_mesh, add_quad
from usdml.cli import main
from usdml.params import PARAMS
from usdml.render.frame import FrameRenderer
from usdml.render.sampling import pixel_offsets
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate
from usdml.errors import UsdmlError

W, H = 40, 30
FOCAL, APERTURE_X, APERTURE_Y = 20.0, 36.0, 27.0
DEPTH = 10.0


def _edge_stage(new_stage):
    """A triangle in the plane z = -DEPTH in front of a camera at the origin looking down -Z: its
    long edge runs diagonally across the whole film. Returns the stage path and the triangle's film
    corners in pixels."""
    stage = new_stage(start=1, end=1)
    tri = [(-20.0, -12.0, -DEPTH), (20.0, -12.0, -DEPTH), (-20.0, 9.0, -DEPTH)]
    mesh = UsdGeom.Mesh.Define(stage, "/World/tri")
    mesh.CreatePointsAttr(tri)
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(APERTURE_X)
    cam.CreateVerticalApertureAttr(APERTURE_Y)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100))
    stage.Save()
    # pinhole projection, by hand: film mm = F·X/−Z, pixel = (ndc + 1)/2 · W, rows from the top
    px = [((FOCAL * x / DEPTH) / (APERTURE_X / 2) + 1) / 2 * W for x, _, _ in tri]
    py = [(1 - (FOCAL * y / DEPTH) / (APERTURE_Y / 2)) / 2 * H for _, y, _ in tri]
    return stage.GetRootLayer().realPath, np.array([px, py]).T


def _coverage(corners: np.ndarray, fine: int = 64) -> np.ndarray:
    """Fraction of each pixel inside the triangle, by a fine x fine grid of point tests per pixel."""
    u = (np.arange(W * fine) + 0.5) / fine
    v = (np.arange(H * fine) + 0.5) / fine
    x, y = np.meshgrid(u, v)
    inside = np.ones_like(x, bool)
    for k in range(3):
        a, b, c = corners[k], corners[(k + 1) % 3], corners[(k + 2) % 3]
        side = lambda px, py: (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])  # noqa: E731
        inside &= np.sign(side(x, y)) == np.sign(side(*c))
    return inside.reshape(H, fine, W, fine).mean(axis=(1, 3))


def _render(path, samples, aovs=("color",), seed=0):
    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=samples, seed=seed))
    try:
        return r.render(d.start_time, W, H, set(aovs)).buffers
    finally:
        r.close()


def test_alpha_converges_to_the_pixel_coverage_of_an_edge(new_stage):
    path, corners = _edge_stage(new_stage)
    truth = _coverage(corners)
    edge = (truth > 0) & (truth < 1)
    assert edge.sum() > 40
    rmse = {n: float(np.sqrt(((_render(path, n)["color"][..., 3] - truth)[edge] ** 2).mean())) for n in (1, 4, 16, 64)}
    # measured 0.239 / 0.117 / 0.042 / 0.0145: a jittered grid's N^-0.75 on a diagonal edge
    assert rmse[1] > 0.2
    assert rmse[4] < 0.14 and rmse[16] < 0.05 and rmse[64] < 0.018
    inside = truth == 1
    assert (_render(path, 16)["color"][..., 3][inside] == 1).all()


def test_offsets_are_stratified_in_cells_and_in_thin_rows_and_columns():
    passes = np.stack(list(pixel_offsets(5, 3, 16, seed=4)), axis=1)      # (pixels, 16, 2)
    assert passes.min() >= 0 and passes.max() < 1
    for p in passes:
        cells = (p * 4).astype(int)
        assert len({(a, b) for a, b in cells}) == 16
        assert sorted((p[:, 0] * 16).astype(int)) == list(range(16))
        assert sorted((p[:, 1] * 16).astype(int)) == list(range(16))
    assert not np.allclose(passes[0], passes[1])            # each pixel its own pattern
    assert np.array_equal(np.concatenate(list(pixel_offsets(2, 2, 1, 0))), np.full((4, 2), 0.5))


def test_offsets_are_correlated_multi_jittered_as_every_text_says():
    """Issue 55, item 11a: ``--help`` said "an s x s stratified grid", the README "correlated multi-jittered". The
    offsets are Kensler's correlated multi-jittered pattern: beyond one ray per cell and per thin row and column
    (above), the rays of a grid row share one sub-column and those of a grid column one sub-row (one permutation
    per pixel, shared by the rows: the "correlated"); the help, the schema and the README say so."""
    s = 4
    passes = np.stack(list(pixel_offsets(5, 3, s * s, seed=7)), axis=1)      # (pixels, 16, 2)
    cells, subs = (passes * s).astype(int), (passes * s * s).astype(int) % s
    for cell, sub in zip(cells, subs):
        for k in range(s):
            assert len(set(sub[cell[:, 1] == k, 0])) == 1                   # row k: one sub-column
            assert len(set(sub[cell[:, 0] == k, 1])) == 1                   # column k: one sub-row
    row = PARAMS["pixel_samples"]
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = next(t for t in readme.splitlines() if "**Final frames**" in t)
    for text in (row.help, row.doc, line):
        assert "correlated multi-jittered" in text and "stratified" not in text, text


def _box_on_ground(new_stage):
    stage = new_stage(start=1, end=1)
    add_quad(stage, "/World/ground", size=40)
    box = add_cube_mesh(stage, "/World/box", size=2)
    box.CreateSubdivisionSchemeAttr("none")
    box.AddTranslateOp().Set((0, 1, 0))
    s = UsdLux.SphereLight.Define(stage, "/World/bulb")
    s.CreateTreatAsPointAttr(True)
    s.CreateIntensityAttr(500)
    s.AddTranslateOp().Set((4, 6, 3))
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(30)
    cam.AddTranslateOp().Set((0, 4, 9))
    cam.AddRotateXOp().Set(-22)
    stage.Save()
    return stage.GetRootLayer().realPath


def test_depth_positions_and_ids_come_from_one_ray_not_a_blend(new_stage):
    path = _box_on_ground(new_stage)
    b = _render(path, 16, ("color", "P", "depth", "primId", "shadow"))
    alpha, p = b["color"][..., 3], b["P"].astype(np.float64)
    hit = b["primId"] >= 0
    # a point on the ground (y = 0) or on the box's surface (Chebyshev distance 1 from its centre)
    on_ground = np.abs(p[..., 1]) < 1e-4
    on_box = np.abs(np.abs(p - [0.0, 1.0, 0.0]).max(-1) - 1.0) < 1e-4
    assert hit.mean() > 0.9 and (on_ground | on_box)[hit].all()
    assert set(np.unique(b["primId"])) <= {-1, 0, 1}
    # where the box's silhouette crosses the ground, filtered AOVs blend, the rest does not
    boundary = np.zeros_like(hit)
    boundary[1:-1, 1:-1] = (b["primId"][1:-1, 1:-1] != b["primId"][:-2, 1:-1]) | \
                           (b["primId"][1:-1, 1:-1] != b["primId"][2:, 1:-1])
    assert boundary.sum() > 10
    assert (np.isfinite(b["depth"]) == hit).all()
    shadow_levels = np.unique(b["shadow"])
    assert len(shadow_levels) > 3 and ((shadow_levels > 0) & (shadow_levels < 1)).any()


def test_pixel_samples_are_deterministic_for_a_seed(new_stage):
    path = _box_on_ground(new_stage)
    a, again, other = (_render(path, 4, ("color", "shadow"), seed=s) for s in (3, 3, 4))
    assert all(np.array_equal(a[k], again[k]) for k in a)
    assert not np.array_equal(a["color"], other["color"])


def test_pixel_samples_from_the_schema_and_the_command_line(new_stage, tmp_path):
    from usdml.aov.exr import read_exr

    from pxr import Usd, UsdRender

    path = _box_on_ground(new_stage)
    stage = Usd.Stage.Open(path)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.GetPrim().ApplyAPI("UsdmlRenderSettingsAPI")
    settings.GetPrim().GetAttribute("usdml:pixelSamples").Set(1)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    assert main(["-q", "render", path, str(tmp_path / "one.exr"), "--imageWidth", "32"]) == 0
    alpha = read_exr(tmp_path / "one.exr")[0]["color"][..., 3]
    assert set(np.unique(alpha)) <= {0.0, 1.0}
    assert main(["-q", "render", path, str(tmp_path / "aa.exr"), "--imageWidth", "32", "--pixel-samples", "9"]) == 0
    alpha = read_exr(tmp_path / "aa.exr")[0]["color"][..., 3]
    assert ((alpha > 0) & (alpha < 1)).any()


@pytest.mark.parametrize("bad", [0, 2, 8, 2048])
def test_pixel_samples_must_be_a_square(bad):
    with pytest.raises(UsdmlError, match="square number"):
        UsdmlSettings(pixel_samples=bad)
