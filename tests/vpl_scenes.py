"""Scenes for light-transport tests (VPLs, cylinder lights): meshes with face normals and an albedo,
single lights as ``usdml.scene.Lights``, an exact backend over a snapshot."""

from __future__ import annotations

import numpy as np

from usdml.scene import Lights, LightType, Mesh, Snapshot
from usdml.visibility.exact import ExactBackend


def mesh(path: str, points, triangles, albedo=(1.0, 1.0, 1.0), id: int = 0) -> Mesh:
    """A mesh with per-triangle face normals (as wound) and a constant albedo."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int32).reshape(-1, 3)
    t = triangles.shape[0]
    p = points[triangles].astype(np.float64)
    ng = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    return Mesh(path=path, id=id, points=points, triangles=triangles,
                normals=np.repeat(ng[:, None, :], 3, axis=1).astype(np.float32),
                albedo=np.broadcast_to(np.asarray(albedo, np.float32), (t, 3, 3)).copy(),
                face_index=np.arange(t, dtype=np.int32))


def box(lo, hi, albedo=(1.0, 1.0, 1.0)) -> Mesh:
    """A watertight indexed box (8 shared corners, 12 triangles)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = [np.where([(i >> k) & 1 for k in range(3)], hi, lo) for i in range(8)]
    quads = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return mesh("/box", pts, tris, albedo)


def snapshot(meshes, meters_per_unit: float = 1.0) -> Snapshot:
    meshes = list(meshes)
    return Snapshot(time=1.0, stage_path="test.usda", meshes=meshes, prototypes=[], lights=Lights.empty(),
                    camera=None, render_settings=None, mesh_paths=[m.path for m in meshes],
                    meters_per_unit=meters_per_unit)


def light(type=LightType.POINT, position=(0.0, 0.0, 0.0), axis=(0.0, -1.0, 0.0), intensity=(1.0, 1.0, 1.0),
          cone=180.0, softness=0.0, focus=0.0, tint=(0.0, 0.0, 0.0)) -> Lights:
    z1 = np.zeros(1)
    xf = np.eye(4)[None].copy()
    xf[0, :3, 3] = position
    return Lights(type=np.array([int(type)], np.int8), position=np.array([position], float),
                  axis=np.array([axis], float) / np.linalg.norm(axis), xform=xf,
                  radiance=np.array([intensity], np.float32), intensity=np.array([intensity], np.float32),
                  radius=z1.copy(), width=z1.copy(), height=z1.copy(), angle=z1.copy(),
                  cone_angle=np.array([cone]), cone_softness=np.array([softness]), focus=np.array([focus]),
                  focus_tint=np.array([tint], np.float32), shadow=np.ones(1, bool), paths=["/light"],
                  instance_ids=np.full(1, -1, np.int64))


def backend_for(snap: Snapshot) -> ExactBackend:
    b = ExactBackend(workers=1)
    b.update(snap, None)
    return b
