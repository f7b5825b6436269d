"""What each piece of a snapshot's geometry is called, for Cryptomatte's mattes (:mod:`usdml.aov.cryptomatte`).

Filled by :class:`usdml.stage.mattes.MatteReader` from the stage (the naming rules are documented there and in
``docs/cryptomatte.md``); plain NumPy and strings, so a frame maps its hits to names without reading USD per pixel.
Three tables of names (objects, assets, materials) and indices into them, -1 where there is none:

* a mesh of ``Snapshot.meshes``: its object and asset;
* a prototype's mesh k for its instance i: ``proto_object[p][k, i]`` and ``proto_asset[p][k, i]``;
* every triangle of a mesh (by ``Mesh.id``): the material bound to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MatteNames"]


@dataclass(eq=False)
class MatteNames:
    objects: list[str]                  #: prim paths of the geometry (instance proxy paths for native instances)
    assets: list[str]                   #: paths of the asset roots (kind component)
    materials: list[str]                #: bound material paths
    mesh_object: np.ndarray             #: (M,) int32 per mesh of ``Snapshot.meshes``: index into ``objects``
    mesh_asset: np.ndarray              #: (M,) int32 index into ``assets``, -1: in no asset
    proto_object: list[np.ndarray]      #: per prototype (meshes, instances) int32 index into ``objects``
    proto_asset: list[np.ndarray]       #: per prototype (meshes, instances) int32 index into ``assets``, -1: none
    triangle_material: dict[int, np.ndarray]    #: ``Mesh.id`` -> (T,) int32 index into ``materials``, -1: none

    def of_sources(self, mesh: np.ndarray, prototype: np.ndarray, instance: np.ndarray,
                   proto_mesh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(object, asset)`` (S,) int32 indices of geometry sources given as ``(S,)`` int arrays: the index in
        ``Snapshot.meshes`` (-1 for an instance), else the prototype, the instance and the prototype's mesh (the
        columns of :class:`usdml.visibility.exact.SourceTable`)."""
        obj = np.full(len(mesh), -1, np.int32)
        asset = np.full(len(mesh), -1, np.int32)
        plain = mesh >= 0
        obj[plain] = self.mesh_object[mesh[plain]]
        asset[plain] = self.mesh_asset[mesh[plain]]
        for p in np.unique(prototype[~plain]):
            rows = np.flatnonzero(~plain & (prototype == p))
            obj[rows] = self.proto_object[p][proto_mesh[rows], instance[rows]]
            asset[rows] = self.proto_asset[p][proto_mesh[rows], instance[rows]]
        return obj, asset
