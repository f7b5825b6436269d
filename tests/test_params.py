"""The parameter table (usdml.params): the settings dataclass, the flags of each command and the schema
follow from it and agree with it; a setting reaches UsdmlSettings from the stage and from its flag
(the flag wins); a bad value is one line naming the flag and the attribute."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math

import pytest
from pxr import Sdf, UsdLux, UsdRender

from conftest import add_cube_mesh
from usdml.cli import build_parser, main
from usdml.params import overrides_from_args
from usdml.errors import UsdmlError
from usdml.params import COMMANDS, PARAMS, check
from usdml.settings import SCHEMA_ATTRIBUTES, UsdmlSettings
from usdml.visibility.registry import backend_names

NEW_VOXEL_KNOBS = ("voxel_normal_offset", "voxel_skip", "voxel_slab", "voxel_max_skip", "voxel_end_skip",
                   "voxel_segment", "voxel_core", "voxel_frame_core", "voxel_memory_limit")


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings}


def test_every_row_is_a_field_an_attribute_and_a_flag():
    rows = list(PARAMS.values())
    assert [f.name for f in dataclasses.fields(UsdmlSettings)] == [*PARAMS, "backend_settings"]
    assert len({p.attribute for p in rows}) == len({p.flag for p in rows}) == len(rows)
    assert SCHEMA_ATTRIBUTES == {p.attribute: p.field for p in rows}
    defaults = UsdmlSettings().as_dict()
    for p in rows:
        assert p.attribute.startswith("usdml:") and p.flag.startswith("--") and p.help and p.commands
        assert set(p.commands) <= set(COMMANDS), p.field
        assert type(p.default) is p.type and defaults[p.field] == p.default, p.field
        assert check(p.field, p.default) == p.default
        assert all(check(p.field, c) == c for c in p.choices)
        assert "\n" not in p.help and "default" not in p.help, f"{p.flag}: argparse adds the default"
    assert set(NEW_VOXEL_KNOBS) | {"dome_samples"} <= set(PARAMS)
    assert PARAMS["visibility"].choices == backend_names()


def test_each_method_declares_its_rows_in_its_folder():
    """A method's settings are declared in its folder (issue 54): the voxel, svo and insm backends' rows through
    the registry, the LGH's among the lighting rows; usdml/params.py keeps the frame-wide ones, and the table
    holds each row once, the backends' right after ``visibility``."""
    from usdml import params
    from usdml.lighting.lgh import params as lgh
    from usdml.visibility import registry
    from usdml.visibility.insm import params as insm
    from usdml.visibility.svo import params as svo
    from usdml.visibility.voxel import params as voxel

    owned = {"voxel": voxel.PARAMS, "svo": svo.PARAMS, "insm": insm.PARAMS}
    for name, rows in owned.items():
        assert registry.PARAMS[name] == f"usdml.visibility.{name}.params:PARAMS"
        assert all(p.field.startswith(name) or name == "voxel" for p in rows)
    fields = list(PARAMS)
    backend_rows = [p.field for name in registry.backend_names() for p in owned.get(name, ())]
    assert fields[:1 + len(backend_rows)] == ["visibility", *backend_rows]
    assert {f for f in fields if f.startswith(("voxel_", "svo_", "insm_"))} <= set(backend_rows)
    lgh_rows = [p.field for p in (*lgh.DIRECT, *lgh.HIERARCHY, *lgh.SHADOWS)]
    assert {f for f in fields if f.startswith(("lgh_", "direct_"))} <= set(lgh_rows) <= set(fields)
    own = {p.field for p in params._SETTINGS} - set(lgh_rows)
    assert own.isdisjoint(backend_rows) and len(fields) == len(set(fields))
    assert {"error_budget", "direct", "gi", "pixel_samples", "seed"} <= own


def test_backends_read_the_table_and_have_no_defaults_of_their_own():
    """A backend's knobs are settings: built without any it reads the table's defaults (0 standing for the
    automatic choice where there is one), its constructor names no default of a setting, and a field given
    by name wins."""
    from usdml.visibility import backend_class
    from usdml.visibility.voxel import backend as voxel

    b = voxel.VoxelBackend(cache=False)
    s = UsdmlSettings()
    assert (b.resolution, b.step, b.rebuild, b.mapping) == (s.voxel_resolution, s.direction_step, s.voxel_rebuild,
                                                          s.voxel_mapping)
    assert (b.normal_offset, b.skip, b.slab, b.end_skip, b.segment, b.core, b.frame_core) == \
        (s.voxel_normal_offset, s.voxel_skip, s.voxel_slab, s.voxel_end_skip, s.voxel_segment, s.voxel_core,
         s.voxel_frame_core)
    assert s.voxel_max_skip == 0 and b.max_skip == voxel.MAX_SKIP and s.voxel_memory_limit == 0 and b.memory_limit is None
    for name in ("voxel", "svo", "insm"):
        cls = backend_class(name)
        assert cls.reads_settings
        assert not set(inspect.signature(cls.__init__).parameters) & set(PARAMS), name
    assert voxel.VoxelBackend(cache=False, voxel_resolution=16).resolution == 16
    with pytest.raises(UsdmlError, match="--voxel-segment"):
        voxel.VoxelBackend(cache=False, voxel_segment=3)


@pytest.mark.parametrize("command", COMMANDS)
def test_flags_follow_the_table(command):
    parser = _subparsers()[command]
    flags = _flags(parser)
    rows = [p for p in PARAMS.values() if command in p.commands]
    assert rows
    for p in rows:
        action = flags[p.flag]
        assert action.dest == p.field and action.default is None, p.flag
        if p.choices and p.parser_choices:
            assert tuple(action.choices) == p.choices, p.flag
        shown = ("off" if not p.default else "on") if p.type is bool else \
            (f"{p.default:g}" if p.type is float else str(p.default))
        text = action.help % {"default": action.default}
        assert text.endswith(f"(default: the stage's {p.attribute}, else {shown})"), text
    args = parser.parse_args(["stage.usda"])
    assert overrides_from_args(args) == {}
    if command == "compare":
        assert "--visibility" in flags and "visibility" not in {p.field for p in rows}   # compare's own flag


def test_existing_flag_spellings():
    render = _flags(_subparsers()["render"])
    for flag in ("--visibility", "--vpls", "--direction-step", "--voxel-resolution", "--fully-dynamic",
                 "--no-fully-dynamic", "--pixel-samples", "--dome-samples", "--seed", "--gi", "--lgh-alpha",
                 "--lgh-levels", "--lgh-start-level", "--shadow-samples", "--shadow-filter-iterations",
                 "--shadow-targets", "--interleave", "--voxel-rebuild", "--voxel-mapping", "--device"):
        assert flag in render, flag
    assert "--device" in _flags(_subparsers()["bench"])


def test_flags_reach_the_settings():
    parser = build_parser()
    argv = ["render", "s.usda", "--vpls", "500", "--direction-step", "5", "--no-fully-dynamic", "--voxel-segment",
            "8", "--voxel-max-skip", "3", "--voxel-memory-limit", "0.5", "--voxel-frame-core", "0.25",
            "--pixel-samples", "9", "--visibility", "voxel"]
    s = UsdmlSettings().updated(**overrides_from_args(parser.parse_args(argv)))
    assert (s.vpl_count, s.direction_step, s.fully_dynamic, s.voxel_segment, s.voxel_max_skip) == (500, 5.0, False, 8, 3.0)
    assert (s.voxel_memory_limit, s.voxel_frame_core, s.pixel_samples, s.visibility) == (0.5, 0.25, 9, "voxel")
    bench = parser.parse_args(["bench", "s.usda", "--visibility", "voxel", "--visibility", "exact", "--voxel-skip", "2"])
    assert bench.visibility == ["voxel", "exact"] and overrides_from_args(bench) == {"voxel_skip": 2.0}


def _stage_with(new_stage, values: dict) -> str:
    stage = new_stage(start=1, end=1)
    add_cube_mesh(stage, "/World/box")
    UsdLux.DistantLight.Define(stage, "/World/sun")
    prim = UsdRender.Settings.Define(stage, "/Render/Settings").GetPrim()
    prim.ApplyAPI("UsdmlRenderSettingsAPI")
    for name, value in values.items():
        prim.GetAttribute(name).Set(value)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    return stage.GetRootLayer().realPath


def test_every_attribute_is_read_from_the_stage_and_the_flag_wins(new_stage):
    from usdml.stage import StageDelegate

    authored = {"usdml:voxel:segment": 8, "usdml:voxel:maxSkip": 3.0, "usdml:voxel:memoryLimit": 1.5,
                "usdml:voxel:normalOffset": 0.5, "usdml:dome:samples": 64, "usdml:vpl:bounces": 2,
                "usdml:voxel:core": 0.25}
    path = _stage_with(new_stage, authored)
    s = StageDelegate(path).usdml_settings
    for name, value in authored.items():
        assert getattr(s, SCHEMA_ATTRIBUTES[name]) == value, name
    # every other setting is the schema's fallback, which is the table's default
    assert {k: v for k, v in s.as_dict().items() if k not in {SCHEMA_ATTRIBUTES[n] for n in authored}} == \
        {p.field: p.default for p in PARAMS.values() if p.attribute not in authored}
    args = build_parser().parse_args(["render", path, "--voxel-segment", "16", "--dome-samples", "32"])
    s = s.updated(**overrides_from_args(args))
    assert (s.voxel_segment, s.dome_samples, s.voxel_max_skip, s.vpl_bounces) == (16, 32, 3.0, 2)


def _one_error(err: str) -> str:
    assert "Traceback" not in err
    (line,) = [line for line in err.splitlines() if line.startswith("usdml: error:")]
    return line


@pytest.mark.parametrize("argv,words", [
    (["--voxel-core", "2"], ["voxel core must be in [0, 1], got 2.0", "--voxel-core", "usdml:voxel:core"]),
    (["--voxel-memory-limit", "-1"], ["voxel memory limit must be finite and >= 0", "--voxel-memory-limit"]),
    (["--direction-step", "0.05"], ["direction step must be in [0.1, 90], got 0.05", "usdml:voxel:directionStep"]),
    (["--visibility", "raytraced"], ["unknown visibility backend 'raytraced'; use one of exact, voxel"]),
    (["--vpl-bounces", "0"], ["VPL bounces must be >= 1, got 0", "--vpl-bounces", "usdml:vpl:bounces"]),
])
def test_a_bad_flag_is_one_line(new_stage, capsys, argv, words):
    path = _stage_with(new_stage, {})
    assert main(["render", path, "out.exr", *argv]) == 2
    line = _one_error(capsys.readouterr().err)
    assert all(w in line for w in words), line


def test_a_bad_stage_value_names_the_prim_and_the_attribute(new_stage, capsys):
    path = _stage_with(new_stage, {"usdml:voxel:frameCore": 1.5})
    assert main(["info", path]) == 2
    line = _one_error(capsys.readouterr().err)
    assert "/Render/Settings: voxel frame core must be in [0, 1], got 1.5 (--voxel-frame-core, usdml:voxel:frameCore)" in line


def test_a_stage_value_of_the_wrong_type(new_stage):
    from usdml.stage import StageDelegate

    path = _stage_with(new_stage, {})
    layer = Sdf.Layer.FindOrOpen(path)
    spec = layer.GetPrimAtPath("/Render/Settings")
    Sdf.AttributeSpec(spec, "usdml:pixelSamples", Sdf.ValueTypeNames.String).default = "lots"
    layer.Save()
    with pytest.raises(UsdmlError, match=r"/Render/Settings: pixel samples must be an integer, got 'lots' "
                                         r"\(--pixel-samples, usdml:pixelSamples\)"):
        StageDelegate(path)


@pytest.mark.parametrize("name,value,message", [
    ("voxel_segment", 3, "voxel segment must be one of 1, 2, 4, 8, 16, 32, got 3"),
    ("pixel_samples", 8, "square number"),
    ("lgh_alpha", math.inf, "LGH alpha must be finite and >= 0"),
    ("fully_dynamic", "yes", "fully dynamic must be true or false"),
    ("voxel_rebuild", "peel", "unknown voxel rebuild 'peel'; use one of rotate, geometry"),
    ("interleave", 3, "interleave must be one of 1, 2, 4"),
    ("seed", True, "seed must be an integer"),
])
def test_check_says_what_to_use(name, value, message):
    with pytest.raises(UsdmlError, match=message.replace("(", r"\(").replace(")", r"\)")) as e:
        check(name, value)
    assert f"({PARAMS[name].flag}, {PARAMS[name].attribute})" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(UsdmlError):
        UsdmlSettings(**{name: value})
    with pytest.raises(UsdmlError, match="unknown setting 'voxel_size'"):
        check("voxel_size", 1)


def test_bench_takes_a_device(new_stage, monkeypatch, capsys):
    import usdml.bench

    seen = {}

    def fake(delegate, backends, **kw):
        seen.update(kw, backends=backends)
        return []

    monkeypatch.setattr(usdml.bench, "bench_visibility", fake)
    monkeypatch.setattr(usdml.bench, "format_bench", lambda results: "")
    path = _stage_with(new_stage, {"usdml:voxel:resolution": 32})
    assert main(["bench", path, "--visibility", "voxel", "--device", "cuda:0", "--voxel-end-skip", "2"]) == 0
    assert seen["device"] == "cuda:0" and seen["backends"] == ["voxel"]
    assert (seen["settings"].voxel_resolution, seen["settings"].voxel_end_skip) == (32, 2.0)


def test_bench_visibility_threads_the_device():
    import usdml.bench

    assert inspect.signature(usdml.bench.bench_visibility).parameters["device"].default == "cpu"
