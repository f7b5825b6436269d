"""Depth of field: a thin lens from the camera's ``focalLength``, ``fStop`` and ``focusDistance``.

USD's camera is a thin lens of aperture diameter ``focalLength / fStop`` (lens units: tenths of a scene unit,
GfCamera's ``FOCAL_LENGTH_UNIT``, so a stage in centimetres has millimetres) focused on the plane
``focusDistance`` scene units in front of it (:attr:`usdml.scene.Camera.lens_radius`). A camera ray leaves a
point on the lens (``lens_points``: a unit disk scaled by the radius, in the camera's XY plane) toward where the
pinhole ray through the same film point meets the plane in focus, so that plane is sharp and a point at depth
``z`` is spread over a disk of diameter ``2 r |z − F| / z`` on it (the circle of confusion). fStop 0 (USD's
default) or focusDistance 0 is a pinhole; an orthographic camera has no lens here (said once by the delegate).

Lens points are stratified with the pixel samples: each pixel's ``samples`` points fall one in each cell of an
s × s grid (and of its thin rows and columns: correlated multi-jittered,
:func:`usdml.render.sampling.pixel_offsets`),
mapped to the disk by Shirley and Chiu's concentric map (which keeps the strata compact). The lens cell a pass
takes is shifted per pixel by a seeded offset, so a pixel's sub-pixel cell and lens cell are paired at random (a
fixed pairing would give every pixel the same bias).
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from usdml.render.sampling import pixel_offsets

#: the lens points' stream of random numbers beside the sub-pixel positions' (``0x5A4D``)
_LENS_STREAM = 0x4C45


def concentric_disk(u: np.ndarray) -> np.ndarray:
    """``(N, 2)`` points of the unit square mapped to the unit disk, area-preserving (Shirley and Chiu 1997)."""
    a, b = 2.0 * u[:, 0] - 1.0, 2.0 * u[:, 1] - 1.0
    wide = np.abs(a) > np.abs(b)
    r = np.where(wide, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(wide, np.pi / 4 * (b / a), np.pi / 2 - np.pi / 4 * (a / b))
    phi = np.where(r == 0.0, 0.0, phi)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)


def lens_points(width: int, height: int, samples: int, seed: int) -> Iterator[np.ndarray]:
    """Yield ``samples`` arrays ``(H·W, 2)`` float64 of where on the unit disk each pixel's ray leaves the lens,
    one per pass (module doc). One sample per pixel: a seeded uniform point per pixel."""
    if round(samples ** 0.5) == 1:
        yield concentric_disk(np.random.default_rng([seed, _LENS_STREAM]).random((width * height, 2)))
        return
    for square in pixel_offsets(width, height, samples, seed, _LENS_STREAM, shifted=True):
        yield concentric_disk(square)


def thin_lens_rays(directions: np.ndarray, lens: np.ndarray, radius: float, focus: float,
                   clipping: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-space rays of a thin lens: ``directions`` ``(N, 3)`` unit pinhole directions (looking down -Z),
    ``lens`` ``(N, 2)`` unit-disk points, the lens ``radius`` and ``focus`` distance in scene units. Returns
    ``(origins on the near plane, unit directions, distance to the far plane)``, as the pinhole's."""
    near, far = clipping
    down = -directions[:, 2]
    in_focus = directions * (focus / down)[:, None]     # where the pinhole ray meets the plane in focus
    start = np.zeros_like(directions)
    start[:, :2] = lens * radius
    d = in_focus - start
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    down = -d[:, 2]
    return start + d * (near / down)[:, None], d, (far - near) / down
