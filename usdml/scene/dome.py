"""A dome light at one timecode as plain data (:class:`Dome`), and the lat-long map convention it uses.

:func:`usdml.stage.dome.read_dome` reads a ``UsdLux.DomeLight`` / ``DomeLight_1`` into a :class:`Dome`;
:func:`usdml.lighting.dome.dome_to_distant_lights` turns it into K distant lights per frame. No ``pxr`` here.

Radiometry
----------
Emitted radiance toward the scene from direction ω (ω points from the scene *toward* the sky):
``L(ω) = radiance ⊙ texture(ω)`` with ``radiance = intensity · 2^exposure · color (· blackbody) · diffuse``
(as :mod:`usdml.stage.lights`; ``diffuse`` is folded in because usdml shades Lambertian surfaces only),
and ``texture(ω)`` the lat-long map's linear RGB (1 for a constant dome). The map is piecewise constant
per texel (nearest filtering): the sampler and the brute-force reference integrate the same function.

Lat-long convention
-------------------
Source: OpenUSD ``pxr/usd/usdLux/schema.usda``, the docs of classes ``DomeLight`` and ``DomeLight_1``,
which quote the OpenEXR lat-long specification (read at OpenUSD commit 59992d2). The dome's default
orientation has its top pole on +Y. A pixel's x is longitude, its y latitude: the
top-left corner of the data window is latitude +π/2, longitude +π, the bottom-right latitude −π/2,
longitude −π. Latitude 0 / longitude 0 points to +Z (the image's centre column faces +Z), latitude 0 /
longitude +π/2 to +X (the column at a quarter of the width faces +X, the three-quarter column −X,
the left and right edges −Z). With image coordinates ``u = x / W`` (0 at the left edge, 1 at the
right) and ``v = y / H`` (0 at the top):

    φ = π (1 − 2u)   (longitude),    θ = π v   (angle from the +Y pole)
    ω_dome = (sin θ sin φ,  cos θ,  sin θ cos φ)

Hydra Storm samples its lat-long maps the same way (``pxr/imaging/hdSt/shaders/surfaceHelpers.glslfx``
``ProjectToLatLong``: ``u = (atan2(z, x) + π/2) / 2π``, ``v = acos(y) / π``, which is the inverse of the
formula above). Like Storm, usdml puts the poles and ±π on the image's *edges* (texture coordinates);
OpenEXR's ``LatLongMap`` puts them on the centres of the first and last pixels, half a texel away.

:attr:`Dome.to_world` rotates dome space into the world (the pole axis and the prim's transform, see
:mod:`usdml.stage.dome`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Dome", "latlong_directions", "latlong_texel"]


def latlong_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dome-space unit directions for image coordinates ``u = x/W`` (from the left), ``v = y/H`` (from the top).

    Longitude φ = π(1 − 2u), polar angle θ = πv from the +Y pole: ω = (sin θ sin φ, cos θ, sin θ cos φ).
    """
    phi, theta = np.broadcast_arrays(np.pi * (1.0 - 2.0 * np.asarray(u, np.float64)),
                                     np.pi * np.asarray(v, np.float64))
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), s * np.cos(phi)], axis=-1)


def latlong_texel(directions: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Column ``i`` and row ``j`` (row 0 = top) of the texel holding each dome-space unit direction."""
    d = np.asarray(directions, np.float64)
    phi = np.arctan2(d[..., 0], d[..., 2])
    theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
    u = (1.0 - phi / np.pi) / 2.0
    i = np.floor(u * width).astype(np.int64) % width
    j = np.clip(np.floor(theta / np.pi * height).astype(np.int64), 0, height - 1)
    return i, j


@dataclass(eq=False)
class Dome:
    """A dome light at one timecode, as plain data (no ``pxr``)."""

    path: str
    radiance: np.ndarray            #: (3,) float64 intensity · 2^exposure · color (· blackbody) · diffuse
    texture: np.ndarray | None      #: (H, W, 3) float32 linear RGB lat-long map, None for a constant dome
    to_world: np.ndarray            #: (3, 3) float64 rotation, dome space -> world (column convention)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: (3,) world translation (unused for shading)
    shadow: bool = True             #: ``inputs:shadow:enable``
    texture_file: str = ""          #: resolved path of the map ("" when none or unreadable)
    pole_axis: str = "Y"            #: the pole actually used: "Y" or "Z"

    @property
    def constant(self) -> bool:
        return self.texture is None

    def radiance_at(self, directions: np.ndarray) -> np.ndarray:
        """``(N, 3)`` radiance L(ω) toward the scene from world directions ``(N, 3)`` (pointing at the sky)."""
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        if self.texture is None:
            return np.broadcast_to(self.radiance, d.shape).copy()
        local = d @ self.to_world          # R^T ω for each row
        i, j = latlong_texel(local, self.texture.shape[1], self.texture.shape[0])
        return self.texture[j, i].astype(np.float64) * self.radiance
