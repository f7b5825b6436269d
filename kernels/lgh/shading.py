"""Warp kernels: lighting from a lighting grid hierarchy with streaming shadow-sample selection.

Paper 004 §3.2 (gather every grid light whose blending function is non-zero at the pixel) and §3.3 /
Appendix A (pick k shadow samples while accumulating: light i replaces sample s with probability
f_i / F_i, F_i the running sum of f). Optionally the input lights themselves are the finest level S0
(§4.1: the paper starts from S1; S0 is exact in the near field). Pure compute: arrays in, arrays out.
"""

import warp as wp

# forward only: nothing here is differentiated, and the adjoint code was most of the compile
# (cold cache, this CPU: 1.2 -> 0.4 s for CPU, 0.9 -> 0.3 s for CUDA)
wp.set_module_options({"enable_backward": False})

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


@wp.func
def lobe_factor(nu: wp.vec3, w: wp.vec3, d: float) -> float:
    """Emission toward the receiver relative to isotropic, for a light of mean normal ``nu`` (|ν| <= 1)
    at ``-w`` from it: ``(1 − |ν|) + 4·max(0, ν·ω)``, ω = −w/d the unit direction light → receiver.

    A blend of an isotropic part and a cosine lobe about ν that keeps the power 4π·I for any |ν|: one
    VPL (|ν| = 1) is the exact Lambertian emitter Φ·cos/π (I = Φ/4π); a grid light of coplanar VPLs is
    exact too; where normals disagree (corners, thin sheets lit from both sides) |ν| shrinks and the
    light tends to isotropic, the paper's grid light."""
    c = -wp.dot(nu, w) / d
    return 1.0 - wp.length(nu) + 4.0 * wp.max(c, 0.0)


@wp.func
def light_term(p: wp.vec3, n: wp.vec3, q: wp.vec3, intensity: wp.vec3, nu: wp.vec3, level: int, top: int,
               r: float, inv_m2: float, clamp_d2: float, scale: float) -> wp.vec4:
    """Irradiance at ``p`` (normal ``n``) from a light at ``q`` of isotropic-equivalent intensity ``I`` and
    mean normal ``nu``: B_level(d) · I · lobe_factor · cos / max(d², d_c²) in xyz, B_level(d) in w (0 where
    the light does not reach the point)."""
    w = q - p
    d2 = wp.dot(w, w)
    d = wp.sqrt(d2)
    if d <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    b = blend(level, top, d, r)
    cos_s = wp.dot(n, w) / d
    if b <= 0.0 or cos_s <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    lobe = lobe_factor(nu, w, d)
    if lobe <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    e = intensity * (b * lobe * cos_s * inv_m2 / wp.max(d2, clamp_d2) * scale)
    return wp.vec4(e[0], e[1], e[2], b)


@wp.func
def vpl_term(p: wp.vec3, n: wp.vec3, q: wp.vec3, intensity: wp.vec3, nq: wp.vec3, inv_m2: float,
             clamp_d2: float) -> wp.vec3:
    """Irradiance at ``p`` (normal ``n``) from one input light at ``q`` (normal ``nq``, 0: isotropic),
    unblended: I · lobe_factor · cos / max(d², d_c²) (:func:`light_term` with B = 1)."""
    w = q - p
    d2 = wp.dot(w, w)
    d = wp.sqrt(d2)
    if d <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    cos_s = wp.dot(n, w) / d
    lobe = lobe_factor(nq, w, d)
    if cos_s <= 0.0 or lobe <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    return intensity * (lobe * cos_s * inv_m2 / wp.max(d2, clamp_d2))


@wp.func
def take(rng: wp.uint32, e: wp.vec3, f: float, b: float, s: int, tid: int, q: wp.vec3, sd: float, v: int,
         out_sample_pos: wp.array2d(dtype=wp.vec3), out_sample_ok: wp.array2d(dtype=int),
         out_sample_light: wp.array2d(dtype=int), out_sample_weight: wp.array2d(dtype=wp.vec3),
         out_sample_blend: wp.array2d(dtype=float),
         out_sample_lum: wp.array2d(dtype=float)) -> wp.uint32:
    """Sample ``s`` takes light ``v`` (as :func:`pick` writes it); its position jittered by ``sd``."""
    state = rng
    jitter = wp.vec3(0.0, 0.0, 0.0)
    if sd > 0.0:
        jitter = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state)) * sd
    out_sample_pos[tid, s] = q + jitter
    out_sample_ok[tid, s] = 1
    out_sample_light[tid, s] = v
    out_sample_weight[tid, s] = e / f
    out_sample_blend[tid, s] = b / f
    out_sample_lum[tid, s] = f
    return state


@wp.func
def pick(rng: wp.uint32, e: wp.vec3, f: float, b: float, total: float, samples: int, tid: int, q: wp.vec3,
         sd: float, v: int, out_sample_pos: wp.array2d(dtype=wp.vec3), out_sample_ok: wp.array2d(dtype=int),
         out_sample_light: wp.array2d(dtype=int), out_sample_weight: wp.array2d(dtype=wp.vec3),
         out_sample_blend: wp.array2d(dtype=float),
         out_sample_lum: wp.array2d(dtype=float)) -> wp.uint32:
    """Appendix A: each of the k samples keeps its light or takes light ``v`` with probability p = f / F.

    The k independent coin flips are drawn as geometric gaps between the samples that take the light
    (the same distribution, one random number per light in the common case instead of k), so many
    samples per pixel cost little more lighting time than a few. The chosen light's RGB irradiance
    over its luminance, ``e / f``, is kept with it: F · mean(V · e / f) over the samples estimates
    the shadowed irradiance per colour channel. So is ``b / f`` (``b`` the blending weight times the
    interleave scale): a member VPL's own irradiance times it, over its share of the light's luminance,
    is that sample's weight instead (:func:`cluster_targets`).
    """
    state = rng
    p = f / total
    lq = float(0.0)                   # log(1 - p), accurate for tiny p
    if p < 1.0e-4:
        lq = -p * (1.0 + 0.5 * p)
    elif p < 1.0:
        lq = wp.log(1.0 - p)
    s = int(-1)
    while s < samples:
        if p >= 1.0:
            s = s + 1
        else:
            gap = wp.log(wp.max(wp.randf(state), 1.0e-30)) / lq     # failures before the next success
            if gap >= float(samples - s - 1):
                break
            s = s + 1 + int(gap)
        if s >= samples:
            break
        state = take(state, e, f, b, s, tid, q, sd, v, out_sample_pos, out_sample_ok, out_sample_light,
                     out_sample_weight, out_sample_blend, out_sample_lum)
    return state


@wp.struct
class Sweep:
    """A point's state while its lights are visited: the sums, and the stratified sweep's position."""

    rng: wp.uint32
    acc: wp.vec3      # unshadowed irradiance so far
    count: float      # Σ B · (lights it stands for) over the lights that reach the point
    total: float      # F, the luminance sum of the first sweep
    run: float        # the second sweep's running luminance sum
    s: int            # the next sample to give out in the second sweep
    u: float          # its position in [0, F): (s + xi) F / k
    step: float       # F / k
    xi: float


@wp.func
def visit(st: Sweep, sweep: int, stratified: int, e4: wp.vec4, scale: float, count: float, samples: int, tid: int,
          q: wp.vec3, sd: float, v: int, out_sample_pos: wp.array2d(dtype=wp.vec3),
          out_sample_ok: wp.array2d(dtype=int), out_sample_light: wp.array2d(dtype=int),
          out_sample_weight: wp.array2d(dtype=wp.vec3), out_sample_blend: wp.array2d(dtype=float),
          out_sample_lum: wp.array2d(dtype=float)) -> Sweep:
    """One light (``light_term``'s ``e4``) of a point: summed in the first sweep (and picked there by
    Appendix A's streaming when not ``stratified``); in the second, it takes the samples whose
    positions fall in its share of the running sum. ``count``: the input lights it stands for."""
    out = st
    e = wp.vec3(e4[0], e4[1], e4[2])
    f = wp.dot(e, LUMA)
    if f <= 0.0:
        return out
    b = e4[3] * scale
    if sweep == 0:
        out.acc = st.acc + e
        out.count = st.count + b * count
        out.total = st.total + f
        if stratified == 0:
            out.rng = pick(st.rng, e, f, b, out.total, samples, tid, q, sd, v, out_sample_pos, out_sample_ok,
                           out_sample_light, out_sample_weight, out_sample_blend, out_sample_lum)
        return out
    out.run = st.run + f
    while out.s < samples and out.u < out.run:
        out.rng = take(out.rng, e, f, b, out.s, tid, q, sd, v, out_sample_pos, out_sample_ok, out_sample_light,
                       out_sample_weight, out_sample_blend, out_sample_lum)
        out.s = out.s + 1
        out.u = (float(out.s) + out.xi) * out.step
    return out


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
    light_int: wp.array(dtype=wp.vec3),       # (M,) RGB isotropic-equivalent intensity (nit·m²): power 4π·I
    light_lobe: wp.array(dtype=wp.vec3),      # (M,) mean emission normal ν (0: isotropic)
    light_std: wp.array(dtype=float),         # (M,) per-axis positional std. dev. for jittered samples
    light_count: wp.array(dtype=float),       # (M,) input lights each grid light stands for
    n_levels: int,
    level_rank: wp.array(dtype=int),          # (L,) the level each entry is (0 = S1; a split hierarchy repeats one)
    top_rank: int,                            # the coarsest level's rank
    s0: int,                                  # 1: the input lights are level S0 (below S1), 0: start from S1
    s0_cells: wp.vec3i,                       # S0 lookup grid: cells per axis (the S1 cells of the first level)
    s0_start: wp.array(dtype=int),            # (cells + 1,) first entry of each cell in s0_light
    s0_light: wp.array(dtype=int),            # input light indices sorted by cell
    s0_pos: wp.array(dtype=wp.vec3),          # (N,) input light positions
    s0_int: wp.array(dtype=wp.vec3),          # (N,) input light intensities
    s0_lobe: wp.array(dtype=wp.vec3),         # (N,) input light normals (0: isotropic)
    alpha: float,
    inv_m2: float,                            # 1 / metersPerUnit²: falloff in metres
    clamp_d2: float,                          # clamped geometry term: d² >= clamp_d2 (scene units²)
    samples: int,
    jitter: int,                              # 1: sample positions jittered by light_std (paper); 0: the centres
    seed: int,
    first: int,                               # global index of this launch's first point (RNG stream)
    tile: wp.array(dtype=int),                # (P,) interleaved-sampling tile of each point
    tiles: int,                               # n² tiles: a point gathers lights with index % n² == its tile, × n²
    stratified: int,                          # 1: stratified picks in a second sweep, 0: Appendix A's streaming
    out_irradiance: wp.array(dtype=wp.vec3),  # (P,) unshadowed irradiance
    out_count: wp.array(dtype=float),         # (P,) Σ B · count over the lights that reach the point
    out_sample_pos: wp.array2d(dtype=wp.vec3),  # (P, k) chosen shadow-sample positions
    out_sample_ok: wp.array2d(dtype=int),     # (P, k) 1 when a sample was chosen
    out_sample_light: wp.array2d(dtype=int),  # (P, k) chosen light: grid light index, or M + input light index
    out_sample_weight: wp.array2d(dtype=wp.vec3),  # (P, k) chosen light's RGB irradiance / its luminance
    out_sample_blend: wp.array2d(dtype=float),  # (P, k) its blending weight (× interleave scale) / its luminance
    out_sample_lum: wp.array2d(dtype=float),  # (P, k) its luminance contribution f (F = Σ f: the irradiance's)
):
    tid = wp.tid()
    p = points[tid]
    n = normals[tid]
    st = Sweep()
    st.rng = wp.rand_init(seed, first + tid)   # a stream per point, whatever the launch blocking
    st.acc = wp.vec3(0.0, 0.0, 0.0)
    st.count = float(0.0)
    st.total = float(0.0)
    st.run = float(0.0)
    st.s = int(0)
    st.u = float(0.0)
    st.step = float(0.0)
    st.xi = float(0.0)
    scale = float(tiles)
    top = top_rank + s0                     # blending index of the top level; S0, when used, is index 0
    m = light_pos.shape[0]
    # stratified: a first sweep sums the lights, a second walks them again and gives sample s the light
    # whose share of the running sum holds u_s = (s + xi) F / k (systematic sampling: a light of share p
    # gets floor(k p) or ceil(k p) samples, never more or fewer); otherwise one sweep picks as it sums
    sweeps = 1
    if stratified == 1 and samples > 0:
        sweeps = 2
    for sweep in range(sweeps):
        if sweep == 1:
            if st.total <= 0.0:
                break
            st.step = st.total / float(samples)
            # through a local: wp.randf on the struct's field draws from a copy and leaves st.rng where it
            # was, so the first jittered sample drew xi again as its first number
            rng = st.rng
            st.xi = wp.randf(rng)
            st.rng = rng
            st.u = st.xi * st.step
        if s0 == 1:
            # S0: the input lights within 2 r_0 = alpha h_1 (h_0 = h_1 / 2), found through a grid of S1 cells
            h1 = level_spacing[0]
            r0 = alpha * 0.5 * h1
            rel0 = (p - level_origin[0]) / h1
            reach = int(wp.ceil(alpha))         # a light within alpha h_1 is at most ceil(alpha) cells away
            ci = int(wp.floor(rel0[0]))
            cj = int(wp.floor(rel0[1]))
            ck = int(wp.floor(rel0[2]))
            for i in range(wp.max(ci - reach, 0), wp.min(ci + reach, s0_cells[0] - 1) + 1):
                for j in range(wp.max(cj - reach, 0), wp.min(cj + reach, s0_cells[1] - 1) + 1):
                    for k in range(wp.max(ck - reach, 0), wp.min(ck + reach, s0_cells[2] - 1) + 1):
                        c = (i * s0_cells[1] + j) * s0_cells[2] + k
                        for e_i in range(s0_start[c], s0_start[c + 1]):
                            v = s0_light[e_i]
                            if sweep == 1 and st.s >= samples:
                                continue
                            if tiles > 1 and v % tiles != tile[tid]:
                                continue
                            q = s0_pos[v]
                            e4 = light_term(p, n, q, s0_int[v], s0_lobe[v], 0, top, r0, inv_m2, clamp_d2, scale)
                            st = visit(st, sweep, stratified, e4, scale, 1.0, samples, tid, q, 0.0, m + v,
                                       out_sample_pos, out_sample_ok, out_sample_light, out_sample_weight,
                                       out_sample_blend, out_sample_lum)
        for l in range(n_levels):
            h = level_spacing[l]
            r = alpha * h
            dims = level_dims[l]
            rel = (p - level_origin[l]) / h
            # a grid light lies within sqrt(3) cells of its vertex (its centre averages lights from the 8 cells
            # around it) and counts only within 2 r = 2 alpha h: visit the vertices in that sphere, not a cube
            span = 2.0 * alpha + 1.7321
            rank = level_rank[l]
            if rank == top_rank:      # the top level reaches every distance: visit all its vertices
                span = 1.0e9
            base = level_offset[l]
            i0 = wp.max(int(wp.ceil(rel[0] - span)), 0)
            i1 = wp.min(int(wp.floor(rel[0] + span)), dims[0] - 1)
            for i in range(i0, i1 + 1):
                dx = float(i) - rel[0]
                ry = wp.sqrt(wp.max(span * span - dx * dx, 0.0))
                j0 = wp.max(int(wp.ceil(rel[1] - ry)), 0)
                j1 = wp.min(int(wp.floor(rel[1] + ry)), dims[1] - 1)
                for j in range(j0, j1 + 1):
                    dy = float(j) - rel[1]
                    rz = wp.sqrt(wp.max(span * span - dx * dx - dy * dy, 0.0))
                    k0 = wp.max(int(wp.ceil(rel[2] - rz)), 0)
                    k1 = wp.min(int(wp.floor(rel[2] + rz)), dims[2] - 1)
                    for k in range(k0, k1 + 1):
                        v = vertex_light[base + (i * dims[1] + j) * dims[2] + k]
                        if v < 0 or (sweep == 1 and st.s >= samples):
                            continue
                        if tiles > 1 and v % tiles != tile[tid]:
                            continue
                        q = light_pos[v]
                        e4 = light_term(p, n, q, light_int[v], light_lobe[v], rank + s0, top, r, inv_m2, clamp_d2, scale)
                        st = visit(st, sweep, stratified, e4, scale, light_count[v], samples, tid, q,
                                   light_std[v] * float(jitter), v,
                                   out_sample_pos, out_sample_ok, out_sample_light, out_sample_weight, out_sample_blend,
                                   out_sample_lum)
    out_irradiance[tid] = st.acc
    out_count[tid] = st.count


@wp.kernel
def cluster_targets(
    lights: wp.array(dtype=int),              # (S,) chosen light: grid light index, or M + input light index
    fallback: wp.array(dtype=wp.vec3),        # (S,) target when the grid light has no member (jittered centre)
    start: wp.array(dtype=int),               # (M,) first member row of each grid light
    stop: wp.array(dtype=int),                # (M,) one past its last member row
    cum: wp.array(dtype=wp.float64),          # (rows + 1,) running sum of the members' luminance
    guide: wp.array(dtype=int),               # (rows,) cut points (usdml.lighting.lgh.shading._guide_table)
    member: wp.array(dtype=int),              # (rows,) input light of each member row
    positions: wp.array(dtype=wp.vec3),       # (N,) input light positions
    grid_lights: int,                         # M
    seed: int,
    first: int,                               # global index of this launch's first sample (RNG stream)
    stratified: int,                          # 1: the rank-th of a run draws from the rank-th share
    rank: wp.array(dtype=int),                # (S,) the sample's place among its point's samples of its light
    run_length: wp.array(dtype=int),          # (S,) how many they are
    reweight: int,                            # 1: weigh each sample by its member's own irradiance
    points: wp.array(dtype=wp.vec3),          # (P,) shading points (reweight only)
    normals: wp.array(dtype=wp.vec3),         # (P,) their shading normals
    pixel: wp.array(dtype=int),               # (S,) the sample's point
    blend_over_f: wp.array(dtype=float),      # (S,) chosen light's blending weight / its luminance (pick)
    intensity: wp.array(dtype=wp.vec3),       # (N,) input light intensities
    emit_normal: wp.array(dtype=wp.vec3),     # (N,) input light normals (0: isotropic)
    inv_m2: float,
    clamp_d2: float,
    out: wp.array(dtype=wp.vec3),             # (S,) shadow-ray targets
    out_weight: wp.array(dtype=wp.vec3),      # (S,) reweight: the sample's RGB weight, as pick's e / f; in: pick's
):
    """Shadow-ray target of each sample: a member of the chosen grid light, drawn in proportion to
    its luminance (inverse CDF by binary search), or the input light itself for an S0 pick.

    With ``reweight`` the sample's weight ``e / f`` (the grid light's irradiance over its luminance)
    becomes ``B · (W / w_j) · e_j / f``: member j's own irradiance at the point (cosine emitter,
    clamped; :func:`vpl_term`) over its share w_j / W of the light's luminance, times the light's
    blending weight. F · mean(V · weight) then estimates Σ_lights B Σ_members e_j V_j, the VPLs' own
    shadowed irradiance, instead of the grid light's irradiance times its members' mean visibility
    (members that face away from the point or lie below its horizon weigh 0 and need no ray)."""
    t = wp.tid()
    v = lights[t]
    if v < 0:                                 # no sample was chosen (out_weight keeps its 0)
        out[t] = fallback[t]
        return
    if v >= grid_lights:
        out[t] = positions[v - grid_lights]
        return
    lo = start[v]
    hi = stop[v]
    c0 = cum[lo]
    total = cum[hi] - c0
    if hi <= lo or total <= wp.float64(0.0):
        out[t] = fallback[t]
        return
    rng = wp.rand_init(seed, first + t)
    u = wp.float64(wp.randf(rng))
    if stratified == 1:
        u = (wp.float64(rank[t]) + u) / wp.float64(run_length[t])
    x = c0 + u * total
    # the last row whose running sum is <= x: from the cut point of x's share, stepping forward (the
    # row a binary search over lo .. hi - 1 finds; a cut point past x, which rounding could give, falls
    # back to that search)
    m_rows = hi - lo
    share = int((x - c0) / total * wp.float64(m_rows))
    share = wp.min(wp.max(share, 0), m_rows - 1)
    a = guide[lo + share]
    if cum[a] > x:
        a = lo
        b = hi - 1
        while a < b:
            m = (a + b + 1) / 2
            if cum[m] <= x:
                a = m
            else:
                b = m - 1
    while a + 1 < hi and cum[a + 1] <= x:
        a = a + 1
    j = member[a]
    out[t] = positions[j]
    if reweight == 1:
        lum = wp.float64(wp.dot(intensity[j], LUMA))
        if lum <= wp.float64(0.0):
            out_weight[t] = wp.vec3(0.0, 0.0, 0.0)
            return
        i = pixel[t]
        e = vpl_term(points[i], normals[i], positions[j], intensity[j], emit_normal[j], inv_m2, clamp_d2)
        out_weight[t] = e * (blend_over_f[t] * float(total / lum))
