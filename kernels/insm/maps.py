"""Paper 001 in Warp: per-light shadow maps rasterized from the triangles reconstructed from the
intermediate shadow maps, and the shadow lookups of shading points in them. The intermediate maps
themselves (Embree primary rays) and their triangulation (Alg. 2) are
:mod:`usdml.visibility.insm.mesh` (NumPy); which maps a light gets is :mod:`usdml.visibility.insm.backend`.

Views
    A map is ``S × S`` values seen from one *view*: an origin ``o``, a rotation ``R`` whose rows are the
    view's right, up and forward axes (view space ``q = R (p - o)``, ``q.z`` the depth along forward)
    and a projection ``proj = (ax, bx, ay, by)`` to pixel coordinates: perspective ``(ax q.x / q.z + bx,
    ay q.y / q.z + by)``, orthographic ``(ax q.x + bx, ay q.y + by)``. Pixel ``(i, j)`` covers
    ``[i, i + 1) × [j, j + 1)``; a map holds at pixel ``(i, j)`` (``j · S + i`` of its block of ``S²``)
    the *nearness* of the nearest triangle covering the pixel's centre: ``1 / z`` in perspective,
    ``-z`` orthographic (nearer is larger), ``-BIG`` where none does. A point light's cube map is six
    perspective views (``+X -X +Y -Y +Z -Z``, 90° each), a spot light's one view of its cone, a distant
    light's one orthographic view over the scene.

Receiver tiles
    Before a light's map is rasterized, every shading point finds where its lookup will read it
    (:func:`locate`) and raises, in each ``TILE × TILE`` tile its four texels fall in, the farthest depth
    compared there (``tile_z``), and its view's farthest (``view_z``). A triangle (or a view) no nearer
    than that is not rasterized there: it could only make a texel nearer than points that are nearer
    still, so no answer changes.

Rasterization
    One thread per (view, triangle), or per triangle over a cube's six faces (``raster_cube``, each face
    first tested against the triangle's box): the triangle is culled against the view's four side
    planes, clipped to ``z >= near`` (perspective), and every pixel centre inside it (edges included, so
    neighbouring triangles leave no crack) takes the larger of its nearness and the texel's. The setup
    is float64 (a corner clipped to a near plane close to the light projects far outside the map);
    the rows are filled over the span where the three barycentrics are >= 0, ``1 / z`` (or ``z``)
    interpolated from the span's start. Deterministic: the maximum does not depend on the order.

Lookup (Alg. 3 with a map in place of the ray)
    A shading point moves ``offset`` map texels along its normal turned toward the light (a texel's
    world size at its depth, ``q.z / ax`` in perspective, ``1 / ax`` orthographic), picks its view (a
    cube's by the dominant axis of ``p - L``) and compares its depth less ``bias`` texels with the four
    texels around it, weighted bilinearly (2 × 2 percentage-closer filtering): blocked when more than
    half of the weight is nearer. A point outside every view (beyond a spot light's cone, where it is
    unlit anyway) is not blocked.

Grades (``REFINE``)
    :func:`lookup_points` with ``levels`` > 0 also grades each answer by the Warp path's rule
    (:mod:`usdml.visibility.insm.backend`, "Refinement"): silhouettes (:func:`edge_between`) within a fixed
    footprint per level, a seam, the bias band; the compiled maps (``kernels/insm/insmr.c``) grade by the full
    rule, whose reach follows the occluder's depth and sample spacing.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "optimization_level": 3, "fast_math": False})

BIG = wp.constant(1.0e30)
#: texels per side of a receiver tile
TILE = wp.constant(16)
PERSPECTIVE = wp.constant(0)
ORTHOGRAPHIC = wp.constant(1)


@wp.func
def edge_fn(ax: wp.float64, ay: wp.float64, bx: wp.float64, by: wp.float64, px: wp.float64,
            py: wp.float64) -> wp.float64:
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@wp.func
def screen(q: wp.vec3, a: float, b: float, axis: int, kind: int) -> wp.float64:
    """Pixel coordinate of view-space ``q`` along ``axis`` (float64: a corner clipped to a near plane
    close to the light projects far outside the map, where float32 edge functions lose the pixel)."""
    x = wp.float64(q[axis])
    if kind == PERSPECTIVE:
        x = x / wp.float64(q[2])
    return wp.float64(a) * x + wp.float64(b)


@wp.func
def span_edge(a: wp.float64, g: wp.float64, lo: wp.float64, hi: wp.float64):
    """``[lo, hi]`` narrowed to where ``a x + g >= 0``."""
    zero = wp.float64(0.0)
    if a > zero:
        lo = wp.max(lo, -g / a)
    elif a < zero:
        hi = wp.min(hi, -g / a)
    elif g < zero:
        hi = lo - wp.float64(1.0)
    return lo, hi


@wp.func
def raster_triangle(q0: wp.vec3, q1: wp.vec3, q2: wp.vec3, proj: wp.vec4, kind: int, size: int, base: int,
                    atomic: int, depth: wp.array(dtype=float), tile_base: int, tiles: int,
                    tile_z: wp.array(dtype=float)):
    """Rasterize one view-space triangle (perspective: every ``z >= near``) into ``depth[base:]``, in
    the receiver tiles ``tile_z[tile_base:]`` (``tiles`` per side) whose farthest compared depth is
    beyond the triangle's nearest corner."""
    x0 = screen(q0, proj[0], proj[1], 0, kind)
    y0 = screen(q0, proj[2], proj[3], 1, kind)
    x1 = screen(q1, proj[0], proj[1], 0, kind)
    y1 = screen(q1, proj[2], proj[3], 1, kind)
    x2 = screen(q2, proj[0], proj[1], 0, kind)
    y2 = screen(q2, proj[2], proj[3], 1, kind)
    one = wp.float64(1.0)
    w0 = wp.float64(q0[2])
    w1 = wp.float64(q1[2])
    w2 = wp.float64(q2[2])
    if kind == PERSPECTIVE:
        w0 = one / w0
        w1 = one / w1
        w2 = one / w2
    area = edge_fn(x0, y0, x1, y1, x2, y2)
    if area == wp.float64(0.0):
        return
    inv_area = one / area
    fs = wp.float64(float(size))
    zero = wp.float64(0.0)
    half = wp.float64(0.5)
    lo_x = wp.max(wp.min(wp.min(x0, x1), x2), zero)
    hi_x = wp.min(wp.max(wp.max(x0, x1), x2), fs)
    lo_y = wp.max(wp.min(wp.min(y0, y1), y2), zero)
    hi_y = wp.min(wp.max(wp.max(y0, y1), y2), fs)
    if lo_x > hi_x or lo_y > hi_y:
        return
    j0 = int(wp.ceil(lo_y - half))
    j1 = wp.min(int(wp.floor(hi_y - half)), size - 1)
    zmin = wp.min(wp.min(q0[2], q1[2]), q2[2])
    # no receiver tile under the box wants it: done before any setup
    bx0 = wp.max(int(wp.ceil(lo_x - half)), 0) // TILE
    bx1 = wp.max(wp.min(int(wp.floor(hi_x - half)), size - 1), 0) // TILE
    wanted = int(0)
    for ty in range(wp.max(j0, 0) // TILE, wp.max(j1, 0) // TILE + 1):
        for tx in range(bx0, bx1 + 1):
            if tile_z[tile_base + ty * tiles + tx] > zmin:
                wanted = 1
    if wanted == 0:
        return
    # barycentric l_k = e_k / area is affine in the pixel: l_k = ak px + bk py + ck; per row, the span
    # where all three are >= 0 is solved for, and 1 / z (or z) steps along it
    a0 = (y1 - y2) * inv_area
    b0 = (x2 - x1) * inv_area
    c0 = (x1 * y2 - x2 * y1) * inv_area
    a1 = (y2 - y0) * inv_area
    b1 = (x0 - x2) * inv_area
    c1 = (x2 * y0 - x0 * y2) * inv_area
    a2 = (y0 - y1) * inv_area
    b2 = (x1 - x0) * inv_area
    c2 = (x0 * y1 - x1 * y0) * inv_area
    dw = a0 * w0 + a1 * w1 + a2 * w2
    for j in range(j0, j1 + 1):
        py = wp.float64(float(j)) + half
        g0 = b0 * py + c0
        g1 = b1 * py + c1
        g2 = b2 * py + c2
        lo = lo_x
        hi = hi_x
        lo, hi = span_edge(a0, g0, lo, hi)
        lo, hi = span_edge(a1, g1, lo, hi)
        lo, hi = span_edge(a2, g2, lo, hi)
        i0 = int(wp.ceil(lo - half))
        i1 = wp.min(int(wp.floor(hi - half)), size - 1)
        if i0 > i1:
            continue
        px = wp.float64(float(i0)) + half
        w_start = (a0 * px + g0) * w0 + (a1 * px + g1) * w1 + (a2 * px + g2) * w2
        row = base + j * size
        tile_row = tile_base + (j // TILE) * tiles
        for tx in range(i0 // TILE, i1 // TILE + 1):
            if tile_z[tile_row + tx] <= zmin:
                continue                   # no lookup there compares a depth beyond the triangle
            s0 = wp.max(i0, tx * TILE)
            s1 = wp.min(i1, tx * TILE + TILE - 1)
            for i in range(s0, s1 + 1):
                # each texel's value from the span's start, as kernels/insm/insmr.c computes it
                key = float(w_start + dw * wp.float64(float(i - i0)))     # 1 / z: nearer is larger
                if kind != PERSPECTIVE:
                    key = -key              # orthographic: -z
                if atomic != 0:
                    wp.atomic_max(depth, row + i, key)
                elif key > depth[row + i]:
                    depth[row + i] = key


@wp.func
def clip_point(a: wp.vec3, b: wp.vec3, near: float) -> wp.vec3:
    """Where the segment ``a b`` (``a.z >= near > b.z``) crosses ``z = near``."""
    s = (a[2] - near) / (a[2] - b[2])
    p = a + (b - a) * s
    return wp.vec3(p[0], p[1], near)


@wp.func
def outside(q: wp.vec3, a: float, b: float, size: float, axis: int, kind: int) -> int:
    """Which side planes of a view ``q`` is beyond along ``axis`` (bit 1: pixel < 0, bit 2: > size)."""
    z = 1.0
    if kind == PERSPECTIVE:
        z = q[2]
    s = a * q[axis] + b * z
    bits = 0
    if s < 0.0:
        bits = 1
    if s > size * z:
        bits = bits | 2
    return bits


@wp.kernel
def raster_views(tris: wp.array(dtype=wp.vec3), view_origin: wp.array(dtype=wp.vec3),
                 view_rot: wp.array(dtype=wp.mat33), view_proj: wp.array(dtype=wp.vec4),
                 view_kind: wp.array(dtype=wp.int32), view_near: wp.array(dtype=float), first_view: int,
                 size: int, atomic: int, depth: wp.array(dtype=float), tiles: int,
                 tile_z: wp.array(dtype=float), view_z: wp.array(dtype=float)):
    """Thread (v, t): triangle ``t`` (corners ``tris[3t:3t+3]``, world) into view ``first_view + v``,
    whose map is ``depth[v S² : (v + 1) S²]``. ``atomic``: threads may share a map (CUDA); 0 where
    a launch runs on one thread (Warp's CPU), which a plain compare-and-store makes faster."""
    v, t = wp.tid()
    view = first_view + v
    o = view_origin[view]
    r = view_rot[view]
    proj = view_proj[view]
    kind = view_kind[view]
    near = view_near[view]
    q0 = r * (tris[3 * t] - o)
    q1 = r * (tris[3 * t + 1] - o)
    q2 = r * (tris[3 * t + 2] - o)
    if wp.min(wp.min(q0[2], q1[2]), q2[2]) >= view_z[v]:
        return
    view_triangle(q0, q1, q2, proj, kind, near, size, v * size * size, atomic, depth, v * tiles * tiles, tiles,
                  tile_z)


@wp.func
def view_triangle(q0: wp.vec3, q1: wp.vec3, q2: wp.vec3, proj: wp.vec4, kind: int, near: float, size: int,
                  base: int, atomic: int, depth: wp.array(dtype=float), tile_base: int, tiles: int,
                  tile_z: wp.array(dtype=float)):
    """One view-space triangle into one view: side-plane cull, near clip (perspective), raster."""
    fs = float(size)
    # all three corners beyond one side plane: the triangle misses the view
    cx = outside(q0, proj[0], proj[1], fs, 0, kind) & outside(q1, proj[0], proj[1], fs, 0, kind) & \
        outside(q2, proj[0], proj[1], fs, 0, kind)
    cy = outside(q0, proj[2], proj[3], fs, 1, kind) & outside(q1, proj[2], proj[3], fs, 1, kind) & \
        outside(q2, proj[2], proj[3], fs, 1, kind)
    if cx != 0 or cy != 0:
        return
    if kind == ORTHOGRAPHIC:
        raster_triangle(q0, q1, q2, proj, kind, size, base, atomic, depth, tile_base, tiles, tile_z)
        return
    m = wp.matrix_from_rows(q0, q1, q2)
    front = 0
    ahead = 0
    for k in range(3):
        if m[k][2] >= near:
            front += 1
            ahead = ahead | (1 << k)
    if front == 3:
        raster_triangle(q0, q1, q2, proj, kind, size, base, atomic, depth, tile_base, tiles, tile_z)
    elif front == 1:
        k = 0
        if ahead == 2:
            k = 1
        elif ahead == 4:
            k = 2
        a = m[k]
        b = m[(k + 1) % 3]
        c = m[(k + 2) % 3]
        raster_triangle(a, clip_point(a, b, near), clip_point(a, c, near), proj, kind, size, base, atomic, depth, tile_base, tiles, tile_z)
    elif front == 2:
        k = 0                     # the corner behind
        if ahead == 5:
            k = 1
        elif ahead == 3:
            k = 2
        c = m[k]
        a = m[(k + 1) % 3]
        b = m[(k + 2) % 3]
        bc = clip_point(b, c, near)
        ac = clip_point(a, c, near)
        raster_triangle(a, b, bc, proj, kind, size, base, atomic, depth, tile_base, tiles, tile_z)
        raster_triangle(a, bc, ac, proj, kind, size, base, atomic, depth, tile_base, tiles, tile_z)


@wp.func
def nearest_abs(lo: float, hi: float) -> float:
    """The smallest ``|x|`` over ``[lo, hi]``."""
    if lo <= 0.0 and hi >= 0.0:
        return 0.0
    return wp.min(wp.abs(lo), wp.abs(hi))


@wp.kernel
def raster_cube(tris: wp.array(dtype=wp.vec3), light: wp.vec3, view_rot: wp.array(dtype=wp.mat33),
                view_proj: wp.array(dtype=wp.vec4), view_near: wp.array(dtype=float), first_view: int, size: int,
                atomic: int, depth: wp.array(dtype=float), tiles: int, tile_z: wp.array(dtype=float),
                view_z: wp.array(dtype=float)):
    """Thread t: triangle ``t`` into the six views of the cube map at ``light`` (views ``first_view`` ..
    ``+ 5``, in the order +X -X +Y -Y +Z -Z): what :func:`raster_views` does over them, with each face
    first tested against the box of the triangle's corners (a face the box misses is never
    transformed; the faces left are rasterized the same), so a triangle costs about the one or two
    faces it falls in."""
    t = wp.tid()
    d0 = tris[3 * t] - light
    d1 = tris[3 * t + 1] - light
    d2 = tris[3 * t + 2] - light
    lo = wp.min(wp.min(d0, d1), d2)
    hi = wp.max(wp.max(d0, d1), d2)
    for face in range(6):
        axis = face // 2
        u = (axis + 1) % 3
        v = (axis + 2) % 3
        # the furthest the box reaches along the face's axis, against the least it must reach there:
        # a point of the face's frustum has |x_u| <= x_axis and |x_v| <= x_axis
        reach = hi[axis]
        if face % 2 == 1:
            reach = -lo[axis]
        need = wp.max(nearest_abs(lo[u], hi[u]), nearest_abs(lo[v], hi[v]))
        if reach <= 0.0 or reach < need:
            continue
        # the nearest the box comes along the face's axis, against the farthest depth a lookup compares
        nearest = lo[axis]
        if face % 2 == 1:
            nearest = -hi[axis]
        if nearest >= view_z[face]:
            continue
        view = first_view + face
        r = view_rot[view]
        view_triangle(r * d0, r * d1, r * d2, view_proj[view], PERSPECTIVE, view_near[view], size,
                      face * size * size, atomic, depth, face * tiles * tiles, tiles, tile_z)


@wp.func
def texel_blocked(depth: wp.array(dtype=float), base: int, size: int, i: int, j: int, key: float) -> float:
    ci = wp.clamp(i, 0, size - 1)
    cj = wp.clamp(j, 0, size - 1)
    if depth[base + cj * size + ci] > key:
        return 1.0
    return 0.0


@wp.func
def locate(p: wp.vec3, nrm: wp.vec3, light: int, light_pos: wp.array(dtype=wp.vec3),
           light_cube: wp.array(dtype=wp.int32), light_view: wp.array(dtype=wp.int32),
           view_origin: wp.array(dtype=wp.vec3), view_rot: wp.array(dtype=wp.mat33),
           view_proj: wp.array(dtype=wp.vec4), view_kind: wp.array(dtype=wp.int32),
           view_near: wp.array(dtype=float), first_view: int, size: int, offset: float, bias: float) -> wp.vec4:
    """Where a lookup of ``p`` (normal ``nrm``) reads light ``light``'s map (module doc, "Lookup"):
    ``(local view, x, y, depth compared)``, the view ``-1`` where no view holds it."""
    local = light_view[light] - first_view
    if light_cube[light] != 0:
        d = p - light_pos[light]
        ax = wp.abs(d[0])
        ay = wp.abs(d[1])
        az = wp.abs(d[2])
        face = 0
        if ax >= ay and ax >= az:
            if d[0] < 0.0:
                face = 1
        elif ay >= az:
            face = 2
            if d[1] < 0.0:
                face = 3
        else:
            face = 4
            if d[2] < 0.0:
                face = 5
        local = local + face
    view = first_view + local
    r = view_rot[view]
    proj = view_proj[view]
    kind = view_kind[view]
    q = r * (p - view_origin[view])
    # the normal turned toward the light: toward -forward in view space (perspective: toward the origin)
    toward = wp.vec3(0.0, 0.0, -1.0)
    if kind == PERSPECTIVE:
        toward = -q
    qn = r * nrm
    if wp.dot(qn, toward) < 0.0:
        qn = -qn
    texel = 1.0 / proj[0]
    if kind == PERSPECTIVE:
        texel = q[2] / proj[0]
    q = q + qn * (offset * texel)
    sx = proj[0] * q[0] + proj[1]
    sy = proj[2] * q[1] + proj[3]
    if kind == PERSPECTIVE:
        if q[2] <= view_near[view]:
            return wp.vec4(-1.0, 0.0, 0.0, 0.0)
        sx = proj[0] * q[0] / q[2] + proj[1]
        sy = proj[2] * q[1] / q[2] + proj[3]
    fs = float(size)
    if sx < 0.0 or sy < 0.0 or sx > fs or sy > fs:
        return wp.vec4(-1.0, 0.0, 0.0, 0.0)
    return wp.vec4(float(local), sx, sy, q[2] - bias * texel)


@wp.kernel
def receiver_tiles(points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                   light_pos: wp.array(dtype=wp.vec3), light_cube: wp.array(dtype=wp.int32),
                   light_view: wp.array(dtype=wp.int32), view_origin: wp.array(dtype=wp.vec3),
                   view_rot: wp.array(dtype=wp.mat33), view_proj: wp.array(dtype=wp.vec4),
                   view_kind: wp.array(dtype=wp.int32), view_near: wp.array(dtype=float), first_view: int,
                   size: int, offset: float, bias: float, first_light: int, tiles: int,
                   tile_z: wp.array(dtype=float), view_z: wp.array(dtype=float)):
    """Thread (b, i): the farthest depth point ``i``'s lookup of light ``first_light + b`` compares,
    into each tile of ``TILE²`` texels its four texels fall in (``atomic_max``): the rasterizer skips
    a tile for a triangle no nearer than that (module doc, "Receiver tiles"); the farthest of a view's
    into ``view_z[view]``."""
    b, pi = wp.tid()
    at = locate(points[pi], normals[pi], first_light + b, light_pos, light_cube, light_view, view_origin,
                view_rot, view_proj, view_kind, view_near, first_view, size, offset, bias)
    if at[0] < 0.0:
        return
    local = int(at[0])
    wp.atomic_max(view_z, local, at[3])
    i0 = int(wp.floor(at[1] - 0.5))
    j0 = int(wp.floor(at[2] - 0.5))
    for dj in range(2):
        cj = wp.clamp(j0 + dj, 0, size - 1) // TILE
        for di in range(2):
            ci = wp.clamp(i0 + di, 0, size - 1) // TILE
            wp.atomic_max(tile_z, (local * tiles + cj) * tiles + ci, at[3])


@wp.func
def pcf_blocked(depth: wp.array(dtype=float), base: int, size: int, sx: float, sy: float, z: float) -> wp.uint8:
    """Whether a lookup at pixel ``(sx, sy)`` comparing nearness ``z`` is blocked in the map at ``depth[base:]``:
    the 2 × 2 texels around it weighted bilinearly, more than half nearer (module doc, "Lookup")."""
    fx = sx - 0.5
    fy = sy - 0.5
    i0 = int(wp.floor(fx))
    j0 = int(wp.floor(fy))
    tx = fx - float(i0)
    ty = fy - float(j0)
    f = (1.0 - tx) * (1.0 - ty) * texel_blocked(depth, base, size, i0, j0, z) \
        + tx * (1.0 - ty) * texel_blocked(depth, base, size, i0 + 1, j0, z) \
        + (1.0 - tx) * ty * texel_blocked(depth, base, size, i0, j0 + 1, z) \
        + tx * ty * texel_blocked(depth, base, size, i0 + 1, j0 + 1, z)
    blocked = wp.uint8(0)
    if f > 0.5:
        blocked = wp.uint8(1)
    return blocked


@wp.func
def edge_between(depth: wp.array(dtype=float), base: int, size: int, tile_z: wp.array(dtype=float), tile_base: int,
                 tiles: int, i: int, j: int, key: float, key_far: float, persp: int, a: float, jump: float) -> int:
    """1 where texel ``(i, j)`` of the view at ``depth[base:]`` is a silhouette between a lookup's sides: in front
    of its compared nearness ``key``, with a neighbour not in front of ``key_far`` (the compared depth less
    ``jump`` texels) that lies farther than the plane through the texel and the one opposite by more than
    ``jump`` texels of depth (an empty neighbour: at least its receiver tile's farthest compared depth; one in a
    tile without receivers is no evidence), as ``kernels/insm/insmr.c`` finds them."""
    m = depth[base + j * size + i]
    if m <= key:
        return 0
    for d in range(4):
        di = 0
        dj = 0
        if d == 0:
            di = 1
        elif d == 1:
            di = -1
        elif d == 2:
            dj = 1
        else:
            dj = -1
        ni = i + di
        nj = j + dj
        if ni < 0 or nj < 0 or ni >= size or nj >= size:
            continue
        tzn = tile_z[tile_base + (nj // TILE) * tiles + ni // TILE]
        if tzn <= -0.5 * BIG:
            continue
        mn = depth[base + nj * size + ni]
        if mn >= key_far:
            continue
        bi = i - di
        bj = j - dj
        mb = m
        if bi >= 0 and bj >= 0 and bi < size and bj < size:
            mo = depth[base + bj * size + bi]
            if mo > -0.5 * BIG:
                mb = mo
        pred = 2.0 * m - mb
        step = 0
        if persp != 0:
            if pred > 0.0:
                if mn > -0.5 * BIG:
                    if (pred - mn) * a * m > jump * mn * pred:
                        step = 1
                elif (tzn * pred - 1.0) * a * m > jump * pred:
                    step = 1
        else:
            zn = tzn
            if mn > -0.5 * BIG:
                zn = -mn
            if (zn + pred) * a > jump:
                step = 1
        if step != 0:
            return 1
    return 0


@wp.kernel
def lookup_points(points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                  light_pos: wp.array(dtype=wp.vec3), light_cube: wp.array(dtype=wp.int32),
                  light_view: wp.array(dtype=wp.int32), view_origin: wp.array(dtype=wp.vec3),
                  view_rot: wp.array(dtype=wp.mat33), view_proj: wp.array(dtype=wp.vec4),
                  view_kind: wp.array(dtype=wp.int32), view_near: wp.array(dtype=float), first_view: int,
                  size: int, depth: wp.array(dtype=float), offset: float, bias: float, first_light: int,
                  out: wp.array(dtype=wp.uint8), tiles: int, tile_z: wp.array(dtype=float),
                  footprint: wp.array(dtype=wp.int32), band: wp.array(dtype=float), levels: int, jump: float,
                  grade: wp.array(dtype=wp.uint8)):
    """Thread (b, i): whether point ``i`` is blocked from light ``l = first_light + b`` (its views from
    ``light_view[l]``, a cube when ``light_cube[l]``; ``depth`` holds the maps of views ``first_view``
    on), into ``out[b P + i]``.

    With ``levels`` > 0 (``REFINE``) also the answer's grade into ``grade[b P + i]`` by the Warp path's rule
    (:mod:`usdml.visibility.insm.backend`, "Refinement"): the first level ``k`` (1 ..) whose footprint of
    ``2 footprint[k] × 2 footprint[k]`` texels around the lookup holds a silhouette between its sides
    (:func:`edge_between`), or reaches past the view's side (a seam), or whose ``band[k]`` holds the depth
    of one of its 2 × 2 texels (within that many texels of the compared depth); 0 where none does.
    Outside every view: 1. ``tile_z`` (``tiles`` a side per view) as :func:`receiver_tiles` left it."""
    b, pi = wp.tid()
    n_points = points.shape[0]
    at = locate(points[pi], normals[pi], first_light + b, light_pos, light_cube, light_view, view_origin,
                view_rot, view_proj, view_kind, view_near, first_view, size, offset, bias)
    if at[0] < 0.0:
        out[b * n_points + pi] = wp.uint8(0)
        if levels > 0:
            grade[b * n_points + pi] = wp.uint8(1)
        return
    local = int(at[0])
    sx = at[1]
    sy = at[2]
    z = -at[3]
    persp = int(0)
    if view_kind[first_view + local] == PERSPECTIVE:
        persp = 1
        z = 1.0 / at[3]
    base = local * size * size
    out[b * n_points + pi] = pcf_blocked(depth, base, size, sx, sy, z)
    if levels == 0:
        return
    i0 = int(wp.floor(sx - 0.5))
    j0 = int(wp.floor(sy - 0.5))
    # the depth band: the 2 x 2 texels' depths against the compared one, in texels (perspective: a texel's
    # size at the compared depth)
    a = view_proj[first_view + local][0]
    texel = 1.0 / a
    if persp != 0:
        texel = at[3] / a
    near_band = float(BIG)
    for dj in range(2):
        for di in range(2):
            m = depth[base + wp.clamp(j0 + dj, 0, size - 1) * size + wp.clamp(i0 + di, 0, size - 1)]
            if m > -0.5 * BIG:
                zt = -m
                if persp != 0:
                    zt = 1.0 / m
                near_band = wp.min(near_band, wp.abs(at[3] - zt) / texel)
    # the footprint: ring r of a texel = the least half-width whose 2r x 2r footprint holds it; the least ring
    # with a silhouette between the lookup's sides, and the least past the view's side
    widest = footprint[levels - 1]
    ring_edge = int(1 << 20)
    ring_out = int(1 << 20)
    tile_base = local * tiles * tiles
    key_far = -(at[3] - jump * texel)
    if persp != 0:
        key_far = 1.0 / (at[3] - jump * texel)
    for dj in range(-widest + 1, widest + 1):
        rj = dj
        if dj <= 0:
            rj = 1 - dj
        for di in range(-widest + 1, widest + 1):
            ri = di
            if di <= 0:
                ri = 1 - di
            ring = wp.max(ri, rj)
            ii = i0 + di
            jj = j0 + dj
            if ii < 0 or jj < 0 or ii >= size or jj >= size:
                ring_out = wp.min(ring_out, ring)
            elif ring < ring_edge:
                if edge_between(depth, base, size, tile_z, tile_base, tiles, ii, jj, z, key_far, persp, a, jump) != 0:
                    ring_edge = ring
    need = wp.min(ring_edge, ring_out)
    g = int(0)
    for k in range(levels):
        if g == 0 and (footprint[k] >= need or near_band < band[k]):
            g = k + 1
    grade[b * n_points + pi] = wp.uint8(g)
