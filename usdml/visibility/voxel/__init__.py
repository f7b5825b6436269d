"""The voxel method (paper 000): per-direction voxel arrays shared by a prototype's instances, rotated for
deforming meshes, queried in constant time. docs/voxel.md; kernels in ``kernels/voxel/``.

``backend`` (the ``voxel`` visibility backend), ``array`` (building and caching an array), ``grid`` (the
direction bins and the array's rows), ``rotate`` (deforming meshes, Alg. 5), ``budget`` (memory), ``codec``
(the cache's coding of an array), ``native`` (the compiled queries and Alg. 3, ``kernels/voxel/voxelq.c``).
:class:`VoxelBackend` is imported on first use, so the folder's light modules load without it.
"""

from usdml.visibility.registry import lazy_attributes

__getattr__ = lazy_attributes(__name__, {"VoxelBackend": "usdml.visibility.voxel.backend"})
