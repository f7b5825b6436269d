"""Read UsdLux light and shadow linking and usdml's light groups into a snapshot's :class:`LinkSets`.

Membership is USD's own: ``UsdCollectionAPI.ComputeMembershipQuery`` (includeRoot, includes, excludes, the
expansion rule, membership expressions) asked for the path of each piece of geometry, as Hydra asks it:

* a mesh: its path (the query includes a path when it or an ancestor is included and not excluded);
* a native instance's mesh: its instance proxy path (the instance prim's path and the mesh's path below the
  prototype), so an instance is in a collection by its own path or an ancestor's;
* a PointInstancer's mesh: its prototype mesh's path when the prototype sits below the PointInstancer (the usual
  layout), else the PointInstancer's path.

A collection that includes every piece of geometry of the frame is "every prim" (-1): the frame renders as if it
were not authored. The labels (:class:`usdml.scene.linking.LightLabel`) also carry ``usdml:lightGroup`` (a string
on the light prim, declared for usdview by ``UsdmlLightGroupAPI``) and ``inputs:diffuse`` / ``inputs:specular``.
"""

from __future__ import annotations

import re
from typing import Callable

import numpy as np
from pxr import Sdf, Usd

from usdml.scene import Snapshot
from usdml.scene.linking import EVERY_PRIM, LightLabel, LinkSets
from usdml.stage.lights import attribute_value, lobe_scale

__all__ = ["GROUP_ATTRIBUTE", "LinkReader", "group_name", "instance_path"]

#: the light-group attribute
GROUP_ATTRIBUTE = "usdml:lightGroup"
_VALID_GROUP = re.compile(r"[A-Za-z0-9_]+\Z")


def group_name(value, where: str, warn: Callable[[str], None]) -> str:
    """A light group's AOV-safe name (``lightgroup:NAME``): letters, digits and ``_``; others become ``_``, said."""
    name = str(value or "").strip()
    if not name or _VALID_GROUP.match(name):
        return name
    fixed = re.sub(r"[^A-Za-z0-9_]", "_", name)
    warn(f"{where}.{GROUP_ATTRIBUTE}: {name!r} is not a valid AOV name (letters, digits, _); "
         f"its light goes in lightgroup:{fixed}")
    return fixed


class LinkReader:
    """Reads the link collections and labels of a stage's lights, once per light path and collection; the geometry
    membership is asked again each frame (the geometry may change), cached by path."""

    def __init__(self, stage: Usd.Stage, warn: Callable[[str], None]):
        """``warn``: the delegate's :class:`usdml.errors.Warnings`, which says each distinct message once."""
        self.stage = stage
        self.warn = warn
        self._queries: dict[tuple[str, str], Usd.UsdCollectionMembershipQuery | None] = {}
        self._included: dict[tuple[str, str, str], bool] = {}

    def links(self, snap: Snapshot, light_paths: list[str], time: Usd.TimeCode) -> LinkSets:
        """The :class:`LinkSets` of ``snap``'s geometry for the lights at ``light_paths`` (the snapshot's and its
        domes'), at ``time``. The geometry's paths are listed only when some light authors a collection."""
        geometry: list[str] | None = None
        sets: dict[bytes, int] = {}
        names: list[str] = []
        rows: list[np.ndarray] = []
        labels: dict[str, LightLabel] = {}
        for path in dict.fromkeys(light_paths):
            prim = self.stage.GetPrimAtPath(path)
            if not prim:
                continue
            link = []
            for which in ("lightLink", "shadowLink"):
                query = self._query(prim, which)
                if query is not None and geometry is None:
                    geometry = _geometry_paths(snap)
                member = None if query is None else self._membership(path, which, query, geometry)
                if member is None or member.all():
                    link.append(EVERY_PRIM)
                    continue
                key = member.tobytes()
                if key not in sets:
                    sets[key] = len(names)
                    names.append(f"{path}.collection:{which}")
                    rows.append(member)
                link.append(sets[key])
            group = group_name(attribute_value(prim, GROUP_ATTRIBUTE, time, ""), path, self.warn)
            m, diffuse, specular = lobe_scale(prim, time)
            label = LightLabel(link[0], link[1], group, diffuse, specular, m if m > 0 else 1.0)
            if label != LightLabel():
                labels[path] = label
        return _sets(snap, geometry, names, rows, labels) if names else LinkSets(labels=labels)

    def _query(self, prim: Usd.Prim, which: str):
        key = (str(prim.GetPath()), which)
        if key not in self._queries:
            api = Usd.CollectionAPI(prim, which)
            query = None
            if api and _authored(api):
                for rel in (api.GetIncludesRel(), api.GetExcludesRel()):
                    for target in rel.GetTargets():
                        if not self.stage.GetPrimAtPath(target) and not self.stage.GetPropertyAtPath(target):
                            self.warn(f"{rel.GetPath()}: {target} does not exist; the collection ignores it")
                query = api.ComputeMembershipQuery()
            self._queries[key] = query
        return self._queries[key]

    def _membership(self, light: str, which: str, query, geometry: list[str]) -> np.ndarray:
        """``(G,) bool``: whether light ``light``'s collection ``which`` (its membership ``query``) includes each
        geometry path."""
        out = np.empty(len(geometry), bool)
        for i, path in enumerate(geometry):
            key = (light, which, path)
            hit = self._included.get(key)
            if hit is None:
                hit = self._included[key] = bool(query.IsPathIncluded(Sdf.Path(path)))
            out[i] = hit
        return out


def _authored(api: Usd.CollectionAPI) -> bool:
    """Whether a collection says anything but UsdLux's default (every prim)."""
    expression = api.GetMembershipExpressionAttr()
    return (bool(api.GetIncludesRel().GetTargets()) or bool(api.GetExcludesRel().GetTargets())
            or api.GetIncludeRootAttr().HasAuthoredValue() or api.GetExpansionRuleAttr().HasAuthoredValue()
            or bool(expression and expression.HasAuthoredValue()))


def instance_path(proto, mesh_path: str, instancer: str) -> str:
    """The path a prototype mesh's instance is asked by (module doc)."""
    root = proto.path.split("[", 1)[0]
    if proto.kind == "native" and mesh_path.startswith(root):
        return instancer + mesh_path[len(root):]
    if proto.kind == "pointInstancer" and not mesh_path.startswith(instancer + "/"):
        return instancer
    return mesh_path


def _geometry_paths(snap: Snapshot) -> list[str]:
    """Every piece of geometry's path: the meshes, then each prototype mesh's instances (the order
    :func:`_sets` reads them back in)."""
    paths = [m.path for m in snap.meshes]
    for p in snap.prototypes:
        for m in p.meshes:
            paths.extend(instance_path(p, m.path, s) for s in p.instancers)
    return paths


def _sets(snap: Snapshot, geometry: list[str], names: list[str], rows: list[np.ndarray],
          labels: dict[str, LightLabel]) -> LinkSets:
    member = np.array(rows, bool).reshape(len(rows), len(geometry))
    meshes = np.ones((len(rows), len(snap.mesh_paths)), bool)
    k = len(snap.meshes)
    for i, m in enumerate(snap.meshes):
        meshes[:, m.id] = member[:, i]
    instanced: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for p in snap.prototypes:
        n = p.instance_count
        order = np.argsort(p.instance_ids, kind="stable")
        for m in p.meshes:
            part = member[:, k:k + n]
            k += n
            if m.id in instanced:       # the same mesh in another prototype part: append its instances
                ids, old = instanced[m.id]
                ids = np.concatenate([ids, p.instance_ids[order]])
                rest = np.concatenate([old, part[:, order]], axis=1)
                again = np.argsort(ids, kind="stable")
                instanced[m.id] = (ids[again], rest[:, again])
            else:
                instanced[m.id] = (p.instance_ids[order], part[:, order])
    return LinkSets(names, meshes, instanced, labels)

