"""``UsdLux.DomeLight`` / ``DomeLight_1``: read a dome light at a timecode into plain data (:class:`usdml.scene.Dome`).

:func:`usdml.lighting.dome.dome_to_distant_lights` turns a dome into K distant lights per frame,
so dome-lit stages go through the same many-light visibility as every other light. What a
:class:`~usdml.scene.Dome` holds (its radiometry, the lat-long map convention) is documented in
:mod:`usdml.scene.dome`; this module reads the prim.

``inputs:normalize`` has no effect on dome lights: UsdLux LightAPI defines it as normalizing the power
"by the surface area of the light" (``pxr/usd/usdLux/schema.usda``), and a dome, being infinitely far
away, has no surface area to divide by. It is ignored here, without a warning.

Pole axis and orientation
-------------------------
``DomeLight_1`` adds ``poleAxis``: "Y" keeps the default; "Z" rotates the dome +90° about X before
its transform (+Y → +Z, and longitude 0 then faces −Y, as the schema says); "scene" (the fallback) is
"Z" when the stage's ``upAxis`` is Z, else "Y". This follows ``usdImaging/domeLight_1Adapter.cpp``
(``_GetDomeOffset``: ``GfRotation((1, 0, 0), 90)`` applied before the prim's transform). The plain
``DomeLight`` always has its pole on +Y, whatever the stage's up axis.

The world rotation :attr:`Dome.to_world` is ``R_xform @ R_pole``, where ``R_xform`` is the rotation of
the dome's local-to-world matrix (its polar decomposition: scale and shear are dropped, since a dome is
infinitely far away, only its orientation matters).

Texture files
-------------
``inputs:texture:file`` is resolved through USD's asset resolver and read once per file (cached by
resolved path, size and modification time) with OpenImageIO: float and half images (EXR, HDR) are used
as they are, integer images (8/16-bit PNG, JPEG, TIFF ...) are taken as sRGB-encoded and linearized,
unless the file declares a linear colour space. One channel is grey; two channels are grey + alpha;
alpha is dropped. Non-finite or negative texels become 0 (with a warning).
``inputs:texture:format``: "latlong" is supported; "automatic" means latlong for a 2:1 image.
"mirroredBall", "angular", "cubeMapVerticalCross" (or "automatic" on an image that is not 2:1) are not
supported yet: a warning, and the dome becomes constant with the image's mean colour. A missing or
unreadable file warns and leaves a constant dome of the light's colour.
"""

from __future__ import annotations

from collections import OrderedDict
import os
import threading
from typing import Callable

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdml.errors import UsdmlError
from usdml.scene import Dome
from usdml.stage.lights import attribute_value, emitted_radiance

__all__ = ["read_dome", "is_dome", "load_texture", "dome_pole_rotation", "clear_texture_cache"]

#: Rotation (column convention) that puts the dome's pole on +Z: +90° about X (+Y → +Z, +Z → −Y).
_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: Texture formats usdml samples; the others fall back to a constant dome of the map's mean colour.
SUPPORTED_FORMATS = {"automatic", "latlong"}

#: Most texture files kept in memory at once (a 8k × 4k float map is 400 MB).
TEXTURE_CACHE_SIZE = 4


def dome_pole_rotation(pole_axis: str) -> np.ndarray:
    """(3, 3) rotation applied to the dome before its transform for a resolved pole axis "Y" or "Z"."""
    return _Z_UP.copy() if pole_axis == "Z" else np.eye(3)


def is_dome(prim: Usd.Prim) -> bool:
    return prim.GetTypeName() in ("DomeLight", "DomeLight_1")


# ---------------------------------------------------------------------------------------------- textures

class _TextureError(Exception):
    pass


_cache: "OrderedDict[tuple, tuple[np.ndarray, int] | _TextureError]" = OrderedDict()
_cache_lock = threading.Lock()


def clear_texture_cache() -> None:
    with _cache_lock:
        _cache.clear()


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function, inverse (encoded [0, 1] -> linear)."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


_LINEAR_NAMES = ("linear", "lin_", "scene_linear", "acescg", "aces2065", "raw")


def _read_image(path: str) -> tuple[np.ndarray, int]:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise _TextureError(oiio.geterror() or "OpenImageIO cannot open it")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if pixels is None:
            raise _TextureError(inp.geterror() or "OpenImageIO cannot decode it")
        colorspace = str(spec.get_string_attribute("oiio:ColorSpace", "")).lower()
        integer = spec.format.basetype not in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    finally:
        inp.close()
    px = np.asarray(pixels, np.float32)
    if px.ndim == 4:                    # (depth, H, W, C) for volume images: first slice
        px = px[0]
    if px.ndim == 2:
        px = px[..., None]
    c = px.shape[2]
    rgb = np.repeat(px[..., :1], 3, axis=2) if c < 3 else px[..., :3]
    if integer and not any(colorspace.startswith(n) or n in colorspace for n in _LINEAR_NAMES):
        rgb = _srgb_decode(np.clip(rgb, 0.0, 1.0)).astype(np.float32)
    rgb = np.ascontiguousarray(rgb, np.float32)
    bad = ~np.isfinite(rgb) | (rgb < 0)
    nbad = int(bad.any(axis=2).sum())
    if nbad:
        rgb = np.where(bad, np.float32(0.0), rgb)
    rgb.setflags(write=False)
    return rgb, nbad


def load_texture(path: str) -> np.ndarray:
    """``(H, W, 3) float32`` linear RGB of an image file, read once and cached (read-only array).

    NaN, infinite and negative values are replaced by 0. Raises ``OSError`` when the file is missing or
    cannot be decoded (the failure is cached too, until the file changes).
    """
    return _load(path)[0]


def _load(path: str) -> tuple[np.ndarray, int]:
    try:
        st = os.stat(path)
    except OSError as e:
        raise OSError(f"cannot read it ({e.strerror or e})") from None
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
    if hit is None:
        try:
            hit = _read_image(path)
        except _TextureError as e:
            hit = e
        except Exception as e:  # OpenImageIO raises various errors on corrupt files
            hit = _TextureError(str(e))
        with _cache_lock:
            _cache[key] = hit
            while len(_cache) > TEXTURE_CACHE_SIZE:
                _cache.popitem(last=False)
    if isinstance(hit, _TextureError):
        raise OSError(" ".join(str(hit).split()) or "unreadable")
    return hit


# ------------------------------------------------------------------------------------------------- read

def _rotation(m: np.ndarray, path: str) -> np.ndarray:
    """Nearest orthogonal matrix (polar decomposition) of the upper 3×3 of a column-convention 4×4."""
    a = np.asarray(m, np.float64)[:3, :3]
    if not np.isfinite(a).all():
        raise UsdmlError(f"{path}: non-finite (NaN/inf) transform; fix its xformOps")
    u, s, vt = np.linalg.svd(a)
    if s[-1] <= 1e-12 * max(s[0], 1e-300):
        raise UsdmlError(f"{path}: degenerate transform (zero scale); a dome needs an invertible rotation")
    return u @ vt


def _resolve_pole(prim: Usd.Prim, time: Usd.TimeCode) -> str:
    if prim.GetTypeName() != "DomeLight_1":
        return "Y"
    pole = str(attribute_value(prim, "poleAxis", time, "scene"))
    if pole == "scene":
        return "Z" if UsdGeom.GetStageUpAxis(prim.GetStage()) == UsdGeom.Tokens.z else "Y"
    return "Z" if pole == "Z" else "Y"


def read_dome(prim: Usd.Prim, time: Usd.TimeCode, to_world4x4: np.ndarray,
              warn: Callable[[str], None]) -> Dome | None:
    """The dome light ``prim`` at ``time``; None for prims that are not dome lights.

    ``to_world4x4`` is the prim's local-to-world ``(4, 4)`` matrix in the column convention
    (``p_world = M @ [p, 1]``). Invalid values (NaN, infinities, a negative colour) raise
    :class:`UsdmlError` like :func:`usdml.stage.lights.read_light`; texture problems only warn. A negative
    intensity gives a negative ``radiance``: a dome that takes light away.
    """
    if not is_dome(prim):
        return None
    path = str(prim.GetPath())

    radiance = emitted_radiance(prim, time)
    # inputs:normalize: no effect on dome lights (UsdLux), deliberately not read.

    m = np.asarray(to_world4x4, np.float64)
    pole = _resolve_pole(prim, time)
    to_world = _rotation(m, path) @ dome_pole_rotation(pole)
    shadow = bool(attribute_value(prim, "inputs:shadow:enable", time, True))
    dome = Dome(path=path, radiance=np.asarray(radiance, np.float64).reshape(3), texture=None,
                to_world=to_world, origin=m[:3, 3].copy(), shadow=shadow, pole_axis=pole)

    asset = attribute_value(prim, "inputs:texture:file", time, None)
    authored = asset.path if isinstance(asset, Sdf.AssetPath) else (str(asset) if asset else "")
    if not authored:
        return dome
    resolved = asset.resolvedPath if isinstance(asset, Sdf.AssetPath) else ""
    if not resolved and os.path.isabs(authored):
        resolved = authored
    if not resolved:
        warn(f"{path}.inputs:texture:file: '{authored}' cannot be found (the asset resolver finds no such "
             "file); using a constant dome of the light's color")
        return dome
    try:
        image, nbad = _load(resolved)
    except OSError as e:
        warn(f"{path}.inputs:texture:file: '{resolved}': {e}; using a constant dome of the light's color")
        return dome

    fmt = str(attribute_value(prim, "inputs:texture:format", time, "automatic"))
    h, w = image.shape[:2]
    if fmt not in SUPPORTED_FORMATS or (fmt == "automatic" and w != 2 * h):
        why = (f"format '{fmt}' is not supported yet" if fmt != "automatic"
               else f"format 'automatic' on a {w}×{h} image (not 2:1, so not a lat-long map) is not supported")
        mean = image.reshape(-1, 3).astype(np.float64).mean(0)
        warn(f"{path}.inputs:texture: {why}; using a constant dome of the map's mean color "
             f"({mean[0]:.4g}, {mean[1]:.4g}, {mean[2]:.4g}); use a lat-long (2:1) map")
        dome.radiance = dome.radiance * np.maximum(mean, 0.0)
        return dome
    if fmt == "latlong" and w != 2 * h:
        warn(f"{path}.inputs:texture:file: lat-long map of {w}×{h} is not 2:1; sampled as lat-long anyway")

    if nbad:
        warn(f"{path}.inputs:texture:file: '{resolved}' has {nbad} texel(s) with NaN, infinite or "
             "negative values; they emit nothing")
    dome.texture = image
    dome.texture_file = resolved
    return dome
