"""The visibility backends usdml knows, by name: a backend is a folder (or a module) plus one line here.

A leaf module (nothing of usdml but :mod:`usdml.errors` is imported), so the parameter table, the
command line and the schema can list the names without importing Embree or Warp. Each entry is
``"module:Class"``; the module is imported the first time the backend is asked for. A backend from
elsewhere (a plugin) joins with :func:`register`, any time: every list of names is read from here when
it is needed (:func:`usdml.params.table`), so one registered after ``import usdml`` is accepted.
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

#: name -> the parameter rows (:class:`usdml.param.Param`) a registered backend adds to the table: a tuple of rows,
#: or ``"module:NAME"`` naming one, imported when the table is built (a built-in backend declares its rows in its
#: folder, a leaf module that imports only :mod:`usdml.param`)
PARAMS: dict[str, tuple | str] = {
    "voxel": "usdml.visibility.voxel.params:PARAMS",
    "svo": "usdml.visibility.svo.params:PARAMS",
    "insm": "usdml.visibility.insm.params:PARAMS",
}


def register(name: str, target: str, params: tuple | str = ()) -> None:
    """Register backend ``name`` as ``target`` (``"module:Class"``), with its own settings: ``params``,
    rows of :class:`usdml.param.Param` (group ``usdml.param.VISIBILITY``), or ``"module:NAME"`` naming them,
    that join the table, its flags and :class:`usdml.settings.UsdmlSettings` (read as attributes, their
    defaults until set)."""
    BACKENDS[name] = target
    PARAMS[name] = params if isinstance(params, str) else tuple(params)


def unregister(name: str) -> None:
    """Forget backend ``name`` and its parameter rows (a test's toy backend)."""
    BACKENDS.pop(name, None)
    PARAMS.pop(name, None)


def state() -> tuple:
    """What the table depends on: the names and the rows (compared, so a change is seen however made)."""
    return tuple(BACKENDS), tuple((n, PARAMS.get(n, ())) for n in BACKENDS)


def backend_names() -> tuple[str, ...]:
    """Every registered backend name, in registry order (``exact`` first)."""
    return tuple(BACKENDS)


def backend_params() -> tuple:
    """The parameter rows the registered backends declare, in registry order."""
    return tuple(p for n in BACKENDS for p in _rows(PARAMS.get(n, ())))


def _rows(params: tuple | str) -> tuple:
    """A backend's rows: as given, or the ``"module:NAME"`` they were named by, imported."""
    if not isinstance(params, str):
        return params
    module, _, name = params.partition(":")
    return tuple(getattr(importlib.import_module(module), name))


def lazy_attributes(package: str, where: dict[str, str]):
    """A package's module ``__getattr__`` (PEP 562): each name of ``where`` (name -> module) from its module,
    imported on first use, so the package itself loads without Embree or Warp (``usdml.visibility``, and a
    method's folder, whose ``params.py`` the parameter table reads)."""
    def __getattr__(name: str):
        if name in where:
            return getattr(importlib.import_module(where[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__


def backend_class(name: str):
    """The class registered as ``name``; ``UsdmlError`` naming the choices when there is none."""
    where = BACKENDS.get(name)
    if where is None:
        raise UsdmlError(f"unknown visibility backend {name!r}; available: {', '.join(backend_names())}")
    module, _, cls = where.partition(":")
    return getattr(importlib.import_module(module), cls)
