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


#: The schema's attributes, all uniform, with the papers' defaults (:data:`ATTRIBUTES`), and the
#: allowed values of its token attributes (:data:`ALLOWED_TOKENS`): both follow from usdml's
#: parameter table, :data:`usdml.params.PARAMS`, which ``tools/gen_schema.py`` writes schema.usda
#: from; built when first asked for, so that importing this module imports neither usdml nor pxr.
ATTRIBUTES: tuple[Attribute, ...]
ALLOWED_TOKENS: dict[str, tuple[str, ...]]


def __getattr__(name: str):
    if name == "ATTRIBUTES":
        from usdml.params import PARAMS

        return tuple(Attribute(p.attribute, p.type, p.default) for p in PARAMS.values())
    if name == "ALLOWED_TOKENS":
        from usdml.params import PARAMS

        return {p.attribute: tuple(p.choices) for p in PARAMS.values() if p.type is str and p.choices}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
