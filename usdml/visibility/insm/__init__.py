"""The insm method (paper 001): intermediate shadow maps, per-light maps rasterized from a few
triangulated depth images of the scene. docs/insm.md; kernels in ``kernels/insm/``.

``backend`` (the ``insm`` visibility backend), ``mesh`` (the depth images and their triangulation),
``native`` (the compiled maps, ``kernels/insm/insmr.c``). :class:`InsmBackend` is imported on first use.
"""

_EXPORTS = {"InsmBackend": "usdml.visibility.insm.backend"}


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
