"""Snapshots built directly from the ``usdml.scene`` dataclasses (no USD stage), shared by the
visibility tests: meshes from points or triangle soups, prototypes, transforms."""

from __future__ import annotations

import numpy as np

from usdml.scene import Lights, Mesh, Prototype, Snapshot


def mesh(path: str, points, triangles, id: int = 0, deforming: bool = False) -> Mesh:
    points = np.asarray(points, np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int32).reshape(-1, 3)
    t = triangles.shape[0]
    return Mesh(path=path, id=id, points=points, triangles=triangles,
                normals=np.zeros((t, 3, 3), np.float32), albedo=np.ones((t, 3, 3), np.float32),
                face_index=np.arange(t, dtype=np.int32), deforming=deforming)


def soup(path: str, tris: np.ndarray, id: int = 0, deforming: bool = False) -> Mesh:
    """A mesh from a ``(T, 3, 3)`` triangle soup."""
    tris = np.asarray(tris, np.float32)
    return mesh(path, tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3), id, deforming)


def prototype(path: str, meshes: list[Mesh], xforms, animated: bool = False) -> Prototype:
    xforms = np.asarray(xforms, np.float64).reshape(-1, 4, 4)
    n = xforms.shape[0]
    return Prototype(path=path, name=path, kind="pointInstancer", meshes=meshes, xforms=xforms,
                     instance_ids=np.arange(100, 100 + n, dtype=np.int64), instancers=[path] * n,
                     animated=animated)


def snapshot(meshes=(), prototypes=(), time: float = 1.0) -> Snapshot:
    meshes, prototypes = list(meshes), list(prototypes)
    paths = [m.path for m in meshes] + [m.path for p in prototypes for m in p.meshes]
    return Snapshot(time=time, stage_path="test.usda", meshes=meshes, prototypes=prototypes,
                    lights=Lights.concat([]), camera=None, render_settings=None, mesh_paths=paths)


def translate(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def rot_y(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = c, s, -s, c
    return m
