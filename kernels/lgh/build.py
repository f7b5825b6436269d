"""Warp kernels: lighting grid hierarchy construction (paper 004 §3.1).

S1 is built by *scatter* (every input light adds to its 8 surrounding grid vertices with trilinear
weights, atomically), every coarser level by *gather* from the S1 grid lights (one thread per
level-l vertex, no atomics), then each level is stream-compacted and finalized.

A grid is stored densely, x-major: vertex ``(i, j, k)`` of a grid with ``dims = (nx, ny, nz)`` has flat
index ``(i * ny + j) * nz + k``; vertex ``(i, j, k)`` sits at ``(i, j, k) * h`` relative to the grid
origin. Each vertex holds one :data:`acc8` (32 bytes, so a corner update touches one cache line),
every term weighted by the trilinear weight ``w``:

* ``[0:3]`` Σ w·I                   RGB intensity
* ``[3]``   Σ w·lum(I)              luminance weight
* ``[4:7]`` Σ w·lum(I)·(p − x_v)    first moment, about the vertex position x_v
* ``[7]``   Σ w·lum(I)·|p − x_v|²   second moment, about x_v

Moments are taken about the vertex (not the origin) so that the variance E|p|² − |E p|² does not
cancel catastrophically in float32 far from the origin. Beside it, a ``vec3`` per vertex holds the
emission lobe's moment Σ w·lum(I)·n of lights that carry a unit normal n (VPLs, cosine emitters; zero
for isotropic lights): divided by Σ w·lum it is the grid light's mean normal ν, |ν| ≤ 1, from which
:mod:`usdml.kernels.lgh.shading` shapes its emission. Pure compute: arrays in, arrays out.
"""

import warp as wp

# forward only: nothing here is differentiated, and the adjoint code was most of the compile
# (cold cache, this CPU: 1.4 -> 0.5 s for CPU, 1.1 -> 0.4 s for CUDA)
wp.set_module_options({"enable_backward": False})

#: Rec. 709 luminance
LUMA = wp.constant(wp.vec3(0.2126, 0.7152, 0.0722))


class acc8(wp.types.vector(length=8, dtype=wp.float32)):
    """Per-vertex accumulator (module doc)."""


@wp.func
def pack(i: wp.vec3, m0: float, m1: wp.vec3, m2: float):
    return acc8(i[0], i[1], i[2], m0, m1[0], m1[1], m1[2], m2)


@wp.func
def cell_and_fraction(g: float, n: int):
    """Lower vertex of the cell holding grid coordinate ``g`` (axis of ``n`` vertices), and ``g``'s fraction in it."""
    # n >= 2 always (a grid has at least one cell per axis); a light on the far face lands in the last cell
    i = wp.clamp(int(wp.floor(g)), 0, n - 2)
    f = wp.clamp(g - float(i), 0.0, 1.0)
    return i, f


@wp.func
def grid_cell(g: wp.vec3, dims: wp.vec3i):
    """Lower vertex of the cell holding grid point ``g`` (grid units), and ``g``'s fractions in it."""
    i, fx = cell_and_fraction(g[0], dims[0])
    j, fy = cell_and_fraction(g[1], dims[1])
    k, fz = cell_and_fraction(g[2], dims[2])
    return wp.vec3i(i, j, k), wp.vec3(fx, fy, fz)


@wp.func
def corner(c: int) -> wp.vec3i:
    """Offset in {0, 1}³ of cell corner ``c`` in 0..7."""
    return wp.vec3i(c >> 2, (c >> 1) & 1, c & 1)


@wp.func
def flat_index(i: int, j: int, k: int, dims: wp.vec3i) -> int:
    return (i * dims[1] + j) * dims[2] + k


@wp.func
def hat(t: float) -> float:
    """1D trilinear (tent) weight of a point ``t`` grid cells away from a vertex."""
    return wp.max(1.0 - wp.abs(t), 0.0)


@wp.func
def corner_weight(d: wp.vec3i, f: wp.vec3) -> float:
    """Trilinear weight of cell corner ``d`` in {0, 1}³ at fractions ``f``."""
    wx = wp.where(d[0] == 1, f[0], 1.0 - f[0])
    wy = wp.where(d[1] == 1, f[1], 1.0 - f[1])
    wz = wp.where(d[2] == 1, f[2], 1.0 - f[2])
    return wx * wy * wz


@wp.kernel
def scatter_s1(
    position: wp.array(dtype=wp.vec3),   # (N,) light positions relative to the grid origin, scene units
    intensity: wp.array(dtype=wp.vec3),  # (N,) RGB radiant intensity
    normal: wp.array(dtype=wp.vec3),     # (N,) unit emission normals, or (1,) unused when has_normal is 0
    has_normal: int,
    h: float,                            # S1 spacing h_1
    dims: wp.vec3i,                      # S1 vertices per axis
    acc: wp.array(dtype=acc8),           # (V,) out, accumulated
    lobe: wp.array(dtype=wp.vec4),       # (V,) out, accumulated (Σ w lum n, Σ w): lobe moment, light count
):
    t = wp.tid()
    I = intensity[t]
    lum = wp.dot(I, LUMA)
    if lum <= 0.0:
        return
    p = position[t]
    cell, f = grid_cell(p / h, dims)
    for c in range(8):
        d = corner(c)
        w = corner_weight(d, f)
        # a light exactly on a vertex (or face) adds nothing to the other corners: they stay empty
        if w > 0.0:
            v = cell + d
            e = p - wp.vec3(float(v[0]), float(v[1]), float(v[2])) * h
            wl = w * lum
            idx = flat_index(v[0], v[1], v[2], dims)
            wp.atomic_add(acc, idx, pack(w * I, wl, wl * e, wl * wp.dot(e, e)))
            nl = wp.vec3(0.0, 0.0, 0.0)
            if has_normal != 0:
                nl = wl * normal[t]
            wp.atomic_add(lobe, idx, wp.vec4(nl[0], nl[1], nl[2], w))


@wp.kernel
def mark_s1(
    position: wp.array(dtype=wp.vec3),   # (N,) light positions relative to the grid origin
    intensity: wp.array(dtype=wp.vec3),  # (N,) RGB intensity (lights with zero luminance mark nothing)
    h: float,
    dims: wp.vec3i,
    flags: wp.array(dtype=wp.uint8),     # (V,) out: 1 where scatter_s1 would add a non-zero weight
):
    """Which S1 vertices are non-empty, without accumulating (the level-count rule, paper 004 §4.3)."""
    t = wp.tid()
    if wp.dot(intensity[t], LUMA) <= 0.0:
        return
    cell, f = grid_cell(position[t] / h, dims)
    for c in range(8):
        d = corner(c)
        if corner_weight(d, f) > 0.0:
            v = cell + d
            # every writer stores the same value: a benign race, no atomic needed
            flags[flat_index(v[0], v[1], v[2], dims)] = wp.uint8(1)


@wp.kernel
def s1_grid_lights(
    acc: wp.array(dtype=acc8),           # (V1,) S1 accumulators, moments about each vertex
    h: float,
    dims: wp.vec3i,
    lights: wp.array(dtype=acc8),        # (V1,) out: [I, Σw lum, centre (grid-origin relative), Σw lum |p − centre|²]
):
    """S1 grid lights as point clusters, the input of gather_level: the centre is taken once here rather
    than once per level-l vertex that sees it."""
    v = wp.tid()
    a = acc[v]
    w0 = a[3]
    if w0 <= 0.0:
        lights[v] = acc8()
        return
    i = v / (dims[1] * dims[2])
    j = (v / dims[2]) % dims[1]
    k = v % dims[2]
    mean = wp.vec3(a[4], a[5], a[6]) / w0
    centre = wp.vec3(float(i), float(j), float(k)) * h + mean
    # central second moment: Σ w lum |p − x_v|² − Σ w lum · |mean|²
    lights[v] = pack(wp.vec3(a[0], a[1], a[2]), w0, centre, wp.max(a[7] - w0 * wp.dot(mean, mean), 0.0))


#: S1 vertices per axis of an occupancy block: gather_level skips blocks without a grid light
BLOCK = wp.constant(4)


@wp.kernel
def mark_blocks(
    s1: wp.array(dtype=acc8),            # (V1,) S1 grid lights from s1_grid_lights
    s1_dims: wp.vec3i,
    block_dims: wp.vec3i,                # blocks per axis, ceil(s1_dims / BLOCK)
    occupied: wp.array(dtype=wp.uint8),  # (blocks,) out, zeroed: 1 where a block holds an S1 grid light
):
    v = wp.tid()
    if s1[v][3] > 0.0:
        i = v / (s1_dims[1] * s1_dims[2])
        j = (v / s1_dims[2]) % s1_dims[1]
        k = v % s1_dims[2]
        # every writer stores the same value: a benign race, no atomic needed
        occupied[flat_index(i / BLOCK, j / BLOCK, k / BLOCK, block_dims)] = wp.uint8(1)


@wp.kernel
def gather_level(
    s1: wp.array(dtype=acc8),            # (V1,) S1 grid lights from s1_grid_lights
    s1_dims: wp.vec3i,
    block_dims: wp.vec3i,                # occupancy blocks per axis
    occupied: wp.array(dtype=wp.uint8),  # (blocks,) from mark_blocks
    stride: int,                         # 2^(l-1): S1 cells per level-l cell
    h: float,                            # level spacing h_l
    dims: wp.vec3i,                      # level-l vertices per axis
    first: int,                          # first flat level-l vertex of this launch
    s1_lobe: wp.array(dtype=wp.vec4),    # (V1,) S1 lobe moments Σ w lum n and light counts Σ w
    out: wp.array(dtype=acc8),           # (V_l,) level-l accumulators, moments about each level-l vertex
    out_lobe: wp.array(dtype=wp.vec4),   # (V_l,) level-l lobe moments and light counts
):
    """Level l by gather from S1 (paper 004 §3.1): each S1 grid light, a point at its illumination
    centre c_u, is distributed over the level-l grid with level-l trilinear weights; this thread sums
    what its vertex V receives. c_u lies within h_1 of its own vertex (a convex combination of points
    in the cells around it), so only S1 vertices within ``stride`` S1 cells of V can reach V. VPLs lie
    on surfaces, so most of S1 is empty: the support is walked block by block (BLOCK³ S1 vertices) and
    empty blocks are skipped, which keeps the coarse levels, whose supports span thousands of S1
    vertices, cheap."""
    v = wp.tid() + first
    i = v / (dims[1] * dims[2])
    j = (v / dims[2]) % dims[1]
    k = v % dims[2]
    xv = wp.vec3(float(i), float(j), float(k)) * h
    inv_h = 1.0 / h
    ci = i * stride
    cj = j * stride
    ck = k * stride
    acc = wp.vec3(0.0, 0.0, 0.0)
    m0 = float(0.0)
    m1 = wp.vec3(0.0, 0.0, 0.0)
    m2 = float(0.0)
    nl = wp.vec4(0.0, 0.0, 0.0, 0.0)
    a0 = wp.max(ci - stride, 0)
    a1 = wp.min(ci + stride, s1_dims[0] - 1)
    b0 = wp.max(cj - stride, 0)
    b1 = wp.min(cj + stride, s1_dims[1] - 1)
    c0 = wp.max(ck - stride, 0)
    c1 = wp.min(ck + stride, s1_dims[2] - 1)
    for ba in range(a0 / BLOCK, a1 / BLOCK + 1):
        for bb in range(b0 / BLOCK, b1 / BLOCK + 1):
            for bc in range(c0 / BLOCK, c1 / BLOCK + 1):
                if occupied[flat_index(ba, bb, bc, block_dims)] == wp.uint8(0):
                    continue
                for a in range(wp.max(a0, ba * BLOCK), wp.min(a1, ba * BLOCK + BLOCK - 1) + 1):
                    for b in range(wp.max(b0, bb * BLOCK), wp.min(b1, bb * BLOCK + BLOCK - 1) + 1):
                        row = flat_index(a, b, 0, s1_dims)
                        for c in range(wp.max(c0, bc * BLOCK), wp.min(c1, bc * BLOCK + BLOCK - 1) + 1):
                            u = s1[row + c]
                            w0 = u[3]
                            if w0 > 0.0:
                                d = wp.vec3(u[4], u[5], u[6]) - xv
                                w = hat(d[0] * inv_h) * hat(d[1] * inv_h) * hat(d[2] * inv_h)
                                if w > 0.0:
                                    ww = w * w0
                                    acc += w * wp.vec3(u[0], u[1], u[2])
                                    m0 += ww
                                    # re-centred from the S1 light's centre to V (parallel-axis theorem)
                                    m1 += ww * d
                                    m2 += w * u[7] + ww * wp.dot(d, d)
                                    nl += w * s1_lobe[row + c]
    out[v] = pack(acc, m0, m1, m2)
    out_lobe[v] = nl


@wp.kernel
def mark_nonempty(
    acc: wp.array(dtype=acc8),           # (V,) accumulators of one level
    flags: wp.array(dtype=int),          # (V,) out: 1 for a vertex that holds a grid light
):
    v = wp.tid()
    flags[v] = wp.where(acc[v][3] > 0.0, 1, 0)


@wp.kernel
def compact_level(
    acc: wp.array(dtype=acc8),           # (V,) accumulators of one level, moments about each vertex
    slot: wp.array(dtype=int),           # (V,) exclusive prefix sum of mark_nonempty's flags
    base: int,                           # first output row of this level (levels share merged buffers)
    origin: wp.vec3,                     # grid origin, scene units
    h: float,                            # level spacing
    dims: wp.vec3i,
    lobe: wp.array(dtype=wp.vec4),           # (V,) lobe moments and light counts of the level
    out_position: wp.array(dtype=wp.vec3),   # (M,) illumination-weighted centre, scene units
    out_intensity: wp.array(dtype=wp.vec3),  # (M,) RGB intensity
    out_variance: wp.array(dtype=float),     # (M,) E|p − centre|², scene units²
    out_vertex: wp.array(dtype=wp.int64),    # (M,) flat vertex index
    out_lobe: wp.array(dtype=wp.vec3),       # (M,) mean emission normal ν (|ν| <= 1; 0: isotropic)
    out_count: wp.array(dtype=float),        # (M,) lights it stands for: Σ of their trilinear weights
):
    """Stream compaction and finalization: one grid light per non-empty vertex, in vertex order."""
    v = wp.tid()
    a = acc[v]
    w0 = a[3]
    if w0 <= 0.0:
        return
    s = base + slot[v]
    i = v / (dims[1] * dims[2])
    j = (v / dims[2]) % dims[1]
    k = v % dims[2]
    mean = wp.vec3(a[4], a[5], a[6]) / w0
    out_position[s] = origin + wp.vec3(float(i), float(j), float(k)) * h + mean
    out_intensity[s] = wp.vec3(a[0], a[1], a[2])
    out_variance[s] = wp.max(a[7] / w0 - wp.dot(mean, mean), 0.0)
    out_vertex[s] = wp.int64(v)
    nl = lobe[v]
    out_lobe[s] = wp.vec3(nl[0], nl[1], nl[2]) / w0
    out_count[s] = nl[3]
