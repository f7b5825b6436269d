"""Intermediate shadow maps (paper 001, Alg. 1 lines 1-3): ``K`` depth images of the scene from
viewpoints on its bounding box, each triangulated into a world-space mesh (Alg. 2).

Viewpoints (paper 001, Fig. 2)
    The paper's ten: the midpoints of the eight edges of the scene's box that are not vertical (the
    stage's up axis) and the centres of its left and right faces (``±X``, or ``±Y`` when X is up).
    Other counts take a prefix of one fixed order (:data:`ORDER`): the four top edges, the two side
    faces, the four bottom edges (the paper's ten), then the four vertical edges, the other four face
    centres and the eight corners (26 at most). A depth image is one perspective view from its
    viewpoint toward the box's centre; a viewpoint on the box would see the box over up to 180°, so
    it moves ``MARGIN`` times as far from the centre, and the view's frustum is fitted (off-axis) to the
    box's eight corners: the scene fills the ``w × w`` image whatever its proportions.

Depth images
    Embree primary rays through the pixel centres (:meth:`usdml.visibility.exact.ExactBackend.intersect`);
    a ray's direction has view depth 1, so its ``t`` is the view depth ``z`` (``inf``: background).

Triangulation (Alg. 2)
    Two triangles per ``2 × 2`` block of samples, ``(a, a + (0, 1), a + (1, 1))`` and
    ``(a + (1, 1), a + (1, 0), a)``; a triangle is kept when its three corners are scene samples and
    its three edges are connected. Edge ``a → b = a + δ`` is connected when both second differences
    along ``δ``, at ``a`` (``a - δ, a, b``) and at ``b`` (``a, b, b + δ``), are small. The paper takes
    the second difference of the depth buffer, which is exactly 0 on any plane: here of ``1 / z``
    (affine in the image for a plane, as a depth buffer is), measured against the sample's size so
    the threshold is scale-free: ``|Δ²(1/z)| · z · a < κ`` with ``a`` the view's pixels per unit of
    ``x / z``: a step of more than about ``κ`` pixel footprints disconnects (``κ`` =
    ``threshold``). A neighbour outside the image or on the background gives no evidence and passes.

    The crease rule (usdml's, beside the paper's): an edge is also connected when each of its two
    samples lies within ``CREASE`` pixel footprints of the other's tangent plane (Embree's geometric
    normal at the hit). A wall standing on the ground is a crease, whose second differences are as
    large as a step's: the paper's rule alone cut every wall from the ground and left a gap of a
    pixel at its foot (city ε_s 19.7 %, with it 4.1 %; docs/insm.md). A step's samples lie far from
    each other's planes, so the rule never bridges one.

    The kept triangles come in the order of ``CLUSTER × CLUSTER``-cell blocks of each image, so a run of
    consecutive triangles is a patch of one image (:func:`clusters`: the compiled maps test a run's box
    first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ORDER", "MARGIN", "MAX_COUNT", "View", "reference_viewpoints", "insm_views", "depth_images",
           "triangulate"]

#: how much farther from the box's centre than the paper's points the viewpoints sit (module doc)
MARGIN = 1.5
#: viewpoints in box coordinates (horizontal a, up u, horizontal b), the paper's ten first (module doc)
ORDER = np.array(
    [(1, 1, 0), (-1, 1, 0), (0, 1, 1), (0, 1, -1),           # the four top edges
     (1, 0, 0), (-1, 0, 0),                                   # the left and right faces
     (1, -1, 0), (-1, -1, 0), (0, -1, 1), (0, -1, -1),       # the four bottom edges
     (1, 0, 1), (-1, 0, -1), (1, 0, -1), (-1, 0, 1),         # the vertical edges
     (0, 1, 0), (0, 0, 1), (0, 0, -1), (0, -1, 0),           # the other face centres
     (1, 1, 1), (-1, -1, -1), (1, 1, -1), (-1, -1, 1), (1, -1, 1), (-1, 1, -1), (1, -1, -1), (-1, 1, 1)],
    np.float64)
MAX_COUNT = len(ORDER)
#: triangles are kept in clusters of this many cells squared of one depth image (module doc)
CLUSTER = 8
#: an edge whose two samples each lie within this many pixel footprints of the other's tangent plane is
#: a crease, connected (module doc); 0: the paper's rule alone
CREASE = 2.0


@dataclass
class View:
    """One perspective view: ``q = rot @ (p - origin)``, pixel ``(ax q.x / q.z + bx, ay q.y / q.z + by)``."""

    origin: np.ndarray      #: (3,) float64 world
    rot: np.ndarray         #: (3, 3) float64 rows: right, up, forward
    proj: np.ndarray        #: (4,) float64 ax, bx, ay, by

    def ray_directions(self, resolution: int) -> np.ndarray:
        """``(w · w, 3)`` world directions through the pixel centres, row-major (row = y), view depth 1."""
        ax, bx, ay, by = self.proj
        centres = np.arange(resolution) + 0.5
        x = (centres - bx) / ax
        y = (centres - by) / ay
        xx, yy = np.meshgrid(x, y)
        local = np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)], axis=1)
        return local @ self.rot


def _axes(up_axis: str) -> tuple[int, int, int]:
    """Indices of the (horizontal a, up u, horizontal b) box axes for a stage's up axis."""
    return (0, 1, 2) if str(up_axis).upper() != "Z" else (0, 2, 1)


def reference_viewpoints(lo, hi, count: int, up_axis: str = "Y") -> np.ndarray:
    """``(count, 3)`` world viewpoints for a box ``lo .. hi`` (module doc; ``count <= MAX_COUNT``)."""
    if not 1 <= count <= MAX_COUNT:
        raise ValueError(f"count must be in [1, {MAX_COUNT}], got {count}")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half = np.maximum(half, 1e-6 * max(float(half.max()), 1e-9))
    a, u, b = _axes(up_axis)
    local = np.zeros((count, 3))
    local[:, [a, u, b]] = ORDER[:count]
    return centre + MARGIN * local * half


def _look_basis(forward: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    f = forward / np.linalg.norm(forward)
    hint = up_hint if abs(float(np.dot(f, up_hint))) < 0.99 else np.roll(up_hint, 1)
    right = np.cross(hint, f)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(f, right), f])


def box_corners(lo, hi) -> np.ndarray:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def insm_views(lo, hi, count: int, resolution: int, up_axis: str = "Y") -> list[View]:
    """The ``count`` depth-image views of the box ``lo .. hi`` at ``resolution`` pixels (module doc)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = 0.5 * (lo + hi)
    up = np.zeros(3)
    up[_axes(up_axis)[1]] = 1.0
    corners = box_corners(lo, hi)
    views = []
    for eye in reference_viewpoints(lo, hi, count, up_axis):
        rot = _look_basis(centre - eye, up)
        q = (corners - eye) @ rot.T
        z = np.maximum(q[:, 2], 1e-9 * max(1.0, float(np.abs(q).max())))
        sx, sy = q[:, 0] / z, q[:, 1] / z
        proj = []
        for s in (sx, sy):
            s0, s1 = float(s.min()), float(s.max())
            pad = 1e-6 * max(1.0, s1 - s0)
            scale = resolution / (s1 - s0 + 2 * pad)
            proj += [scale, -(s0 - pad) * scale]
        views.append(View(eye, rot, np.array(proj)))
    return views


def depth_images(exact, views: list[View], resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K, w, w) float32`` view depths (``inf``: background), ``(K, w, w, 3) float32`` world hit
    points and ``(K, w, w, 3) float32`` unit geometric normals of every view, by Embree primary rays of
    ``exact`` (an updated ``ExactBackend``)."""
    k, w = len(views), int(resolution)
    origins = np.repeat(np.array([v.origin for v in views]), w * w, axis=0)
    dirs = np.concatenate([v.ray_directions(w) for v in views])
    got = exact.intersect(origins, dirs)
    t = got["t"].astype(np.float64)
    hit = np.isfinite(t)
    points = np.where(hit[:, None], origins + dirs * np.where(hit, t, 0.0)[:, None], np.nan)
    ng = got["ng"].astype(np.float64)
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-30)
    shape = (k, w, w, 3)
    return (t.astype(np.float32).reshape(k, w, w), points.astype(np.float32).reshape(shape),
            ng.astype(np.float32).reshape(shape))


def _shift(a: np.ndarray, di: int, dj: int, fill) -> np.ndarray:
    """``out[i, j] = a[i + di, j + dj]`` (``fill`` outside)."""
    out = np.full_like(a, fill)
    h, w = a.shape
    src = a[max(di, 0):h + min(di, 0), max(dj, 0):w + min(dj, 0)]
    out[max(-di, 0):h + min(-di, 0), max(-dj, 0):w + min(-dj, 0)] = src
    return out


def _shift3(a: np.ndarray, di: int, dj: int) -> np.ndarray:
    return np.stack([_shift(a[..., c], di, dj, np.nan) for c in range(3)], axis=-1)


def connected_edges(z: np.ndarray, scale: float, threshold: float, points: np.ndarray | None = None,
                    normals: np.ndarray | None = None) -> dict:
    """For one ``(h, w)`` depth image (``inf``: background) and its pixels per unit of ``x / z``: per
    edge direction ``δ`` in ``(0, 1), (1, 0), (1, 1)``, ``(h, w) bool`` whether edge ``a → a + δ`` is
    connected (module doc, Alg. 2's IsConnected per edge; with the samples' ``(h, w, 3)`` world
    ``points`` and unit ``normals``, also the crease rule)."""
    valid = np.isfinite(z)
    inv = np.where(valid, 1.0 / np.where(valid, z, 1.0), np.nan).astype(np.float64)
    zz = np.where(valid, z, np.nan).astype(np.float64)
    crease = CREASE > 0 and points is not None and normals is not None
    if crease:
        p = np.where(valid[..., None], points, np.nan).astype(np.float64)
        n = np.where(valid[..., None], normals, np.nan).astype(np.float64)
    out = {}
    for di, dj in ((0, 1), (1, 0), (1, 1)):
        b = _shift(inv, di, dj, np.nan)
        before = _shift(inv, -di, -dj, np.nan)
        after = _shift(inv, 2 * di, 2 * dj, np.nan)
        zb = _shift(zz, di, dj, np.nan)
        with np.errstate(invalid="ignore"):
            at_a = np.abs(before + b - 2 * inv) * zz * scale
            at_b = np.abs(inv + after - 2 * b) * zb * scale
            # both must be small (the paper's rule); a NaN (a missing neighbour) is no evidence, passes
            ok = ~(at_a >= threshold) & ~(at_b >= threshold)
            if crease:
                # two surfaces meeting (a wall on the ground): each sample lies near the other's
                # tangent plane, which a step's samples do not (module doc)
                pb, nb = _shift3(p, di, dj), _shift3(n, di, dj)
                gap = np.maximum(np.abs(((pb - p) * n).sum(-1)), np.abs(((p - pb) * nb).sum(-1)))
                ok |= gap <= CREASE * np.minimum(zz, zb) / scale
        out[(di, dj)] = valid & np.isfinite(b) & ok
    return out


def triangulate(depth: np.ndarray, points: np.ndarray, views: list[View], threshold: float,
                normals: np.ndarray | None = None) -> np.ndarray:
    """Alg. 2 over every depth image: ``(3 T, 3) float32`` corners of the kept triangles, world space,
    in clusters of ``CLUSTER × CLUSTER`` cells of one image (:func:`clusters` finds them).

    ``depth`` (K, w, w), ``points`` and ``normals`` (K, w, w, 3) from :func:`depth_images`;
    ``threshold`` is ``κ`` (module doc)."""
    pieces, keys = [], []
    for k, (z, p, view) in enumerate(zip(depth, points, views)):
        c = connected_edges(z, float(min(view.proj[0], view.proj[2])), threshold, p,
                            None if normals is None else normals[k])
        right, down, diag = c[(0, 1)], c[(1, 0)], c[(1, 1)]
        # cell (i, j) with corners a = (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)
        t1 = right[:-1, :-1] & down[:-1, 1:] & diag[:-1, :-1]       # a, a + (0, 1), a + (1, 1)
        t2 = down[:-1, :-1] & right[1:, :-1] & diag[:-1, :-1]       # a + (1, 1), a + (1, 0), a
        blocks = -(-z.shape[1] // CLUSTER)
        for mask, corners in ((t1, ((0, 0), (0, 1), (1, 1))), (t2, ((1, 1), (1, 0), (0, 0)))):
            i, j = np.nonzero(mask)
            if len(i):
                pieces.append(np.stack([p[i + di, j + dj] for di, dj in corners], axis=1))
                keys.append((k * blocks + i // CLUSTER) * blocks + j // CLUSTER)
    if not pieces:
        return np.zeros((0, 3), np.float32)
    order = np.argsort(np.concatenate(keys), kind="stable")
    return np.ascontiguousarray(np.concatenate(pieces)[order].reshape(-1, 3), np.float32)


def clusters(tris: np.ndarray, size: int = CLUSTER * CLUSTER * 2) -> tuple[np.ndarray, np.ndarray]:
    """Runs of at most ``size`` consecutive triangles of ``tris`` ((3 T, 3), :func:`triangulate`'s order,
    where neighbours in a run are neighbours in an image) and their world boxes: ``(C + 1,) int64``
    first triangle of each run and ``(C, 6) float32`` ``lo, hi``; the compiled maps test a run's box
    before its triangles."""
    t = np.asarray(tris, np.float32).reshape(-1, 3, 3)
    n = len(t)
    starts = np.arange(0, n, size, dtype=np.int64)
    if not n:
        return np.zeros(1, np.int64), np.zeros((0, 6), np.float32)
    lo = np.minimum.reduceat(t.min(axis=1), starts)
    hi = np.maximum.reduceat(t.max(axis=1), starts)
    return np.append(starts, n), np.ascontiguousarray(np.concatenate([lo, hi], axis=1), np.float32)
