"""UsdSkel: posed points of skinned meshes (blend shapes, then linear/dual-quaternion skinning)."""

from __future__ import annotations

from typing import Callable

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel, Vt


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
                self.cache.Populate(root, Usd.TraverseInstanceProxies())
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

    def is_animated(self, prim: Usd.Prim) -> bool:
        q = self.query(prim)
        if q is None:
            return False
        sq, skq, skel_prim = q
        anim = skq.GetAnimQuery()
        return bool(
            (anim and (anim.JointTransformsMightBeTimeVarying() or anim.BlendShapeWeightsMightBeTimeVarying()))
            or UsdGeom.Mesh(prim).GetPointsAttr().ValueMightBeTimeVarying()
            or UsdGeom.Xformable(skel_prim).TransformMightBeTimeVarying())

    def posed_world_points(self, prim: Usd.Prim, time: Usd.TimeCode, xf: UsdGeom.XformCache) -> np.ndarray | None:
        """``(V, 3)`` float64 posed points in world space, None when the mesh is not skinned."""
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
                return self._rest_world(prim, points, xf)
            # skinned points are in skeleton space
            to_world = np.array(xf.GetLocalToWorldTransform(skel_prim), np.float64)
        else:
            return self._rest_world(prim, points, xf)
        pts = np.asarray(points, np.float64)
        return pts @ to_world[:3, :3] + to_world[3, :3]

    @staticmethod
    def _rest_world(prim: Usd.Prim, points, xf: UsdGeom.XformCache) -> np.ndarray:
        m = np.array(xf.GetLocalToWorldTransform(prim), np.float64)
        pts = np.asarray(points, np.float64)
        return pts @ m[:3, :3] + m[3, :3]
