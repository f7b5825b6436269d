"""Depth of field: a thin lens from the camera's focalLength, fStop and focusDistance (usdml.render.lens).

The reference is the thin lens's own geometry, from the optics and sharing no usdml code
(``tools/final_frames_accuracy.py``'s ``disk_blur``, and its stage): a point
of the plane at depth D, seen through a lens of radius r focused at F, is spread over a disk of radius
r·|D/F − 1| on that plane around where the pinhole ray meets it; a half-plane's edge is therefore blurred into
the disk's area fraction beyond the edge (a circular segment), averaged over the pixel.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdRender

from usdml.render.frame import FrameRenderer
from usdml.render.lens import concentric_disk, lens_points
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
from final_frames_accuracy import disk_blur as tool_disk_blur, edge_stage as tool_edge_stage  # noqa: E402

FOCAL, APERTURE, DEPTH = 100.0, 10.0, 1000.0       # lens units (mm in a centimetre stage); the plane 10 m away


def edge_stage(path, f_stop=1.0, focus=300.0, render_settings=None):
    """A centimetre stage: a camera at the origin looking down -Z, a plane at depth DEPTH filling x < 0
    (the tool's), and, with ``render_settings``, RenderSettings whose disableDepthOfField is that."""
    path = tool_edge_stage(path, FOCAL, f_stop, focus, DEPTH, APERTURE)
    if render_settings is not None:
        s = Usd.Stage.Open(path)
        UsdRender.Settings.Define(s, "/Render/settings").CreateDisableDepthOfFieldAttr(render_settings)
        s.SetMetadata("renderSettingsPrimPath", "/Render/settings")
        s.Save()
    return path


def coverage(path, width, samples, **settings):
    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=samples, **settings))
    try:
        return r.render(d.start_time, width, width // 2, {"color"}).buffers["color"][..., 3].astype(np.float64)
    finally:
        r.close()


def disk_blur(width, f_stop=1.0, focus=300.0):
    return tool_disk_blur(width, FOCAL, f_stop, focus, DEPTH, APERTURE)


def test_an_out_of_focus_edge_is_the_thin_lens_disk_blur(tmp_path):
    path = edge_stage(tmp_path / "edge.usda")
    got = coverage(path, 96, 64)
    want = disk_blur(96)
    assert ((want > 0.02) & (want < 0.98)).sum() >= 16        # the blur spans many pixels
    profile = np.abs(got.mean(axis=0) - want)           # the edge's profile: its 48 rows averaged
    assert profile.max() <= 0.05, profile.max()
    err = np.abs(got - want[None, :])                   # each pixel: 64 stratified samples' noise
    assert err.mean() <= 0.01 and err.max() <= 0.1, (err.mean(), err.max())
    sharp = coverage(path, 96, 64, depth_of_field=False)        # --no-depth-of-field: the pinhole's hard edge
    assert np.abs(sharp - want[None, :]).max() > 0.4
    assert set(np.unique(sharp[:, np.abs(np.arange(96) - 47.5) > 1])) == {0.0, 1.0}


def test_the_plane_in_focus_is_sharp_and_fstop_zero_is_a_pinhole(tmp_path):
    focused = coverage(edge_stage(tmp_path / "f.usda", focus=DEPTH), 96, 16)
    pinhole = coverage(edge_stage(tmp_path / "p.usda", f_stop=0.0), 96, 16)
    np.testing.assert_array_equal(focused, pinhole)
    assert set(np.unique(pinhole[:, :40])) == {1.0} and set(np.unique(pinhole[:, 56:])) == {0.0}


def test_render_settings_disable_depth_of_field(tmp_path):
    off = coverage(edge_stage(tmp_path / "off.usda", render_settings=True), 64, 4)
    on = coverage(edge_stage(tmp_path / "on.usda", render_settings=False), 64, 4)
    assert set(np.unique(off[:, np.abs(np.arange(64) - 31.5) > 1])) == {0.0, 1.0}
    assert not np.array_equal(on, off)


def test_lens_points_are_stratified_and_seeded():
    points = np.stack(list(lens_points(3, 2, 16, seed=5)), axis=1)      # (pixels, passes, 2)
    assert np.all(np.hypot(points[..., 0], points[..., 1]) <= 1.0 + 1e-12)
    again = np.stack(list(lens_points(3, 2, 16, seed=5)), axis=1)
    np.testing.assert_array_equal(points, again)
    # the square's points before the disk map: one in each of the 4 x 4 cells, per pixel
    r = np.hypot(points[..., 0], points[..., 1])
    assert np.all(np.abs(np.mean(r ** 2, axis=1) - 0.5) < 0.15)         # E[r²] = ½ on the unit disk
    quads = np.sign(points[..., 0]) + 2 * np.sign(points[..., 1])
    for row in quads:                                                   # each quadrant four times
        assert sorted(np.unique(row, return_counts=True)[1]) == [4, 4, 4, 4]


def test_concentric_map_preserves_area():
    u = np.random.default_rng(1).random((200000, 2))
    p = concentric_disk(u)
    r2 = (p ** 2).sum(1)
    assert r2.max() <= 1 + 1e-12
    assert abs((r2 < 0.25).mean() - 0.25) < 0.005        # uniform: a quarter of the points within radius ½


@pytest.mark.parametrize("attr,value,message", [
    ("fStop", -2.0, r"/cam\.fStop: -2 at time .* must be finite and >= 0"),
    ("focusDistance", -1.0, r"/cam\.focusDistance: -1 at time .* must be finite and >= 0"),
])
def test_a_negative_lens_is_one_line(tmp_path, attr, value, message):
    path = edge_stage(tmp_path / "bad.usda")
    s = Usd.Stage.Open(path)
    s.GetPrimAtPath("/cam").GetAttribute(attr).Set(value)
    s.Save()
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "render", path, str(tmp_path / "out.exr"),
                          "--imageWidth", "16"], capture_output=True, text=True)
    assert run.returncode == 2
    lines = [line for line in run.stderr.splitlines() if line.startswith("usdml: error:")]
    assert len(lines) == 1 and "Traceback" not in run.stderr
    import re
    assert re.search(message, lines[0]), lines[0]


def test_focus_distance_zero_with_an_fstop_says_so_once(tmp_path, warnings_log):
    path = edge_stage(tmp_path / "nofocus.usda", focus=0.0)
    coverage(path, 32, 4)
    said = [m for m in warnings_log.messages if "focusDistance" in m]
    assert len(said) == 1 and "rendered sharp" in said[0]
