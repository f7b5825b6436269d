"""The small scenes every backend is checked on (tests/test_backends.py, tests/test_voxel_native.py):
a single occluder lit by point and distant lights; moving instances of one prototype (Alg. 4); a
deforming mesh (Alg. 5); many moving instances (the instance BVH). Two frames each."""

from __future__ import annotations

import numpy as np

from usdml.lighting.direct import facing_pairs
from usdml.scene import Lights, LightType

from plain_scenes import prototype, rot_y, snapshot, soup, translate
from voxel_reference import box


def lights(rng, n_point: int = 16) -> Lights:
    """``n_point`` point lights above the scene, a disk and a spot among them, and three distant lights."""
    n = n_point + 3
    kind = np.full(n, LightType.POINT, np.int8)
    kind[3], kind[n_point:] = LightType.DISK, LightType.DISTANT
    pos = np.c_[rng.uniform(-8, 8, n), rng.uniform(3, 9, n), rng.uniform(-8, 8, n)]
    axis = np.tile([0.0, -1.0, 0.0], (n, 1))
    axis[n_point:] = [[0.4, -1.0, 0.2], [-0.7, -0.5, 0.1], [0.1, -0.6, -0.8]]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    cone = np.full(n, 180.0)
    cone[5] = 50.0
    return Lights(type=kind, position=pos, axis=axis, xform=np.tile(np.eye(4), (n, 1, 1)),
                  radiance=np.ones((n, 3), np.float32), intensity=rng.uniform(1, 5, (n, 3)).astype(np.float32),
                  radius=np.zeros(n), width=np.zeros(n), height=np.zeros(n), angle=np.zeros(n),
                  cone_angle=cone, cone_softness=np.full(n, 0.2), focus=np.zeros(n),
                  focus_tint=np.ones((n, 3), np.float32), shadow=np.ones(n, bool),
                  paths=[f"/l{i}" for i in range(n)], instance_ids=np.full(n, -1, np.int64))


GROUND = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)
PLANE = [soup("/plane/m", np.concatenate([box((-2, -0.2, -0.5), (2, 0.2, 0.5)), box((-0.3, -0.1, -2.5), (0.3, 0.1, 2.5))]))]


def scene_frames(scene: str) -> list:
    """Two snapshots of ``scene`` (occluder: the same geometry twice)."""
    if scene == "occluder":
        tower = soup("/tower", box((-1.5, 0, -1), (1.5, 4, 1)), id=2)
        return [snapshot([GROUND, tower], time=t) for t in (1.0, 2.0)]
    if scene == "instances":
        def frame(t):
            xf = [translate(-5 + t, 3, 0) @ rot_y(30 * t), translate(4, 2 + t, 3) @ rot_y(-60),
                  translate(0, 2.5, -5 + t) @ rot_y(15 * t)]
            return snapshot([GROUND], [prototype("/plane", PLANE, xf, animated=True)], time=t)
        return [frame(1.0), frame(2.0)]
    if scene == "many_instances":
        def frame(t):
            xf = [translate(-8 + 1.6 * i, 2 + 0.3 * j + 0.1 * t, -8 + 1.6 * j) @ rot_y(7 * i + 11 * j + 20 * t)
                  for i in range(11) for j in range(11)]
            return snapshot([GROUND], [prototype("/plane", PLANE, xf, animated=True)], time=t)
        return [frame(1.0), frame(2.0)]
    if scene == "deforming":
        def frame(t):
            blob = soup("/blob", box((-2 + t, 0.5, -1), (1 + t, 2 + t, 1.5)), id=2, deforming=True)
            return snapshot([GROUND, blob], time=t)
        return [frame(1.0), frame(2.0)]
    raise ValueError(scene)


def surface_points(rng, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Points on the ground (normal +Y) where the scenes cast their shadows."""
    return np.c_[rng.uniform(-9, 9, n), np.zeros(n), rng.uniform(-9, 9, n)], np.tile([0.0, 1.0, 0.0], (n, 1))


def queries(points, normals, lit: Lights):
    """The shadow queries direct lighting asks (facing pairs), concatenated."""
    blocks = list(facing_pairs(points, normals, lit))
    o, t, nrm, dist = (np.concatenate([b[k] for b in blocks]) for k in range(4))
    return o, t, dict(normals=nrm, distant=dist.astype(bool))
