"""NumPy references and scenes for the voxel-array tests: box soups, a small random city with shadow
queries over it, voxels set and found the way the kernels pack and find them."""

from __future__ import annotations

import numpy as np

from usdml.visibility import ExactBackend
from usdml.visibility.voxel.grid import RowLayout

from plain_scenes import snapshot, soup


def box(lo, hi) -> np.ndarray:
    """(12, 3, 3) triangles of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[c[a], c[b], c[d]] for a, b, cc, d in quads for (b, d) in ((b, cc), (cc, d))])


def city_tris(rng) -> np.ndarray:
    tris = [box((-10, -0.5, -10), (10, 0, 10))]
    for _ in range(12):
        x, z = rng.uniform(-8, 8, 2)
        w, d, h = rng.uniform(0.5, 2.5, 3) * (1, 1, 3)
        tris.append(box((x - w, 0, z - d), (x + w, h, z + d)))
    return np.concatenate(tris)


def ground_queries(rng, n=4000):
    """Points on the ground and box tops, lights above: shadow queries with normals."""
    o = np.c_[rng.uniform(-9, 9, n), np.zeros(n), rng.uniform(-9, 9, n)]
    t = np.c_[rng.uniform(-9, 9, n), rng.uniform(2, 9, n), rng.uniform(-9, 9, n)]
    return o, t, np.tile([0.0, 1.0, 0.0], (n, 1))


def set_voxels(words: np.ndarray, d: int, ijl: np.ndarray, layout: RowLayout) -> None:
    """Set voxels ``(i, j, l)`` (inside the grid) of direction ``d`` in packed ``words``, those their
    rows do not store dropped: the packing the kernels write."""
    ijl = np.asarray(ijl, np.int64).reshape(-1, 3)
    w = layout.word_index(ijl)
    ok = w >= 0
    np.bitwise_or.at(words, d * layout.words + w[ok], np.uint32(1) << (ijl[ok, 2] % 32).astype(np.uint32))


def centre_line_voxels(points: np.ndarray, triangles: np.ndarray, center: np.ndarray, half: float, n: int,
                       frame: np.ndarray, axes=(0, 1, 2)) -> tuple[set, int]:
    """NumPy reference of the centre-line rule (float64): the voxels ``(i, j, l)`` of the grid with
    frame ``frame`` where a line parallel to one of grid ``axes`` through voxel centres crosses a
    triangle, and the number of crossings."""
    q = ((np.asarray(points, np.float64) - center) @ np.asarray(frame, np.float64).T + half) * (n / (2.0 * half))
    voxels, crossings = set(), 0
    for t in np.asarray(triangles).reshape(-1, 3):
        a, b, c = q[t]
        for k in axes:
            x, y = (k + 1) % 3, (k + 2) % 3
            m = np.array([[b[x] - a[x], c[x] - a[x]], [b[y] - a[y], c[y] - a[y]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            tri = np.array([a, b, c])
            ii = np.arange(max(0, int(np.ceil(tri[:, x].min() - 0.5))), min(n - 1, int(np.floor(tri[:, x].max() - 0.5))) + 1)
            jj = np.arange(max(0, int(np.ceil(tri[:, y].min() - 0.5))), min(n - 1, int(np.floor(tri[:, y].max() - 0.5))) + 1)
            gi, gj = (g.ravel() for g in np.meshgrid(ii, jj, indexing="ij"))
            lb, lc = np.linalg.solve(m, np.stack([gi + 0.5 - a[x], gj + 0.5 - a[y]]))
            inside = (lb >= -1e-9) & (lc >= -1e-9) & (lb + lc <= 1 + 1e-9)
            depth = np.floor(a[k] + lb * (b[k] - a[k]) + lc * (c[k] - a[k])).astype(np.int64)
            keep = inside & (depth >= 0) & (depth < n)
            crossings += int(keep.sum())
            for i_, j_, l_ in zip(gi[keep], gj[keep], depth[keep]):
                v = [0, 0, 0]
                v[k], v[x], v[y] = l_, i_, j_
                voxels.add(tuple(int(e) for e in v))
    return voxels, crossings


def small_city_scene():
    """The city of :func:`city_tris` (seed 3), shadow queries over it and exact's answers:
    ``(snapshot, origins, targets, normals, occluded)``."""
    rng = np.random.default_rng(3)
    snap = snapshot([soup("/city", city_tris(rng))])
    exact = ExactBackend()
    exact.update(snap)
    o, t, nrm = ground_queries(rng)
    ref = exact.occluded(o, t, normals=nrm)
    exact.close()
    return snap, o, t, nrm, ref
