"""The AOV registry: every render variable usdml writes, its EXR channels and pixel type.

Names follow Hydra's AOV tokens (``HdAovTokens``) where one exists; usdml adds ``direct``,
``indirect``, ``albedo``, ``shadow`` and ``lightCount``. One table, used by the renderer (buffer
shapes and clear values), by :func:`usdml.aov.exr.write_exr` (channel names, pixel types) and by the
README.

====================  =======================  =======  ==========================================
AOV (aliases)         EXR channels             type     meaning; value where no surface is hit
====================  =======================  =======  ==========================================
``color``             ``R G B A``              half     linear RGBA, premultiplied; 0, or the dome
                                                        or light seen there (visible lights)
``direct``            ``direct.R/G/B``         half     direct (light-to-surface) radiance; 0
``indirect``          ``indirect.R/G/B``       half     indirect (VPL / LGH) radiance; 0
``background``        ``background.R/G/B``     half     the domes' radiance where a camera ray reaches
                                                        nothing (visible lights); 0
``color_noisy``       ``color_noisy.R/G/B/A``  half     ``color`` before ``--denoise`` (``color`` itself
                                                        when the frame is not denoised)
``albedo``            ``albedo.R/G/B``         half     diffuse reflectance of the first hit; 0
``shadow``            ``shadow.Y``             float    fraction of the lights facing the point
                                                        that are blocked (hiddenLightsN / n); 0
``lightCount``        ``lightCount.Y``         float    lights facing the point (the n above); 0
``depth``             ``Z``                    float    camera-space depth along the viewing axis
(``cameraDepth``)                                       (EXR ``worldToCamera`` z, > 0); +inf
``normal`` (``N``)    ``normal.X/Y/Z``         float    world-space unit shading normal; 0
``denoiseNormal``     ``denoiseNormal.X/Y/Z``  float    the shading normal averaged over the pixel's
                                                        rays like color (``--denoise``'s guide); 0
``Neye``              ``Neye.X/Y/Z``           float    normal in USD eye space (-Z forward); 0
``P``                 ``P.X/Y/Z``              float    world-space position; 0
``Peye``              ``Peye.X/Y/Z``           float    position in USD eye space (-Z forward); 0
``primId``            ``primId.id``            uint     prim index; no hit: -1 (stored 0xFFFFFFFF)
``instanceId``        ``instanceId.id``        uint     instance index; -1 (stored 0xFFFFFFFF)
``CryptoObject``      ``CryptoObject00.R/G/B/  float    Cryptomatte of prim paths: ids and coverage of
                      A``, ``01``, ``02``               6 ranks (docs/cryptomatte.md); id 0, coverage 0
``CryptoMaterial``    likewise                 float    Cryptomatte of bound material paths
``CryptoAsset``       likewise                 float    Cryptomatte of asset (kind component) paths
====================  =======================  =======  ==========================================

Choices, and why:

* ``color`` alone uses the unprefixed ``R,G,B,A`` and ``depth`` the unprefixed ``Z``: every EXR
  viewer and compositor shows ``RGBA`` as the image and treats ``Z`` as depth.
* One-channel quantities (``shadow``, ``lightCount``) are ``<aov>.Y``: a lone ``Y`` is OpenEXR's
  luminance channel, so viewers (OIIO ``iv``, tev, Nuke) show the layer as a grey image.
* Ids are 32-bit ``UINT`` channels, OpenEXR's integer pixel type, exact for every id (a float
  channel is exact only below 2**24). In memory ids are signed integers with Hydra's ``-1`` for "no
  prim"; in the file ``-1`` is stored as its 32-bit two's-complement pattern ``0xFFFFFFFF``
  (4294967295), and :func:`usdml.aov.exr.read_exr` gives back ``-1``. Valid ids are 0 .. 2**32-2.
* Colours are half (ample for radiance and reflectance), geometry is float.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

#: the stored value of Hydra's "no prim" id (-1) in a ``uint`` channel
NO_ID = 0xFFFFFFFF

_DTYPES = {"half": np.float16, "float": np.float32, "uint": np.uint32}


@dataclass(frozen=True)
class AovSpec:
    """One AOV: its name, EXR channel suffixes, pixel type and clear value."""

    name: str
    suffixes: tuple[str, ...]   #: channel names (``prefixed=False``) or what follows ``<layer>.``
    pixel_type: str             #: "half", "float" or "uint"
    clear: float                #: value of a pixel no surface covers (ids: -1)
    description: str
    prefixed: bool = True       #: False for ``color`` (``R,G,B,A``) and ``depth`` (``Z``)
    hydra: bool = False         #: the name is one of Hydra's AOV tokens
    #: averaged over a pixel's primary rays (box filter); otherwise the value of the ray nearest the
    #: pixel centre (depth, positions and normals are not meaningful averaged, ids not at all, as in Hydra)
    filtered: bool = False
    #: a Cryptomatte AOV (:mod:`usdml.aov.cryptomatte`): each pass gives an id per pixel, and the ids are ranked by
    #: the fraction of a pixel's passes that hit them, written as ``<layer>00 .. 02`` (rank id, coverage, ...)
    ranked: bool = False
    separator: str = "."        #: between the layer and a suffix (Cryptomatte's ``CryptoObject00.R``: none)

    @property
    def components(self) -> int:
        return len(self.suffixes)

    @property
    def dtype(self) -> type:
        """NumPy dtype of the channels *in the file* (in memory ids are signed, see module doc)."""
        return _DTYPES[self.pixel_type]

    @property
    def is_id(self) -> bool:
        return self.pixel_type == "uint"

    def channels(self, layer: str | None = None) -> tuple[str, ...]:
        """EXR channel names; ``layer`` renames the layer prefix (a RenderVar's name)."""
        if not self.prefixed:
            return self.suffixes
        prefix = layer or self.name
        return tuple(f"{prefix}{self.separator}{s}" for s in self.suffixes)

    def shape(self, height: int, width: int) -> tuple[int, ...]:
        """Buffer shape: ``(H, W)`` for one channel, ``(H, W, C)`` otherwise (row 0 = top)."""
        return (height, width) if self.components == 1 else (height, width, self.components)

    def empty(self, height: int, width: int) -> np.ndarray:
        """A buffer filled with the clear value (float32; ids as int64 with -1)."""
        if self.is_id:
            return np.full(self.shape(height, width), -1, np.int64)
        return np.full(self.shape(height, width), self.clear, np.float32)


#: Cryptomatte's layers and what names their ids (:mod:`usdml.aov.cryptomatte`)
CRYPTOMATTE = {"CryptoObject": "prim paths", "CryptoMaterial": "bound material paths",
               "CryptoAsset": "asset (kind component) paths"}
#: ranks per Cryptomatte AOV: the specification's suggested default, 3 RGBA layers
RANKS = 6
#: a Cryptomatte AOV's channels after its layer name: ``00.R`` (rank 0 id), ``00.G`` (its coverage), ``00.B``
#: (rank 1 id), ``00.A``, ``01.R`` ..
RANK_CHANNELS = tuple(f"{k // 4:02d}.{'RGBA'[k % 4]}" for k in range(2 * RANKS))

_RGB = ("R", "G", "B")
_XYZ = ("X", "Y", "Z")

AOVS: dict[str, AovSpec] = {a.name: a for a in (
    AovSpec("color", ("R", "G", "B", "A"), "half", 0.0,
            "linear RGBA radiance, premultiplied by alpha", prefixed=False, hydra=True, filtered=True),
    AovSpec("direct", _RGB, "half", 0.0, "direct radiance from the scene's lights", filtered=True),
    AovSpec("indirect", _RGB, "half", 0.0, "indirect radiance (virtual point lights / LGH)", filtered=True),
    AovSpec("diffuse", _RGB, "half", 0.0, "direct radiance of the diffuse lobe (direct = diffuse + specular)",
            filtered=True),
    AovSpec("specular", _RGB, "half", 0.0, "direct radiance of the specular and clearcoat lobes", filtered=True),
    AovSpec("emission", _RGB, "half", 0.0, "emitted radiance seen: emissiveColor of the surface, or the area "
            "light in front of it (visible lights)", filtered=True),
    AovSpec("background", _RGB, "half", 0.0, "the domes' radiance seen where a camera ray reaches nothing "
            "(visible lights)", filtered=True),
    AovSpec("color_noisy", ("R", "G", "B", "A"), "half", 0.0, "color before denoising (--denoise; color itself "
            "when the frame is not denoised)", filtered=True),
    AovSpec("albedo", _RGB, "half", 0.0, "diffuse reflectance at the first hit", filtered=True),
    AovSpec("shadow", ("Y",), "float", 0.0,
            "fraction of the lights facing the point that are blocked (hiddenLightsN / n)", filtered=True),
    AovSpec("lightCount", ("Y",), "float", 0.0, "number of lights facing the point (n)", filtered=True),
    AovSpec("depth", ("Z",), "float", float("inf"),
            "camera-space depth along the viewing axis, positive in front (EXR camera z)",
            prefixed=False, hydra=True),
    AovSpec("normal", _XYZ, "float", 0.0, "world-space unit shading normal", hydra=True),
    AovSpec("denoiseNormal", _XYZ, "float", 0.0, "world-space shading normal averaged over the pixel's rays as "
            "color is (not unit length at edges): the denoiser's guide, as Cycles' Denoising Normal", filtered=True),
    AovSpec("Neye", _XYZ, "float", 0.0, "unit normal in USD eye space (camera looks down -Z)",
            hydra=True),
    AovSpec("P", _XYZ, "float", 0.0, "world-space position"),
    AovSpec("Peye", _XYZ, "float", 0.0, "position in USD eye space (camera looks down -Z)",
            hydra=True),
    AovSpec("primId", ("id",), "uint", -1, "prim index, -1 where no prim", hydra=True),
    AovSpec("instanceId", ("id",), "uint", -1, "instance index, -1 where no instance", hydra=True),
    *(AovSpec(name, RANK_CHANNELS, "float", 0.0, f"Cryptomatte {what}: 6 ranks of (id, coverage)", ranked=True,
              separator="") for name, what in CRYPTOMATTE.items()),
)}

#: other names accepted for an AOV (Hydra's ``cameraDepth``, RenderMan's ``N``)
ALIASES: dict[str, str] = {"cameraDepth": "depth", "N": "normal"}


def get_aov(name: str) -> AovSpec:
    """The AOV called ``name`` (or an alias); KeyError naming the known AOVs otherwise."""
    spec = find_aov(name)
    if spec is None:
        raise KeyError(f"unknown AOV {name!r}; known: {', '.join(AOVS)} "
                       f"(aliases: {', '.join(f'{a}={b}' for a, b in ALIASES.items())})")
    return spec


#: the prefix of a light group's AOV, ``lightgroup:NAME`` (the direct light of the lights whose
#: ``usdml:lightGroup`` is NAME; ``lightgroup:default``: the lights that name none)
LIGHT_GROUP = "lightgroup:"
#: ``--aovs``' word for one ``lightgroup:NAME`` per group the stage's lights name
EVERY_LIGHT_GROUP = LIGHT_GROUP + "*"


def is_light_group(name: str) -> bool:
    """Whether ``name`` is a light group's AOV (``lightgroup:NAME``, the wildcard aside)."""
    return name.startswith(LIGHT_GROUP) and len(name) > len(LIGHT_GROUP) and name != EVERY_LIGHT_GROUP


def light_group(name: str) -> str:
    """The group a ``lightgroup:NAME`` AOV shows."""
    return name[len(LIGHT_GROUP):]


def find_aov(name: str) -> AovSpec | None:
    if is_light_group(name):
        return AovSpec(name, _RGB, "half", 0.0, f"direct radiance of light group {light_group(name)}", filtered=True)
    return AOVS.get(ALIASES.get(name, name))


# --- RenderVar -> AOV ---------------------------------------------------------------------------

#: ``sourceType`` "raw" / "intrinsic" ``sourceName`` -> AOV (exact, case-sensitive)
RAW_SOURCE_NAMES: dict[str, str] = {
    "color": "color", "Ci": "color", "rgba": "color", "RGBA": "color", "beauty": "color",
    "depth": "depth", "cameraDepth": "depth", "z": "depth", "Z": "depth",
    "normal": "normal", "N": "normal", "Neye": "Neye",
    "P": "P", "Peye": "Peye",
    "primId": "primId", "instanceId": "instanceId",
    "direct": "direct", "indirect": "indirect", "albedo": "albedo", "color_noisy": "color_noisy",
    "denoiseNormal": "denoiseNormal",
    "diffuse": "diffuse", "specular": "specular", "emission": "emission", "background": "background",
    "shadow": "shadow", "lightCount": "lightCount",
    # Cryptomatte: its layer names, and Arnold's AOV names for them
    **{name: name for name in CRYPTOMATTE}, "crypto_object": "CryptoObject", "crypto_material": "CryptoMaterial",
    "crypto_asset": "CryptoAsset",
}

#: ``sourceType`` "lpe" expressions (whitespace ignored, ``lpe:`` prefix optional) -> AOV.
#: RenderMan's directDiffuse / directSpecular LPEs are usdml's ``diffuse`` / ``specular``, its emission ``CO``
#: ``emission``; indirect light is gathered from the diffuse lobe only, so indirectDiffuse is ``indirect``. A light
#: seen by the camera (``CL``, Arnold's emission ``C[LO]``) is ``emission``, the dome seen behind everything
#: Arnold's background ``CB``: ``background`` (visible lights; a dome is the one light usdml writes there).
LPE_SOURCE_NAMES: dict[str, str] = {
    "C.*": "color", "C.*[<L.>O]": "color", "C.*L": "color",
    "C<RD>L": "diffuse", "CDL": "diffuse", "C<RD>[<L.>O]": "diffuse", "CD[<L.>O]": "diffuse",
    "C<RS>L": "specular", "CSL": "specular", "C<RS>[<L.>O]": "specular", "CS[<L.>O]": "specular",
    "CO": "emission", "C<O>": "emission", "CL": "emission", "C<L>": "emission", "C[LO]": "emission",
    "CB": "background", "C<B>": "background",
    "C<RD>.+L": "indirect", "CD.+L": "indirect", "C<RD>.+[<L.>O]": "indirect",
    "CD.+[<L.>O]": "indirect",
}


def aov_for_render_var(source_name: str, source_type: str = "raw") -> AovSpec | None:
    """The usdml AOV a ``UsdRenderVar`` (``sourceName``, ``sourceType``) asks for, or None.

    * ``raw`` / ``intrinsic`` (and an empty type): :data:`RAW_SOURCE_NAMES` -- Hydra's tokens
      (``color``, ``depth``, ``cameraDepth``, ``normal``, ``Neye``, ``Peye``, ``primId``,
      ``instanceId``), RenderMan's (``Ci``, ``N``, ``P``, ``z``) and usdml's own names. A raw name
      ``lpe:<expr>`` (Hydra's spelling) is read as an LPE.
    * ``lpe``: :data:`LPE_SOURCE_NAMES` (``C.*`` -> color; directDiffuse / indirectDiffuse
      expressions -> direct / indirect).
    * ``primvar`` and anything unknown: None; the caller warns and skips the RenderVar.

    Note Hydra's ``depth`` is an NDC depth in Storm; usdml's ``depth`` is always camera-space
    depth (Hydra's ``cameraDepth``), and both names map to it. A RenderVar's ``dataType`` does not
    change what usdml writes (see :func:`data_type_matches`).
    """
    name = (source_name or "").strip()
    kind = (source_type or "raw").strip()
    if kind in ("raw", "intrinsic") and name.startswith("lpe:"):
        kind, name = "lpe", name[4:]
    if kind in ("raw", "intrinsic"):
        if is_light_group(name):
            return find_aov(name)
        aov = RAW_SOURCE_NAMES.get(name)
    elif kind == "lpe":
        aov = LPE_SOURCE_NAMES.get(re.sub(r"\s+", "", name.removeprefix("lpe:")))
    else:
        aov = None
    return AOVS[aov] if aov else None


_DATA_TYPE_COMPONENTS = {
    "float": 1, "half": 1, "double": 1,
    "int": 1, "uint": 1, "int64": 1, "uint64": 1,
    "float2": 2, "half2": 2, "double2": 2,
    "float3": 3, "half3": 3, "double3": 3, "color3f": 3, "color3h": 3, "color3d": 3,
    "point3f": 3, "point3h": 3, "point3d": 3, "normal3f": 3, "normal3h": 3, "normal3d": 3,
    "vector3f": 3, "vector3h": 3, "vector3d": 3,
    "float4": 4, "half4": 4, "double4": 4, "color4f": 4, "color4h": 4, "color4d": 4,
}


def data_type_matches(aov: AovSpec, data_type: str | None) -> bool:
    """Whether a RenderVar ``dataType`` has the AOV's component count (True if unknown / empty).

    ``color`` also accepts 3-component types (``color3f``, UsdRender's fallback): usdml still
    writes ``R,G,B,A``. Integer types match only the id AOVs. Callers warn on False and write the
    AOV in its own layout anyway.
    """
    if not data_type:
        return True
    n = _DATA_TYPE_COMPONENTS.get(data_type)
    if n is None:
        return True
    if data_type.startswith(("int", "uint")) != aov.is_id:
        return False
    if aov.ranked:          # the layout is the Cryptomatte specification's whatever type the RenderVar names
        return True
    if aov.name == "color":
        return n in (3, 4)
    return n == aov.components
