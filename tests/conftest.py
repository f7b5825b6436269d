"""Shared fixtures: tiny stages built with pxr inside the tests, paths to real test data."""

from __future__ import annotations

import logging
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


@pytest.fixture
def warnings_log(caplog):
    caplog.set_level(logging.WARNING, logger="usdml")
    return caplog


__all__ = ["Gf", "add_quad", "add_cube_mesh", "world_points", "instance_world_points"]
