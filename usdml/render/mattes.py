"""A frame's Cryptomatte ids: what each primary ray hit, named (:mod:`usdml.stage.mattes`) and hashed
(:mod:`usdml.aov.cryptomatte`), pass by pass, for the ranking filter of :class:`usdml.render.frame.FrameRenderer`.

Per frame the names are mapped once onto the primary backend's geometry sources (and, for materials, onto every
triangle of every mesh), so a pass looks its ids up with two gathers: ``(H·W)`` reads, no strings.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from usdml.aov.cryptomatte import name_ids
from usdml.scene.mattes import MatteNames

__all__ = ["MatteIds", "FrameMattes"]


class MatteIds:
    """Names' Cryptomatte ids, each hashed once per renderer; a name with no UTF-8 form is said once (``warn``)
    and has no id."""

    def __init__(self, warn: Callable[[str], None]):
        self.warn = warn
        self._ids: dict[str, int] = {}

    def __call__(self, names: list[str]) -> np.ndarray:
        """``(len(names) + 1,) uint32``: the ids, then 0 (what index -1 reads)."""
        new = [n for n in dict.fromkeys(names) if n not in self._ids]
        bad = lambda n: self.warn(f"{n!r}: the name cannot be encoded as UTF-8; it has no Cryptomatte id")  # noqa: E731
        self._ids.update(zip(new, name_ids(new, bad).tolist()))
        return np.array([self._ids[n] for n in names] + [0], np.uint32)


class FrameMattes:
    """The ids of one frame's geometry sources and triangles for the Cryptomatte AOVs ``aovs``."""

    def __init__(self, names: MatteNames, sources, ids: MatteIds):
        """``sources``: the primary (exact) backend's :class:`usdml.visibility.exact.SourceTable` for the frame."""
        self.names = names
        obj, asset = names.of_sources(sources.mesh, sources.prototype, sources.instance, sources.proto_mesh)
        self.object_ids, self.asset_ids, self.material_ids = ids(names.objects), ids(names.assets), ids(names.materials)
        # index -1 (none) reads the trailing 0 of each id table
        self.source = {"CryptoObject": self.object_ids[obj], "CryptoAsset": self.asset_ids[asset]}
        meshes = sorted(names.triangle_material)
        sizes = [len(names.triangle_material[m]) for m in meshes]
        base = np.zeros(max(meshes, default=-1) + 1, np.int64)
        base[meshes] = np.cumsum([0] + sizes[:-1])
        flat = np.concatenate([names.triangle_material[m] for m in meshes]) if meshes else np.zeros(0, np.int32)
        self.triangle_ids = self.material_ids[flat]
        self.source_base = base[np.asarray(sources.prim_id, np.int64)] if len(base) else np.zeros(0, np.int64)

    def pass_ids(self, geom: np.ndarray, triangle: np.ndarray, aov: str) -> np.ndarray:
        """``(H, W) uint32`` ids of one pass's hits (``geom``, ``triangle``: :class:`usdml.render.gbuffer.GBuffer`'s),
        0 where the ray hit nothing named."""
        out = np.zeros(geom.shape, np.uint32)
        hit = geom >= 0
        g = geom[hit]
        if aov == "CryptoMaterial":
            out[hit] = self.triangle_ids[self.source_base[g] + triangle[hit]]
        else:
            out[hit] = self.source[aov][g]
        return out

    def manifest(self, aov: str, present: np.ndarray) -> dict[str, int]:
        """``{name: id}`` of the names whose ids are in ``present`` (the ids a frame wrote)."""
        names, ids = {"CryptoObject": (self.names.objects, self.object_ids),
                      "CryptoMaterial": (self.names.materials, self.material_ids),
                      "CryptoAsset": (self.names.assets, self.asset_ids)}[aov]
        keep = np.isin(ids[:-1], present) & (ids[:-1] != 0)
        return {names[i]: int(ids[i]) for i in np.flatnonzero(keep)}
