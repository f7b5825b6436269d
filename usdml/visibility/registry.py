"""The visibility backends usdml knows, by name: a backend is one module plus one line here.

A leaf module (nothing of usdml but :mod:`usdml.errors` is imported), so the parameter table, the
command line and the schema can list the names without importing Embree or Warp. Each entry is
``"module:Class"``; the module is imported the first time the backend is asked for.
"""

from __future__ import annotations

import importlib

from usdml.errors import UsdmlError

#: name -> "module:Class" of its :class:`usdml.visibility.base.VisibilityBackend`; ``exact`` is the reference
BACKENDS: dict[str, str] = {
    "exact": "usdml.visibility.exact:ExactBackend",
    "voxel": "usdml.visibility.voxel:VoxelBackend",
    "svo": "usdml.visibility.svo:SvoBackend",
    "insm": "usdml.visibility.insm:InsmBackend",
}


def backend_names() -> tuple[str, ...]:
    """Every registered backend name, in registry order (``exact`` first)."""
    return tuple(BACKENDS)


def backend_class(name: str):
    """The class registered as ``name``; ``UsdmlError`` naming the choices when there is none."""
    where = BACKENDS.get(name)
    if where is None:
        raise UsdmlError(f"unknown visibility backend {name!r}; available: {', '.join(backend_names())}")
    module, _, cls = where.partition(":")
    return getattr(importlib.import_module(module), cls)
