"""The svo method (paper 003)'s rows of the parameter table (:mod:`usdml.params`): its settings, declared with the method
and joined to the table through the backend registry (``usdml.visibility.registry``). A leaf module: it imports only :mod:`usdml.param`, so the table is built without
importing the backend."""

from __future__ import annotations

from usdml.param import VIS, Param

#: when the octree is read: shadow rays through it, or ``--gi svo``'s rays
SVO = (("visibility", ("svo",)), ("gi", ("svo",)))

#: the svo backend's settings
PARAMS = (
    Param("svo_resolution", int, 0, "voxels per axis of the sparse voxel octree, a power of two; 0 = automatic: "
          "128 for a room (at most 20 m across), else 256", **VIS,
          choices=(0, 16, 32, 64, 128, 256, 512, 1024, 2048), applies=SVO, source="paper 003",
          doc="""Voxels per axis of the sparse voxel octree (svo backend), a power of two from 16 to 2048.

    0 picks the paper's: 128 for a room (a scene at most 20 m across by
    its metersPerUnit, like the paper's Cornell box), 256 for a larger
    scene (its Sponza)."""),
    Param("svo_cpu_kernel", str, "auto", "how SVO queries run on a CPU: auto (the compiled traversal when it was "
          "built, else Warp), native (the compiled traversal; an error without it) or warp", **VIS,
          choices=("auto", "native", "warp"), applies=SVO, source="measured (usdml): docs/svo.md"),
)
