/* Paper 000's voxel shadow queries (Alg. 2 / 4) and many-light shading (Alg. 3) on the CPU, compiled:
 * the rule of kernels/voxel/query.py and kernels/voxel/shading.py, answering 32 queries at a time with
 * AVX-512 or 16 with AVX2 (two registers per vector, kernels/include/simd_x2.h; picked at run time) or one at a
 * time in plain C. Loaded with ctypes by usdml.visibility.voxel.native, which says what every table
 * below holds; called from a thread pool (ctypes releases the GIL). vq_query_refine answers the same
 * queries and says which answers are uncertain (the thick-ray rule: five rays per query, the row
 * lookups of the query's own and of the rows ``thick`` voxels to either side; see there);
 * vq_shade_refine is vq_shade with that rule, the uncertain answers listed for the caller.
 *
 * Differences from the Warp kernels, none changing the rule:
 *   - one folded affine map per (array, direction bin), grid = F p + f, instead of world -> array then
 *     array -> bin (for the static array the world -> array map is folded in too);
 *   - a row's table entries packed in two words (start of its words, first and end word);
 *   - instances found by a BVH over their world boxes built here (the Warp kernel uses wp.Bvh), the
 *     segment, not the whole ray, tested against the boxes.
 * The answers agree with the Warp kernel's but for floating-point rounding at voxel borders
 * (tests/test_voxel_native.py states the agreement).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "brdf.h"
#include "light_term.h"
#include "simd_pick.h"

#if defined(__x86_64__) || defined(_M_X64)
#define VQ_X86 1
#include <immintrin.h>
#endif

typedef struct {
    const uint32_t *words;       /* every array's words */
    const int32_t *arr_n;        /* per array: resolution */
    const int32_t *arr_base;     /* per array: first word */
    const float *arr_inv_h;      /* per array: voxels per array-space unit */
    const float *arr_sphere;     /* per array: centre xyz and radius (array space) of a sphere holding every voxel */
    const float *fold;           /* per array, per bin: 12 floats, rows (F00 F01 F02 f0, ...): array space -> grid */
    const float *world_fold[2];  /* per world-space array, per bin: the same from world space */
    const int32_t *row_start;    /* per row r = i n + j: offset of its words minus its first word index */
    const int32_t *row_span;     /* per row: first word | end word << 16 */
    int32_t wpd;                 /* words per direction */
    int32_t n_bins;
    float d_theta;               /* degrees */
    int32_t n_rings;
    const int32_t *ring_count;
    const int32_t *ring_start;
    int32_t n_world;             /* world-space arrays queried first, in SIMD: the static one, the per-frame one */
    int32_t world_array[2];
    float world_inv[2][12];      /* world -> that array's space, 3 x 4 */
    int32_t n_inst;
    const float *inst_inv;       /* per instance: world -> its array's space, 3 x 4 */
    const int32_t *inst_array;
    int32_t n_nodes;             /* BVH over the instances' world boxes */
    const float *node_box;       /* per node: lo xyz, hi xyz */
    const int32_t *node_kids;    /* per node: (first, count) for a leaf (count > 0), (left, -right) inside */
    const int32_t *bvh_items;
    float inst_voxel;            /* the largest world-space voxel over the instances (vq_query_refine's reach) */
} VQScene;

typedef struct {
    float offset, skip, slab, max_skip, end_skip, far;
    float far_center[3];
    int32_t seg;
} VQRule;


#define VQ_INLINE static inline __attribute__((always_inline))
#define DEG 57.29577951308232f
#define BATCH 256
#define PF_ROUNDS 2  /* the inputs are prefetched this many rounds of GROUPS groups ahead */

/* ---------------------------------------------------------------- scalar rule */

static inline float fast_atan2(float y, float x) {
    float ax = fabsf(x), ay = fabsf(y);
    float mx = ax > ay ? ax : ay;
    if (mx == 0.0f) return 0.0f;
    float a = (ax < ay ? ax : ay) / mx;
    float s = a * a;
    float r = a * (0.99997726f + s * (-0.33262347f + s * (0.19354346f + s * (-0.11643287f + s * (0.05265332f - 0.01172120f * s)))));
    if (ay > ax) r = 1.57079637f - r;
    if (x < 0.0f) r = 3.14159274f - r;
    if (y < 0.0f) r = -r;
    return r;
}

static inline int direction_bin(const VQScene *s, float dx, float dy, float dz) {
    if (dz < 0.0f) { dx = -dx; dy = -dy; dz = -dz; }
    float theta = fast_atan2(sqrtf(dx * dx + dy * dy), dz) * DEG;
    int ring = (int)(theta / s->d_theta + 0.5f);
    if (ring < 0) ring = 0;
    if (ring > s->n_rings - 1) ring = s->n_rings - 1;
    float phi = fast_atan2(dy, dx) * DEG;
    if (phi < 0.0f) phi += 360.0f;
    int cnt = s->ring_count[ring];
    int col = (int)(phi * (float)cnt * (1.0f / 360.0f) + 0.5f);
    if (col >= cnt) col -= cnt;
    return s->ring_start[ring] + col;
}

static inline void affine(const float *m, const float p[3], float out[3]) {
    for (int i = 0; i < 3; i++) out[i] = m[4 * i] * p[0] + m[4 * i + 1] * p[1] + m[4 * i + 2] * p[2] + m[4 * i + 3];
}

static inline float len3(const float v[3]) { return sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

/* one segment's walk through an array's bin grid (Alg. 2): the segment xa -> xb in the grid, clipped
 * to the cube and trimmed by the skips, and its voxels lo .. hi along the grid's third axis */
typedef struct {
    float qa[3], dq[3], t0, t1, inv_dw, fn;
    int n, lo, hi, forward, npieces;
    int64_t dir_base;
} Walk;

/* the walk of the segment xa -> xb in array a (``tab``: the array's folded maps from the space xa, xb
 * are in; ``da``: the segment in array space); its number of pieces of ``seg`` voxels, 0: none */
VQ_INLINE int walk_start(const VQScene *s, int a, const float *tab, const float xa[3], const float xb[3],
                         const float da[3], float skip0, float skip1, int seg, Walk *k) {
    int n = s->arr_n[a];
    float inv_h = s->arr_inv_h[a];
    float length = len3(da) * inv_h;
    if (length <= skip0 + skip1 || length <= 0.0f) return 0;
    int d = direction_bin(s, da[0], da[1], da[2]);
    const float *F = tab + (size_t)d * 12;
    float qb[3];
    affine(F, xa, k->qa);
    affine(F, xb, qb);
    for (int i = 0; i < 3; i++) k->dq[i] = qb[i] - k->qa[i];
    const float *qa = k->qa, *dq = k->dq;
    float t0 = skip0 / length, t1 = 1.0f - skip1 / length, fn = (float)n;
    for (int ax = 0; ax < 3; ax++) {
        int a_in = qa[ax] >= 0.0f && qa[ax] < fn, b_in = qb[ax] >= 0.0f && qb[ax] < fn;
        if (!(a_in && b_in)) {
            if (fabsf(dq[ax]) < 1.0e-12f) return 0;
            float inv = 1.0f / dq[ax];
            float ta = (0.0f - qa[ax]) * inv, tb = (fn - qa[ax]) * inv;
            float lo_t = ta < tb ? ta : tb, hi_t = ta < tb ? tb : ta;
            if (lo_t > t0) t0 = lo_t;
            if (hi_t < t1) t1 = hi_t;
        }
    }
    if (t0 > t1) return 0;
    float wa = qa[2] + dq[2] * t0, wb = qa[2] + dq[2] * t1;
    int lo = (int)(wa < wb ? wa : wb), hi = (int)(wa < wb ? wb : wa);
    k->lo = lo < 0 ? 0 : (lo > n - 1 ? n - 1 : lo);
    k->hi = hi < 0 ? 0 : (hi > n - 1 ? n - 1 : hi);
    k->forward = dq[2] >= 0.0f;
    k->dir_base = (int64_t)s->arr_base[a] + (int64_t)d * s->wpd;
    k->inv_dw = fabsf(dq[2]) > 1.0e-12f ? 1.0f / dq[2] : 0.0f;
    k->t0 = t0;
    k->t1 = t1;
    k->fn = fn;
    k->n = n;
    k->npieces = k->hi / seg - k->lo / seg + 1;
    return k->npieces;
}

/* piece p (from the segment's start): its voxels st .. en and the segment's grid position at its middle */
static inline void walk_piece(const Walk *k, int p, int seg, int *st, int *en, float *fu, float *fv) {
    int ps = k->forward ? (k->lo / seg + p) * seg : (k->hi / seg - p) * seg;
    *st = ps > k->lo ? ps : k->lo;
    *en = ps + seg - 1 < k->hi ? ps + seg - 1 : k->hi;
    float t = (0.5f * (float)(*st + *en + 1) - k->qa[2]) * k->inv_dw;
    t = t < k->t0 ? k->t0 : (t > k->t1 ? k->t1 : t);
    *fu = k->qa[0] + k->dq[0] * t;
    *fv = k->qa[1] + k->dq[1] * t;
}

/* the occupied voxels st .. en of row (fu, fv), as bits of their word; 0 outside the grid */
static inline uint32_t row_bits(const VQScene *s, const Walk *k, float fu, float fv, int st, int en) {
    if (!(fu >= 0.0f && fu < k->fn && fv >= 0.0f && fv < k->fn)) return 0;
    int r = (int)fu * k->n + (int)fv;
    int w = st >> 5, span = s->row_span[r];
    if (!(w >= (span & 0xFFFF) && w < (span >> 16))) return 0;
    uint32_t word = s->words[k->dir_base + s->row_start[r] + w];
    return word & (0xFFFFFFFFu >> (31 - (en & 31))) & (0xFFFFFFFFu << (st & 31));
}

/* first occupied voxel of the segment xa -> xb in array a, in voxels from its trimmed start; -1: free.
 * ``tab``: the array's folded maps (from the space xa, xb are in); ``da``: the segment in array space. */
static float array_hit(const VQScene *s, int a, const float *tab, const float xa[3], const float xb[3],
                       const float da[3], float skip0, float skip1, int seg, int want_t) {
    Walk k;
    int npieces = walk_start(s, a, tab, xa, xb, da, skip0, skip1, seg, &k);
    for (int p = 0; p < npieces; p++) {
        int st, en;
        float fu, fv;
        walk_piece(&k, p, seg, &st, &en, &fu, &fv);
        uint32_t hit = row_bits(s, &k, fu, fv, st, en);
        if (hit) {
            if (!want_t) return 0.0f;
            int first = k.forward ? __builtin_ctz(hit) : 31 - __builtin_clz(hit);
            float vox = (float)((st >> 5) * 32 + first);
            float w_start = k.qa[2] + k.dq[2] * k.t0;
            float dist = k.forward ? vox - w_start : w_start - (vox + 1.0f);
            return dist > 0.0f ? dist : 0.0f;
        }
    }
    return -1.0f;
}

/* the refinement's rays (vq_query_refine, vq_shade_refine): the centre one and, for each width, the
 * rows that many voxels to either side along the grid's u and v axes (u + w, u - w, v + w, v - w),
 * piece by piece, same voxels st .. en */
#define MAX_WIDTHS 4
#define MAX_RAYS (1 + 4 * MAX_WIDTHS)
typedef struct {
    int n, n_widths;                 /* rays: 1 + 4 n_widths */
    unsigned all;                    /* (1 << n) - 1 */
    float du[MAX_RAYS], dv[MAX_RAYS]; /* each ray's shift (voxels) */
    float reach;                     /* the widest width */
} Rays;

/* the rays of ``n_widths`` (at most MAX_WIDTHS) widths */
static Rays make_rays(const float *widths, int n_widths) {
    static const float SU[4] = {1.0f, -1.0f, 0.0f, 0.0f}, SV[4] = {0.0f, 0.0f, 1.0f, -1.0f};
    Rays R;
    R.n_widths = n_widths < 0 ? 0 : (n_widths > MAX_WIDTHS ? MAX_WIDTHS : n_widths);
    R.n = 1 + 4 * R.n_widths;
    R.all = (1u << R.n) - 1;
    R.du[0] = R.dv[0] = 0.0f;
    R.reach = 0.0f;
    for (int w = 0; w < R.n_widths; w++) {
        for (int j = 0; j < 4; j++) {
            R.du[1 + 4 * w + j] = SU[j] * widths[w];
            R.dv[1 + 4 * w + j] = SV[j] * widths[w];
        }
        if (widths[w] > R.reach) R.reach = widths[w];
    }
    return R;
}

/* array_hit for the rays: the bits (1 << ray) of those in ``need`` meeting an occupied voxel */
static unsigned array_refine(const VQScene *s, int a, const float *tab, const float xa[3], const float xb[3],
                             const float da[3], float skip0, float skip1, int seg, const Rays *R, unsigned need) {
    Walk k;
    int npieces = walk_start(s, a, tab, xa, xb, da, skip0, skip1, seg, &k);
    unsigned got = 0;
    for (int p = 0; p < npieces && (need & ~got); p++) {
        int st, en;
        float fu, fv;
        walk_piece(&k, p, seg, &st, &en, &fu, &fv);
        for (int j = 0; j < R->n; j++)
            if ((need & ~got) >> j & 1 && row_bits(s, &k, fu + R->du[j], fv + R->dv[j], st, en)) got |= 1u << j;
    }
    return got;
}

/* whether the segment o -> o + dl (inv: 1 / dl) meets the box b (lo xyz, hi xyz) grown by ``grow`` */
static inline int meets_box(const float *b, const float o[3], const float dl[3], const float inv[3], float grow) {
    float tn = 0.0f, tf = 1.0f;
    for (int i = 0; i < 3; i++) {
        float lo = b[i] - grow, hi = b[3 + i] + grow;
        if (dl[i] == 0.0f) {
            if (o[i] < lo || o[i] > hi) return 0;
            continue;
        }
        float ta = (lo - o[i]) * inv[i], tb = (hi - o[i]) * inv[i];
        if (ta > tb) { float x = ta; ta = tb; tb = x; }
        if (ta > tn) tn = ta;
        if (tb < tf) tf = tb;
        if (tn > tf) return 0;
    }
    return 1;
}

/* the segment o -> e through the moving instances whose world boxes it meets (Alg. 4): the first hit's
 * distance (instance_hits), or with ``R`` the rays' (array_refine): ``*clear`` the rays still free, in
 * and out. The shifted rays visit the boxes grown by ``grow`` (their reach, world units), the centre
 * one those the plain query visits. */
VQ_INLINE float instance_walk(const VQScene *s, const float o[3], const float e[3], float skip0, float skip1, int seg,
                              int want_t, const Rays *R, float grow, unsigned *clear) {
    int refine = R != NULL;
    if (s->n_inst <= 0 || s->n_nodes <= 0) return -1.0f;
    float dl[3] = {e[0] - o[0], e[1] - o[1], e[2] - o[2]};
    if (len3(dl) <= 0.0f) return -1.0f;
    float inv[3];
    for (int i = 0; i < 3; i++) inv[i] = dl[i] != 0.0f ? 1.0f / dl[i] : (dl[i] >= 0.0f ? INFINITY : -INFINITY);
    /* refine: node << 1 | whether the plain query visits it */
    int stack[128], top = 0;
    stack[top++] = refine ? 1 : 0;
    while (top > 0) {
        int item = stack[--top], node = refine ? item >> 1 : item;
        const float *b = s->node_box + 6 * (size_t)node;
        int centre = (!refine || (item & 1)) && meets_box(b, o, dl, inv, 0.0f);
        if (!centre && !(refine && meets_box(b, o, dl, inv, grow))) continue;
        int first = s->node_kids[2 * node], count = s->node_kids[2 * node + 1];
        if (count > 0) {
            for (int k = first; k < first + count; k++) {
                int inst = s->bvh_items[k];
                const float *m = s->inst_inv + 12 * (size_t)inst;
                float pa[3], pb[3], da[3];
                affine(m, o, pa);
                affine(m, e, pb);
                for (int i = 0; i < 3; i++) da[i] = pb[i] - pa[i];
                int a = s->inst_array[inst];
                const float *tab = s->fold + (size_t)a * s->n_bins * 12;
                if (refine) {
                    unsigned want = *clear & (centre ? R->all : R->all & ~1u);
                    if (want) *clear &= ~array_refine(s, a, tab, pa, pb, da, skip0, skip1, seg, R, want);
                    if (!*clear) return 0.0f;
                    continue;
                }
                float t = array_hit(s, a, tab, pa, pb, da, skip0, skip1, seg, want_t);
                if (t >= 0.0f) return t;
            }
        } else if (top + 2 <= 128) {
            stack[top++] = refine ? -count * 2 + centre : -count;
            stack[top++] = refine ? first * 2 + centre : first;
        }
    }
    return -1.0f;
}

static float instance_hits(const VQScene *s, const float o[3], const float e[3], float skip0, float skip1, int seg,
                           int want_t) {
    return instance_walk(s, o, e, skip0, skip1, seg, want_t, NULL, 0.0f, NULL);
}

/* the rays of ``*clear`` the instances block taken out of it (instance_walk) */
static void instance_refine(const VQScene *s, const float o[3], const float e[3], float skip0, float skip1, int seg,
                            const Rays *R, unsigned *clear) {
    instance_walk(s, o, e, skip0, skip1, seg, 0, R, R->reach * s->inst_voxel, clear);
}

/* where the ray leaves its surface and ends, and the voxels skipped at its start and end */
static inline void ray_setup(const VQRule *r, const float p[3], const float tg[3], const float nm[3], int distant,
                             float o[3], float e[3], float *skip0, float *skip1) {
    float dir[3];
    for (int i = 0; i < 3; i++) dir[i] = distant ? tg[i] : tg[i] - p[i];
    float nn = len3(nm), ln = len3(dir);
    for (int i = 0; i < 3; i++) o[i] = p[i];
    if (nn > 0.0f) {
        float nrm[3] = {nm[0] / nn, nm[1] / nn, nm[2] / nn};
        float sg = nrm[0] * dir[0] + nrm[1] * dir[1] + nrm[2] * dir[2] < 0.0f ? -1.0f : 1.0f;
        for (int i = 0; i < 3; i++) o[i] = p[i] + nrm[i] * sg * r->offset;
    }
    if (distant) {
        float lt = len3(tg);
        float oc[3] = {o[0] - r->far_center[0], o[1] - r->far_center[1], o[2] - r->far_center[2]};
        float reach = (len3(oc) + r->far) / lt;
        for (int i = 0; i < 3; i++) e[i] = o[i] + tg[i] * reach;
        *skip1 = 0.0f;
    } else {
        for (int i = 0; i < 3; i++) e[i] = tg[i];
        *skip1 = r->end_skip;
    }
    *skip0 = r->skip;
    if (nn > 0.0f && ln > 0.0f && r->slab > 0.0f) {
        float sin_b = fabsf(nm[0] * dir[0] + nm[1] * dir[1] + nm[2] * dir[2]) / (nn * ln);
        float k = r->slab / (sin_b > 1.0e-6f ? sin_b : 1.0e-6f);
        k = k < r->max_skip ? k : r->max_skip;
        *skip0 = k > r->skip ? k : r->skip;
    }
}

/* the segment o -> e in world-space array w's space (da) */
static inline void world_segment(const VQScene *s, int w, const float o[3], const float e[3], float da[3]) {
    float pa[3], pb[3];
    affine(s->world_inv[w], o, pa);
    affine(s->world_inv[w], e, pb);
    for (int i = 0; i < 3; i++) da[i] = pb[i] - pa[i];
}

static float shadow_scalar(const VQScene *s, const VQRule *r, const float p[3], const float tg[3], const float nm[3],
                           int distant, int want_t) {
    float o[3], e[3], s0, s1;
    ray_setup(r, p, tg, nm, distant, o, e, &s0, &s1);
    for (int w = 0; w < s->n_world; w++) {
        float da[3];
        world_segment(s, w, o, e, da);
        float t = array_hit(s, s->world_array[w], s->world_fold[w], o, e, da, s0, s1, r->seg, want_t);
        if (t >= 0.0f) return t;
    }
    return instance_hits(s, o, e, s0, s1, r->seg, want_t);
}

/* a query's answer from its rays' blocked bits: the centre ray's, and 2 where the centre ray and the
 * four of any width disagree */
static inline uint8_t refine_code(unsigned blocked, const Rays *R) {
    unsigned c = blocked & 1u, unsure = 0;
    for (int w = 0; w < R->n_widths; w++) {
        unsigned five = c | (blocked >> (1 + 4 * w) & 15u) << 1;
        unsure |= five != 0 && five != 31u;
    }
    return (uint8_t)(c | unsure << 1);
}

/* shadow_scalar for the rays (vq_query_refine): refine_code of their blocked bits */
static uint8_t shadow_refine(const VQScene *s, const VQRule *r, const float p[3], const float tg[3], const float nm[3],
                             int distant, const Rays *R) {
    float o[3], e[3], s0, s1;
    ray_setup(r, p, tg, nm, distant, o, e, &s0, &s1);
    unsigned clear = R->all;
    for (int w = 0; w < s->n_world && clear; w++) {
        float da[3];
        world_segment(s, w, o, e, da);
        clear &= ~array_refine(s, s->world_array[w], s->world_fold[w], o, e, da, s0, s1, r->seg, R, clear);
    }
    if (clear) instance_refine(s, o, e, s0, s1, r->seg, R, &clear);
    return refine_code(R->all & ~clear, R);
}

/* a batch: p, target and normal either as 9 coordinate arrays (``stride`` 1) or as three (n, 3)
 * arrays in c[0], c[3], c[6] (``stride`` 3); the distant flags */
typedef struct {
    const float *c[9];
    const int32_t *distant;
    int stride;
    const double *d[3];          /* stride 3: float64 points / targets / normals in place of c[0], c[3], c[6] (NULL: float32) */
    const uint8_t *distant8;     /* bool flags in place of distant (NULL: int32) */
} SoA;

/* query i of a batch: its point, target and normal, and whether it is distant */
static inline int batch_ray(const SoA *b, int i, float p[3], float t[3], float nm[3]) {
    float *dst[3] = {p, t, nm};
    for (int a = 0; a < 3; a++)
        for (int k = 0; k < 3; k++) {
            int j = b->stride == 3 ? 3 * i + k : i, c = b->stride == 3 ? 3 * a : 3 * a + k;
            dst[a][k] = b->stride == 3 && b->d[a] ? (float)b->d[a][j] : b->c[c][j];
        }
    return b->distant8 ? b->distant8[i] != 0 : b->distant[i] != 0;
}

static void batch_scalar(const VQScene *s, const VQRule *r, int n, const SoA *b, int want_t, float *out) {
    for (int i = 0; i < n; i++) {
        float p[3], t[3], nm[3];
        int dist = batch_ray(b, i, p, t, nm);
        out[i] = shadow_scalar(s, r, p, t, nm, dist, want_t);
    }
}

static void refine_scalar(const VQScene *s, const VQRule *r, int n, const SoA *b, const Rays *R, uint8_t *out) {
    for (int i = 0; i < n; i++) {
        float p[3], t[3], nm[3];
        int dist = batch_ray(b, i, p, t, nm);
        out[i] = shadow_refine(s, r, p, t, nm, dist, R);
    }
}

/* ---------------------------------------------------------------- Alg. 3 shading, shared */

typedef void (*BatchFn)(const VQScene *, const VQRule *, int, const SoA *, int, float *);

/* the batched shadow rays of vq_shade: blocked ones counted, the others' light added (rgb_b 0 .. 2), and with
 * material rows their specular part (rgb_b 3 .. 5) to ``specular`` (NULL: none); returns 0 */
static int flush(BatchFn fn, const VQScene *s, const VQRule *r, int nb, const SoA *b, float *res, float rgb_b[6][BATCH],
                 const int32_t *who, float *radiance, float *specular, int32_t *blocked) {
    if (nb <= 0) return 0;
    fn(s, r, nb, b, 0, res);
    for (int q = 0; q < nb; q++) {
        if (res[q] >= 0.0f) {
            blocked[who[q]]++;
            continue;
        }
        for (int k = 0; k < 3; k++) radiance[3 * who[q] + k] += rgb_b[k][q];
        if (specular)
            for (int k = 0; k < 3; k++) specular[3 * who[q] + k] += rgb_b[3 + k][q];
    }
    return 0;
}

typedef void (*RefineFn)(const VQScene *, const VQRule *, int, const SoA *, const Rays *, uint8_t *);

/* vq_shade_refine's rays and list (the queries shading leaves to the caller); NULL in vq_shade */
typedef struct {
    Rays rays;
    const uint8_t *near;          /* per point, whether its certain free answers are listed (NULL: none) */
    int32_t *point, *light;       /* per entry: the point, the light, */
    float *rgb;                   /* the light's term (3 floats) */
    uint8_t *kind;                /* and 0 uncertain, 1 certain free at a near point */
    int64_t capacity, count;      /* entries the list holds, entries written */
    int64_t resume, queries;      /* the tile the caller resumes from, shadow queries answered */
} Listing;

/* vq_shade_refine's flush: the batch's answers by the refinement's rays (o->rays); the certain blocked
 * counted, the certain free added but a near point's, which is listed as kind 1, and the uncertain
 * listed as kind 0; returns 0 */
static int flush_refine(RefineFn fn, const VQScene *s, const VQRule *r, int nb, const SoA *b, uint8_t *code,
                        float rgb_b[6][BATCH], const int32_t *who, const int32_t *light, float *radiance,
                        int32_t *blocked, Listing *o) {
    if (nb <= 0) return 0;
    fn(s, r, nb, b, &o->rays, code);
    o->queries += nb;
    for (int q = 0; q < nb; q++) {
        int32_t i = who[q];
        uint8_t kind;
        if (code[q] & 2) {
            kind = 0;
        } else if (code[q] & 1) {
            blocked[i]++;
            continue;
        } else if (o->near && o->near[i]) {
            kind = 1;
        } else {
            for (int k = 0; k < 3; k++) radiance[3 * i + k] += rgb_b[k][q];
            continue;
        }
        int64_t c = o->count++;
        o->point[c] = i;
        o->light[c] = light[q];
        for (int k = 0; k < 3; k++) o->rgb[3 * c + k] = rgb_b[k][q];
        o->kind[c] = kind;
    }
    return 0;
}

/* a shading batch's flush: vq_shade's, or with a list vq_shade_refine's (the light of each ray in light; no
 * material rows) */
VQ_INLINE int flush_shade(BatchFn fn, RefineFn rfn, Listing *o, const VQScene *s, const VQRule *r, int nb,
                          const SoA *b, float *res, uint8_t *code, float rgb_b[6][BATCH], const int32_t *who,
                          const int32_t *light, float *radiance, float *specular, int32_t *blocked) {
    return o ? flush_refine(rfn, s, r, nb, b, code, rgb_b, who, light, radiance, blocked, o)
             : flush(fn, s, r, nb, b, res, rgb_b, who, radiance, specular, blocked);
}

/* whether tile t of ``points`` points starts: always without a list, else when the list has room for
 * all its pairs; where not, the tile is where the caller resumes */
VQ_INLINE int tile_fits(Listing *o, int64_t t, int64_t points, int n_lights) {
    if (!o || o->capacity - o->count >= points * (int64_t)n_lights) return 1;
    o->resume = t;
    return 0;
}

#define MAX_TILE 256     /* most points per shading tile of the SIMD shading */

/* ---------------------------------------------------------------- SIMD: 16 (AVX2) or 32 (AVX-512) queries at a time */


#ifdef VQ_X86
/* each instruction set with two registers per vector (simd_x2.h): AVX-512 32 lanes, AVX2 16; two groups
 * in flight (on the city's bench rays, one thread: AVX-512 15.2 -> 13.6 ns a query against one register
 * of 16 lanes and four groups, AVX2 23.2-23.5 -> 19.5-21.8 ns against 8 lanes and four groups) */
#define GROUPS 2     /* SIMD groups whose memory reads overlap (voxelq_simd.h's batch) */
#define X2_TAG avx2x2
#include "simd_avx2.h"
#include "simd_x2.h"
#include "voxelq_simd.h"
#include "simd_undef.h"
#undef X2_TAG

#define X2_TAG avx512x2
#include "simd_avx512.h"
#include "simd_x2.h"
#include "voxelq_simd.h"
#include "simd_undef.h"
#undef X2_TAG
#endif

/* one instruction set's batches: the queries' and vq_query_refine's */
typedef struct {
    BatchFn query;
    RefineFn refine;
} Kernels;

/* kernel: 0 the widest this CPU has, 1 scalar, 2 at most AVX2 */
static Kernels pick(int kernel) {
#ifdef VQ_X86
    switch (simd_lanes(kernel)) {
    case 16: return (Kernels){batch_avx512x2, batch_refine_avx512x2};
    case 8: return (Kernels){batch_avx2x2, batch_refine_avx2x2};
    }
#endif
    return (Kernels){batch_scalar, refine_scalar};
}

/* ---------------------------------------------------------------- entry points */

/* queries answered at once by ``kernel`` (as pick) on this CPU: 32 (AVX-512), 16 (AVX2), both as two
 * registers per vector, or 1 (plain C) */
int vq_simd_width(int32_t kernel) {
    int lanes = simd_lanes(kernel);
    return lanes > 1 ? 2 * lanes : 1;
}

/* the lanes of one register of the instruction set ``kernel`` runs: 16 (AVX-512), 8 (AVX2) or 1 */
int vq_simd_isa(int32_t kernel) { return simd_lanes(kernel); }

/* queries first .. of vq_query's inputs as a batch */
static SoA query_inputs(int64_t first, const void *pts, const void *tgt, const void *nrm, const void *distant,
                       int32_t f64_mask, int32_t distant_u8) {
    SoA b = {{NULL}, NULL, 3, {NULL}, NULL};
    const void *src[3] = {pts, tgt, nrm};
    for (int a = 0; a < 3; a++) {
        if (f64_mask >> a & 1) b.d[a] = (const double *)src[a] + 3 * first;
        else b.c[3 * a] = (const float *)src[a] + 3 * first;
    }
    if (distant_u8) b.distant8 = (const uint8_t *)distant + first;
    else b.distant = (const int32_t *)distant + first;
    return b;
}

/* queries first .. first + count of (n, 3) float32 points, targets, normals and int32 distant flags;
 * out[i] = distance in voxels to the first occupied voxel (0 for any hit unless want_t), -1 free; or,
 * when blocked is not NULL, blocked[i] = 1 for a hit, 0 free (out unused: occluded() wants no more, and
 * on the city's bench rays a float per ray and NumPy's comparison pass took 5 % of the time).
 * f64_mask bit a: input a (points, targets, normals) is float64; distant_u8: the flags are bytes (bool).
 * kernel: as pick(). */
#define BYTES_CHUNK 8192     /* queries answered into a float buffer on the stack per call, for blocked */
void vq_query(const VQScene *s, const VQRule *r, int64_t first, int64_t count, const void *pts, const void *tgt,
              const void *nrm, const void *distant, int32_t want_t, int32_t kernel, float *out, int32_t f64_mask,
              int32_t distant_u8, uint8_t *blocked) {
    BatchFn fn = pick(kernel).query;
    SoA b = query_inputs(first, pts, tgt, nrm, distant, f64_mask, distant_u8);
    if (!blocked) {
        fn(s, r, (int)count, &b, want_t, out + first);
        return;
    }
    float buf[BYTES_CHUNK];
    for (int64_t i = 0; i < count; i += BYTES_CHUNK) {
        int m = count - i < BYTES_CHUNK ? (int)(count - i) : BYTES_CHUNK;
        SoA c = b;
        for (int a = 0; a < 3; a++) {
            if (c.d[a]) c.d[a] += 3 * i;
            else c.c[3 * a] += 3 * i;
        }
        if (c.distant8) c.distant8 += i;
        else c.distant += i;
        fn(s, r, m, &c, 0, buf);
        for (int q = 0; q < m; q++) blocked[first + i + q] = buf[q] >= 0.0f;
    }
}

/* vq_query's queries (its inputs and ``kernel``), each answered with whether its answer is certain:
 * out[first + i] = blocked (vq_query's answer) | uncertain << 1. Uncertain at a width: the five rays of
 * the query disagree, the centre one and the rows that many voxels to either side of it along the bin
 * grid's u and v axes, looked up for each of the centre ray's pieces over the same voxels (outside
 * the grid: free), each ray blocked when any array blocks it; uncertain at any of the ``n_widths``
 * (at most 4) ``widths``, all looked up in one pass. The shifted rays visit the instances whose world
 * boxes grown by the widest width of the largest instance voxel (inst_voxel) the segment meets. */
void vq_query_refine(const VQScene *s, const VQRule *r, int64_t first, int64_t count, const void *pts, const void *tgt,
                     const void *nrm, const void *distant, const float *widths, int32_t n_widths, int32_t kernel,
                     int32_t f64_mask, int32_t distant_u8, uint8_t *out) {
    SoA b = query_inputs(first, pts, tgt, nrm, distant, f64_mask, distant_u8);
    Rays R = make_rays(widths, n_widths);
    pick(kernel).refine(s, r, (int)count, &b, &R, out + first);
}

/* Alg. 3 over tiles first_tile .. of ``tile`` points (vq_shade's, and with a list vq_shade_refine's),
 * in plain C: the shadow rays in batches. With material rows ``mat`` (NULL: Lambertian) each light's term is
 * split by the BRDF (brdf.h): E kd summed into radiance, E ks into specular. */
VQ_INLINE void shade_scalar(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts, const float *nrm,
                            const float *geo, int64_t n_points, int64_t first_tile, int64_t n_tiles, int32_t tile,
                            Kernels fns, Listing *o, const float *mat, float *radiance, float *specular,
                            int32_t *blocked, int32_t *facing) {
    float buf[9][BATCH], rgb_b[6][BATCH], res[BATCH];
    int32_t dist_b[BATCH], who[BATCH], light_b[BATCH];
    uint8_t code[BATCH];
    SoA b = {{NULL}, dist_b, 1, {NULL}, NULL};
    for (int k = 0; k < 9; k++) b.c[k] = buf[k];
    for (int64_t t = first_tile; t < first_tile + n_tiles; t++) {
        int64_t i0 = t * tile, i1 = i0 + tile < n_points ? i0 + tile : n_points;
        if (i0 >= i1) break;
        if (!tile_fits(o, t, i1 - i0, L->n)) return;
        for (int64_t i = i0; i < i1; i++) {
            radiance[3 * i] = radiance[3 * i + 1] = radiance[3 * i + 2] = 0.0f;
            if (mat) specular[3 * i] = specular[3 * i + 1] = specular[3 * i + 2] = 0.0f;
            blocked[i] = facing[i] = 0;
        }
        int nb = 0;
        for (int l = 0; l < L->n; l++) {
            for (int64_t i = i0; i < i1; i++) {
                float rgb[3], tg[3], sp[3] = {0.0f, 0.0f, 0.0f};
                int code_l = light_term(L, l, pts + 3 * i, nrm + 3 * i, geo + 3 * i, rgb, tg);
                if (!code_l) continue;
                facing[i]++;
                if (mat) {
                    /* the unit direction to the light, as light_term's (-axis for a distant light) */
                    int dist = L->flags[l] & DISTANT;
                    float lv[3], kd[3], ks[3];
                    for (int k = 0; k < 3; k++) lv[k] = dist ? tg[k] : tg[k] - pts[3 * i + k];
                    float d2 = dist ? 1.0f : dot3(lv, lv), inv_d = 1.0f / sqrtf(d2 > 1.0e-30f ? d2 : 1.0e-30f);
                    for (int k = 0; k < 3; k++) lv[k] *= inv_d;
                    brdf_terms(mat + (size_t)BRDF_WIDTH * i, nrm + 3 * i, lv, kd, ks);
                    for (int k = 0; k < 3; k++) {
                        sp[k] = rgb[k] * ks[k];
                        rgb[k] *= kd[k];
                    }
                }
                if (code_l == 1) {
                    for (int k = 0; k < 3; k++) radiance[3 * i + k] += rgb[k];
                    if (mat)
                        for (int k = 0; k < 3; k++) specular[3 * i + k] += sp[k];
                    continue;
                }
                for (int k = 0; k < 3; k++) {
                    buf[k][nb] = pts[3 * i + k];
                    buf[3 + k][nb] = tg[k];
                    buf[6 + k][nb] = geo[3 * i + k];
                    rgb_b[k][nb] = rgb[k];
                    if (mat) rgb_b[3 + k][nb] = sp[k];
                }
                dist_b[nb] = L->flags[l] & DISTANT;
                light_b[nb] = l;
                who[nb++] = (int32_t)i;
                if (nb == BATCH)
                    nb = flush_shade(fns.query, fns.refine, o, s, r, nb, &b, res, code, rgb_b, who, light_b, radiance,
                                     mat ? specular : NULL, blocked);
            }
        }
        flush_shade(fns.query, fns.refine, o, s, r, nb, &b, res, code, rgb_b, who, light_b, radiance,
                    mat ? specular : NULL, blocked);
    }
}

/* vq_shade or, with a list, vq_shade_refine (no material rows): the SIMD shading where ``kernel`` has it, else
 * plain C */
VQ_INLINE void shade_any(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts, const float *nrm,
                         const float *geo, int64_t n_points, int64_t first_tile, int64_t n_tiles, int32_t tile,
                         int32_t kernel, Listing *o, const float *mat, float *radiance, float *specular,
                         int32_t *blocked, int32_t *facing) {
    Kernels fns = pick(kernel);
#ifdef VQ_X86
    if (tile <= MAX_TILE && (fns.query == batch_avx512x2 || fns.query == batch_avx2x2)) {
        int wide = fns.query == batch_avx512x2;
        if (o)
            (wide ? shade_refine_avx512x2 : shade_refine_avx2x2)(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles,
                                                               tile, radiance, blocked, facing, o);
        else if (mat)
            (wide ? shade_material_avx512x2 : shade_material_avx2x2)(s, r, L, pts, nrm, geo, n_points, first_tile,
                                                                   n_tiles, tile, mat, radiance, specular, blocked,
                                                                   facing);
        else
            (wide ? shade_avx512x2 : shade_avx2x2)(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile,
                                                 radiance, blocked, facing);
        return;
    }
#endif
    if (mat)
        shade_scalar(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, fns, o, mat, radiance, specular,
                     blocked, facing);
    else
        shade_scalar(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, fns, o, NULL, radiance, NULL,
                     blocked, facing);
}

/* Alg. 3 over tiles first_tile .. first_tile + n_tiles of ``tile`` points (kernels/voxel/shading.py's
 * shade_tiles): radiance (3 per point), blocked and facing counts; shadow rays in batches. With material rows
 * ``mat`` (BRDF_WIDTH floats per point, brdf.h; NULL: Lambertian, radiance the sum of E) each visible light adds
 * E kd to radiance and E ks to ``specular`` (3 per point). */
void vq_shade(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts, const float *nrm, const float *geo,
              int64_t n_points, int64_t first_tile, int64_t n_tiles, int32_t tile, int32_t kernel, float *radiance,
              int32_t *blocked, int32_t *facing, const float *mat, float *specular) {
    shade_any(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, kernel, NULL, mat, radiance, specular,
              blocked, facing);
}

/* the caller's answers to vq_shade_refine's list: entry k (of n; point list_point[k], term list_rgb[3 k ..])
 * free[k] != 0: its light added to the point's radiance, else the point's blocked count + 1. Entries of one
 * point are added in list order, in float32 as the kernel adds its certain lights (the list's order is the
 * same whatever the bands: the same pixels on any number of threads). */
void vq_list_apply(int64_t n, const int32_t *list_point, const float *list_rgb, const uint8_t *free_, float *radiance,
                   int32_t *blocked) {
    for (int64_t k = 0; k < n; k++) {
        int32_t i = list_point[k];
        if (free_[k])
            for (int c = 0; c < 3; c++) radiance[3 * (int64_t)i + c] += list_rgb[3 * k + c];
        else blocked[i]++;
    }
}

/* vq_shade with the refinement's rule (vq_query_refine's, over the ``n_widths`` widths ``widths``, at
 * most 4: uncertain where the centre ray and the four rows of any width disagree; blocked the centre
 * ray's, vq_shade's answer). Per shadow query: uncertain, it is listed (kind 0) and not counted;
 * certain and blocked, blocked[i]++; certain and free, its light added, but at a point with near[i]
 * (near NULL: none) it is listed (kind 1) instead. Lights without a shadow test are added. The list:
 * entries *count .. (in and out) of list_point, list_light (int32), list_rgb (3 floats: the light's
 * term) and list_kind, which hold ``capacity``; a tile starts only while the list has room for all its
 * pairs (points x lights), else *resume_tile is that tile (the caller empties the list and calls again
 * from it), and first_tile + n_tiles when every tile was shaded. *queries (when not NULL) is added the
 * shadow queries answered. Point indices are those of pts. */
void vq_shade_refine(const VQScene *s, const VQRule *r, const VQLights *L, const float *pts, const float *nrm,
                     const float *geo, int64_t n_points, int64_t first_tile, int64_t n_tiles, int32_t tile,
                     int32_t kernel, const float *widths, int32_t n_widths, const uint8_t *near, float *radiance,
                     int32_t *blocked, int32_t *facing, int32_t *list_point, int32_t *list_light, float *list_rgb,
                     uint8_t *list_kind, int64_t capacity, int64_t *count, int64_t *resume_tile, int64_t *queries) {
    Listing o = {make_rays(widths, n_widths), near, list_point, list_light, list_rgb, list_kind, capacity, *count,
                 first_tile + n_tiles, 0};
    shade_any(s, r, L, pts, nrm, geo, n_points, first_tile, n_tiles, tile, kernel, &o, NULL, radiance, NULL, blocked,
              facing);
    *count = o.count;
    *resume_tile = o.resume;
    if (queries) *queries += o.queries;
}

/* ---------------------------------------------------------------- Alg. 5, point mapping */

/* directions d0 .. d1 - 1 of an array filled from the reference voxelization's occupied voxels by the
 * rotation tables (kernels/voxel/rotate.py's rotate_voxels with the point mapping, the same integer
 * arithmetic): row_ij / row_start / depth the voxels grouped by row, table (directions x 3 x n, 3)
 * 16.16 fixed-point steps, rows (n^2) each row's offset << 10 | first stored word << 5 | stored words
 * (one int: 5.55 against 8.66 ns per voxel with three, the bear at 128^3 / 2 deg, one thread); each
 * direction's words (wpd from out + base + d wpd) are cleared first */
void vq_rotate_point(const int32_t *row_ij, const int32_t *row_start, const int32_t *depth, int32_t n_rows,
                     const int32_t *table, int32_t n, int32_t d0, int32_t d1, const int32_t *rows, int32_t wpd,
                     int64_t base, uint32_t *out) {
    for (int d = d0; d < d1; d++) {
        uint32_t *dir = out + base + (int64_t)d * wpd;
        memset(dir, 0, sizeof(uint32_t) * (size_t)wpd);
        const int32_t *t0 = table + (size_t)d * 9 * n, *t1 = t0 + 3 * n, *t2 = t1 + 3 * n;
        for (int r = 0; r < n_rows; r++) {
            int ij = row_ij[r], i = ij >> 10, j = ij & 1023;
            int rx = t0[3 * i] + t1[3 * j], ry = t0[3 * i + 1] + t1[3 * j + 1], rz = t0[3 * i + 2] + t1[3 * j + 2];
            for (int v = row_start[r]; v < row_start[r + 1]; v++) {
                const int32_t *t = t2 + 3 * depth[v];
                int iu = (rx + t[0]) >> 16, iv = (ry + t[1]) >> 16, il = (rz + t[2]) >> 16;
                if (iu < 0 || iu >= n || iv < 0 || iv >= n) continue;
                int pk = rows[iu * n + iv], k = (il >> 5) - ((pk >> 5) & 31);
                if ((unsigned)k < (unsigned)(pk & 31)) dir[(pk >> 10) + k] |= 1u << (il & 31);
            }
        }
    }
}

/* ---------------------------------------------------------------- BVH over instance boxes */

typedef struct {
    const float *lo, *hi;
    int32_t *items;
    float *box;
    int32_t *kids;
    int used;
} Build;

static float centroid(const Build *b, int item, int axis) { return b->lo[3 * item + axis] + b->hi[3 * item + axis]; }

static void select_nth(Build *b, int *it, int n, int k, int axis) {
    int lo = 0, hi = n - 1;
    while (lo < hi) {
        float pivot = centroid(b, it[(lo + hi) / 2], axis);
        int i = lo, j = hi;
        while (i <= j) {
            while (centroid(b, it[i], axis) < pivot) i++;
            while (centroid(b, it[j], axis) > pivot) j--;
            if (i <= j) { int x = it[i]; it[i] = it[j]; it[j] = x; i++; j--; }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else break;
    }
}

static int build_node(Build *b, int first, int count) {
    int node = b->used++;
    float *box = b->box + 6 * (size_t)node;
    float clo[3] = {INFINITY, INFINITY, INFINITY}, chi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int k = 0; k < 3; k++) { box[k] = INFINITY; box[3 + k] = -INFINITY; }
    for (int i = first; i < first + count; i++) {
        int it = b->items[i];
        for (int k = 0; k < 3; k++) {
            if (b->lo[3 * it + k] < box[k]) box[k] = b->lo[3 * it + k];
            if (b->hi[3 * it + k] > box[3 + k]) box[3 + k] = b->hi[3 * it + k];
            float c = centroid(b, it, k);
            if (c < clo[k]) clo[k] = c;
            if (c > chi[k]) chi[k] = c;
        }
    }
    if (count <= 4) {
        b->kids[2 * node] = first;
        b->kids[2 * node + 1] = count;
        return node;
    }
    int axis = 0;
    for (int k = 1; k < 3; k++)
        if (chi[k] - clo[k] > chi[axis] - clo[axis]) axis = k;
    int half = count / 2;
    select_nth(b, b->items + first, count, half, axis);
    int left = build_node(b, first, half);
    int right = build_node(b, first + half, count - half);
    b->kids[2 * node] = left;
    b->kids[2 * node + 1] = -right;
    return node;
}

/* a BVH over n boxes (lo, hi: 3 floats each): items (n), node boxes (6 per node) and kids (2 per
 * node) sized for 2 n nodes; returns the node count */
int32_t vq_build_bvh(int32_t n, const float *lo, const float *hi, int32_t *items, float *box, int32_t *kids) {
    if (n <= 0) return 0;
    Build b = {lo, hi, items, box, kids, 0};
    for (int i = 0; i < n; i++) items[i] = i;
    build_node(&b, 0, n);
    return b.used;
}

/* an importable module, so that the import system finds the library (usdml.visibility.voxel.native) */
static struct PyModuleDef vq_module = {PyModuleDef_HEAD_INIT, .m_name = "_voxelq",
                                       .m_doc = "Compiled voxel shadow queries; called through ctypes.", .m_size = -1};

PyMODINIT_FUNC PyInit__voxelq(void) { return PyModule_Create(&vq_module); }
