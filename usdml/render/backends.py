"""The visibility backends of one :class:`usdml.render.frame.FrameRenderer`, by role, with one lifecycle.

Roles:

* ``primary``: the exact (Embree) backend: primary rays (the G-buffer) and the VPLs' light paths;
* ``shadow``: the configured ``--visibility`` backend, the direct light's shadow rays (``primary`` itself
  when that is ``exact``);
* ``gi``: ``--gi svo``'s (pixel, VPL) rays (:func:`usdml.lighting.interleaved.gi_visibility_backend`,
  ``svo`` unless told otherwise; one of the others when it has that name); None for every other ``--gi``.

Each backend is made once, updated once per frame and closed once, however many roles it holds.

``usdml compare --visibility`` and ``usdml bench`` set their backends up here too, with the roles of
:data:`QUERY_ROLES` (``usdml bench``: one ``Backends`` per backend it times, every one sharing the exact
backend of the first).
"""

from __future__ import annotations

import time as _time

from usdml.scene import Changes, Snapshot
from usdml.scene.cutout import kept_snapshot
from usdml.settings import UsdmlSettings
from usdml.visibility import ExactBackend, make_backend
from usdml.visibility.base import VisibilityBackend

ROLES = ("primary", "shadow", "gi")
#: the roles of a comparison of shadow queries against exact (``usdml compare --visibility``, ``usdml bench``)
QUERY_ROLES = ("primary", "shadow")
#: what ``--error-budget`` does with a shadow backend that does not declare ``REFINE``: a render's warning,
#: nothing (``usdml bench``), or a one-line :class:`usdml.errors.UsdmlError` (``usdml compare``)
UNREFINABLE = ("warn", "ignore", "raise")


class Backends:
    """A renderer's backends by role (module doc): ``primary``, ``shadow``, ``gi`` (None without ``--gi svo``).

    ``options`` (``report``, ``progress``: :mod:`usdml.visibility.base`) go to the shadow backend;
    ``gi_visibility`` names the backend of ``--gi svo``'s rays (default
    :data:`usdml.lighting.interleaved.GI_VISIBILITY`). ``roles``: :data:`ROLES`, or :data:`QUERY_ROLES` for no
    ``gi`` backend; ``primary``: the exact backend of another ``Backends`` (``usdml bench``: one for every
    backend it times), held here but neither updated nor closed; ``unrefinable``: one of :data:`UNREFINABLE`.
    """

    def __init__(self, settings: UsdmlSettings, device: str = "cpu", options: dict | None = None,
                 gi_visibility: str | None = None, *, roles: tuple[str, ...] = ROLES,
                 primary: VisibilityBackend | None = None, unrefinable: str = "warn"):
        if unrefinable not in UNREFINABLE:
            raise ValueError(f"unrefinable={unrefinable!r}: one of {', '.join(UNREFINABLE)}")
        self._shared = primary
        self._kept: dict = {}       # see-through meshes as kept triangles (usdml.scene.cutout), across frames
        self._roles: dict[str, VisibilityBackend | None] = {"primary": ExactBackend() if primary is None else primary}
        self._roles["shadow"] = self._named(settings.visibility) or \
            make_backend(settings.visibility, settings, device, **(options or {}))
        self._roles["gi"] = None
        #: ``--error-budget``: the shadow backend refined by the exact one (usdml.visibility.refine), which then
        #: answers the shadow role; None without a budget
        self.refined = None
        from usdml.render.budget import active

        if active(settings.error_budget, self._roles["shadow"], self._roles["primary"]):
            from usdml.errors import UsdmlError, log
            from usdml.visibility import backend_class, backend_names
            from usdml.visibility.base import REFINE
            from usdml.visibility.refine import Refined

            shadow = self._roles["shadow"]
            if shadow.supports(REFINE):
                self.refined = Refined(shadow, self._roles["primary"])
            elif unrefinable == "raise":
                able = [n for n in backend_names() if n != "exact" and backend_class(n).supports(REFINE)]
                use = f", or use {', '.join(able[:-1])} or {able[-1]}" if len(able) > 1 else ""
                self.close()
                raise UsdmlError(f"--error-budget: the {shadow.name} backend does not say which of its answers are "
                                 f"uncertain; leave --error-budget out{use}")
            elif unrefinable == "warn":
                log.warning(f"--error-budget is ignored: the {shadow.name} backend does not say which of its answers "
                            "are uncertain")
        if "gi" in roles and settings.gi == "svo":
            from usdml.lighting.interleaved import GI_VISIBILITY, gi_visibility_backend

            name = gi_visibility or GI_VISIBILITY
            self._roles["gi"] = self._named(name) or gi_visibility_backend(settings, device, name)

    @property
    def primary(self) -> VisibilityBackend:
        return self._roles["primary"]

    @property
    def shadow(self) -> VisibilityBackend:
        """The direct light's shadow rays: the configured backend, refined under ``--error-budget``."""
        return self.refined or self._roles["shadow"]

    @property
    def configured(self) -> VisibilityBackend:
        """The ``--visibility`` backend itself: :attr:`shadow` without the ``--error-budget`` refinement."""
        return self._roles["shadow"]

    @property
    def gi(self) -> VisibilityBackend | None:
        return self._roles["gi"]

    def _named(self, name: str) -> VisibilityBackend | None:
        """The backend already made under ``name``, the latest role's first (a backend is made once)."""
        return next((b for _, b in reversed(self.owners()) if b.name == name), None)

    def owners(self) -> list[tuple[str, VisibilityBackend]]:
        """``(first role, backend)`` of each distinct backend, in the order they were made."""
        seen: dict[int, tuple[str, VisibilityBackend]] = {}
        for role, backend in self._roles.items():
            if backend is not None and id(backend) not in seen:
                seen[id(backend)] = (role, backend)
        return list(seen.values())

    def update(self, snapshot: Snapshot, changes: Changes) -> dict[str, float]:
        """Each backend brought to ``snapshot`` once, rebuilding what ``changes`` names; returns the seconds
        of each update under the first role its backend holds (a role sharing another's backend has none; a
        shared ``primary`` is updated by its own ``Backends``)."""
        seconds = {}
        kept = None
        for role, backend in self.owners():
            if backend is self._shared:
                continue
            t0 = _time.perf_counter()
            if isinstance(backend, ExactBackend):
                backend.update(snapshot, changes)
            else:       # built from triangles: cutouts and partial opacity as the triangles that stop light
                if kept is None:
                    kept = kept_snapshot(snapshot, self._kept)
                backend.update(kept, changes)
            seconds[role] = _time.perf_counter() - t0
        return seconds

    def close(self) -> None:
        """Release every backend once (a shared ``primary``: its own ``Backends`` does)."""
        for _, backend in self.owners():
            if backend is not self._shared:
                backend.close()
