"""Light linking, shadow linking and light groups of a frame, as plain data (read by :mod:`usdml.stage.linking`).

UsdLux gives every light two collections: ``collection:lightLink`` (the prims the light illuminates) and
``collection:shadowLink`` (the prims that cast its shadows). Both include every prim unless authored otherwise, so
a light with neither authored is labelled -1 ("every prim") and costs nothing. :class:`LinkSets` numbers the distinct
authored collections of a snapshot's lights (two collections with the same members are one set) and holds which
geometry each includes:

* a non-instanced mesh by its :attr:`usdml.scene.Mesh.id` (its path, or an ancestor's, in the collection);
* an instance of a prototype mesh by ``(mesh id, instance id)`` (the G-buffer's ``primId`` and ``instanceId``):
  a native instance by its instance proxy path, a PointInstancer's by its prototype mesh's path.

:meth:`LinkSets.label` writes each light's sets, group and lobe factors from its prim path (:attr:`Lights.paths`:
an instanced light carries its prototype light's path, so it takes that light's collections and group).
:meth:`LinkSets.members` answers which points a light set reaches; :meth:`LinkSets.filtered` is the geometry that
casts a shadow set's shadows.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from usdml.scene import Lights, Snapshot

__all__ = ["DEFAULT_GROUP", "EVERY_PRIM", "LightLabel", "LinkSets", "group_of"]

#: a light's link set when its collection includes every prim (UsdLux's default)
EVERY_PRIM = -1
#: the light group of a light that names none (``lightgroup:default``)
DEFAULT_GROUP = "default"


def group_of(group: str) -> str:
    """The light group a light's ``group`` label puts it in: :data:`DEFAULT_GROUP` for none."""
    return group or DEFAULT_GROUP


@dataclass(frozen=True)
class LightLabel:
    """What a light prim says besides its emission: its link sets, group and lobe factors (:class:`Lights`)."""

    light_link: int = EVERY_PRIM
    shadow_link: int = EVERY_PRIM
    group: str = ""
    diffuse: float = 1.0
    specular: float = 1.0
    scale: float = 1.0      #: the factor the stored radiance carries (:attr:`usdml.scene.Lights.scale`)


@dataclass(eq=False)
class LinkSets:
    """The distinct authored link collections of a snapshot's lights and the geometry in each (module doc)."""

    names: list[str] = field(default_factory=list)     #: (C,) the first collection of each set, for messages
    meshes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))   #: (C, M) by mesh id
    #: mesh id of a prototype mesh -> (sorted instance ids (n,), (C, n) bool membership of each instance)
    instanced: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    labels: dict[str, LightLabel] = field(default_factory=dict)    #: light prim path -> its label

    def __len__(self) -> int:
        return len(self.names)

    def label(self, lights: Lights) -> Lights:
        """``lights`` with :attr:`Lights.light_link`, ``shadow_link``, ``group``, ``diffuse``, ``specular``, ``scale`` set
        from their paths (a path without a label keeps the defaults)."""
        if not self.labels or not len(lights):
            return lights
        rows = [self.labels.get(p, LightLabel()) for p in lights.paths]
        return replace(lights, light_link=np.fromiter((r.light_link for r in rows), np.int32, len(rows)),
                       shadow_link=np.fromiter((r.shadow_link for r in rows), np.int32, len(rows)),
                       group=[r.group for r in rows],
                       diffuse=np.fromiter((r.diffuse for r in rows), np.float32, len(rows)),
                       specular=np.fromiter((r.specular for r in rows), np.float32, len(rows)),
                       scale=np.fromiter((r.scale for r in rows), np.float32, len(rows)))

    def members(self, link: int, prim_id: np.ndarray, instance_id: np.ndarray) -> np.ndarray:
        """``(P,) bool``: the hit points (``prim_id``, ``instance_id`` of each, as the G-buffer's) that set
        ``link`` includes; every point for :data:`EVERY_PRIM`."""
        prim_id = np.asarray(prim_id, np.int64)
        if link == EVERY_PRIM:
            return np.ones(len(prim_id), bool)
        row = self.meshes[link]
        inside = (prim_id >= 0) & (prim_id < len(row))
        out = np.zeros(len(prim_id), bool)
        out[inside] = row[prim_id[inside]]
        instance_id = np.asarray(instance_id, np.int64)
        for mesh_id in self.instanced:
            sel = np.flatnonzero(prim_id == mesh_id)
            if len(sel):
                out[sel] = self._instance_mask(link, mesh_id, instance_id[sel])
        return out

    def filtered(self, snap: Snapshot, link: int) -> Snapshot:
        """``snap`` with only the geometry set ``link`` includes (what casts the shadows of a shadow set); a
        prototype's meshes are split by which of its instances are members (one prototype per distinct
        membership), each part keeping its meshes' ids."""
        meshes = [m for m in snap.meshes if self.meshes[link, m.id]]
        prototypes = []
        for p in snap.prototypes:
            parts: dict[bytes, list] = {}
            for m in p.meshes:
                keep = self._instance_mask(link, m.id, p.instance_ids)
                if keep.any():
                    parts.setdefault(keep.tobytes(), [keep, []])[1].append(m)
            for k, (keep, group) in enumerate(parts.values()):
                whole = len(parts) == 1 and keep.all()
                prototypes.append(p if whole else replace(
                    p, path=f"{p.path}{{shadowLink {link}.{k}}}", meshes=group, xforms=p.xforms[keep],
                    instance_ids=p.instance_ids[keep], instancers=[s for s, y in zip(p.instancers, keep) if y]))
        return replace(snap, meshes=meshes, prototypes=prototypes)

    def _instance_mask(self, link: int, mesh_id: int, instance_ids: np.ndarray) -> np.ndarray:
        if mesh_id not in self.instanced:
            return np.full(len(instance_ids), bool(self.meshes[link, mesh_id]))
        ids, member = self.instanced[mesh_id]
        k = np.clip(np.searchsorted(ids, instance_ids), 0, len(ids) - 1)
        return member[link, k] & (ids[k] == instance_ids)
