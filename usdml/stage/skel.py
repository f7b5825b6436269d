"""UsdSkel: posed points of skinned meshes (blend shapes, then linear/dual-quaternion skinning).

Skinned meshes inside native instances are read through their instance proxies (UsdSkel binds
them there: the SkelRoot is often the instance prim itself, and ``skel:animationSource`` may be
authored per instance, as UsdSkel's "bind state" instancing does); :meth:`SkelResolver.binding_key`
says which instances pose alike, so they share one posed prototype.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

#: prims a SkelRoot's bindings are read from: instance proxies included, and prims defined below an
#: ``over`` (PointInstancer prototypes often sit under one), as the scene delegate walks them
_POPULATE = Usd.TraverseInstanceProxies(Usd.PrimIsActive & Usd.PrimIsLoaded & ~Usd.PrimIsAbstract)


class SkelResolver:
    """Skinning queries for meshes under a ``SkelRoot``, populated lazily per SkelRoot."""

    def __init__(self, warn: Callable[[str], None]):
        self.cache = UsdSkel.Cache()
        self._populated: set[str] = set()
        self._queries: dict[str, tuple | None] = {}
        self.warn = warn

    def query(self, prim: Usd.Prim):
        """``(skinning query, skeleton query, skeleton prim)`` or None when ``prim`` is not skinned."""
        key = str(prim.GetPath())
        if key in self._queries:
            return self._queries[key]
        result = None
        root = UsdSkel.Root.Find(prim)
        if root:
            rkey = str(root.GetPrim().GetPath())
            if rkey not in self._populated:
                self.cache.Populate(root, _POPULATE)
                self._populated.add(rkey)
            sq = self.cache.GetSkinningQuery(prim)
            if sq and (sq.HasJointInfluences() or sq.HasBlendShapes()):
                skel = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
                skq = self.cache.GetSkelQuery(skel) if skel else None
                if skq:
                    result = (sq, skq, skel.GetPrim())
                else:
                    self.warn(f"{key}: skinned mesh has no valid skeleton binding; rendered at rest")
        self._queries[key] = result
        return result

    def is_animated(self, prim: Usd.Prim, space: Usd.Prim | None = None) -> bool:
        """Whether the posed points of ``prim`` in ``space``'s frame (world when None) might vary:
        animated joints or blend-shape weights, time-sampled rest points, or a moving skeleton."""
        q = self.query(prim)
        if q is None:
            return False
        sq, skq, skel_prim = q
        anim = skq.GetAnimQuery()
        return bool(
            (anim and (anim.JointTransformsMightBeTimeVarying() or anim.BlendShapeWeightsMightBeTimeVarying()))
            or UsdGeom.Mesh(prim).GetPointsAttr().ValueMightBeTimeVarying()
            or _moves_in(skel_prim, space))

    def binding_key(self, prim: Usd.Prim, space: Usd.Prim, xf: UsdGeom.XformCache) -> tuple | None:
        """What decides the pose of ``prim`` (an instance proxy below the native instance ``space``)
        in ``space``'s frame: its skeleton and animation (paths below ``space`` made relative, so
        every instance of one prototype names its own alike) and, for a skeleton outside the
        instance, where that skeleton sits relative to it. Equal keys pose equal points; None when
        ``prim`` is not skinned."""
        q = self.query(prim)
        if q is None:
            return None
        sq, skq, skel_prim = q
        anim = skq.GetAnimQuery()
        base = space.GetPath()

        def local(path: Sdf.Path) -> str:
            return str(path.MakeRelativePath(base)) if path.HasPrefix(base) else str(path)

        key = (local(skel_prim.GetPath()), local(anim.GetPrim().GetPath()) if anim else "")
        if not skel_prim.GetPath().HasPrefix(base):
            key += (_space_matrix(skel_prim, space, xf).tobytes(),)
        return key

    def posed_points(self, prim: Usd.Prim, time: Usd.TimeCode, xf: UsdGeom.XformCache,
                     space: Usd.Prim | None = None) -> np.ndarray | None:
        """``(V, 3)`` float64 posed points in the frame of ``space`` (world when None), None when the
        mesh is not skinned. ``space`` is the prim a prototype's points are relative to: a native
        instance (``prim`` then one of its instance proxies) or a PointInstancer prototype root."""
        q = self.query(prim)
        if q is None:
            return None
        sq, skq, skel_prim = q
        points = UsdGeom.Mesh(prim).GetPointsAttr().Get(time)
        if points is None:
            return None
        points = Vt.Vec3fArray(points)
        anim = skq.GetAnimQuery()
        path = prim.GetPath()
        if sq.HasBlendShapes() and anim:
            weights = anim.ComputeBlendShapeWeights(time)
            mapper = sq.GetBlendShapeMapper()
            if weights is not None and mapper is not None:
                weights = mapper.Remap(weights) if not mapper.IsNull() else weights
                bsq = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
                sub_weights, shape_idx, sub_idx = bsq.ComputeSubShapeWeights(weights)
                point_idx = bsq.ComputeBlendShapePointIndices()
                offsets = bsq.ComputeSubShapePointOffsets()
                if not bsq.ComputeDeformedPoints(sub_weights, shape_idx, sub_idx, point_idx, offsets, points):
                    self.warn(f"{path}: blend shapes could not be applied")
        if sq.HasJointInfluences():
            xforms = skq.ComputeSkinningTransforms(time)
            if xforms is None:
                self.warn(f"{path}: skinning transforms unavailable at {time.GetValue()}; rendered at rest")
                skinned = False
            elif sq.IsRigidlyDeformed():
                m = sq.ComputeSkinnedTransform(xforms, time)
                skinned = m is not None
                if skinned:
                    pts = np.asarray(points, np.float64)
                    mm = np.array(m, np.float64)
                    points = Vt.Vec3fArray.FromNumpy((pts @ mm[:3, :3] + mm[3, :3]).astype(np.float32))
            else:
                skinned = sq.ComputeSkinnedPoints(xforms, points, time)
            if not skinned:
                self.warn(f"{path}: skinning failed; rendered at rest")
                return _in_space(prim, points, space, xf)
        else:
            return _in_space(prim, points, space, xf)
        return _in_space(skel_prim, points, space, xf)     # skinned points are in skeleton space


def _space_matrix(prim: Usd.Prim, space: Usd.Prim | None, xf: UsdGeom.XformCache) -> np.ndarray:
    """(4, 4) float64 row-convention ``prim``-local to ``space``-local (to world when None)."""
    m = xf.GetLocalToWorldTransform(prim)
    if space is not None:
        m = m * xf.GetLocalToWorldTransform(space).GetInverse()
    return np.array(m, np.float64)


def _in_space(prim: Usd.Prim, points, space: Usd.Prim | None, xf: UsdGeom.XformCache) -> np.ndarray:
    """``(V, 3)`` float64 ``points`` from ``prim``'s frame into ``space``'s (world when None)."""
    m = _space_matrix(prim, space, xf)
    pts = np.asarray(points, np.float64)
    return pts @ m[:3, :3] + m[3, :3]


def _moves_in(prim: Usd.Prim, space: Usd.Prim | None) -> bool:
    """Whether ``prim``'s transform into ``space``'s frame (world when None) might vary: a time-varying
    xform on ``prim`` or an ancestor below ``space``, or, for a prim outside ``space``, on either side."""
    def chain(p: Usd.Prim, stop: Usd.Prim | None) -> tuple[bool, bool]:
        while p and not p.IsPseudoRoot():
            if stop is not None and p == stop:
                return False, True
            x = UsdGeom.Xformable(p)
            if x and x.TransformMightBeTimeVarying():
                return True, False
            p = p.GetParent()
        return False, False

    varies, reached = chain(prim, space)
    return varies or (space is not None and not reached and chain(space, None)[0])
