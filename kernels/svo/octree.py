"""Paper 003 in Warp: conservative voxelization of triangles into 4³-voxel bricks, and the SVO
restart traversal (Fig. 3) of shadow segments. The octree itself is assembled from the bricks by
``usdml.visibility.svo.tree`` (NumPy); the compiled CPU traversal is ``kernels/svo/svoq.c``.

Grid
    A tree covers ``n³`` voxels (``n = 2^depth``) of a world-space cube with corner ``lo`` and voxel
    size ``h``: voxel ``(x, y, z)`` holds ``lo + [x, x+1) h`` … Kernels take points already in voxel
    units (``q = (p - lo) / h``), so the grid is ``[0, n)³``.

Bricks
    The voxelization writes one bit per voxel into a dense brick grid: brick ``(bx, by, bz) =
    (x, y, z) >> 2`` is two ``uint32`` words at ``2 · ((bz · nb + by) · nb + bx)`` (``nb = n / 4``), bit
    ``(x & 3) + 4 (y & 3) + 16 (z & 3)`` of the 64 (bits 0-31 in the first word).

Tree (``nodes``, ``bricks``)
    Groups of eight child entries, as the paper places them: ``nodes[8 g + octant]`` with ``octant =
    xbit + 2 ybit + 4 zbit``. Group 0 holds the root's children (level 1, each ``n / 2`` voxels wide);
    an entry at levels ``1 … depth - 3`` is the index of its node's child group (0: empty), an entry
    at level ``depth - 2`` (a 4³ brick) is its brick's index + 1 in ``bricks`` (0: empty), two words
    per brick as above. The last two levels of the octree (2³ and single voxels) are the brick's
    bits: a brick's octant is empty when its eight bits are.

Traversal (Fig. 3, restart)
    The segment is clipped to the grid; from its entry point the descent finds the deepest node that
    holds it: an occupied voxel ends the query (hit), an empty node of any level is left through its
    far face, and the next descent starts from the root again at the voxel across that face. Instead
    of the paper's ``t + ε`` the step names that voxel in integers (the exit axis one cell on, the
    other two the cells the ray is in at the exit, kept inside the node left), so the march always
    advances and never skips a voxel the ray's line enters through a face.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "optimization_level": 3, "fast_math": False})

BIG = wp.constant(1.0e30)


@wp.func
def tri_box_overlap(c: wp.vec3, half: float, a: wp.vec3, b: wp.vec3, d: wp.vec3, nrm: wp.vec3) -> int:
    """Whether the triangle ``a b d`` (normal ``nrm``) touches the cube ``c ± half`` (separating
    axes, Akenine-Möller: the nine crosses of an edge with a box axis, then the plane; the cube's
    own three axes are the caller's range)."""
    v0 = a - c
    v1 = b - c
    v2 = d - c
    for ei in range(3):
        e = v1 - v0
        if ei == 1:
            e = v2 - v1
        elif ei == 2:
            e = v0 - v2
        for k in range(3):
            # the axis (box axis k) x e has components -e[j] at i and e[i] at j
            i = (k + 1) % 3
            j = (k + 2) % 3
            p0 = e[i] * v0[j] - e[j] * v0[i]
            p1 = e[i] * v1[j] - e[j] * v1[i]
            p2 = e[i] * v2[j] - e[j] * v2[i]
            rad = half * (wp.abs(e[i]) + wp.abs(e[j]))
            if wp.min(p0, wp.min(p1, p2)) > rad or wp.max(p0, wp.max(p1, p2)) < -rad:
                return 0
    # the plane: the box's extent along the normal must reach it
    r = half * (wp.abs(nrm[0]) + wp.abs(nrm[1]) + wp.abs(nrm[2]))
    s = wp.dot(nrm, v0)
    if s > r or s < -r:
        return 0
    return 1


@wp.func
def set_voxel(out: wp.array(dtype=wp.uint32), x: int, y: int, z: int, nb: int, atomic: int):
    """Set voxel ``(x, y, z)``'s bit in the brick grid (module doc)."""
    brick = ((z >> 2) * nb + (y >> 2)) * nb + (x >> 2)
    bit = (x & 3) + 4 * (y & 3) + 16 * (z & 3)
    w = 2 * brick + (bit >> 5)
    m = wp.uint32(1) << wp.uint32(bit & 31)
    if atomic == 0:
        out[w] = out[w] | m
    else:
        wp.atomic_or(out, w, m)


@wp.kernel
def voxelize(points: wp.array(dtype=wp.vec3), tris: wp.array(dtype=wp.vec3i), first: int, lo: wp.vec3,
             inv_h: float, n: int, slack: float, atomic: int, out: wp.array(dtype=wp.uint32)):
    """Conservative voxelization of triangle ``first + tid``: every voxel of ``[0, n)³`` whose cube,
    grown by ``slack`` voxels (float rounding), the triangle touches. Columns along the normal's
    dominant axis: in each column only the voxels between the plane's heights at the column's
    corners are tested, so a triangle costs about its area in voxels, not its box's volume."""
    t = tris[first + wp.tid()]
    a = (points[t[0]] - lo) * inv_h
    b = (points[t[1]] - lo) * inv_h
    c = (points[t[2]] - lo) * inv_h
    nrm = wp.cross(b - a, c - a)
    ln = wp.length(nrm)
    if ln <= 0.0:
        return
    nrm = nrm / ln
    tlo = wp.min(a, wp.min(b, c))
    thi = wp.max(a, wp.max(b, c))
    # dominant axis k; the column axes i, j
    k = int(2)
    if wp.abs(nrm[0]) >= wp.abs(nrm[1]) and wp.abs(nrm[0]) >= wp.abs(nrm[2]):
        k = 0
    elif wp.abs(nrm[1]) >= wp.abs(nrm[2]):
        k = 1
    i = (k + 1) % 3
    j = (k + 2) % 3
    half = 0.5 + slack
    i0 = wp.max(int(wp.floor(tlo[i] - slack)), 0)
    i1 = wp.min(int(wp.floor(thi[i] + slack)), n - 1)
    j0 = wp.max(int(wp.floor(tlo[j] - slack)), 0)
    j1 = wp.min(int(wp.floor(thi[j] + slack)), n - 1)
    k_lo = wp.max(int(wp.floor(tlo[k] - slack)), 0)
    k_hi = wp.min(int(wp.floor(thi[k] + slack)), n - 1)
    if i0 > i1 or j0 > j1 or k_lo > k_hi:
        return
    nb = n >> 2
    d = wp.dot(nrm, a)
    inv_nk = 1.0 / nrm[k]
    for ci in range(i0, i1 + 1):
        for cj in range(j0, j1 + 1):
            # the plane's heights along k over the column's (grown) square
            ua = float(ci) - slack
            ub = float(ci) + 1.0 + slack
            va = float(cj) - slack
            vb = float(cj) + 1.0 + slack
            h00 = (d - nrm[i] * ua - nrm[j] * va) * inv_nk
            h01 = (d - nrm[i] * ua - nrm[j] * vb) * inv_nk
            h10 = (d - nrm[i] * ub - nrm[j] * va) * inv_nk
            h11 = (d - nrm[i] * ub - nrm[j] * vb) * inv_nk
            hmin = wp.min(wp.min(h00, h01), wp.min(h10, h11))
            hmax = wp.max(wp.max(h00, h01), wp.max(h10, h11))
            c0 = wp.max(int(wp.floor(hmin - slack)), k_lo)
            c1 = wp.min(int(wp.floor(hmax + slack)), k_hi)
            for ck in range(c0, c1 + 1):
                v = wp.vec3(0.0, 0.0, 0.0)
                v[i] = float(ci) + 0.5
                v[j] = float(cj) + 0.5
                v[k] = float(ck) + 0.5
                if tri_box_overlap(v, half, a, b, c, nrm) == 1:
                    x = ci
                    y = cj
                    z = ck
                    if k == 0:
                        x = ck
                        y = ci
                        z = cj
                    elif k == 1:
                        x = cj
                        y = ck
                        z = ci
                    else:
                        x = ci
                        y = cj
                        z = ck
                    set_voxel(out, x, y, z, nb, atomic)


@wp.struct
class SvoScene:
    """Every tree of the scene (static, per-frame): ``tree_lo[t]``, ``tree_inv_h[t]`` (1 / voxel
    size), ``tree_int[t] = (depth, node_base, brick_base, 0)``; ``nodes`` and ``bricks`` of all trees
    concatenated (module doc; a tree's entries are relative to its bases)."""

    nodes: wp.array(dtype=wp.int32)
    bricks: wp.array(dtype=wp.uint32)
    tree_lo: wp.array(dtype=wp.vec3)
    tree_inv_h: wp.array(dtype=float)
    tree_int: wp.array(dtype=wp.vec4i)
    n_trees: int


@wp.struct
class SvoRule:
    """Leaving the surface and shrinking the segment (``usdml.visibility.svo.backend``), in world units:
    ``offset`` along the normal, ``skip`` / ``slab`` / ``max_skip`` at the start, ``end_skip`` before
    the light; distant rays end ``far`` beyond the scene sphere's centre."""

    offset: float
    skip: float
    slab: float
    max_skip: float
    end_skip: float
    far: float
    far_center: wp.vec3


@wp.func
def brick_octant_mask(octant: int, word: int) -> wp.uint32:
    """The bits of a brick's 2³ octant ``octant`` that lie in its word ``word`` (0: z < 2, 1: z >= 2)."""
    # bits of the octant's 8 voxels: (x&3) + 4 (y&3) + 16 (z&3) with x, y, z in the octant's half
    base = wp.uint32(0x33)          # x in {0,1}, y in {0,1} at z = 0: bits 0,1,4,5
    sx = wp.uint32((octant & 1) * 2)
    sy = wp.uint32(((octant >> 1) & 1) * 8)
    m = (base << (sx + sy)) | (base << (sx + sy + wp.uint32(16)))
    if ((octant >> 2) & 1) == word:
        return m
    return wp.uint32(0)


@wp.func
def tree_hit(vs: SvoScene, tr: int, o: wp.vec3, e: wp.vec3, skip0: float, skip1: float, to_infinity: int) -> float:
    """The restart traversal (module doc) of tree ``tr`` along world segment ``o → e`` without its
    first ``skip0`` and last ``skip1`` world units (``to_infinity``: no end): the distance in voxels
    from ``o`` to the first occupied voxel, -1 when free."""
    ti = vs.tree_int[tr]
    depth = ti[0]
    node_base = ti[1]
    brick_base = ti[2]
    n = 1 << depth
    inv_h = vs.tree_inv_h[tr]
    lo = vs.tree_lo[tr]
    q = (o - lo) * inv_h
    qe = (e - lo) * inv_h
    dv = qe - q
    length = wp.length(dv)
    if length <= 0.0:
        return -1.0
    dir = dv / length
    ta = skip0 * inv_h
    tb = length - skip1 * inv_h
    if to_infinity != 0:
        tb = BIG
    fn = float(n)
    inv = wp.vec3(BIG, BIG, BIG)
    for ax in range(3):
        if dir[ax] != 0.0:
            inv[ax] = 1.0 / dir[ax]
            t0 = (0.0 - q[ax]) * inv[ax]
            t1 = (fn - q[ax]) * inv[ax]
            ta = wp.max(ta, wp.min(t0, t1))
            tb = wp.min(tb, wp.max(t0, t1))
        elif q[ax] < 0.0 or q[ax] >= fn:
            return -1.0
    if ta >= tb:
        return -1.0
    p = q + dir * ta
    c = wp.vec3i(wp.clamp(int(wp.floor(p[0])), 0, n - 1), wp.clamp(int(wp.floor(p[1])), 0, n - 1),
                 wp.clamp(int(wp.floor(p[2])), 0, n - 1))
    t = ta
    for _guard in range(1 << 20):
        # descend from the root to the deepest node holding voxel c
        size = int(1)
        g = int(0)
        hit = int(0)
        for level in range(1, depth - 1):
            shift = depth - level
            octant = ((c[0] >> shift) & 1) | (((c[1] >> shift) & 1) << 1) | (((c[2] >> shift) & 1) << 2)
            entry = vs.nodes[node_base + 8 * g + octant]
            if entry == 0:
                size = 1 << shift
                break
            if level < depth - 2:
                g = entry
            else:
                bw = 2 * (brick_base + entry - 1)
                sub = ((c[0] >> 1) & 1) | (((c[1] >> 1) & 1) << 1) | (((c[2] >> 1) & 1) << 2)
                wsub = (sub >> 2) & 1
                if (vs.bricks[bw + wsub] & brick_octant_mask(sub, wsub)) == wp.uint32(0):
                    size = 2
                else:
                    bit = (c[0] & 3) + 4 * (c[1] & 3) + 16 * (c[2] & 3)
                    if ((vs.bricks[bw + (bit >> 5)] >> wp.uint32(bit & 31)) & wp.uint32(1)) != wp.uint32(0):
                        hit = 1
                    size = 1
        if hit == 1:
            return t
        # leave the empty node (origin c & ~(size - 1)) through its far face
        m = ~(size - 1)
        cx = c[0] & m
        cy = c[1] & m
        cz = c[2] & m
        fx = float(cx)
        fy = float(cy)
        fz = float(cz)
        if dir[0] > 0.0:
            fx = float(cx + size)
        if dir[1] > 0.0:
            fy = float(cy + size)
        if dir[2] > 0.0:
            fz = float(cz + size)
        tx = BIG
        ty = BIG
        tz = BIG
        if dir[0] != 0.0:
            tx = (fx - q[0]) * inv[0]
        if dir[1] != 0.0:
            ty = (fy - q[1]) * inv[1]
        if dir[2] != 0.0:
            tz = (fz - q[2]) * inv[2]
        t_exit = wp.min(tx, wp.min(ty, tz))
        if t_exit >= tb:
            return -1.0
        t = wp.max(t, t_exit)
        pe = q + dir * t_exit
        nx = wp.clamp(int(wp.floor(pe[0])), cx, cx + size - 1)
        ny = wp.clamp(int(wp.floor(pe[1])), cy, cy + size - 1)
        nz = wp.clamp(int(wp.floor(pe[2])), cz, cz + size - 1)
        if tx <= ty and tx <= tz:
            nx = cx - 1
            if dir[0] > 0.0:
                nx = cx + size
        elif ty <= tz:
            ny = cy - 1
            if dir[1] > 0.0:
                ny = cy + size
        else:
            nz = cz - 1
            if dir[2] > 0.0:
                nz = cz + size
        if nx < 0 or nx >= n or ny < 0 or ny >= n or nz < 0 or nz >= n:
            return -1.0
        c = wp.vec3i(nx, ny, nz)
    return -1.0


@wp.func
def shadow_segment(vs: SvoScene, rule: SvoRule, p: wp.vec3, target: wp.vec3, normal: wp.vec3, distant: int) -> float:
    """The shadow ray from surface point ``p`` to a light (position, or for ``distant`` the direction
    toward it), leaving the surface by ``rule``: the hit distance in voxels of the first tree hit
    (static first), -1 when free."""
    dir = target - p
    if distant != 0:
        dir = target
    ln = wp.length(dir)
    if ln <= 0.0:
        return -1.0
    o = p
    skip0 = rule.skip
    nn = wp.length(normal)
    if nn > 0.0:
        nrm = normal / nn
        cos_b = wp.dot(nrm, dir) / ln
        if cos_b < 0.0:
            nrm = -nrm
            cos_b = -cos_b
        o = p + nrm * rule.offset
        if rule.slab > 0.0:
            skip0 = wp.max(rule.skip, wp.min(rule.slab / wp.max(cos_b, 1.0e-6), rule.max_skip))
    e = target
    skip1 = rule.end_skip
    inf = int(0)
    if distant != 0:
        e = o + (dir / ln) * (wp.length(o - rule.far_center) + rule.far)
        skip1 = 0.0
        inf = 1
    for tr in range(vs.n_trees):
        t = tree_hit(vs, tr, o, e, skip0, skip1, inf)
        if t >= 0.0:
            return t
    return -1.0


@wp.kernel
def query_segments(origins: wp.array(dtype=wp.vec3), targets: wp.array(dtype=wp.vec3),
                   normals: wp.array(dtype=wp.vec3), distant: wp.array(dtype=wp.int32), first: int,
                   rule: SvoRule, vs: SvoScene, hit_voxels: wp.array(dtype=float)):
    """Segments ``first + tid``: ``hit_voxels`` gets the distance (voxels of the tree hit) from the
    ray's offset start to the first occupied voxel, -1 when free."""
    i = first + wp.tid()
    hit_voxels[i] = shadow_segment(vs, rule, origins[i], targets[i], normals[i], distant[i])
