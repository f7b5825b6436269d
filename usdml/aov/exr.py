"""Writing and reading usdml's per-timecode OpenEXR files, and PNG previews.

One file per timecode (and product): a single-part scanline EXR holding every AOV as channels named
by :mod:`usdml.aov.names` (``R,G,B,A`` for ``color``, ``Z`` for ``depth``, ``<aov>.R/G/B``,
``<aov>.X/Y/Z``, ``<aov>.Y``, ``<aov>.id``), each channel in its own pixel type: half colours,
float geometry, uint ids, in the same file.

Library. Pixels and header go through the OpenEXR project's own Python bindings (``OpenEXR.File``,
OpenEXR >= 3.3): they write each channel from a NumPy array of its own dtype, so uint ids are exact
and the timecode is a ``double`` attribute. OpenImageIO's Python ``ImageOutput.write_image`` takes
one buffer type for all channels and converts float -> uint as a *normalized* value through float,
which corrupts ids above 2**24, and its ``ImageSpec.attribute`` cannot set a ``double``.
OpenImageIO reads the files back (:func:`is_complete_exr` decodes them with it) and writes the PNG
previews.

Channel order. OpenEXR stores a part's channels sorted by name (``A,B,G,R,Z,albedo.B,...``), whoever
writes them. OpenImageIO presents them with ``R,G,B,A`` first, then ``Z``, then each layer's channels
(``direct.R,direct.G,direct.B``). :func:`read_exr` returns arrays by AOV with components in the
registry's order (R,G,B,A / X,Y,Z), never by file position.

Orientation. Arrays are ``(H, W)`` or ``(H, W, C)`` with row 0 the TOP of the image, which is
OpenEXR's own order (y grows downwards from the data window's top-left corner).

Header.

* ``worldToCamera`` (M44f): OpenEXR's standard attribute. OpenEXR (``ImfStandardAttributes.h``,
  openexr.com "Standard Attributes") defines camera space as RenderMan's: left-handed, origin at the
  camera, +x right, +y up, **+z the viewing direction** (points in front have z > 0). Imath matrices
  act on row vectors (``p' = p * M``, translation in the last row). usdml matrices act on column
  vectors (``p' = M @ [p, 1]``) and USD cameras look down **-Z** (right-handed, +Y up), so
  ``exr = (diag(1, 1, -1, 1) @ world_to_camera).T``.
* ``worldToNDC`` (M44f): OpenEXR's NDC is the image plane, (0, 0) the upper-left and (1, 1) the
  lower-right corner of the display window, +y down; a world point ``[x y z 1] * M`` divided by its
  w gives it (z is discarded). usdml's ``world_to_ndc`` argument is world -> OpenGL clip space
  (``Camera.projection_matrix() @ inv(camera.xform)``: after the divide x, y in [-1, 1], +y up), so
  ``exr = (A @ world_to_ndc).T`` with ``A`` mapping x -> (x + 1) / 2, y -> (1 - y) / 2 and keeping
  z and w. Pixel (i, j) has its centre at NDC ((i + 0.5) / W, (j + 0.5) / H).
  :func:`usdml_world_to_camera` / :func:`usdml_world_to_ndc` undo both conversions.
* ``chromaticities`` (OpenEXR's standard attribute): the primaries and white point of the colours, the rendering
  space's: linear Rec.709 / sRGB primaries (ITU-R BT.709: red 0.64, 0.33; green 0.30, 0.60; blue 0.15, 0.06) and
  D65 white (0.3127, 0.3290), :data:`REC709_CHROMATICITIES`. usdml renders in that space: textures are decoded to
  it (``sourceColorSpace``), colours are taken as given in it, as Storm does. ``write_png_preview`` encodes the
  same primaries with the sRGB transfer function.
* ``usdml:timeCode`` (double), ``usdml:stage`` (string, the stage's path),
  ``usdml:settings`` (string, JSON with sorted keys; a render writes what its pixels depend on and
  ``usdml:settingsDigest``, :mod:`usdml.render.identity`), ``usdml:aovs`` (string, JSON
  ``{layer: aov}``, so a renamed layer reads back as its AOV), ``usdml:version`` (string);
  then every entry of ``metadata`` (see :func:`write_exr` for the types).

Atomicity. Every file is written under a hidden temporary name in the destination folder
(``.<name>.<pid>.<random>.tmp.exr``), flushed to disk, then renamed onto the final name with
``os.replace`` (atomic on POSIX and Windows within one file system). Any exception, including a
``KeyboardInterrupt`` during the write, removes the temporary file and leaves the final name as it
was: absent, or the previous complete file. Only a hard kill (SIGKILL, power loss) can leave a
``.*.tmp.exr`` behind, never a partial file under the final name.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from usdml.aov.names import AOVS, NO_ID, AovSpec, find_aov
from usdml.errors import UsdmlError
from usdml.outputs import atomic_write, write_image

__all__ = [
    "ExrError", "REC709_CHROMATICITIES", "write_exr", "read_exr", "is_complete_exr", "exr_attribute", "write_png_preview",
    "exr_world_to_camera", "exr_world_to_ndc", "usdml_world_to_camera", "usdml_world_to_ndc",
    "camera_matrices", "COMPRESSIONS",
]


class ExrError(UsdmlError):
    """An EXR file that cannot be read (missing, truncated, not an EXR)."""


# --- camera matrices ----------------------------------------------------------------------------

_FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])
#: OpenGL clip (x, y in [-1, 1] after the divide, +y up) -> OpenEXR NDC ([0, 1], +y down)
_GL_TO_EXR_NDC = np.array([
    [0.5, 0.0, 0.0, 0.5],
    [0.0, -0.5, 0.0, 0.5],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
])


def _mat4(m: Any, what: str) -> np.ndarray:
    m = np.asarray(m, np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{what} must be a (4, 4) matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError(f"{what} has non-finite entries")
    return m


def exr_world_to_camera(world_to_camera: Any) -> np.ndarray:
    """usdml world->camera (column vectors, camera looks down -Z) -> OpenEXR ``worldToCamera``."""
    # C order matters: OpenEXR's bindings read a matrix's raw buffer, ignoring NumPy strides
    return np.ascontiguousarray((_FLIP_Z @ _mat4(world_to_camera, "world_to_camera")).T, np.float32)


def exr_world_to_ndc(world_to_ndc: Any) -> np.ndarray:
    """usdml world->OpenGL clip (column vectors) -> OpenEXR ``worldToNDC`` (row vectors, +y down)."""
    return np.ascontiguousarray((_GL_TO_EXR_NDC @ _mat4(world_to_ndc, "world_to_ndc")).T, np.float32)


def usdml_world_to_camera(exr_matrix: Any) -> np.ndarray:
    """Inverse of :func:`exr_world_to_camera` (float64, column vectors, -Z forward)."""
    return _FLIP_Z @ np.asarray(exr_matrix, np.float64).reshape(4, 4).T


def usdml_world_to_ndc(exr_matrix: Any) -> np.ndarray:
    """Inverse of :func:`exr_world_to_ndc` (float64, column vectors, OpenGL clip space)."""
    return np.linalg.inv(_GL_TO_EXR_NDC) @ np.asarray(exr_matrix, np.float64).reshape(4, 4).T


def camera_matrices(camera: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(world_to_camera, world_to_ndc)`` for :func:`write_exr` from a :class:`usdml.scene.Camera`."""
    world_to_camera = np.linalg.inv(np.asarray(camera.xform, np.float64))
    return world_to_camera, np.asarray(camera.projection_matrix(), np.float64) @ world_to_camera


# --- EXR writing --------------------------------------------------------------------------------

def _compressions() -> dict[str, Any]:
    import OpenEXR

    out = {}
    for member in OpenEXR.Compression.__members__.values():
        name = member.name
        if name.endswith("_COMPRESSION"):
            out[name[: -len("_COMPRESSION")].lower()] = member
    out["none"] = out.pop("no")
    return out


#: lossless: none, rle, zips, zip (default), piz; lossy: pxr24 (float channels to 24 bits),
#: b44 / b44a (half channels), dwaa / dwab (lossy on colour-named half channels); plus whatever the
#: installed OpenEXR adds (zstd, htj2k...)
COMPRESSIONS: tuple[str, ...] = tuple(sorted(_compressions()))

#: the rendering space's primaries and white point, OpenEXR's ``chromaticities`` order (red x, y, green x, y, blue x, y,
#: white x, y): linear Rec.709 / sRGB (ITU-R BT.709) with D65 white (module doc)
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

#: header attributes that describe the image itself, not metadata
_STRUCTURAL = frozenset({
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "tiles", "name", "version", "chunkCount",
    "maxSamplesPerPixel", "view",
})
_INT32 = (-(2 ** 31), 2 ** 31 - 1)


def _attribute(key: str, value: Any) -> Any:
    """A Python / NumPy metadata value as something ``OpenEXR.File`` stores faithfully."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (str, np.str_)):
        return str(value)
    if isinstance(value, (int, np.integer)):
        v = int(value)
        if _INT32[0] <= v <= _INT32[1]:
            return v
        return np.array([float(v)], np.float64) if abs(v) <= 2 ** 53 else str(v)
    if isinstance(value, (float, np.floating)):
        return np.array([float(value)], np.float64)       # an EXR "double" attribute
    if isinstance(value, Mapping):
        return json.dumps(value, sort_keys=True, default=str)
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value) and value:
        return [str(v) for v in value]                     # stringvector
    if isinstance(value, (list, tuple, np.ndarray)):
        a = np.asarray(value)
        # C-contiguous copies: OpenEXR's bindings read the raw buffer, ignoring NumPy strides
        if a.shape in ((4, 4), (3, 3)) and a.dtype.kind in "fiu":
            return np.ascontiguousarray(a, np.float32 if a.dtype == np.float32 else np.float64)
        if a.shape in ((2,), (3,)) and a.dtype.kind == "f":
            return np.ascontiguousarray(a, np.float32 if a.dtype == np.float32 else np.float64)
        if a.shape in ((2,), (3,)) and a.dtype.kind in "iu" and np.all(np.abs(a) < 2 ** 31):
            return np.ascontiguousarray(a, np.int32)                               # V2i/V3i
        if a.dtype.kind in "fiub" and a.ndim == 1:
            return json.dumps(a.tolist())
    raise TypeError(f"EXR metadata {key!r}: cannot store a {type(value).__name__} "
                    f"(use str, int, float, a dict (JSON), a list of str, or a 2/3-vector / 3x3 / "
                    f"4x4 matrix)")


def _layer_spec(layer: str, layers: Mapping[str, str] | None) -> AovSpec:
    aov = (layers or {}).get(layer, layer)
    spec = find_aov(aov)
    if spec is None:
        raise ValueError(f"AOV layer {layer!r}: unknown AOV {aov!r}; known: {', '.join(AOVS)} "
                         f"(map a renamed layer with layers={{{layer!r}: '<aov>'}})")
    return spec


def _id_channel(a: np.ndarray, layer: str) -> np.ndarray:
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or not np.all(a == np.round(a)):
            raise ValueError(f"AOV {layer!r}: ids must be integers (or integral floats)")
    elif a.dtype.kind not in "iu":
        raise ValueError(f"AOV {layer!r}: ids must be integers, got dtype {a.dtype}")
    a = a.astype(np.int64)
    if a.size and (a.min() < -1 or a.max() > NO_ID - 1):
        raise ValueError(f"AOV {layer!r}: ids must lie in [-1, {NO_ID - 1}] (-1 = no prim), "
                         f"got [{a.min()}, {a.max()}]")
    return np.where(a < 0, NO_ID, a).astype(np.uint32)


def _channels(aovs: Mapping[str, Any], layers: Mapping[str, str] | None) -> tuple[dict, dict, tuple]:
    if not aovs:
        raise ValueError("write_exr: no AOVs to write")
    channels: dict[str, np.ndarray] = {}
    names: dict[str, str] = {}
    size = None
    for layer, data in aovs.items():
        spec = _layer_spec(layer, layers)
        a = np.asarray(data)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.ndim != 3 or a.shape[2] != spec.components:
            want = "(H, W)" if spec.components == 1 else f"(H, W, {spec.components})"
            raise ValueError(f"AOV {layer!r} ({spec.name}) must have shape {want}, got {np.shape(data)}")
        if size is None:
            size = a.shape[:2]
            if min(size) < 1:
                raise ValueError(f"AOV {layer!r}: empty image {size}")
        elif a.shape[:2] != size:
            raise ValueError(f"AOV {layer!r} is {a.shape[1]}x{a.shape[0]} (W x H) but the other AOVs "
                             f"are {size[1]}x{size[0]}; all AOVs of one file share a resolution")
        if spec.is_id:
            stored = _id_channel(a, layer)
        else:
            if a.dtype.kind not in "fiub":
                raise ValueError(f"AOV {layer!r}: expected numbers, got dtype {a.dtype}")
            stored = a.astype(spec.dtype)
        for i, name in enumerate(spec.channels(layer)):
            if name in channels:
                raise ValueError(f"AOV {layer!r}: channel {name!r} is already written by AOV "
                                 f"{names[name]!r} (one color and one depth AOV per file)")
            channels[name] = np.ascontiguousarray(stored[:, :, i])
            names[name] = layer
    return channels, {layer: _layer_spec(layer, layers).name for layer in aovs}, size


def write_exr(
    path: str | os.PathLike,
    aovs: Mapping[str, Any],
    *,
    metadata: Mapping[str, Any] | None = None,
    world_to_camera: Any = None,
    world_to_ndc: Any = None,
    timecode: float | None = None,
    stage: str | os.PathLike | None = None,
    settings: Mapping[str, Any] | str | None = None,
    layers: Mapping[str, str] | None = None,
    compression: str = "zip",
) -> Path:
    """Write ``aovs`` as one scanline OpenEXR file at ``path``, atomically. Returns the path.

    ``aovs`` maps a layer name to an array ``(H, W)`` or ``(H, W, C)``, row 0 the top of the image.
    The layer name is an AOV of :data:`usdml.aov.names.AOVS` (or an alias), or any name that
    ``layers`` maps to one (a RenderVar's name: ``layers={"beauty": "color"}``; a renamed layer
    prefixes its channels, ``color`` and ``depth`` keep ``R,G,B,A`` and ``Z``). Colours are stored
    as half, geometry as float, ids (integers, ``-1`` = none) as uint.

    ``world_to_camera`` / ``world_to_ndc`` (usdml's column-vector convention, see the module doc)
    become ``worldToCamera`` / ``worldToNDC``; ``timecode`` ``usdml:timeCode`` (double); ``stage``
    ``usdml:stage``; ``settings`` (a dict, stored as JSON with sorted keys, or a JSON string)
    ``usdml:settings``. ``metadata`` adds attributes (names as given, e.g. ``usdml:backend``):
    str -> string, int -> int (double beyond 32 bits), float -> double, bool -> int,
    dict -> JSON string, list of str -> stringvector, 2/3-vectors -> V2/V3, 3x3 / 4x4 -> M33/M44
    (f for float32 input, d otherwise). The explicit arguments win over same-named ``metadata``.
    ``compression``: one of :data:`COMPRESSIONS` (``zip`` by default; lossless: none, rle, zips,
    zip, piz).
    """
    import OpenEXR

    comp = _compressions().get(str(compression).lower())
    if comp is None:
        raise ValueError(f"unknown EXR compression {compression!r}; choose one of {', '.join(COMPRESSIONS)}")
    channels, layer_aovs, _ = _channels(aovs, layers)

    header: dict[str, Any] = {}
    for key, value in (metadata or {}).items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"EXR metadata names must be non-empty strings, got {key!r}")
        if key in _STRUCTURAL:
            raise ValueError(f"EXR metadata {key!r} is a structural attribute and cannot be set")
        if value is not None:
            header[key] = _attribute(key, value)
    from usdml import __version__

    header["usdml:version"] = __version__
    header["usdml:aovs"] = json.dumps(layer_aovs)
    header["chromaticities"] = REC709_CHROMATICITIES
    if world_to_camera is not None:
        header["worldToCamera"] = exr_world_to_camera(world_to_camera)
    if world_to_ndc is not None:
        header["worldToNDC"] = exr_world_to_ndc(world_to_ndc)
    if timecode is not None:
        t = float(timecode)
        if not math.isfinite(t):
            raise ValueError(f"timecode must be finite, got {timecode!r}")
        header["usdml:timeCode"] = np.array([t], np.float64)
    if stage is not None:
        header["usdml:stage"] = os.fspath(stage)
    if settings is not None:
        header["usdml:settings"] = (settings if isinstance(settings, str)
                                    else json.dumps(settings, sort_keys=True, default=str))
    header["compression"] = comp
    header["type"] = OpenEXR.scanlineimage

    return atomic_write(path, ".exr", lambda tmp: _write_file(tmp, header, channels))


def _write_file(path: Path, header: dict, channels: dict) -> None:
    """The one call that touches the disk (tests replace it to simulate a failure mid-write)."""
    import OpenEXR

    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


# --- EXR reading --------------------------------------------------------------------------------

def _header_value(value: Any) -> Any:
    if isinstance(value, np.ndarray) and value.shape == (1,) and value.dtype == np.float64:
        return float(value[0])
    return value


def read_exr(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(aovs, metadata)`` of a usdml EXR (or any single-part scanline EXR).

    ``aovs`` maps layer names to ``(H, W)`` / ``(H, W, C)`` arrays in the stored precision
    (float16 / float32), components in the registry's order; id layers come back as int64 with
    ``-1`` for no prim. ``R,G,B,A`` is ``color`` and ``Z`` is ``depth`` unless ``usdml:aovs`` names
    the layer otherwise. Channels of unknown layers are grouped by prefix in name order; bare
    channels keep their name.

    ``metadata`` holds the header without the structural attributes (channels, windows, ...) plus
    ``compression`` as a name. ``worldToCamera`` / ``worldToNDC`` are the stored OpenEXR matrices
    (float32, row vectors, see the module doc; :func:`usdml_world_to_camera` and
    :func:`usdml_world_to_ndc` convert them back), ``usdml:timeCode`` a float.
    Raises :class:`ExrError` for a missing or unreadable file.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: no such EXR file; check the path")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = dict(f.header())
            pixels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as e:  # noqa: BLE001 - the bindings raise several types for a bad file
        raise ExrError(f"{path}: not a complete OpenEXR file ({e})") from e

    metadata = {k: _header_value(v) for k, v in header.items() if k not in _STRUCTURAL}
    comp = header.get("compression")
    if comp is not None:
        name = getattr(comp, "name", str(comp))
        metadata["compression"] = {"NO_COMPRESSION": "none"}.get(
            name, name.removesuffix("_COMPRESSION").lower())

    try:
        layer_aovs = json.loads(metadata.get("usdml:aovs", "{}"))
    except (TypeError, ValueError):
        layer_aovs = {}
    unprefixed = {find_aov(a).name: layer for layer, a in layer_aovs.items()
                  if find_aov(a) is not None and not find_aov(a).prefixed}

    # layers whose channels follow their name directly (Cryptomatte's CryptoObject00.R): layer -> its suffixes
    joined = {layer: set(spec.suffixes) for layer, spec in
              [(n, a) for n, a in AOVS.items()] + [(n, find_aov(a)) for n, a in layer_aovs.items() if find_aov(a)]
              if spec.separator == ""}
    groups: dict[str, dict[str, np.ndarray]] = {}
    for name, a in pixels.items():
        whole = next((layer for layer, suffixes in joined.items()
                      if name.startswith(layer) and name[len(layer):] in suffixes), None)
        if whole is not None:
            layer, suffix = whole, name[len(whole):]
        elif name in ("R", "G", "B", "A"):
            layer, suffix = unprefixed.get("color", "color"), name
        elif name == "Z":
            layer, suffix = unprefixed.get("depth", "depth"), name
        elif "." in name:
            layer, suffix = name.rsplit(".", 1)
        else:
            layer, suffix = name, ""
        groups.setdefault(layer, {})[suffix] = a

    aovs: dict[str, np.ndarray] = {}
    for layer, chans in groups.items():
        spec = find_aov(layer_aovs.get(layer, layer))
        if spec is not None and set(chans) == set(spec.suffixes):
            order = list(spec.suffixes)
        else:
            spec = None
            order = sorted(chans, key=lambda s: ("RGBAXYZ".find(s) if len(s) == 1 and s in "RGBAXYZ"
                                                 else 7, s))
        arrays = [chans[s] for s in order]
        if len(arrays) == 1:
            out = arrays[0]
        elif len({a.dtype for a in arrays}) == 1:
            out = np.stack(arrays, axis=-1)
        else:                       # mixed types in an unknown layer: keep each channel
            for s, a in zip(order, arrays):
                aovs[f"{layer}.{s}"] = a
            continue
        if out.dtype == np.uint32:
            out = out.astype(np.int64)
            out[out == NO_ID] = -1
        aovs[layer] = out
    return aovs, metadata


def _open_input(path: str | os.PathLike):
    """OpenImageIO's reader of the file at ``path`` (the caller closes it), or None for a missing or
    unreadable file."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path)) if Path(path).is_file() else None
    if inp is None:
        oiio.geterror()     # clear the global error message
    return inp


def is_complete_exr(path: str | os.PathLike, channels: Any = None) -> bool:
    """True when ``path`` is an OpenEXR file OpenImageIO opens and decodes in full.

    A missing, truncated or corrupt file, or one lacking any of ``channels`` (EXR channel names, for
    ``--resume``: a file without the requested AOVs is redone), gives False. Never raises for a
    bad file.
    """
    import OpenImageIO as oiio

    inp = _open_input(path)
    if inp is None:
        return False
    try:
        if inp.format_name() != "openexr":
            return False
        spec = inp.spec()
        if channels is not None and not set(channels) <= set(spec.channelnames):
            return False
        # decode every scanline, a band at a time (bounded memory for 4K frames with many AOVs)
        band = max(1, (64 << 20) // max(1, spec.width * spec.nchannels * 4))
        for y in range(spec.y, spec.y + spec.height, band):
            y_end = min(y + band, spec.y + spec.height)
            pixels = inp.read_scanlines(0, 0, y, y_end, spec.z, 0, spec.nchannels, oiio.FLOAT)
            if pixels is None or inp.geterror() or (
                    np.asarray(pixels).size != (y_end - y) * spec.width * spec.nchannels):
                return False
        return True
    except Exception:  # noqa: BLE001
        return False
    finally:
        inp.close()


def exr_attribute(path: str | os.PathLike, name: str) -> str | None:
    """The string attribute ``name`` of an OpenEXR file's header (``usdml:settingsDigest``), read
    without its pixels; None for a missing attribute or an unreadable file. Never raises for a bad file."""
    inp = _open_input(path)
    if inp is None:
        return None
    try:
        value = inp.spec().getattribute(name)
        return value if isinstance(value, str) else None
    finally:
        inp.close()


# --- PNG preview --------------------------------------------------------------------------------

def _srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), input clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_png_preview(
    path: str | os.PathLike,
    rgba: Any,
    *,
    exposure: float = 0.0,
    tonemap: str = "clamp",
    alpha: bool = True,
) -> Path:
    """An 8-bit sRGB PNG of a linear, premultiplied ``(H, W, 4)`` (or ``(H, W, 3)``) image, atomically.

    Steps: multiply by ``2**exposure``; with ``alpha`` (and 4 channels) un-premultiply (PNG alpha is
    straight) and keep A, else composite over black (use the premultiplied RGB) and write RGB;
    tone map -- ``clamp``: clip to [0, 1]; ``reinhard``: ``c / (1 + L)`` with L the Rec.709
    luminance of c (keeps hue, rolls highlights off), then clip; encode with the sRGB transfer
    function and round to 8 bits. NaN -> 0, +inf -> white. The file is tagged sRGB.
    """
    if tonemap not in ("clamp", "reinhard"):
        raise ValueError(f"tonemap must be 'clamp' or 'reinhard', got {tonemap!r}")
    img = np.asarray(rgba, np.float64)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or min(img.shape[:2]) < 1:
        raise ValueError(f"preview image must have shape (H, W, 4) or (H, W, 3), got {img.shape}")
    img = np.nan_to_num(img, nan=0.0, posinf=1e30, neginf=0.0)
    rgb = img[..., :3] * (2.0 ** float(exposure))
    keep_alpha = alpha and img.shape[2] == 4
    if keep_alpha:
        a = np.clip(img[..., 3:4], 0.0, 1.0)
        rgb = np.where(a > 0, rgb / np.maximum(a, 1e-30), 0.0)
    if tonemap == "reinhard":
        lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
        rgb = rgb / (1.0 + np.maximum(lum, 0.0))[..., None]
    out = _srgb_encode(rgb)
    if keep_alpha:
        out = np.concatenate([out, a], axis=-1)
    return write_image(path, np.round(out * 255.0).astype(np.uint8), suffix=".png")
