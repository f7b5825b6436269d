"""The svo method (paper 003): a sparse voxel octree and its restart traversal, for shadow rays and for
``--gi svo``'s interleaved VPL rays. docs/svo.md; kernels in ``kernels/svo/``.

``backend`` (the ``svo`` visibility backend), ``tree`` (building and caching a tree), ``native`` (the
compiled traversal, ``kernels/svo/svoq.c``). :class:`SvoBackend` is imported on first use.
"""

_EXPORTS = {"SvoBackend": "usdml.visibility.svo.backend"}


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
