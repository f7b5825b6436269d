"""Resolve a gprim's bound surfaces to what the renderer samples (:class:`usdml.scene.shading.MeshShading`), as Hydra
does: every UsdPreviewSurface input per triangle corner, images sampled again at each hit.

What is resolved, and how (each rule follows Hydra / Storm or the UsdPreviewSurface specification):

* **Binding**: ``UsdShade.MaterialBindingAPI.ComputeBoundMaterial`` with purpose ``full``, then
  ``preview`` (what a final-quality Hydra render delegate asks for). USD itself handles inherited,
  direct and collection-based bindings and ``bindMaterialAs`` strength. Prims inside a native
  prototype (``/__Prototype_N/...``) see the bindings authored inside the instanced asset; pass
  ``instance=`` (an instance prim of that prototype) to resolve through that instance's instance
  proxy instead, so bindings authored on or above the instance apply too. GeomSubsets of family
  ``materialBind`` (element type ``face``) bind their own material to their faces, the first subset naming a face
  winning; the other faces take the prim's.
* **Surface**: ``UsdShadeMaterial.ComputeSurfaceSource`` for the universal render context, then any
  other context's surface output, keeping the first whose shader is ``UsdPreviewSurface`` (or
  MaterialX's ``ND_UsdPreviewSurface_surfaceshader``, whose inputs are the same): Storm's choice where a material
  has both a preview surface and a MaterialX one. Else MaterialX's standard_surface or open_pbr_surface, authored
  as ``ND_`` nodes in the file or in a referenced ``.mtlx`` document, mapped onto the preview inputs
  (:mod:`usdml.stage.materialx`); a binding whose target prim is missing because its ``.mtlx`` reference did not
  compose is read from that document. Materials with none of these give None (the caller shades those faces
  with displayColor, Lambertian, as Storm's fallback surface does) with one warning per material.
* **Inputs**: every UsdPreviewSurface input (:data:`usdml.stage.network.PREVIEW_DEFAULTS`), its value-producing
  attribute followed through material interface inputs: a constant (authored, else the spec's fallback), a
  ``UsdUVTexture`` output (``rgb``, ``rgba``, ``r``, ``g``, ``b`` or ``a``), or a ``UsdPrimvarReader_*``.
  Colours and weights are clipped to [0, 1]; ``emissiveColor``, ``ior`` and ``normal`` keep their range.
  ``displacement``, inputs that are not the spec's, shaders usdml does not evaluate and UDIM sets with no tile on
  disk are said once per material and listed in :attr:`MaterialResolver.unsupported` (``usdml info``).
* **Texture coordinates**: ``UsdUVTexture.inputs:st`` from a ``UsdPrimvarReader_float2`` (``varname``
  string or token, possibly from a material interface input), optionally through a
  ``UsdTransform2d``; the primvar is found on the gprim with inheritance and expanded per corner.
* **Texels**: each image is read once per resolved path with OpenImageIO into a NumPy array (kept at
  its file's precision: 8-bit images stay uint8) and sampled bilinearly in NumPy, vectorized over
  all corners. A TextureSystem lookup per corner from Python would be far slower, and with no
  derivatives (one sample per vertex) it reduces to a bilinear lookup on the top MIP level anyway;
  sampling ourselves also gives exact control of the four wrap modes.
* **Colour spaces**: texels are linearized *before* filtering, as a GPU sRGB texture format does.
  ``sRGB`` applies the exact piecewise sRGB curve to R, G, B (never alpha); ``raw`` leaves values as
  they are; ``auto`` means sRGB for 8-bit images with 3 or 4 channels and raw otherwise (float and
  half EXRs, 16-bit images, single-channel masks) — Hio's rule, which Storm applies.
* **Wrap**: ``repeat``, ``clamp``, ``mirror`` (mirrored repeat) and ``black`` (zero outside the
  image). ``useMetadata`` (the default) reads OpenImageIO's ``wrapmodes`` metadata (written by
  ``maketx``) and otherwise means ``repeat``, which is what Storm does for files without metadata.
* ``inputs:scale`` / ``inputs:bias`` apply to the linear rgba sample: ``rgba * scale + bias``.
  A file that cannot be read gives ``inputs:fallback`` (authored, else the spec's (0, 0, 0, 1)),
  used as the node's output as is, with one warning naming the value used. UDIM sets (``<UDIM>`` in the file name,
  anchored to the layer that authored it, since usd-core resolves none) read every tile 1001-1100 found beside it;
  st picks tile ``1001 + ⌊s⌋ + 10⌊t⌋``, sampled clamped at its edges, and st on no tile gives the fallback.
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from pxr import Ar, Sdf, Usd, UsdGeom, UsdShade

from usdml.scene.shading import Field, MeshShading
from usdml.stage.network import PREVIEW_DEFAULTS, Constant, Image, Primvar, SurfaceNetwork, Transform2d

if TYPE_CHECKING:       # mesh.py may import this module: no import cycle at run time
    from usdml.stage.mesh import Topology

#: UsdPreviewSurface's fallback diffuseColor
DIFFUSE_FALLBACK = (0.18, 0.18, 0.18)
#: UsdUVTexture's fallback output when its file cannot be read
TEXTURE_FALLBACK = (0.0, 0.0, 0.0, 1.0)

_PREVIEW_IDS = ("UsdPreviewSurface", "ND_UsdPreviewSurface_surfaceshader")
_PURPOSES = (UsdShade.Tokens.full, UsdShade.Tokens.preview)
_WRAPS = ("repeat", "clamp", "mirror", "black")
#: OpenImageIO ``wrapmodes`` metadata names -> UsdUVTexture wrap tokens
_OIIO_WRAPS = {"periodic": "repeat", "clamp": "clamp", "mirror": "mirror", "black": "black"}


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The exact piecewise sRGB decoding curve (IEC 61966-2-1)."""
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


_SRGB_LUT = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)


# --------------------------------------------------------------------------------------------------
@dataclass
class Texture:
    """One image as read from disk: ``pixels`` (H, W, C) at the file's precision, top row first."""

    pixels: np.ndarray
    eight_bit: bool
    wrap_metadata: tuple[str, str] | None

    @property
    def channels(self) -> int:
        return self.pixels.shape[2]

    def _texels(self, iy: np.ndarray, ix: np.ndarray, srgb: bool) -> np.ndarray:
        """Linear rgba ``(N, 4)`` float32 for integer texel coordinates (already wrapped into range)."""
        raw = self.pixels[iy, ix]                                     # (N, C)
        c = self.channels
        if raw.dtype == np.uint8:
            vals = _SRGB_LUT[raw] if srgb else raw.astype(np.float32) / 255.0
            if srgb and c in (2, 4):                                  # alpha stays linear
                vals[:, c - 1] = raw[:, c - 1].astype(np.float32) / 255.0
        else:
            vals = raw.astype(np.float32)
            if raw.dtype == np.uint16:
                vals /= 65535.0
            if srgb:
                n_color = 1 if c <= 2 else 3
                vals[:, :n_color] = srgb_to_linear(vals[:, :n_color])
        n = len(vals)
        if c == 1:
            return np.concatenate([np.repeat(vals, 3, axis=1), np.ones((n, 1), np.float32)], axis=1)
        if c == 2:                                                    # luminance + alpha
            return np.concatenate([np.repeat(vals[:, :1], 3, axis=1), vals[:, 1:2]], axis=1)
        if c == 3:
            return np.concatenate([vals, np.ones((n, 1), np.float32)], axis=1)
        return vals[:, :4]

    def sample(self, st: np.ndarray, wrap_s: str, wrap_t: str, srgb: bool) -> np.ndarray:
        """Bilinear linear-rgba ``(N, 4)`` at texture coordinates ``st`` (N, 2); (0, 0) is the bottom-left."""
        h, w = self.pixels.shape[:2]
        st = np.nan_to_num(np.asarray(st, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(-1e7, 1e7)
        x = st[:, 0] * w - 0.5                   # texel centres at (i + 0.5) / w
        y = (1.0 - st[:, 1]) * h - 0.5           # image rows run top to bottom
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        out = np.zeros((len(st), 4), np.float32)
        for dy, wy in ((0, 1.0 - fy), (1, fy)):
            iy, vy = _wrap(y0 + dy, h, wrap_t)
            for dx, wx in ((0, 1.0 - fx), (1, fx)):
                ix, vx = _wrap(x0 + dx, w, wrap_s)
                weight = wx * wy * (vx & vy)
                out += weight[:, None] * self._texels(iy, ix, srgb)
        return out


@dataclass(eq=False)
class TextureLookup:
    """An image feeding one surface input, ready to sample per hit (plain NumPy, kept on the Mesh).

    ``sample(st)`` applies wrap modes, colour space, ``scale``/``bias``, the node's output (``rgb``, ``rgba``, or one
    channel), the input's width and, for colours and weights, the [0, 1] clip, exactly as the per-corner values do.
    """

    texture: Texture
    wrap_s: str
    wrap_t: str
    srgb: bool
    scale: np.ndarray       #: (4,)
    bias: np.ndarray        #: (4,)
    output: str = "rgb"     #: rgb, rgba, r, g, b or a
    width: int = 3          #: floats of the input it feeds
    clip: bool = True       #: clip to [0, 1] (colours and weights; not emission nor normals)

    def sample(self, st: np.ndarray) -> np.ndarray:
        """``(N, width)`` float32 linear values at texture coordinates ``st`` ``(N, 2)``."""
        rgba = self.texture.sample(np.asarray(st, np.float32).reshape(-1, 2), self.wrap_s, self.wrap_t,
                                   self.srgb) * self.scale + self.bias
        v = _widen(_select(rgba, self.output), self.width)
        return (np.clip(v, 0.0, 1.0) if self.clip else v).astype(np.float32)


def _wrap(i: np.ndarray, n: int, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """Texel index ``i`` wrapped into ``[0, n)`` and whether the texel exists (False only for ``black``)."""
    if mode == "clamp":
        return i.clip(0, n - 1), np.ones(len(i), bool)
    if mode == "mirror":
        m = np.mod(i, 2 * n)
        return np.where(m >= n, 2 * n - 1 - m, m), np.ones(len(i), bool)
    if mode == "black":
        return i.clip(0, n - 1), (i >= 0) & (i < n)
    return np.mod(i, n), np.ones(len(i), bool)


def read_texture(path: str) -> Texture:
    """Read an image with OpenImageIO (subimage 0, top MIP level); raise OSError when it cannot.

    A path inside a package (``pkg.usdz[tex.png]``) is read through USD's asset resolver and handed to
    OpenImageIO as a temporary file.
    """
    import OpenImageIO as oiio

    if path.endswith("]") and "[" in path:
        asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(path))
        if asset is None:
            raise OSError(f"cannot open {path} through the asset resolver")
        inner = path[path.rindex("[") + 1:-1]
        fd, tmp = tempfile.mkstemp(suffix=os.path.splitext(inner)[1])
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(asset.GetBuffer())
            return read_texture(tmp)
        finally:
            os.unlink(tmp)
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise OSError(oiio.geterror() or f"cannot open {path}")
    try:
        spec = inp.spec()
        base = spec.format.basetype
        fmt = {oiio.UINT8: oiio.UINT8, oiio.UINT16: oiio.UINT16, oiio.HALF: oiio.HALF}.get(base, oiio.FLOAT)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None or spec.width <= 0 or spec.height <= 0:
            raise OSError(inp.geterror() or f"cannot read the pixels of {path}")
        wrap = spec.get_string_attribute("wrapmodes", "")
    finally:
        inp.close()
    pixels = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    modes = [_OIIO_WRAPS.get(m.strip()) for m in wrap.split(",")] if wrap else []
    meta = None
    if modes and all(modes):
        meta = (modes[0], modes[1] if len(modes) > 1 else modes[0])
    return Texture(pixels=pixels, eight_bit=base == oiio.UINT8, wrap_metadata=meta)


# --------------------------------------------------------------------------------------------------
def shader_id(shader: UsdShade.Shader) -> str:
    sid = shader.GetShaderId()
    if not sid:
        sid = shader.GetIdAttr().Get()
    return str(sid or "")


def value_source(inp: UsdShade.Input | None) -> Usd.Attribute | None:
    """The attribute producing ``inp``'s value: a shader output, or an input holding a value; None when
    nothing is connected nor authored."""
    if not inp:
        return None
    attrs = inp.GetValueProducingAttributes(False)
    if attrs:
        return attrs[0]
    return inp.GetAttr() if inp.GetAttr().HasValue() else None


def is_output(attr: Usd.Attribute) -> bool:
    return UsdShade.Utils.GetType(attr.GetName()) == UsdShade.AttributeType.Output


def _value(shader: UsdShade.Shader, name: str, time: Usd.TimeCode, default):
    """A constant input's value (following interface connections), else ``default``."""
    attr = value_source(shader.GetInput(name))
    if attr is None or is_output(attr):
        return default
    v = attr.Get(time)
    return default if v is None else v


def _token(shader: UsdShade.Shader, name: str, time: Usd.TimeCode, default: str) -> str:
    return str(_value(shader, name, time, default) or default)


def _vec(v, n: int) -> np.ndarray:
    a = np.asarray(v, np.float32).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, n)
    return np.concatenate([a[:n], np.zeros(max(0, n - a.size), np.float32)])


def as_numbers(v, n: int) -> tuple[float, ...] | None:
    """``v`` as ``n`` floats (a scalar repeated, a longer vector cut), or None when it is not numeric."""
    try:
        a = np.asarray(v, np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    if a.size == 0 or not np.isfinite(a).all():
        return None
    return tuple(float(x) for x in _vec(a, n))


_UDIM = re.compile(r"<udim>", re.IGNORECASE)


def udim_tiles(attr: Usd.Attribute, authored: str, time: Usd.TimeCode) -> tuple[str, tuple[tuple[int, str], ...]]:
    """``(anchored pattern, ((tile, path), ...))`` of a UDIM file name (``<UDIM>`` standing for 1001-1100): the
    pattern anchored to the layer that authored it (usd-core resolves no UDIM path), its tiles found on disk."""
    pattern = authored
    stack = attr.GetPropertyStack(time)
    if stack and not os.path.isabs(authored):
        pattern = stack[0].layer.ComputeAbsolutePath(authored)
    folder, name = os.path.split(pattern)
    if not folder or not os.path.isdir(folder):
        return pattern, ()
    head, tail = _UDIM.split(name, maxsplit=1)
    match = re.compile(re.escape(head) + r"(1\d{3})" + re.escape(tail) + r"$")
    tiles = []
    for entry in sorted(os.listdir(folder)):
        m = match.match(entry)
        if m and 1001 <= int(m.group(1)) <= 1100:
            tiles.append((int(m.group(1)), os.path.join(folder, entry)))
    return pattern, tuple(tiles)


@dataclass(eq=False)
class UdimTexture:
    """A UDIM set as one texture: tile ``1001 + ⌊s⌋ + 10⌊t⌋`` holds st in [⌊s⌋, ⌊s⌋ + 1) × [⌊t⌋, ⌊t⌋ + 1);
    coordinates on no tile (or outside 0 ≤ s < 10, t ≥ 0) give ``missing`` (the node's fallback)."""

    tiles: dict                     #: tile number -> :class:`Texture`
    missing: np.ndarray             #: (4,) rgba where no tile is

    @property
    def pixels(self) -> np.ndarray:             # the first tile's: its size stands for the set's texel size
        return next(iter(self.tiles.values())).pixels

    @property
    def eight_bit(self) -> bool:
        return all(t.eight_bit for t in self.tiles.values())

    @property
    def channels(self) -> int:
        return max(t.channels for t in self.tiles.values())

    wrap_metadata = None

    def sample(self, st: np.ndarray, wrap_s: str, wrap_t: str, srgb: bool) -> np.ndarray:
        """Bilinear linear rgba (N, 4) of each st in its tile (clamped at the tile's edges, as tiles are)."""
        st = np.nan_to_num(np.asarray(st, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(-1e7, 1e7)
        cell = np.floor(st)
        number = (1001 + cell[:, 0] + 10 * cell[:, 1]).astype(np.int64)
        number[(cell[:, 0] < 0) | (cell[:, 0] > 9) | (cell[:, 1] < 0)] = -1
        out = np.broadcast_to(np.asarray(self.missing, np.float32), (len(st), 4)).copy()
        for tile, texture in self.tiles.items():
            rows = np.flatnonzero(number == tile)
            if len(rows):
                out[rows] = texture.sample(st[rows] - cell[rows], "clamp", "clamp", srgb)
        return out


def fallback_words(fallback: np.ndarray, authored: bool) -> str:
    """How a warning names the ``inputs:fallback`` a UsdUVTexture gives in place of its file: the value, and when
    it is not authored, that it is the spec's black (a whole material, a whole frame black)."""
    values = ", ".join(f"{v:g}" for v in fallback)
    return f"inputs:fallback ({values})" + ("" if authored else ", unauthored: the spec's default black")


_READER_WIDTH = {"float": 1, "float2": 2, "float3": 3, "normal": 3, "point": 3, "vector": 3, "float4": 4,
                 "int": 1, "string": 0}
#: inputs whose value is a colour or weight in [0, 1] (clipped where evaluated); the others keep their range
_UNIT_INPUTS = {"diffuseColor", "specularColor", "metallic", "roughness", "clearcoat", "clearcoatRoughness",
                "opacity", "occlusion"}


class _PreviewReader:
    """Reads one UsdPreviewSurface shader into a :class:`SurfaceNetwork` (UsdShade side only: no texels read)."""

    def __init__(self, material: str, time: Usd.TimeCode):
        self.material, self.time = material, time
        self.net = SurfaceNetwork(material=material, origin="UsdPreviewSurface")

    def unsupported(self, item: str) -> None:
        if item not in self.net.unsupported:
            self.net.unsupported.append(item)

    def read(self, shader: UsdShade.Shader) -> SurfaceNetwork:
        for inp in shader.GetInputs():
            name = inp.GetBaseName()
            if name == "displacement":
                attr = value_source(inp)
                if attr is not None and (is_output(attr) or np.any(np.asarray(attr.Get(self.time) or 0.0))):
                    self.unsupported("inputs:displacement (not rendered)")
                continue
            if name not in PREVIEW_DEFAULTS:
                if value_source(inp) is not None:
                    self.unsupported(f"inputs:{name} (not a UsdPreviewSurface input)")
                continue
            source = self.source(inp, name, len(PREVIEW_DEFAULTS[name]))
            if source is not None:
                self.net.inputs[name] = source
        return self.net

    def source(self, inp: UsdShade.Input, name: str, width: int):
        """What drives input ``name`` (``width`` floats): a Constant, Primvar or Image; None: the default."""
        attr = value_source(inp)
        if attr is None:
            return None
        if not is_output(attr):
            v = attr.Get(self.time)
            if v is None:
                return None
            numbers = as_numbers(v, width)
            if numbers is None:
                default = ", ".join(f"{x:g}" for x in PREVIEW_DEFAULTS[name])
                self.unsupported(f"inputs:{name} = {v!r} is not a number (type {attr.GetTypeName()}); using "
                                 f"the default {default}")
                return None
            return Constant(numbers)
        own = as_numbers(inp.GetAttr().Get(self.time), width) if inp.GetAttr().HasValue() else None
        node = UsdShade.Shader(attr.GetPrim())
        sid = shader_id(node)
        out_name = str(UsdShade.Utils.GetBaseNameAndType(attr.GetName())[0])
        if sid == "UsdUVTexture":
            return self.image(node, out_name, name, own)
        if sid.startswith("UsdPrimvarReader_"):
            return self.primvar(node, sid)
        what = f"{node.GetPath()} ({sid})" if sid else f"{node.GetPath()} (a shader with no info:id)"
        fallback = own if own is not None else PREVIEW_DEFAULTS[name]
        self.unsupported(f"inputs:{name} comes from {what}, which usdml does not evaluate; using "
                         f"{', '.join(f'{x:g}' for x in fallback)} (author a UsdUVTexture, a primvar reader or a "
                         "constant)")
        return Constant(fallback) if own is not None else None

    def primvar(self, node: UsdShade.Shader, sid: str) -> Primvar:
        kind = sid[len("UsdPrimvarReader_"):]
        width = _READER_WIDTH.get(kind, 3) or 1
        name = str(_value(node, "varname", self.time, "") or "")
        fallback = as_numbers(_value(node, "fallback", self.time, 0.0), width) or (0.0,) * width
        return Primvar(name=name, width=width, fallback=fallback, node=str(node.GetPath()))

    def st(self, inp: UsdShade.Input | None, seen: tuple = ()):
        """(st source, transforms) of a UsdUVTexture's ``inputs:st`` (``seen``: the UsdTransform2d nodes on the way,
        so that a connection cycle is said, not followed)."""
        attr = value_source(inp)
        if attr is None:
            return Constant((0.0, 0.0)), ()
        if not is_output(attr):
            return Constant(as_numbers(attr.Get(self.time), 2) or (0.0, 0.0)), ()
        node = UsdShade.Shader(attr.GetPrim())
        sid = shader_id(node)
        if sid.startswith("UsdPrimvarReader_"):
            reader = self.primvar(node, sid)
            return Primvar(reader.name, 2, as_numbers(reader.fallback, 2), reader.node), ()
        if sid == "UsdTransform2d" and str(node.GetPath()) in seen:
            self.unsupported(f"texture coordinates: a connection cycle through {node.GetPath()}; using (0, 0) (break "
                             "the cycle)")
            return Constant((0.0, 0.0)), ()
        if sid == "UsdTransform2d":
            src, inner = self.st(node.GetInput("in"), seen + (str(node.GetPath()),))
            step = Transform2d(scale=tuple(_vec(_value(node, "scale", self.time, (1.0, 1.0)), 2).tolist()),
                               rotation=float(_value(node, "rotation", self.time, 0.0)),
                               translation=tuple(_vec(_value(node, "translation", self.time, (0.0, 0.0)), 2).tolist()))
            return src, inner + (step,)
        what = f"{node.GetPath()} ({sid or 'no id'})"
        self.unsupported(f"texture coordinates come from {what}, which usdml does not evaluate; using (0, 0) (use a "
                         "UsdPrimvarReader_float2)")
        return Constant((0.0, 0.0)), ()

    def image(self, node: UsdShade.Shader, output: str, name: str, own):
        path = str(node.GetPath())
        asset = _value(node, "file", self.time, None)
        raw_path = getattr(asset, "path", "") or ""
        resolved = getattr(asset, "resolvedPath", "") or ""
        tiles: tuple = ()
        if "<UDIM>" in raw_path.upper():
            resolved, tiles = udim_tiles(node.GetInput("file").GetAttr(), raw_path, self.time)
            if not tiles:
                value = own if own is not None else PREVIEW_DEFAULTS[name]
                self.unsupported(f"{path}.inputs:file {raw_path}: no tile of the UDIM set was found (1001-1100 beside "
                                 f"{resolved or raw_path}); using the {name} value "
                                 f"{', '.join(f'{x:g}' for x in value)}")
                return Constant(value)
        authored = _value(node, "fallback", self.time, None)
        st, transforms = self.st(node.GetInput("st"))
        return Image(node=path, file=resolved, authored=raw_path, st=st, transforms=transforms,
                     wrap_s=_token(node, "wrapS", self.time, "useMetadata"),
                     wrap_t=_token(node, "wrapT", self.time, "useMetadata"),
                     color_space=_token(node, "sourceColorSpace", self.time, "auto"),
                     scale=tuple(_vec(_value(node, "scale", self.time, (1.0,) * 4), 4).tolist()),
                     bias=tuple(_vec(_value(node, "bias", self.time, (0.0,) * 4), 4).tolist()),
                     fallback=tuple(_vec(TEXTURE_FALLBACK if authored is None else authored, 4).tolist()),
                     fallback_authored=authored is not None, output=output, tiles=tiles)


class MaterialResolver:
    """Resolves bound surfaces (UsdPreviewSurface, else MaterialX's common surfaces) of gprims and their
    GeomSubsets; caches per stage: bindings, surfaces, textures.

    ``warn`` receives one-line messages naming the prim or material and what to do; it is expected to
    de-duplicate, and the resolver also reports each (material, problem) once.
    """

    def __init__(self, warn: Callable[[str], None]):
        self.warn = warn
        self._stage: Usd.Stage | None = None
        self._bindings: dict[str, str | None] = {}
        self._surfaces: dict[str, Sdf.Path | None] = {}
        self._networks: dict[tuple[str, float], SurfaceNetwork | None] = {}
        self._textures: dict[str, Texture | None] = {}
        self._warned: set[tuple[str, str]] = set()
        #: material path -> what it authors that usdml does not render (``usdml info``'s ``unsupported``)
        self.unsupported: dict[str, list[str]] = {}

    # ----------------------------------------------------------------------------------------------
    def _warn_once(self, key: str, kind: str, message: str) -> None:
        if (key, kind) not in self._warned:
            self._warned.add((key, kind))
            self.warn(message)

    def _use_stage(self, stage: Usd.Stage) -> None:
        if self._stage is None or self._stage != stage:
            self._stage = stage
            self._bindings.clear()
            self._surfaces.clear()
            self._networks.clear()
            self._textures.clear()
            self._warned.clear()
            self.unsupported.clear()

    @staticmethod
    def _through_instance(prim: Usd.Prim, instance: Usd.Prim | None) -> Usd.Prim:
        """``prim`` inside a prototype, seen through ``instance``'s instance proxy (else ``prim``)."""
        if instance is None or not prim.IsInPrototype() or not instance.IsInstance():
            return prim
        proto = instance.GetPrototype()
        path = prim.GetPath()
        if not path.HasPrefix(proto.GetPath()):
            return prim
        proxy = prim.GetStage().GetPrimAtPath(path.ReplacePrefix(proto.GetPath(), instance.GetPath()))
        return proxy if proxy else prim

    def bound_path(self, prim: Usd.Prim, instance: Usd.Prim | None = None) -> str | None:
        """The path of the material Hydra would bind to ``prim`` (purpose ``full``, then ``preview``), or None.
        A winning binding whose target is no material prim (a material of a ``.mtlx`` document: usd-core cannot
        compose it) still gives its target's path."""
        self._use_stage(prim.GetStage())
        prim = self._through_instance(prim, instance)
        key = str(prim.GetPath())
        if key not in self._bindings:
            api = UsdShade.MaterialBindingAPI(prim)
            bound = [api.ComputeBoundMaterial(purpose) for purpose in _PURPOSES]
            found = next((str(m.GetPath()) for m, _rel in bound if m), None)
            if found is None:           # no material prim: a target a .mtlx reference did not compose
                found = next((t for t in (_binding_target(rel) for _m, rel in bound) if t is not None), None)
            self._bindings[key] = found
        return self._bindings[key]

    def bound_material(self, prim: Usd.Prim, instance: Usd.Prim | None = None) -> UsdShade.Material | None:
        """The material Hydra would bind to ``prim`` (purpose ``full``, then ``preview``), or None (also where the
        binding targets a path with no material prim: :meth:`bound_path`)."""
        path = self.bound_path(prim, instance)
        found = prim.GetStage().GetPrimAtPath(path) if path else None
        return UsdShade.Material(found) if found and found.IsA(UsdShade.Material) else None

    def surface_shader(self, material: UsdShade.Material) -> UsdShade.Shader | None:
        """The material's UsdPreviewSurface (universal render context first), or None."""
        key = str(material.GetPath())
        if key not in self._surfaces:
            found = None
            candidates = [material.ComputeSurfaceSource("")[0]]
            for output in material.GetSurfaceOutputs():
                candidates.append(UsdShade.Shader(output.GetConnectedSource()[0].GetPrim())
                                  if output.HasConnectedSource() else None)
            for shader in candidates:
                if shader and shader_id(shader) in _PREVIEW_IDS:
                    found = shader.GetPath()
                    break
            self._surfaces[key] = found
        path = self._surfaces[key]
        return UsdShade.Shader(material.GetPrim().GetStage().GetPrimAtPath(path)) if path else None

    def _other_surfaces(self, material: UsdShade.Material) -> list[str]:
        ids = []
        for output in material.GetSurfaceOutputs():
            if output.HasConnectedSource():
                shader = UsdShade.Shader(output.GetConnectedSource()[0].GetPrim())
                ids.append(shader_id(shader) or str(shader.GetPath()))
        return list(dict.fromkeys(ids))

    def network(self, material: UsdShade.Material, time: Usd.TimeCode) -> SurfaceNetwork | None:
        """The material's surface as usdml renders it: its UsdPreviewSurface (Storm's choice where a material also
        has a MaterialX surface), else its MaterialX standard_surface / open_pbr_surface; None (one warning: the
        caller falls back to displayColor) when it has neither. What it authors and usdml does not render is said
        once per material and kept in :attr:`unsupported`."""
        key = str(material.GetPath())
        cache = (key, time.GetValue() if not time.IsDefault() else float("nan"))
        if cache in self._networks:
            return self._networks[cache]
        shader = self.surface_shader(material)
        said: list[str] = []
        net = _PreviewReader(key, time).read(shader) if shader is not None else \
            _read_materialx(material, time, said.append)
        self._settle(key, net, said, lambda: self._other_surfaces(material))
        self._networks[cache] = net
        return net

    def network_at(self, path: str, time: Usd.TimeCode) -> SurfaceNetwork | None:
        """:meth:`network` of the material at ``path``; where no material prim is there (a binding to a material
        of a ``.mtlx`` document, which usd-core cannot compose), the document's material read with the
        ``materialx`` package (:func:`usdml.stage.materialx.read_materialx_path`)."""
        prim = self._stage.GetPrimAtPath(path) if self._stage is not None else None
        if prim and prim.IsA(UsdShade.Material):
            return self.network(UsdShade.Material(prim), time)
        cache = (path, time.GetValue() if not time.IsDefault() else float("nan"))
        if cache not in self._networks:
            said: list[str] = []
            net = _read_materialx_path(self._stage, path, time, said.append)
            if net is not None or said:     # else no .mtlx above it either: displayColor, as before
                self._settle(path, net, said, lambda: [])
            self._networks[cache] = net
        return self._networks[cache]

    def _settle(self, key: str, net: SurfaceNetwork | None, said: list[str], other: Callable[[], list[str]]) -> None:
        """Say, once per material, what a read surface does not render, or that there is none (the reader's own
        words where it gave any: a ``.mtlx`` that does not parse)."""
        for message in said:
            self._warn_once(key, "said:" + message, message)
        if net is None:
            other = other()
            if not said:
                self._warn_once(key, "surface", f"{key}: no UsdPreviewSurface (MaterialX/other only); using "
                                f"displayColor" + (f" (surface shaders: {', '.join(other)})" if other else ""))
            self.unsupported.setdefault(key, [])
            item = "surface " + (", ".join(other) or "(none)") + " not rendered: displayColor used"
            if item not in self.unsupported[key]:
                self.unsupported[key].append(item)
        elif net.unsupported:
            known = self.unsupported.setdefault(key, [])
            new = [item for item in net.unsupported if item not in known]
            known.extend(new)
            for item in new:
                self._warn_once(key, "unsupported:" + item, f"{key}: {item}")

    def texture(self, path: str, material: str, fallback: str = "inputs:fallback") -> Texture | None:
        """The image at resolved ``path``, read once; None (one warning, saying what is used instead: ``fallback``,
        :func:`fallback_words`) when it cannot be read."""
        if path not in self._textures:
            try:
                self._textures[path] = read_texture(path)
            except OSError as e:
                msg = " ".join(str(e).split())
                self._warn_once(material, "read:" + path, f"{material}: cannot read texture {path} ({msg}); "
                                f"using the UsdUVTexture's {fallback} (fix or convert the file)")
                self._textures[path] = None
        return self._textures[path]

    # ----------------------------------------------------------------------------------------------
    def shading(self, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology, n_points: int,
                instance: Usd.Prim | None = None) -> MeshShading | None:
        """The gprim's surfaces per triangle (its own bound material, and each ``materialBind`` GeomSubset's),
        evaluated at the corners and ready to sample per hit; None when no face has a surface usdml renders
        (then the caller shades displayColor, Lambertian, as Storm's fallback surface does)."""
        parts: list[tuple[np.ndarray | None, SurfaceNetwork]] = []
        for mask, path in self.face_bindings(prim, time, topo.face, instance):
            net = self.network_at(path, time) if path is not None else None
            if net is not None:
                parts.append((mask, net))
        if not parts:
            return None
        return _build_shading(self, prim, time, topo, n_points, parts)

    def face_bindings(self, prim: Usd.Prim, time: Usd.TimeCode, face: np.ndarray,
                      instance: Usd.Prim | None = None) -> list[tuple[np.ndarray | None, str | None]]:
        """Which material path (:meth:`bound_path`, None: none bound) each triangle of the gprim is bound to, as
        ``(mask, path)`` pairs: each ``materialBind`` GeomSubset's faces (the first subset naming a face wins), then
        the prim's own binding for the faces no subset names (``mask`` None: every triangle). ``face`` (T,) is the
        authored face of each triangle; masks are (T,) bool and never overlap."""
        self._use_stage(prim.GetStage())
        out: list[tuple[np.ndarray | None, str | None]] = []
        covered = np.zeros(len(face), bool)
        seen = self._through_instance(prim, instance)
        for subset in UsdGeom.Subset.GetGeomSubsets(UsdGeom.Imageable(seen), UsdGeom.Tokens.face, "materialBind"):
            faces = np.asarray(subset.GetIndicesAttr().Get(time) or [], np.int64)
            mask = np.isin(face, faces) & ~covered
            if not mask.any():
                continue
            covered |= mask
            out.append((mask, self.bound_path(subset.GetPrim())))
        if not covered.all():
            out.append((None if not covered.any() else ~covered, self.bound_path(prim, instance)))
        return out

    def albedo(self, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology, n_points: int,
               instance: Usd.Prim | None = None) -> np.ndarray | None:
        """``(T, 3, 3)`` float32 linear-RGB diffuse reflectance per triangle corner of the prim's bound surfaces
        (``diffuseColor·(1 − metallic)``, constant or textured, clipped to [0, 1]), or None when no usable material
        is bound (then the caller uses displayColor). ``instance`` optionally names the instance prim through which
        a prototype prim is seen."""
        shading = self.shading(prim, time, topo, n_points, instance)
        return None if shading is None or shading.lambert is not None else shading.albedo_corners()


def _read_materialx(material: UsdShade.Material, time: Usd.TimeCode,
                    warn: Callable[[str], None]) -> SurfaceNetwork | None:
    """MaterialX's common surfaces, when :mod:`usdml.stage.materialx` can read them; else None."""
    try:
        from usdml.stage.materialx import read_materialx
    except ImportError:
        return None
    return read_materialx(material, time, warn)


def _read_materialx_path(stage: Usd.Stage, path: str, time: Usd.TimeCode,
                         warn: Callable[[str], None]) -> SurfaceNetwork | None:
    """A bound material with no prim, read from the ``.mtlx`` document referenced above it; else None."""
    try:
        from usdml.stage.materialx import read_materialx_path
    except ImportError:
        return None
    return read_materialx_path(stage, path, time, warn)


def _binding_target(rel: Usd.Relationship | None) -> str | None:
    """The material path a winning binding relationship names (direct or collection binding), or None."""
    if not rel:
        return None
    if UsdShade.MaterialBindingAPI.CollectionBinding.IsCollectionBindingRel(rel):
        path = UsdShade.MaterialBindingAPI.CollectionBinding(rel).GetMaterialPath()
    else:
        path = UsdShade.MaterialBindingAPI.DirectBinding(rel).GetMaterialPath()
    return str(path) if path and not path.isEmpty else None


class _Eval:
    """Evaluates one material's network for one gprim at one time: per-corner values and per-hit lookups."""

    def __init__(self, resolver: MaterialResolver, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology,
                 n_points: int, material: str):
        self.r, self.prim, self.time, self.topo, self.n_points, self.material = \
            resolver, prim, time, topo, n_points, material

    def warn(self, kind: str, message: str) -> None:
        self.r._warn_once(self.material, kind, f"{self.material}: {message}")

    @property
    def n_corners(self) -> int:
        return len(self.topo.face) * 3

    def field(self, source, width: int, clip: bool):
        """``(values, lookup)``: ``values`` (width,) for a constant or (T·3, width) per corner; ``lookup`` a
        ``(TextureLookup, st (T, 3, 2))`` when the values come from a readable image (sampled again per hit)."""
        if isinstance(source, Constant):
            v = _vec(source.value, width)
            return (np.clip(v, 0.0, 1.0) if clip else v), None
        if isinstance(source, Primvar):
            v = self.primvar_values(source)
            v = _widen(v, width)
            return (np.clip(v, 0.0, 1.0) if clip else v), None
        rgba, lookup, st = self.image(source)
        lookup_out = None
        if lookup is not None:
            lookup = TextureLookup(lookup.texture, lookup.wrap_s, lookup.wrap_t, lookup.srgb, lookup.scale,
                                   lookup.bias, output=source.output, width=width, clip=clip)
            lookup_out = (lookup, st.reshape(-1, 3, 2))
        v = _widen(_select(rgba, source.output), width)
        return (np.clip(v, 0.0, 1.0) if clip else v).astype(np.float32), lookup_out

    # ----------------------------------------------------------------------------------------------
    def primvar(self, name: str, width: int, what: str) -> np.ndarray | None:
        """The gprim's primvar ``name`` per corner ``(T*3, width)``, found with inheritance, or None."""
        pv = UsdGeom.PrimvarsAPI(self.prim).FindPrimvarWithInheritance(name)
        if not pv or not pv.HasValue():
            self.warn("pv:" + name, f"{self.prim.GetPath()} has no primvar '{name}' for {what}; using the "
                      f"reader's fallback (author primvars:{name})")
            return None
        raw = pv.ComputeFlattened(self.time)
        if raw is None or len(raw) == 0:
            return None
        try:
            values = np.asarray(raw, np.float32).reshape(len(raw), -1)
        except (TypeError, ValueError):
            self.warn("pv:" + name, f"{self.prim.GetPath()}: primvars:{name} is not numeric; using the reader's "
                      "fallback")
            return None
        per_corner = self.topo.expand(values, pv.GetInterpolation(), self.n_points)
        if per_corner is None:
            self.warn("pv:" + name, f"{self.prim.GetPath()}: {len(raw)} primvars:{name} values do not match "
                      f"interpolation {pv.GetInterpolation()!r}; using the reader's fallback")
            return None
        per_corner = per_corner.reshape(self.n_corners, -1)
        return _widen(per_corner, width)

    def primvar_values(self, reader: Primvar) -> np.ndarray:
        """(N, width) values of a primvar reader (its fallback where the primvar is missing)."""
        values = self.primvar(reader.name, reader.width, reader.node or "a primvar reader") if reader.name else None
        if values is None:
            if not reader.name:
                self.warn("varname:" + reader.node, f"{reader.node} has no inputs:varname; using its "
                          "fallback (set varname to the primvar's name, e.g. 'st')")
            values = np.broadcast_to(_vec(reader.fallback, reader.width), (self.n_corners, reader.width))
        return np.asarray(values, np.float32)

    def st(self, image: Image) -> np.ndarray:
        """(N, 2) texture coordinates of ``image``: its primvar (or constant), then its UsdTransform2d steps."""
        if isinstance(image.st, Primvar):
            st = self.primvar_values(image.st)[:, :2]
        else:
            st = np.broadcast_to(_vec(image.st.value, 2), (self.n_corners, 2))
        for step in image.transforms:
            angle = np.radians(step.rotation)
            c, s = np.cos(angle), np.sin(angle)
            p = st * np.asarray(step.scale, np.float32)
            st = np.stack([p[:, 0] * c - p[:, 1] * s, p[:, 0] * s + p[:, 1] * c], axis=1) + \
                np.asarray(step.translation, np.float32)
        return np.ascontiguousarray(st, np.float32)

    def image(self, node: Image):
        """``(rgba (N, 4) after scale and bias, TextureLookup or None, st (N, 2) or None)`` of an image at every
        corner; its fallback (one warning) where the file is missing or unreadable."""
        fallback = np.asarray(node.fallback, np.float32)
        using = fallback_words(fallback, node.fallback_authored)
        constant = np.broadcast_to(fallback, (self.n_corners, 4))
        if not node.authored:
            self.warn("nofile:" + node.node, f"{node.node} has no inputs:file; using its {using}")
            return constant, None, None
        if not node.file:
            self.warn("missing:" + node.node, f"{node.node}.inputs:file @{node.authored}@ does not resolve (missing "
                      f"file?); using its {using} (fix the asset path)")
            return constant, None, None
        if node.tiles:
            read = {tile: self.r.texture(path, self.material, using) for tile, path in node.tiles}
            read = {tile: t for tile, t in read.items() if t is not None}
            tex = UdimTexture(read, fallback) if read else None
        else:
            tex = self.r.texture(node.file, self.material, using)
        if tex is None:
            return constant, None, None
        wraps = []
        for axis, mode, meta_index in (("wrapS", node.wrap_s, 0), ("wrapT", node.wrap_t, 1)):
            if mode == "useMetadata":
                mode = tex.wrap_metadata[meta_index] if tex.wrap_metadata else "repeat"
            elif mode not in _WRAPS:
                self.warn("wrap:" + node.node, f"{node.node}.inputs:{axis} = {mode!r} is not a wrap mode "
                          f"({', '.join(_WRAPS)}, useMetadata); using repeat")
                mode = "repeat"
            wraps.append(mode)
        space = node.color_space
        if space == "sRGB":
            srgb = True
        elif space == "raw":
            srgb = False
        else:
            if space != "auto":
                self.warn("cs:" + node.node, f"{node.node}.inputs:sourceColorSpace = {space!r} is not raw/sRGB/auto; "
                          "using auto")
            srgb = tex.eight_bit and tex.channels in (3, 4)
        st = self.st(node)
        scale = np.asarray(node.scale, np.float32)
        bias = np.asarray(node.bias, np.float32)
        rgba = tex.sample(st, wraps[0], wraps[1], srgb) * scale + bias
        return rgba, TextureLookup(tex, wraps[0], wraps[1], srgb, scale, bias), st


def _select(rgba: np.ndarray, output: str) -> np.ndarray:
    """The channels a texture output gives: rgb, rgba, or one of r/g/b/a."""
    if output in ("r", "g", "b", "a"):
        c = "rgba".index(output)
        return rgba[:, c:c + 1]
    return rgba if output == "rgba" else rgba[:, :3]


def _widen(values: np.ndarray, width: int) -> np.ndarray:
    """(N, C) values as (N, width): one channel repeated, extra channels dropped, missing ones 0."""
    c = values.shape[1]
    if c == width:
        return values
    if c == 1:
        return np.repeat(values, width, axis=1)
    if c > width:
        return values[:, :width]
    return np.pad(values, ((0, 0), (0, width - c)))


def _build_shading(resolver: MaterialResolver, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology, n_points: int,
                   parts: list) -> MeshShading:
    """Every preview input of a gprim's surfaces per triangle: one :class:`Field` per input, constant where every
    part agrees on a constant, else per corner; image lookups kept per part for sampling at hits."""
    n_tri = len(topo.face)
    fields: dict[str, Field] = {}
    for name, default in PREVIEW_DEFAULTS.items():
        width, clip = len(default), name in _UNIT_INPUTS
        values, lookups = [], []
        for mask, net in parts:
            ev = _Eval(resolver, prim, time, topo, n_points, net.material)
            v, lookup = ev.field(net.inputs.get(name, Constant(default)), width, clip)
            values.append(v)
            if lookup is not None:
                lookups.append((mask, lookup[0], lookup[1]))
        if all(v.ndim == 1 for v in values) and all(np.array_equal(v, values[0]) for v in values) \
                and parts[0][0] is None:
            fields[name] = Field(values[0].astype(np.float32), lookups)
            continue
        corners = np.zeros((n_tri, 3, width), np.float32)
        for (mask, _net), v in zip(parts, values):
            full = np.broadcast_to(v, (n_tri * 3, width)).reshape(n_tri, 3, width)
            if mask is None:
                corners[:] = full
            else:
                corners[mask] = full[mask]
        fields[name] = Field(corners, lookups)
    lambert = None
    if parts[0][0] is not None or len(parts) > 1:
        lambert = np.ones(n_tri, bool)
        for mask, _net in parts:
            lambert &= ~mask if mask is not None else False
        lambert = lambert if lambert.any() else None
    return MeshShading(fields=fields, n_tri=n_tri, lambert=lambert)
