"""``tools/embree_motion_blur.py`` drives the Embree 4 library bundled in embreex's wheel through ctypes, with the
ray and packet layouts declared by hand from Embree's headers. These tests check those declarations against the
geometry of a moving square whose coverage at every time is known: a wrong field offset (origin, time, tfar), a
wrong time-step slot or a wrong valid mask gives other answers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

import embree_motion_blur as emb  # noqa: E402

SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
#: the square's x offset at its time steps, spread evenly over ray times [0, 1]: out to 3 and part of the way back
OFFSETS = (0.0, 3.0, 2.0, 1.0)


@pytest.fixture(scope="module")
def embree():
    path = emb.library_path()
    if path is None:
        pytest.skip("embreex's bundled libembree4 not found")
    device = emb.Embree(path)
    yield device
    device.close()


def offset_at(tau: np.ndarray) -> np.ndarray:
    """The square's x offset at ray time ``tau``: linear between the time steps, as Embree moves vertices."""
    return np.interp(tau, np.linspace(0, 1, len(OFFSETS)), OFFSETS)


def down_rays(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays straight down onto the plane z = 0 at ``x`` (y = 0.5), from z = 1, 2 long."""
    o = np.stack([x, np.full(len(x), 0.5), np.ones(len(x))], axis=1).astype(np.float32)
    d = np.tile(np.array([[0, 0, -1]], np.float32), (len(x), 1))
    return o, d, np.full(len(x), 2.0, np.float32)


@pytest.mark.parametrize("width", emb.WIDTHS)
@pytest.mark.parametrize("loop", [False, True], ids=["ctypes", "compiled"])
def test_moving_square_is_where_its_time_steps_put_it(embree, width, loop):
    if loop and emb.compiled_loop() is None:
        pytest.skip("no C compiler for the compiled loop")
    # 19 rays: packets of 4, 8 and 16 end with a partial one (valid mask)
    tau = np.linspace(0.0, 1.0, 19, dtype=np.float32)
    x = (np.arange(19) % 5 * 1.1 + 0.05).astype(np.float32)          # 0.05 .. 4.45, never on an edge
    x[16:] = 1.8, 1.8, 1.5          # every lane of the last (partial) packet on the square
    inside = (x > offset_at(tau)) & (x < offset_at(tau) + 1)
    assert inside[16:].all() and 3 < inside.sum() < 16                 # both answers are tested
    scene = embree.scene([([SQUARE + np.float32([dx, 0, 0]) for dx in OFFSETS], TRIANGLES)])
    packets = emb.Packets(*down_rays(x), tau, width=width)
    embree.occluded(scene, packets, loop=loop)
    embree.release(scene)
    np.testing.assert_array_equal(packets.blocked(), inside)


def test_time_steps_agree_with_static_scenes_of_the_same_pose(embree):
    x = np.linspace(-0.45, 4.45, 50).astype(np.float32)
    rays = down_rays(x)
    steps = [SQUARE + np.float32([dx, 0, 0]) for dx in OFFSETS]
    moving = embree.scene([(steps, TRIANGLES)])
    for j, pose in enumerate(steps):
        static = embree.scene([([pose], TRIANGLES)])
        a = emb.Packets(*rays, width=8)
        b = emb.Packets(*rays, np.full(len(x), j / (len(steps) - 1), np.float32), width=8)
        embree.occluded(static, a)
        embree.occluded(moving, b)
        embree.release(static)
        assert a.blocked().any()
        np.testing.assert_array_equal(a.blocked(), b.blocked())
    embree.release(moving)
