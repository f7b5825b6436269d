"""Visibility backends: one interface ("is the segment P → L blocked?"), several implementations.

``make_backend(name, settings, device, **options)`` builds one by name through its class's
``from_settings`` (the contract and the optional capabilities: :mod:`usdml.visibility.base`); each
backend owns its acceleration structures and updates them per frame from a
:class:`usdml.scene.Snapshot`. ``exact`` (Embree) is the reference the approximate backends are
measured against. The names live in :mod:`usdml.visibility.registry`; this package imports a
backend's module only when it is asked for (so listing names costs nothing).
"""

from __future__ import annotations

from usdml.visibility.registry import backend_class, backend_names, lazy_attributes

__all__ = ["VisibilityBackend", "ExactBackend", "VoxelBackend", "make_backend", "available_backends",
           "backend_class", "backend_names"]

__getattr__ = lazy_attributes(__name__, {"VisibilityBackend": "usdml.visibility.base",
                                         "ExactBackend": "usdml.visibility.exact",
                                         "VoxelBackend": "usdml.visibility.voxel.backend"})


def available_backends() -> list[str]:
    """Names :func:`make_backend` accepts, sorted."""
    return sorted(backend_names())


def make_backend(name: str, settings=None, device: str = "cpu", **options):
    """A new backend ``name`` (``UsdmlError`` naming the choices when there is none), configured from
    ``settings`` (a :class:`usdml.settings.UsdmlSettings`; ``None``: the backend's defaults) on
    ``device``, keyword ``options`` overriding them: ``cls.from_settings(settings, device, **options)``.
    Every backend accepts ``report`` and ``progress`` (:mod:`usdml.visibility.base`)."""
    return backend_class(name).from_settings(settings, device, **options)
