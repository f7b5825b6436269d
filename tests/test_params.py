"""The parameter table (usdml.params): the settings dataclass and the schema follow from it and agree
with it; every attribute reaches UsdmlSettings from the stage; a bad value is one line naming the
flag and the attribute."""

from __future__ import annotations

import dataclasses
import inspect
import math

import pytest
from pxr import Sdf, UsdLux, UsdRender

from conftest import add_cube_mesh
from usdml.cli import main
from usdml.errors import UsdmlError
from usdml.params import COMMANDS, PARAMS, check
from usdml.settings import SCHEMA_ATTRIBUTES, UsdmlSettings
from usdml.visibility.registry import backend_names

NEW_VOXEL_KNOBS = ("voxel_normal_offset", "voxel_skip", "voxel_slab", "voxel_max_skip", "voxel_end_skip",
                   "voxel_segment", "voxel_core", "voxel_frame_core", "voxel_memory_limit")


def test_every_row_is_a_field_an_attribute_and_a_flag():
    rows = list(PARAMS.values())
    assert [f.name for f in dataclasses.fields(UsdmlSettings)] == list(PARAMS)
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


def test_voxel_knob_defaults_are_the_backends():
    """0 stands for the backend's automatic choice (None) where it has one."""
    from usdml.visibility import voxel

    sig = inspect.signature(voxel.VoxelBackend.__init__).parameters
    s = UsdmlSettings()
    for knob in ("normal_offset", "skip", "slab", "end_skip", "segment"):
        assert getattr(s, f"voxel_{knob}") == sig[knob].default, knob
    for knob in ("max_skip", "memory_limit"):
        assert sig[knob].default is None and getattr(s, f"voxel_{knob}") == 0, knob
    assert sig["core"].default is None and s.voxel_core == voxel.CORE
    assert sig["frame_core"].default is None and s.voxel_frame_core == voxel.PER_FRAME_CORE
    assert (s.voxel_resolution, s.direction_step) == (sig["resolution"].default, sig["step"].default)
    assert (s.voxel_rebuild, s.voxel_mapping) == (sig["rebuild"].default, sig["mapping"].default)


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
    s = s.updated(voxel_segment=16, dome_samples=32)
    assert (s.voxel_segment, s.dome_samples, s.voxel_max_skip, s.vpl_bounces) == (16, 32, 3.0, 2)


def _one_error(err: str) -> str:
    assert "Traceback" not in err
    (line,) = [line for line in err.splitlines() if line.startswith("usdml: error:")]
    return line


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
    ("lgh_alpha", math.inf, "LGH alpha must be finite and > 0"),
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
