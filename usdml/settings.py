"""usdml's one settings object, with the papers' defaults.

Fed, in increasing priority, from these defaults, the stage's ``UsdmlRenderSettingsAPI`` attributes
on its RenderSettings prim, and command-line flags. Its fields, defaults and validation follow from
the parameter table, :data:`usdml.params.PARAMS` (one row per field: see there what each means).
"""

from __future__ import annotations

from dataclasses import field, fields, make_dataclass, replace

from usdml.params import MAX_PIXEL_SAMPLES, PARAMS, check

#: schema attribute name -> settings field
SCHEMA_ATTRIBUTES: dict[str, str] = {p.attribute: p.field for p in PARAMS.values()}

VISIBILITY_BACKENDS = PARAMS["visibility"].choices
GI_METHODS = PARAMS["gi"].choices
VOXEL_REBUILDS = PARAMS["voxel_rebuild"].choices
VOXEL_MAPPINGS = PARAMS["voxel_mapping"].choices
SHADOW_TARGETS = PARAMS["shadow_targets"].choices


def _post_init(self) -> None:
    for name in PARAMS:
        check(name, getattr(self, name))


def _updated(self, **values):
    """A copy with the given non-None values replaced."""
    return replace(self, **{k: v for k, v in values.items() if v is not None})


def _as_dict(self) -> dict:
    return {f.name: getattr(self, f.name) for f in fields(self)}


UsdmlSettings = make_dataclass(
    "UsdmlSettings", [(p.field, p.type, field(default=p.default)) for p in PARAMS.values()], frozen=True,
    namespace={"__module__": __name__, "__post_init__": _post_init, "updated": _updated, "as_dict": _as_dict,
               "__doc__": "usdml's settings (frozen); fields as :data:`usdml.params.PARAMS`:\n\n"
                          + "\n".join(f"- ``{p.field}`` = {p.default!r}: {p.help}" for p in PARAMS.values())})

__all__ = ["GI_METHODS", "MAX_PIXEL_SAMPLES", "SCHEMA_ATTRIBUTES", "SHADOW_TARGETS", "UsdmlSettings",
           "VISIBILITY_BACKENDS", "VOXEL_MAPPINGS", "VOXEL_REBUILDS"]
