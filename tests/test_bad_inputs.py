"""What a new user hits (issue 38): output paths that cannot be written, flags that are not quite right,
options that do nothing, a script's wrong keyword. Each ends in one ``usdml: error:`` line and exit 2,
or renders with a ``usdml: warning:`` line naming what was ignored; never a traceback, a segfault or
silence."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numpy as np
import pytest
from pxr import UsdGeom, UsdLux

import usdml
from conftest import STAGES, add_quad
from usdml.cli import build_parser, main

CORNELL = str(STAGES / "cornell.usda")
#: the quickest approximate comparison on cornell (an 8-pixel-wide octree compare takes well under a second)
SVO = ["--visibility", "svo", "--imageWidth", "8", "--svo-resolution", "16"]


def _one_error(capsys, argv, *needles):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("usdml: error:")]
    assert code == 2, (code, err)
    assert len(errors) == 1 and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and "usage:" not in err, err
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


def _image_size(path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    fmt = inp.format_name()
    inp.close()
    return spec.width, spec.height, fmt


# ---------------------------------------------------------------------------------- 1. output paths

def test_heatmap_under_a_regular_file_is_one_line_not_a_segfault(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_error(capsys, ["compare", CORNELL, *SVO, "--heatmap", blocker / "x.exr"], "is a file, not a folder")


def test_heatmap_in_a_missing_folder_is_made(tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "x.exr"
    assert main(["compare", CORNELL, *SVO, "--heatmap", str(out)]) == 0
    w, h, fmt = _image_size(out)
    assert (w, fmt) == (8, "openexr")            # the extension's format, the render's pixels (paper 000 Fig. 6)
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]     # no temporary file left


@pytest.mark.parametrize("name, needle", [("x.txt", ".txt is not an image format"),
                                          ("x", "no extension is not an image format")])
def test_heatmap_names_a_format(tmp_path, capsys, name, needle):
    _one_error(capsys, ["compare", CORNELL, *SVO, "--heatmap", tmp_path / name], "--heatmap", needle)


def test_heatmap_on_a_folder(tmp_path, capsys):
    _one_error(capsys, ["compare", CORNELL, *SVO, "--heatmap", tmp_path], "is a folder")


def test_plot_and_png_under_a_regular_file(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_error(capsys, ["compare", CORNELL, *SVO, "--plot", blocker / "p"], "is a file, not a folder")
    _one_error(capsys, ["compare", CORNELL, "--gi", "lgh", "--imageWidth", "8", "--png", blocker / "p"],
               "is a file, not a folder")


def test_view_png_under_a_regular_file(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_error(capsys, ["view", CORNELL, "--png", blocker / "x.png"], "is a file, not a folder")
    _one_error(capsys, ["view", CORNELL, "--png", tmp_path / "x.exr"], ".exr is not an image format")


def test_render_output_under_a_regular_file(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_error(capsys, ["render", CORNELL, blocker / "x.exr", "--imageWidth", "8"], "is a file, not a folder")


# ------------------------------------------------------------------------- 9. what the plots look like

def test_plot_heat_map_is_readable_whatever_the_image_size(tmp_path, capsys):
    prefix = tmp_path / "p"
    assert main(["compare", CORNELL, *SVO, "--plot", str(prefix)]) == 0
    w, h, fmt = _image_size(f"{prefix}.heatmap.png")
    assert fmt == "png" and w >= 512, (w, h)      # an 8-pixel image drawn large, with its colour bar
    import OpenImageIO as oiio

    img = np.asarray(oiio.ImageInput.open(f"{prefix}.heatmap.png").read_image("uint8"))[..., :3].astype(int)
    # the colour bar's two ends: a red (brighter) and a blue (darker) run of pixels
    red = (img[..., 0] > 200) & (img[..., 1] < 90) & (img[..., 2] < 90)
    blue = (img[..., 2] > 200) & (img[..., 0] < 90)
    assert red.sum() > 50 and blue.sum() > 50
    assert _image_size(f"{prefix}.hist.png")[2] == "png"


def test_view_writes_the_format_its_name_says(tmp_path, capsys):
    from usdml.view import probe

    why = probe()
    if why:
        pytest.skip(why)
    jpg = tmp_path / "v.jpg"
    assert main(["view", CORNELL, "--png", str(jpg), "--window-size", "160,100"]) == 0
    assert jpg.read_bytes()[:2] == b"\xff\xd8"       # JPEG data, not PNG under a .jpg name
    assert _image_size(jpg)[:2] == (160, 100)


def _group_of(help_text: str, flag: str) -> str:
    """The title of the help group ``flag`` is listed under."""
    title = None
    for line in help_text.splitlines():
        if line and not line.startswith(" ") and line.endswith(":"):
            title = line
        elif line.strip().startswith(flag):
            return title
    raise AssertionError(f"{flag} not in the help")


@pytest.mark.parametrize("command", ["render", "compare", "bench"])
def test_help_groups_every_backends_flags_under_visibility(command):
    parser = build_parser()
    text = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command].format_help()
    group = _group_of(text, "--voxel-resolution")
    assert group.startswith("visibility")
    if command == "render":                       # compare's and bench's --visibility are their own flags
        assert _group_of(text, "--visibility") == group
    for flag in ("--svo-resolution", "--svo-cpu-kernel", "--insm-count", "--insm-cpu-kernel"):
        assert _group_of(text, flag) == group, flag
    if command != "bench":
        assert _group_of(text, "--gi") != group


def test_image_width_shows_its_default(capsys):
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--imageWidth W image width in pixels, height from the aspect ratio (default: the RenderSettings' " \
           "resolution, else 960)" in text


# ---------------------------------------------------------------------------- 5. one line, one meaning

def _subparsers():
    parser = build_parser()
    return parser, next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_no_parser_matches_prefixes():
    parser, subs = _subparsers()
    assert not parser.allow_abbrev
    assert subs and all(not p.allow_abbrev for p in subs.values())


def test_an_abbreviated_flag_is_refused_and_the_full_one_named(tmp_path, capsys):
    line = _one_error(capsys, ["render", CORNELL, tmp_path / "x.exr", "--direct-s", "4"],
                      "usdml render: unrecognized arguments: --direct-s 4", "--direct-shadow-samples",
                      "usdml render --help")
    assert not (tmp_path / "x.exr").exists(), line


@pytest.mark.parametrize("argv, needle", [
    (["render", CORNELL, "x.exr", "--imageWidth", "abc"], "argument --imageWidth/W: invalid int value: 'abc'"),
    (["render", CORNELL, "x.exr", "--frames"], "argument --frames: expected one argument"),
    (["compare", CORNELL, "--against"], "argument --against: expected one argument"),
    (["bench", CORNELL, "--imageWidth", "1.5"], "invalid int value: '1.5'"),
    (["render", CORNELL, "--voxel-rebuild", "spin"], "argument --voxel-rebuild: invalid choice: 'spin'"),
    (["rendr", CORNELL], "invalid choice: 'rendr'"),
    (["info"], "the following arguments are required: stage"),
    (["bake", CORNELL, "--fully-dynamic=yes"], "--fully-dynamic"),
])
def test_argument_errors_are_one_line_without_usage(capsys, argv, needle):
    _one_error(capsys, argv, needle.replace("/W", "") if "/W" in needle and "W" not in argv else needle)


def test_quiet_works_after_the_command(tmp_path, capsys):
    argv = ["render", CORNELL, str(tmp_path / "x.exr"), "--imageWidth", "8", "--gi-svo-skip", "0.2"]
    assert main(argv) == 0
    assert "usdml: warning: --gi-svo-skip is ignored" in capsys.readouterr().err
    for quiet in (["-q", *argv], [*argv, "-q"], [argv[0], "--quiet", *argv[1:]]):
        assert main(quiet) == 0
        assert "warning" not in capsys.readouterr().err, quiet


def test_no_cuda_driver_warning_on_a_cpu_machine(tmp_path):
    """Warp's native start-up writes it to the process's standard error: usdml drops that line."""
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    for argv in (["render", CORNELL, str(tmp_path / "x.exr"), "--imageWidth", "8", "--visibility", "svo"],
                 ["render", CORNELL, str(tmp_path / "y.exr"), "--imageWidth", "8", "-q"]):
        run = subprocess.run([sys.executable, "-m", "usdml.cli", *argv], capture_output=True, text=True, env=env,
                             timeout=300)
        assert run.returncode == 0, run.stderr
        assert "CUDA driver" not in run.stderr and "Warp CUDA" not in run.stderr, run.stderr


def test_the_first_render_with_a_fresh_warp_cache_prints_only_usdml_lines(tmp_path):
    """Issue 55: the driver line still came once, on the first command after the install; with a fresh Warp
    kernel cache (the kernels compiled) and fresh usdml cache, every line on stderr is usdml's."""
    env = {k: v for k, v in os.environ.items() if k != "CUDA_VISIBLE_DEVICES"}
    env.update(HOME=str(tmp_path), WARP_CACHE_PATH=str(tmp_path / "warp"), USDML_CACHE_DIR=str(tmp_path / "usdml"))
    run = subprocess.run([sys.executable, "-m", "usdml.cli", "render", str(STAGES / "boxes.usda"),
                          str(tmp_path / "x.exr"), "--imageWidth", "32"], capture_output=True, text=True, env=env,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert any((tmp_path / "warp").rglob("*.o")), "the kernels were not compiled into the fresh cache"
    assert all(line.startswith("usdml:") for line in run.stderr.splitlines()), run.stderr


def test_warp_starts_once_and_its_other_lines_are_usdml_warnings(monkeypatch, capfd, caplog):
    """What Warp's native start-up writes to descriptor 2 but the driver line is a ``usdml`` warning; threads
    asking for Warp together start it once, and descriptor 2 is the terminal's again after."""
    import logging
    import threading

    import warp

    import usdml.kernels as kernels
    from usdml.errors import collect_warnings

    starts = []

    def native_init():
        starts.append(threading.current_thread().name)
        os.write(2, f"Warp CUDA warning: {kernels.NO_DRIVER}. GPU execution will not be available.\n".encode())
        os.write(2, b"Warp: something else\n")

    monkeypatch.setattr(kernels, "_ready", False)
    monkeypatch.setattr(warp, "init", native_init)
    log = logging.getLogger("usdml")
    monkeypatch.setattr(log, "handlers", [])            # the warnings go to the collector alone, not to stderr
    monkeypatch.setattr(log, "propagate", False)
    caplog.set_level(logging.WARNING, logger="usdml")     # not an earlier -q's level
    capfd.readouterr()
    with collect_warnings() as warnings:
        threads = [threading.Thread(target=kernels.warp) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    os.write(2, b"after\n")
    assert len(starts) == 1 and capfd.readouterr().err == "after\n"
    assert warnings == ["Warp: Warp: something else"]


# ------------------------------------------------------------------------- 4. options that do nothing

@pytest.mark.parametrize("extra, needle", [
    (["--gi-svo-skip", "0.2"], "--gi-svo-skip is ignored: it applies with --gi svo (here: --gi none)"),
    (["--gi", "lgh", "--vpls", "50", "--gi-svo-skip", "0.2"], "--gi-svo-skip is ignored: it applies with --gi svo "
                                                               "(here: --gi lgh)"),
    (["--direct-alpha", "2"], "--direct-alpha is ignored: it applies with --direct lgh (here: --direct all)"),
    (["--voxel-resolution", "16"], "--voxel-resolution is ignored: it applies with --visibility voxel"),
    (["--insm-count", "4", "--visibility", "svo", "--svo-resolution", "16"], "--insm-count is ignored"),
    (["--vpls", "10"], "--vpls is ignored: it applies with --gi lgh/svo/vpl-bruteforce"),
])
def test_a_flag_the_render_does_not_read_is_a_warning(tmp_path, capsys, extra, needle):
    assert main(["render", CORNELL, str(tmp_path / "x.exr"), "--imageWidth", "8", *extra]) == 0
    err = capsys.readouterr().err
    assert f"usdml: warning: {needle}" in err, err


def test_flags_the_render_reads_give_no_warning(tmp_path, capsys):
    argv = ["render", CORNELL, str(tmp_path / "x.exr"), "--imageWidth", "8", "--visibility", "svo",
            "--svo-resolution", "16", "--gi", "svo", "--vpls", "64", "--gi-svo-skip", "0.2"]
    assert main(argv) == 0
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("argv, needle", [
    (["--gi", "lgh", "--vpls", "50", "--plot", "P"], "--plot is ignored: it applies to compare --visibility"),
    (["--gi", "lgh", "--vpls", "50", "--heatmap", "H.png"], "--heatmap is ignored"),
    (SVO + ["--png", "P"], "--png is ignored: it applies to compare --gi or --direct (this comparison: --visibility)"),
    (SVO + ["--reference-pixels", "10"], "--reference-pixels is ignored"),
])
def test_compare_options_of_another_comparison_warn(tmp_path, capsys, argv, needle):
    argv = [str(tmp_path / a) if a in ("P", "H.png") else a for a in argv]
    assert main(["compare", CORNELL, "--imageWidth", "8", *argv]) == 0
    err = capsys.readouterr().err
    assert f"usdml: warning: {needle}" in err, err
    assert not list(tmp_path.iterdir())          # and nothing half-written


def test_direct_lgh_over_lights_that_all_go_every_light_warns(new_stage, tmp_path, capsys):
    stage = new_stage("spots.usda")
    add_quad(stage, "/ground", size=4.0)
    for i in range(3):
        light = UsdLux.SphereLight.Define(stage, f"/spot{i}")
        light.CreateIntensityAttr(20.0)
        UsdGeom.Xformable(light).AddTranslateOp().Set((i - 1.0, 2.0, 0.0))
        UsdGeom.Xformable(light).AddRotateXOp().Set(-90.0)      # the cone (about -Z) turned down
        UsdLux.ShapingAPI.Apply(light.GetPrim()).CreateShapingConeAngleAttr(30.0)
    cam = UsdGeom.Camera.Define(stage, "/cam")
    cam.AddTranslateOp().Set((0, 1, 6))
    stage.Save()
    path = stage.GetRootLayer().realPath
    outs = []
    for direct in ("lgh", "all"):
        out = tmp_path / f"{direct}.exr"
        assert main(["render", path, str(out), "--imageWidth", "16", "--direct", direct, "--aovs", "direct"]) == 0
        outs.append(out)
        err = capsys.readouterr().err
        assert ("none of its 3 light(s)" in err) == (direct == "lgh"), err
    from usdml.aov.exr import read_exr

    lgh, every = (read_exr(o)[0]["direct"] for o in outs)
    assert lgh.max() > 0
    np.testing.assert_array_equal(lgh, every)        # what the warning says: the same pixels as --direct all


# --------------------------------------------------------------------------- 6. the Python API's checks

@pytest.mark.parametrize("kwargs, needle", [
    ({"image_width": "64"}, "Recorder: image_width '64': give an integer from 1 to 16384 (pixels)"),
    ({"image_width": 64.5}, "image_width 64.5"),
    ({"image_width": True}, "image_width True"),
    ({"voxel_resolution": "64"}, "voxel resolution must be an integer, got '64' (keyword voxel_resolution"),
    ({"pixel_samples": True}, "keyword pixel_samples"),
    ({"direction_step": float("nan")}, "keyword direction_step"),
    ({"preview": 1}, "Recorder: preview 1: give True or False"),
    ({"device": "gpu"}, "Recorder: device 'gpu': give cpu or cuda"),
    ({"workers": 0}, "Recorder: workers 0"),
    ({"aovs": 3}, "Recorder: aovs 3"),
    ({"implicit_detail": 2}, "Recorder: implicit_detail 2: give an integer from 3 to 1024"),
    ({"purposes": ["render", "bogus"]}, "Recorder: purposes: unknown purpose(s) bogus; use render, proxy or guide"),
    ({"purposes": "proxy,bogus"}, "Recorder: purposes: unknown purpose(s) bogus"),
    ({"voxel_resolutoin": 64}, "voxel_resolutoin (did you mean voxel_resolution?)"),
    ({"imageWidth": 64}, "imageWidth (did you mean image_width?)"),
])
def test_the_api_checks_types_and_names_keywords(kwargs, needle):
    with pytest.raises(usdml.UsdmlError) as e:
        usdml.Recorder(**kwargs)
    message = str(e.value)
    assert needle in message, message
    assert "--" not in message, message            # a keyword, not a flag the script never typed


def _typed_flags():
    """(command, flag, a value it refuses) for every flag of every command that takes a typed value or a
    choice: the table's and each command's own."""
    _, subs = _subparsers()
    out = []
    for command, parser in sorted(subs.items()):
        for action in parser._actions:
            flag = next((o for o in action.option_strings if o.startswith("--")), None)
            if flag is None or action.nargs == 0:
                continue
            if action.choices:
                out.append((command, flag, "no-such-choice"))
            elif action.type in (int, float):
                out.append((command, flag, "abc"))
    return out


@pytest.mark.parametrize("command, flag, value", _typed_flags())
def test_every_flag_refuses_a_bad_value_in_one_line(capsys, command, flag, value):
    positional = {"cache": "clean"}.get(command, CORNELL)     # clean: a refused value must remove nothing
    _one_error(capsys, [command, positional, flag, value], flag)


@pytest.mark.parametrize("command", ["render", "compare", "bench", "bake", "info", "view"])
def test_every_command_refuses_an_unknown_flag_and_a_missing_stage(capsys, command, tmp_path):
    _one_error(capsys, [command, CORNELL, "--no-such-flag"], f"usdml {command}: unrecognized arguments")
    needs = {"compare": ["--visibility", "svo"], "view": ["--png", tmp_path / "v.png"]}.get(command, [])
    _one_error(capsys, [command, tmp_path / "nope.usda", *needs], "nope.usda")
