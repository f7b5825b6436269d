"""MaterialX's common surfaces as the preview surface usdml renders (:class:`usdml.stage.network.SurfaceNetwork`).

Two sources, one mapping:

* **MaterialX nodes in the USD file**: a material whose surface output (render context ``mtlx``, else any other)
  leads to a shader with ``info:id`` ``ND_standard_surface_surfaceshader``, ``ND_open_pbr_surface_surfaceshader``
  or ``ND_UsdPreviewSurface_surfaceshader``; inputs followed through node graphs and material interface inputs.
* **A referenced ``.mtlx`` document**: usd-core has no MaterialX file format, so a reference or payload to a
  ``.mtlx`` file is a composition error and the material prim below it is empty or missing. The arc is found in
  the authored prim specs of the material or of an ancestor (``@look.mtlx@</MaterialX/Materials>`` on a scope,
  the bound path ``<scope>/<name>``), the document is read with the ``materialx`` package, and its
  ``surfacematerial`` ``<name>`` is read as UsdMtlx would translate it (``/MaterialX/Materials/<name>``).

Mapping onto the preview surface's metallic workflow (what each input becomes; the formulas are the only
approximation, and every authored input outside them is listed, once per lobe, in ``unsupported``):

==================  ====================================  ==========================================
preview input       standard_surface                      open_pbr_surface
==================  ====================================  ==========================================
diffuseColor        base · base_color                     base_weight · base_color
metallic            metalness                             base_metalness
roughness           specular_roughness                    specular_roughness
ior                 specular · mean(specular_color) · F0(specular_IOR) as an ior (below)
clearcoat           coat                                  coat_weight
clearcoatRoughness  coat_roughness                        coat_roughness
emissiveColor       emission · emission_color             emission_luminance · emission_color
opacity             mean(opacity) (a colour)              geometry_opacity
normal              normal ← normalmap(image)             geometry_normal ← normalmap(image)
==================  ====================================  ==========================================

* **Specular weight and tint** have no preview input: the dielectric's normal-incidence reflectance
  ``F0 = specular · mean(specular_color) · ((IOR − 1)/(IOR + 1))²`` is kept by writing the ior that gives it,
  ``ior = (1 + √F0)/(1 − √F0)`` (``specular`` 0 gives ior 1, no reflection at normal incidence; the preview
  surface still reflects at grazing angles, its F90 being 1). Only constants fold: a specular weight, tint or
  IOR from a node uses the node definition's default, said once. The preview surface takes its clearcoat's F0
  from the same ior; a metal's edge tint (``specular_color`` with metalness 1) is not rendered.
* **Subsurface** is not scattered: its weight mixes ``subsurface_color`` into a constant diffuse colour, as both
  surfaces mix their diffuse and subsurface lobes, and the lobe is listed as not rendered.
* **Products** (``base · base_color``, ``emission · emission_color``): constants multiply; a constant times an
  image folds into the image's scale; an image times an image, or a colour that is not grey times a scalar image,
  keeps one factor (said once).
* **Images** (``ND_image_*``, ``ND_tiledimage_*``) become UsdUVTexture lookups: ``default`` is the fallback,
  ``uaddressmode``/``vaddressmode`` periodic, clamp, mirror and constant become repeat, clamp, mirror and black
  (zero outside, not ``default``); ``uvtiling``/``uvoffset`` (and the real-world sizes) become a Transform2d.
  Texture coordinates: unconnected or ``ND_texcoord_vector2`` read primvar ``st`` (UsdMtlx's name for UV set 0),
  ``ND_geompropvalue_vector2`` its ``geomprop``. Colour spaces: MaterialX converts colour images only (vector and
  float images are raw); ``srgb_texture`` is sRGB, a linear Rec.709 name raw, none Storm's ``auto``, any other
  read as raw (said once). ``ND_convert_*``, ``ND_dot_*``, ``ND_extract_*``/``ND_separate*`` (one channel) and
  ``ND_multiply_*`` by a constant are followed; another node feeding an input leaves its default (said once).
* **Normals**: ``ND_normalmap`` of an image becomes the preview's tangent-space normal with scale 2 and bias
  −1 (times normalmap's ``scale`` on x and y), the UsdPreviewSurface convention.

Nothing here raises on bad content: a ``.mtlx`` that does not parse, a material name it lacks, a surface type
that is not mapped go to ``warn`` (naming the material) and give None; what a mapped surface authors and usdml
does not render goes to the network's ``unsupported``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from typing import Callable, Iterator

import numpy as np
from pxr import Ar, Sdf, Usd, UsdShade

from usdml.stage.materials import as_numbers, is_output, shader_id, value_source
from usdml.stage.network import PREVIEW_DEFAULTS, Constant, Image, Primvar, Source, SurfaceNetwork, Transform2d

Warn = Callable[[str], None]

STANDARD_SURFACE = "ND_standard_surface_surfaceshader"
OPEN_PBR_SURFACE = "ND_open_pbr_surface_surfaceshader"
PREVIEW_SURFACE = "ND_UsdPreviewSurface_surfaceshader"
SURFACES = (STANDARD_SURFACE, OPEN_PBR_SURFACE, PREVIEW_SURFACE)
#: the primvar UsdMtlx reads for MaterialX's default texture coordinates (UV set 0)
PRIMARY_UV = "st"
#: where UsdMtlx puts a document's materials
MATERIALS_SCOPE = Sdf.Path("/MaterialX/Materials")

#: the inputs the mapping reads (the coat's IOR only to say where the preview's clearcoat differs)
_MAPPED = {
    STANDARD_SURFACE: {"base", "base_color", "metalness", "specular", "specular_color", "specular_roughness",
                       "specular_IOR", "coat", "coat_roughness", "coat_IOR", "emission", "emission_color", "opacity",
                       "normal"},
    OPEN_PBR_SURFACE: {"base_weight", "base_color", "base_metalness", "specular_weight", "specular_color",
                       "specular_roughness", "specular_ior", "coat_weight", "coat_roughness", "coat_ior",
                       "emission_luminance", "emission_color", "geometry_opacity", "geometry_normal"},
}
#: lobes whose inputs are said as one item, and the input that switches each off at 0
_LOBES = {
    STANDARD_SURFACE: {"transmission": "transmission", "subsurface": "subsurface", "sheen": "sheen", "coat": "coat",
                       "thin_film": "thin_film_thickness", "specular_anisotropy": "specular_anisotropy"},
    OPEN_PBR_SURFACE: {"transmission": "transmission_weight", "subsurface": "subsurface_weight",
                       "fuzz": "fuzz_weight", "coat": "coat_weight", "thin_film": "thin_film_weight",
                       "specular_roughness_anisotropy": "specular_roughness_anisotropy"},
}
#: inputs that belong to a lobe without sharing its prefix
_LOBE_OF = {"specular_rotation": "specular_anisotropy", "geometry_coat_normal": "coat",
            "geometry_coat_tangent": "coat"}
#: inputs that are geometry defaults when unconnected (a value authored on them means nothing)
_GEOMETRY = {"normal", "tangent", "coat_normal", "geometry_normal", "geometry_tangent", "geometry_coat_normal",
             "geometry_coat_tangent"}
_ADDRESS = {"periodic": "repeat", "clamp": "clamp", "mirror": "mirror", "constant": "black"}
_SRGB = {"srgb_texture", "srgb", "srgb_rec709", "g22_rec709"}
_LINEAR = {"lin_rec709", "lin_srgb", "linear", "raw", "rec709_linear", "lin_rec709_scene"}
_CHANNEL = {"r": "r", "g": "g", "b": "b", "a": "a", "x": "r", "y": "g", "z": "b", "w": "a"}
#: defaults of node definitions the data library may lack (MaterialX 1.38's names that USD files still carry)
_OLD_DEFAULTS = {"ND_normalmap": {"in": (0.5, 0.5, 1.0), "scale": (1.0,), "space": "tangent"}}


# --------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _library():
    """MaterialX's data library (the node definitions and their defaults), loaded once; None without MaterialX."""
    try:
        import MaterialX as mx
    except ImportError:
        return None
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def _plain(value):
    """A MaterialX or USD value as a float, a tuple of floats, a string, or None."""
    if value is None:
        return None
    if isinstance(value, (bool, int, float)):
        return float(value)
    if isinstance(value, str):
        return value
    if hasattr(value, "asTuple"):
        return tuple(float(x) for x in value.asTuple())
    if isinstance(value, Sdf.AssetPath):
        return value.path
    try:
        return tuple(float(x) for x in value)
    except (TypeError, ValueError):
        return str(value)


def _default(nodedef: str, name: str):
    """The node definition's default for input ``name`` (None when unknown or a geometric default)."""
    lib = _library()
    nd = lib.getNodeDef(nodedef) if lib is not None else None
    if nd is None:
        return _OLD_DEFAULTS.get(nodedef, {}).get(name)
    inp = nd.getActiveInput(name)
    if inp is None or not inp.hasValueString():
        return None
    return _plain(inp.getValue())


def _words(value) -> str:
    if isinstance(value, tuple):
        return "(" + ", ".join(f"{v:g}" for v in value) + ")" if len(value) > 1 else f"{value[0]:g}"
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value)


# --------------------------------------------------------------------------------------------------
# One view of a node, whichever file holds it: its node definition, and what feeds each input
@dataclasses.dataclass
class Port:
    """What feeds one input: a constant ``value``, or ``node``'s output ``output``."""

    value: object = None
    node: "Node | None" = None
    output: str = "out"
    color_space: str = ""           #: the input's colour space (MaterialX ``colorspace``, USD ``colorSpace``)


class Node:
    path: str                       #: for messages
    nodedef: str                    #: ND_... id

    def port(self, name: str) -> Port | None:
        """What feeds input ``name``; None when unauthored."""
        raise NotImplementedError

    def file(self, name: str) -> tuple[str, str]:
        """(as authored, resolved path or "" when it does not resolve) of a filename input."""
        raise NotImplementedError

    def inputs(self) -> list[str]:
        raise NotImplementedError


class UsdNode(Node):
    """A shader prim with an ``ND_`` ``info:id``; inputs followed through node graphs and interface inputs."""

    def __init__(self, shader: UsdShade.Shader, time: Usd.TimeCode):
        self.shader, self.time = shader, time
        self.path = str(shader.GetPath())
        self.nodedef = shader_id(shader)

    def inputs(self) -> list[str]:
        return [str(i.GetBaseName()) for i in self.shader.GetInputs()]

    def port(self, name: str) -> Port | None:
        inp = self.shader.GetInput(name)
        attr = value_source(inp)
        if attr is None:
            return None
        space = inp.GetAttr().GetColorSpace() if inp.GetAttr().HasColorSpace() else ""
        if is_output(attr):
            out = str(UsdShade.Utils.GetBaseNameAndType(attr.GetName())[0])
            return Port(node=UsdNode(UsdShade.Shader(attr.GetPrim()), self.time), output=out, color_space=space)
        value = attr.Get(self.time)
        if value is None:
            return None
        if not space and attr.HasColorSpace():
            space = attr.GetColorSpace()
        return Port(value=_plain(value), color_space=str(space))

    def file(self, name: str) -> tuple[str, str]:
        attr = value_source(self.shader.GetInput(name))
        value = attr.Get(self.time) if attr is not None and not is_output(attr) else None
        if isinstance(value, Sdf.AssetPath):
            return value.path, value.resolvedPath or ""
        return (str(value), "") if value else ("", "")


class MxNode(Node):
    """A node of a MaterialX document read with the ``materialx`` package; ``where`` resolves its file names."""

    def __init__(self, node, where: "_Document"):
        self.node, self.where = node, where
        self.path = f"{where.label}:{node.getNamePath()}"
        nd = node.getNodeDef()
        self.nodedef = nd.getName() if nd is not None else f"{node.getCategory()} ({node.getType()})"

    def inputs(self) -> list[str]:
        return [i.getName() for i in self.node.getInputs()]

    def _input(self, name: str):
        inp = self.node.getInput(name)
        for _ in range(16):         # an input inside a node graph bound to the graph's interface
            if inp is None or not inp.hasInterfaceName():
                break
            inp = inp.getInterfaceInput()
        return inp

    def port(self, name: str) -> Port | None:
        inp = self._input(name)
        if inp is None:
            return None
        space = inp.getActiveColorSpace() or ""
        upstream = inp.getConnectedNode()
        if upstream is not None:
            out = inp.getConnectedOutput()
            output = inp.getOutputString() if not inp.hasNodeGraphString() else ""
            if out is not None and out.hasOutputString():
                output = out.getOutputString()
            return Port(node=MxNode(upstream, self.where), output=output or "out", color_space=space)
        if inp.getNodeName() or inp.hasNodeGraphString():
            return Port(node=_Missing(f"{self.path}.{name}", inp.getNodeName() or inp.getNodeGraphString()))
        if not inp.hasValueString():
            return None
        return Port(value=_plain(inp.getValue()), color_space=space)

    def file(self, name: str) -> tuple[str, str]:
        inp = self._input(name)
        if inp is None or not inp.hasValueString():
            return "", ""
        authored = inp.getResolvedValueString()         # with the document's fileprefix
        return authored, self.where.resolve(authored)


class _Missing(Node):
    """A connection to a node the document lacks."""

    def __init__(self, path: str, name: str):
        self.path, self.nodedef = path, f"missing node {name!r}"

    def inputs(self) -> list[str]:
        return []

    def port(self, name: str) -> Port | None:
        return None

    def file(self, name: str) -> tuple[str, str]:
        return "", ""


@dataclasses.dataclass
class _Document:
    """A read ``.mtlx`` document: ``label`` names it in messages; texture paths resolve against ``folder``
    (a folder, or inside a package: ``pkg.usdz[dir]``)."""

    doc: object
    label: str
    folder: str
    package: str = ""

    def resolve(self, authored: str) -> str:
        if not authored or "<UDIM>" in authored.upper():
            return ""
        if self.package:
            inner = os.path.normpath(os.path.join(self.folder, authored)).lstrip("/")
            path = f"{self.package}[{inner}]"
            return path if Ar.GetResolver().OpenAsset(Ar.ResolvedPath(path)) is not None else ""
        path = authored if os.path.isabs(authored) else os.path.normpath(os.path.join(self.folder, authored))
        return path if os.path.isfile(path) else ""


# --------------------------------------------------------------------------------------------------
class _Mapper:
    """Reads one MaterialX surface shader node into a :class:`SurfaceNetwork`."""

    def __init__(self, material: str, origin: str):
        self.net = SurfaceNetwork(material=material, origin=origin)

    def unsupported(self, item: str) -> None:
        if item not in self.net.unsupported:
            self.net.unsupported.append(item)

    # ----------------------------------------------------------------------------------------------
    def read(self, shader: Node) -> SurfaceNetwork:
        sid = shader.nodedef
        if sid == PREVIEW_SURFACE:
            for name, default in PREVIEW_DEFAULTS.items():
                port = shader.port(name)
                if port is not None:
                    src = self.source(port, len(default), shader, name)
                    if src is not None:
                        self.net.inputs[name] = src
            return self.net
        std = sid == STANDARD_SURFACE
        names = ("base", "metalness", "specular", "specular_IOR", "coat", "emission", "opacity", "normal") if std \
            else ("base_weight", "base_metalness", "specular_weight", "specular_ior", "coat_weight",
                  "emission_luminance", "geometry_opacity", "geometry_normal")
        base, metal, spec, ior, coat, emit, opacity, normal = names
        inputs = self.net.inputs
        inputs["diffuseColor"] = self.subsurface(shader, "subsurface" if std else "subsurface_weight",
                                                 self.product(shader, base, "base_color"))
        inputs["metallic"] = self.input(shader, metal, 1)
        inputs["roughness"] = self.input(shader, "specular_roughness", 1)
        inputs["ior"] = self.ior(shader, spec, "specular_color", ior)
        inputs["clearcoat"] = self.input(shader, coat, 1)
        inputs["clearcoatRoughness"] = self.input(shader, "coat_roughness", 1)
        inputs["emissiveColor"] = self.product(shader, emit, "emission_color")
        inputs["opacity"] = self.opacity(shader, opacity, width=3 if std else 1)
        n = self.normal(shader, normal)
        if n is not None:
            inputs["normal"] = n
        self.coat_ior(shader, "coat_IOR" if std else "coat_ior")
        self.rest(shader)
        return self.net

    def input(self, shader: Node, name: str, width: int) -> Source:
        """An input mapped as it is: its source, else the node definition's default."""
        port = shader.port(name)
        src = self.source(port, width, shader, name) if port is not None else None
        return src if src is not None else Constant(self.default(shader, name, width))

    def default(self, shader: Node, name: str, width: int) -> tuple[float, ...]:
        return as_numbers(_default(shader.nodedef, name), width) or (0.0,) * width

    def constant(self, shader: Node, name: str, width: int) -> tuple[float, ...]:
        """An input that only folds as a constant: its value, else (said once) the default."""
        src = self.input(shader, name, width)
        if isinstance(src, Constant):
            return src.value
        value = self.default(shader, name, width)
        self.unsupported(f"{name} comes from {_node_words(src)}; usdml folds only a constant {name} into the "
                         f"preview surface: using its default {_words(value)}")
        return value

    # ----------------------------------------------------------------------------------------------
    def product(self, shader: Node, weight: str, color: str) -> Source:
        """``weight · color`` (a float and a colour input) as one source."""
        w, c = self.input(shader, weight, 1), self.input(shader, color, 3)
        if isinstance(w, Constant):
            scaled = _scale(c, (w.value[0],) * 3 + (1.0,))
            if scaled is not None:
                return scaled
        if isinstance(c, Constant):
            rgb = np.asarray(c.value, np.float64)
            if isinstance(w, Constant):
                return Constant(tuple(float(x) for x in rgb * w.value[0]))
            grey = bool(np.allclose(rgb, rgb[0]))
            scaled = _scale(w, (float(rgb.mean()),) * 3 + (1.0,))
            if scaled is not None:
                if not grey:
                    self.unsupported(f"{color} {_words(c.value)} tints {weight} from {_node_words(w)}: usdml "
                                     f"scales that by the tint's mean {rgb.mean():g} (a grey tint)")
                return scaled
        keep = c if not isinstance(c, Constant) else w
        self.unsupported(f"{weight} from {_node_words(w)} times {color} from {_node_words(c)} is not one lookup: "
                         f"usdml renders {color if keep is c else weight} alone")
        return keep

    def subsurface(self, shader: Node, weight: str, diffuse: Source) -> Source:
        """Both surfaces mix subsurface scattering into the diffuse lobe by its weight: a constant diffuse colour
        becomes ``lerp(diffuse, subsurface_color, weight)`` (the scattering itself is listed as not rendered)."""
        w, c = self.input(shader, weight, 1), self.input(shader, "subsurface_color", 3)
        if not isinstance(w, Constant) or w.value[0] <= 0.0:
            return diffuse
        if isinstance(diffuse, Constant) and isinstance(c, Constant):
            s = min(max(w.value[0], 0.0), 1.0)
            return Constant(tuple((1.0 - s) * d + s * x for d, x in zip(diffuse.value, c.value)))
        return diffuse

    def ior(self, shader: Node, weight: str, color: str, ior: str) -> Constant:
        """The ior whose F0 is ``weight · mean(color) · F0(ior)`` (module docstring)."""
        w = self.constant(shader, weight, 1)[0]
        tint = float(np.mean(self.constant(shader, color, 3)))
        n = self.constant(shader, ior, 1)[0]
        f0 = max(w, 0.0) * max(tint, 0.0) * ((n - 1.0) / (n + 1.0)) ** 2 if n > -1.0 else 0.0
        r = math.sqrt(min(f0, 0.98))
        return Constant(((1.0 + r) / (1.0 - r),))

    def coat_ior(self, shader: Node, name: str) -> None:
        """The preview surface's clearcoat reflects by ``ior``: say so where the coat's own IOR differs."""
        c = self.net.inputs.get("clearcoat")
        if isinstance(c, Constant) and c.value[0] <= 0.0:
            return
        own = self.constant(shader, name, 1)[0]
        ior = self.net.inputs["ior"].value[0]
        if abs(own - ior) > 0.01:
            self.unsupported(f"{name} {own:g}: the preview surface's clearcoat reflects by the surface's ior "
                             f"{ior:.4g}")

    def opacity(self, shader: Node, name: str, width: int) -> Source:
        src = self.input(shader, name, width)
        if isinstance(src, Constant):
            return Constant((float(np.mean(src.value)),))
        if isinstance(src, Image) and width == 3 and src.output in ("rgb", "rgba"):
            return dataclasses.replace(src, output="r")     # a grey mask: its red channel
        return src

    def normal(self, shader: Node, name: str) -> Source | None:
        """The tangent-space normal of a ``normalmap`` of an image (scale 2, bias −1, times its xy scale)."""
        port = shader.port(name)
        if port is None or port.node is None:
            return None
        node = port.node
        if not node.nodedef.startswith("ND_normalmap"):
            self.unsupported(f"{name} comes from {node.path} ({node.nodedef}), which usdml does not evaluate: "
                             "the geometric normal is used (use a normalmap of an image)")
            return None
        space = node.port("space")
        if space is not None and space.value not in (None, "tangent"):
            self.unsupported(f"{node.path}: normalmap space {space.value!r} is not rendered: the geometric normal "
                             "is used (use tangent space)")
            return None
        s = self.input(node, "scale", 2)
        sx, sy = s.value if isinstance(s, Constant) else (1.0, 1.0)
        tex_port = node.port("in")
        tex = self.source(tex_port, 3, node, "in") if tex_port is not None else None
        if not isinstance(tex, Image):
            if tex is not None and not isinstance(tex, Constant):
                self.unsupported(f"{node.path}.in is not an image: the geometric normal is used")
            return None
        mul = np.array([2.0 * sx, 2.0 * sy, 2.0, 1.0])
        add = np.array([-sx, -sy, -1.0, 0.0])
        return dataclasses.replace(tex, color_space="raw",
                                   scale=tuple(float(x) for x in np.asarray(tex.scale) * mul),
                                   bias=tuple(float(x) for x in np.asarray(tex.bias) * mul + add))

    def rest(self, shader: Node) -> None:
        """Authored inputs outside the mapping, one item per lobe (none for a lobe switched off by a constant 0)."""
        sid = shader.nodedef
        mapped, lobes = _MAPPED[sid], _LOBES[sid]
        groups: dict[str, list[str]] = {}
        for name in shader.inputs():
            if name in mapped:
                continue
            port = shader.port(name)
            if port is None:
                continue
            if port.node is None:
                if name in _GEOMETRY:
                    continue
                default = _default(sid, name)
                if default is not None and _same(port.value, default):
                    continue
                what = f"{name} {_words(port.value)}"
            else:
                what = f"{name} from {port.node.path}"
            lobe = _LOBE_OF.get(name) or next((k for k in lobes if name == k or name.startswith(k + "_")), name)
            groups.setdefault(lobe, []).append(what)
        for lobe, items in groups.items():
            switch = lobes.get(lobe)
            if switch is not None:
                port = shader.port(switch)
                value = _default(sid, switch) if port is None else port.value if port.node is None else None
                if value is not None and as_numbers(value, 1) == (0.0,):
                    continue                # switched off: its other inputs change nothing
            mixed = ": its colour is mixed into the diffuse" if lobe == "subsurface" else ""
            self.unsupported(f"{lobe} is not rendered ({', '.join(items)}){mixed}")

    # ----------------------------------------------------------------------------------------------
    def source(self, port: Port, width: int, owner: Node, name: str, depth: int = 0) -> Source | None:
        """What ``port`` gives as a preview source of ``width`` floats; None (said once) where usdml cannot
        evaluate it (the caller uses the default)."""
        if port.node is None:
            count = len(port.value) if isinstance(port.value, tuple) else 1
            numbers = as_numbers(port.value, width or count)
            if numbers is None:
                self.unsupported(f"{owner.path}.{name} = {port.value!r} is not a number: using the default")
            return None if numbers is None else Constant(numbers)
        node, sid = port.node, port.node.nodedef
        if depth > 32:
            return None
        if sid.startswith(("ND_image_", "ND_tiledimage_")):
            return self.image(node, port.output)
        if sid.startswith(("ND_convert_", "ND_dot_")):
            inner = node.port("in")
            return self.source(inner, width, node, "in", depth + 1) if inner is not None else \
                self.source(Port(value=_default(sid, "in")), width, node, "in")
        if sid.startswith("ND_extract_") or sid.startswith("ND_separate"):
            return self.channel(node, sid, port.output, depth)
        if sid.startswith("ND_multiply_"):
            return self.multiply(node, depth)
        if sid.startswith("ND_geompropvalue_"):
            geomprop = node.port("geomprop")
            default = node.port("default")
            fallback = as_numbers(default.value if default is not None else _default(sid, "default"), width)
            return Primvar(name=str(geomprop.value) if geomprop is not None and geomprop.value else "",
                           width=width, fallback=fallback or (0.0,) * width, node=node.path)
        if sid.startswith("ND_texcoord_"):
            return self.texcoord(node, width)
        self.unsupported(f"{owner.path}.{name} comes from {node.path} ({sid}), which usdml does not evaluate: "
                         "using the default")
        return None

    def texcoord(self, node: Node, width: int) -> Primvar:
        index = node.port("index")
        if index is not None and index.value not in (None, 0.0):
            self.unsupported(f"{node.path}: texcoord index {_words(index.value)} is read as primvar "
                             f"'{PRIMARY_UV}' (UV set 0)")
        return Primvar(name=PRIMARY_UV, width=width, fallback=(0.0,) * width, node=node.path)

    def channel(self, node: Node, sid: str, output: str, depth: int) -> Source | None:
        if sid.startswith("ND_extract_"):
            index = node.port("index")
            i = int((as_numbers(index.value, 1) or (0.0,))[0]) if index is not None else 0
        else:
            i = "rgba".index(_CHANNEL.get(output[-1:], "r"))
        inner = node.port("in")
        src = self.source(inner, 4, node, "in", depth + 1) if inner is not None else None
        if src is None:
            return None
        if isinstance(src, Constant):
            return Constant((src.value[min(i, len(src.value) - 1)],))
        if isinstance(src, Image) and src.output in ("rgb", "rgba") and 0 <= i < 4:
            return dataclasses.replace(src, output="rgba"[i])
        self.unsupported(f"{node.path} ({sid}) picks a channel of {_node_words(src)}, which usdml does not "
                         "evaluate: using the whole value")
        return src

    def multiply(self, node: Node, depth: int) -> Source | None:
        a, b = node.port("in1"), node.port("in2")
        sa = self.source(a, 0, node, "in1", depth + 1) if a is not None else Constant((1.0,))
        sb = self.source(b, 0, node, "in2", depth + 1) if b is not None else Constant((1.0,))
        if sa is None or sb is None:
            return None
        const, other = (sa, sb) if isinstance(sa, Constant) else (sb, sa)
        if isinstance(const, Constant):
            f = np.asarray(const.value, np.float64)
            if isinstance(other, Constant):
                g = np.asarray(other.value, np.float64)
                if len(f) == 1 or len(g) == 1 or len(f) == len(g):
                    return Constant(tuple(float(x) for x in f * g))
            factors = (float(f[0]),) * 4 if len(f) == 1 else tuple(_vec4(f[:3]) if len(f) == 3 else _vec4(f))
            scaled = _scale(other, factors)
            if scaled is not None:
                return scaled
        self.unsupported(f"{node.path} ({node.nodedef}) multiplies two lookups, which usdml does not evaluate: "
                         "using its first input")
        return sa

    def image(self, node: Node, output: str) -> Source | None:
        sid = node.nodedef
        kind = sid.split("_")[-1]
        authored, resolved = node.file("file")
        default = node.port("default")
        dvalue = default.value if default is not None and default.node is None else _default(sid, "default")
        if isinstance(dvalue, float):
            fallback = (dvalue,) * 3 + (1.0,)
        elif isinstance(dvalue, tuple) and dvalue:
            fallback = tuple(_vec4(dvalue[:3]) if len(dvalue) <= 3 else dvalue[:4])
        else:
            fallback = (0.0, 0.0, 0.0, 1.0)
        if "<UDIM>" in authored.upper():
            self.unsupported(f"{node.path}.file {authored} is a UDIM set, which usdml does not read: using its "
                             f"default {_words(fallback[:3])}")
            return Constant(fallback)
        st: Primvar | Constant = Primvar(PRIMARY_UV, 2, (0.0, 0.0), node.path)
        tc = node.port("texcoord")
        if tc is not None and tc.node is not None and \
                not tc.node.nodedef.startswith(("ND_texcoord_", "ND_geompropvalue_")):
            self.unsupported(f"{node.path}.texcoord comes from {tc.node.path} ({tc.node.nodedef}), which usdml does "
                             f"not evaluate: using primvar '{PRIMARY_UV}'")
        elif tc is not None:
            src = self.source(tc, 2, node, "texcoord")
            if isinstance(src, (Primvar, Constant)):
                st = src
        transforms: tuple[Transform2d, ...] = ()
        if sid.startswith("ND_tiledimage_"):
            values = {k: np.asarray(self.constant(node, k, 2), np.float64)
                      for k in ("uvtiling", "uvoffset", "realworldimagesize", "realworldtilesize")}
            size = np.where(values["realworldimagesize"] == 0, 1.0, values["realworldimagesize"])
            k = values["realworldtilesize"] / size
            transforms = (Transform2d(scale=tuple(float(x) for x in values["uvtiling"] * k),
                                      translation=tuple(float(x) for x in -values["uvoffset"] * k)),)
            wraps = ("repeat", "repeat")
        else:
            wraps = tuple(self.address(node, axis) for axis in ("uaddressmode", "vaddressmode"))
        out = {"float": "r", "color4": "rgba", "vector4": "rgba"}.get(kind, "rgb")
        if output and output != "out":
            out = _CHANNEL.get(output[-1:], out)
        return Image(node=node.path, file=resolved, authored=authored, st=st, transforms=transforms,
                     wrap_s=wraps[0], wrap_t=wraps[1], color_space=self.color_space(node, kind),
                     fallback=tuple(float(x) for x in fallback), fallback_authored=default is not None,
                     output=out)

    def address(self, node: Node, name: str) -> str:
        port = node.port(name)
        mode = str(port.value if port is not None and port.node is None else _default(node.nodedef, name)
                   or "periodic")
        if mode not in _ADDRESS:
            self.unsupported(f"{node.path}.{name} {mode!r} is not an address mode: using periodic")
        return _ADDRESS.get(mode, "repeat")

    def color_space(self, node: Node, kind: str) -> str:
        """Colour images follow their colour space; vector and float images are data (raw)."""
        if kind not in ("color3", "color4"):
            return "raw"
        port = node.port("file")
        space = (port.color_space if port is not None else "").strip()
        if not space:
            return "auto"
        if space.lower() in _SRGB:
            return "sRGB"
        if space.lower() not in _LINEAR:
            self.unsupported(f"{node.path}: colour space {space!r} is not converted: read as linear Rec.709")
        return "raw"


def _same(value, default) -> bool:
    if isinstance(value, str) or isinstance(default, str):
        return str(value) == str(default)
    a, b = np.atleast_1d(np.asarray(value, np.float64)), np.atleast_1d(np.asarray(default, np.float64))
    return a.shape == b.shape and bool(np.allclose(a, b))


def _scale(src: Source, factors: tuple[float, ...]) -> Source | None:
    """``src`` times per-channel ``factors`` (4 floats), or None when that is not one source."""
    f = np.asarray(factors, np.float64)
    if isinstance(src, Constant):
        v = np.asarray(src.value, np.float64)
        return Constant(tuple(float(x) for x in v * (f[:len(v)] if len(v) > 1 else f[0])))
    if isinstance(src, Image):
        if src.output in ("r", "g", "b", "a"):
            c = "rgba".index(src.output)
            if not np.allclose(f[:3], f[0]):
                return None
            f = np.where(np.arange(4) == c, f[0], 1.0)
        return dataclasses.replace(src, scale=tuple(float(x) for x in np.asarray(src.scale) * f),
                                   bias=tuple(float(x) for x in np.asarray(src.bias) * f))
    return src if np.allclose(f[:3], 1.0) else None


def _vec4(v) -> tuple[float, ...]:
    """A colour (3) as rgba with alpha 1; 4 floats as they are."""
    v = [float(x) for x in v]
    return tuple(v + [0.0] * (3 - len(v)) + [1.0]) if len(v) < 4 else tuple(v[:4])


def _node_words(src: Source) -> str:
    if isinstance(src, Image):
        return f"image {src.node}"
    if isinstance(src, Primvar):
        return f"primvar '{src.name}'"
    return _words(src.value)


# --------------------------------------------------------------------------------------------------
def surface_node(material: UsdShade.Material) -> UsdShade.Shader | None:
    """The material's MaterialX surface shader in the USD file (render context ``mtlx`` first), or None."""
    contexts = ["mtlx"] + [o.GetBaseName().rpartition(":")[0] for o in material.GetSurfaceOutputs()]
    candidates = [material.ComputeSurfaceSource(context)[0] for context in dict.fromkeys(contexts)]
    for shader in candidates:
        if shader and shader_id(shader) in SURFACES:
            return shader
    return None


def read_materialx(material: UsdShade.Material, time: Usd.TimeCode, warn: Warn | None = None
                   ) -> SurfaceNetwork | None:
    """The material's MaterialX surface as the preview surface usdml renders: its own ``ND_`` nodes, else the
    ``.mtlx`` document it (or an ancestor) references; None when it has neither, or what it has cannot be read
    (``warn`` says why, naming the material)."""
    path = str(material.GetPath())
    shader = surface_node(material)
    if shader is not None:
        node = UsdNode(shader, time)
        try:
            return _Mapper(path, f"MaterialX {node.nodedef} ({node.path})").read(node)
        except Exception as e:            # noqa: BLE001 — bad content never stops a frame
            say = warn if warn is not None else _quiet
            say(f"{path}: cannot read its MaterialX surface {node.path} ({type(e).__name__}: {e}); using displayColor")
            return None
    return read_materialx_path(material.GetPrim().GetStage(), path, time, warn)


def read_materialx_path(stage: Usd.Stage, path: str, time: Usd.TimeCode, warn: Warn | None = None
                        ) -> SurfaceNetwork | None:
    """The material at ``path`` read from the ``.mtlx`` document that a reference or payload on it or an ancestor
    names (the prim may be missing: usd-core cannot compose a ``.mtlx``); None when there is none, its file is
    missing (the composition error says so), or it cannot be read (``warn`` says why)."""
    say = warn if warn is not None else _quiet
    arcs = list(mtlx_arcs(stage, path))
    if not arcs:
        return None
    problems: list[str] = []
    names = set()
    for file, target in arcs:
        doc = _read_document(file)
        if doc is None:
            continue                           # a missing file: the composition error names it
        if isinstance(doc, str):
            problems.append(doc)
            continue
        if target.GetParentPath() != MATERIALS_SCOPE:
            problems.append(f"{doc.label} maps it to <{target}>, not a material (</MaterialX/Materials/name>)")
            continue
        name = target.name
        names.add(name)
        element = doc.doc.getChild(name)
        if element is None or element.getCategory() != "surfacematerial":
            continue
        try:
            return _from_document(path, doc, element, say)
        except Exception as e:             # noqa: BLE001
            problems.append(f"{doc.label}: material {name!r} cannot be read ({type(e).__name__}: {e})")
    if problems:
        say(f"{path}: {'; '.join(problems)}; using displayColor")
    elif names:
        files = ", ".join(sorted({_label(f) for f, _t in arcs}))
        say(f"{path}: no surfacematerial {', '.join(sorted(names))!s} in {files}; using displayColor")
    return None


def _quiet(_message: str) -> None:
    pass


def _from_document(path: str, doc: _Document, element, warn: Warn) -> SurfaceNetwork | None:
    import MaterialX as mx

    shaders = [s for s in mx.getShaderNodes(element) if s.getType() == "surfaceshader"]
    if not shaders:
        warn(f"{path}: {doc.label} material {element.getName()!r} has no surface shader; using displayColor")
        return None
    node = MxNode(shaders[0], doc)
    if node.nodedef not in SURFACES:
        warn(f"{path}: {doc.label} material {element.getName()!r} has surface {node.nodedef}, which usdml does "
             "not render (standard_surface, open_pbr_surface, UsdPreviewSurface); using displayColor")
        return None
    return _Mapper(path, f"MaterialX {node.nodedef} ({node.path})").read(node)


def mtlx_arcs(stage: Usd.Stage, path: str) -> Iterator[tuple[str, Sdf.Path]]:
    """``(resolved .mtlx file, the path in its UsdMtlx namespace)`` for each reference or payload to a ``.mtlx``
    authored on ``path``'s prim or its nearest ancestors' (nearest first); ``path`` itself may not exist."""
    target_path = Sdf.Path(path)
    at = target_path
    while at != Sdf.Path.absoluteRootPath and not at.isEmpty:
        prim = stage.GetPrimAtPath(at)
        if prim:
            for spec in prim.GetPrimStack():
                for arc in list(spec.referenceList.GetAddedOrExplicitItems()) + \
                        list(spec.payloadList.GetAddedOrExplicitItems()):
                    asset = arc.assetPath
                    if not asset.lower().endswith(".mtlx"):
                        continue
                    root = arc.primPath if not arc.primPath.isEmpty else Sdf.Path("/MaterialX")
                    rel = target_path.MakeRelativePath(at)
                    full = root if rel == Sdf.Path(".") else root.AppendPath(rel)
                    yield _resolve(spec.layer, asset), full
        at = at.GetParentPath()


def _resolve(layer: Sdf.Layer, asset: str) -> str:
    anchored = Sdf.ComputeAssetPathRelativeToLayer(layer, asset) if layer is not None else asset
    resolved = str(Ar.GetResolver().Resolve(anchored) or "")
    return resolved or anchored


def _label(file: str) -> str:
    return os.path.basename(file.rstrip("]").split("[")[-1]) if file.endswith("]") else os.path.basename(file)


def _read_document(file: str) -> "_Document | str | None":
    """The document at ``file`` (cached while the file is unchanged); None when it does not exist, a one-line
    problem when it does not read."""
    package = ""
    if file.endswith("]") and "[" in file:
        package = file[:file.rindex("[")]
        stamp = _stamp(package)
    else:
        stamp = _stamp(file)
    if stamp is None:
        return None
    return _read_cached(file, stamp)


def _stamp(path: str):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=64)
def _read_cached(file: str, _stamp) -> "_Document | str":
    label = _label(file)
    try:
        import MaterialX as mx
    except ImportError:
        return f"{label} is MaterialX and the materialx package is not installed (pip install materialx)"
    doc = mx.createDocument()
    try:
        if file.endswith("]") and "[" in file:
            asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(file))
            if asset is None:
                return f"{label} cannot be opened inside its package"
            mx.readFromXmlString(doc, bytes(asset.GetBuffer()).decode("utf-8", "replace"))
            package, inner = file[:file.rindex("[")], file[file.rindex("[") + 1:-1]
            where = _Document(doc, label, os.path.dirname(inner), package)
        else:
            mx.readFromXmlFile(doc, file)
            where = _Document(doc, label, os.path.dirname(file))
    except Exception as e:              # noqa: BLE001 — MaterialX raises its own exception types
        message = " ".join(str(e).split()) or type(e).__name__
        return f"{label} does not parse as MaterialX ({message})"
    lib = _library()
    if lib is not None:
        doc.setDataLibrary(lib)
    return where
