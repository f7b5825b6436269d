"""Resolve a gprim's bound ``UsdPreviewSurface`` diffuse colour to a per-corner albedo, as Hydra does.

What is resolved, and how (each rule follows Hydra / Storm or the UsdPreviewSurface specification):

* **Binding**: ``UsdShade.MaterialBindingAPI.ComputeBoundMaterial`` with purpose ``full``, then
  ``preview`` (what a final-quality Hydra render delegate asks for). USD itself handles inherited,
  direct and collection-based bindings and ``bindMaterialAs`` strength. Prims inside a native
  prototype (``/__Prototype_N/...``) see the bindings authored inside the instanced asset; pass
  ``instance=`` (an instance prim of that prototype) to resolve through that instance's instance
  proxy instead, so bindings authored on or above the instance apply too.
* **Surface**: ``UsdShadeMaterial.ComputeSurfaceSource`` for the universal render context, then any
  other context's surface output, keeping the first whose shader is ``UsdPreviewSurface`` (or
  MaterialX's ``ND_UsdPreviewSurface_surfaceshader``, whose inputs are the same). Materials with only
  a MaterialX / other surface give None (the caller falls back to displayColor, as Storm's fallback
  material does) with one warning per material.
* **diffuseColor**: its value-producing attribute (connections followed through material interface
  inputs): a constant (authored, else the spec fallback 0.18), a ``UsdUVTexture`` output
  (``rgb``, ``r``, ``g``, ``b`` or ``a``), or a ``UsdPrimvarReader_float/float3/float4``.
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
  used as the node's output as is, with one warning naming the value used. UDIM sets are not read: the diffuseColor's
  constant value is used instead, with a warning.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from pxr import Ar, Sdf, Usd, UsdGeom, UsdShade

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
    """A UsdUVTexture feeding diffuseColor, ready to sample per pixel (plain NumPy, kept on the Mesh).

    ``sample(st)`` applies wrap modes, colour space, ``scale``/``bias``, the output channel and the
    [0, 1] albedo clip, exactly as the per-corner albedo does.
    """

    texture: Texture
    wrap_s: str
    wrap_t: str
    srgb: bool
    scale: np.ndarray       #: (4,)
    bias: np.ndarray        #: (4,)
    channel: int | None = None   #: 0-3 for an ``r``/``g``/``b``/``a`` output, None for ``rgb``

    def sample(self, st: np.ndarray) -> np.ndarray:
        """``(N, 3)`` float32 linear albedo at texture coordinates ``st`` ``(N, 2)``."""
        rgba = self.texture.sample(np.asarray(st, np.float32).reshape(-1, 2), self.wrap_s, self.wrap_t,
                                   self.srgb) * self.scale + self.bias
        rgb = np.repeat(rgba[:, self.channel:self.channel + 1], 3, axis=1) if self.channel is not None \
            else rgba[:, :3]
        return np.clip(rgb, 0.0, 1.0).astype(np.float32)


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
def _shader_id(shader: UsdShade.Shader) -> str:
    sid = shader.GetShaderId()
    if not sid:
        sid = shader.GetIdAttr().Get()
    return str(sid or "")


def _source(inp: UsdShade.Input | None) -> Usd.Attribute | None:
    """The attribute producing ``inp``'s value: a shader output, or an input holding a value; None when
    nothing is connected nor authored."""
    if not inp:
        return None
    attrs = inp.GetValueProducingAttributes(False)
    if attrs:
        return attrs[0]
    return inp.GetAttr() if inp.GetAttr().HasValue() else None


def _is_output(attr: Usd.Attribute) -> bool:
    return UsdShade.Utils.GetType(attr.GetName()) == UsdShade.AttributeType.Output


def _value(shader: UsdShade.Shader, name: str, time: Usd.TimeCode, default):
    """A constant input's value (following interface connections), else ``default``."""
    attr = _source(shader.GetInput(name))
    if attr is None or _is_output(attr):
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


def fallback_words(fallback: np.ndarray, authored: bool) -> str:
    """How a warning names the ``inputs:fallback`` a UsdUVTexture gives in place of its file: the value, and when
    it is not authored, that it is the spec's black (a whole material, a whole frame black)."""
    values = ", ".join(f"{v:g}" for v in fallback)
    return f"inputs:fallback ({values})" + ("" if authored else ", unauthored: the spec's default black")


class MaterialResolver:
    """Resolves bound UsdPreviewSurface diffuse colours; caches per stage: bindings, surfaces, textures.

    ``warn`` receives one-line messages naming the prim or material and what to do; it is expected to
    de-duplicate, and the resolver also reports each (material, problem) once.
    """

    def __init__(self, warn: Callable[[str], None]):
        self.warn = warn
        self._stage: Usd.Stage | None = None
        self._bindings: dict[str, str | None] = {}
        self._surfaces: dict[str, Sdf.Path | None] = {}
        self._textures: dict[str, Texture | None] = {}
        self._warned: set[tuple[str, str]] = set()

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
            self._textures.clear()
            self._warned.clear()

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

    def bound_material(self, prim: Usd.Prim, instance: Usd.Prim | None = None) -> UsdShade.Material | None:
        """The material Hydra would bind to ``prim`` (purpose ``full``, then ``preview``), or None."""
        self._use_stage(prim.GetStage())
        prim = self._through_instance(prim, instance)
        key = str(prim.GetPath())
        if key not in self._bindings:
            found = None
            api = UsdShade.MaterialBindingAPI(prim)
            for purpose in _PURPOSES:
                material, _rel = api.ComputeBoundMaterial(purpose)
                if material:
                    found = str(material.GetPath())
                    break
            self._bindings[key] = found
        path = self._bindings[key]
        return UsdShade.Material(prim.GetStage().GetPrimAtPath(path)) if path else None

    def surface_shader(self, material: UsdShade.Material) -> UsdShade.Shader | None:
        """The material's UsdPreviewSurface (universal render context first), or None with one warning."""
        key = str(material.GetPath())
        if key not in self._surfaces:
            found, other = None, []
            candidates = [material.ComputeSurfaceSource("")[0]]
            for output in material.GetSurfaceOutputs():
                candidates.append(UsdShade.Shader(output.GetConnectedSource()[0].GetPrim())
                                  if output.HasConnectedSource() else None)
            for shader in candidates:
                if not shader:
                    continue
                sid = _shader_id(shader)
                if sid in _PREVIEW_IDS:
                    found = shader.GetPath()
                    break
                other.append(sid or str(shader.GetPath()))
            if found is None:
                self._warn_once(key, "surface", f"{key}: no UsdPreviewSurface (MaterialX/other only); using "
                                f"displayColor" + (f" (surface shaders: {', '.join(dict.fromkeys(other))})"
                                                   if other else ""))
            self._surfaces[key] = found
        path = self._surfaces[key]
        return UsdShade.Shader(material.GetPrim().GetStage().GetPrimAtPath(path)) if path else None

    # ----------------------------------------------------------------------------------------------
    def albedo(self, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology, n_points: int,
               instance: Usd.Prim | None = None) -> np.ndarray | None:
        """``(T, 3, 3)`` float32 linear-RGB albedo per triangle corner from the prim's bound
        UsdPreviewSurface diffuseColor (constant or UsdUVTexture), or None when no usable material is
        bound (then the caller uses displayColor).

        Values are clipped to [0, 1]: a Lambertian albedo above 1 would reflect more light than
        arrives, which is non-physical (and makes light bounces diverge); below 0 is meaningless.
        ``instance`` optionally names the instance prim through which a prototype prim is seen.
        """
        return self.albedo_and_texture(prim, time, topo, n_points, instance)[0]

    def albedo_and_texture(self, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology, n_points: int,
                           instance: Usd.Prim | None = None):
        """``(albedo, texture)``: the per-corner albedo of :meth:`albedo`, and when diffuseColor comes
        from a readable UsdUVTexture, ``(TextureLookup, (T, 3, 2) float32 st per corner)`` so the
        renderer can sample it per pixel (per-corner values alone would blur a texture to its
        vertices); ``texture`` is None otherwise."""
        material = self.bound_material(prim, instance)
        if material is None:
            return None, None
        shader = self.surface_shader(material)
        if shader is None:
            return None, None
        ctx = _Eval(self, prim, time, topo, n_points, str(material.GetPath()))
        rgb = ctx.diffuse(shader)
        n = len(topo.face)
        out = np.broadcast_to(np.asarray(rgb, np.float32), (n, 3, 3)) if np.ndim(rgb) == 1 else rgb
        texture = (ctx.lookup, ctx.st.reshape(-1, 3, 2)) if ctx.lookup is not None else None
        return np.ascontiguousarray(np.clip(out, 0.0, 1.0), np.float32), texture

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


class _Eval:
    """Evaluates one material's diffuse network for one gprim at one time."""

    def __init__(self, resolver: MaterialResolver, prim: Usd.Prim, time: Usd.TimeCode, topo: Topology,
                 n_points: int, material: str):
        self.r, self.prim, self.time, self.topo, self.n_points, self.material = \
            resolver, prim, time, topo, n_points, material
        self.lookup: TextureLookup | None = None     # set when diffuseColor is a readable texture
        self.st: np.ndarray | None = None

    def warn(self, kind: str, message: str) -> None:
        self.r._warn_once(self.material, kind, f"{self.material}: {message}")

    @property
    def n_corners(self) -> int:
        return len(self.topo.face) * 3

    def diffuse(self, surface: UsdShade.Shader) -> np.ndarray:
        """(3,) constant or (T, 3, 3) per-corner diffuse colour."""
        inp = surface.GetInput("diffuseColor")
        constant = np.asarray(_value(surface, "diffuseColor", self.time, DIFFUSE_FALLBACK), np.float32)[:3]
        attr = _source(inp)
        if attr is None or not _is_output(attr):
            return constant
        own = inp.GetAttr().Get(self.time)        # a connected input's own value: used when the network cannot be
        if own is not None:                       # evaluated (UDIM, unsupported node)
            constant = np.asarray(own, np.float32)[:3]
        node = UsdShade.Shader(attr.GetPrim())
        sid = _shader_id(node)
        out_name = UsdShade.Utils.GetBaseNameAndType(attr.GetName())[0]
        if sid == "UsdUVTexture":
            rgba = self.texture(node, constant)
            if rgba is None:
                return constant
        elif sid.startswith("UsdPrimvarReader_"):
            rgba = self.primvar_reader(node, sid)
            out_name = "rgb" if rgba.shape[-1] > 1 else "r"
        else:
            self.warn("node:" + str(node.GetPath()), f"diffuseColor comes from {node.GetPath()} ({sid or 'no id'}), "
                      "which usdml does not evaluate; using the diffuseColor value (author a UsdUVTexture "
                      "or a constant)")
            return constant
        channel = {"r": 0, "g": 1, "b": 2, "a": 3}.get(str(out_name))
        if self.lookup is not None:
            self.lookup.channel = channel
        rgb = np.repeat(rgba[:, channel:channel + 1], 3, axis=1) if channel is not None else rgba[:, :3]
        return rgb.reshape(-1, 3, 3)

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
        values = np.asarray(raw, np.float32).reshape(len(raw), -1)
        per_corner = self.topo.expand(values, pv.GetInterpolation(), self.n_points)
        if per_corner is None:
            self.warn("pv:" + name, f"{self.prim.GetPath()}: {len(raw)} primvars:{name} values do not match "
                      f"interpolation {pv.GetInterpolation()!r}; using the reader's fallback")
            return None
        per_corner = per_corner.reshape(self.n_corners, -1)
        if per_corner.shape[1] < width:
            per_corner = np.repeat(per_corner[:, :1], width, axis=1) if per_corner.shape[1] == 1 else \
                np.pad(per_corner, ((0, 0), (0, width - per_corner.shape[1])))
        return per_corner[:, :width]

    def primvar_reader(self, node: UsdShade.Shader, sid: str) -> np.ndarray:
        """(N, C) values of a UsdPrimvarReader_* node."""
        width = {"float": 1, "float2": 2, "float3": 3, "normal": 3, "point": 3, "vector": 3,
                 "float4": 4}.get(sid[len("UsdPrimvarReader_"):], 3)
        name = str(_value(node, "varname", self.time, "") or "")
        values = self.primvar(name, width, str(node.GetPath())) if name else None
        if values is None:
            if not name:
                self.warn("varname:" + str(node.GetPath()), f"{node.GetPath()} has no inputs:varname; using its "
                          "fallback (set varname to the primvar's name, e.g. 'st')")
            fb = _vec(_value(node, "fallback", self.time, 0.0), width)
            values = np.broadcast_to(fb, (self.n_corners, width))
        return np.asarray(values, np.float32)

    def float2(self, inp: UsdShade.Input | None, depth: int = 0) -> np.ndarray:
        """(N, 2) texture coordinates from whatever drives ``inp``: a primvar reader, a UsdTransform2d or
        a constant."""
        attr = _source(inp)
        if attr is None:
            return np.zeros((self.n_corners, 2), np.float32)
        if not _is_output(attr):
            return np.broadcast_to(_vec(attr.Get(self.time), 2), (self.n_corners, 2))
        node = UsdShade.Shader(attr.GetPrim())
        sid = _shader_id(node)
        if sid.startswith("UsdPrimvarReader_"):
            return self.primvar_reader(node, sid)[:, :2] if sid != "UsdPrimvarReader_float" else \
                np.repeat(self.primvar_reader(node, sid), 2, axis=1)
        if sid == "UsdTransform2d" and depth < 16:
            st = self.float2(node.GetInput("in"), depth + 1)
            scale = _vec(_value(node, "scale", self.time, (1.0, 1.0)), 2)
            angle = np.radians(float(_value(node, "rotation", self.time, 0.0)))
            trans = _vec(_value(node, "translation", self.time, (0.0, 0.0)), 2)
            c, s = np.cos(angle), np.sin(angle)
            p = st * scale
            return np.stack([p[:, 0] * c - p[:, 1] * s, p[:, 0] * s + p[:, 1] * c], axis=1) + trans
        self.warn("st:" + str(node.GetPath()), f"texture coordinates come from {node.GetPath()} ({sid or 'no id'}), "
                  "which usdml does not evaluate; using (0, 0) (use a UsdPrimvarReader_float2)")
        return np.zeros((self.n_corners, 2), np.float32)

    def texture(self, node: UsdShade.Shader, constant: np.ndarray) -> np.ndarray | None:
        """(N, 4) rgba of a UsdUVTexture node at every corner, after scale and bias; None means use
        the diffuseColor ``constant`` (an unsupported UDIM set)."""
        name = str(node.GetPath())
        authored = _value(node, "fallback", self.time, None)
        fallback = _vec(TEXTURE_FALLBACK if authored is None else authored, 4)
        using = fallback_words(fallback, authored is not None)
        asset = _value(node, "file", self.time, None)
        raw_path = getattr(asset, "path", "") or ""
        resolved = getattr(asset, "resolvedPath", "") or ""
        if "<UDIM>" in raw_path.upper() or "<UDIM>" in resolved.upper():
            self.warn("udim:" + name, f"{name}.inputs:file {raw_path} is a UDIM set, which usdml does not "
                      "read; using the diffuseColor value (bake the tiles into one texture)")
            return None
        if not raw_path:
            self.warn("nofile:" + name, f"{name} has no inputs:file; using its {using}")
            return np.broadcast_to(fallback, (self.n_corners, 4))
        if not resolved:
            self.warn("missing:" + name, f"{name}.inputs:file @{raw_path}@ does not resolve (missing file?); "
                      f"using its {using} (fix the asset path)")
            return np.broadcast_to(fallback, (self.n_corners, 4))
        tex = self.r.texture(resolved, self.material, using)
        if tex is None:
            return np.broadcast_to(fallback, (self.n_corners, 4))

        wraps = []
        for axis, meta_index in (("wrapS", 0), ("wrapT", 1)):
            mode = _token(node, axis, self.time, "useMetadata")
            if mode == "useMetadata":
                mode = tex.wrap_metadata[meta_index] if tex.wrap_metadata else "repeat"
            elif mode not in _WRAPS:
                self.warn("wrap:" + name, f"{name}.inputs:{axis} = {mode!r} is not a wrap mode "
                          f"({', '.join(_WRAPS)}, useMetadata); using repeat")
                mode = "repeat"
            wraps.append(mode)
        space = _token(node, "sourceColorSpace", self.time, "auto")
        if space == "sRGB":
            srgb = True
        elif space == "raw":
            srgb = False
        else:
            if space != "auto":
                self.warn("cs:" + name, f"{name}.inputs:sourceColorSpace = {space!r} is not raw/sRGB/auto; "
                          "using auto")
            srgb = tex.eight_bit and tex.channels in (3, 4)
        st = self.float2(node.GetInput("st"))
        rgba = tex.sample(st, wraps[0], wraps[1], srgb)
        scale = _vec(_value(node, "scale", self.time, (1.0, 1.0, 1.0, 1.0)), 4)
        bias = _vec(_value(node, "bias", self.time, (0.0, 0.0, 0.0, 0.0)), 4)
        self.lookup = TextureLookup(tex, wraps[0], wraps[1], srgb, scale, bias)
        self.st = np.ascontiguousarray(st, np.float32)
        return rgba * scale + bias
