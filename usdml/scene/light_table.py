"""The frame's lights packed for shading: UsdLux's rules as per-light float32 constants, written once.

:class:`LightTable` is what every direct shading reads, the NumPy one (:mod:`usdml.lighting.direct`)
and the fused kernels of the visibility backends (``kernels/voxel/shading.py``, ``kernels/include/light_term.h``
through :func:`usdml.visibility.voxel.native.compiled_lights`); it lives in the render index so that
both layers take it from below. Shaping follows UsdLux: zero outside the cone half-angle, a smoothstep
from ``cos(angle)`` to ``cos(angle·(1−softness))`` across the cone edge, and focus as
``focusTint + (1 − focusTint)·cos^focus θ_l`` (θ_l the angle between the light's axis and the direction
from the light to the point).
"""

from __future__ import annotations

from enum import IntFlag

import numpy as np

from usdml.scene import Lights, LightType

__all__ = ["LightFlag", "LightTable", "cone_edges", "smoothstep_cone"]


def cone_edges(cone_deg: np.ndarray, softness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cos`` of the cone's outer edge and the width in ``cos`` of its soft edge (<= 1e-12: hard)."""
    angle = np.radians(np.minimum(cone_deg, 180.0))
    outer = np.cos(angle)
    return outer, np.cos(angle * (1.0 - np.clip(softness, 0.0, 1.0))) - outer


def smoothstep_cone(cos_l: np.ndarray, cone_deg: np.ndarray, softness: np.ndarray) -> np.ndarray:
    """UsdLux cone with softness: 0 outside ``cone_deg``, smoothstep across the soft edge.

    Float32 in, float32 out (the shading blocks); float64 in, float64 out.
    """
    outer, width = cone_edges(cone_deg, softness)
    hard = width <= 1e-12
    dtype = np.result_type(cos_l, np.float32)
    x = np.where(hard, (cos_l >= outer).astype(dtype), (cos_l - outer) / np.where(hard, 1.0, width))
    x = np.clip(x, 0.0, 1.0)
    return np.where(cone_deg >= 180.0, 1.0, x * x * (3.0 - 2.0 * x)).astype(dtype)


class LightFlag(IntFlag):
    """Bits of :attr:`LightTable.flags`, what the shading needs to know of each light's kind; the Warp
    kernels (``usdml.kernels.voxel.shading``) and ``kernels/include/light_term.h`` test the same bits."""

    DISTANT = 1         #: a distant light: direction ``-axis``, no falloff
    ONE_SIDED = 2       #: disk, rect or triangle: ``max(0, cos θ_l)`` emission profile
    SHAPED = 4          #: shaping cone narrower than 180°
    FOCUSED = 8         #: shaping focus > 0
    CASTS_SHADOWS = 16  #: ShadowAPI ``inputs:shadow:enable``
    CYLINDER = 32       #: cylinder light: projected area of its side


class LightTable:
    """Per-light constants of direct shading (:func:`usdml.lighting.direct.shade_direct`), as float32
    rows ready to broadcast against pixels.

    ``lights`` are the frame's; ``meters_per_unit`` the stage's (falloff in metres); ``min_distance``
    the clamp of the geometry term in scene units. Boolean ``(L,)`` masks ``distant``, ``one_sided``,
    ``shaped``, ``focused``, ``casts``, ``cylinder``; :attr:`flags` packs them.
    """

    def __init__(self, lights: Lights, meters_per_unit: float = 1.0, min_distance: float = 0.0):
        self.n = len(lights)
        self.inv_m2 = np.float32(1.0 / meters_per_unit ** 2)   # 1/d² with d in metres
        self.min_d2 = np.float32(max(min_distance, 1e-12) ** 2)  # clamped geometry term (scene units²)
        self.position = lights.position.T.astype(np.float32)           # (3, L)
        self.axis = lights.axis.T.astype(np.float32)                   # (3, L)
        self.distant = lights.type == LightType.DISTANT
        self.one_sided = np.isin(lights.type, (LightType.DISK, LightType.RECT, LightType.TRIANGLE))
        self.cylinder = lights.type == LightType.CYLINDER
        self.cylinder_axis = lights.cylinder_axis().T.astype(np.float32)   # (3, L)
        self.cone = lights.cone_angle.astype(np.float32)
        self.softness = lights.cone_softness.astype(np.float32)
        self.focus = lights.focus.astype(np.float32)
        self.shaped = lights.cone_angle < 180.0
        self.focused = lights.focus > 0
        tint = lights.focus_tint.astype(np.float64)
        intensity = lights.intensity.astype(np.float64)
        # E = g · (I ⊙ tint + I ⊙ (1 − tint) · cos^focus): two RGB rows per light, so Σ_l is a matmul
        self.base = np.where(self.focused[:, None], intensity * tint, intensity).astype(np.float32)
        self.focus_rgb = np.where(self.focused[:, None], intensity * (1.0 - tint), 0.0).astype(np.float32)
        self.casts = lights.shadow.copy()
        outer, width = cone_edges(lights.cone_angle, lights.cone_softness)
        #: ``(L, 3) float32`` the kernels' cone: cos of the outer edge, the soft edge's width in cos (0:
        #: hard), the focus exponent
        self.kernel_cone = np.stack([outer, np.where(width <= 1e-12, 0.0, width), lights.focus],
                                    axis=1).astype(np.float32)

    @property
    def flags(self) -> np.ndarray:
        """``(L,) int32`` :class:`LightFlag` bits of every light."""
        flags = np.zeros(self.n, np.int32)
        for flag, mask in ((LightFlag.DISTANT, self.distant), (LightFlag.ONE_SIDED, self.one_sided),
                           (LightFlag.SHAPED, self.shaped), (LightFlag.FOCUSED, self.focused),
                           (LightFlag.CASTS_SHADOWS, self.casts), (LightFlag.CYLINDER, self.cylinder)):
            flags[np.asarray(mask, bool)] |= np.int32(flag)
        return flags
