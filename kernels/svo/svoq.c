/* The SVO restart traversal (paper 003, Fig. 3) compiled for the CPU: the same rule, layout and
 * float32 arithmetic as kernels/svo/octree.py (read its module doc first), called through ctypes by
 * usdml/visibility/svo/native.py on bands of queries from several threads (ctypes drops the GIL).
 *
 * Two kernels, picked at run time like voxelq.c's: a scalar walk, one ray at a time, and a SIMD walk
 * (svoq_simd.h, AVX2: 8 rays, AVX-512: 16) in which every lane walks its own ray one node per
 * iteration and takes the next ray when its own ends. One ray's walk is a chain of dependent loads
 * and unpredictable branches (is this node empty? which face does the ray leave by?); the lanes turn
 * the branches into masks and overlap the chains.
 *
 * One difference in how, not what: after leaving an empty node, Fig. 3 descends again from the root.
 * Here the descent starts at the deepest node that still holds the next voxel (the highest bit in
 * which the old and new voxel coordinates differ says which), whose child groups were read on the
 * way down and kept: the same nodes are reached, so the answers are the same (tests compare both).
 */
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "simd_pick.h"

#if defined(__x86_64__) || defined(_M_X64)
#define SQ_X86 1
#include <immintrin.h>
#endif

#define BIG 1.0e30f
#define MAX_LEVELS 16

typedef struct {
    const int32_t *nodes;      /* groups of eight child entries, every tree */
    const uint32_t *bricks;    /* two words per brick, every tree */
    const int32_t *tree_int;   /* per tree: depth, node_base, brick_base, top_base */
    const float *tree_lo;      /* per tree: corner (3) */
    const float *tree_inv_h;   /* per tree: 1 / voxel size */
    int32_t n_trees;
    const int32_t *tops;       /* per tree from top_base: the dense top table (svo/tree.py: top_table) */
    int32_t top_level;         /* its level T (svo/tree.py: TOP_LEVEL, or depth - 2 for small trees) */
} SvoScene;

typedef struct {
    float offset, skip, slab, max_skip, end_skip, far;
    float far_center[3];
} SvoRule;

static inline uint32_t octant_mask(int octant, int word) {
    uint32_t base = 0x33u;
    uint32_t s = (uint32_t)((octant & 1) * 2 + ((octant >> 1) & 1) * 8);
    return (((octant >> 2) & 1) == word) ? ((base << s) | (base << (s + 16))) : 0u;
}

static inline int clampi(int v, int a, int b) { return v < a ? a : (v > b ? b : v); }
/* floor, min and max without libm calls: the baseline x86-64 target has no SSE4.1 rounding, and
 * fminf / fmaxf keep NaN rules that cost a call (measured: 61 -> see docs/svo.md ns per step) */
static inline int ifloor(float x) { int i = (int)x; return i - (x < (float)i); }
static inline float fmin2(float a, float b) { return a < b ? a : b; }
static inline float fmax2(float a, float b) { return a > b ? a : b; }

/* one ray in one tree, in the tree's voxel units: the start of tree_hit in kernels/svo/octree.py */
typedef struct {
    float q[3], dir[3], inv[3], t, tb;
    int c[3];
} Walk;

/* the clipped segment of world segment o -> e without its first skip0 and last skip1 world units
 * (to_infinity: no end) in tree tr; 0 when nothing of it lies in the tree's grid */
static inline int walk_setup(const SvoScene *s, int tr, const float o[3], const float e[3], float skip0, float skip1,
                             int to_infinity, Walk *w) {
    const int n = 1 << s->tree_int[4 * tr];
    const float inv_h = s->tree_inv_h[tr];
    const float *lo = s->tree_lo + 3 * tr;
    float dv[3];
    for (int a = 0; a < 3; a++) {
        w->q[a] = (o[a] - lo[a]) * inv_h;
        dv[a] = (e[a] - lo[a]) * inv_h - w->q[a];
    }
    float length = sqrtf(dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]);
    if (!(length > 0.0f)) return 0;
    float ta = skip0 * inv_h, tb = length - skip1 * inv_h;
    if (to_infinity) tb = BIG;
    const float fn = (float)n;
    for (int a = 0; a < 3; a++) {
        w->dir[a] = dv[a] / length;
        w->inv[a] = BIG;
        if (w->dir[a] != 0.0f) {
            w->inv[a] = 1.0f / w->dir[a];
            float t0 = (0.0f - w->q[a]) * w->inv[a], t1 = (fn - w->q[a]) * w->inv[a];
            ta = fmax2(ta, fmin2(t0, t1));
            tb = fmin2(tb, fmax2(t0, t1));
        } else if (w->q[a] < 0.0f || w->q[a] >= fn) {
            return 0;
        }
    }
    if (ta >= tb) return 0;
    for (int a = 0; a < 3; a++) w->c[a] = clampi(ifloor(w->q[a] + w->dir[a] * ta), 0, n - 1);
    w->t = ta;
    w->tb = tb;
    return 1;
}

/* the rest of tree_hit: the distance in voxels to the first occupied voxel, -1 when free */
static float walk_scalar(const SvoScene *s, int tr, Walk *w) {
    const int32_t *ti = s->tree_int + 4 * tr;
    const int depth = ti[0];
    const int32_t *nodes = s->nodes + ti[1];
    const uint32_t *bricks = s->bricks + 2 * (int64_t)ti[2];
    const int n = 1 << depth;
    const float *q = w->q, *dir = w->dir, *inv = w->inv;
    const float tb = w->tb;
    float t = w->t;
    int c[3] = {w->c[0], w->c[1], w->c[2]};
    int32_t stack[MAX_LEVELS];      /* group read at each level of the last descent */
    stack[1] = 0;
    int reached = 1, start = 1;
    for (;;) {
        int size = 1, hit = 0, level, g = stack[start];
        for (level = start; level < depth - 1; level++) {
            const int shift = depth - level;
            const int octant = ((c[0] >> shift) & 1) | (((c[1] >> shift) & 1) << 1) | (((c[2] >> shift) & 1) << 2);
            stack[level] = g;
            const int32_t entry = nodes[8 * g + octant];
            if (entry == 0) { size = 1 << shift; break; }
            if (level < depth - 2) { g = entry; continue; }
            const uint32_t *bw = bricks + 2 * (int64_t)(entry - 1);
            const int sub = ((c[0] >> 1) & 1) | (((c[1] >> 1) & 1) << 1) | (((c[2] >> 1) & 1) << 2);
            const int wsub = (sub >> 2) & 1;
            if ((bw[wsub] & octant_mask(sub, wsub)) == 0u) {
                size = 2;
            } else {
                const int bit = (c[0] & 3) + 4 * (c[1] & 3) + 16 * (c[2] & 3);
                if ((bw[bit >> 5] >> (bit & 31)) & 1u) hit = 1;
                size = 1;
            }
            break;
        }
        if (hit) return t;
        reached = level < depth - 1 ? level : depth - 2;
        /* leave the empty node through its far face */
        const int m = ~(size - 1);
        const int cx = c[0] & m, cy = c[1] & m, cz = c[2] & m;
        const float fx = (float)(dir[0] > 0.0f ? cx + size : cx);
        const float fy = (float)(dir[1] > 0.0f ? cy + size : cy);
        const float fz = (float)(dir[2] > 0.0f ? cz + size : cz);
        const float tx = dir[0] != 0.0f ? (fx - q[0]) * inv[0] : BIG;
        const float ty = dir[1] != 0.0f ? (fy - q[1]) * inv[1] : BIG;
        const float tz = dir[2] != 0.0f ? (fz - q[2]) * inv[2] : BIG;
        const float t_exit = fmin2(tx, fmin2(ty, tz));
        if (t_exit >= tb) return -1.0f;
        t = fmax2(t, t_exit);
        int nx = clampi(ifloor(q[0] + dir[0] * t_exit), cx, cx + size - 1);
        int ny = clampi(ifloor(q[1] + dir[1] * t_exit), cy, cy + size - 1);
        int nz = clampi(ifloor(q[2] + dir[2] * t_exit), cz, cz + size - 1);
        if (tx <= ty && tx <= tz) nx = dir[0] > 0.0f ? cx + size : cx - 1;
        else if (ty <= tz) ny = dir[1] > 0.0f ? cy + size : cy - 1;
        else nz = dir[2] > 0.0f ? cz + size : cz - 1;
        if (nx < 0 || nx >= n || ny < 0 || ny >= n || nz < 0 || nz >= n) return -1.0f;
        /* restart at the deepest kept node that holds the new voxel */
        const unsigned diff = (unsigned)((nx ^ c[0]) | (ny ^ c[1]) | (nz ^ c[2]));
        const int b = 31 - __builtin_clz(diff | 1u);
        start = depth - b;
        if (start > reached) start = reached;
        if (start < 1) start = 1;
        c[0] = nx; c[1] = ny; c[2] = nz;
    }
}

static inline void load3(const void *p, int f64, int64_t i, float out[3]) {
    if (f64) {
        const double *d = (const double *)p + 3 * i;
        out[0] = (float)d[0]; out[1] = (float)d[1]; out[2] = (float)d[2];
    } else {
        const float *f = (const float *)p + 3 * i;
        out[0] = f[0]; out[1] = f[1]; out[2] = f[2];
    }
}

/* rays of a chunk: the inputs as float32 (structure of arrays), then after the surface rule
 * (shadow_segment in kernels/svo/octree.py) the segments each tree walks */
#define CHUNK 1024
typedef struct {
    float p[3][CHUNK], tg[3][CHUNK], nr[3][CHUNK];
    int32_t dist[CHUNK];
    float o[3][CHUNK], e[3][CHUNK], skip0[CHUNK], skip1[CHUNK];
    int32_t inf[CHUNK];                     /* distant: no end */
    int32_t pending[CHUNK], n_pending;      /* rays no tree has hit yet, by index in the chunk */
} Chunk;

/* the walks of a chunk's pending rays in one tree, structure of arrays (the SIMD walk's setup) */
typedef struct {
    float q[3][CHUNK], dir[3][CHUNK], inv[3][CHUNK], t[CHUNK], tb[CHUNK];
    int32_t c[3][CHUNK], ok[CHUNK];
} Walks;

typedef struct {
    const void *origins, *targets, *normals;
    int o_f64, t_f64, n_f64;
    const uint8_t *distant;
} Inputs;

/* queries i0 .. i0 + m - 1 into the chunk as float32, out = -1 for all */
static void chunk_load(const Inputs *in, int64_t i0, int m, Chunk *ch, float *out) {
    for (int k = 0; k < m; k++) {
        float a[3], b[3], c[3] = {0.0f, 0.0f, 0.0f};
        load3(in->origins, in->o_f64, i0 + k, a);
        load3(in->targets, in->t_f64, i0 + k, b);
        if (in->normals) load3(in->normals, in->n_f64, i0 + k, c);
        for (int x = 0; x < 3; x++) { ch->p[x][k] = a[x]; ch->tg[x][k] = b[x]; ch->nr[x][k] = c[x]; }
        ch->dist[k] = in->distant ? in->distant[i0 + k] != 0 : 0;
        out[i0 + k] = -1.0f;
    }
}

/* shadow_segment's surface rule for the chunk's m rays, one at a time; rays with no length are left
 * out of the pending list */
static void chunk_rule_scalar(const SvoRule *r, int m, Chunk *ch) {
    ch->n_pending = 0;
    for (int k = 0; k < m; k++) {
        float p[3], tg[3], nr[3], d[3], o[3], e[3];
        for (int a = 0; a < 3; a++) { p[a] = ch->p[a][k]; tg[a] = ch->tg[a][k]; nr[a] = ch->nr[a][k]; }
        const int dist = ch->dist[k];
        for (int a = 0; a < 3; a++) d[a] = dist ? tg[a] : tg[a] - p[a];
        const float ln = sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        if (!(ln > 0.0f)) continue;
        float skip0 = r->skip;
        const float nn = sqrtf(nr[0] * nr[0] + nr[1] * nr[1] + nr[2] * nr[2]);
        o[0] = p[0]; o[1] = p[1]; o[2] = p[2];
        if (nn > 0.0f) {
            float mm[3] = {nr[0] / nn, nr[1] / nn, nr[2] / nn};
            float cos_b = (mm[0] * d[0] + mm[1] * d[1] + mm[2] * d[2]) / ln;
            if (cos_b < 0.0f) { mm[0] = -mm[0]; mm[1] = -mm[1]; mm[2] = -mm[2]; cos_b = -cos_b; }
            for (int a = 0; a < 3; a++) o[a] = p[a] + mm[a] * r->offset;
            if (r->slab > 0.0f) skip0 = fmax2(r->skip, fmin2(r->slab / fmax2(cos_b, 1.0e-6f), r->max_skip));
        }
        float skip1 = r->end_skip;
        if (dist) {
            float fc[3] = {o[0] - r->far_center[0], o[1] - r->far_center[1], o[2] - r->far_center[2]};
            const float reach = sqrtf(fc[0] * fc[0] + fc[1] * fc[1] + fc[2] * fc[2]) + r->far;
            for (int a = 0; a < 3; a++) e[a] = o[a] + (d[a] / ln) * reach;
            skip1 = 0.0f;
        } else {
            e[0] = tg[0]; e[1] = tg[1]; e[2] = tg[2];
        }
        for (int a = 0; a < 3; a++) { ch->o[a][k] = o[a]; ch->e[a][k] = e[a]; }
        ch->skip0[k] = skip0;
        ch->skip1[k] = skip1;
        ch->inf[k] = dist;
        ch->pending[ch->n_pending++] = k;
    }
}

/* tree tr for the chunk's pending rays, one at a time: hits written to out, the rest stay pending */
static void chunk_tree_scalar(const SvoScene *s, int tr, Chunk *ch, float *out) {
    int kept = 0;
    for (int j = 0; j < ch->n_pending; j++) {
        const int k = ch->pending[j];
        Walk w;
        float t = -1.0f;
        const float o[3] = {ch->o[0][k], ch->o[1][k], ch->o[2][k]}, e[3] = {ch->e[0][k], ch->e[1][k], ch->e[2][k]};
        if (walk_setup(s, tr, o, e, ch->skip0[k], ch->skip1[k], ch->inf[k], &w)) t = walk_scalar(s, tr, &w);
        if (t >= 0.0f) out[k] = t;
        else ch->pending[kept++] = k;
    }
    ch->n_pending = kept;
}

typedef void (*TreeFn)(const SvoScene *, int, Chunk *, float *);
typedef void (*RuleFn)(const SvoRule *, int, Chunk *);
typedef struct { TreeFn tree; RuleFn rule; } Kernel;

/* lane groups the SIMD walk steps in turn (svoq_simd.h). Measured on the city's 7.35 M rays, one
 * thread, AVX-512: 1, 2, 3, 4 groups 0.97, 1.09, 1.14, 1.00 s: the walk is not latency-bound here
 * (nor are its gathers: emulating them with scalar loads took 1.5-1.7 s), so one group */
#ifndef GROUPS
#define GROUPS 1
#endif

#ifdef SQ_X86
#include "simd_avx2.h"
#include "svoq_simd.h"
#include "simd_undef.h"

#include "simd_avx512.h"
#include "svoq_simd.h"
#endif

/* kernel: 0 the widest this CPU has, 1 scalar, 2 at most AVX2 */
static Kernel pick(int kernel) {
#ifdef SQ_X86
    switch (simd_lanes(kernel)) {
    case 16: return (Kernel){chunk_tree_avx512, chunk_rule_avx512};
    case 8: return (Kernel){chunk_tree_avx2, chunk_rule_avx2};
    }
#endif
    return (Kernel){chunk_tree_scalar, chunk_rule_scalar};
}

/* rays walked at once by ``kernel`` (as pick) on this CPU: 16 (AVX-512), 8 (AVX2) or 1 */
int svo_simd_width(int32_t kernel) { return simd_lanes(kernel); }

/* shadow_segment of kernels/svo/octree.py for queries first .. first + count - 1: out[i] the hit distance in
 * voxels of the first tree hit, -1 when free. origins / targets / normals: (N, 3) float32 or float64
 * (the *_f64 flags), normals may be NULL (no normals); distant: (N,) bool bytes or NULL. kernel: as pick. */
void svo_query(const SvoScene *s, const SvoRule *r, int64_t first, int64_t count, const void *origins, int o_f64,
               const void *targets, int t_f64, const void *normals, int n_f64, const uint8_t *distant, int32_t kernel,
               float *out) {
    Kernel fn = pick(kernel);
    Inputs in = {origins, targets, normals, o_f64, t_f64, n_f64, distant};
    static __thread Chunk ch;
    for (int64_t i0 = first; i0 < first + count; i0 += CHUNK) {
        const int m = (int)(first + count - i0 < CHUNK ? first + count - i0 : CHUNK);
        chunk_load(&in, i0, m, &ch, out);
        fn.rule(r, m, &ch);
        for (int tr = 0; tr < s->n_trees && ch.n_pending; tr++) fn.tree(s, tr, &ch, out + i0);
    }
}

int svo_version(void) { return 2; }

/* an importable module with no Python functions: it exists so that pip builds the library as a
 * package file ctypes can find (usdml/visibility/svo/native.py) */
static struct PyModuleDef svo_module = {PyModuleDef_HEAD_INIT, "_svoq", "SVO traversal (ctypes)", -1, NULL};
PyMODINIT_FUNC PyInit__svoq(void) { return PyModule_Create(&svo_module); }
