"""Visibility backends: one interface ("is the segment P → L blocked?"), several implementations.

``make_backend(name, **kw)`` builds one by name; each backend owns its acceleration structures and
updates them per frame from a :class:`usdml.scene.Snapshot`. ``exact`` (Embree) is the reference the
approximate backends are measured against.
"""

from __future__ import annotations

from usdml.errors import UsdmlError
from usdml.visibility.base import VisibilityBackend
from usdml.visibility.exact import ExactBackend
from usdml.visibility.voxel import VoxelBackend

__all__ = ["VisibilityBackend", "ExactBackend", "VoxelBackend", "make_backend", "available_backends",
           "backend_for"]

#: name -> backend class; approximate backends register here as they land
_BACKENDS: dict[str, type[VisibilityBackend]] = {
    ExactBackend.name: ExactBackend,
    VoxelBackend.name: VoxelBackend,
}


def available_backends() -> list[str]:
    """Names :func:`make_backend` accepts, sorted."""
    return sorted(_BACKENDS)


def make_backend(name: str, **kw) -> VisibilityBackend:
    """A new backend ``name`` built with keyword settings ``kw`` (see each backend's class)."""
    cls = _BACKENDS.get(name)
    if cls is None:
        raise UsdmlError(f"unknown visibility backend {name!r}; available: {', '.join(available_backends())}")
    return cls(**kw)


def backend_for(settings, device: str = "cpu", **kw) -> VisibilityBackend:
    """The backend ``settings.visibility`` names, configured from ``settings`` (voxel resolution and
    direction step, per-frame rebuild, mapping, fully dynamic) and ``kw`` (e.g. ``report``, ``progress`` for the voxel backend)."""
    if settings.visibility == "voxel":
        return VoxelBackend(resolution=settings.voxel_resolution, step=settings.direction_step, device=device,
                            rebuild=settings.voxel_rebuild, mapping=settings.voxel_mapping,
                            fully_dynamic=settings.fully_dynamic, **kw)
    return make_backend(settings.visibility)
