"""``usdml view``: off-screen pictures of a stage that are not blank (coverage and colours checked), the
render camera highlighted, bad flags one line; skipped cleanly where VTK cannot render off-screen."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from pxr import UsdLux

from conftest import STAGES, add_cube_mesh
from usdml.cli import main

pytest.importorskip("pyvista")


@pytest.fixture(scope="module")
def offscreen():
    from usdml.view import probe
    why = probe()
    if why:
        pytest.skip(why)


def _read(path):
    import OpenImageIO as oiio
    img = oiio.ImageInput.open(str(path))
    data = img.read_image("uint8")
    img.close()
    return np.asarray(data)[..., :3]


def test_view_draws_geometry_cameras_and_lights(offscreen, tmp_path, capsys):
    png = tmp_path / "cornell.png"
    assert main(["view", str(STAGES / "cornell.usda"), "--png", str(png), "--window-size", "320,200"]) == 0
    assert "lights 2" in capsys.readouterr().out
    img = _read(png)
    assert img.shape == (200, 320, 3)
    background = img[0, 0]
    covered = np.any(np.abs(img.astype(int) - background) > 8, axis=2).mean()
    assert 0.05 < covered < 0.95, covered                     # something drawn, not a filled frame
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50     # shaded, not flat
    # the render camera's frustum in its highlight colour (#ffd84a)
    assert (np.abs(img.astype(int) - [255, 216, 74]).max(axis=2) < 40).sum() > 20
    # the red and green walls by their albedo
    r, g, b = (img[..., k].astype(int) for k in range(3))
    assert ((r > 60) & (r > 2.5 * g) & (r > 2.5 * b)).sum() > 50
    assert ((g > 40) & (g > 2 * r) & (g > 2 * b)).sum() > 50


def test_instances_are_told_apart(offscreen, tmp_path):
    plain, inst = tmp_path / "a.png", tmp_path / "b.png"
    park = str(STAGES / "park.usda")
    assert main(["view", park, "--png", str(plain), "--show", "geometry", "--window-size", "240,160"]) == 0
    assert main(["view", park, "--png", str(inst), "--show", "geometry,instances", "--window-size", "240,160"]) == 0
    a, b = _read(plain), _read(inst)
    assert (np.abs(a.astype(int) - b).max(axis=2) > 30).mean() > 0.01     # the prototypes' colours show


def test_bad_view_flags_are_one_line(tmp_path, capsys):
    stage = str(STAGES / "cornell.usda")
    assert main(["view", stage, "--show", "teapots", "--png", str(tmp_path / "x.png")]) != 0
    assert "--show teapots" in capsys.readouterr().err
    assert main(["view", stage, "--window-size", "huge", "--png", str(tmp_path / "x.png")]) != 0
    assert "--window-size" in capsys.readouterr().err
    assert main(["view", stage]) != 0
    assert "--png" in capsys.readouterr().err
    assert main(["view", stage, "--octree-resolution", "12", "--png", str(tmp_path / "x.png")]) == 2
    assert "--octree-resolution 12: give a power of two" in capsys.readouterr().err


def _usdml_view(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "usdml.cli", "view", str(STAGES / "cornell.usda"), *map(str, argv)],
                          capture_output=True, text=True, timeout=300)


def test_the_old_voxel_resolution_name_is_refused_in_one_line(tmp_path):
    """On usdml render --voxel-resolution is the voxel arrays' resolution: usdml view does not take it as
    another name for --octree-resolution, and says so."""
    run = _usdml_view("--show", "voxels", "--voxel-resolution", "16", "--png", tmp_path / "x.png")
    assert run.returncode == 2, run.stderr
    assert run.stderr.startswith("usdml: error: usdml view: --voxel-resolution is now --octree-resolution")
    assert len(run.stderr.splitlines()) == 1 and not (tmp_path / "x.png").exists(), run.stderr


def test_octree_resolution_draws_the_voxels(offscreen, tmp_path):
    run = _usdml_view("--show", "voxels", "--octree-resolution", "8", "--png", tmp_path / "v.png",
                      "--window-size", "64,48")
    assert run.returncode == 0, run.stderr
    assert "voxels " in run.stdout and (tmp_path / "v.png").exists(), run.stdout


def test_voxels_vpls_and_lgh_layers(offscreen, tmp_path, capsys):
    stage = str(STAGES / "cornell.usda")
    png = tmp_path / "vox.png"
    assert main(["view", stage, "--show", "voxels", "--octree-resolution", "16", "--png", str(png),
                 "--window-size", "200,160"]) == 0
    out = capsys.readouterr().out
    voxels = int(out.split("voxels ")[1].split()[0])
    assert 500 < voxels < 16 ** 3           # the box's walls and blocks, not the whole cube
    img = _read(png)
    assert np.any(np.abs(img.astype(int) - img[0, 0]) > 8, axis=2).mean() > 0.05
    assert main(["view", stage, "--show", "geometry,vpls,lgh", "--lgh-level", "2", "--png", str(tmp_path / "v.png"),
                 "--window-size", "200,160"]) == 0
    out = capsys.readouterr().out
    assert "vpls " in out and "lgh_level 2" in out
    assert main(["view", stage, "--show", "lgh", "--lgh-level", "99", "--png", str(tmp_path / "w.png")]) != 0
    assert "--lgh-level 99" in capsys.readouterr().err


def test_a_distant_light_draws_without_a_warning(offscreen, new_stage, tmp_path):
    """Issue 55, item 8: a distant light's arrow printed pyvista's four-line deprecation warning (positional
    ``pv.Arrow`` arguments) on every ``usdml view``, ``-q`` or not."""
    stage = new_stage()
    add_cube_mesh(stage, "/World/box")
    UsdLux.DistantLight.Define(stage, "/World/sun")
    stage.Save()
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "view", stage.GetRootLayer().realPath, "--png",
                          str(tmp_path / "sun.png"), "--window-size", "64,48"], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0 and run.stderr == "", run.stderr
    assert "lights 1" in run.stdout


@pytest.mark.parametrize("quiet", [False, True])
def test_a_third_party_warning_is_one_line_and_q_hides_it(monkeypatch, capsys, quiet):
    """Issue 55, item 8: a Python warning of a library usdml calls (pyvista's here) is one ``usdml: warning:``
    line, as usdml's own, and ``-q`` hides it."""
    from pyvista.core.errors import PyVistaDeprecationWarning

    def warns(*args, **kwargs):
        warnings.warn("\nArguments 'start' must be passed as keyword arguments to function 'Arrow'.\nFrom version "
                      "0.50, passing these as positional arguments will result in a TypeError.",
                      PyVistaDeprecationWarning)
        return {}

    monkeypatch.setattr("usdml.view.view", warns)
    assert main(["view", str(STAGES / "cornell.usda"), "--png", "x.png", *(["-q"] if quiet else [])]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == ([] if quiet else [
        "usdml: warning: pyvista: Arguments 'start' must be passed as keyword arguments to function 'Arrow'. "
        "(PyVistaDeprecationWarning)"])
