/* The LGH's CPU kernels in C: kernels/lgh/shading.py's lgh_gather and cluster_targets, the same rule
 * in the same order, one point (one sample) at a time over a block of rows, called from the thread
 * pool (ctypes releases the GIL).
 *
 * Why: Warp runs a CPU launch on one thread and its code for the gather spent about 25 ns per light
 * visited (city, 100k VPLs, alpha 4: some 4,300 lights in each of two sweeps per point). Warp's random
 * numbers (PCG hash, randf) are reproduced bit for bit; the arithmetic follows the Warp kernels
 * expression by expression, built without contraction (-ffp-contract=off), so the picks agree with
 * them (usdml.lighting.lgh.native states the agreement and tests/test_lgh_native.py checks it).
 * Pure compute: arrays in, arrays out.
 */

#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "brdf.h"

#define EXPORT __attribute__((visibility("default")))

static const float LUMA0 = 0.2126f, LUMA1 = 0.7152f, LUMA2 = 0.0722f;

/* ---- Warp's random numbers (warp/native/rand.h) ---- */

static inline uint32_t pcg(uint32_t state) {
    uint32_t b = state * 747796405u + 2891336453u;
    uint32_t c = ((b >> ((b >> 28u) + 4u)) ^ b) * 277803737u;
    return (c >> 22u) ^ c;
}

static inline uint32_t rand_init(int32_t seed, int32_t offset) {
    return pcg((uint32_t)seed + pcg((uint32_t)offset));
}

static inline float randf(uint32_t *state) {
    *state = pcg(*state);
    return (float)(*state >> 8) * (1.0f / 16777216.0f);
}

static inline float randn(uint32_t *state) {
    float a = randf(state);
    float b = randf(state);
    return sqrtf(-2.0f * logf(a + 5.96e-8f)) * cosf(2.0f * 3.14159265358979323846f * b);
}

static inline float clampf(float x, float a, float b) { return fminf(fmaxf(a, x), b); }

static inline float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* ---- the gather (lgh_gather) ---- */

typedef struct {
    int32_t n_levels;
    const float *level_origin;     /* (L, 3) */
    const float *level_spacing;    /* (L,) */
    const int32_t *level_dims;     /* (L, 3) */
    const int32_t *level_offset;   /* (L,) */
    const int32_t *vertex_light;   /* vertex -> light or -1 */
    const float *light_pos;        /* (M, 3) */
    const float *light_int;        /* (M, 3) */
    const float *light_lobe;       /* (M, 3) */
    const float *light_std;        /* (M,) */
    const float *light_count;      /* (M,) */
    int32_t m;
    int32_t s0;
    int32_t s0_cells[3];
    const int32_t *s0_start;
    const int32_t *s0_light;
    const float *s0_pos, *s0_int, *s0_lobe;
    float alpha, inv_m2, clamp_d2;
    int32_t samples, jitter, seed, tiles, stratified;
    /* which vertices hold a light, a bit each: per level its columns (i, j) of occ_words[l] 64-bit words
     * along k from occ_offset[l]; the walk reads the vertex's light only where its bit is set (most of
     * a point's vertices are empty, and their entries were cache misses) */
    const uint64_t *occupancy;
    const int64_t *occ_offset;
    const int32_t *occ_words;
    /* the level each entry of level_* is (0 = S1): a hierarchy split by VPL normal (usdml.lighting.lgh.build's
     * build_lgh_split) lists each level once per normal class on one grid; top_rank is the coarsest */
    const int32_t *level_rank;
    int32_t top_rank;
} Gather;

typedef struct {
    float *irradiance;     /* (P, 3) */
    float *count;          /* (P,) */
    float *sample_pos;     /* (P, stride, 3) */
    int32_t *sample_ok;    /* (P, stride) */
    int32_t *sample_light; /* (P, stride) */
    float *sample_weight;  /* (P, stride, 3) */
    float *sample_blend;   /* (P, stride) */
    float *sample_lum;     /* (P, stride) */
    int32_t stride;        /* max(samples, 1) */
} Outputs;

typedef struct {
    uint32_t rng;
    float acc[3], count, total, run;
    int32_t s;
    float u, step, xi;
} Sweep;

static inline float blend(int level, int top, float d, float r) {
    if (level == top && level == 0) return 1.0f;
    float w = 1.0f;
    if (level > 0) {
        float x = clampf((d - 0.5f * r) / (0.5f * r), 0.0f, 1.0f);
        w = x * x * (3.0f - 2.0f * x);
    }
    if (level < top) {
        float y = clampf((d - r) / r, 0.0f, 1.0f);
        w = w * (1.0f - y * y * (3.0f - 2.0f * y));
    }
    return w;
}

static inline float lobe_factor(const float *nu, const float *w, float d) {
    float c = -dot3(nu, w) / d;
    return 1.0f - sqrtf(dot3(nu, nu)) + 4.0f * fmaxf(c, 0.0f);
}

/* light_term: e (3) and B in e4[3]; 0 where the light does not reach the point */
static inline void light_term(const float *p, const float *n, const float *q, const float *intensity, const float *nu,
                              int level, int top, float r, float inv_m2, float clamp_d2, float scale, float *e4) {
    float w[3] = {q[0] - p[0], q[1] - p[1], q[2] - p[2]};
    float d2 = dot3(w, w);
    float d = sqrtf(d2);
    e4[0] = e4[1] = e4[2] = e4[3] = 0.0f;
    if (d <= 0.0f) return;
    float b = blend(level, top, d, r);
    float cos_s = dot3(n, w) / d;
    if (b <= 0.0f || cos_s <= 0.0f) return;
    float lobe = lobe_factor(nu, w, d);
    if (lobe <= 0.0f) return;
    float s = b * lobe * cos_s * inv_m2 / fmaxf(d2, clamp_d2) * scale;
    e4[0] = intensity[0] * s;
    e4[1] = intensity[1] * s;
    e4[2] = intensity[2] * s;
    e4[3] = b;
}

static inline void take(uint32_t *rng, const float *e, float f, float b, int32_t s, int64_t row, const float *q,
                        float sd, int32_t v, const Outputs *o) {
    float jitter[3] = {0.0f, 0.0f, 0.0f};
    if (sd > 0.0f) {
        jitter[0] = randn(rng) * sd;
        jitter[1] = randn(rng) * sd;
        jitter[2] = randn(rng) * sd;
    }
    int64_t at = row * o->stride + s;
    o->sample_pos[3 * at + 0] = q[0] + jitter[0];
    o->sample_pos[3 * at + 1] = q[1] + jitter[1];
    o->sample_pos[3 * at + 2] = q[2] + jitter[2];
    o->sample_ok[at] = 1;
    o->sample_light[at] = v;
    o->sample_weight[3 * at + 0] = e[0] / f;
    o->sample_weight[3 * at + 1] = e[1] / f;
    o->sample_weight[3 * at + 2] = e[2] / f;
    o->sample_blend[at] = b / f;
    o->sample_lum[at] = f;
}

/* Appendix A's streaming pick (not stratified) */
static inline void pick(uint32_t *rng, const float *e, float f, float b, float total, int32_t samples, int64_t row,
                        const float *q, float sd, int32_t v, const Outputs *o) {
    float p = f / total;
    float lq = 0.0f;
    if (p < 1.0e-4f)
        lq = -p * (1.0f + 0.5f * p);
    else if (p < 1.0f)
        lq = logf(1.0f - p);
    int32_t s = -1;
    while (s < samples) {
        if (p >= 1.0f) {
            s = s + 1;
        } else {
            float gap = logf(fmaxf(randf(rng), 1.0e-30f)) / lq;
            if (gap >= (float)(samples - s - 1)) break;
            s = s + 1 + (int32_t)gap;
        }
        if (s >= samples) break;
        take(rng, e, f, b, s, row, q, sd, v, o);
    }
}

static inline void visit(Sweep *st, int sweep, int stratified, const float *e4, float scale, float count,
                         int32_t samples, int64_t row, const float *q, float sd, int32_t v, const Outputs *o) {
    float f = e4[0] * LUMA0 + e4[1] * LUMA1 + e4[2] * LUMA2;
    if (f <= 0.0f) return;
    float b = e4[3] * scale;
    if (sweep == 0) {
        st->acc[0] = st->acc[0] + e4[0];
        st->acc[1] = st->acc[1] + e4[1];
        st->acc[2] = st->acc[2] + e4[2];
        st->count = st->count + b * count;
        st->total = st->total + f;
        if (stratified == 0) pick(&st->rng, e4, f, b, st->total, samples, row, q, sd, v, o);
        return;
    }
    st->run = st->run + f;
    while (st->s < samples && st->u < st->run) {
        take(&st->rng, e4, f, b, st->s, row, q, sd, v, o);
        st->s = st->s + 1;
        st->u = ((float)st->s + st->xi) * st->step;
    }
}

static inline int32_t imax(int32_t a, int32_t b) { return a > b ? a : b; }
static inline int32_t imin(int32_t a, int32_t b) { return a < b ? a : b; }

/* the lights that reach a point, in the Warp kernel's visiting order: light_term's e and B, and the
 * light's index as a sample names it (M + input light for S0) */
typedef struct {
    float e[4];
    int32_t v;
} Reached;

typedef struct {
    Reached *at;
    int64_t n, cap;
} List;

static int push(List *list, const float *e4, int32_t v) {
    if (list->n == list->cap) {
        int64_t cap = list->cap ? 2 * list->cap : 4096;
        Reached *grown = (Reached *)realloc(list->at, (size_t)cap * sizeof(Reached));
        if (!grown) return 0;
        list->at = grown;
        list->cap = cap;
    }
    Reached *r = list->at + list->n++;
    r->e[0] = e4[0];
    r->e[1] = e4[1];
    r->e[2] = e4[2];
    r->e[3] = e4[3];
    r->v = v;
    return 1;
}

/* A batch of up to 8 candidate lights of one level (the same blending level and radius): their
 * light_term, then those that reach the point pushed in order. Scalar C, or AVX2 with the same IEEE
 * operations in the same order (division and square root are correctly rounded in both): the same bits. */
typedef struct {
    int32_t v[8];
    int n;
} Batch;

typedef struct {
    const float *pos, *inten, *lobe;   /* the level's tables (grid lights, or S0's input lights) */
    int32_t name_base;                 /* a sample's name for light v: name_base + v */
    int level, top;
    float r, inv_m2, clamp_d2, scale;
} Level;

static int flush_scalar(const Level *lv, const float *p, const float *n, Batch *b, List *list) {
    for (int i = 0; i < b->n; i++) {
        int32_t v = b->v[i];
        float e4[4];
        light_term(p, n, lv->pos + 3 * (int64_t)v, lv->inten + 3 * (int64_t)v, lv->lobe + 3 * (int64_t)v, lv->level,
                   lv->top, lv->r, lv->inv_m2, lv->clamp_d2, lv->scale, e4);
        if (e4[0] * LUMA0 + e4[1] * LUMA1 + e4[2] * LUMA2 > 0.0f && !push(list, e4, lv->name_base + v)) return 0;
    }
    b->n = 0;
    return 1;
}

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define LGHQ_AVX2 1

__attribute__((target("avx2"))) static int flush_avx2(const Level *lv, const float *p, const float *n, Batch *b,
                                                      List *list) {
    if (b->n == 0) return 1;
    int32_t idx[8];
    for (int i = 0; i < 8; i++) idx[i] = 3 * b->v[i < b->n ? i : 0];
    __m256i ix = _mm256_loadu_si256((const __m256i *)idx);
    __m256i iy = _mm256_add_epi32(ix, _mm256_set1_epi32(1)), iz = _mm256_add_epi32(ix, _mm256_set1_epi32(2));
    __m256 wx = _mm256_sub_ps(_mm256_i32gather_ps(lv->pos, ix, 4), _mm256_set1_ps(p[0]));
    __m256 wy = _mm256_sub_ps(_mm256_i32gather_ps(lv->pos, iy, 4), _mm256_set1_ps(p[1]));
    __m256 wz = _mm256_sub_ps(_mm256_i32gather_ps(lv->pos, iz, 4), _mm256_set1_ps(p[2]));
    __m256 d2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(wx, wx), _mm256_mul_ps(wy, wy)), _mm256_mul_ps(wz, wz));
    __m256 d = _mm256_sqrt_ps(d2);
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), two = _mm256_set1_ps(2.0f),
                 three = _mm256_set1_ps(3.0f);
    __m256 w = one;
    if (!(lv->level == lv->top && lv->level == 0)) {
        if (lv->level > 0) {
            __m256 half = _mm256_set1_ps(0.5f * lv->r);
            __m256 x = _mm256_div_ps(_mm256_sub_ps(d, half), half);
            x = _mm256_min_ps(_mm256_max_ps(zero, x), one);
            w = _mm256_mul_ps(_mm256_mul_ps(x, x), _mm256_sub_ps(three, _mm256_mul_ps(two, x)));
        }
        if (lv->level < lv->top) {
            __m256 r = _mm256_set1_ps(lv->r);
            __m256 y = _mm256_div_ps(_mm256_sub_ps(d, r), r);
            y = _mm256_min_ps(_mm256_max_ps(zero, y), one);
            w = _mm256_mul_ps(w, _mm256_sub_ps(one, _mm256_mul_ps(_mm256_mul_ps(y, y),
                                                                  _mm256_sub_ps(three, _mm256_mul_ps(two, y)))));
        }
    }
    __m256 ndw = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_set1_ps(n[0]), wx),
                                             _mm256_mul_ps(_mm256_set1_ps(n[1]), wy)),
                               _mm256_mul_ps(_mm256_set1_ps(n[2]), wz));
    __m256 cos_s = _mm256_div_ps(ndw, d);
    __m256 ux = _mm256_i32gather_ps(lv->lobe, ix, 4), uy = _mm256_i32gather_ps(lv->lobe, iy, 4),
           uz = _mm256_i32gather_ps(lv->lobe, iz, 4);
    __m256 udw = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ux, wx), _mm256_mul_ps(uy, wy)), _mm256_mul_ps(uz, wz));
    __m256 c = _mm256_div_ps(_mm256_sub_ps(zero, udw), d);
    __m256 len = _mm256_sqrt_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ux, ux), _mm256_mul_ps(uy, uy)),
                                              _mm256_mul_ps(uz, uz)));
    __m256 lobe = _mm256_add_ps(_mm256_sub_ps(one, len), _mm256_mul_ps(_mm256_set1_ps(4.0f), _mm256_max_ps(c, zero)));
    __m256 ok = _mm256_and_ps(_mm256_and_ps(_mm256_cmp_ps(d, zero, _CMP_GT_OQ), _mm256_cmp_ps(w, zero, _CMP_GT_OQ)),
                              _mm256_and_ps(_mm256_cmp_ps(cos_s, zero, _CMP_GT_OQ), _mm256_cmp_ps(lobe, zero, _CMP_GT_OQ)));
    __m256 sc = _mm256_mul_ps(_mm256_mul_ps(_mm256_mul_ps(w, lobe), cos_s), _mm256_set1_ps(lv->inv_m2));
    sc = _mm256_mul_ps(_mm256_div_ps(sc, _mm256_max_ps(d2, _mm256_set1_ps(lv->clamp_d2))), _mm256_set1_ps(lv->scale));
    sc = _mm256_and_ps(sc, ok);
    w = _mm256_and_ps(w, ok);
    __m256 ex = _mm256_mul_ps(_mm256_i32gather_ps(lv->inten, ix, 4), sc);
    __m256 ey = _mm256_mul_ps(_mm256_i32gather_ps(lv->inten, iy, 4), sc);
    __m256 ez = _mm256_mul_ps(_mm256_i32gather_ps(lv->inten, iz, 4), sc);
    float e0[8], e1[8], e2[8], bb[8];
    _mm256_storeu_ps(e0, ex);
    _mm256_storeu_ps(e1, ey);
    _mm256_storeu_ps(e2, ez);
    _mm256_storeu_ps(bb, w);
    for (int i = 0; i < b->n; i++) {
        float e4[4] = {e0[i], e1[i], e2[i], bb[i]};
        if (e4[0] * LUMA0 + e4[1] * LUMA1 + e4[2] * LUMA2 > 0.0f && !push(list, e4, lv->name_base + b->v[i])) return 0;
    }
    b->n = 0;
    return 1;
}
#endif

/* which batch evaluator this CPU runs: 8 (AVX2) or 1 (scalar); lghq_simd(0) forces scalar,
 * lghq_simd(1) takes AVX2 where the CPU has it, lghq_simd(-1) only says which is in use */
static int use_avx2 = -1;

EXPORT int lghq_simd(int allow) {
    if (allow < 0 && use_avx2 >= 0) return use_avx2 ? 8 : 1;
    if (allow < 0) allow = 1;
#ifdef LGHQ_AVX2
    use_avx2 = allow && __builtin_cpu_supports("avx2");
#else
    (void)allow;
    use_avx2 = 0;
#endif
    return use_avx2 ? 8 : 1;
}

static inline int flush(const Level *lv, const float *p, const float *n, Batch *b, List *list) {
#ifdef LGHQ_AVX2
    if (use_avx2) return flush_avx2(lv, p, n, b, list);
#endif
    return flush_scalar(lv, p, n, b, list);
}

static inline int add(const Level *lv, const float *p, const float *n, Batch *b, List *list, int32_t v) {
    b->v[b->n++] = v;
    return b->n < 8 ? 1 : flush(lv, p, n, b, list);
}

/* every light whose term at the point is non-zero, in order (a light of luminance 0 visits nothing) */
static int collect(const Gather *g, const float *p, const float *n, int32_t tile, List *list) {
    const float scale = (float)g->tiles;
    const int top = g->top_rank + g->s0;
    Batch batch = {{0}, 0};
    list->n = 0;
    if (g->s0 == 1) {
        float h1 = g->level_spacing[0];
        float r0 = g->alpha * 0.5f * h1;
        float rel0[3] = {(p[0] - g->level_origin[0]) / h1, (p[1] - g->level_origin[1]) / h1,
                         (p[2] - g->level_origin[2]) / h1};
        int32_t reach = (int32_t)ceilf(g->alpha);
        int32_t ci = (int32_t)floorf(rel0[0]), cj = (int32_t)floorf(rel0[1]), ck = (int32_t)floorf(rel0[2]);
        const int32_t *cells = g->s0_cells;
        Level lv0 = {g->s0_pos, g->s0_int, g->s0_lobe, g->m, 0, top, r0, g->inv_m2, g->clamp_d2, scale};
        for (int32_t i = imax(ci - reach, 0); i <= imin(ci + reach, cells[0] - 1); i++)
            for (int32_t j = imax(cj - reach, 0); j <= imin(cj + reach, cells[1] - 1); j++)
                for (int32_t k = imax(ck - reach, 0); k <= imin(ck + reach, cells[2] - 1); k++) {
                    int32_t c = (i * cells[1] + j) * cells[2] + k;
                    for (int32_t e_i = g->s0_start[c]; e_i < g->s0_start[c + 1]; e_i++) {
                        int32_t v = g->s0_light[e_i];
                        if (g->tiles > 1 && v % g->tiles != tile) continue;
                        if (!add(&lv0, p, n, &batch, list, v)) return 0;
                    }
                }
        if (!flush(&lv0, p, n, &batch, list)) return 0;
    }
    for (int l = 0; l < g->n_levels; l++) {
        float h = g->level_spacing[l];
        float r = g->alpha * h;
        const int32_t *dims = g->level_dims + 3 * l;
        const float *origin = g->level_origin + 3 * l;
        float rel[3] = {(p[0] - origin[0]) / h, (p[1] - origin[1]) / h, (p[2] - origin[2]) / h};
        float span = 2.0f * g->alpha + 1.7321f;
        const int32_t rank = g->level_rank[l];
        if (rank == g->top_rank) span = 1.0e9f;
        const int32_t *vl = g->vertex_light + g->level_offset[l];
        const uint64_t *occ = g->occupancy + g->occ_offset[l];
        const int32_t words = g->occ_words[l];
        Level lvl = {g->light_pos, g->light_int, g->light_lobe, 0, rank + g->s0, top, r, g->inv_m2, g->clamp_d2, scale};
        int32_t i0 = imax((int32_t)ceilf(rel[0] - span), 0);
        int32_t i1 = imin((int32_t)floorf(rel[0] + span), dims[0] - 1);
        for (int32_t i = i0; i <= i1; i++) {
            float dx = (float)i - rel[0];
            float ry = sqrtf(fmaxf(span * span - dx * dx, 0.0f));
            int32_t j0 = imax((int32_t)ceilf(rel[1] - ry), 0);
            int32_t j1 = imin((int32_t)floorf(rel[1] + ry), dims[1] - 1);
            for (int32_t j = j0; j <= j1; j++) {
                float dy = (float)j - rel[1];
                float rz = sqrtf(fmaxf(span * span - dx * dx - dy * dy, 0.0f));
                int32_t k0 = imax((int32_t)ceilf(rel[2] - rz), 0);
                int32_t k1 = imin((int32_t)floorf(rel[2] + rz), dims[2] - 1);
                if (k0 > k1) continue;
                const int32_t *col = vl + (i * dims[1] + j) * dims[2];
                const uint64_t *bits = occ + ((int64_t)i * dims[1] + j) * words;
                for (int32_t w = k0 >> 6; w <= (k1 >> 6); w++) {
                    uint64_t mask = bits[w];
                    if (w == (k0 >> 6)) mask &= ~0ULL << (k0 & 63);
                    if (w == (k1 >> 6)) mask &= ~0ULL >> (63 - (k1 & 63));
                    while (mask) {            /* the set bits in ascending k: the Warp kernel's order */
                        int32_t k = (w << 6) + __builtin_ctzll(mask);
                        mask &= mask - 1;
                        int32_t v = col[k];
                        if (g->tiles > 1 && v % g->tiles != tile) continue;
                        if (!add(&lvl, p, n, &batch, list, v)) return 0;
                    }
                }
            }
        }
        if (!flush(&lvl, p, n, &batch, list)) return 0;
    }
    return 1;
}

/* ---- the preview surface (issue 51): a light's term as the outgoing radiance it adds ---- */

static const float LGHQ_PI = 3.14159265358979f;     /* np.float32(np.pi), as the NumPy shading divides rho by */

/* the radiance r = e (rho/pi kd + ks) and its specular part s = e ks that irradiance e (3) from a light at q adds
 * at p (material row m, unit shading normal n, rp = rho/pi): the BRDF evaluated toward q, a grid light's
 * illumination centre (paper 004 shades each grid light as a point light there) */
static inline void brdf_radiance(const float *m, const float *rp, const float *p, const float *n, const float *q,
                                 const float *e, float *r, float *s) {
    float l[3] = {q[0] - p[0], q[1] - p[1], q[2] - p[2]};
    float d = sqrtf(dot3(l, l));
    r[0] = r[1] = r[2] = s[0] = s[1] = s[2] = 0.0f;
    if (!(d > 0.0f)) return;
    l[0] = l[0] / d, l[1] = l[1] / d, l[2] = l[2] / d;
    float kd[3], ks[3];
    brdf_terms(m, n, l, kd, ks);
    for (int c = 0; c < 3; c++) {
        s[c] = e[c] * ks[c];
        r[c] = e[c] * (rp[c] * kd[c] + ks[c]);
    }
}

/* The Warp kernel's two sweeps over the lights that reach the point, each light's term computed once
 * (the Warp kernel computes it in both sweeps): the same sums, picks and random numbers. With a material row
 * `m` (and rp = rho/pi), each light's irradiance becomes the radiance it adds (brdf_radiance) before the sweeps:
 * the sums are the point's outgoing radiance, the shadow samples are drawn by its luminance (the BRDF weighs
 * the draws), `spec` gets the specular part; the count stays the lights that reach the point. */
static int gather_point(const Gather *g, const float *p, const float *n, int32_t tile, uint32_t rng, int64_t row,
                        const Outputs *o, List *list, const float *mat, const float *rp, float *spec) {
    if (!collect(g, p, n, tile, list)) return 0;
    float reach = 0.0f;
    if (mat != NULL) {
        const float scale = (float)g->tiles;
        float sp[3] = {0.0f, 0.0f, 0.0f};
        for (int64_t a = 0; a < list->n; a++) {
            Reached *r = list->at + a;
            int32_t v = r->v;
            const float *q = v >= g->m ? g->s0_pos + 3 * (int64_t)(v - g->m) : g->light_pos + 3 * (int64_t)v;
            reach = reach + r->e[3] * scale * (v >= g->m ? 1.0f : g->light_count[v]);
            float rad[3], s[3];
            brdf_radiance(mat, rp, p, n, q, r->e, rad, s);
            sp[0] += s[0], sp[1] += s[1], sp[2] += s[2];
            r->e[0] = rad[0], r->e[1] = rad[1], r->e[2] = rad[2];
        }
        spec[3 * row + 0] = sp[0], spec[3 * row + 1] = sp[1], spec[3 * row + 2] = sp[2];
    }
    Sweep st = {0};
    st.rng = rng;
    const int32_t samples = g->samples;
    const float scale = (float)g->tiles;
    const int32_t m = g->m;
    int sweeps = (g->stratified == 1 && samples > 0) ? 2 : 1;
    for (int sweep = 0; sweep < sweeps; sweep++) {
        if (sweep == 1) {
            if (st.total <= 0.0f) break;
            st.step = st.total / (float)samples;
            st.xi = randf(&st.rng);
            st.u = st.xi * st.step;
        }
        for (int64_t a = 0; a < list->n; a++) {
            if (sweep == 1 && st.s >= samples) break;
            const Reached *r = list->at + a;
            int32_t v = r->v;
            const float *q = v >= m ? g->s0_pos + 3 * (int64_t)(v - m) : g->light_pos + 3 * (int64_t)v;
            float count = v >= m ? 1.0f : g->light_count[v];
            float sd = v >= m ? 0.0f : g->light_std[v] * (float)g->jitter;
            visit(&st, sweep, g->stratified, r->e, scale, count, samples, row, q, sd, v, o);
        }
    }
    o->irradiance[3 * row + 0] = st.acc[0];
    o->irradiance[3 * row + 1] = st.acc[1];
    o->irradiance[3 * row + 2] = st.acc[2];
    o->count[row] = mat != NULL ? reach : st.count;
    return 1;
}

/* Points lo .. hi - 1 of the arrays (rows of points, normals, tile and the outputs); point i's random
 * stream is numbered first + i, as the Warp kernel's first + tid. The outputs start zeroed. Returns 0
 * when out of memory (the list of a point's lights). */
EXPORT int lghq_gather(const Gather *g, const float *points, const float *normals, const int32_t *tile, int64_t lo,
                       int64_t hi, int64_t first, const Outputs *o) {
    List list = {NULL, 0, 0};
    int ok = 1;
    if (use_avx2 < 0) lghq_simd(1);
    for (int64_t i = lo; i < hi && ok; i++)
        ok = gather_point(g, points + 3 * i, normals + 3 * i, g->tiles > 1 ? tile[i] : 0,
                          rand_init(g->seed, (int32_t)(first + i)), i, o, &list, NULL, NULL, NULL);
    free(list.at);
    return ok;
}

/* lghq_gather with the preview surface: `material` (P, BRDF_WIDTH) rows and `albedo` (P, 3) the diffuse
 * reflectance rho; o->irradiance gets each point's unshadowed outgoing radiance, `specular` (P, 3) its specular
 * and clearcoat part, the samples drawn and weighed by each light's radiance (gather_point) */
EXPORT int lghq_gather_brdf(const Gather *g, const float *points, const float *normals, const int32_t *tile,
                            int64_t lo, int64_t hi, int64_t first, const Outputs *o, const float *material,
                            const float *albedo, float *specular) {
    List list = {NULL, 0, 0};
    int ok = 1;
    if (use_avx2 < 0) lghq_simd(1);
    for (int64_t i = lo; i < hi && ok; i++) {
        const float rp[3] = {albedo[3 * i] / LGHQ_PI, albedo[3 * i + 1] / LGHQ_PI, albedo[3 * i + 2] / LGHQ_PI};
        ok = gather_point(g, points + 3 * i, normals + 3 * i, g->tiles > 1 ? tile[i] : 0,
                          rand_init(g->seed, (int32_t)(first + i)), i, o, &list, material + BRDF_WIDTH * i, rp,
                          specular);
    }
    free(list.at);
    return ok;
}

/* ---- shadow-ray targets (cluster_targets) ---- */

/* a member row: its running luminance and what a draw reads of its input light, in one 48-byte
 * record (cum[row], then the light's position, intensity and normal, and its index): a draw reads the
 * guide, then one or two records instead of the running sums, the member table and three light tables
 * (each a cache miss: those loads were most of the targets' time) */
typedef struct {
    double cum;
    float pos[3], inten[3], nrm[3];
    int32_t member;
} Row;

typedef struct {
    const int32_t *start, *stop;   /* (M,) member rows of each grid light */
    const Row *rows;               /* (rows + 1,) the last one only for its running sum */
    const int32_t *guide;          /* (rows,) cut points */
    const float *positions;        /* (N, 3) input light positions (S0 picks) */
    int32_t grid_lights;
    float inv_m2, clamp_d2;
} Members;

static inline void vpl_term(const float *p, const float *n, const float *q, const float *intensity, const float *nq,
                            float inv_m2, float clamp_d2, float *e) {
    float w[3] = {q[0] - p[0], q[1] - p[1], q[2] - p[2]};
    float d2 = dot3(w, w);
    float d = sqrtf(d2);
    e[0] = e[1] = e[2] = 0.0f;
    if (d <= 0.0f) return;
    float cos_s = dot3(n, w) / d;
    float lobe = lobe_factor(nq, w, d);
    if (cos_s <= 0.0f || lobe <= 0.0f) return;
    float s = lobe * cos_s * inv_m2 / fmaxf(d2, clamp_d2);
    e[0] = intensity[0] * s;
    e[1] = intensity[1] * s;
    e[2] = intensity[2] * s;
}

/* Samples lo .. hi - 1: targets (and with reweight the weights, in: pick's e / f). rank / run_length
 * are read when stratified, points / normals / pixel / blend_over_f when reweight. The samples go in
 * batches of 32 in three passes (the draw's share, its guide entry, its record), each pass prefetching
 * what the next reads: a draw's loads depend on one another, and one after another they were cache
 * misses in a row. The same draws, in the same order, as cluster_targets. */
#define TARGET_BATCH 32

EXPORT void lghq_targets(const Members *mb, const int32_t *lights, const float *fallback, int32_t seed, int64_t first,
                         int32_t stratified, const int32_t *rank, const int32_t *run_length, int32_t reweight,
                         const float *points, const float *normals, const int32_t *pixel, const float *blend_over_f,
                         int64_t lo, int64_t hi, float *out, float *out_weight) {
    const Row *rows = mb->rows;
    double xs[TARGET_BATCH], totals[TARGET_BATCH];
    int32_t at[TARGET_BATCH];   /* guide row of the draw; -1: the fallback, -2: an S0 light */
    for (int64_t t0 = lo; t0 < hi; t0 += TARGET_BATCH) {
        int nb = (int)(hi - t0 < TARGET_BATCH ? hi - t0 : TARGET_BATCH);
        for (int i = 0; i < nb; i++) {
            int64_t t = t0 + i;
            int32_t v = lights[t];
            at[i] = -1;
            if (v >= mb->grid_lights) {
                at[i] = -2;
            } else if (v >= 0) {
                int32_t a0 = mb->start[v], hi_row = mb->stop[v];
                double c0 = rows[a0].cum;
                double total = rows[hi_row].cum - c0;
                if (hi_row > a0 && total > 0.0) {
                    uint32_t rng = rand_init(seed, (int32_t)(first + t));
                    double u = (double)randf(&rng);
                    if (stratified == 1) u = ((double)rank[t] + u) / (double)run_length[t];
                    double x = c0 + u * total;
                    int32_t m_rows = hi_row - a0;
                    int32_t share = (int32_t)((x - c0) / total * (double)m_rows);
                    share = imin(imax(share, 0), m_rows - 1);
                    xs[i] = x;
                    totals[i] = total;
                    at[i] = a0 + share;
                    __builtin_prefetch(mb->guide + at[i]);
                }
            }
        }
        for (int i = 0; i < nb; i++)
            if (at[i] >= 0) {
                int32_t a = mb->guide[at[i]];
                __builtin_prefetch(rows + a);
                __builtin_prefetch((const char *)(rows + a) + 63);
            }
        for (int i = 0; i < nb; i++) {
            int64_t t = t0 + i;
            int32_t v = lights[t];
            const float *target = fallback + 3 * t;
            if (at[i] == -2) {
                target = mb->positions + 3 * (int64_t)(v - mb->grid_lights);
            } else if (at[i] >= 0) {
                int32_t a0 = mb->start[v], hi_row = mb->stop[v];
                double x = xs[i], total = totals[i];
                int32_t a = mb->guide[at[i]];
                if (rows[a].cum > x) {
                    int32_t b = hi_row - 1;
                    a = a0;
                    while (a < b) {
                        int32_t mid = (a + b + 1) / 2;
                        if (rows[mid].cum <= x)
                            a = mid;
                        else
                            b = mid - 1;
                    }
                }
                while (a + 1 < hi_row && rows[a + 1].cum <= x) a = a + 1;
                const Row *row = rows + a;
                target = row->pos;
                if (reweight == 1) {
                    const float *ij = row->inten;
                    double lum = (double)(ij[0] * LUMA0 + ij[1] * LUMA1 + ij[2] * LUMA2);
                    float *w = out_weight + 3 * t;
                    if (lum <= 0.0) {
                        w[0] = w[1] = w[2] = 0.0f;
                    } else {
                        int32_t p = pixel[t];
                        float e[3];
                        vpl_term(points + 3 * (int64_t)p, normals + 3 * (int64_t)p, target, ij, row->nrm, mb->inv_m2,
                                 mb->clamp_d2, e);
                        float s = blend_over_f[t] * (float)(total / lum);
                        w[0] = e[0] * s;
                        w[1] = e[1] * s;
                        w[2] = e[2] * s;
                    }
                }
            }
            out[3 * t + 0] = target[0];
            out[3 * t + 1] = target[1];
            out[3 * t + 2] = target[2];
        }
    }
}

/* Points lo .. hi - 1 of k samples each: num = sum_s V_s w_s and den = sum_s w_s per channel (visible
 * (P, k) float32 0/1, weight (P, k, 3)), summed in sample order in double and rounded once. */
EXPORT void lghq_sums(const float *visible, const float *weight, int64_t k, int64_t lo, int64_t hi, float *num,
                      float *den) {
    for (int64_t p = lo; p < hi; p++) {
        double sn[3] = {0, 0, 0}, sd[3] = {0, 0, 0};
        const float *v = visible + p * k, *w = weight + 3 * p * k;
        for (int64_t s = 0; s < k; s++)
            for (int c = 0; c < 3; c++) {
                sd[c] += w[3 * s + c];
                sn[c] += v[s] * w[3 * s + c];
            }
        for (int c = 0; c < 3; c++) {
            num[3 * p + c] = (float)sn[c];
            den[3 * p + c] = (float)sd[c];
        }
    }
}

/* The member draws' guide table (usdml.lighting.lgh.shading._guide_table, the same cut points): for each group
 * g of rows start[g] .. stop[g] - 1 (running sums cum, non-decreasing), row start + b of guide holds the last row
 * r of the group with cum[r] <= cum[start] + b * (cum[stop] - cum[start]) / size, found by one forward walk
 * per group (the cut points rise with b). */
EXPORT void lghq_guide(const double *cum, const int64_t *start, const int64_t *stop, int64_t groups, int32_t *guide) {
    for (int64_t g = 0; g < groups; g++) {
        const int64_t lo = start[g], hi = stop[g], size = hi - lo;
        if (size <= 0) continue;
        const double total = cum[hi] - cum[lo];
        int64_t at = lo;
        for (int64_t b = 0; b < size; b++) {
            const double edge = cum[lo] + (double)b * total / (double)size;
            while (at + 1 < hi && cum[at + 1] <= edge) at++;
            guide[lo + b] = (int32_t)at;
        }
    }
}

/* Points lo .. hi - 1: the unshadowed irradiance of every input light as a one-sided cosine emitter (the model
 * the gather approximates, usdml.lighting.lgh.choice.vpl_irradiance), summed in double: out (P, 3) +=
 * sum_j 4 I_j max(0, n_p . w) max(0, -n_j . w) / (d^2 max(d^2, clamp_d2)), w = q_j - p, d = |w|. The lights
 * come as nine float32 columns (light: x, y, z, normal x, y, z, intensity r, g, b; n each), taken 8 at a time
 * into 8 running sums per channel (lane k: lights k, k + 8, ...; the last few alone) added in lane order at the
 * end: the compiler vectorizes the lanes, and a point's sum is the same on any thread. */
#define COSINE_LANES 8
/* where GCC makes function clones per ISA, dispatched at load (Linux on x86) */
#if (defined(__x86_64__) || defined(__i386__)) && defined(__linux__) && defined(__GNUC__) && !defined(__clang__)
#define LGHQ_CLONES 1
#endif
/* the lanes vectorize only where a division need not be guarded by a branch (GCC: no trapping math here), and
 * run 4 doubles at a time where the CPU has AVX2 (the clones) */
#if defined(__GNUC__) && !defined(__clang__)
#define COSINE_NO_TRAP __attribute__((optimize("no-trapping-math")))
#else
#define COSINE_NO_TRAP
#endif
#ifdef LGHQ_CLONES
#define COSINE_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define COSINE_CLONES
#endif
COSINE_NO_TRAP __attribute__((always_inline)) static inline double cosine_term(
    const float *const *light, int64_t j, double px, double py, double pz, double nx, double ny, double nz,
    double clamp_d2) {
    const double wx = light[0][j] - px, wy = light[1][j] - py, wz = light[2][j] - pz;
    const double d2 = wx * wx + wy * wy + wz * wz;
    double cs = nx * wx + ny * wy + nz * wz;
    double cl = -(light[3][j] * wx + light[4][j] * wy + light[5][j] * wz);
    cs = cs > 0.0 ? cs : 0.0;
    cl = cl > 0.0 ? cl : 0.0;
    const double den = d2 * (d2 > clamp_d2 ? d2 : clamp_d2);
    const int ok = den > 1e-300;          /* a light on the point adds nothing; no division decided by a branch */
    return (ok ? 4.0 * cs * cl : 0.0) / (ok ? den : 1.0);
}

COSINE_NO_TRAP COSINE_CLONES EXPORT void lghq_cosine_sum(const float *points, const float *normals,
                                                         const float *const *light, int64_t n, double clamp_d2,
                                                         int64_t lo, int64_t hi, double *out) {
    const int64_t whole = n - n % COSINE_LANES;
    for (int64_t p = lo; p < hi; p++) {
        const double px = points[3 * p], py = points[3 * p + 1], pz = points[3 * p + 2];
        const double nx = normals[3 * p], ny = normals[3 * p + 1], nz = normals[3 * p + 2];
        double acc[3][COSINE_LANES] = {{0}};
        for (int64_t j = 0; j < whole; j += COSINE_LANES)
            for (int k = 0; k < COSINE_LANES; k++) {
                const double g = cosine_term(light, j + k, px, py, pz, nx, ny, nz, clamp_d2);
                acc[0][k] += g * light[6][j + k];
                acc[1][k] += g * light[7][j + k];
                acc[2][k] += g * light[8][j + k];
            }
        for (int64_t j = whole; j < n; j++) {
            const double g = cosine_term(light, j, px, py, pz, nx, ny, nz, clamp_d2);
            for (int c = 0; c < 3; c++) acc[c][j - whole] += g * light[6 + c][j];
        }
        for (int c = 0; c < 3; c++) {
            double sum = 0.0;
            for (int k = 0; k < COSINE_LANES; k++) sum += acc[c][k];
            out[3 * p + c] += sum;
        }
    }
}

/* ---- every light its own light (--lgh-split each, --direct-gather each): the hierarchy's limit, summed ---- */

/* Points lo .. hi - 1 of the frame: the unshadowed irradiance of every input light (lghq_cosine_sum's model, in
 * float, generalised as the LGH's lobe: an isotropic share a plus a one-sided cosine lobe 4 max(0, cos θ_l) about
 * the light's normal, a = 1 - |normal|: a VPL or a disk light has a = 0, a point light a = 1 and no normal), and
 * `samples` of those lights drawn for shadow rays with probability in proportion to their luminance at the point
 * (systematic: one uniform u per point, thresholds (s + u) / k of the total), each with its own RGB irradiance over
 * that luminance and the luminance, and the count of lights that reach the point. The lights come as eleven
 * float32 columns (x, y, z, normal x, y, z, intensity r, g, b, luminance of the intensity, isotropic share a), n a
 * multiple of EACH_GROUP (the caller pads with lights of no intensity, no normal and a = 0, which add nothing);
 * `mode` says which terms the lights have (EACH_COSINE: every a is 0; EACH_ISOTROPIC: every a is 1; EACH_MIXED),
 * so that a sum of VPLs takes no square root and one of point lights reads no normals. Lane k sums lights k,
 * k + 16, ... of each block of 16; a tile of EACH_TILE points goes through the lights a chunk of EACH_CHUNK at a
 * time (the chunk's columns from L2 for all but the first pair of points: at a million lights they stream from
 * memory, and two points a pass were bound by that), and each point keeps its lanes' running luminance at the end
 * of every group of EACH_GROUP lights; a pair of points skips a chunk whose box lies behind both their tangent
 * planes, and a group whose lights share one unit normal that is both points' normal (cos θ_s and cos θ_l one dot
 * product and its negation): every term there is 0, the same sums. The sum up to a group is those 16 floats added
 * as a tree (when the draws' search first reads it): monotone in the group, which a binary search over the groups
 * then inverts; the group's 64 terms are computed again to find the light. A point's answer is the same on any thread; its random stream is seed and first + p (Warp's PCG). */
#define EACH_LANES 16
/* float terms contracted into fused multiply-adds where the compiler can (this sum is not one of those that
 * must give Warp's bits) */
#if defined(__GNUC__) && !defined(__clang__)
#define EACH_FAST __attribute__((optimize("no-trapping-math", "fp-contract=fast")))
#else
#define EACH_FAST
#endif
#ifdef LGHQ_CLONES
#define EACH_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define EACH_CLONES
#endif

/* the lanes lghq_each's clone runs on this CPU: 16 (AVX-512), 8 (AVX2), 4 (the baseline's SSE), 0 where the
 * clones are not made (another compiler or platform: whatever it vectorizes) */
EXPORT int lghq_each_lanes(void) {
#ifdef LGHQ_CLONES
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f")) return 16;
    if (__builtin_cpu_supports("avx2")) return 8;
    return 4;
#else
    return 0;
#endif
}

#define EACH_COSINE 0
#define EACH_ISOTROPIC 1
#define EACH_MIXED 2

/* light j's irradiance at a point over its intensity (before metersPerUnit): cos θ_s (a + 4 max(0, cos θ_l)) /
 * max(d², d_c²) */
EACH_FAST __attribute__((always_inline)) static inline float each_term(
    const float *const *light, int64_t j, const int mode, float px, float py, float pz, float nx, float ny, float nz,
    float clamp_d2) {
    const float wx = light[0][j] - px, wy = light[1][j] - py, wz = light[2][j] - pz;
    const float d2 = wx * wx + wy * wy + wz * wz;
    float cs = nx * wx + ny * wy + nz * wz;
    cs = cs > 0.0f ? cs : 0.0f;
    const float den = d2 * (d2 > clamp_d2 ? d2 : clamp_d2);
    const int ok = den > 0.0f;            /* a light on the point adds nothing */
    float lobe;                           /* (a d + 4 max(0, -m.w)) = d (a + 4 max(0, cos θ_l)) */
    if (mode == EACH_ISOTROPIC) {
        lobe = sqrtf(d2);
    } else {
        float cl = -(light[3][j] * wx + light[4][j] * wy + light[5][j] * wz);
        cl = cl > 0.0f ? cl : 0.0f;
        lobe = mode == EACH_MIXED ? light[10][j] * sqrtf(d2) + 4.0f * cl : 4.0f * cl;
    }
    return (ok ? cs * lobe : 0.0f) / (ok ? den : 1.0f);
}

/* the 16 lanes' running sums added as a tree in float (a fixed order: monotone from block to block as every lane
 * is, so the blocks' totals can be searched) */
EACH_FAST __attribute__((always_inline)) static inline float each_lanes_sum(const float *v) {
    float h[EACH_LANES / 2];
    for (int k = 0; k < EACH_LANES / 2; k++) h[k] = v[k] + v[k + EACH_LANES / 2];
    for (int w = EACH_LANES / 4; w > 0; w /= 2)
        for (int k = 0; k < w; k++) h[k] += h[k + w];
    return h[0];
}

/* points taken together through a block of lights (each light's columns loaded once for all of them: at 100,000
 * lights the columns outgrow L2, and one point at a time was bound by the loads; four spilled the lanes) */
#define EACH_POINTS 2

/* lights per group: a point's running total is kept at the end of each group (a horizontal sum of the lanes per
 * block of 16 cost a third of the sum), and a draw computes its group's terms again */
#define EACH_GROUP 64

/* sample `row` not taken (until a draw takes it) */
__attribute__((always_inline)) static inline void each_no_sample(int64_t row, int32_t *sample_light,
                                                                 float *sample_weight, float *sample_lum,
                                                                 uint8_t *sample_ok) {
    sample_ok[row] = 0;
    sample_light[row] = -1;
    sample_lum[row] = 0.0f;
    sample_weight[3 * row] = sample_weight[3 * row + 1] = sample_weight[3 * row + 2] = 0.0f;
}

/* point p's irradiance from its lanes' sums, and its shadow draws from `total`, the running sum of its lights'
 * luminance at the end of each group of EACH_GROUP lights, in its 16 lanes (each_lanes_sum adds them into
 * `totals`): a draw's group is the first whose total exceeds its threshold, and its light the group's light at
 * which the group's terms, computed again, pass it */
EACH_FAST __attribute__((always_inline)) static inline void each_finish(
    const float *const *light, int64_t n, const int mode, float px, float py, float pz, float nx, float ny, float nz,
    float clamp_d2, float inv_m2, int32_t samples, int32_t seed, int64_t first, int64_t p,
    const float acc[5][EACH_LANES], const float *total, float *restrict totals, float *irradiance, float *count,
    int32_t *sample_light, float *sample_weight, float *sample_lum, uint8_t *sample_ok) {
    const int64_t groups = n / EACH_GROUP;
    for (int c = 0; c < 3; c++) {
        double sum = 0.0;
        for (int k = 0; k < EACH_LANES; k++) sum += acc[c][k];
        irradiance[3 * p + c] = (float)(sum * inv_m2);
    }
    double reach = 0.0;
    for (int k = 0; k < EACH_LANES; k++) reach += acc[4][k];
    count[p] = (float)reach;
    if (samples <= 0) return;
    /* a group's total is its lanes added when the search first reads it (a draw reads about log2 of the groups
     * past the last draw's: at a million lights adding every group's lanes cost more than the draws) */
    for (int64_t g = 0; g < groups; g++) totals[g] = -1.0f;
#define EACH_TOTAL(g) (totals[g] >= 0.0f ? totals[g] : (totals[g] = each_lanes_sum(total + (g) * EACH_LANES)))
    const double all = groups ? (double)EACH_TOTAL(groups - 1) : 0.0;
    uint32_t rng = rand_init(seed, (int32_t)(first + p));
    const float u = randf(&rng);
    int64_t from = 0;
    for (int32_t s = 0; s < samples; s++) {
        const int64_t row = p * samples + s;
        each_no_sample(row, sample_light, sample_weight, sample_lum, sample_ok);
        if (!(all > 0.0)) continue;
        const double t = ((double)s + (double)u) / (double)samples * all;
        int64_t a = from, z = groups - 1;           /* the first group whose running sum exceeds t */
        for (int64_t step = 1; a + step < z; step *= 2) {     /* galloping from the last draw's group */
            if ((double)EACH_TOTAL(a + step - 1) > t) { z = a + step - 1; break; }
            a += step;
        }
        while (a < z) {
            const int64_t m = a + (z - a) / 2;
            if ((double)EACH_TOTAL(m) > t) z = m; else a = m + 1;
        }
        from = a;
        const int64_t j0 = a * EACH_GROUP;
        float f[EACH_GROUP];
        for (int k = 0; k < EACH_GROUP; k++)
            f[k] = each_term(light, j0 + k, mode, px, py, pz, nx, ny, nz, clamp_d2) * light[9][j0 + k];
        double run = a > 0 ? (double)EACH_TOTAL(a - 1) : 0.0;
        int chosen = -1, last = -1;
        for (int k = 0; k < EACH_GROUP; k++) {
            if (!(f[k] > 0.0f)) continue;
            last = k;
            run += f[k];
            if (run > t) { chosen = k; break; }
        }
        if (chosen < 0) chosen = last;              /* rounding: the group's last light that adds */
        if (chosen < 0) continue;
        const int64_t j = j0 + chosen;
        const float g = each_term(light, j, mode, px, py, pz, nx, ny, nz, clamp_d2) * inv_m2;
        const float fj = g * light[9][j];
        if (!(fj > 0.0f)) continue;
        sample_ok[row] = 1;
        sample_light[row] = (int32_t)j;
        sample_lum[row] = fj;
        for (int c = 0; c < 3; c++) sample_weight[3 * row + c] = g * light[6 + c][j] / fj;
    }
#undef EACH_TOTAL
}

/* whether every light in the chunk's box (centre, half extents) lies behind the tangent planes of all the points
 * (cos θ_s <= 0: each term 0), with a margin for the rounding of the terms' dot products */
EACH_FAST __attribute__((always_inline)) static inline int each_behind(const float *box, const float *px,
                                                                      const float *py, const float *pz,
                                                                      const float *nx, const float *ny,
                                                                      const float *nz) {
    for (int i = 0; i < EACH_POINTS; i++) {
        const float dx = box[0] - px[i], dy = box[1] - py[i], dz = box[2] - pz[i];
        const float reach = nx[i] * dx + ny[i] * dy + nz[i] * dz + fabsf(nx[i]) * box[3] + fabsf(ny[i]) * box[4] +
                            fabsf(nz[i]) * box[5];
        const float scale = fabsf(dx) + fabsf(dy) + fabsf(dz) + box[3] + box[4] + box[5];
        if (!(reach < -1e-5f * scale)) return 0;
    }
    return 1;
}

/* lights per chunk: a tile's points go through one chunk before the next, so that its columns are read from
 * memory once per tile and from L2 for its other points (4,096 lights: 180 KB of columns); points per tile */
#define EACH_CHUNK 4096
#define EACH_TILE 32

/* points lo .. hi - 1, tile by tile, for one `mode` (a constant where it is inlined); `state` holds a tile's
 * lanes (EACH_TILE * 5 * EACH_LANES floats), `total` its points' lanes at the end of each group (EACH_TILE *
 * n / EACH_GROUP * EACH_LANES) and `totals` one point's group totals (n / EACH_GROUP) */
EACH_FAST __attribute__((always_inline)) static inline void each_points(
    const float *points, const float *normals, const float *const *light, int64_t n, const int mode, float clamp_d2,
    float inv_m2, int32_t samples, int32_t seed, int64_t first, int64_t lo, int64_t hi, const float *box,
    const float *group_normal, float *restrict state, float *restrict total, float *restrict totals,
    float *irradiance, float *count, int32_t *sample_light, float *sample_weight, float *sample_lum,
    uint8_t *sample_ok) {
    const int64_t groups = n / EACH_GROUP;
    for (int64_t t0 = lo; t0 < hi; t0 += EACH_TILE) {
        const int64_t tile = hi - t0 < EACH_TILE ? hi - t0 : EACH_TILE;
        memset(state, 0, sizeof(float) * EACH_TILE * 5 * EACH_LANES);
        for (int64_t c0 = 0; c0 < n; c0 += EACH_CHUNK) {
            const int64_t c1 = n - c0 < EACH_CHUNK ? n : c0 + EACH_CHUNK;
            for (int64_t i0 = 0; i0 < tile; i0 += EACH_POINTS) {
                float px[EACH_POINTS], py[EACH_POINTS], pz[EACH_POINTS], nx[EACH_POINTS], ny[EACH_POINTS],
                    nz[EACH_POINTS];
                for (int i = 0; i < EACH_POINTS; i++) {     /* past the tile: its last point again, not kept */
                    const int64_t p = t0 + (i0 + i < tile ? i0 + i : tile - 1);
                    px[i] = points[3 * p], py[i] = points[3 * p + 1], pz[i] = points[3 * p + 2];
                    nx[i] = normals[3 * p], ny[i] = normals[3 * p + 1], nz[i] = normals[3 * p + 2];
                }
                float acc[EACH_POINTS][5][EACH_LANES] = {{{0}}};      /* the chunk's own sums */
                float base[EACH_POINTS][EACH_LANES];    /* each lane's running luminance before the chunk */
                for (int i = 0; i < EACH_POINTS; i++)
                    memcpy(base[i], state + ((i0 + i < tile ? i0 + i : tile - 1) * 5 + 3) * EACH_LANES, sizeof base[i]);
                if (box != NULL && each_behind(box + 6 * (c0 / EACH_CHUNK), px, py, pz, nx, ny, nz)) {
                    /* every light of the chunk behind both points: each term 0, the totals stay */
                    for (int i = 0; i < EACH_POINTS; i++)
                        for (int64_t g0 = c0; g0 < c1; g0 += EACH_GROUP)
                            memcpy(total + ((i0 + i) * groups + g0 / EACH_GROUP) * EACH_LANES, base[i], sizeof base[i]);
                    continue;
                }
                for (int64_t g0 = c0; g0 < c1; g0 += EACH_GROUP) {
                    if (group_normal != NULL) {
                        /* the group's lights share one unit normal (NaN where they do not) and it is both points'
                         * normal: cos θ_s and cos θ_l are one dot product and its negation, so every term is 0 */
                        const float *gn = group_normal + 3 * (g0 / EACH_GROUP);
                        int same = 1;
                        for (int i = 0; i < EACH_POINTS; i++)
                            same &= nx[i] == gn[0] && ny[i] == gn[1] && nz[i] == gn[2];
                        if (same) {
                            for (int i = 0; i < EACH_POINTS; i++)
                                for (int k = 0; k < EACH_LANES; k++)
                                    total[((i0 + i) * groups + g0 / EACH_GROUP) * EACH_LANES + k] = base[i][k] +
                                                                                                acc[i][3][k];
                            continue;
                        }
                    }
                    for (int64_t j = g0; j < g0 + EACH_GROUP; j += EACH_LANES)
                        for (int i = 0; i < EACH_POINTS; i++)    /* the block's lights from L1 for the second point */
                            for (int k = 0; k < EACH_LANES; k++) {
                                const float g = each_term(light, j + k, mode, px[i], py[i], pz[i], nx[i], ny[i], nz[i],
                                                          clamp_d2);
                                acc[i][0][k] += g * light[6][j + k];
                                acc[i][1][k] += g * light[7][j + k];
                                acc[i][2][k] += g * light[8][j + k];
                                const float f = g * light[9][j + k];
                                acc[i][3][k] += f;
                                acc[i][4][k] += f > 0.0f ? 1.0f : 0.0f;     /* (a padding light has no luminance) */
                                /* the group's running totals, lane by lane: written by each of its blocks (the
                                 * last one's stay), in the loop that sums them (a store after it cost a third) */
                                total[((i0 + i) * groups + g0 / EACH_GROUP) * EACH_LANES + k] = base[i][k] +
                                                                                            acc[i][3][k];
                            }
                }
                for (int i = 0; i < EACH_POINTS && i0 + i < tile; i++)
                    for (int c = 0; c < 5; c++)
                        for (int k = 0; k < EACH_LANES; k++) state[((i0 + i) * 5 + c) * EACH_LANES + k] += acc[i][c][k];
            }
        }
        for (int64_t i = 0; i < tile; i++) {
            const int64_t p = t0 + i;
            each_finish(light, n, mode, points[3 * p], points[3 * p + 1], points[3 * p + 2], normals[3 * p],
                        normals[3 * p + 1], normals[3 * p + 2], clamp_d2, inv_m2, samples, seed, first, p,
                        (const float(*)[EACH_LANES])(state + i * 5 * EACH_LANES), total + i * groups * EACH_LANES,
                        totals, irradiance,
                        count, sample_light, sample_weight, sample_lum, sample_ok);
        }
    }
}

/* ---- one step of the edge-avoiding à-trous filter (usdml/lighting/atrous.py) on a CPU ---- */

/* kernels/atrous.py's atrous_step for image rows row0 .. row1 - 1, the same weights in the same order: `values`
 * (h, w, nc) this step's input, `normal` and `position` (h, w, 3), `valid` (h, w), `inv_scale` (nc), taps `step`
 * pixels apart; each tap weighs h(dy) h(dx) max(0, n_p.n_q)^sigma_normal exp(-|x_p - x_q|^2 inv_sx2 - dv^2
 * inv_sv2) (a whole sigma_normal by squaring, another as exp(sigma_normal log(n_p.n_q)); no value term when
 * inv_sv2 is 0); an invalid pixel is copied and never a tap. The Warp kernel ran a tap in about 50 ns on this CPU
 * (one launch per band of rows, no vector code, a log and an exp a tap) */
static const float ATROUS_TAP[3] = {0.375f, 0.25f, 0.0625f};

EXPORT void lghq_atrous_step(const float *values, const float *normal, const float *position, const uint8_t *valid,
                             const float *inv_scale, int32_t h, int32_t w, int32_t nc, int32_t step,
                             float sigma_normal, float inv_sx2, float inv_sv2, int32_t row0, int32_t row1,
                             float *out) {
    const int32_t power = sigma_normal >= 1.0f && sigma_normal <= 4096.0f &&
                          sigma_normal == (float)(int32_t)sigma_normal ? (int32_t)sigma_normal : 0;
    for (int32_t y = row0; y < row1; y++)
        for (int32_t x = 0; x < w; x++) {
            const int64_t p = (int64_t)y * w + x;
            const float *vp = values + p * nc;
            float *op = out + p * nc;
            if (!valid[p]) {
                for (int c = 0; c < nc; c++) op[c] = vp[c];
                continue;
            }
            const float *np_ = normal + 3 * p, *xp = position + 3 * p;
            for (int c = 0; c < nc; c++) op[c] = 0.0f;
            float wsum = 0.0f;
            for (int dy = -2; dy <= 2; dy++) {
                const int32_t yq = y + dy * step;
                if (yq < 0 || yq >= h) continue;
                const float hy = ATROUS_TAP[dy < 0 ? -dy : dy];
                for (int dx = -2; dx <= 2; dx++) {
                    const int32_t xq = x + dx * step;
                    if (xq < 0 || xq >= w) continue;
                    const int64_t q = (int64_t)yq * w + xq;
                    if (!valid[q]) continue;
                    float wn = 1.0f;
                    if (sigma_normal > 0.0f) {
                        const float cos_nq = dot3(np_, normal + 3 * q);
                        if (cos_nq <= 0.0f) continue;
                        if (power > 0) {            /* a whole power (the default 128): by squaring, no log */
                            float b = cos_nq;
                            for (int32_t e = power; e; e >>= 1) {
                                if (e & 1) wn *= b;
                                b *= b;
                            }
                        } else {
                            wn = expf(sigma_normal * logf(cos_nq));
                        }
                    }
                    const float *xq3 = position + 3 * q, *vq = values + q * nc;
                    const float d0 = xp[0] - xq3[0], d1 = xp[1] - xq3[1], d2 = xp[2] - xq3[2];
                    float dv2 = 0.0f;
                    if (inv_sv2 != 0.0f)
                        for (int c = 0; c < nc; c++) {
                            const float dv = (vp[c] - vq[c]) * inv_scale[c];
                            dv2 += dv * dv;
                        }
                    const float wgt = hy * ATROUS_TAP[dx < 0 ? -dx : dx] * wn *
                                      expf(-((d0 * d0 + d1 * d1 + d2 * d2) * inv_sx2 + dv2 * inv_sv2));
                    if (wgt > 0.0f) {
                        wsum += wgt;
                        for (int c = 0; c < nc; c++) op[c] += wgt * vq[c];
                    }
                }
            }
            if (wsum > 0.0f) {      /* (a zero normal can leave nothing: the input kept) */
                const float inv = 1.0f / wsum;
                for (int c = 0; c < nc; c++) op[c] *= inv;
            } else {
                for (int c = 0; c < nc; c++) op[c] = vp[c];
            }
        }
}

/* the lights per chunk lghq_each's `box` is given for */
EXPORT int lghq_each_chunk(void) { return EACH_CHUNK; }

/* `box`: each chunk's box of lights (centre x, y, z, half extents x, y, z; n / EACH_CHUNK rounded up), or NULL;
 * `group_normal`: each group's one unit normal where its lights share it and have a = 0, else NaN (n / EACH_GROUP
 * by 3), or NULL */
EACH_FAST EACH_CLONES EXPORT int lghq_each(const float *points, const float *normals, const float *const *light,
                                            const float *box, const float *group_normal,
                                            int64_t n, int32_t mode, float clamp_d2, float inv_m2, int32_t samples,
                                            int32_t seed, int64_t first, int64_t lo, int64_t hi, float *irradiance,
                                            float *count, int32_t *sample_light, float *sample_weight,
                                            float *sample_lum, uint8_t *sample_ok) {
    if (n % EACH_GROUP || mode < EACH_COSINE || mode > EACH_MIXED) return 0;
    float *state = (float *)malloc(sizeof(float) * EACH_TILE * 5 * EACH_LANES);
    float *total = (float *)malloc(sizeof(float) * EACH_LANES * (size_t)EACH_TILE *
                                  (size_t)(n > 0 ? n / EACH_GROUP : 1));
    float *totals = (float *)malloc(sizeof(float) * (size_t)(n > 0 ? n / EACH_GROUP : 1));
    if (!total || !state || !totals) {
        free(total);
        free(state);
        free(totals);
        return 0;
    }
    if (mode == EACH_COSINE)
        each_points(points, normals, light, n, EACH_COSINE, clamp_d2, inv_m2, samples, seed, first, lo, hi, box,
                    group_normal, state, total, totals, irradiance, count, sample_light, sample_weight, sample_lum, sample_ok);
    else if (mode == EACH_ISOTROPIC)
        each_points(points, normals, light, n, EACH_ISOTROPIC, clamp_d2, inv_m2, samples, seed, first, lo, hi, box,
                    group_normal, state, total, totals, irradiance, count, sample_light, sample_weight, sample_lum, sample_ok);
    else
        each_points(points, normals, light, n, EACH_MIXED, clamp_d2, inv_m2, samples, seed, first, lo, hi, box,
                    group_normal, state, total, totals, irradiance, count, sample_light, sample_weight, sample_lum, sample_ok);
    free(total);
    free(state);
    free(totals);
    return 1;
}

/* ---- every light its own light with the preview surface (issue 51) ---- */

/* light j's outgoing radiance r (3) and specular part s (3) at a point (rp = rho/pi, material row m): its
 * irradiance g I (g = each_term · inv_m2) times rho/pi kd + ks toward the light; returns g */
EACH_FAST __attribute__((always_inline)) static inline float each_brdf_term(
    const float *const *light, int64_t j, const int mode, const float *p, const float *n, const float *m,
    const float *rp, float clamp_d2, float inv_m2, float *r, float *s) {
    const float g = each_term(light, j, mode, p[0], p[1], p[2], n[0], n[1], n[2], clamp_d2) * inv_m2;
    r[0] = r[1] = r[2] = s[0] = s[1] = s[2] = 0.0f;
    if (!(g > 0.0f)) return g;
    const float q[3] = {light[0][j], light[1][j], light[2][j]};
    const float e[3] = {g * light[6][j], g * light[7][j], g * light[8][j]};
    brdf_radiance(m, rp, p, n, q, e, r, s);
    return g;
}

EACH_FAST __attribute__((always_inline)) static inline void each_brdf_points(
    const float *points, const float *normals, const float *const *light, const float *box, int64_t n, const int mode,
    float clamp_d2, float inv_m2, int32_t samples, int32_t seed, int64_t first, int64_t lo, int64_t hi,
    const float *material, const float *albedo, float *restrict f, float *irradiance, float *specular, float *count,
    int32_t *sample_light, float *sample_weight, float *sample_lum, uint8_t *sample_ok) {
    for (int64_t p = lo; p < hi; p++) {
        const float *pp = points + 3 * p, *pn = normals + 3 * p, *m = material + BRDF_WIDTH * p;
        const float rp[3] = {albedo[3 * p] / LGHQ_PI, albedo[3 * p + 1] / LGHQ_PI, albedo[3 * p + 2] / LGHQ_PI};
        double acc[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}, all = 0.0;
        float reach = 0.0f;
        const float px[EACH_POINTS] = {pp[0], pp[0]}, py[EACH_POINTS] = {pp[1], pp[1]},
                    pz[EACH_POINTS] = {pp[2], pp[2]}, nx[EACH_POINTS] = {pn[0], pn[0]},
                    ny[EACH_POINTS] = {pn[1], pn[1]}, nz[EACH_POINTS] = {pn[2], pn[2]};
        for (int64_t c0 = 0; c0 < n; c0 += EACH_CHUNK) {
            const int64_t c1 = n - c0 < EACH_CHUNK ? n : c0 + EACH_CHUNK;
            if (box != NULL && each_behind(box + 6 * (c0 / EACH_CHUNK), px, py, pz, nx, ny, nz)) {
                for (int64_t j = c0; j < c1; j++) f[j] = 0.0f;
                continue;
            }
            for (int64_t j = c0; j < c1; j++) {
                float r[3], s[3];
                const float g = each_brdf_term(light, j, mode, pp, pn, m, rp, clamp_d2, inv_m2, r, s);
                const float fj = r[0] * LUMA0 + r[1] * LUMA1 + r[2] * LUMA2;
                f[j] = fj > 0.0f ? fj : 0.0f;
                reach += g * light[9][j] > 0.0f ? 1.0f : 0.0f;
                for (int c = 0; c < 3; c++) acc[c] += r[c], acc[3 + c] += s[c];
            }
        }
        for (int c = 0; c < 3; c++) irradiance[3 * p + c] = (float)acc[c], specular[3 * p + c] = (float)acc[3 + c];
        count[p] = reach;
        if (samples <= 0) continue;
        for (int64_t j = 0; j < n; j++) all += f[j];
        uint32_t rng = rand_init(seed, (int32_t)(first + p));
        const float u = randf(&rng);
        double run = 0.0;
        int64_t j = 0, last = -1;
        for (int32_t s = 0; s < samples; s++) {       /* systematic: thresholds (s + u) / k of the total */
            const int64_t row = p * samples + s;
            each_no_sample(row, sample_light, sample_weight, sample_lum, sample_ok);
            if (!(all > 0.0)) continue;
            const double t = ((double)s + (double)u) / (double)samples * all;
            int64_t chosen = -1;
            if (last >= 0 && run > t) chosen = last;           /* the last light drawn again */
            while (chosen < 0 && j < n) {
                if (f[j] > 0.0f) {
                    last = j;
                    run += f[j];
                    if (run > t) chosen = j;
                }
                j++;
            }
            if (chosen < 0) chosen = last;                     /* rounding: the last light that adds */
            if (chosen < 0) continue;
            float r[3], sp[3];
            each_brdf_term(light, chosen, mode, pp, pn, m, rp, clamp_d2, inv_m2, r, sp);
            const float fj = f[chosen];
            if (!(fj > 0.0f)) continue;
            sample_ok[row] = 1;
            sample_light[row] = (int32_t)chosen;
            sample_lum[row] = fj;
            for (int c = 0; c < 3; c++) sample_weight[3 * row + c] = r[c] / fj;
        }
    }
}

/* lghq_each with the preview surface, a point at a time: `material` (P, BRDF_WIDTH) rows and `albedo` (P, 3) the
 * diffuse reflectance rho; `irradiance` gets each point's unshadowed outgoing radiance (every light's
 * each_brdf_term, summed in double), `specular` its specular and clearcoat part, and the samples are drawn in
 * proportion to each light's radiance luminance (systematic, one uniform per point as lghq_each), each weighed by
 * its RGB radiance over that luminance; `count` the lights that reach the point. `box` as lghq_each's (chunks
 * behind the point add nothing), or NULL */
EACH_FAST EACH_CLONES EXPORT int lghq_each_brdf(const float *points, const float *normals, const float *const *light,
                                                 const float *box, int64_t n, int32_t mode, float clamp_d2,
                                                 float inv_m2, int32_t samples, int32_t seed, int64_t first,
                                                 int64_t lo, int64_t hi, const float *material, const float *albedo,
                                                 float *irradiance, float *specular, float *count,
                                                 int32_t *sample_light, float *sample_weight, float *sample_lum,
                                                 uint8_t *sample_ok) {
    if (mode < EACH_COSINE || mode > EACH_MIXED) return 0;
    float *f = (float *)malloc(sizeof(float) * (size_t)(n > 0 ? n : 1));
    if (!f) return 0;
    if (mode == EACH_COSINE)
        each_brdf_points(points, normals, light, box, n, EACH_COSINE, clamp_d2, inv_m2, samples, seed, first, lo, hi,
                         material, albedo, f, irradiance, specular, count, sample_light, sample_weight, sample_lum,
                         sample_ok);
    else if (mode == EACH_ISOTROPIC)
        each_brdf_points(points, normals, light, box, n, EACH_ISOTROPIC, clamp_d2, inv_m2, samples, seed, first, lo,
                         hi, material, albedo, f, irradiance, specular, count, sample_light, sample_weight, sample_lum,
                         sample_ok);
    else
        each_brdf_points(points, normals, light, box, n, EACH_MIXED, clamp_d2, inv_m2, samples, seed, first, lo, hi,
                         material, albedo, f, irradiance, specular, count, sample_light, sample_weight, sample_lum,
                         sample_ok);
    free(f);
    return 1;
}

/* an importable module, so that setuptools builds it as an extension; the functions are called by ctypes */
static struct PyModuleDef lghq_module = {PyModuleDef_HEAD_INIT, "_lghq", "LGH gather and shadow targets (ctypes)", -1, NULL};
PyMODINIT_FUNC PyInit__lghq(void) { return PyModule_Create(&lghq_module); }
