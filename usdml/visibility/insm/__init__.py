"""The insm method (paper 001): intermediate shadow maps, per-light maps rasterized from a few
triangulated depth images of the scene. docs/insm.md; kernels in ``kernels/insm/``.

``backend`` (the ``insm`` visibility backend), ``mesh`` (the depth images and their triangulation),
``native`` (the compiled maps, ``kernels/insm/insmr.c``). :class:`InsmBackend` is imported on first use.
"""

from usdml.visibility.registry import lazy_attributes

__getattr__ = lazy_attributes(__name__, {"InsmBackend": "usdml.visibility.insm.backend"})
