"""usdml's codeless USD schemas (installed as ``usdml.schemas``).

The folder holds a USD plugin with no compiled code: ``schema.usda`` (the source),
``generatedSchema.usda`` and ``plugInfo.json`` (both written from it by ``tools/gen_schema.py``).
It defines one applied API schema, ``UsdmlRenderSettingsAPI``, for RenderSettings prims.

In Python, :func:`register` makes USD load the plugin (``import usdml`` calls it). Any other USD
tool (usdview, usdcat, usdchecker, a DCC) gets the schema from the plugin search path::

    export PXR_PLUGINPATH_NAME=$(python -c "import usdml.schemas as s; print(s.PLUGIN_DIR)")${PXR_PLUGINPATH_NAME:+:$PXR_PLUGINPATH_NAME}
    usdview scene.usda

Importing this module does not import ``pxr``.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import NamedTuple

#: The plugin folder: holds plugInfo.json and generatedSchema.usda.
PLUGIN_DIR: Path = Path(__file__).resolve().parent

#: Schema identifier, as used by ``Usd.Prim.ApplyAPI`` and the ``apiSchemas`` metadata. (Its TfType,
#: declared in plugInfo.json, is ``UsdmlUsdmlRenderSettingsAPI``: usdGenSchema's libraryPrefix +
#: prim name, and it must differ from the identifier, which is the type's UsdSchemaBase alias.)
SCHEMA_NAME = "UsdmlRenderSettingsAPI"

#: Prim type the schema may be applied to (``apiSchemaCanOnlyApplyTo``).
APPLIES_TO = ("RenderSettings",)


class Attribute(NamedTuple):
    """One ``UsdmlRenderSettingsAPI`` attribute: USD name, Python type of its value, fallback."""

    name: str
    type: type
    default: object


#: The schema's attributes, all uniform, with the papers' defaults. Kept by hand in step with
#: schema.usda; tests/test_schema.py checks it against the registered prim definition.
ATTRIBUTES: tuple[Attribute, ...] = (
    Attribute("usdml:visibility", str, "exact"),             # token
    Attribute("usdml:voxel:resolution", int, 128),           # paper 000
    Attribute("usdml:voxel:directionStep", float, 2.0),      # degrees, k in paper 000
    Attribute("usdml:voxel:fullyDynamic", bool, False),      # paper 000, Alg. 5
    Attribute("usdml:voxel:rebuild", str, "rotate"),         # token, paper 000 Alg. 5 or Alg. 1
    Attribute("usdml:voxel:mapping", str, "point"),          # token, Alg. 5's voxel mapping
    Attribute("usdml:gi", str, "none"),                      # token
    Attribute("usdml:vpl:bounces", int, 3),                  # paper 004
    Attribute("usdml:vpl:count", int, 100_000),              # paper 004
    Attribute("usdml:lgh:alpha", float, 1.0),                # r_l = alpha h_l, paper 004
    Attribute("usdml:lgh:levels", int, 0),                   # 0 = automatic, paper 004
    Attribute("usdml:lgh:interleave", int, 1),               # paper 004, interleaved sampling
    Attribute("usdml:lgh:startLevel", int, 1),               # 1 = S1 (paper 004), 0 = S0
    Attribute("usdml:shadow:samples", int, 4),               # paper 004
    Attribute("usdml:shadow:filterIterations", int, -1),     # à-trous iterations, -1 = by samples
    Attribute("usdml:shadow:targets", str, "cluster"),       # token: cluster, or jitter (paper 004)
    Attribute("usdml:pixelSamples", int, 4),                 # s x s stratified primary rays, box filter
    Attribute("usdml:seed", int, 0),
)

#: Allowed values of the token attributes.
ALLOWED_TOKENS: dict[str, tuple[str, ...]] = {
    "usdml:visibility": ("exact", "voxel", "insm", "svo"),
    "usdml:gi": ("none", "lgh", "vpl-bruteforce"),
    "usdml:voxel:rebuild": ("rotate", "geometry"),
    "usdml:voxel:mapping": ("point", "conservative"),
    "usdml:shadow:targets": ("cluster", "jitter"),
}

_lock = threading.Lock()
_registered = False


def register() -> bool:
    """Register the plugin with USD, once; return whether ``Usd.SchemaRegistry`` knows the schema.

    Safe to call repeatedly, and a no-op where ``PXR_PLUGINPATH_NAME`` already names
    :data:`PLUGIN_DIR`. Call it before anything builds ``Usd.SchemaRegistry`` (opening a stage
    does): USD reads schema plugins when the registry is first built, and a registry built before
    this call does not see the schema, so this returns False.

    Raises ImportError when ``pxr`` (usd-core) is not installed.
    """
    global _registered
    from pxr import Plug

    with _lock:
        if not _registered:
            Plug.Registry().RegisterPlugins(str(PLUGIN_DIR))
            _registered = True
    return is_registered()


def is_registered() -> bool:
    """Whether ``Usd.SchemaRegistry`` has the ``UsdmlRenderSettingsAPI`` definition."""
    from pxr import Usd

    return Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(SCHEMA_NAME) is not None


__all__ = ["ALLOWED_TOKENS", "APPLIES_TO", "ATTRIBUTES", "Attribute", "PLUGIN_DIR", "SCHEMA_NAME",
           "is_registered", "register"]
