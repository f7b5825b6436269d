"""A mesh's surfaces as the renderer samples them: every UsdPreviewSurface input per triangle corner, images
sampled again at each hit, and the BRDF rows (``kernels/brdf``) a hit's shading needs.

Filled by :meth:`usdml.stage.materials.MaterialResolver.shading` (plain NumPy: pickles with the snapshot). The
preview surface's parameters become a row as usdImaging's ``previewSurface.glslfx`` does (``evaluateLight``):

* metallic workflow: ``specColor = lerp(1, diffuseColor, metallic)``, ``F0 = lerp(R²·specColor, specColor,
  metallic)``, ``F90 = specColor``, diffuse reflectance ``diffuseColor·(1 − metallic)``;
* specular workflow (``useSpecularWorkflow`` 1): ``F0 = specularColor``, ``F90 = 1``, diffuse ``diffuseColor``;
* ``R = (1 − ior)/(1 + ior)``; clearcoat ``F0 = R²``, ``F90 = 1``; ``α = max(roughness, 0.001)²`` for each lobe
  (Storm's clamp);
* ``occlusion`` scales both lobes of direct light, as Storm's ``evaluateLight`` does.

Triangles with no surface (no material bound, or one usdml cannot read) are Lambertian with their
displayColor: Storm's fallback surface shades displayColor with no specular lobe.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from usdml.kernels.brdf import ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0, EYE, F0, F90, OCCLUSION, WIDTH

__all__ = ["Field", "HitShading", "LAMBERT_ROW", "MeshShading", "lambert_rows"]

#: a row whose BRDF is Lambert's: kd = 1, ks = 0 (F0 = F90 = 0, occlusion 0)
LAMBERT_ROW = np.zeros(WIDTH, np.float32)
LAMBERT_ROW[ALPHA] = LAMBERT_ROW[CLEARCOAT_ALPHA] = 1.0


def lambert_rows(n: int, eye: np.ndarray | None = None) -> np.ndarray:
    """``(n, WIDTH)`` Lambertian rows (``eye`` (n, 3) written in, though Lambert does not read it)."""
    rows = np.tile(LAMBERT_ROW, (n, 1))
    if eye is not None:
        rows[:, EYE:EYE + 3] = eye
    return rows


@dataclass(eq=False)
class Field:
    """One input over a mesh: ``corners`` (C,) when constant, else (T, 3, C) per triangle corner; ``textures``:
    ``(triangles (T,) bool or None for all, TextureLookup, st (T, 3, 2))`` sampled again at hits on those
    triangles (per-corner values alone would blur an image to its vertices)."""

    corners: np.ndarray
    textures: list = field(default_factory=list)

    def at(self, tri: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(K, C) values at hits on triangles ``tri`` (K,) with barycentric weights ``w`` (K, 3, 1)."""
        if self.corners.ndim == 1:
            out = np.broadcast_to(self.corners, (len(tri), len(self.corners))).astype(np.float32)
        else:
            c = self.corners[tri]
            out = (c[:, 0] * w[:, 0] + c[:, 1] * w[:, 1] + c[:, 2] * w[:, 2]).astype(np.float32)
        for mask, lookup, st in self.textures:
            rows = np.arange(len(tri)) if mask is None else np.flatnonzero(mask[tri])
            if len(rows):
                s = st[tri[rows]]
                ww = w[rows]
                out[rows] = lookup.sample(s[:, 0] * ww[:, 0] + s[:, 1] * ww[:, 1] + s[:, 2] * ww[:, 2])
        return out

    def per_corner(self, n_tri: int) -> np.ndarray:
        """(T, 3, C) values at the corners."""
        if self.corners.ndim == 1:
            return np.broadcast_to(self.corners, (n_tri, 3, len(self.corners)))
        return self.corners


@dataclass
class HitShading:
    """A surface at hits: what shading reads."""

    #: (K, 3) effective ρ of kernels/brdf: diffuseColor·(1 − metallic)·occlusion (displayColor where Lambertian)
    reflectance: np.ndarray
    rows: np.ndarray        #: (K, WIDTH) BRDF rows
    emission: np.ndarray    #: (K, 3) emissiveColor
    normal: np.ndarray | None  #: (K, 3) tangent-space normal where a normal map perturbs, else None


@dataclass(eq=False)
class MeshShading:
    """Every preview input of a mesh (:data:`usdml.stage.network.PREVIEW_DEFAULTS`' names) as a :class:`Field`."""

    fields: dict
    n_tri: int                          #: the mesh's triangles
    lambert: np.ndarray | None = None   #: (T,) bool triangles with no surface (displayColor, Lambertian); None: none

    def albedo_corners(self) -> np.ndarray:
        """(T, 3, 3) diffuse reflectance ``diffuseColor·(1 − metallic)`` (specular workflow: diffuseColor) at corners
        (Lambertian triangles: zeros, for the caller's displayColor)."""
        n = self.n_tri
        d = self.fields["diffuseColor"].per_corner(n).reshape(-1, 3)
        m = self.fields["metallic"].per_corner(n).reshape(-1, 1)
        s = self.fields["useSpecularWorkflow"].per_corner(n).reshape(-1, 1)
        out = np.ascontiguousarray(_diffuse(d, m, s).reshape(n, 3, 3), np.float32)
        if self.lambert is not None:
            out[self.lambert] = 0.0
        return out

    @property
    def cutout(self) -> bool:
        """Rays can pass through some face: an ``opacityThreshold`` > 0 (holes where opacity is under it) or an
        ``opacity`` < 1 (partial coverage)."""
        return bool(np.any(self.fields["opacityThreshold"].corners > 0) or np.any(self.fields["opacity"].corners < 1)
                    or self.fields["opacity"].textures)

    def kept(self, tri: np.ndarray, w: np.ndarray, xi: np.ndarray | None = None) -> np.ndarray:
        """(K,) bool: hits on triangles ``tri`` with barycentric weights ``w`` (K, 3, 1) that stop the ray.

        * ``opacityThreshold`` > 0: a cutout, kept where ``opacity ≥ opacityThreshold`` (the spec; Storm discards
          the fragment otherwise);
        * threshold 0 and ``opacity`` < 1: partial coverage, kept with probability ``opacity``: where ``xi`` (K,)
          (uniform in [0, 1), one per hit) is under it (stochastic transparency: pixel samples and jittered shadow
          rays average to the coverage); without ``xi`` kept;
        * faces with no surface are always kept."""
        threshold = self.fields["opacityThreshold"].at(tri, w)[:, 0]
        opacity = self.fields["opacity"].at(tri, w)[:, 0]
        cut = threshold > 0
        keep = np.where(cut, opacity >= threshold, True)
        if xi is not None:
            keep &= cut | (xi < opacity)
        if self.lambert is not None:
            keep |= self.lambert[tri]
        return keep

    def normal_map(self, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(rows, st (k, 3, 2))``: the hits on triangles ``tri`` (K,) whose ``normal`` comes from an image, and the
        texture coordinates of that image at their triangles' corners (the tangent frame follows them); None when
        no hit has a normal map."""
        textures = self.fields["normal"].textures
        if not textures:
            return None
        rows_all, st_all = [], []
        taken = np.zeros(len(tri), bool)
        for mask, _lookup, st in textures:
            rows = np.flatnonzero(~taken if mask is None else (mask[tri] & ~taken))
            if len(rows):
                taken[rows] = True
                rows_all.append(rows)
                st_all.append(st[tri[rows]])
        if not rows_all:
            return None
        return np.concatenate(rows_all), np.concatenate(st_all)

    def at(self, tri: np.ndarray, w: np.ndarray, eye: np.ndarray, lambert_albedo: np.ndarray | None = None) -> HitShading:
        """The surface at hits on triangles ``tri`` (K,) with barycentric weights ``w`` (K, 3, 1), seen from unit
        directions ``eye`` (K, 3) (toward the ray's origin); ``lambert_albedo`` (K, 3): the displayColor of
        Lambertian triangles' hits."""
        v = {name: f.at(tri, w) for name, f in self.fields.items()}
        diffuse, metallic = v["diffuseColor"], v["metallic"]
        specular_wf = v["useSpecularWorkflow"][:, 0] > 0.5
        ior = v["ior"][:, 0]
        r = (1.0 - ior) / np.where(1.0 + ior == 0.0, 1.0, 1.0 + ior)
        r2 = (r * r)[:, None]
        spec_color = 1.0 + (diffuse - 1.0) * metallic
        f0 = np.where(specular_wf[:, None], v["specularColor"], r2 * spec_color + (spec_color - r2 * spec_color) * metallic)
        f90 = np.where(specular_wf[:, None], 1.0, spec_color)
        albedo = _diffuse(diffuse, metallic, v["useSpecularWorkflow"])
        occlusion = v["occlusion"]
        rows = np.empty((len(tri), WIDTH), np.float32)
        rows[:, EYE:EYE + 3] = eye
        rows[:, F0:F0 + 3] = f0
        rows[:, F90:F90 + 3] = f90
        rows[:, ALPHA] = np.maximum(v["roughness"][:, 0], 0.001) ** 2
        rows[:, CLEARCOAT] = v["clearcoat"][:, 0]
        rows[:, CLEARCOAT_ALPHA] = np.maximum(v["clearcoatRoughness"][:, 0], 0.001) ** 2
        rows[:, CLEARCOAT_F0] = r2[:, 0]
        rows[:, OCCLUSION] = occlusion[:, 0]
        rows[:, OCCLUSION + 1:] = 0.0
        emission = v["emissiveColor"]
        if self.lambert is not None:
            flat = self.lambert[tri]
            if flat.any():
                rows[flat] = LAMBERT_ROW
                rows[flat, EYE:EYE + 3] = eye[flat]
                albedo[flat] = lambert_albedo[flat] if lambert_albedo is not None else albedo[flat]
                occlusion = np.where(flat[:, None], 1.0, occlusion)
                emission = np.where(flat[:, None], 0.0, emission)
        normal = v["normal"] if self.fields["normal"].textures else None
        return HitShading(reflectance=(albedo * occlusion).astype(np.float32), rows=rows,
                          emission=emission.astype(np.float32), normal=normal)


def _diffuse(diffuse: np.ndarray, metallic: np.ndarray, specular_wf: np.ndarray) -> np.ndarray:
    """Diffuse reflectance: ``diffuseColor·(1 − metallic)`` in the metallic workflow, diffuseColor in the specular."""
    return np.where(specular_wf > 0.5, diffuse, diffuse * (1.0 - metallic)).astype(np.float32)
