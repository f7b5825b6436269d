"""Geometry of paper 000's per-direction voxel arrays: direction bins, the rotated grid, row layout.

Direction bins
    A line and its reverse share rows, so only the hemisphere ``z >= 0`` is binned (a direction with
    ``z < 0`` is flipped first). Bins are the paper's (theta, phi) grid at ``k`` degrees, with
    theta the polar angle from +z in rings ``0, Δθ, 2Δθ, …, 90°`` (``Δθ = 90 / ceil(90 / k) <= k``)
    and phi the azimuth, but each ring holds only as many azimuth bins as keep the arc between
    bin centres at most ``k`` at the ring's outer edge: ``ceil(360 · sin(θ_r + Δθ/2) / k)``
    (one bin at the pole). The paper's 90 × 90 grid spends the same 2° steps on rings near its
    poles that are a few degrees around; these rings give the same worst-case angle with ~35 %
    fewer bins (5,357 instead of 8,100 at 2°). A ray uses the bin of the nearest ring and nearest
    azimuth in that ring; :func:`worst_case_angle` measures the largest angle between a direction
    and its bin centre (1.41° at 2°, i.e. about k/√2).

Rotated grid
    Bin ``b`` has an orthonormal frame ``(u, v, w)`` with ``w`` its centre direction. A voxelization
    is an ``N³`` grid in that frame, centred on the array's bounding sphere (centre ``c``, half size
    ``R``), voxel size ``h = 2R / N``: voxel ``(i, j, l)`` holds ``u, v, w`` in
    ``[-R + i h, -R + (i+1) h)`` … Rows run along ``w``; row ``(i, j)`` is ``N`` bits.

Row layout (packing)
    The sphere fits every frame, so a row whose square cross-section misses the sphere's disk is
    always empty, and within a row only the words overlapping the sphere's chord can hold bits. The
    layout is therefore the same for every direction and stored once per resolution: for each row,
    its first word ``w0``, its word count ``nw`` and its offset into the direction's packed words.
    At 128³ this keeps 70 % of the dense words; with the ring bins an array at 128³ / 2° is
    939 MiB (0.98 GB) instead of the paper's 2 GB.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
import math

import numpy as np

__all__ = ["DirectionBins", "RowLayout", "array_bytes", "worst_case_angle", "surface_samples", "core_bounds",
           "clip_to_box"]


@dataclass(frozen=True)
class DirectionBins:
    """Direction bins at ``step`` degrees (see module doc)."""

    step: float
    ring_theta: np.ndarray = field(repr=False)      #: (R,) float64 polar angle of each ring, degrees
    ring_count: np.ndarray = field(repr=False)      #: (R,) int32 azimuth bins per ring
    ring_start: np.ndarray = field(repr=False)      #: (R,) int32 first bin of each ring
    frames: np.ndarray = field(repr=False)          #: (B, 3, 3) float32 rows u, v, w of each bin

    @staticmethod
    @lru_cache(maxsize=8)
    def make(step: float) -> "DirectionBins":
        """The bins at ``step`` degrees (made once per step: per-frame rebuilds ask for them)."""
        if not (0.1 <= step <= 90.0):
            raise ValueError(f"direction step must be in [0.1, 90] degrees, got {step}")
        n_gaps = math.ceil(90.0 / step - 1e-9)
        d_theta = 90.0 / n_gaps
        theta = np.arange(n_gaps + 1) * d_theta
        outer = np.minimum(theta + d_theta / 2, 90.0)
        count = np.maximum(1, np.ceil(360.0 * np.sin(np.radians(outer)) / step - 1e-9)).astype(np.int32)
        count[0] = 1
        start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int32)
        frames = []
        for t, n in zip(theta, count):
            phi = np.radians(np.arange(n) * 360.0 / n)
            st, ct = math.sin(math.radians(t)), math.cos(math.radians(t))
            for p in phi:
                frames.append(_frame(np.array([st * math.cos(p), st * math.sin(p), ct])))
        return DirectionBins(float(step), theta, count, start, np.asarray(frames, np.float32))

    @property
    def count(self) -> int:
        return int(self.frames.shape[0])

    @property
    def d_theta(self) -> float:
        return float(self.ring_theta[1] - self.ring_theta[0]) if len(self.ring_theta) > 1 else 90.0

    def directions(self) -> np.ndarray:
        """(B, 3) unit centre direction of every bin."""
        return self.frames[:, 2, :].astype(np.float64)

    def bin_of(self, d: np.ndarray) -> np.ndarray:
        """(n,) bin of each (n, 3) direction (any length, any hemisphere); the kernels' rule."""
        d = np.asarray(d, np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(d[:, 2:3] < 0, -d, d)
        theta = np.degrees(np.arccos(np.clip(d[:, 2], -1.0, 1.0)))
        ring = np.clip(np.floor(theta / self.d_theta + 0.5).astype(np.int64), 0, len(self.ring_theta) - 1)
        phi = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0
        n = self.ring_count[ring]
        col = np.floor(phi * n / 360.0 + 0.5).astype(np.int64) % n
        return self.ring_start[ring] + col


def _frame(w: np.ndarray) -> np.ndarray:
    """Rows ``u, v, w`` of an orthonormal frame with third axis ``w``."""
    w = w / np.linalg.norm(w)
    helper = np.array([0.0, 0.0, 1.0]) if abs(w[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, w)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(w, u), w])


def worst_case_angle(bins: DirectionBins, samples: int = 400_000, seed: int = 0) -> float:
    """Largest angle (degrees) between a direction and its bin's centre, over ``samples`` random
    directions plus the bin cell corners (the worst places)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(samples, 3))
    # cell corners: half a ring step and half an azimuth step away from every bin centre
    corners = []
    for t, n in zip(bins.ring_theta, bins.ring_count):
        for dt in (-0.5, 0.5):
            tt = np.radians(np.clip(t + dt * bins.d_theta * 0.999, 0.0, 90.0))
            phi = np.radians((np.arange(n) + 0.4995) * 360.0 / n)
            corners.append(np.stack([np.sin(tt) * np.cos(phi), np.sin(tt) * np.sin(phi), np.full(n, np.cos(tt))], 1))
    d = np.concatenate([d / np.linalg.norm(d, axis=1, keepdims=True)] + corners)
    centre = bins.directions()[bins.bin_of(d)]
    cos = np.abs(np.sum(d * centre, axis=1))
    return float(np.degrees(np.arccos(np.clip(cos.min(), -1.0, 1.0))))


@dataclass(frozen=True)
class RowLayout:
    """Which words of which rows can hold bits at resolution ``n`` (see module doc)."""

    n: int
    words_per_row: int
    w0: np.ndarray = field(repr=False)          #: (n*n,) int32 first stored word of row i*n + j
    nw: np.ndarray = field(repr=False)          #: (n*n,) int32 stored words (0: row misses the sphere)
    offset: np.ndarray = field(repr=False)      #: (n*n,) int32 first word of the row in a direction
    words: int                                  #: packed words per direction

    @staticmethod
    @lru_cache(maxsize=8)
    def make(n: int) -> "RowLayout":
        """The layout at resolution ``n`` (made once per resolution)."""
        if not (4 <= n <= 2048):
            raise ValueError(f"voxel resolution must be in [4, 2048], got {n}")
        wpr = (n + 31) // 32
        # grid in units of the half size R = 1: voxel edges at -1 + k h
        h = 2.0 / n
        lo = -1.0 + np.arange(n) * h
        # nearest point of each row's square to the axis, squared distance
        near = np.where(lo > 0, lo, np.where(lo + h < 0, -(lo + h), 0.0))
        d2 = near[:, None] ** 2 + near[None, :] ** 2
        half_chord = np.sqrt(np.maximum(1.0 - d2, 0.0))
        inside = d2 < 1.0
        first_voxel = np.clip(np.floor((1.0 - half_chord) / h), 0, n - 1)
        last_voxel = np.clip(np.floor((1.0 + half_chord) / h), 0, n - 1)
        w0 = (first_voxel // 32).astype(np.int32)
        nw = np.where(inside, last_voxel // 32 - first_voxel // 32 + 1, 0).astype(np.int32)
        offset = np.concatenate([[0], np.cumsum(nw.ravel())[:-1]]).astype(np.int32)
        return RowLayout(n, wpr, np.where(inside, w0, 0).ravel(), nw.ravel(), offset, int(nw.sum()))

    def word_index(self, ijl: np.ndarray) -> np.ndarray:
        """Word within a direction holding each voxel ``(i, j, l)`` (``(K, 3)``, inside the grid), -1
        where its row does not store that voxel (outside the sphere)."""
        ijl = np.asarray(ijl, np.int64).reshape(-1, 3)
        r = ijl[:, 0] * self.n + ijl[:, 1]
        k = ijl[:, 2] // 32 - self.w0[r]
        return np.where((k >= 0) & (k < self.nw[r]), self.offset[r] + k, -1)

    @property
    def fill(self) -> float:
        """Stored words over dense words."""
        return self.words / (self.n * self.n * self.words_per_row)


def array_bytes(resolution: int, step: float) -> int:
    """Bytes of one packed array at ``resolution``³ and ``step`` degrees."""
    return DirectionBins.make(step).count * RowLayout.make(resolution).words * 4


def surface_samples(points: np.ndarray, triangles: np.ndarray, spacing: float, snap: float | None = None) -> np.ndarray:
    """Points on every triangle no farther than ``spacing`` apart (a barycentric lattice with
    ``ceil(longest edge / spacing)`` steps per edge, vertices and edges included), deduplicated by
    snapping to a ``snap`` grid (default ``spacing / 8``), float32 ``(S, 3)``.

    A plane crossing a row's centre line then has a sample within ``0.58 · spacing + 0.11 · spacing``
    of the crossing; with ``spacing <= h / 2`` that sample lies inside the row's square, so every row
    whose centre line pierces the surface gets a bit (no holes along rows).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if triangles.shape[0] == 0:
        return np.zeros((0, 3), np.float32)
    snap = spacing / 8.0 if snap is None else snap
    a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    longest = np.sqrt(np.max([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=0))
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
    origin = points[np.unique(triangles)].min(axis=0)
    out, keys = [], []

    def add(pts: np.ndarray) -> None:
        # one int64 key per snap cell (21 bits per axis): 1-D unique is far faster than rows
        q = np.floor((pts - origin) / snap).astype(np.int64)
        key = (np.clip(q[:, 0], 0, (1 << 21) - 1) << 42) | (np.clip(q[:, 1], 0, (1 << 21) - 1) << 21) \
            | np.clip(q[:, 2], 0, (1 << 21) - 1)
        k, first = np.unique(key, return_index=True)
        out.append(pts[first])
        keys.append(k)

    one = steps == 1
    if one.any():
        # triangles shorter than the spacing: their vertices (shared with neighbours) and centroid
        t = triangles[one]
        add(np.concatenate([points[np.unique(t)], (a[one] + b[one] + c[one]) / 3.0]))
    for s in np.unique(steps[~one]):
        sel = np.nonzero(steps == s)[0]
        i, j = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
        keep = (i + j) <= s
        bi = (i[keep] / s)[None, :, None]
        bj = (j[keep] / s)[None, :, None]
        per = max(1, (4 << 20) // bi.shape[1])
        for lo in range(0, len(sel), per):
            t = sel[lo:lo + per]
            pa, pb, pc = a[t][:, None, :], b[t][:, None, :], c[t][:, None, :]
            add((pa + (pb - pa) * bi + (pc - pa) * bj).reshape(-1, 3))
    pts = np.concatenate(out)
    _, first = np.unique(np.concatenate(keys), return_index=True)
    return pts[np.sort(first)].astype(np.float32)


def core_bounds(points: np.ndarray, triangles: np.ndarray, trim: float = 0.001
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """Box holding the scene's detail: the bounds of every triangle except the few that are both
    large (longer than half the diagonal of the box of the ``trim`` … ``1 - trim`` quantiles of the
    triangle centroids) and reaching outside that quantile box; and how many triangles reach
    outside the box.

    A terrain or ground slab of a few huge triangles reaching far past the rest of the scene
    (common: a ground to the horizon) then does not stretch the box, so the voxels stay sized to
    where occluders are; everything else, tall outliers included, stays inside. With few triangles
    (< 1 / trim) nothing is trimmed.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if triangles.shape[0] == 0:
        return points.min(0), points.max(0), 0
    # per-corner gathers and element-wise min / max: a (T, 3, 3) reduction along its middle axis is
    # several times slower (1M triangles: 1.1 s -> 0.3 s), the values are the same
    a, b, c = (points[triangles[:, k]] for k in range(3))
    tlo, thi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
    lo, hi = tlo.min(0), thi.max(0)
    if triangles.shape[0] * trim < 1.0:
        return lo, hi, 0
    cen = (a + b + c) / 3.0
    qlo, qhi = np.quantile(cen, trim, axis=0), np.quantile(cen, 1.0 - trim, axis=0)
    # outliers: triangles reaching outside the quantile box that are large next to it
    big = np.linalg.norm(thi - tlo, axis=1) > 0.5 * float(np.linalg.norm(qhi - qlo))
    reach = np.any((tlo < qlo) | (thi > qhi), axis=1)
    keep = ~(big & reach)
    if keep.all() or not keep.any():
        # the box of every triangle: none reaches outside it (a deforming mesh rebuilt per frame,
        # 254 k triangles: 0.073 -> 0.05 s without the count)
        return lo, hi, 0
    lo, hi = tlo[keep].min(0), thi[keep].max(0)
    outside = int((~np.all((tlo >= lo) & (thi <= hi), axis=1)).sum())
    return lo, hi, outside


def clip_to_box(points: np.ndarray, triangles: np.ndarray, lo: np.ndarray, hi: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """Triangles cut to the box ``[lo, hi]``: those inside kept, those outside dropped, those
    crossing it clipped (Sutherland-Hodgman, fan-triangulated). Returns points, triangles and
    the number of triangles that lay partly or wholly outside."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if len(points) and np.all(points.min(0) >= lo) and np.all(points.max(0) <= hi):
        # every point inside, so every triangle (a per-frame array in its own bounds: 254 k
        # triangles, 0.02 s of the per-frame rebuild without the per-triangle tests)
        return points, triangles, 0
    tri = points[triangles]
    # element-wise min / max of the corners, as core_bounds (a (T, 3, 3) reduction along its middle
    # axis is slower; the 254 k-triangle creature, all inside: 0.126 -> 0.088 s, the same output)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    tlo, thi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
    inside = np.all((tlo >= lo) & (thi <= hi), axis=1)
    outside = np.any((thi < lo) | (tlo > hi), axis=1)
    cross = ~inside & ~outside
    new_pts: list[np.ndarray] = []
    new_tris: list[tuple[int, int, int]] = []
    start = points.shape[0]
    for t in np.nonzero(cross)[0]:
        poly = list(tri[t])
        for axis in range(3):
            for bound, keep_ge in ((lo[axis], True), (hi[axis], False)):
                out, m = [], len(poly)
                for i in range(m):
                    a, b = poly[i], poly[(i + 1) % m]
                    ina = a[axis] >= bound if keep_ge else a[axis] <= bound
                    inb = b[axis] >= bound if keep_ge else b[axis] <= bound
                    if ina:
                        out.append(a)
                    if ina != inb:
                        out.append(a + (b - a) * ((bound - a[axis]) / (b[axis] - a[axis])))
                poly = out
                if not poly:
                    break
            if not poly:
                break
        if len(poly) >= 3:
            new_pts.append(np.asarray(poly))
            new_tris += [(start, start + i, start + i + 1) for i in range(1, len(poly) - 1)]
            start += len(poly)
    pts = np.concatenate([points] + new_pts) if new_pts else points
    kept = triangles[inside]
    tris = np.concatenate([kept, np.asarray(new_tris, np.int64).reshape(-1, 3)]) if new_tris else kept
    return pts, tris, int((~inside).sum())
