/* The SIMD walk of kernels/svo/svoq.c, written once against the vector API of simd_avx2.h / simd_avx512.h
 * and included once per instruction set. W lanes each walk their own ray through tree tr: one node
 * per iteration (a descent from the root, Fig. 3's restart, then the step out of an empty node); a
 * lane whose ray hit or left takes the next pending ray. The arithmetic is walk_scalar's, operation
 * for operation (svoq.c is compiled without contracting a * b + c), so the answers are the same. */

typedef struct {
    float q[3][W], dir[3][W], inv[3][W], t[W], tb[W];
    int32_t c[3][W], ray[W];
} SUFFIX(Lanes);

/* chunk_rule_scalar, W rays at a time (the same operations in the same order) */
TARGET static void SUFFIX(chunk_rule)(const SvoRule *r, int m, Chunk *ch) {
    const V zero = SET(0.0f), minus = SET(-1.0f);
    ch->n_pending = 0;
    for (int k0 = 0; k0 < m; k0 += W) {
        const int w = m - k0 < W ? m - k0 : W;
        const M lanes = MFROMBITS(w == 32 ? ~0u : (1u << w) - 1);
        V p[3], tg[3], nr[3], d[3], o[3], e[3];
        const M dist = MAND(lanes, INZ(MILOAD(ch->dist + k0, lanes)));
        for (int a = 0; a < 3; a++) {
            p[a] = MLOAD(ch->p[a] + k0, lanes); tg[a] = MLOAD(ch->tg[a] + k0, lanes); nr[a] = MLOAD(ch->nr[a] + k0, lanes);
            d[a] = SEL(dist, tg[a], SUB(tg[a], p[a]));
        }
        V ln = SQRT(ADD(ADD(MUL(d[0], d[0]), MUL(d[1], d[1])), MUL(d[2], d[2])));
        M ok = MAND(lanes, GT(ln, zero));
        V skip0 = SET(r->skip);
        V nn = SQRT(ADD(ADD(MUL(nr[0], nr[0]), MUL(nr[1], nr[1])), MUL(nr[2], nr[2])));
        M has = GT(nn, zero);
        V mm[3];
        for (int a = 0; a < 3; a++) mm[a] = DIV(nr[a], nn);
        V cos_b = DIV(ADD(ADD(MUL(mm[0], d[0]), MUL(mm[1], d[1])), MUL(mm[2], d[2])), ln);
        M flip = LT(cos_b, zero);
        cos_b = SEL(flip, MUL(cos_b, minus), cos_b);
        for (int a = 0; a < 3; a++) {
            mm[a] = SEL(flip, MUL(mm[a], minus), mm[a]);
            o[a] = SEL(has, ADD(p[a], MUL(mm[a], SET(r->offset))), p[a]);
        }
        if (r->slab > 0.0f)
            skip0 = SEL(has, MAX(SET(r->skip), MIN(DIV(SET(r->slab), MAX(cos_b, SET(1.0e-6f))), SET(r->max_skip))), skip0);
        V skip1 = SEL(dist, zero, SET(r->end_skip));
        V fc2 = zero;
        for (int a = 0; a < 3; a++) {
            V fc = SUB(o[a], SET(r->far_center[a]));
            fc2 = a == 0 ? MUL(fc, fc) : ADD(fc2, MUL(fc, fc));
        }
        V reach = ADD(SQRT(fc2), SET(r->far));
        for (int a = 0; a < 3; a++) {
            e[a] = SEL(dist, ADD(o[a], MUL(DIV(d[a], ln), reach)), tg[a]);
            STORE(ch->o[a] + k0, o[a]); STORE(ch->e[a] + k0, e[a]);
        }
        STORE(ch->skip0 + k0, skip0); STORE(ch->skip1 + k0, skip1);
        ISTORE(ch->inf + k0, SELI(dist, ISET(1), ISET(0)));
        ch->n_pending += COMPRESS_I(ch->pending + ch->n_pending, ok, IADD(IOTA, ISET(k0)));
    }
}

/* walk_setup for every pending ray of the chunk, W at a time, into S (same operations, same order) */
TARGET static void SUFFIX(walks)(const SvoScene *s, int tr, const Chunk *ch, Walks *S) {
    const int n = 1 << s->tree_int[4 * tr];
    const V inv_h = SET(s->tree_inv_h[tr]), fn = SET((float)n), zero = SET(0.0f), big = SET(BIG);
    const float *lo = s->tree_lo + 3 * tr;
    for (int j0 = 0; j0 < ch->n_pending; j0 += W) {
        const int m = ch->n_pending - j0 < W ? ch->n_pending - j0 : W;
        const M lanes = MFROMBITS((1u << m) - 1);
        VI k = MILOAD(ch->pending + j0, lanes);
        V q[3], dv[3], dir[3], inv[3];
        for (int a = 0; a < 3; a++) {
            V o = GATHER_F(ch->o[a], k), e = GATHER_F(ch->e[a], k);
            q[a] = MUL(SUB(o, SET(lo[a])), inv_h);
            dv[a] = SUB(MUL(SUB(e, SET(lo[a])), inv_h), q[a]);
        }
        V length = SQRT(ADD(ADD(MUL(dv[0], dv[0]), MUL(dv[1], dv[1])), MUL(dv[2], dv[2])));
        M ok = GT(length, zero);
        V ta = MUL(GATHER_F(ch->skip0, k), inv_h);
        V tb = SUB(length, MUL(GATHER_F(ch->skip1, k), inv_h));
        VI inf = GATHER_I(ch->inf, k);
        tb = SEL(INZ(inf), big, tb);
        for (int a = 0; a < 3; a++) {
            dir[a] = DIV(dv[a], length);
            M nz = MANDN(EQ(dir[a], zero), MALL);
            inv[a] = SEL(nz, DIV(SET(1.0f), dir[a]), big);
            V t0 = MUL(SUB(zero, q[a]), inv[a]), t1 = MUL(SUB(fn, q[a]), inv[a]);
            ta = SEL(nz, MAX(ta, MIN(t0, t1)), ta);
            tb = SEL(nz, MIN(tb, MAX(t0, t1)), tb);
            ok = MANDN(MANDN(nz, MOR(LT(q[a], zero), GE(q[a], fn))), ok);
        }
        ok = MAND(ok, LT(ta, tb));
        for (int a = 0; a < 3; a++) {
            VI c = IMIN(IMAX(CVTT(FLOOR(ADD(q[a], MUL(dir[a], ta)))), ISET(0)), ISET(n - 1));
            STORE(S->q[a] + j0, q[a]); STORE(S->dir[a] + j0, dir[a]); STORE(S->inv[a] + j0, inv[a]);
            ISTORE(S->c[a] + j0, c);
        }
        STORE(S->t + j0, ta); STORE(S->tb + j0, tb);
        ISTORE(S->ok + j0, SELI(MAND(ok, lanes), ISET(1), ISET(0)));
    }
}

/* what one step reads that is the same for every lane: the tree and its sizes */
typedef struct {
    const int32_t *nodes, *tops;
    const uint32_t *bricks;
    int depth, n, top;
} SUFFIX(Tree);

/* refill: every idle lane of L takes the next pending ray that enters the tree (S: their walks) */
TARGET static inline unsigned SUFFIX(refill)(SUFFIX(Lanes) *L, unsigned act, const Walks *S, Chunk *ch, int *next,
                                             int *kept) {
    for (unsigned idle = ~act & ((1u << W) - 1); idle && *next < ch->n_pending; idle &= idle - 1) {
        const int l = __builtin_ctz(idle);
        while (*next < ch->n_pending) {
            const int j = (*next)++, k = ch->pending[j];
            if (!S->ok[j]) {
                ch->pending[(*kept)++] = k;          /* free in this tree: pending for the next */
                continue;
            }
            for (int a = 0; a < 3; a++) {
                L->q[a][l] = S->q[a][j]; L->dir[a][l] = S->dir[a][j]; L->inv[a][l] = S->inv[a][j];
                L->c[a][l] = S->c[a][j];
            }
            L->t[l] = S->t[j]; L->tb[l] = S->tb[j]; L->ray[l] = k;
            act |= 1u << l;
            break;
        }
    }
    return act;
}

/* one step of every active lane: a descent (levels 1 .. top in one read of the top table, then the
 * tree), then a hit or the step out of the empty node reached. Returns the lanes still walking;
 * hits are written to out, rays that left the segment or the grid appended to pending. */
TARGET static inline unsigned SUFFIX(step)(const SUFFIX(Tree) *T, SUFFIX(Lanes) *L, unsigned act, Chunk *ch,
                                           int *kept, float *out) {
    const int depth = T->depth, n = T->n, top = T->top;
    const V zero = SET(0.0f), big = SET(BIG);
    const VI izero = ISET(0), one = ISET(1);
    const M live0 = MFROMBITS(act);
    V q[3], dir[3], inv[3];
    VI c[3];
    for (int a = 0; a < 3; a++) {
        q[a] = LOAD(L->q[a]); dir[a] = LOAD(L->dir[a]); inv[a] = LOAD(L->inv[a]); c[a] = ILOAD(L->c[a]);
    }
    V t = LOAD(L->t), tb = LOAD(L->tb);
    const int ts = depth - top;
    VI cell = IADD(ISLL(IADD(ISLL(ISRL(c[2], ts), top), ISRL(c[1], ts)), top), ISRL(c[0], ts));
    VI g = MGATHER_I(T->tops, cell, live0);
    M live = MAND(live0, IGT(g, izero));
    VI size = SELI(live, izero, ISLLV(one, ISUB(izero, g)));
    M hit = MNONE;
    /* levels top + 1 .. depth - 2 of the tree; an entry at level depth - 2 is a brick (index + 1) */
    for (int level = top + 1; level < depth - 1 && MBITS(live); level++) {
        const int shift = depth - level;
        VI oct = IOR(IAND(ISRL(c[0], shift), one),
                     IOR(ISLL(IAND(ISRL(c[1], shift), one), 1), ISLL(IAND(ISRL(c[2], shift), one), 2)));
        VI entry = MGATHER_I(T->nodes, IADD(ISLL(g, 3), oct), live);
        M empty = MAND(live, IEQ(entry, izero));
        size = SELI(empty, ISET(1 << shift), size);
        live = MANDN(empty, live);
        g = entry;
    }
    if (MBITS(live)) {
        /* a brick: its 2^3 octant, then the voxel. Both lie in the brick's word (z & 3) >> 1: one read */
        VI sub = IOR(IAND(ISRL(c[0], 1), one),
                     IOR(ISLL(IAND(ISRL(c[1], 1), one), 1), ISLL(IAND(ISRL(c[2], 1), one), 2)));
        VI sh = IADD(ISLL(IAND(sub, one), 1), ISLL(IAND(ISRL(sub, 1), one), 3));
        VI om = IOR(ISLLV(ISET(0x33), sh), ISLLV(ISET(0x33), IADD(sh, ISET(16))));
        VI w = MGATHER_I(T->bricks, IADD(ISLL(ISUB(g, one), 1), ISRL(sub, 2)), live);
        M sub_empty = MAND(live, IEQ(IAND(w, om), izero));
        size = SELI(sub_empty, ISET(2), size);
        M rest = MANDN(sub_empty, live);
        VI bit = IADD(IAND(c[0], ISET(3)), IADD(ISLL(IAND(c[1], ISET(3)), 2), ISLL(IAND(c[2], ISET(3)), 4)));
        hit = MAND(rest, INZ(IAND(ISRLV(w, IAND(bit, ISET(31))), one)));
        size = SELI(MANDN(hit, rest), one, size);
    }
    /* leave the empty nodes through their far faces */
    M go = MANDN(hit, live0);
    VI m = ISUB(izero, size);                     /* ~(size - 1) */
    VI c0[3], nc[3];
    V tf[3];
    M pos[3];
    for (int a = 0; a < 3; a++) {
        c0[a] = IAND(c[a], m);
        pos[a] = GT(dir[a], zero);
        V f = CVTF(SELI(pos[a], IADD(c0[a], size), c0[a]));
        tf[a] = SEL(EQ(dir[a], zero), big, MUL(SUB(f, q[a]), inv[a]));
    }
    V t_exit = MIN(tf[0], MIN(tf[1], tf[2]));
    M gone = MAND(go, GE(t_exit, tb));
    t = SEL(go, MAX(t, t_exit), t);
    for (int a = 0; a < 3; a++)
        nc[a] = IMIN(IMAX(CVTT(FLOOR(ADD(q[a], MUL(dir[a], t_exit)))), c0[a]), IADD(c0[a], ISUB(size, one)));
    M xs = MAND(LE(tf[0], tf[1]), LE(tf[0], tf[2]));
    M ys = MANDN(xs, LE(tf[1], tf[2]));
    M zs = MANDN(MOR(xs, ys), MALL);
    M sel[3] = {xs, ys, zs};
    M outside = MNONE;
    for (int a = 0; a < 3; a++) {
        VI across = SELI(pos[a], IADD(c0[a], size), ISUB(c0[a], one));
        nc[a] = SELI(sel[a], across, nc[a]);
        outside = MOR(outside, MOR(IGT(izero, nc[a]), IGT(nc[a], ISET(n - 1))));
    }
    gone = MOR(gone, MAND(go, outside));
    M cont = MANDN(gone, go);
    for (int a = 0; a < 3; a++) ISTORE(L->c[a], SELI(cont, nc[a], c[a]));
    STORE(L->t, t);
    /* lanes that end: hits written, free rays pending for the next tree */
    const unsigned hb = MBITS(hit) & act, gb = MBITS(gone) & act;
    for (unsigned b = hb; b; b &= b - 1) out[L->ray[__builtin_ctz(b)]] = L->t[__builtin_ctz(b)];
    for (unsigned b = gb; b; b &= b - 1) ch->pending[(*kept)++] = L->ray[__builtin_ctz(b)];
    return act & ~(hb | gb);
}

/* tree tr for the chunk's pending rays: GROUPS groups of W lanes stepped in turn (their chains of
 * gathers are independent, so the CPU overlaps them), hits written to out, the rest left pending */
TARGET static void SUFFIX(chunk_tree)(const SvoScene *s, int tr, Chunk *ch, float *out) {
    const int32_t *ti = s->tree_int + 4 * tr;
    SUFFIX(Tree) T;
    T.depth = ti[0];
    T.nodes = s->nodes + ti[1];
    T.bricks = s->bricks + 2 * (int64_t)ti[2];
    T.tops = s->tops + ti[3];
    T.n = 1 << T.depth;
    T.top = T.depth - 2 < s->top_level ? T.depth - 2 : s->top_level;     /* svo/tree.py: top_level */
    static __thread Walks S;
    SUFFIX(walks)(s, tr, ch, &S);
    SUFFIX(Lanes) L[GROUPS];
    unsigned act[GROUPS] = {0};
    int next = 0, kept = 0;
    for (;;) {
        unsigned any = 0;
        for (int g = 0; g < GROUPS; g++) any |= act[g] = SUFFIX(refill)(&L[g], act[g], &S, ch, &next, &kept);
        if (!any) break;
        for (int g = 0; g < GROUPS; g++)
            if (act[g]) act[g] = SUFFIX(step)(&T, &L[g], act[g], ch, &kept, out);
    }
    ch->n_pending = kept;
}
