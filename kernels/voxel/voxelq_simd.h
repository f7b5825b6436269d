/* The SIMD body of kernels/voxel/voxelq.c, written once against a small vector API and included once per
 * instruction set (AVX2: 8 lanes, AVX-512: 32 as two registers of 16). The including file defines:
 *   W (lanes), SUFFIX(name), TARGET (the function attribute), V / VI / M (float, int32 and mask
 *   vectors) and the operations used below (vq_* functions and macros, see voxelq.c).
 * The rule is array_hit / shadow_scalar's in voxelq.c, lane by lane. */

#include "brdf_lobes.h"     /* the preview surface's BRDF, W points at a time (SUFFIX(brdf_lobes)) */

TARGET static inline V SUFFIX(vatan2)(V y, V x) {
    V ax = ABS(x), ay = ABS(y);
    V mx = MAX(ax, ay), mn = MIN(ax, ay);
    M zero = EQ(mx, SET(0.0f));
    V a = MUL(mn, RCP(SEL(zero, SET(1.0f), mx)));
    V q2 = MUL(a, a);
    V q = FMA(q2, SET(-0.01172120f), SET(0.05265332f));
    q = FMA(q2, q, SET(-0.11643287f));
    q = FMA(q2, q, SET(0.19354346f));
    q = FMA(q2, q, SET(-0.33262347f));
    q = FMA(q2, q, SET(0.99997726f));
    V r = MUL(a, q);
    r = SEL(GT(ay, ax), SUB(SET(1.57079637f), r), r);
    r = SEL(LT(x, SET(0.0f)), SUB(SET(3.14159274f), r), r);
    r = SEL(LT(y, SET(0.0f)), SUB(SET(0.0f), r), r);
    return SEL(zero, SET(0.0f), r);
}

/* direction bin of W directions (direction_bin) */
TARGET static inline VI SUFFIX(vbin)(const VQScene *s, V dx, V dy, V dz) {
    V flip = SEL(LT(dz, SET(0.0f)), SET(-1.0f), SET(1.0f));
    dx = MUL(dx, flip); dy = MUL(dy, flip); dz = MUL(dz, flip);
    V theta = MUL(SUFFIX(vatan2)(SQRT(FMA(dx, dx, MUL(dy, dy))), dz), SET(DEG));
    VI ring = CVTT(FMA(theta, SET(1.0f / s->d_theta), SET(0.5f)));
    ring = IMIN(IMAX(ring, ISET(0)), ISET(s->n_rings - 1));
    V phi = MUL(SUFFIX(vatan2)(dy, dx), SET(DEG));
    phi = SEL(LT(phi, SET(0.0f)), ADD(phi, SET(360.0f)), phi);
    VI cnt = GATHER_I(s->ring_count, ring);
    VI col = CVTT(ADD(MUL(MUL(phi, CVTF(cnt)), SET(1.0f / 360.0f)), SET(0.5f)));
    col = SELI(IGT(col, ISUB(cnt, ISET(1))), ISUB(col, cnt), col);
    return IADD(GATHER_I(s->ring_start, ring), col);
}

/* one group of W queries against the static array between its two stages (see batch) */
typedef struct {
    V qa[3], dq[3], t0, t1, inv_dw;
    VI lo, hi, lo_p, hi_p, npieces, dir_base, idx, st, en, idx1, st1, en1;
    M active, forward, ok, ok1, centre;
    int maxp, seg_shift, n;
} SUFFIX(Group);

/* piece p of the group's lanes: its first and last voxel and the ray's grid position at its middle */
TARGET static inline void SUFFIX(piece_at)(const SUFFIX(Group) *g, int p, VI *st, VI *en, V *fu, V *fv) {
    VI pv = ISET(p);
    VI ps = SELI(g->forward, ISLL(IADD(g->lo_p, pv), g->seg_shift), ISLL(ISUB(g->hi_p, pv), g->seg_shift));
    *st = IMAX(ps, g->lo);
    *en = IMIN(IADD(ps, ISET((1 << g->seg_shift) - 1)), g->hi);
    V mid = MUL(SET(0.5f), CVTF(IADD(IADD(*st, *en), ISET(1))));
    V t = MIN(MAX(MUL(SUB(mid, g->qa[2]), g->inv_dw), g->t0), g->t1);
    *fu = FMA(g->dq[0], t, g->qa[0]);
    *fv = FMA(g->dq[1], t, g->qa[1]);
}

/* Alg. 2's row lookup for the lanes of m: the index of the word of row (fu, fv) holding voxel st and
 * whether the row holds that word (``ok``; not outside the grid) */
TARGET static inline VI SUFFIX(row_word)(const VQScene *s, const SUFFIX(Group) *g, M m, V fu, V fv, VI st,
                                         M *ok_out) {
    V zf = SET(0.0f), fn = SET((float)g->n);
    m = MAND(m, MAND(MAND(GE(fu, zf), LT(fu, fn)), MAND(GE(fv, zf), LT(fv, fn))));
    VI r = IADD(IMUL(CVTT(fu), ISET(g->n)), CVTT(fv));
    VI span = MGATHER_I(s->row_span, r, m);
    VI rst = MGATHER_I(s->row_start, r, m);
    VI w = ISRL(st, 5);
    *ok_out = MAND(m, MAND(IGE(w, IAND(span, ISET(0xFFFF))), IGT(ISRL(span, 16), w)));
    return IADD(IADD(g->dir_base, rst), w);
}

/* piece p of every active lane: the index of the word it reads, its first and last voxel and whether
 * the row holds that word (``ok``) */
TARGET static inline VI SUFFIX(piece)(const VQScene *s, const SUFFIX(Group) *g, int p, VI *st_out, VI *en_out,
                                      M *ok_out) {
    V fu, fv;
    SUFFIX(piece_at)(g, p, st_out, en_out, &fu, &fv);
    return SUFFIX(row_word)(s, g, MAND(g->active, IGT(g->npieces, ISET(p))), fu, fv, *st_out, ok_out);
}

/* the bits of voxels st .. en in their word */
TARGET static inline VI SUFFIX(span_bits)(VI st, VI en) {
    return IAND(ISRLV(ISET(-1), ISUB(ISET(31), IAND(en, ISET(31)))), ISLLV(ISET(-1), IAND(st, ISET(31))));
}

/* stage 1 up to the row lookups: the lanes of ``live`` whose segments meet world-space array ``world``,
 * their bin, grid map, clipped range and pieces; 0 when no lane is left. ``widen``: how far (array
 * units) beyond the sphere holding the array's voxels a segment may pass and still be looked up (the
 * refinement's shifted rows), ``g->centre`` the lanes within the sphere itself (with ``widen`` > 0) */
TARGET VQ_INLINE int SUFFIX(clip)(const VQScene *s, int world, SUFFIX(Group) *g, M live, const V o[3], const V e[3],
                                  V skip0, V skip1, int seg_shift, float widen) {
    int a = s->world_array[world], n = s->arr_n[a];
    const float *A = s->world_inv[world];
    V inv_h = SET(s->arr_inv_h[a]), fn = SET((float)n), zf = SET(0.0f);
    g->maxp = 0;
    g->n = n;
    g->seg_shift = seg_shift;
    V dl[3] = {SUB(e[0], o[0]), SUB(e[1], o[1]), SUB(e[2], o[2])};
    V da[3];
    for (int i = 0; i < 3; i++) da[i] = FMA(SET(A[4 * i]), dl[0], FMA(SET(A[4 * i + 1]), dl[1], MUL(SET(A[4 * i + 2]), dl[2])));
    V length = MUL(SQRT(FMA(da[0], da[0], FMA(da[1], da[1], MUL(da[2], da[2])))), inv_h);
    M active = MAND(live, MAND(GT(length, ADD(skip0, skip1)), GT(length, zf)));
    if (!MBITS(active)) return 0;
    {
        /* segments passing farther from the array's centre than its sphere cannot meet a voxel: they
         * leave before the direction bin (the per-frame array of a small deforming mesh, most rays) */
        const float *sp = s->arr_sphere + 4 * (size_t)a;
        V q[3], dq = zf, dd = zf;
        for (int i = 0; i < 3; i++) {
            V pa = FMA(SET(A[4 * i]), o[0], FMA(SET(A[4 * i + 1]), o[1], FMA(SET(A[4 * i + 2]), o[2], SET(A[4 * i + 3]))));
            q[i] = SUB(SET(sp[i]), pa);
            dq = FMA(q[i], da[i], dq);
            dd = FMA(da[i], da[i], dd);
        }
        V t = MIN(MAX(MUL(dq, RCP(dd)), zf), SET(1.0f));
        V d2 = zf;
        for (int i = 0; i < 3; i++) {
            V x = SUB(q[i], MUL(da[i], t));
            d2 = FMA(x, x, d2);
        }
        g->centre = widen > 0.0f ? MAND(active, LE(d2, SET(sp[3] * sp[3]))) : active;
        active = MAND(active, LE(d2, SET((sp[3] + widen) * (sp[3] + widen))));
        if (!MBITS(active)) return 0;
    }
    VI d = SUFFIX(vbin)(s, da[0], da[1], da[2]);
    /* the bins' folded maps, read per lane (neighbouring points' rays to one light meet 7 bins per 16
     * on the city's bench rays, so loading shared bins whole and blending them lost) */
    V F[12];
    d = SELI(active, d, ISET(0));
    GATHER_ROWS12(s->world_fold[world], d, active, F);
    V qa[3], qb[3], dq[3];
    for (int i = 0; i < 3; i++) {
        qa[i] = FMA(F[4 * i], o[0], FMA(F[4 * i + 1], o[1], FMA(F[4 * i + 2], o[2], F[4 * i + 3])));
        qb[i] = FMA(F[4 * i], e[0], FMA(F[4 * i + 1], e[1], FMA(F[4 * i + 2], e[2], F[4 * i + 3])));
        dq[i] = SUB(qb[i], qa[i]);
    }
    V inv_len = RCP(length);
    V t0 = MUL(skip0, inv_len), t1 = SUB(SET(1.0f), MUL(skip1, inv_len));
    /* clip to the cube [0, n]^3 */
    for (int ax = 0; ax < 3; ax++) {
        M both = MAND(MAND(GE(qa[ax], zf), LT(qa[ax], fn)), MAND(GE(qb[ax], zf), LT(qb[ax], fn)));
        M flat = LT(ABS(dq[ax]), SET(1.0e-12f));
        active = MANDN(MANDN(both, flat), active);
        V inv = RCP(SEL(flat, SET(1.0f), dq[ax]));
        V ta = MUL(SUB(zf, qa[ax]), inv), tb = MUL(SUB(fn, qa[ax]), inv);
        t0 = SEL(both, t0, MAX(t0, MIN(ta, tb)));
        t1 = SEL(both, t1, MIN(t1, MAX(ta, tb)));
    }
    active = MANDN(GT(t0, t1), active);
    if (!MBITS(active)) return 0;
    V wa = FMA(dq[2], t0, qa[2]), wb = FMA(dq[2], t1, qa[2]);
    g->lo = IMIN(IMAX(CVTT(MIN(wa, wb)), ISET(0)), ISET(n - 1));
    g->hi = IMIN(IMAX(CVTT(MAX(wa, wb)), ISET(0)), ISET(n - 1));
    g->forward = GE(dq[2], zf);
    M wflat = LE(ABS(dq[2]), SET(1.0e-12f));
    g->inv_dw = SEL(wflat, zf, RCP(SEL(wflat, SET(1.0f), dq[2])));
    g->dir_base = IADD(ISET(s->arr_base[a]), IMUL(d, ISET(s->wpd)));
    g->lo_p = ISRL(g->lo, seg_shift);
    g->hi_p = ISRL(g->hi, seg_shift);
    g->npieces = IADD(ISUB(g->hi_p, g->lo_p), ISET(1));
    for (int i = 0; i < 3; i++) { g->qa[i] = qa[i]; g->dq[i] = dq[i]; }
    g->t0 = t0;
    g->t1 = t1;
    g->active = active;
    g->maxp = IREDUCE_MAX(SELI(active, g->npieces, ISET(0)));
    return 1;
}

/* stage 1: everything up to the first two pieces' words, which are prefetched */
TARGET static void SUFFIX(prepare)(const VQScene *s, int world, SUFFIX(Group) *g, M live, const V o[3], const V e[3],
                                   V skip0, V skip1, int seg_shift) {
    if (!SUFFIX(clip)(s, world, g, live, o, e, skip0, skip1, seg_shift, 0.0f)) return;
    /* the first two pieces' rows, and their words prefetched (a prefetch retires at once; a gather here
     * would hold up the instructions behind it until its cache lines arrive). Every lane's words, without
     * a branch per lane: a lane that reads nothing still names a word of the array */
    g->idx = SUFFIX(piece)(s, g, 0, &g->st, &g->en, &g->ok);
    int idx[W];
    ISTORE(idx, g->idx);
    for (int l = 0; l < W; l++) __builtin_prefetch(s->words + idx[l]);
    g->ok1 = MNONE;
    if (g->maxp > 1) {
        g->idx1 = SUFFIX(piece)(s, g, 1, &g->st1, &g->en1, &g->ok1);
        ISTORE(idx, g->idx1);
        for (int l = 0; l < W; l++) __builtin_prefetch(s->words + idx[l]);
    }
}

/* stage 2: the pieces in order from the ray's start, the first hit ending a lane. out: -1 free,
 * >= 0 hit (the distance in voxels when want_t) */
TARGET static void SUFFIX(finish)(const VQScene *s, SUFFIX(Group) *g, int want_t, float *out) {
    V zf = SET(0.0f);
    STORE(out, SET(-1.0f));
    if (g->maxp == 0) return;
    M active = g->active, hit_any = MNONE;
    VI hit_word = ISET(0), hit_st = ISET(0);
    VI st = g->st, en = g->en;
    M ok = g->ok;
    VI word = MGATHER_I(s->words, g->idx, ok);
    for (int p = 0;;) {
        VI mask = SUFFIX(span_bits)(st, en);
        M hm = MAND(ok, INZ(IAND(word, mask)));
        hit_any = MOR(hit_any, hm);
        if (want_t) {
            hit_word = SELI(hm, IAND(word, mask), hit_word);
            hit_st = SELI(hm, st, hit_st);
        }
        active = MANDN(hm, active);
        g->active = active;
        if (++p >= g->maxp || !MBITS(MAND(active, IGT(g->npieces, ISET(p))))) break;
        VI idx;
        if (p == 1) {
            /* the second piece's row was looked up and its word prefetched in prepare */
            idx = g->idx1;
            st = g->st1;
            en = g->en1;
            ok = MAND(g->ok1, active);
        } else {
            idx = SUFFIX(piece)(s, g, p, &st, &en, &ok);
        }
        word = MGATHER_I(s->words, idx, ok);
    }
    unsigned hb = MBITS(hit_any);
    if (!hb) return;
    if (!want_t) {
        STORE(out, SEL(hit_any, zf, SET(-1.0f)));
        return;
    }
    int hw[W], hs[W];
    float qa2[W], dq2[W], t0s[W];
    ISTORE(hw, hit_word);
    ISTORE(hs, hit_st);
    STORE(qa2, g->qa[2]);
    STORE(dq2, g->dq[2]);
    STORE(t0s, g->t0);
    for (int l = 0; l < W; l++) {
        if (!(hb >> l & 1)) continue;
        int fwd = dq2[l] >= 0.0f;
        uint32_t w32 = (uint32_t)hw[l];
        int first = fwd ? __builtin_ctz(w32) : 31 - __builtin_clz(w32);
        float vox = (float)((hs[l] >> 5) * 32 + first);
        float w_start = qa2[l] + dq2[l] * t0s[l];
        float dist = fwd ? vox - w_start : w_start - (vox + 1.0f);
        out[l] = dist > 0.0f ? dist : 0.0f;
    }
}

/* a group's rays: where they leave their surfaces and end, the voxels skipped (ray_setup) */
TARGET static inline void SUFFIX(setup)(const VQRule *r, const V c[9], M dist, V o[3], V e[3], V *skip0, V *skip1) {
    V zf = SET(0.0f);
    const V *p = c, *tg = c + 3, *nm = c + 6;
    V dir[3];
    for (int k = 0; k < 3; k++) dir[k] = SEL(dist, tg[k], SUB(tg[k], p[k]));
    V nn = SQRT(FMA(nm[0], nm[0], FMA(nm[1], nm[1], MUL(nm[2], nm[2]))));
    V ln = SQRT(FMA(dir[0], dir[0], FMA(dir[1], dir[1], MUL(dir[2], dir[2]))));
    M hasn = GT(nn, zf);
    V nd = FMA(nm[0], dir[0], FMA(nm[1], dir[1], MUL(nm[2], dir[2])));
    /* offset world units along the normal turned toward the light */
    V step = SEL(hasn, DIV(SEL(LT(nd, zf), SET(-r->offset), SET(r->offset)), SEL(hasn, nn, SET(1.0f))), zf);
    for (int k = 0; k < 3; k++) o[k] = FMA(nm[k], step, p[k]);
    for (int k = 0; k < 3; k++) e[k] = tg[k];
    if (MBITS(dist)) {
        /* a distant ray ends its distance from the scene's centre plus the scene's diameter away */
        V oc0 = SUB(o[0], SET(r->far_center[0])), oc1 = SUB(o[1], SET(r->far_center[1])), oc2 = SUB(o[2], SET(r->far_center[2]));
        V lt = SQRT(FMA(tg[0], tg[0], FMA(tg[1], tg[1], MUL(tg[2], tg[2]))));
        V reach = DIV(ADD(SQRT(FMA(oc0, oc0, FMA(oc1, oc1, MUL(oc2, oc2)))), SET(r->far)), SEL(GT(lt, zf), lt, SET(1.0f)));
        for (int k = 0; k < 3; k++) e[k] = SEL(dist, FMA(tg[k], reach, o[k]), tg[k]);
    }
    *skip1 = SEL(dist, zf, SET(r->end_skip));
    M use = MAND(hasn, GT(ln, zf));
    if (!(r->slab > 0.0f)) use = MNONE;
    /* slab / sin β voxels, sin β = |n·dir| / (|n| |dir|), at most max_skip */
    V nl = MUL(nn, ln);
    V k = MIN(DIV(MUL(SET(r->slab), nl), MAX(ABS(nd), MUL(SET(1.0e-6f), nl))), SET(r->max_skip));
    *skip0 = SEL(use, MAX(SET(r->skip), k), SET(r->skip));
}

/* the inputs PF_ROUNDS rounds ahead of the round from query i0, streamed from memory while this round
 * computes (on the city's bench rays: 21.5 -> 18.5 ns a query) */
TARGET VQ_INLINE void SUFFIX(prefetch_inputs)(const SoA *b, int i0, int n) {
    int ahead = i0 + PF_ROUNDS * GROUPS * W;
    if (b->stride != 3 || ahead >= n) return;
    int end = ahead + GROUPS * W < n ? ahead + GROUPS * W : n;
    for (int a = 0; a < 3; a++) {
        const char *base = b->d[a] ? (const char *)b->d[a] : (const char *)b->c[3 * a];
        size_t triple = b->d[a] ? 3 * sizeof(double) : 3 * sizeof(float);
        for (const char *q = base + triple * ahead; q < base + triple * end; q += 64) __builtin_prefetch(q);
    }
}

/* queries j0 .. j0 + m - 1 (m <= W) of a batch as a group's rays (setup); returns the lanes holding one */
TARGET VQ_INLINE M SUFFIX(load_group)(const VQRule *r, const SoA *b, int j0, int m, V o[3], V e[3], V *skip0,
                                      V *skip1) {
    M live = IGT(ISET(m), IOTA);
    V c[9];
    if (b->stride == 3) {
        for (int a = 0; a < 3; a++) {
            if (b->d[a]) {
                /* float64 input: rounded to float on the way in */
                LOAD_XYZ64(b->d[a] + 3 * j0, m, live, c + 3 * a);
            } else {
                LOAD_XYZ(b->c[3 * a] + 3 * j0, m, live, c + 3 * a);
            }
        }
    } else {
        for (int k = 0; k < 9; k++) c[k] = m == W ? LOAD(b->c[k] + j0) : MLOAD(b->c[k] + j0, live);
    }
    M dist;
    if (b->distant8) {
        int32_t tmp[W];
        for (int q = 0; q < W; q++) tmp[q] = q < m ? b->distant8[j0 + q] : 0;
        dist = INZ(ILOAD(tmp));
    } else {
        dist = INZ(m == W ? ILOAD(b->distant + j0) : MILOAD(b->distant + j0, live));
    }
    SUFFIX(setup)(r, c, dist, o, e, skip0, skip1);
    return live;
}

/* shadow rays of a batch (batch_scalar's), GROUPS groups of W at a time: every group's first words are
 * prefetched before the first group reads its own, so the groups' memory reads overlap */
TARGET static void SUFFIX(batch)(const VQScene *s, const VQRule *r, int n, const SoA *b, int want_t, float *out) {
    int seg_shift = __builtin_ctz((unsigned)r->seg);
    SUFFIX(Group) grp[GROUPS];
    V o[GROUPS][3], e[GROUPS][3], skip0[GROUPS], skip1[GROUPS];
    M live[GROUPS];
    for (int i0 = 0; i0 < n; i0 += GROUPS * W) {
        int ng = (n - i0 + W - 1) / W;
        ng = ng < GROUPS ? ng : GROUPS;
        float res[GROUPS][W];
        SUFFIX(prefetch_inputs)(b, i0, n);
        for (int h = 0; h < ng; h++) {
            int j0 = i0 + h * W, m = n - j0 < W ? n - j0 : W;
            live[h] = SUFFIX(load_group)(r, b, j0, m, o[h], e[h], &skip0[h], &skip1[h]);
            STORE(res[h], SET(-1.0f));
        }
        /* the world-space arrays in turn (static, then per-frame), each for the lanes still free */
        for (int w = 0; w < s->n_world; w++) {
            for (int h = 0; h < ng; h++) SUFFIX(prepare)(s, w, &grp[h], live[h], o[h], e[h], skip0[h], skip1[h], seg_shift);
            for (int h = 0; h < ng; h++) {
                float part[W];
                SUFFIX(finish)(s, &grp[h], want_t, part);
                V pv = LOAD(part);
                M hit = GE(pv, SET(0.0f));
                STORE(res[h], SEL(hit, pv, LOAD(res[h])));
                live[h] = MANDN(hit, live[h]);
            }
        }
        for (int h = 0; h < ng; h++) {
            int j0 = i0 + h * W, m = n - j0 < W ? n - j0 : W;
            if (s->n_inst > 0 && MBITS(live[h])) {
                float ob[3][W], eb[3][W], s0b[W], s1b[W];
                for (int k = 0; k < 3; k++) { STORE(ob[k], o[h][k]); STORE(eb[k], e[h][k]); }
                STORE(s0b, skip0[h]);
                STORE(s1b, skip1[h]);
                for (unsigned lb = MBITS(live[h]); lb; lb &= lb - 1) {
                    int l = __builtin_ctz(lb);
                    float ol[3] = {ob[0][l], ob[1][l], ob[2][l]}, el[3] = {eb[0][l], eb[1][l], eb[2][l]};
                    res[h][l] = instance_hits(s, ol, el, s0b[l], s1b[l], r->seg, want_t);
                }
            }
            memcpy(out + j0, res[h], sizeof(float) * m);
        }
    }
}

/* the refinement's stage 2 (finish's, for the rays of vq_query_refine): every piece's rows, read for
 * a lane until each of its rays met an occupied voxel or its pieces end. clear[j]: the lanes whose
 * ray j (shifted by du[j], dv[j] voxels; Rays) is still free, in and out */
TARGET VQ_INLINE void SUFFIX(finish_refine)(const VQScene *s, const SUFFIX(Group) *g, int nr, const V *du,
                                            const V *dv, M *clear) {
    if (g->maxp == 0) return;
    M need[MAX_RAYS];
    need[0] = MAND(MAND(g->centre, g->active), clear[0]);
    for (int j = 1; j < nr; j++) need[j] = MAND(g->active, clear[j]);
    for (int p = 0; p < g->maxp; p++) {
        M any = need[0];
        for (int j = 1; j < nr; j++) any = MOR(any, need[j]);
        M live_p = MAND(any, IGT(g->npieces, ISET(p)));
        if (!MBITS(live_p)) break;
        VI st, en;
        V fu, fv;
        SUFFIX(piece_at)(g, p, &st, &en, &fu, &fv);
        VI bits = SUFFIX(span_bits)(st, en);
        for (int j = 0; j < nr; j++) {
            M m = MAND(need[j], live_p), ok;
            if (!MBITS(m)) continue;
            VI idx = SUFFIX(row_word)(s, g, m, ADD(fu, du[j]), ADD(fv, dv[j]), st, &ok);
            M hm = MAND(ok, INZ(IAND(MGATHER_I(s->words, idx, ok), bits)));
            need[j] = MANDN(hm, need[j]);
            clear[j] = MANDN(hm, clear[j]);
        }
    }
}

/* the refinement's stage 1 (prepare's): clip, and the first piece's words of the rays prefetched */
TARGET VQ_INLINE void SUFFIX(prepare_refine)(const VQScene *s, int world, SUFFIX(Group) *g, M live, const V o[3],
                                             const V e[3], V skip0, V skip1, int seg_shift, float widen, int nr,
                                             const V *du, const V *dv) {
    if (!SUFFIX(clip)(s, world, g, live, o, e, skip0, skip1, seg_shift, widen)) return;
    VI st, en;
    V fu, fv;
    SUFFIX(piece_at)(g, 0, &st, &en, &fu, &fv);
    for (int j = 0; j < nr; j++) {
        M ok;
        int idx[W];
        ISTORE(idx, SUFFIX(row_word)(s, g, g->active, ADD(fu, du[j]), ADD(fv, dv[j]), st, &ok));
        for (int l = 0; l < W; l++) __builtin_prefetch(s->words + idx[l]);
    }
}

/* vq_query_refine's batch (batch's rays, nr = R->n per query): out[i] = refine_code of the query's rays */
TARGET VQ_INLINE void SUFFIX(batch_refine_n)(const VQScene *s, const VQRule *r, int n, const SoA *b, const Rays *R,
                                             int nr, uint8_t *out) {
    int seg_shift = __builtin_ctz((unsigned)r->seg);
    SUFFIX(Group) grp[GROUPS];
    V o[GROUPS][3], e[GROUPS][3], skip0[GROUPS], skip1[GROUPS];
    M live[GROUPS], clear[GROUPS][MAX_RAYS];
    V du[MAX_RAYS], dv[MAX_RAYS];
    for (int j = 0; j < nr; j++) {
        du[j] = SET(R->du[j]);
        dv[j] = SET(R->dv[j]);
    }
    for (int i0 = 0; i0 < n; i0 += GROUPS * W) {
        int ng = (n - i0 + W - 1) / W;
        ng = ng < GROUPS ? ng : GROUPS;
        SUFFIX(prefetch_inputs)(b, i0, n);
        for (int h = 0; h < ng; h++) {
            int j0 = i0 + h * W, m = n - j0 < W ? n - j0 : W;
            live[h] = SUFFIX(load_group)(r, b, j0, m, o[h], e[h], &skip0[h], &skip1[h]);
            for (int j = 0; j < nr; j++) clear[h][j] = live[h];
        }
        for (int w = 0; w < s->n_world; w++) {
            /* the shifted rows reach the widest width's voxels beyond the centre ray */
            float widen = R->reach / s->arr_inv_h[s->world_array[w]];
            for (int h = 0; h < ng; h++)
                SUFFIX(prepare_refine)(s, w, &grp[h], live[h], o[h], e[h], skip0[h], skip1[h], seg_shift, widen, nr,
                                       du, dv);
            for (int h = 0; h < ng; h++) {
                SUFFIX(finish_refine)(s, &grp[h], nr, du, dv, clear[h]);
                live[h] = clear[h][0];
                for (int j = 1; j < nr; j++) live[h] = MOR(live[h], clear[h][j]);
            }
        }
        for (int h = 0; h < ng; h++) {
            int j0 = i0 + h * W, m = n - j0 < W ? n - j0 : W;
            unsigned fb[MAX_RAYS];
            for (int j = 0; j < nr; j++) fb[j] = MBITS(clear[h][j]);
            float ob[3][W], eb[3][W], s0b[W], s1b[W];
            int inst = s->n_inst > 0 && MBITS(live[h]);
            if (inst) {
                for (int k = 0; k < 3; k++) { STORE(ob[k], o[h][k]); STORE(eb[k], e[h][k]); }
                STORE(s0b, skip0[h]);
                STORE(s1b, skip1[h]);
            }
            for (int l = 0; l < m; l++) {
                unsigned f = 0;
                for (int j = 0; j < nr; j++) f |= (fb[j] >> l & 1u) << j;
                if (inst && f) {
                    float ol[3] = {ob[0][l], ob[1][l], ob[2][l]}, el[3] = {eb[0][l], eb[1][l], eb[2][l]};
                    instance_refine(s, ol, el, s0b[l], s1b[l], r->seg, R, &f);
                }
                out[j0 + l] = refine_code(R->all & ~f, R);
            }
        }
    }
}

/* batch_refine_n, compiled apart for one width (its loops over the five rays unrolled: vq_query_refine
 * and level 1) */
TARGET static void SUFFIX(batch_refine)(const VQScene *s, const VQRule *r, int n, const SoA *b, const Rays *R,
                                        uint8_t *out) {
    if (R->n == 5) SUFFIX(batch_refine_n)(s, r, n, b, R, 5, out);
    else SUFFIX(batch_refine_n)(s, r, n, b, R, R->n, out);
}

/* Alg. 3 over tiles (vq_shade's, and with a list ``o`` vq_shade_refine's), W points of a tile against
 * one light at a time: light_term's arithmetic in SIMD, the casting lanes compressed into the batch of
 * shadow rays. With material rows ``mat`` (NULL: Lambertian; never with a list) each light's term is split by
 * the BRDF, W points at a time: E kd into radiance, E ks into specular (the batch carries both). */
TARGET VQ_INLINE void SUFFIX(shade_tiles)(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts,
                                          const float *nrm, const float *geo, int64_t n_points, int64_t first_tile,
                                          int64_t n_tiles, int tile, const float *mat, float *radiance,
                                          float *specular, int32_t *blocked, int32_t *facing, Listing *o) {
    /* the batch of shadow rays (flushed while it has room for W more) and the tile in SoA form: points, normals,
     * geometric normals, and with material rows the columns the BRDF reads */
    float sbuf[9][BATCH], srgb[6][BATCH], res[BATCH];
    int32_t sdist[BATCH], swho[BATCH], slight[BATCH];
    uint8_t code[BATCH];
    float P[9][MAX_TILE + W], acc[6][MAX_TILE + W], MR[BRDF_OCCLUSION + 1][MAX_TILE + W];
    int32_t fac[MAX_TILE + W];
    SoA b = {{NULL}, sdist, 1, {NULL}, NULL};
    for (int k = 0; k < 9; k++) b.c[k] = sbuf[k];
    V zf = SET(0.0f);
    for (int64_t t = first_tile; t < first_tile + n_tiles; t++) {
        int64_t i0 = t * tile, i1 = i0 + tile < n_points ? i0 + tile : n_points;
        if (i0 >= i1) break;
        int m = (int)(i1 - i0);
        if (!tile_fits(o, t, m, L->n)) return;
        for (int j = 0; j < m + W; j++) {
            for (int k = 0; k < 3; k++) {
                P[k][j] = j < m ? pts[3 * (i0 + j) + k] : 0.0f;
                P[3 + k][j] = j < m ? nrm[3 * (i0 + j) + k] : 0.0f;
                P[6 + k][j] = j < m ? geo[3 * (i0 + j) + k] : 0.0f;
                acc[k][j] = 0.0f;
            }
            fac[j] = 0;
        }
        if (mat)
            for (int j = 0; j < m + W; j++) {
                for (int c = 0; c <= BRDF_OCCLUSION; c++)
                    MR[c][j] = j < m ? mat[(size_t)BRDF_WIDTH * (i0 + j) + c] : 0.0f;
                for (int k = 3; k < 6; k++) acc[k][j] = 0.0f;
            }
        for (int64_t i = i0; i < i1; i++) {
            radiance[3 * i] = radiance[3 * i + 1] = radiance[3 * i + 2] = 0.0f;
            if (mat) specular[3 * i] = specular[3 * i + 1] = specular[3 * i + 2] = 0.0f;
            blocked[i] = 0;
        }
        int nb = 0;
        for (int l = 0; l < L->n; l++) {
            int flags = L->flags[l], dist = flags & DISTANT;
            const float *lp = L->pos + 3 * (size_t)l, *ax = L->axis + 3 * (size_t)l, *cy = L->cylinder_axis + 3 * (size_t)l;
            const float *cone = L->cone + 3 * (size_t)l, *bs = L->base + 3 * (size_t)l, *fc = L->focus_rgb + 3 * (size_t)l;
            const float *tp = L->target ? L->target + 3 * (size_t)l : lp;     /* the shadow ray's end */
            for (int j0 = 0; j0 < m; j0 += W) {
                M live = IGT(ISET(m - j0), IOTA);
                V p[3], n[3], g[3], dv[3];
                for (int k = 0; k < 3; k++) {
                    p[k] = LOAD(P[k] + j0);
                    n[k] = LOAD(P[3 + k] + j0);
                    g[k] = LOAD(P[6 + k] + j0);
                    dv[k] = dist ? SET(-ax[k]) : SUB(SET(lp[k]), p[k]);
                }
                V d2 = dist ? SET(1.0f) : FMA(dv[0], dv[0], FMA(dv[1], dv[1], MUL(dv[2], dv[2])));
                M ok = MAND(live, MAND(GT(d2, zf), GT(FMA(g[0], dv[0], FMA(g[1], dv[1], MUL(g[2], dv[2]))), zf)));
                V inv_d = RCP(SQRT(MAX(d2, SET(1.0e-30f))));
                V cos_s = MUL(FMA(n[0], dv[0], FMA(n[1], dv[1], MUL(n[2], dv[2]))), inv_d);
                ok = MAND(ok, GT(cos_s, zf));
                if (!MBITS(ok)) continue;
                V gg = cos_s;
                if (!dist) gg = MUL(gg, MUL(SET(L->inv_m2), RCP(MAX(d2, SET(L->min_d2)))));
                if (flags & CYLINDER) {
                    V cc = MUL(FMA(SET(cy[0]), dv[0], FMA(SET(cy[1]), dv[1], MUL(SET(cy[2]), dv[2]))), inv_d);
                    gg = MUL(gg, SQRT(MAX(SUB(SET(1.0f), MUL(cc, cc)), zf)));
                }
                V f = zf;
                if (flags & (ONE_SIDED | SHAPED | FOCUSED)) {
                    V cos_l = MUL(SUB(zf, FMA(SET(ax[0]), dv[0], FMA(SET(ax[1]), dv[1], MUL(SET(ax[2]), dv[2])))), inv_d);
                    if (flags & ONE_SIDED) gg = MUL(gg, MAX(cos_l, zf));
                    if (flags & SHAPED) {
                        if (cone[1] <= 0.0f) {
                            gg = SEL(LT(cos_l, SET(cone[0])), zf, gg);
                        } else {
                            V x = MIN(MAX(DIV(SUB(cos_l, SET(cone[0])), SET(cone[1])), zf), SET(1.0f));
                            gg = MUL(gg, MUL(MUL(x, x), SUB(SET(3.0f), MUL(SET(2.0f), x))));
                        }
                    }
                    if (flags & FOCUSED) {
                        float cl[W], fo[W];
                        STORE(cl, cos_l);
                        for (int q = 0; q < W; q++)
                            fo[q] = powf(cl[q] < 0.0f ? 0.0f : (cl[q] > 1.0f ? 1.0f : cl[q]), cone[2]);
                        f = LOAD(fo);
                    }
                }
                ok = MAND(ok, GT(gg, zf));
                unsigned okb = MBITS(ok);
                if (!okb) continue;
                V gf = MUL(gg, f);
                V rgb[3], spec[3];
                for (int k = 0; k < 3; k++) rgb[k] = FMA(SET(fc[k]), gf, MUL(SET(bs[k]), gg));
                if (mat) {
                    /* the light's term split by the BRDF toward the unit direction to the light */
                    V mv[BRDF_OCCLUSION + 1], lv[3], kd[3], ks[3];
                    for (int c = 0; c <= BRDF_OCCLUSION; c++) mv[c] = LOAD(MR[c] + j0);
                    for (int k = 0; k < 3; k++) lv[k] = MUL(dv[k], inv_d);
                    SUFFIX(brdf_lobes)(mv, n, lv, kd, ks);
                    for (int k = 0; k < 3; k++) {
                        spec[k] = MUL(rgb[k], ks[k]);
                        rgb[k] = MUL(rgb[k], kd[k]);
                    }
                }
                ISTORE(fac + j0, IADD(ILOAD(fac + j0), SELI(ok, ISET(1), ISET(0))));
                if (!(flags & CASTS_SHADOWS)) {
                    for (int k = 0; k < 3; k++) STORE(acc[k] + j0, ADD(LOAD(acc[k] + j0), SEL(ok, rgb[k], zf)));
                    if (mat)
                        for (int k = 0; k < 3; k++)
                            STORE(acc[3 + k] + j0, ADD(LOAD(acc[3 + k] + j0), SEL(ok, spec[k], zf)));
                    continue;
                }
                int c = 0;
                for (int k = 0; k < 3; k++) {
                    c = COMPRESS_F(sbuf[k] + nb, ok, p[k]);
                    COMPRESS_F(sbuf[3 + k] + nb, ok, SET(dist ? -ax[k] : tp[k]));
                    COMPRESS_F(sbuf[6 + k] + nb, ok, g[k]);
                    COMPRESS_F(srgb[k] + nb, ok, rgb[k]);
                    if (mat) COMPRESS_F(srgb[3 + k] + nb, ok, spec[k]);
                }
                COMPRESS_I(swho + nb, ok, IADD(ISET((int)(i0 + j0)), IOTA));
                COMPRESS_I(sdist + nb, ok, ISET(dist));
                if (o)
                    for (int q = nb; q < nb + c; q++) slight[q] = l;
                nb += c;
                if (nb > BATCH - W)
                    nb = flush_shade(SUFFIX(batch), SUFFIX(batch_refine), o, s, r, nb, &b, res, code, srgb, swho,
                                     slight, radiance, mat ? specular : NULL, blocked);
            }
        }
        flush_shade(SUFFIX(batch), SUFFIX(batch_refine), o, s, r, nb, &b, res, code, srgb, swho, slight, radiance,
                    mat ? specular : NULL, blocked);
        for (int j = 0; j < m; j++) {
            for (int k = 0; k < 3; k++) radiance[3 * (i0 + j) + k] += acc[k][j];
            if (mat)
                for (int k = 0; k < 3; k++) specular[3 * (i0 + j) + k] += acc[3 + k][j];
            facing[i0 + j] = fac[j];
        }
    }
}

TARGET static void SUFFIX(shade)(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts,
                                 const float *nrm, const float *geo, int64_t n_points, int64_t first_tile,
                                 int64_t n_tiles, int tile, float *radiance, int32_t *blocked, int32_t *facing) {
    SUFFIX(shade_tiles)(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, NULL, radiance, NULL, blocked,
                        facing, NULL);
}

/* vq_shade with material rows (compiled apart: the Lambertian shading above keeps its code) */
TARGET static void SUFFIX(shade_material)(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts,
                                          const float *nrm, const float *geo, int64_t n_points, int64_t first_tile,
                                          int64_t n_tiles, int tile, const float *mat, float *radiance,
                                          float *specular, int32_t *blocked, int32_t *facing) {
    SUFFIX(shade_tiles)(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, mat, radiance, specular, blocked,
                        facing, NULL);
}

TARGET static void SUFFIX(shade_refine)(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts,
                                        const float *nrm, const float *geo, int64_t n_points, int64_t first_tile,
                                        int64_t n_tiles, int tile, float *radiance, int32_t *blocked,
                                        int32_t *facing, Listing *o) {
    SUFFIX(shade_tiles)(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, NULL, radiance, NULL, blocked,
                        facing, o);
}
