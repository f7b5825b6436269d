"""Visibility backends: one interface ("is the segment P → L blocked?"), several implementations.

``make_backend(name, ...)`` builds one by name; each backend owns its acceleration structures and
updates them per frame from a :class:`usdml.scene.Snapshot`. ``exact`` (Embree) is the reference the
approximate backends are measured against. The names live in :mod:`usdml.visibility.registry`; this
package imports a backend's module only when it is asked for (so listing names costs nothing).
"""

from __future__ import annotations

from usdml.visibility.registry import backend_class, backend_names

__all__ = ["VisibilityBackend", "ExactBackend", "VoxelBackend", "make_backend", "available_backends",
           "backend_for", "backend_class", "backend_names"]

_LAZY = {"VisibilityBackend": "usdml.visibility.base", "ExactBackend": "usdml.visibility.exact",
         "VoxelBackend": "usdml.visibility.voxel"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'usdml.visibility' has no attribute {name!r}")


def available_backends() -> list[str]:
    """Names :func:`make_backend` accepts, sorted."""
    return sorted(backend_names())


def make_backend(name: str, **kw):
    """A new backend ``name`` built with keyword settings ``kw`` (see each backend's class)."""
    return backend_class(name)(**kw)


def backend_for(settings, device: str = "cpu", **kw):
    """The backend ``settings.visibility`` names, configured from ``settings`` (voxel resolution and
    direction step, per-frame rebuild, mapping, fully dynamic) and ``kw`` (e.g. ``report``, ``progress`` for the voxel backend)."""
    if settings.visibility == "voxel":
        return backend_class("voxel")(resolution=settings.voxel_resolution, step=settings.direction_step,
                                      device=device, rebuild=settings.voxel_rebuild, mapping=settings.voxel_mapping,
                                      fully_dynamic=settings.fully_dynamic, **kw)
    return make_backend(settings.visibility)
