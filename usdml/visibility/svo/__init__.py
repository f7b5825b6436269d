"""The svo method (paper 003): a sparse voxel octree and its restart traversal, for shadow rays and for
``--gi svo``'s interleaved VPL rays. docs/svo.md; kernels in ``kernels/svo/``.

``backend`` (the ``svo`` visibility backend), ``tree`` (building and caching a tree), ``native`` (the
compiled traversal, ``kernels/svo/svoq.c``). :class:`SvoBackend` is imported on first use.
"""

from usdml.visibility.registry import lazy_attributes

__getattr__ = lazy_attributes(__name__, {"SvoBackend": "usdml.visibility.svo.backend"})
