"""A surface material as usdml renders it, whatever authored it: the UsdPreviewSurface inputs each fed by a
constant, a primvar or an image. Two readers fill it (:mod:`usdml.stage.materials` from UsdShade networks,
:mod:`usdml.stage.materialx` from MaterialX's common surfaces); one evaluator turns it into per-corner and
per-hit values (:mod:`usdml.stage.materials`).

Input names and defaults are UsdPreviewSurface's (:data:`PREVIEW_DEFAULTS`, the specification's fallbacks).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Union

#: every UsdPreviewSurface input usdml renders, with the specification's fallback value
PREVIEW_DEFAULTS: dict[str, tuple[float, ...]] = {
    "diffuseColor": (0.18, 0.18, 0.18),
    "emissiveColor": (0.0, 0.0, 0.0),
    "useSpecularWorkflow": (0.0,),
    "specularColor": (0.0, 0.0, 0.0),
    "metallic": (0.0,),
    "roughness": (0.5,),
    "clearcoat": (0.0,),
    "clearcoatRoughness": (0.01,),
    "opacity": (1.0,),
    "opacityThreshold": (0.0,),
    "ior": (1.5,),
    "normal": (0.0, 0.0, 1.0),
    "occlusion": (1.0,),
}


@dataclass(frozen=True)
class Constant:
    value: tuple[float, ...]


@dataclass(frozen=True)
class Primvar:
    """A primvar of the gprim (found with inheritance), ``width`` floats per value; ``fallback`` where absent."""

    name: str
    width: int
    fallback: tuple[float, ...]
    node: str = ""          #: the reader's path, for messages


@dataclass(frozen=True)
class Transform2d:
    """``st' = R(rotation) · (st · scale) + translation`` (UsdTransform2d; rotation in degrees)."""

    scale: tuple[float, float] = (1.0, 1.0)
    rotation: float = 0.0
    translation: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class Image:
    """A texture lookup (UsdUVTexture's semantics; MaterialX image nodes map onto it)."""

    node: str                               #: the node's path, for messages
    file: str                               #: resolved path; "" when it does not resolve
    authored: str                           #: the file as authored (messages, UDIM detection)
    st: Union[Primvar, Constant]            #: texture coordinates
    transforms: tuple[Transform2d, ...] = ()  #: applied to st in order
    wrap_s: str = "useMetadata"             #: repeat, clamp, mirror, black or useMetadata
    wrap_t: str = "useMetadata"
    color_space: str = "auto"               #: auto, sRGB or raw
    scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    bias: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    fallback: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    fallback_authored: bool = False
    output: str = "rgb"                     #: rgb, rgba, r, g, b or a
    #: a UDIM set: ``(tile number, resolved path)`` of each tile found (``file`` is then the anchored pattern)
    tiles: tuple[tuple[int, str], ...] = ()
    #: a MaterialX ``normalmap``-style remap applied after scale/bias is expressed by scale/bias themselves


Source = Union[Constant, Primvar, Image]


@dataclass
class SurfaceNetwork:
    """One material's surface: the preview inputs that are authored or connected (the rest take
    :data:`PREVIEW_DEFAULTS`), and what it authors that usdml does not render (one warning per material)."""

    material: str                                   #: the material's path
    origin: str                                     #: "UsdPreviewSurface", "standard_surface", "open_pbr_surface"
    inputs: dict[str, Source] = field(default_factory=dict)
    unsupported: list[str] = field(default_factory=list)   #: e.g. "inputs:displacement", "node ND_noise3d"
