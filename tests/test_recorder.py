"""The Python API (``usdml.Recorder``, shaped like usdrecord's FrameRecorder): the same pixels as the
command line, open stages with session-layer edits and in-memory stages, the command line's
validation and messages, sequences with resume, warnings collected, the example script."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

import usdml
from conftest import ROOT, add_cube_mesh, add_quad, ground_stage
from pxr import Usd, UsdGeom, UsdLux
from usdml.aov.exr import read_exr
from usdml.cli import main
from usdml.render.budget import BudgetEstimate
from usdml.render.estimate import VisibilityEstimate
from usdml.render.lighting_estimate import LightingEstimate
from usdml.render.result import DaskRun, SequenceResult

pytest.importorskip("embreex")


def _shot(new_stage) -> str:
    def scene(stage):
        cube = add_cube_mesh(stage, "/World/cube", size=4)
        cube.AddTranslateOp().Set((0, 2, 0))
        light = UsdLux.SphereLight.Define(stage, "/World/bulb")
        light.CreateIntensityAttr(100.0)
        light.AddTranslateOp().Set((3, 8, 1))
    return ground_stage(new_stage, scene)


def _result(**fields) -> SequenceResult:
    """A render's result with nothing in it but ``fields``."""
    return SequenceResult(**{**dict(stage="s.usda", frames=[], skipped=[], stale=[], recovered=[], resolution=(1, 1),
                                    seconds_per_frame=0.0, seconds=0.0, visibility="exact", outputs=[], previews=[],
                                    skipped_outputs=[], settings_digest=[]), **fields})


def test_frames_reach_the_job_as_floats(monkeypatch):
    """Timecodes go to the RenderJob as floats (a FrameSpec string as it is), not through FrameSpec text."""
    import usdml.render.sequence as sequence

    jobs = []

    def fake(job):
        jobs.append(job)
        return _result()
    monkeypatch.setattr(sequence, "render_sequence", fake)
    rec = usdml.Recorder()
    rec.record_sequence("s.usda", [1, 12345.678], "o.####.exr")
    rec.record("s.usda", 2, "o.exr")
    rec.record_sequence("s.usda", "1:3x2", "o.####.exr")
    assert [j.frames for j in jobs] == [[1.0, 12345.678], [2.0], "1:3x2"]
    with pytest.raises(usdml.UsdmlError, match="give a FrameSpec"):
        rec.record_sequence("s.usda", [True], "o.####.exr")


def test_record_writes_what_the_command_line_writes(new_stage, tmp_path):
    path = _shot(new_stage)
    assert main(["render", path, str(tmp_path / "cli.exr"), "--imageWidth", "24", "--aovs", "color,shadow",
                 "--pixel-samples", "1"]) == 0
    result = usdml.Recorder(image_width=24, aovs=["color", "shadow"], pixel_samples=1).record(
        path, 1, str(tmp_path / "api.exr"))
    assert result.files == [str(tmp_path / "api.exr")] and result.frames == [1.0] and result.resolution == [24, 24]
    cli, api = read_exr(tmp_path / "cli.exr")[0], read_exr(tmp_path / "api.exr")[0]
    for aov in ("color", "shadow"):
        np.testing.assert_array_equal(cli[aov], api[aov])
    assert api["shadow"].max() > 0          # the cube shadows the ground


def test_an_open_stage_renders_with_its_session_layer_edits(new_stage, tmp_path):
    path = _shot(new_stage)
    rec = usdml.Recorder(image_width=16, aovs=["direct"], pixel_samples=1)
    base = read_exr(rec.record(path, 1, str(tmp_path / "a.exr")).files[0])[0]["direct"]
    stage = Usd.Stage.Open(path)
    with Usd.EditContext(stage, stage.GetSessionLayer()):
        UsdLux.SphereLight(stage.GetPrimAtPath("/World/bulb")).GetIntensityAttr().Set(400.0)
    brighter = read_exr(rec.record(stage, 1, str(tmp_path / "b.exr")).files[0])[0]["direct"]
    lit = base > 1e-3
    np.testing.assert_allclose(brighter[lit], 4 * base[lit], rtol=2e-3)     # half floats in the EXR
    # the file on disk is untouched
    assert Usd.Stage.Open(path).GetPrimAtPath("/World/bulb").GetAttribute("inputs:intensity").Get() == 100.0


def test_an_in_memory_stage_renders(tmp_path):
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    add_quad(stage, "/World/ground", size=20)
    add_cube_mesh(stage, "/World/box")          # the framing camera looks along -Z: the ground alone is edge-on
    light = UsdLux.SphereLight.Define(stage, "/World/bulb")
    light.CreateIntensityAttr(50.0)
    light.AddTranslateOp().Set((0, 5, 5))
    result = usdml.Recorder(image_width=12, aovs=["direct"]).record(stage, 0, str(tmp_path / "mem.exr"))
    img, meta = read_exr(result.files[0])
    assert img["direct"].max() > 0
    assert result.summary["stage"].startswith("anon:")


def test_settings_are_checked_as_the_command_line_checks_them(new_stage, capsys):
    path = _shot(new_stage)
    # the same rule; a script's message names its keyword, the command line's the flag
    with pytest.raises(usdml.UsdmlError) as api:
        usdml.Recorder(voxel_resolution=2)
    assert main(["render", path, "/tmp/x.exr", "--voxel-resolution", "2"]) != 0
    err = capsys.readouterr().err
    assert str(api.value) == "voxel resolution must be in [4, 2048], got 2 (keyword voxel_resolution, stage " \
                             "attribute usdml:voxel:resolution)"
    assert "usdml: error: voxel resolution must be in [4, 2048], got 2 (--voxel-resolution, " \
           "usdml:voxel:resolution)" in err
    with pytest.raises(usdml.UsdmlError, match="unknown keyword.*colour"):
        usdml.Recorder(colour="red")
    with pytest.raises(usdml.UsdmlError, match="image_width 0"):
        usdml.Recorder(image_width=0)
    with pytest.raises(usdml.UsdmlError, match="no such file"):
        usdml.Recorder().record("/nope/shot.usda", 1, "/tmp/x.exr")
    # two ways of running the frames (issue 55, item 4): refused when the recorder is made, as the flags are
    with pytest.raises(usdml.UsdmlError, match=r"^Recorder: workers=2 and scheduler='tcp://h:8786': two ways of "
                                               r"running the frames; give workers .* or scheduler .*, not both$"):
        usdml.Recorder(workers=2, scheduler="tcp://h:8786")


def test_a_sequence_resumes_and_warnings_come_back(new_stage, tmp_path):
    stage = new_stage(start=1, end=3)
    add_quad(stage, "/World/ground", size=20)
    stage.Save()
    path = stage.GetRootLayer().realPath
    rec = usdml.Recorder(image_width=8, aovs=["color"], pixel_samples=1)
    out = str(tmp_path / "seq.####.exr")
    first = rec.record_sequence(path, "1:2", out)
    assert first.frames == [1.0, 2.0] and len(first.files) == 2
    assert any("no lights" in w for w in first.warnings)          # lit by a camera light, said once
    again = rec.record_sequence(path, [1, 2, 3], out, resume=True)
    assert again.skipped == [1.0, 2.0] and again.frames == [3.0] and again.files == [str(tmp_path / "seq.0003.exr")]
    # one frame: to the path as it is, or with a placeholder the frame's
    assert rec.record(path, 2, str(tmp_path / "one.####.exr")).files == [str(tmp_path / "one.0002.exr")]
    assert rec.record(path, 2, str(tmp_path / "plain.exr")).files == [str(tmp_path / "plain.exr")]


def test_a_result_lists_the_files_this_call_wrote(new_stage, tmp_path):
    """Issue 38: ``files`` holds the EXRs this call wrote, ``skipped_files`` those a resume left alone,
    ``previews`` the PNGs, ``stale`` the frames whose files had other settings."""
    stage = new_stage(start=1, end=3)
    add_quad(stage, "/World/ground", size=20)
    stage.Save()
    path = stage.GetRootLayer().realPath
    out = str(tmp_path / "seq.####.exr")

    def record(frames, width=8, **options):
        return usdml.Recorder(image_width=width, aovs=["color"], pixel_samples=1, **options).record_sequence(
            path, frames, out, resume=True)

    def files(ext, *frames):
        return [str(tmp_path / f"seq.000{f}.{ext}") for f in frames]

    first = record("1:2", preview=True)
    assert first.files == files("exr", 1, 2) and first.previews == files("png", 1, 2)
    again = record("1:3")
    assert again.frames == [3.0] and again.files == files("exr", 3) and again.previews == []
    assert again.skipped == [1.0, 2.0] and again.skipped_files == files("exr", 1, 2) and again.stale == []
    wider = record("1:3", width=12)
    assert wider.stale == [1.0, 2.0, 3.0] and wider.skipped == [] and wider.skipped_files == []
    assert wider.files == files("exr", 1, 2, 3)


#: the keys of ``usdml render --json`` (docs/rendering.md), in their order; on Dask the run's
SUMMARY_KEYS = ["stage", "frames", "skipped", "stale", "recovered", "resolution", "secondsPerFrame", "seconds",
                "visibility", "outputs", "previews", "skippedOutputs", "settingsDigest", "estimates", "lightingEstimates",
                "warnings"]
DASK_KEYS = ["stage", "frames", "failed", "skipped", "stale", "rerun", "errors", "resolution", "visibility",
             "secondsPerFrame", "seconds", "startupSeconds", "workers", "scheduler", "chunkSize", "retries",
             "threadsPerWorker", "outputs", "previews", "skippedOutputs", "estimates", "lightingEstimates", "warnings"]


def test_the_typed_result_is_the_summary_and_the_record(monkeypatch):
    """``render_sequence``'s :class:`SequenceResult` makes the JSON summary (its documented keys, timecodes as
    FrameSpec text only there) and ``RecordResult``'s fields (timecodes as the floats they were: 12345.678, which
    ``f"{f:g}"`` would turn into 12345.7)."""
    import usdml.render.sequence as sequence

    visibility = VisibilityEstimate(0.1, 0.05, 0.2, 0.01, 0.0, 0.02, 128, 2048, 1500, False, 0.5)
    budget = BudgetEstimate(**visibility.as_dict(), budget=0.01, level=2, met=True, levels={"0": 0.3, "2": 0.008},
                            refined_fraction=0.1, near_fraction=0.02)
    lighting = LightingEstimate(0.1, 0.05, 0.15, -0.01, -0.02, 0.0, 192, 600, 24000, 19000, 0.25)
    result = _result(frames=[1.0, 12345.678], resolution=(24, 14), seconds_per_frame=0.5, seconds=1.25,
                     outputs=["o.0001.exr", "o.12345.678.exr"], settings_digest=["sha256:0"],
                     estimates={1.0: visibility, 12345.678: budget}, lighting_estimates={1.0: {"gi": lighting}},
                     warnings=["a warning"])
    summary = result.as_json()
    assert list(summary) == SUMMARY_KEYS
    assert summary["resolution"] == [24, 14] and summary["secondsPerFrame"] == 0.5
    assert summary["estimates"] == {"1": visibility.as_dict(), "12345.7": budget.as_dict()}
    assert list(budget.as_dict())[-6:] == ["budget", "level", "met", "levels", "refined_fraction", "near_fraction"]
    assert "refined_fraction" not in BudgetEstimate(**visibility.as_dict()).as_dict()     # before the frame's passes
    assert summary["lightingEstimates"] == {"1": {"gi": lighting.as_dict()}}
    json.dumps(summary)

    monkeypatch.setattr(sequence, "render_sequence", lambda job: result)
    record = usdml.Recorder().record_sequence("s.usda", [1, 12345.678], "o.####.exr")
    assert record.frames == [1.0, 12345.678] and record.files == result.outputs and record.resolution == [24, 14]
    assert (record.seconds, record.seconds_per_frame, record.warnings) == (1.25, 0.5, ["a warning"])
    assert record.estimates == {1.0: visibility.as_dict(), 12345.678: budget.as_dict()}
    assert record.lighting_estimates == {1.0: {"gi": lighting.as_dict()}}
    assert record.summary == summary and record.failed == [] and record.rerun is None

    run = DaskRun(failed=[2.0], rerun="2", errors={2.0: "boom"}, startup_seconds=1.0, workers=2, scheduler=None,
                  chunk_size=1, retries=0, threads_per_worker=1)
    on_dask = replace(result, dask=run).as_json()
    assert list(on_dask) == DASK_KEYS and on_dask["errors"] == {"2": "boom"}
    record = usdml.RecordResult.of(replace(result, dask=run))
    assert record.failed == [2.0] and record.rerun == "2" and record.summary == on_dask


def test_the_json_summary_has_the_documented_keys(new_stage, tmp_path, capsys):
    path = _shot(new_stage)
    assert main(["render", path, str(tmp_path / "keys.exr"), "--imageWidth", "8", "--pixel-samples", "1", "--json",
                 "-q"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert list(summary) == SUMMARY_KEYS and summary["frames"] == [1.0] and summary["resolution"] == [8, 8]


def test_the_example_script_relights_a_shot(new_stage, tmp_path):
    path = _shot(new_stage)
    out = tmp_path / "shot.####.exr"
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "record_shot.py"), path, str(out), "--light-scale", "2",
                           "--imageWidth", "12", "--frames", "1"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert str(tmp_path / "shot.0001.exr") in done.stdout
    assert read_exr(tmp_path / "shot.0001.exr")[0]["direct"].max() > 0
