"""Name a snapshot's geometry for Cryptomatte (:class:`usdml.scene.mattes.MatteNames`): objects, materials, assets.

The rules (``docs/cryptomatte.md``):

* **CryptoObject**: the prim path of the gprim hit, as Hydra names it and as light linking asks collections
  (:func:`usdml.stage.linking.instance_path`): a mesh, its path; a native instance's mesh, its instance proxy
  path (the instance prim's path and the mesh's path below the prototype: every instance its own matte); a
  PointInstancer's mesh, its prototype mesh's path (every instance of a prototype shares the matte, as they share
  Hydra's scene path: a scatter of 10⁶ instances does not put 10⁶ names in every file; ``instanceId`` tells them
  apart).
* **CryptoMaterial**: the path of the material bound to the face hit (``materialBind`` GeomSubsets included), as
  the renderer resolves it (:meth:`usdml.stage.materials.MaterialResolver.face_bindings`), whether or not usdml
  can render that material; a face with no material has no id. A native instance's faces take the binding inside
  its prototype (instances share it: Karma's behaviour too).
* **CryptoAsset**: the nearest prim at or above the object (through instance proxies) whose ``kind`` is
  ``component`` or derived from it: the unit a pipeline publishes as an asset. Geometry in no component has no id.

Paths inside a native prototype (``/__Prototype_N/...``, whose numbering changes between processes) are named
through the prototype's first instance by path, the same in every process and on every farm worker. An instance
nested in another instance's prototype is named so too: the snapshot keeps the outer prototype as its instancer, not
the nested instance's proxy path, so every nested instance shares the path through the first outer and inner
instances (``/World/Chair_0/leg/geo``).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from pxr import Kind, Usd

from usdml.scene import Snapshot, content_hash
from usdml.scene.mattes import MatteNames
from usdml.stage.linking import instance_path

__all__ = ["MatteReader"]


class _Table:
    """Names in first-seen order and their indices."""

    def __init__(self):
        self.names: list[str] = []
        self.index: dict[str, int] = {}

    def add(self, name: str | None) -> int:
        if name is None:
            return -1
        i = self.index.get(name)
        if i is None:
            i = self.index[name] = len(self.names)
            self.names.append(name)
        return i


class MatteReader:
    """Reads the names of a stage's geometry, caching what does not change between frames (asset roots by path,
    a mesh's face bindings by its faces)."""

    def __init__(self, stage: Usd.Stage, materials, warn: Callable[[str], None]):
        """``materials``: the delegate's :class:`usdml.stage.materials.MaterialResolver`."""
        self.stage = stage
        self.materials = materials
        self.warn = warn
        self._asset: dict[str, str | None] = {}
        self._first: dict[str, str] = {}
        self._bindings: dict[tuple[str, str], list[tuple[np.ndarray | None, str | None]]] = {}

    def names(self, snap: Snapshot) -> MatteNames:
        objects, assets, materials = _Table(), _Table(), _Table()

        def named(path: str) -> tuple[int, int]:
            path = self.stable(path)
            return objects.add(path), assets.add(self.asset(path))

        mesh_object, mesh_asset = np.array([named(m.path) for m in snap.meshes], np.int32).reshape(-1, 2).T
        proto_object, proto_asset = [], []
        for p in snap.prototypes:
            obj = np.empty((len(p.meshes), p.instance_count), np.int32)
            asset = np.empty_like(obj)
            for k, m in enumerate(p.meshes):
                by_instancer = {s: named(m.path if s.startswith("/__Prototype_") else instance_path(p, m.path, s))
                                for s in dict.fromkeys(p.instancers)}
                pairs = np.array([by_instancer[s] for s in p.instancers], np.int32).reshape(-1, 2)
                obj[k], asset[k] = pairs[:, 0], pairs[:, 1]
            proto_object.append(obj)
            proto_asset.append(asset)
        triangle_material = {}
        time = Usd.TimeCode(snap.time)
        for m in snap.meshes + [m for p in snap.prototypes for m in p.meshes]:
            if m.id in triangle_material:
                continue
            index = np.full(m.triangle_count, -1, np.int32)
            for mask, path in self.bindings(m.path, m.face_index, time):
                index[slice(None) if mask is None else mask] = materials.add(
                    None if path is None else self.stable(path))
            triangle_material[m.id] = index
        return MatteNames(objects.names, assets.names, materials.names, mesh_object, mesh_asset, proto_object,
                          proto_asset, triangle_material)

    def bindings(self, path: str, face: np.ndarray, time: Usd.TimeCode):
        """The material bindings of the gprim at ``path`` per triangle (``face`` (T,): each triangle's authored
        face), read once per gprim and faces."""
        key = (path, content_hash(face))
        if key not in self._bindings:
            self._bindings[key] = self.materials.face_bindings(self.stage.GetPrimAtPath(path), time, face)
        return self._bindings[key]

    def stable(self, path: str) -> str:
        """``path`` with a native prototype's root (``/__Prototype_N``) replaced by its first instance's path (by
        path order, itself made stable: instances nest; instances under a class skipped), so names do not depend on
        USD's prototype numbering."""
        if not path.startswith("/__Prototype_"):
            return path
        root, _, rest = path[1:].partition("/")
        root = "/" + root
        if root not in self._first:
            proto = self.stage.GetPrimAtPath(root)
            # instances under a class (abstract: not rendered) do not name it; nested ones sort by their stable path
            instances = [self.stable(str(i.GetPath())) for i in (proto.GetInstances() if proto else [])
                         if not i.IsAbstract()]
            self._first[root] = min(instances, default=root)
        return self._first[root] + ("/" + rest if rest else "")

    def asset(self, path: str) -> str | None:
        """The nearest prim at or above ``path`` whose kind is a component (instance proxies walked), or None."""
        if path in self._asset:
            return self._asset[path]
        prim = self.stage.GetPrimAtPath(path)
        found = None
        if prim and not prim.IsPseudoRoot():
            kind = Usd.ModelAPI(prim).GetKind()
            if kind and Kind.Registry.IsA(kind, Kind.Tokens.component):
                found = path
            else:
                parent = str(prim.GetPath().GetParentPath())
                found = self.asset(parent) if parent != "/" else None
        self._asset[path] = found
        return found
