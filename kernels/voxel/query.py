"""Paper 000 in Warp: per-direction bit voxelizations (Alg. 1) and constant-time segment queries
(Alg. 2) with rigid instancing (Alg. 4). The many-light shading kernel that asks these queries
(Alg. 3) is :mod:`usdml.kernels.voxel.shading`.

Data layout (built by ``usdml.visibility.voxel.array`` and ``usdml.visibility.voxel.backend``; geometry in ``usdml.visibility.voxel.grid``)

* ``words``: every array of the scene concatenated, uint32. Array ``a`` starts at
  ``arr_int[a, 2]``; direction ``d`` of it at ``+ d * arr_int[a, 1]`` (packed words per direction);
  row ``r = i * n + j`` at ``+ row_off[arr_int[a, 3] + r]`` holding words ``row_w0 … row_w0 + row_nw - 1``
  of the row. Bit ``b`` of row word ``k`` is voxel ``32 k + b`` along the row.
* ``arr_center[a]``, ``arr_half[a]`` (half size ``R``), ``arr_int[a, 0]`` resolution ``n``.
* Direction bins (shared by all arrays): ``frames[d]`` rows ``u, v, w``; ``ring_count``, ``ring_start``,
  ``d_theta`` (degrees).

Query rule (Alg. 2, refined)
    The paper looks the whole ray up in the row containing its midpoint. Here the ray's extent along
    the row axis is cut at word boundaries (and into ``seg``-voxel pieces, ``seg`` dividing 32), and
    each piece is looked up in the row containing the ray's own position at the middle of the piece:
    the same ≤ 4 word reads at 128³, but the row follows the ray instead of drifting up to
    ``length · tan(bin error)`` (≈ 1.6 voxels over a 128-voxel ray at 2°) away from it.
"""

import warp as wp

# no gradients here; -O3 and fast math (measured: see usdml.visibility.voxel.backend)
wp.set_module_options({"enable_backward": False, "optimization_level": 3, "fast_math": True})

DEG = wp.constant(57.29577951308232)
ALL_BITS = wp.constant(wp.uint32(0xFFFFFFFF))


@wp.func
def core_voxel(p: wp.vec3, m: wp.mat33, center: wp.vec3, half: float, inv_h: float, n: int, lo: float,
               hi: float) -> wp.vec3i:
    """The voxel ``(u, v, w)`` of the grid with frame ``m`` (rows ``u, v, w``) over the cube
    ``center ± half`` that holds point ``p``, when ``p`` lies within the central part ``[lo, hi]``
    of its row's square; ``u = -1`` otherwise (outside the cube, or off the row's core)."""
    q = (m * (p - center) + wp.vec3(half, half, half)) * inv_h
    fu = wp.floor(q[0])
    fv = wp.floor(q[1])
    iu = int(fu)
    iv = int(fv)
    il = int(wp.floor(q[2]))
    ru = q[0] - fu
    rv = q[1] - fv
    # one return (a branchy early return measured 30 % slower in Alg. 1)
    inside = iu >= 0 and iu < n and iv >= 0 and iv < n and il >= 0 and il < n
    core_hit = ru >= lo and ru <= hi and rv >= lo and rv <= hi
    return wp.vec3i(wp.where(inside and core_hit, iu, -1), iv, il)


@wp.func
def set_bit(out: wp.array(dtype=wp.uint32), w: int, bit: wp.uint32, mode: int):
    """``out[w] |= bit``: plainly (``mode`` 0, the word's thread owns it) or atomically (1)."""
    if mode == 0:
        out[w] = out[w] | bit
    else:
        wp.atomic_or(out, w, bit)


@wp.kernel
def voxelize(samples: wp.array(dtype=wp.vec3), center: wp.vec3, half: float, n: int, core: float,
             frames: wp.array(dtype=wp.mat33), dir0: int, chunk: int, row_w0: wp.array(dtype=wp.int32),
             row_nw: wp.array(dtype=wp.int32), row_off: wp.array(dtype=wp.int32), words_per_dir: int,
             word0: int, out: wp.array(dtype=wp.uint32)):
    """Set the bit of the voxel holding each sample, in direction ``dir0 + i`` (Alg. 1) of the
    array starting at word ``word0`` of ``out``.

    Launched with ``dim = (directions, ceil(samples / chunk))``; thread ``(i, c)`` rotates samples
    ``c * chunk …`` (on CPU one chunk holds every sample, so one direction's voxelization stays in
    cache while all samples stream through it). A sample marks its voxel only when it lies within
    the central ``core`` fraction of its row's square (1: every voxel the surface touches; smaller:
    thinner, less biased surfaces, which need proportionally denser samples to stay hole-free).
    """
    i, c = wp.tid()
    d = dir0 + i
    m = frames[d]
    inv_h = float(n) / (2.0 * half)
    lo = 0.5 - 0.5 * core
    hi = 0.5 + 0.5 * core
    s0 = c * chunk
    s1 = wp.min(s0 + chunk, samples.shape[0])
    base = word0 + d * words_per_dir
    for s in range(s0, s1):
        vox = core_voxel(samples[s], m, center, half, inv_h, n, lo, hi)
        if vox[0] >= 0:
            r = vox[0] * n + vox[1]
            il = vox[2]
            k = (il >> 5) - row_w0[r]
            if k >= 0 and k < row_nw[r]:
                wp.atomic_or(out, base + row_off[r] + k, wp.uint32(1) << wp.uint32(il & 31))


@wp.func
def grid_map(frame: wp.mat33, center: wp.vec3, half: float, n: int):
    """``(m, off)``: ``m p + off`` is point ``p`` in the ``n``³ grid with rows ``frame`` over the cube
    ``center ± half``, in voxels from the grid's corner."""
    inv_h = float(n) / (2.0 * half)
    m = frame * inv_h
    return m, wp.vec3(half, half, half) * inv_h - m * center


#: slack of the inside test in barycentric units: a line through a shared edge or vertex marks a
#: voxel for both triangles (setting a bit twice costs nothing) instead of slipping between them
EDGE_SLACK = wp.constant(1.0e-6)


@wp.func
def centre_line_crossings(qa: wp.vec3, qb: wp.vec3, qc: wp.vec3, k: int, n: int, out: wp.array(dtype=wp.uint32),
                          base: int, row_w0: wp.array(dtype=wp.int32), row_nw: wp.array(dtype=wp.int32),
                          row_off: wp.array(dtype=wp.int32), packed: int, mode: int) -> int:
    """Set the voxels where the lines parallel to grid axis ``k`` through voxel centres cross
    triangle ``(qa, qb, qc)`` (grid coordinates in voxels, corner origin; the paper's depth peel
    along ``k``); returns the crossings. ``packed`` 1: into the packed direction from word ``base``
    (rows ``row_w0`` / ``row_nw`` / ``row_off``, voxels outside the stored words dropped); 0: into
    the dense ``n``³ bit grid from word ``base`` (voxel ``(i, j, l)`` is bit ``(i n + j) n + l``).
    ``mode`` as :func:`set_bit`. A triangle edge-on to the axis crosses no line."""
    x = (k + 1) % 3
    y = (k + 2) % 3
    # the voxel centres i + 1/2 inside the triangle's projected box; most triangles of a detailed
    # mesh are smaller than a voxel and hold none
    i0 = wp.max(0, int(wp.ceil(wp.min(wp.min(qa[x], qb[x]), qc[x]) - 0.5)))
    i1 = wp.min(n - 1, int(wp.floor(wp.max(wp.max(qa[x], qb[x]), qc[x]) - 0.5)))
    j0 = wp.max(0, int(wp.ceil(wp.min(wp.min(qa[y], qb[y]), qc[y]) - 0.5)))
    j1 = wp.min(n - 1, int(wp.floor(wp.max(wp.max(qa[y], qb[y]), qc[y]) - 0.5)))
    count = int(0)
    if i0 > i1 or j0 > j1:
        return count
    ax = qa[x]
    ay = qa[y]
    ux = qb[x] - ax
    uy = qb[y] - ay
    vx = qc[x] - ax
    vy = qc[y] - ay
    area = ux * vy - uy * vx
    if wp.abs(area) < 1.0e-12:
        return count
    inv = 1.0 / area
    dzb = qb[k] - qa[k]
    dzc = qc[k] - qa[k]
    for i in range(i0, i1 + 1):
        px = float(i) + 0.5 - ax
        for j in range(j0, j1 + 1):
            py = float(j) + 0.5 - ay
            lb = (px * vy - py * vx) * inv
            lc = (ux * py - uy * px) * inv
            if lb >= -EDGE_SLACK and lc >= -EDGE_SLACK and lb + lc <= 1.0 + EDGE_SLACK:
                l = int(wp.floor(qa[k] + lb * dzb + lc * dzc))
                if l >= 0 and l < n:
                    v = wp.vec3i(0, 0, 0)
                    v[k] = l
                    v[x] = i
                    v[y] = j
                    if packed == 1:
                        r = v[0] * n + v[1]
                        w = (v[2] >> 5) - row_w0[r]
                        if w >= 0 and w < row_nw[r]:
                            set_bit(out, base + row_off[r] + w, wp.uint32(1) << wp.uint32(v[2] & 31), mode)
                    else:
                        b = (v[0] * n + v[1]) * n + v[2]
                        set_bit(out, base + (b >> 5), wp.uint32(1) << wp.uint32(b & 31), mode)
                    count += 1
    return count


@wp.kernel
def voxelize_triangles(points: wp.array(dtype=wp.vec3), tris: wp.array(dtype=wp.vec3i), center: wp.vec3,
                       half: float, n: int, frames: wp.array(dtype=wp.mat33), dir0: int, chunk: int,
                       row_w0: wp.array(dtype=wp.int32), row_nw: wp.array(dtype=wp.int32),
                       row_off: wp.array(dtype=wp.int32), words_per_dir: int, word0: int, mode: int,
                       out: wp.array(dtype=wp.uint32)):
    """Alg. 1 by centre lines: in direction ``dir0 + i`` of the array starting at word ``word0``,
    triangles ``c * chunk …`` set every voxel where a row's centre line crosses them.

    Launched with ``dim = (directions, ceil(triangles / chunk))``; on CPU one chunk holds every
    triangle (a thread owns its direction, ``mode`` 0), on a GPU bits are set atomically (1).
    """
    i, c = wp.tid()
    d = dir0 + i
    m, off = grid_map(frames[d], center, half, n)
    t0 = c * chunk
    t1 = wp.min(t0 + chunk, tris.shape[0])
    base = word0 + d * words_per_dir
    for t in range(t0, t1):
        tri = tris[t]
        centre_line_crossings(m * points[tri[0]] + off, m * points[tri[1]] + off, m * points[tri[2]] + off, 2, n,
                              out, base, row_w0, row_nw, row_off, 1, mode)


@wp.func
def fast_atan2(y: float, x: float) -> float:
    """atan2 by a degree-11 minimax polynomial (max error ~1e-5 rad): libm's atan2 and acos were
    a third of a query's time here; 1e-5 rad only moves directions lying on a bin border."""
    ax = wp.abs(x)
    ay = wp.abs(y)
    mx = wp.max(ax, ay)
    if mx == 0.0:
        return 0.0
    a = wp.min(ax, ay) / mx
    s = a * a
    r = a * (0.99997726 + s * (-0.33262347 + s * (0.19354346 + s * (-0.11643287 + s * (0.05265332 - 0.01172120 * s)))))
    if ay > ax:
        r = 1.57079637 - r
    if x < 0.0:
        r = 3.14159274 - r
    if y < 0.0:
        r = -r
    return r


@wp.func
def direction_bin(d: wp.vec3, d_theta: float, ring_count: wp.array(dtype=wp.int32),
                  ring_start: wp.array(dtype=wp.int32)) -> int:
    """Bin of direction ``d`` (any length): nearest ring, nearest azimuth; ``z < 0`` flipped."""
    e = d
    if e[2] < 0.0:
        e = -e
    theta = fast_atan2(wp.sqrt(e[0] * e[0] + e[1] * e[1]), e[2]) * DEG
    n_rings = ring_count.shape[0]
    ring = wp.clamp(int(theta / d_theta + 0.5), 0, n_rings - 1)
    phi = fast_atan2(e[1], e[0]) * DEG
    if phi < 0.0:
        phi = phi + 360.0
    cnt = ring_count[ring]
    col = int(phi * float(cnt) * (1.0 / 360.0) + 0.5)
    if col >= cnt:
        col = col - cnt
    return ring_start[ring] + col


@wp.struct
class VoxelScene:
    """Every array of a scene and how queries reach them (module doc), as one kernel argument."""

    words: wp.array(dtype=wp.uint32)
    arr_center: wp.array(dtype=wp.vec3)
    arr_half: wp.array(dtype=float)
    arr_int: wp.array2d(dtype=wp.int32)     # per array: resolution, words per direction, base, row table base
    row_w0: wp.array(dtype=wp.int32)
    row_nw: wp.array(dtype=wp.int32)
    row_off: wp.array(dtype=wp.int32)
    frames: wp.array(dtype=wp.mat33)
    d_theta: float
    ring_count: wp.array(dtype=wp.int32)
    ring_start: wp.array(dtype=wp.int32)
    static_array: int                       # -1: none
    static_inv: wp.mat44                    # world -> the static array's space
    bvh: wp.uint64                          # over the world boxes of the instances below
    n_inst: int
    inst_inv: wp.array(dtype=wp.mat44)      # world -> instance (prototype array) space
    inst_array: wp.array(dtype=wp.int32)


@wp.struct
class RayRule:
    """How a shadow ray leaves its surface and its light (``usdml.visibility.voxel.backend`` module doc)."""

    offset: float       # world units along the normal turned toward the light
    skip: float         # voxels skipped at the start (at least)
    slab: float         # ... or until this many voxels above the tangent plane
    max_skip: float
    end_skip: float     # voxels cut before a point light
    far: float          # with the ray's distance from far_center: a length that takes a distant ray out of every array
    far_center: wp.vec3
    seg: int            # voxels read per row lookup (divides 32)


@wp.func
def array_hit(vs: VoxelScene, a: int, pa: wp.vec3, pb: wp.vec3, skip0: float, skip1: float, seg: int,
              want_t: int) -> float:
    """Distance in voxels from ``pa`` (after the skip) to the first occupied voxel of segment
    ``pa → pb`` (array space) in array ``a``; -1 when the segment is free (Alg. 2).

    ``skip0`` / ``skip1`` voxels are cut from the start / end of the segment.
    """
    n = vs.arr_int[a, 0]
    wpd = vs.arr_int[a, 1]
    base = vs.arr_int[a, 2]
    rbase = vs.arr_int[a, 3]
    half = vs.arr_half[a]
    c = vs.arr_center[a]
    inv_h = float(n) / (2.0 * half)
    delta = pb - pa
    length = wp.length(delta) * inv_h           # voxels
    if length <= skip0 + skip1 or length <= 0.0:
        return -1.0
    d = direction_bin(delta, vs.d_theta, vs.ring_count, vs.ring_start)
    m = vs.frames[d]
    # grid coordinates in voxels: [0, n) on every axis inside the cube
    qa = (m * (pa - c) + wp.vec3(half, half, half)) * inv_h
    qb = (m * (pb - c) + wp.vec3(half, half, half)) * inv_h
    dq = qb - qa
    t0 = skip0 / length
    t1 = 1.0 - skip1 / length
    # clip to the cube [0, n]^3 (slabs)
    fn = float(n)
    for ax in range(3):
        qa_in = qa[ax] >= 0.0 and qa[ax] < fn
        qb_in = qb[ax] >= 0.0 and qb[ax] < fn
        if not (qa_in and qb_in):
            if wp.abs(dq[ax]) < 1.0e-12:
                return -1.0
            inv = 1.0 / dq[ax]
            ta = (0.0 - qa[ax]) * inv
            tb = (fn - qa[ax]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    if t0 > t1:
        return -1.0
    wa = qa[2] + dq[2] * t0
    wb = qa[2] + dq[2] * t1
    lo = wp.clamp(int(wp.min(wa, wb)), 0, n - 1)
    hi = wp.clamp(int(wp.max(wa, wb)), 0, n - 1)
    forward = dq[2] >= 0.0
    dir_base = base + d * wpd
    inv_dw = float(0.0)
    if wp.abs(dq[2]) > 1.0e-12:
        inv_dw = 1.0 / dq[2]
    # visit the ray's pieces from its start, so the first hit found is the nearest
    npieces = hi / seg - lo / seg + 1
    for p in range(npieces):
        ps = int(0)
        if forward:
            ps = (lo / seg + p) * seg
        else:
            ps = (hi / seg - p) * seg
        s = wp.max(ps, lo)
        e = wp.min(ps + seg - 1, hi)
        # the ray's position at the middle of the piece
        t = wp.clamp((0.5 * float(s + e + 1) - qa[2]) * inv_dw, t0, t1)
        fu = qa[0] + dq[0] * t
        fv = qa[1] + dq[1] * t
        if fu >= 0.0 and fu < fn and fv >= 0.0 and fv < fn:
            r = rbase + int(fu) * n + int(fv)
            k = (s >> 5) - vs.row_w0[r]
            if k >= 0 and k < vs.row_nw[r]:
                word = vs.words[dir_base + vs.row_off[r] + k]
                mask = (ALL_BITS >> wp.uint32(31 - (e & 31))) & (ALL_BITS << wp.uint32(s & 31))
                hit = word & mask
                if hit != wp.uint32(0):
                    if want_t == 0:
                        return 0.0
                    # nearest set bit along the ray
                    b = int(0)
                    first = int(-1)
                    for bb in range(32):
                        b = bb
                        if not forward:
                            b = 31 - bb
                        if first < 0 and (hit & (wp.uint32(1) << wp.uint32(b))) != wp.uint32(0):
                            first = b
                    vox = float((s >> 5) * 32 + first)
                    # distance along the ray from its trimmed start to that voxel's near face
                    w_start = qa[2] + dq[2] * t0
                    dist = vox - w_start
                    if not forward:
                        dist = w_start - (vox + 1.0)
                    return wp.max(dist, 0.0)
    return -1.0


@wp.func
def ray_start(p: wp.vec3, target: wp.vec3, normal: wp.vec3, distant: int, offset: float) -> wp.vec3:
    """``p`` moved ``offset`` along the normal turned toward the light (no normal: unchanged)."""
    dir = target - p
    if distant != 0:
        dir = target
    nn = wp.length(normal)
    if nn > 0.0:
        nrm = normal / nn
        if wp.dot(nrm, dir) < 0.0:
            nrm = -nrm
        return p + nrm * offset
    return p


@wp.func
def start_skip(p: wp.vec3, target: wp.vec3, normal: wp.vec3, distant: int, skip: float, slab: float,
               max_skip: float) -> float:
    """Voxels skipped at the ray's start: ``skip``, or until the ray is ``slab`` voxels above the
    tangent plane of its surface (``slab / sin β``), capped at ``max_skip``."""
    dir = target - p
    if distant != 0:
        dir = target
    nn = wp.length(normal)
    ln = wp.length(dir)
    if nn > 0.0 and ln > 0.0 and slab > 0.0:
        sin_b = wp.abs(wp.dot(normal, dir)) / (nn * ln)
        return wp.max(skip, wp.min(slab / wp.max(sin_b, 1.0e-6), max_skip))
    return skip


@wp.func
def segment_blocked(vs: VoxelScene, o: wp.vec3, e: wp.vec3, skip0: float, skip1: float, seg: int,
                    want_t: int) -> float:
    """Alg. 4: the static array first, then only the moving instances whose bounds the ray meets
    (a BVH over their world boxes), each in its own space; the first hit ends the query.
    Returns the hit distance in voxels of the array that was hit, -1 when free."""
    if vs.static_array >= 0:
        t = array_hit(vs, vs.static_array, wp.transform_point(vs.static_inv, o),
                      wp.transform_point(vs.static_inv, e), skip0, skip1, seg, want_t)
        if t >= 0.0:
            return t
    if vs.n_inst > 0:
        delta = e - o
        ln = wp.length(delta)
        if ln > 0.0:
            query = wp.bvh_query_ray(vs.bvh, o, delta / ln)
            inst = int(0)
            while wp.bvh_query_next(query, inst):
                m = vs.inst_inv[inst]
                t = array_hit(vs, vs.inst_array[inst], wp.transform_point(m, o), wp.transform_point(m, e),
                              skip0, skip1, seg, want_t)
                if t >= 0.0:
                    return t
    return -1.0


@wp.func
def shadow_ray(vs: VoxelScene, rule: RayRule, p: wp.vec3, target: wp.vec3, normal: wp.vec3, distant: int,
               want_t: int) -> float:
    """The shadow ray from surface point ``p`` to a light (position, or for ``distant`` the direction
    toward it), leaving the surface by ``rule``: hit distance in voxels, -1 when free."""
    o = ray_start(p, target, normal, distant, rule.offset)
    e = target
    s1 = rule.end_skip
    if distant != 0:
        e = o + wp.normalize(target) * (wp.length(o - rule.far_center) + rule.far)
        s1 = 0.0
    s0 = start_skip(p, target, normal, distant, rule.skip, rule.slab, rule.max_skip)
    return segment_blocked(vs, o, e, s0, s1, rule.seg, want_t)


@wp.kernel
def query_segments(origins: wp.array(dtype=wp.vec3), targets: wp.array(dtype=wp.vec3),
                   normals: wp.array(dtype=wp.vec3), distant: wp.array(dtype=wp.int32), first: int,
                   rule: RayRule, want_t: int, vs: VoxelScene, hit_voxels: wp.array(dtype=float)):
    """Alg. 2 / 4 for explicit segments ``first + tid``: ``hit_voxels`` gets the distance (voxels) to
    the first occupied voxel (0 for any hit unless ``want_t``), -1 when free."""
    i = first + wp.tid()
    hit_voxels[i] = shadow_ray(vs, rule, origins[i], targets[i], normals[i], distant[i], want_t)
