"""Frames on Dask (usdml.render.farm): a LocalCluster render equals a one-process render pixel for pixel,
a worker killed with SIGKILL mid-sequence costs a retry and never a frame, a frame that fails every
attempt is reported with a FrameSpec to render it again and a non-zero exit."""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pytest

import usdml
from conftest import STAGES, add_quad
from pxr import Sdf, UsdLux, UsdRender
from usdml.aov.exr import is_complete_exr, read_exr
from usdml.cli import main
from usdml.render.farm import chunks, rerun_spec

pytest.importorskip("distributed")
pytest.importorskip("embreex")

PARK = str(STAGES / "park.usda")


def test_chunks_and_the_rerun_framespec():
    assert chunks([1.0, 2.0, 3.0, 4.0, 5.0], 2) == [[1.0, 2.0], [3.0, 4.0], [5.0]]
    assert chunks([1.0], 4) == [[1.0]]
    assert rerun_spec([7.0, 2.0, 2.5]) == "2,2.5,7"


def test_frames_on_a_local_cluster_equal_one_process(tmp_path, capsys):
    args = ["--frames", "1:3", "--imageWidth", "16", "--pixel-samples", "1", "--aovs", "color,shadow,depth"]
    assert main(["render", PARK, str(tmp_path / "one" / "p.####.exr"), *args]) == 0
    capsys.readouterr()
    assert main(["render", PARK, str(tmp_path / "farm" / "p.####.exr"), *args, "--workers", "2", "--chunk-size", "2",
                 "--nthreads", "1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == [1.0, 2.0, 3.0] and summary["failed"] == [] and summary["rerun"] is None
    assert summary["threadsPerWorker"] == 1 and summary["startupSeconds"] > 0
    for f in (1, 2, 3):
        one = read_exr(tmp_path / "one" / f"p.{f:04d}.exr")[0]
        farm = read_exr(tmp_path / "farm" / f"p.{f:04d}.exr")[0]
        for aov in one:
            np.testing.assert_array_equal(one[aov], farm[aov])


def test_a_retry_keeps_what_this_run_wrote_with_its_settings(tmp_path):
    """Issue 38: the farm's retry rule is --resume's test: a file written since the run started (here: dated
    in the future) counts as this run's only if its settings digest is this render's; such a frame is done
    and its file in ``files``, a file with other settings is rendered again."""
    out = str(tmp_path / "p.####.exr")
    settings = dict(aovs=["color"], pixel_samples=1)
    usdml.Recorder(image_width=12, **settings).record_sequence(PARK, "1", out)
    usdml.Recorder(image_width=8, **settings).record_sequence(PARK, "2", out)
    future = time.time() + 3600
    for f in (1, 2):
        os.utime(tmp_path / f"p.000{f}.exr", (future, future))
    result = usdml.Recorder(image_width=12, workers=1, **settings).record_sequence(PARK, "1:3", out)
    assert result.frames == [1.0, 2.0, 3.0] and result.failed == [] and result.skipped == []
    assert result.files == [str(tmp_path / f"p.000{f}.exr") for f in (1, 2, 3)]
    assert os.stat(tmp_path / "p.0001.exr").st_mtime == pytest.approx(future)          # kept
    assert read_exr(tmp_path / "p.0002.exr")[0]["color"].shape[1] == 12                # rendered again


def _is_worker(proc) -> bool:
    """A Dask worker process (multiprocessing's spawned child), not its resource tracker."""
    try:
        cmd = " ".join(proc.cmdline())
    except Exception:
        return False
    return "spawn_main" in cmd and "resource_tracker" not in cmd


def test_frames_on_a_running_scheduler_equal_one_process(tmp_path, capsys):
    from distributed import LocalCluster

    args = ["--frames", "1:2", "--imageWidth", "12", "--pixel-samples", "1", "--aovs", "color"]
    assert main(["render", PARK, str(tmp_path / "one" / "p.####.exr"), *args]) == 0
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert main(["render", PARK, str(tmp_path / "sch" / "p.####.exr"), *args, "--scheduler",
                     cluster.scheduler_address]) == 0
    for f in (1, 2):
        np.testing.assert_array_equal(read_exr(tmp_path / "one" / f"p.{f:04d}.exr")[0]["color"],
                                      read_exr(tmp_path / "sch" / f"p.{f:04d}.exr")[0]["color"])
    assert "frame 2 done" in capsys.readouterr().err


@pytest.mark.slow
def test_a_killed_worker_costs_a_retry_never_a_frame(tmp_path):
    """Every worker process is killed (SIGKILL) once the first frame is on disk; the nannies start new
    ones, the lost chunks run again, and every frame ends complete (about 40 s)."""
    import psutil

    out = tmp_path / "k" / "p.####.exr"
    frames = "1:8"
    box = {}

    def render():
        rec = usdml.Recorder(image_width=48, aovs=["color"], pixel_samples=4, workers=2, retries=3)
        box["result"] = rec.record_sequence(PARK, frames, str(out))

    t = threading.Thread(target=render)
    t.start()
    me = psutil.Process(os.getpid())
    killed = []
    deadline = time.time() + 120
    while time.time() < deadline and not killed and t.is_alive():
        written = list((tmp_path / "k").glob("p.*.exr")) if (tmp_path / "k").exists() else []
        workers = [p for p in me.children(recursive=True) if _is_worker(p)]
        if written and workers:
            for p in workers:                  # every worker process, mid-sequence
                os.kill(p.pid, signal.SIGKILL)
                killed.append(p.pid)
        time.sleep(0.05)
    t.join(300)
    assert killed, "no worker was running to be killed"
    result = box["result"]
    assert result.failed == [] and sorted(result.frames) == [float(f) for f in range(1, 9)]
    for f in range(1, 9):
        path = tmp_path / "k" / f"p.{f:04d}.exr"
        assert path.exists() and is_complete_exr(str(path))
    assert not [p for p in (tmp_path / "k").iterdir() if not p.name.endswith(".exr")]   # no partial file left


def test_a_frame_that_fails_every_attempt_is_reported_with_a_rerun_framespec(new_stage, tmp_path, capsys):
    stage = new_stage(start=1, end=3)
    add_quad(stage, "/World/ground", size=20)
    UsdLux.SphereLight.Define(stage, "/World/bulb").AddTranslateOp().Set((0, 4, 0))
    (tmp_path / "blocker").write_text("a file where frame 2's folder must go")
    product = UsdRender.Product.Define(stage, "/Render/Product")
    name = product.CreateProductNameAttr()
    for f, path in ((1, tmp_path / "ok" / "a.0001.exr"), (2, tmp_path / "blocker" / "b.exr"),
                    (3, tmp_path / "ok" / "a.0003.exr")):
        name.Set(str(path), f)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets([Sdf.Path("/Render/Product")])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    path = stage.GetRootLayer().realPath
    code = main(["render", path, "--frames", "1:3", "--imageWidth", "8", "--workers", "2", "--retries", "1", "--json"])
    out, err = capsys.readouterr()
    assert code == 1
    summary = json.loads(out)
    assert summary["frames"] == [1.0, 3.0] and summary["failed"] == [2.0] and summary["rerun"] == "2"
    assert "cannot create the output folder" in summary["errors"]["2"]
    assert "--frames 2" in err and "Traceback" not in err
    assert (tmp_path / "ok" / "a.0001.exr").exists() and (tmp_path / "ok" / "a.0003.exr").exists()


def test_motion_blur_and_lens_on_a_cluster_equal_one_process(tmp_path, capsys):
    """Each pass a time slice and a lens point: frames rendered on two workers (each renderer starting from a
    different frame) equal one process's, pixel for pixel."""
    from pxr import Usd, UsdGeom

    layer = Sdf.Layer.CreateNew(str(tmp_path / "blurred.usda"))
    layer.subLayerPaths.append(PARK)
    stage = Usd.Stage.Open(layer)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/main_cam"))
    cam.CreateShutterOpenAttr(-0.25)
    cam.CreateShutterCloseAttr(0.25)
    cam.CreateFStopAttr(0.5)
    cam.CreateFocusDistanceAttr(30.0)
    layer.Save()
    args = ["--frames", "1:3", "--imageWidth", "16", "--pixel-samples", "4", "--aovs", "color,depth"]
    assert main(["render", layer.identifier, str(tmp_path / "one" / "p.####.exr"), *args]) == 0
    assert main(["render", layer.identifier, str(tmp_path / "farm" / "p.####.exr"), *args, "--workers", "2",
                 "--chunk-size", "1", "--nthreads", "1"]) == 0
    capsys.readouterr()
    for f in (1, 2, 3):
        one, header = read_exr(tmp_path / "one" / f"p.{f:04d}.exr")
        assert header["usdml:shutter:slices"] == 4 and header["usdml:lens:fStop"] == 0.5
        farm = read_exr(tmp_path / "farm" / f"p.{f:04d}.exr")[0]
        for aov in one:
            np.testing.assert_array_equal(one[aov], farm[aov])
