"""Warp kernels: lighting from a lighting grid hierarchy with streaming shadow-sample selection.

Paper 004 §3.2 (gather every grid light whose blending function is non-zero at the pixel) and §3.3 /
Appendix A (pick k shadow samples while accumulating: light i replaces sample s with probability
f_i / F_i, F_i the running sum of f). Pure compute: arrays in, arrays out.
"""

import warp as wp

LUMA = wp.constant(wp.vec3(0.2126, 0.7152, 0.0722))


@wp.func
def blend(level: int, top: int, d: float, r: float) -> float:
    """Blending function B_level(d): a partition of unity over the levels (r_level = alpha h_level).

    The finest level used is 1 up to r and fades out over [r, 2r]; the top level fades in over
    [r/2, r] and stays 1; the others fade in over [r/2, r] and out over [r, 2r]. Consecutive levels
    have r doubling, so each fade-out is the next level's fade-in (smoothstep both ways).
    """
    if level == top and level == 0:
        return 1.0
    w = float(1.0)
    if level > 0:
        x = wp.clamp((d - 0.5 * r) / (0.5 * r), 0.0, 1.0)
        w = x * x * (3.0 - 2.0 * x)
    if level < top:
        y = wp.clamp((d - r) / r, 0.0, 1.0)
        w = w * (1.0 - y * y * (3.0 - 2.0 * y))
    return w


@wp.kernel
def lgh_gather(
    points: wp.array(dtype=wp.vec3),          # (P,) surface points, scene units
    normals: wp.array(dtype=wp.vec3),         # (P,) unit normals
    level_origin: wp.array(dtype=wp.vec3),    # (L,) grid origin of each level
    level_spacing: wp.array(dtype=float),     # (L,) h_l
    level_dims: wp.array(dtype=wp.vec3i),     # (L,) vertices per axis
    level_offset: wp.array(dtype=int),        # (L,) offset of the level in vertex_light
    vertex_light: wp.array(dtype=int),        # (sum of vertex counts,) light index or -1
    light_pos: wp.array(dtype=wp.vec3),       # (M,) grid light positions
    light_int: wp.array(dtype=wp.vec3),       # (M,) RGB isotropic intensity (nit·m²)
    light_std: wp.array(dtype=float),         # (M,) per-axis positional std. dev. for jittered samples
    n_levels: int,
    alpha: float,
    inv_m2: float,                            # 1 / metersPerUnit²: falloff in metres
    clamp_d2: float,                          # clamped geometry term: d² >= clamp_d2 (scene units²)
    samples: int,
    seed: int,
    first: int,                               # global index of this launch's first point (RNG stream)
    tile: wp.array(dtype=int),                # (P,) interleaved-sampling tile of each point
    tiles: int,                               # n² tiles: a point gathers lights with index % n² == its tile, × n²
    out_irradiance: wp.array(dtype=wp.vec3),  # (P,) unshadowed irradiance
    out_sample_pos: wp.array2d(dtype=wp.vec3),  # (P, k) chosen shadow-sample positions
    out_sample_ok: wp.array2d(dtype=int),     # (P, k) 1 when a sample was chosen
    out_sample_light: wp.array2d(dtype=int),  # (P, k) index of the grid light chosen
):
    tid = wp.tid()
    p = points[tid]
    n = normals[tid]
    rng = wp.rand_init(seed, first + tid)   # a stream per point, whatever the launch blocking
    acc = wp.vec3(0.0, 0.0, 0.0)
    total = float(0.0)
    top = n_levels - 1
    for l in range(n_levels):
        h = level_spacing[l]
        r = alpha * h
        dims = level_dims[l]
        rel = (p - level_origin[l]) / h
        reach = int(wp.ceil(2.0 * alpha)) + 1
        i0 = wp.max(int(wp.floor(rel[0])) - reach, 0)
        j0 = wp.max(int(wp.floor(rel[1])) - reach, 0)
        k0 = wp.max(int(wp.floor(rel[2])) - reach, 0)
        i1 = wp.min(int(wp.floor(rel[0])) + reach + 1, dims[0] - 1)
        j1 = wp.min(int(wp.floor(rel[1])) + reach + 1, dims[1] - 1)
        k1 = wp.min(int(wp.floor(rel[2])) + reach + 1, dims[2] - 1)
        if l == top:              # the top level reaches every distance: visit all its vertices
            i0 = 0
            j0 = 0
            k0 = 0
            i1 = dims[0] - 1
            j1 = dims[1] - 1
            k1 = dims[2] - 1
        base = level_offset[l]
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    v = vertex_light[base + (i * dims[1] + j) * dims[2] + k]
                    if v < 0:
                        continue
                    if tiles > 1 and v % tiles != tile[tid]:
                        continue
                    q = light_pos[v]
                    w = q - p
                    d2 = wp.dot(w, w)
                    d = wp.sqrt(d2)
                    b = blend(l, top, d, r)
                    if b <= 0.0 or d <= 0.0:
                        continue
                    cos_s = wp.dot(n, w) / d
                    if cos_s <= 0.0:
                        continue
                    g = b * cos_s * inv_m2 / wp.max(d2, clamp_d2) * float(tiles)
                    e = light_int[v] * g
                    acc = acc + e
                    f = wp.dot(e, LUMA)
                    if f <= 0.0:
                        continue
                    total = total + f
                    for s in range(samples):
                        # Appendix A: keep the current sample or replace it with probability f / F
                        if wp.randf(rng) * total < f:
                            sd = light_std[v]
                            out_sample_pos[tid, s] = q + wp.vec3(wp.randn(rng), wp.randn(rng), wp.randn(rng)) * sd
                            out_sample_ok[tid, s] = 1
                            out_sample_light[tid, s] = v
    out_irradiance[tid] = acc
