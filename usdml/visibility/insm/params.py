"""The insm method (paper 001)'s rows of the parameter table (:mod:`usdml.params`): its settings, declared with the method
and joined to the table through the backend registry (``usdml.visibility.registry``). A leaf module: it imports only :mod:`usdml.param`, so the table is built without
importing the backend."""

from __future__ import annotations

from usdml.param import VIS, Param, Range

#: when the shadow maps are made
INSM = (("visibility", ("insm",)),)

#: the insm backend's settings
PARAMS = (
    Param("insm_count", int, 10, "depth images (intermediate shadow maps) per frame, from viewpoints on the "
          "scene's box", **VIS, range=Range(1, 26), metavar="K", applies=INSM, source="paper 001, Table 4",
          doc="""Depth images (intermediate shadow maps) per frame, insm backend.

    10 are the paper's: the midpoints of the box's eight non-vertical
    edges and the centres of its left and right faces; other counts
    take a prefix of one fixed order of 26 (docs/insm.md)."""),
    Param("insm_resolution", int, 128, "pixels per side of each depth image", **VIS, range=Range(8, 4096),
          metavar="W", applies=INSM, source="paper 001, Table 2"),
    Param("insm_light_resolution", int, 512, "texels per side of each view of a light's shadow map (six views for "
          "a point light)", **VIS, range=Range(16, 8192), metavar="S", applies=INSM, source="paper 001, Table 3"),
    Param("insm_threshold", float, 2.0, "depth-discontinuity threshold of the triangulation, in pixel footprints "
          "of the depth image", **VIS, range=Range(0, low_open=True), metavar="PIXELS", applies=INSM,
          source="paper 001, Alg. 2 (scene-dependent there; measured: docs/insm.md)"),
    Param("insm_cpu_kernel", str, "auto", "how the per-light maps run on a CPU: auto (the compiled maps when they "
          "were built, else Warp), native (the compiled maps; an error without them) or warp", **VIS,
          choices=("auto", "native", "warp"), applies=INSM, source="measured (usdml): docs/insm.md"),
)
