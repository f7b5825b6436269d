"""Shared fixtures: tiny stages built with pxr inside the tests, paths to real test data."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

import usdml  # noqa: F401  (registers the schemas before pxr builds its schema registry)
from pxr import Gf, Usd, UsdGeom

from usdml.scene import instance_points

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT.parent / "shared" / "assets"
STAGES = ROOT / "stages"


@pytest.fixture
def assets() -> Path:
    if not ASSETS.is_dir():
        pytest.skip(f"real test data not found at {ASSETS} (shared/ beside the checkout)")
    return ASSETS


@pytest.fixture
def new_stage(tmp_path):
    """``new_stage(name="s.usda", start=1, end=1)`` -> a fresh stage saved under tmp_path."""

    def make(name: str = "s.usda", start: float | None = None, end: float | None = None) -> Usd.Stage:
        stage = Usd.Stage.CreateNew(str(tmp_path / name))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        if start is not None:
            stage.SetStartTimeCode(start)
            stage.SetEndTimeCode(end if end is not None else start)
        return stage

    return make


def add_quad(stage: Usd.Stage, path: str, size: float = 1.0, y: float = 0.0) -> UsdGeom.Mesh:
    """A unit quad in the XZ plane facing +Y."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    s = size / 2
    mesh.CreatePointsAttr([(-s, y, -s), (-s, y, s), (s, y, s), (s, y, -s)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return mesh


def add_cube_mesh(stage: Usd.Stage, path: str, size: float = 1.0) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    s = size / 2
    pts = [(x, y, z) for x in (-s, s) for y in (-s, s) for z in (-s, s)]
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    return mesh


def world_points(stage: Usd.Stage, path: str, time: float) -> np.ndarray:
    """Reference: a mesh's points through USD's own local-to-world transform."""
    prim = stage.GetPrimAtPath(path)
    m = np.array(UsdGeom.XformCache(time).GetLocalToWorldTransform(prim))
    p = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(time), np.float64)
    return p @ m[:3, :3] + m[3, :3]


def instance_world_points(proto, mesh_index: int = 0) -> np.ndarray:
    """(N, V, 3) world points of every instance of a usdml Prototype (:func:`usdml.scene.instance_points`)."""
    return instance_points(proto.xforms, proto.meshes[mesh_index].points)


#: albedo of :func:`ground_stage`'s ground
ALBEDO = 0.5


def add_top_camera(stage, height: float = 15.0):
    """``/World/main_cam`` looking straight down at the origin from ``height`` (90 degrees of view, square): a
    stage's own camera, so a ground is seen from above and not framed edge-on by usdml's (issue 55)."""
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(18)
    cam.CreateHorizontalApertureAttr(36)
    cam.CreateVerticalApertureAttr(36)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 1000))
    cam.AddTranslateOp().Set((0, height, 0))
    cam.AddRotateXOp().Set(-90)
    return cam


def ground_stage(new_stage, light, name: str = "s.usda"):
    """A 40 x 40 ground (albedo 0.5) seen from straight above, lit by ``light(stage)``, saved as ``name``."""
    stage = new_stage(name, start=1, end=1)
    ground = add_quad(stage, "/World/ground", size=40)
    ground.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    add_top_camera(stage)
    light(stage)
    stage.Save()
    return stage.GetRootLayer().realPath


def render_aovs(path, width=64, aovs=("direct", "P", "normal", "shadow", "color")):
    """The buffers of ``aovs`` of the stage's start frame, ``width`` × ``width`` pixels, one ray per pixel, the
    lights unseen (the light on the surfaces, not the lights in front of them)."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    d = StageDelegate(path)
    # point values at P: one ray through each pixel centre
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, visible_lights=False))
    try:
        return r.render(d.start_time, width, width, set(aovs)).buffers
    finally:
        r.close()


def assert_direct(b, expected_e, min_lit=0.3):
    """direct == albedo/π · E to 1e-3 relative where E is not tiny."""
    got = b["direct"][..., 0].astype(np.float64)
    want = ALBEDO / math.pi * expected_e
    mask = want > 1e-3 * want.max()
    assert mask.mean() > min_lit
    rel = np.abs(got[mask] - want[mask]) / want[mask]
    assert rel.max() < 1e-3, rel.max()
    assert np.all(got[~mask] <= 1e-3 * want.max() * (1 + 1e-3))


@pytest.fixture(scope="module")
def small_city():
    """:func:`voxel_reference.small_city_scene`, built once per test module."""
    from voxel_reference import small_city_scene

    return small_city_scene()


def _cuda_available() -> bool:
    """Whether Warp sees a CUDA device (False, not an error, where Warp has no CUDA build or driver)."""
    try:
        import warp as wp

        wp.config.quiet = True
        wp.init()
        return wp.is_cuda_available()
    except Exception:   # no usable Warp: the cuda cases skip, and the cpu ones fail loudly on their own
        return False


#: one case per Warp device, as Warp's own tests (``add_function_test``) and Mitsuba's variant fixtures do:
#: the CUDA path runs wherever a GPU exists and is skipped, by name, where there is none
DEVICES = [
    pytest.param("cpu", id="cpu"),
    pytest.param("cuda:0", id="cuda_0", marks=pytest.mark.skipif(not _cuda_available(), reason="no CUDA device")),
]


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """The Warp device a kernel test runs on: ``cpu``, and ``cuda:0`` where a GPU is present."""
    return request.param


@pytest.fixture
def warnings_log(caplog):
    caplog.set_level(logging.WARNING, logger="usdml")
    return caplog


__all__ = ["Gf", "add_quad", "add_cube_mesh", "world_points", "instance_world_points", "ALBEDO", "ground_stage",
           "render_aovs", "assert_direct"]


def gi_frame(stage, width: int, vpl_count: int, time=None):
    """A stage's frame (default: its start) at ``width`` px for indirect light: ``(snapshot, exact backend,
    G-buffer, hit points, normals, albedo, VPLs)``."""
    from dataclasses import replace

    from usdml.lighting.vpl import generate_vpls
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer
    from usdml.scene import diff
    from usdml.stage import StageDelegate
    from usdml.visibility import ExactBackend

    d = StageDelegate(str(stage))
    snap = d.snapshot(d.start_time if time is None else time)
    ex = ExactBackend()
    ex.update(snap, diff(None, snap))
    w, h = snap.camera.resolution(width)
    gb = build_gbuffer(replace(snap, camera=conform_camera(snap.camera, w, h)), ex, w, h)
    hit = gb.hit.ravel()
    pts, nrm, alb = (gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit], gb.albedo.reshape(-1, 3)[hit])
    vpls = generate_vpls(snap, ex, snap.lights, vpl_count, 3, seed=0)
    return snap, ex, gb, pts, nrm, alb, vpls


@pytest.fixture(scope="module")
def cornell():
    """cornell.usda's frame 1 at 48 px for indirect light: ``(snapshot, exact backend, G-buffer, hit points,
    normals, albedo, 3,000 VPLs)``."""
    return gi_frame(STAGES / "cornell.usda", 48, 3000, time=1)
