"""Paper 000 Alg. 5 in Warp: every direction's voxelization filled by rotating one reference
voxelization, with precomputed rotation tables (no trigonometry, no matrix product per voxel).

Inputs (built by ``usdml.visibility.voxel.rotate``)

* ``row_ij``, ``row_start``, ``depth``: the occupied voxels ``(i, j, l)`` of the reference
  voxelization ``V0`` (direction bin 0, voxelized from the geometry), grouped by row ``(i, j)``.
* ``table[d, a, x]``: where step ``x`` along axis ``a`` of ``V0`` lands in direction ``d``'s grid, in
  voxels: ``R_d[:, a] · (x + ½ - n/2)`` (axis 0 also carries the ``+ n/2`` that moves the origin to
  the grid's corner), ``R_d = M_d M_0ᵀ``. A voxel centre's position in direction ``d`` is the sum
  of three table entries. They are 16.16 fixed point: integer adds and shifts instead of
  float-to-int conversions (measured 8.4 against 9.9 ns per voxel on one core).
* ``inv_axes[d]`` (``R_dᵀ``), ``reach[d]`` (half extent of a rotated voxel on each grid axis,
  ``½ Σ_m |R_d[k, m]|``) and ``radius[d]`` (half extent of a grid voxel on each rotated axis
  ``m``, ``½ Σ_k |R_d[k, m]|``): the conservative mapping's constants.

Mappings
    * ``point`` (the paper): the rotated centre of each occupied voxel sets the voxel it falls in.
    * ``conservative``: each rotated voxel (a cube) sets every grid voxel it overlaps, by the
      separating-axis test on the six face normals (the grid's three via the candidate range, the
      rotated cube's three here). Edge-edge separations, which only occur for corner-to-corner near
      misses, are not tested, so a few voxels that only touch the cube's corner region are set too.
"""

import warp as wp

from usdml.kernels.voxel.query import centre_line_crossings, grid_map, set_bit

wp.set_module_options({"enable_backward": False, "optimization_level": 3, "fast_math": True})


FIX = wp.constant(16)                       # fixed-point fraction bits of the tables
INV_FIX = wp.constant(1.0 / 65536.0)


@wp.func
def set_voxel(out: wp.array(dtype=wp.uint32), dir_base: int, n: int, iu: int, iv: int, il: int,
              rows: wp.array(dtype=wp.vec3i), mode: int):
    """Set voxel ``(iu, iv, il)`` of the direction starting at word ``dir_base``; ``rows[r]`` =
    (row's offset minus its first stored word, first stored voxel, end of its stored voxels).
    ``mode``: 0 set the bit, 1 set it atomically."""
    if iu < 0 or iu >= n or iv < 0 or iv >= n:
        return
    rw = rows[iu * n + iv]
    if il >= rw[1] and il < rw[2]:
        set_bit(out, dir_base + rw[0] + (il >> 5), wp.uint32(1) << wp.uint32(il & 31), mode)


@wp.func
def map_voxels(row_ij: wp.array(dtype=wp.int32), row_start: wp.array(dtype=wp.int32),
               depth: wp.array(dtype=wp.int32), r0: int, r1: int, table: wp.array(dtype=wp.vec3i),
               inv_axes: wp.array(dtype=wp.mat33), reach: wp.array(dtype=wp.vec3),
               radius: wp.array(dtype=wp.vec3), n: int, conservative: int, d: int,
               rows: wp.array(dtype=wp.vec3i), dir_base: int, mode: int, out: wp.array(dtype=wp.uint32)):
    """Map the occupied voxels of ``V0``'s rows ``r0 … r1`` into direction ``d`` (module doc),
    ``mode`` as :func:`set_voxel`. A row's two table entries are summed once for all its voxels."""
    t0 = d * 3 * n
    t1 = t0 + n
    t2 = t1 + n
    if conservative == 0:
        for r in range(r0, r1):
            ij = row_ij[r]
            row = table[t0 + (ij >> 10)] + table[t1 + (ij & 1023)]
            for v in range(row_start[r], row_start[r + 1]):
                p = row + table[t2 + depth[v]]
                set_voxel(out, dir_base, n, p[0] >> FIX, p[1] >> FIX, p[2] >> FIX, rows, mode)
        return
    e = reach[d]
    rb = radius[d]
    m = inv_axes[d]
    for r in range(r0, r1):
        ij = row_ij[r]
        row = table[t0 + (ij >> 10)] + table[t1 + (ij & 1023)]
        for v in range(row_start[r], row_start[r + 1]):
            p = row + table[t2 + depth[v]]
            q = wp.vec3(float(p[0]), float(p[1]), float(p[2])) * INV_FIX
            a0 = int(wp.floor(q[0] - e[0]))
            a1 = int(wp.floor(q[0] + e[0]))
            b0 = int(wp.floor(q[1] - e[1]))
            b1 = int(wp.floor(q[1] + e[1]))
            l0 = int(wp.floor(q[2] - e[2]))
            l1 = int(wp.floor(q[2] + e[2]))
            for a in range(a0, a1 + 1):
                for b in range(b0, b1 + 1):
                    for l in range(l0, l1 + 1):
                        # the candidate's centre in the rotated cube's frame
                        s = m * (wp.vec3(float(a) + 0.5, float(b) + 0.5, float(l) + 0.5) - q)
                        if wp.abs(s[0]) < 0.5 + rb[0] and wp.abs(s[1]) < 0.5 + rb[1] and wp.abs(s[2]) < 0.5 + rb[2]:
                            set_voxel(out, dir_base, n, a, b, l, rows, mode)


@wp.kernel
def rotate_voxels(row_ij: wp.array(dtype=wp.int32), row_start: wp.array(dtype=wp.int32),
                  depth: wp.array(dtype=wp.int32), table: wp.array(dtype=wp.vec3i),
                  inv_axes: wp.array(dtype=wp.mat33), reach: wp.array(dtype=wp.vec3),
                  radius: wp.array(dtype=wp.vec3), n: int, conservative: int, dir0: int, chunk: int,
                  rows: wp.array(dtype=wp.vec3i), words_per_dir: int, base: int, mode: int,
                  out: wp.array(dtype=wp.uint32)):
    """Fill direction ``dir0 + i`` from ``V0``'s occupied rows ``c * chunk …`` (Alg. 5, line 7); the
    words must be cleared before.

    ``V0``'s occupied voxels come grouped by row: row ``r`` is ``(i, j) = (row_ij[r] >> 10,
    row_ij[r] & 1023)`` (resolution <= 1024) and holds the voxels at depths ``depth[row_start[r] …
    row_start[r + 1] - 1]``; ``table[(d * 3 + a) * n + x]`` is the fixed-point (16 fraction bits)
    table entry (module doc). Launched with ``dim = (directions, ceil(rows / chunk))``. On CPU one
    chunk holds every row and a thread owns its direction (``mode`` 0: no atomics); on a GPU bits
    are set atomically (``mode`` 1).

    (Grouping by row and clearing by a memset before the launch instead of a word loop here
    measured 1.58 -> 1.12 s per creature frame at 128³ / 2° on one core. Clearing only the words
    the previous frame set, by mapping its voxels again, was measured slower: a scattered write
    costs about as much as memset-ing a few hundred words.)
    """
    i, c = wp.tid()
    d = dir0 + i
    r0 = c * chunk
    r1 = wp.min(r0 + chunk, row_ij.shape[0])
    map_voxels(row_ij, row_start, depth, r0, r1, table, inv_axes, reach, radius, n, conservative, d, rows,
               base + d * words_per_dir, mode, out)


@wp.kernel
def reference_raster(points: wp.array(dtype=wp.vec3), tris: wp.array(dtype=wp.vec3i), first: int,
                     frame: wp.mat33, center: wp.vec3, half: float, n: int, no_rows: wp.array(dtype=wp.int32),
                     mode: int, out: wp.array(dtype=wp.uint32), word0: int, crossings: wp.array(dtype=wp.int32)):
    """``V0`` (Alg. 5, line 1) as the paper makes it, by depth peeling along three axes: triangle
    ``first + tid`` sets every voxel where one of the three axis-parallel lines through the voxel's
    centre crosses it (``kernels.voxel.centre_line_crossings``) in the dense ``n``³ bit grid from
    word ``word0``; ``crossings[first + tid]``: how many it set (``no_rows``: an empty array in the
    place of the packed layout). ``mode``: 0 plain writes (a CPU thread owns its grid), 1 atomic."""
    t = tris[first + wp.tid()]
    m, off = grid_map(frame, center, half, n)
    qa = m * points[t[0]] + off
    qb = m * points[t[1]] + off
    qc = m * points[t[2]] + off
    count = int(0)
    for k in range(3):
        count += centre_line_crossings(qa, qb, qc, k, n, out, word0, no_rows, no_rows, no_rows, 0, mode)
    crossings[first + wp.tid()] = count
