"""usdml's one settings object, with the papers' defaults, and a render's options.

Fed, in increasing priority, from these defaults, the stage's ``UsdmlRenderSettingsAPI`` attributes
on its RenderSettings prim, and command-line flags. Its fields, defaults and validation follow from
the parameter table, :data:`usdml.params.PARAMS` (one row per field: see there what each means); the
settings a registered backend declares (``usdml.visibility.registry.register(..., params=...)``) are
read as attributes too (their default until :meth:`updated` sets them).
"""

from __future__ import annotations

from dataclasses import field, fields, make_dataclass, replace

from usdml.params import MAX_PIXEL_SAMPLES, OPTIONS, PARAMS, check, table

#: schema attribute name -> settings field
SCHEMA_ATTRIBUTES: dict[str, str] = {p.attribute: p.field for p in PARAMS.values()}

GI_METHODS = PARAMS["gi"].choices
VOXEL_REBUILDS = PARAMS["voxel_rebuild"].choices
VOXEL_MAPPINGS = PARAMS["voxel_mapping"].choices
SHADOW_TARGETS = PARAMS["shadow_targets"].choices

#: the table's own fields (a registered backend's settings live in ``backend_settings``)
_FIELDS = tuple(PARAMS)


def _post_init(self) -> None:
    for name in _FIELDS:
        check(name, getattr(self, name))
    for name, value in self.backend_settings:
        check(name, value)


def _updated(self, **values):
    """A copy with the given non-None values replaced."""
    values = {k: v for k, v in values.items() if v is not None}
    extra = {k: values.pop(k) for k in list(values) if k not in _FIELDS and k in table()}
    if extra:
        values["backend_settings"] = tuple({**dict(self.backend_settings), **extra}.items())
    return replace(self, **values)


def _getattr(self, name: str):
    # only for names that are no field: a registered backend's setting, its default until set
    row = table().get(name) if not name.startswith("_") else None
    if row is None:
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
    return dict(self.backend_settings).get(name, row.default)


def _as_dict(self) -> dict:
    return {**{f: getattr(self, f) for f in _FIELDS}, **dict(self.backend_settings)}


UsdmlSettings = make_dataclass(
    "UsdmlSettings", [(p.field, p.type, field(default=p.default)) for p in PARAMS.values()]
    + [("backend_settings", tuple, field(default=(), repr=False))], frozen=True,
    namespace={"__module__": __name__, "__post_init__": _post_init, "updated": _updated, "as_dict": _as_dict,
               "__getattr__": _getattr,
               "__doc__": "usdml's settings (frozen); fields as :data:`usdml.params.PARAMS`:\n\n"
                          + "\n".join(f"- ``{p.field}`` = {p.default!r}: {p.help}" for p in PARAMS.values())
                          + "\n- ``backend_settings``: (field, value) pairs of registered backends' own settings"})

#: a render's options besides the settings (:data:`usdml.params.OPTIONS`), with their defaults: the base of
#: :class:`usdml.render.sequence.RenderJob`
RenderOptions = make_dataclass(
    "RenderOptions", [(p.field, p.type if p.default is not None else p.type | None, field(default=p.default))
                      for p in OPTIONS.values()], kw_only=True,
    namespace={"__module__": __name__, "__doc__": "A render's options (:data:`usdml.params.OPTIONS`)."})

__all__ = ["GI_METHODS", "MAX_PIXEL_SAMPLES", "RenderOptions", "SCHEMA_ATTRIBUTES", "SHADOW_TARGETS", "UsdmlSettings",
           "VOXEL_MAPPINGS", "VOXEL_REBUILDS"]
