/* The compiled CPU path of paper 001's per-light maps: kernels/insm/maps.py's receiver tiles, cube and
 * view rasterization and lookups, the same rules in the same arithmetic (float32 view transforms,
 * float64 triangle setup), one light per call. Python calls it from its thread pool through ctypes
 * (usdml/visibility/insm/native.py), which releases the GIL, so the lights of a frame run on every
 * core. Why compiled: Warp's CPU code spent 26 ns per triangle only to reject it against a cube's six
 * faces, and 160 ns to rasterize it (docs/insm.md). */

#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#include "light_term.h"

#define BIG 1.0e30f
#define TILE 16
#define TILE_LEVEL 4   /* TILE = 2^TILE_LEVEL */
#define PERSPECTIVE 0

typedef struct {
    const float *origin;  /* (V, 3) */
    const float *rot;     /* (V, 3, 3) rows right, up, forward */
    const float *proj;    /* (V, 4) ax, bx, ay, by */
    const int32_t *kind;  /* (V,) */
    const float *near;    /* (V,) */
} Views;

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static inline void mat_vec(const float *r, const float *v, float *out) {
    for (int i = 0; i < 3; i++) out[i] = r[3 * i] * v[0] + r[3 * i + 1] * v[1] + r[3 * i + 2] * v[2];
}

/* floor, ceil, min and max without libm calls: the x86-64 baseline has no rounding instruction, and
 * fmin's NaN rules cost a call; the values here are finite (compiled with -ffp-contract=off only) */
static inline int ifloor(double x) {
    int i = (int)x;
    return x < (double)i ? i - 1 : i;
}
static inline int iceil(double x) {
    int i = (int)x;
    return x > (double)i ? i + 1 : i;
}
static inline double dmin(double a, double b) { return a < b ? a : b; }
static inline double dmax(double a, double b) { return a > b ? a : b; }
static inline float fmn(float a, float b) { return a < b ? a : b; }
static inline float fmx(float a, float b) { return a > b ? a : b; }
static inline int imin(int a, int b) { return a < b ? a : b; }
static inline int imax(int a, int b) { return a > b ? a : b; }
static inline int iclamp(int x, int lo, int hi) { return x < lo ? lo : (x > hi ? hi : x); }

static inline double screen(const float *q, float a, float b, int axis, int kind) {
    double x = (double)q[axis];
    if (kind == PERSPECTIVE) x = x / (double)q[2];
    return (double)a * x + (double)b;
}

static inline void span_edge(double a, double g, double *lo, double *hi) {
    if (a > 0.0) {
        double v = -g / a;
        if (v > *lo) *lo = v;
    } else if (a < 0.0) {
        double v = -g / a;
        if (v < *hi) *hi = v;
    } else if (g < 0.0) {
        *hi = *lo - 1.0;
    }
}

typedef struct {
    int size, tiles;
    float *depth;          /* this view's S x S */
    const float *tile_z;   /* this view's tiles x tiles */
    float *hmap;           /* refining: this view's S x S sample spacing of the nearest triangle; else NULL */
    float h;               /* refining: the triangle being rasterized's sample spacing (world) */
} Target;

static void raster_triangle(const float *q0, const float *q1, const float *q2, const float *proj, int kind,
                            const Target *tg) {
    const int size = tg->size, tiles = tg->tiles;
    double x0 = screen(q0, proj[0], proj[1], 0, kind), y0 = screen(q0, proj[2], proj[3], 1, kind);
    double x1 = screen(q1, proj[0], proj[1], 0, kind), y1 = screen(q1, proj[2], proj[3], 1, kind);
    double x2 = screen(q2, proj[0], proj[1], 0, kind), y2 = screen(q2, proj[2], proj[3], 1, kind);
    double w0 = q0[2], w1 = q1[2], w2 = q2[2];
    if (kind == PERSPECTIVE) {
        w0 = 1.0 / w0;
        w1 = 1.0 / w1;
        w2 = 1.0 / w2;
    }
    double area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0);
    if (area == 0.0) return;
    double inv_area = 1.0 / area, fs = (double)size;
    double lo_x = dmax(dmin(dmin(x0, x1), x2), 0.0), hi_x = dmin(dmax(dmax(x0, x1), x2), fs);
    double lo_y = dmax(dmin(dmin(y0, y1), y2), 0.0), hi_y = dmin(dmax(dmax(y0, y1), y2), fs);
    if (lo_x > hi_x || lo_y > hi_y) return;
    int j0 = iceil(lo_y - 0.5), j1 = imin(ifloor(hi_y - 0.5), size - 1);
    float zmin = fmn(fmn(q0[2], q1[2]), q2[2]);
    int bx0 = imax(iceil(lo_x - 0.5), 0) / TILE, bx1 = imax(imin(ifloor(hi_x - 0.5), size - 1), 0) / TILE;
    int wanted = 0;
    for (int ty = imax(j0, 0) / TILE; ty <= imax(j1, 0) / TILE && !wanted; ty++)
        for (int tx = bx0; tx <= bx1; tx++)
            if (tg->tile_z[ty * tiles + tx] > zmin) {
                wanted = 1;
                break;
            }
    if (!wanted) return;
    double a0 = (y1 - y2) * inv_area, b0 = (x2 - x1) * inv_area, c0 = (x1 * y2 - x2 * y1) * inv_area;
    double a1 = (y2 - y0) * inv_area, b1 = (x0 - x2) * inv_area, c1 = (x2 * y0 - x0 * y2) * inv_area;
    double a2 = (y0 - y1) * inv_area, b2 = (x1 - x0) * inv_area, c2 = (x0 * y1 - x1 * y0) * inv_area;
    double dw = a0 * w0 + a1 * w1 + a2 * w2;
    const float sign = kind == PERSPECTIVE ? 1.0f : -1.0f;   /* perspective 1 / z, orthographic -z */
    for (int j = j0; j <= j1; j++) {
        double py = (double)j + 0.5;
        double g0 = b0 * py + c0, g1 = b1 * py + c1, g2 = b2 * py + c2;
        double lo = lo_x, hi = hi_x;
        span_edge(a0, g0, &lo, &hi);
        span_edge(a1, g1, &lo, &hi);
        span_edge(a2, g2, &lo, &hi);
        int i0 = iceil(lo - 0.5), i1 = imin(ifloor(hi - 0.5), size - 1);
        if (i0 > i1) continue;
        double px = (double)i0 + 0.5;
        double w_start = (a0 * px + g0) * w0 + (a1 * px + g1) * w1 + (a2 * px + g2) * w2;
        float *row = tg->depth + (int64_t)j * size;
        const float *tile_row = tg->tile_z + (j / TILE) * tiles;
        for (int tx = i0 / TILE; tx <= i1 / TILE; tx++) {
            if (tile_row[tx] <= zmin) continue;
            int s0 = imax(i0, tx * TILE), s1 = imin(i1, tx * TILE + TILE - 1);
            if (tg->hmap) {
                /* refining: the winning triangle's sample spacing beside its depth (the same depths) */
                float *hrow = tg->hmap + (int64_t)j * size;
                const float h = tg->h;
                for (int i = s0; i <= s1; i++) {   /* selects, not branches: the loop vectorizes */
                    float key = sign * (float)(w_start + dw * (double)(i - i0));
                    float old = row[i], hold = hrow[i];
                    int nearer = key > old;
                    row[i] = nearer ? key : old;
                    hrow[i] = nearer ? h : hold;
                }
                continue;
            }
            /* each texel's value from the span's start (no chain of adds: the loop vectorizes) */
            for (int i = s0; i <= s1; i++) {
                float key = sign * (float)(w_start + dw * (double)(i - i0));   /* nearer is larger */
                row[i] = key > row[i] ? key : row[i];
            }
        }
    }
}

static inline int outside(const float *q, float a, float b, float size, int axis, int kind) {
    float z = kind == PERSPECTIVE ? q[2] : 1.0f;
    float s = a * q[axis] + b * z;
    int bits = 0;
    if (s < 0.0f) bits = 1;
    if (s > size * z) bits |= 2;
    return bits;
}

static inline void clip_point(const float *a, const float *b, float near, float *out) {
    float s = (a[2] - near) / (a[2] - b[2]);
    out[0] = a[0] + (b[0] - a[0]) * s;
    out[1] = a[1] + (b[1] - a[1]) * s;
    out[2] = near;
}

static void view_triangle(const float *q0, const float *q1, const float *q2, const float *proj, int kind,
                          float near, const Target *tg) {
    float fs = (float)tg->size;
    int cx = outside(q0, proj[0], proj[1], fs, 0, kind) & outside(q1, proj[0], proj[1], fs, 0, kind) &
             outside(q2, proj[0], proj[1], fs, 0, kind);
    int cy = outside(q0, proj[2], proj[3], fs, 1, kind) & outside(q1, proj[2], proj[3], fs, 1, kind) &
             outside(q2, proj[2], proj[3], fs, 1, kind);
    if (cx || cy) return;
    if (kind != PERSPECTIVE) {
        raster_triangle(q0, q1, q2, proj, kind, tg);
        return;
    }
    const float *m[3] = {q0, q1, q2};
    int front = 0, ahead = 0;
    for (int k = 0; k < 3; k++)
        if (m[k][2] >= near) {
            front++;
            ahead |= 1 << k;
        }
    if (front == 3) {
        raster_triangle(q0, q1, q2, proj, kind, tg);
    } else if (front == 1) {
        int k = ahead == 2 ? 1 : (ahead == 4 ? 2 : 0);
        const float *a = m[k], *b = m[(k + 1) % 3], *c = m[(k + 2) % 3];
        float ab[3], ac[3];
        clip_point(a, b, near, ab);
        clip_point(a, c, near, ac);
        raster_triangle(a, ab, ac, proj, kind, tg);
    } else if (front == 2) {
        int k = ahead == 5 ? 1 : (ahead == 3 ? 2 : 0);   /* the corner behind */
        const float *c = m[k], *a = m[(k + 1) % 3], *b = m[(k + 2) % 3];
        float bc[3], ac[3];
        clip_point(b, c, near, bc);
        clip_point(a, c, near, ac);
        raster_triangle(a, b, bc, proj, kind, tg);
        raster_triangle(a, bc, ac, proj, kind, tg);
    }
}

static inline float nearest_abs(float lo, float hi) {
    if (lo <= 0.0f && hi >= 0.0f) return 0.0f;
    return fmn(fabsf(lo), fabsf(hi));
}

/* Whether any triangle inside a cluster's box (corners rel[8][3], relative to the view's origin) can
 * change an answer of the view: the box's pixels hold a receiver tile whose farthest compared depth
 * is beyond the box's nearest corner (conservative: a box reaching behind the near plane, or over
 * more than 64 tiles, is taken). */
static int cluster_wanted(const float rel[8][3], const float *r, const float *proj, int kind, float near,
                          const Target *tg) {
    float x0 = 1e30f, x1 = -1e30f, y0 = 1e30f, y1 = -1e30f, zmin = 1e30f;
    for (int c = 0; c < 8; c++) {
        float q[3];
        mat_vec(r, rel[c], q);
        if (kind == PERSPECTIVE && q[2] < near) return 1;
        float x = q[0], y = q[1];
        if (kind == PERSPECTIVE) {
            x /= q[2];
            y /= q[2];
        }
        x = proj[0] * x + proj[1];
        y = proj[2] * y + proj[3];
        x0 = fmn(x0, x); x1 = fmx(x1, x);
        y0 = fmn(y0, y); y1 = fmx(y1, y);
        zmin = fmn(zmin, q[2]);
    }
    float fs = (float)tg->size;
    if (x1 < 0.0f || y1 < 0.0f || x0 > fs || y0 > fs) return 0;
    int i0 = ifloor(fmx(x0, 0.0f)) - 1, i1 = ifloor(fmn(x1, fs)) + 1;
    int j0 = ifloor(fmx(y0, 0.0f)) - 1, j1 = ifloor(fmn(y1, fs)) + 1;
    int tx0 = iclamp(i0, 0, tg->size - 1) / TILE, tx1 = iclamp(i1, 0, tg->size - 1) / TILE;
    int ty0 = iclamp(j0, 0, tg->size - 1) / TILE, ty1 = iclamp(j1, 0, tg->size - 1) / TILE;
    if ((tx1 - tx0 + 1) * (ty1 - ty0 + 1) > 64) return 1;
    for (int ty = ty0; ty <= ty1; ty++)
        for (int tx = tx0; tx <= tx1; tx++)
            if (tg->tile_z[ty * tg->tiles + tx] > zmin) return 1;
    return 0;
}

static void box_corners(const float *lo, const float *hi, const float *o, float rel[8][3]) {
    for (int c = 0; c < 8; c++) {
        rel[c][0] = ((c & 1) ? hi[0] : lo[0]) - o[0];
        rel[c][1] = ((c & 2) ? hi[1] : lo[1]) - o[1];
        rel[c][2] = ((c & 4) ? hi[2] : lo[2]) - o[2];
    }
}

/* Which of a cube's faces a box (lo, hi relative to the light) may fall in and matter to: the six
 * faces' tests of insm_light's triangles, on the box. */
static inline int face_passes(const float *lo, const float *hi, int face, const float *view_z) {
    int axis = face / 2, u = (axis + 1) % 3, w = (axis + 2) % 3;
    float reach = face % 2 ? -lo[axis] : hi[axis];
    float need = fmx(nearest_abs(lo[u], hi[u]), nearest_abs(lo[w], hi[w]));
    if (reach <= 0.0f || reach < need) return 0;
    float nearest = face % 2 ? -hi[axis] : lo[axis];
    return nearest < view_z[face];
}

/* Where a lookup of p reads the light's maps: returns the local view (-1: none), x, y, depth compared; with
 * texel_out the texel's world size there, with moved the point as compared (offset along its normal), world. */
static int locate(const float *p, const float *nrm, int cube, const float *light, const Views *v, int first_view,
                  int size, float offset, float bias, float *sx, float *sy, float *zc, float *texel_out,
                  float *moved) {
    int local = 0;
    if (cube) {
        float d[3] = {p[0] - light[0], p[1] - light[1], p[2] - light[2]};
        float ax = fabsf(d[0]), ay = fabsf(d[1]), az = fabsf(d[2]);
        int face;
        if (ax >= ay && ax >= az) face = d[0] < 0.0f ? 1 : 0;
        else if (ay >= az) face = d[1] < 0.0f ? 3 : 2;
        else face = d[2] < 0.0f ? 5 : 4;
        local = face;
    }
    int view = first_view + local;
    const float *r = v->rot + 9 * view, *proj = v->proj + 4 * view, *o = v->origin + 3 * view;
    int kind = v->kind[view];
    float rel[3] = {p[0] - o[0], p[1] - o[1], p[2] - o[2]}, q[3], qn[3];
    mat_vec(r, rel, q);
    float toward[3] = {0.0f, 0.0f, -1.0f};
    if (kind == PERSPECTIVE) {
        toward[0] = -q[0];
        toward[1] = -q[1];
        toward[2] = -q[2];
    }
    mat_vec(r, nrm, qn);
    if (qn[0] * toward[0] + qn[1] * toward[1] + qn[2] * toward[2] < 0.0f) {
        qn[0] = -qn[0];
        qn[1] = -qn[1];
        qn[2] = -qn[2];
    }
    float texel = 1.0f / proj[0];
    if (kind == PERSPECTIVE) texel = q[2] / proj[0];
    float step = offset * texel;
    for (int c = 0; c < 3; c++) q[c] = q[c] + qn[c] * step;
    if (moved)   /* the point as it is compared, in world space: o + R^T q */
        for (int c = 0; c < 3; c++) moved[c] = o[c] + r[c] * q[0] + r[3 + c] * q[1] + r[6 + c] * q[2];
    float x = proj[0] * q[0] + proj[1], y = proj[2] * q[1] + proj[3];
    if (kind == PERSPECTIVE) {
        if (q[2] <= v->near[view]) return -1;
        x = proj[0] * q[0] / q[2] + proj[1];
        y = proj[2] * q[1] / q[2] + proj[3];
    }
    float fs = (float)size;
    if (x < 0.0f || y < 0.0f || x > fs || y > fs) return -1;
    *sx = x;
    *sy = y;
    *zc = q[2] - bias * texel;
    if (texel_out) *texel_out = texel;
    return local;
}

/* ---- refinement (REFINE): which answers may be wrong, by the reconstruction's own geometry ----
 *
 * The maps are rasterized from triangles reconstructed from depth images whose samples lie h apart (a
 * triangle's h: its sample spacing, world units, kept per texel as the map is rasterized), so an
 * occluder's outline in a map can be off by about h. A lookup is uncertain where an outline lies between
 * its sides within c h of its ray at the outline's depth: a *silhouette texel* (nearer than a neighbour by
 * more than `jump` texels of depth, against the plane through the texel and the one opposite, so that a
 * plane at any slope has none) in front of the lookup's compared depth, whose neighbour is not in front of
 * it by more than `jump` texels, within c h a / z texels (perspective; h a orthographic) of the lookup,
 * plus r0 texels of the lookup's own footprint. Each answer gets the first level whose c reaches it
 * (least_level: a search of a per-view pyramid of the silhouettes' nearness, far sides and reach), on a
 * cube map the four faces beside its own searched too (the point projected into each: the seam), or
 * whose depth band (|compared depth - a 2 x 2 texel's depth| in texels under band[k]) holds it. A lookup
 * outside every view is uncertain at every level.
 *
 * Texels of tiles with no receiver were never rasterized: a neighbour there is no evidence, and the
 * pyramid's blocks there are empty. An empty texel of a receiver tile is at least as far as that tile's
 * farthest compared depth (what the tile test culled lies beyond it). */

typedef struct {
    int levels;
    float jump, r0;
    const float *c;      /* (levels,) non-decreasing */
    const float *band;   /* (levels,) non-decreasing */
} Rule;

/* levels of the pyramid above the S x S texels: ceil(S / 2^L) blocks a side, L = 1 .. until one */
static int pyramid_levels(int size, int64_t *offsets) {
    int n = 0;
    int64_t at = 0;
    for (int side = size; side > 1;) {
        side = (side + 1) / 2;
        if (offsets) offsets[n] = at;
        at += (int64_t)side * side;
        n++;
    }
    if (offsets) offsets[n] = at;
    return n;
}

/* depth of a nearness (perspective 1 / z, orthographic -z) */
static inline float depth_of(float m, int persp) { return persp ? 1.0f / m : -m; }

/* One view's silhouettes from its nearness map m and spacing map h (its receiver tiles' farthest compared
 * depths tz, the view's `farthest`): per texel of a receiver tile the triple
 * leaf[3t ..] = (its nearness, the nearness of its farthest stepped-to neighbour (-BIG: an empty one), its
 * reach h a / z (perspective; h a orthographic) in texels per unit of c) where it is a silhouette, else
 * (-BIG, BIG, 0); then per block of the pyramid (pyr, offsets off in blocks) the triple of the silhouettes'
 * greatest nearness, least far side and greatest reach. Each triple's three values in one place: a search
 * reads a block's at once. */
static void silhouettes(const float *m, const float *h, float *leaf, const float *tz, int size, int tiles, float a,
                        int persp, float jump, float farthest, float *pyr) {
    const float empty = -0.5f * BIG;
    /* a texel no nearer than the view's farthest compared depth is in front of no lookup: never a silhouette
     * that matters */
    const float front = farthest > empty ? (persp ? 1.0f / farthest : -farthest) : BIG;
    for (int j = 0; j < size; j++) {
        const float *tz_row = tz + (j / TILE) * tiles;
        for (int i = 0; i < size; i++) {
            if (!(tz_row[i / TILE] > empty)) {       /* a tile without receivers: nothing was rasterized */
                i = (i / TILE) * TILE + TILE - 1;
                continue;
            }
            int64_t t = (int64_t)j * size + i;
            float mt = m[t], *out = leaf + 3 * t;
            out[0] = -BIG;
            out[1] = BIG;
            out[2] = 0.0f;
            if (!(mt > empty) || !(mt > front)) continue;
            int sil = 0;
            float fs = BIG;
            for (int d = 0; d < 4; d++) {
                int di = d == 0 ? 1 : (d == 1 ? -1 : 0), dj = d == 2 ? 1 : (d == 3 ? -1 : 0);
                int ni = i + di, nj = j + dj;
                if (ni < 0 || nj < 0 || ni >= size || nj >= size) continue;
                float tzn = tz[(nj / TILE) * tiles + ni / TILE];
                if (!(tzn > empty)) continue;                 /* a tile without receivers: unknown */
                float mn = m[(int64_t)nj * size + ni];
                int bi = i - di, bj = j - dj;
                float mb = mt;
                if (bi >= 0 && bj >= 0 && bi < size && bj < size && m[(int64_t)bj * size + bi] > empty)
                    mb = m[(int64_t)bj * size + bi];
                float pred = 2.0f * mt - mb;                  /* the plane through t - d and t, at t + d */
                int step;
                if (persp) {
                    if (!(pred > 0.0f)) continue;             /* the plane runs off to infinity: no step */
                    /* (1 / mn - 1 / pred) texels of depth at t (a texel: z / a) over jump, without a division */
                    step = mn > empty ? (pred - mn) * a * mt > jump * mn * pred
                                      : (tzn * pred - 1.0f) * a * mt > jump * pred;
                } else {
                    step = ((mn > empty ? -mn : tzn) + pred) * a > jump;
                }
                if (step) {
                    sil = 1;
                    fs = fmn(fs, mn);         /* an empty neighbour: -BIG, behind anything */
                }
            }
            if (sil) {
                out[0] = mt;
                out[1] = fs;
                out[2] = h[t] * (persp ? a * mt : a);
            }
        }
    }
    /* level 1 from the texels, each next level from the one below; below level TILE_LEVEL (a block a
     * receiver tile) the blocks of tiles without receivers are skipped, never searched (their tile's block
     * is empty) */
    int64_t off[40];
    int levels = pyramid_levels(size, off);
    int below = size;
    for (int l = 0; l < levels; l++) {
        int side = (below + 1) / 2, level = l + 1;
        float *here = pyr + 3 * off[l];
        const float *under = l ? pyr + 3 * off[l - 1] : leaf;
        for (int by = 0; by < side; by++) {
            for (int bx = 0; bx < side; bx++) {
                float ev = -BIG, fv = BIG, pv = 0.0f, *out = here + 3 * ((int64_t)by * side + bx);
                if (level <= TILE_LEVEL) {
                    int sh = TILE_LEVEL - level;
                    if (!(tz[(by >> sh) * tiles + (bx >> sh)] > empty)) {
                        if (level == TILE_LEVEL || level == levels) {
                            out[0] = -BIG;
                            out[1] = BIG;
                            out[2] = 0.0f;
                        }
                        continue;
                    }
                }
                for (int k = 0; k < 4; k++) {
                    int ci = 2 * bx + (k & 1), cj = 2 * by + (k >> 1);
                    if (ci >= below || cj >= below) continue;
                    const float *c = under + 3 * ((int64_t)cj * below + ci);
                    ev = fmx(ev, c[0]);
                    fv = fmn(fv, c[1]);
                    pv = fmx(pv, c[2]);
                }
                out[0] = ev;
                out[1] = fv;
                out[2] = pv;
            }
        }
        below = side;
    }
}

/* Chebyshev distance from (x, y) to the texel centres of block (bx, by) of level l (2^l texels a side) */
static inline float block_distance(float x, float y, int bx, int by, int level, int size) {
    int w = 1 << level;
    float lo_x = (float)(bx * w) + 0.5f, hi_x = (float)(imin((bx + 1) * w, size) - 1) + 0.5f;
    float lo_y = (float)(by * w) + 0.5f, hi_y = (float)(imin((by + 1) * w, size) - 1) + 0.5f;
    float dx = fmx(0.0f, fmx(lo_x - x, x - hi_x)), dy = fmx(0.0f, fmx(lo_y - y, y - hi_y));
    return fmx(dx, dy);
}

typedef struct {
    int level, bx, by;
    float bound;    /* the least c any texel of the block could need */
} Block;

/* Whether block (bx, by) of level l (0: a texel) may hold a silhouette between the lookup's sides (its near
 * side in front of nearness `key`, its far side not in front of `key_far`) reaching (x, y) within `limit`:
 * its bound (the least c it could need, exact for a texel), or -1. */
static inline float block_bound(const float *leaf, const float *pyr, int size, const int64_t *off, const int *sides,
                                int l, int bx, int by, float x, float y, float key, float key_far, float r0,
                                float limit) {
    const float *b = l ? pyr + 3 * (off[l - 1] + (int64_t)by * sides[l] + bx) : leaf + 3 * ((int64_t)by * size + bx);
    float e = b[0], f = b[1], p = b[2];
    if (!(e > key) || !(f < key_far) || !(p > 0.0f)) return -1.0f;
    float d = fmx(0.0f, block_distance(x, y, bx, by, l, size) - r0);
    if (d > limit * p) return -1.0f;
    return d / p;
}

/* The first level (0-based; r->levels: none; at most `found`) whose c lets a silhouette between the
 * lookup's sides reach (x, y): its near side in front of the compared nearness `key`, its far side not in
 * front of `key_far` (the compared depth less `jump` texels: the receiver's own surface beyond an outline
 * may lie a little in front of it), so that, moved, the outline would change the answer. A silhouette
 * reaches at c = max(0, distance - r0) / reach. A search of the pyramid (levels' offsets off, sides, top),
 * started at the level whose blocks are as wide as the farthest reach, the most promising block first,
 * pruning blocks that cannot beat the level found so far. */
static int least_level(const float *leaf, const float *pyr, int size, const int64_t *off, const int *sides, int top,
                       float x, float y, float key, float key_far, const Rule *r, int found) {
    if (found <= 0) return found;
    float limit = r->c[found - 1];         /* a block must be reached within this to matter */
    Block stack[4 * 40];
    int n = 0;
    /* start at the level whose blocks are as wide as the farthest reach in the view: the blocks around (x, y) */
    float far_reach;
    if (top) {
        const float *b = pyr + 3 * off[top - 1];
        if (!(b[0] > key) || !(b[1] < key_far)) return found;
        far_reach = limit * b[2] + r->r0;
    } else {
        far_reach = (float)size;
    }
    /* no lower than a receiver tile's level: below it the blocks of tiles without receivers are not made */
    int l0 = top < TILE_LEVEL ? top : TILE_LEVEL;
    while (l0 < top && (float)(1 << l0) < far_reach) l0++;
    int w = 1 << l0, side = sides[l0];
    int bx0 = iclamp(ifloor((x - far_reach) / (float)w), 0, side - 1), bx1 = iclamp(ifloor((x + far_reach) / (float)w), 0, side - 1);
    int by0 = iclamp(ifloor((y - far_reach) / (float)w), 0, side - 1), by1 = iclamp(ifloor((y + far_reach) / (float)w), 0, side - 1);
    for (int by = by0; by <= by1; by++)
        for (int bx = bx0; bx <= bx1; bx++) {
            float bound = block_bound(leaf, pyr, size, off, sides, l0, bx, by, x, y, key, key_far, r->r0, limit);
            if (bound < 0.0f) continue;
            if (l0 == 0) {
                int lv = 0;
                while (lv < found && bound > r->c[lv]) lv++;
                found = lv;
                limit = lv ? r->c[lv - 1] : -1.0f;
            } else if (n < (int)(sizeof stack / sizeof stack[0])) {
                stack[n++] = (Block){l0, bx, by, bound};
            }
        }
    while (n && found > 0) {
        Block b = stack[--n];
        if (b.bound > limit) continue;
        int l = b.level - 1;
        Block kids[4];
        int count = 0;
        for (int k = 0; k < 4; k++) {
            int ci = 2 * b.bx + (k & 1), cj = 2 * b.by + (k >> 1);
            if (ci >= sides[l] || cj >= sides[l]) continue;
            float bound = block_bound(leaf, pyr, size, off, sides, l, ci, cj, x, y, key, key_far, r->r0, limit);
            if (bound < 0.0f) continue;
            if (l == 0) {               /* a texel: its bound is its need */
                int lv = 0;
                while (lv < found && bound > r->c[lv]) lv++;
                found = lv;
                limit = lv ? r->c[lv - 1] : -1.0f;
                continue;
            }
            kids[count++] = (Block){l, ci, cj, bound};
        }
        /* the most promising (least bound) on top */
        for (int a = 0; a < count; a++)
            for (int c = a + 1; c < count; c++)
                if (kids[c].bound > kids[a].bound) {
                    Block t = kids[a];
                    kids[a] = kids[c];
                    kids[c] = t;
                }
        for (int k = 0; k < count && n < (int)(sizeof stack / sizeof stack[0]); k++) stack[n++] = kids[k];
    }
    return found;
}

/* the grade of an answer: the first level (1 ..) whose c reaches it (`reached`, 0-based, from
 * least_level) or whose band holds its band distance `band` (texels), 0 where none does */
static inline uint8_t grade_of(const Rule *r, int reached, float band) {
    for (int k = 0; k < r->levels; k++)
        if (k >= reached || band < r->band[k]) return (uint8_t)(k + 1);
    return 0;
}

/* One light: receiver tiles, its views rasterized from the triangles, every point looked up.
 * seconds[0..2] += receivers, rasterization, lookups. Without L: each point's answer into out (1:
 * blocked). With L (light l of the table; shading normals, two scratch arrays of P): Alg. 3 for this
 * light, fused: a point it faces (light_term) counts in facing; casting, it is looked up (queries)
 * and counts in blocked or adds its light to radiance (3 per point); only those points are receivers.
 * With grade (refining; tri_h the triangles' sample spacings, scratch the views' maps and pyramids, rule =
 * levels, jump, r0, c[levels], band[levels]): without L, each answer's grade too (the refinement's rule
 * above), the answers the same; with L, the looked-up points whose grade is 1 .. hand_level are handed back:
 * counted in facing and queries but neither blocked nor lit, their grade in grade (0 for every other point),
 * for the caller to answer exactly. */
void insm_light(const float *tris, int64_t n_tris, const int64_t *cl_first, const float *cl_box, int64_t n_clusters,
                const float *origin, const float *rot, const float *proj,
                const int32_t *kind, const float *near, int32_t first_view, int32_t n_views, int32_t cube,
                const float *light, int32_t size, float *depth, int32_t tiles, float *tile_z, float *view_z,
                const float *points, const float *normals, int64_t n_points, float offset, float bias,
                uint8_t *out, double *seconds, const VQLights *L, int32_t l, const float *shading,
                float *scratch_rgb, uint8_t *scratch_code, float *radiance, int32_t *blocked, int32_t *facing,
                int64_t *queries, const float *tri_h, float *scratch, const float *rule, uint8_t *grade,
                int32_t hand_level) {
    Views v = {origin, rot, proj, kind, near};
    const int64_t plane = (int64_t)size * size, tplane = (int64_t)tiles * tiles;
    if ((!L && !out) || !tri_h || !scratch || !rule) grade = NULL;
    /* refining: scratch holds the views' spacing maps (S^2 each), their silhouettes' triples (3 S^2 each),
     * then their pyramids' triples (3 pyr each) */
    int64_t pyr_off[40];
    int pyr_side[40], pyr_top = pyramid_levels(size, pyr_off);
    const int64_t pyr = pyr_off[pyr_top];
    pyr_side[0] = size;
    for (int k = 1; k <= pyr_top; k++) pyr_side[k] = (pyr_side[k - 1] + 1) / 2;
    float *hmap = grade ? scratch : NULL, *leaves = grade ? scratch + n_views * plane : NULL;
    float *pyrs = grade ? scratch + 4 * n_views * plane : NULL;
    float *hm = hmap;
    double t0 = now();
    for (int64_t i = 0; i < n_views * tplane; i++) tile_z[i] = -BIG;
    for (int i = 0; i < n_views; i++) view_z[i] = -BIG;
    for (int64_t i = 0; i < n_points; i++) {
        if (L) {
            float tg[3];
            int code = light_term(L, l, points + 3 * i, shading + 3 * i, normals + 3 * i, scratch_rgb + 3 * i, tg);
            scratch_code[i] = (uint8_t)code;
            if (code != 2) continue;
        }
        float sx, sy, z;
        int local = locate(points + 3 * i, normals + 3 * i, cube, light, &v, first_view, size, offset, bias, &sx, &sy, &z, NULL, NULL);
        if (local < 0) continue;
        if (z > view_z[local]) view_z[local] = z;
        int i0 = ifloor(sx - 0.5f), j0 = ifloor(sy - 0.5f);
        for (int dj = 0; dj < 2; dj++) {
            int cj = iclamp(j0 + dj, 0, size - 1) / TILE;
            for (int di = 0; di < 2; di++) {
                int ci = iclamp(i0 + di, 0, size - 1) / TILE;
                float *t = tile_z + local * tplane + cj * tiles + ci;
                if (z > *t) *t = z;
            }
        }
    }
    double t1 = now();
    for (int64_t i = 0; i < n_views * plane; i++) depth[i] = -BIG;
    if (cube) {
        const float zero[3] = {0.0f, 0.0f, 0.0f};
        for (int64_t ci = 0; ci < n_clusters; ci++) {
            const float *box = cl_box + 6 * ci;
            float blo[3], bhi[3], rel[8][3];
            for (int c = 0; c < 3; c++) {
                blo[c] = box[c] - light[c];
                bhi[c] = box[3 + c] - light[c];
            }
            box_corners(blo, bhi, zero, rel);
            int faces = 0;
            for (int face = 0; face < 6; face++) {
                if (!face_passes(blo, bhi, face, view_z)) continue;
                int view = first_view + face;
                Target tg = {size, tiles, depth + face * plane, tile_z + face * tplane, NULL, 0.0f};
                if (cluster_wanted(rel, rot + 9 * view, proj + 4 * view, PERSPECTIVE, near[view], &tg)) faces |= 1 << face;
            }
            if (!faces) continue;
            for (int64_t t = cl_first[ci]; t < cl_first[ci + 1]; t++) {
                const float *a = tris + 9 * t;
                float d[3][3];
                for (int k = 0; k < 3; k++)
                    for (int c = 0; c < 3; c++) d[k][c] = a[3 * k + c] - light[c];
                float lo[3], hi[3];
                for (int c = 0; c < 3; c++) {
                    lo[c] = fmn(fmn(d[0][c], d[1][c]), d[2][c]);
                    hi[c] = fmx(fmx(d[0][c], d[1][c]), d[2][c]);
                }
                for (int face = 0; face < 6; face++) {
                    if (!(faces & (1 << face)) || !face_passes(lo, hi, face, view_z)) continue;
                    int view = first_view + face;
                    float q0[3], q1[3], q2[3];
                    mat_vec(rot + 9 * view, d[0], q0);
                    mat_vec(rot + 9 * view, d[1], q1);
                    mat_vec(rot + 9 * view, d[2], q2);
                    Target tg = {size, tiles, depth + face * plane, tile_z + face * tplane,
                                 hm ? hm + face * plane : NULL, hm ? tri_h[t] : 0.0f};
                    view_triangle(q0, q1, q2, proj + 4 * view, PERSPECTIVE, near[view], &tg);
                }
            }
        }
    } else {
        for (int vi = 0; vi < n_views; vi++) {
            int view = first_view + vi;
            const float *o = origin + 3 * view, *r = rot + 9 * view;
            Target tg = {size, tiles, depth + vi * plane, tile_z + vi * tplane, hm ? hm + vi * plane : NULL, 0.0f};
            for (int64_t ci = 0; ci < n_clusters; ci++) {
                float rel[8][3];
                box_corners(cl_box + 6 * ci, cl_box + 6 * ci + 3, o, rel);
                if (!cluster_wanted(rel, r, proj + 4 * view, kind[view], near[view], &tg)) continue;
                for (int64_t t = cl_first[ci]; t < cl_first[ci + 1]; t++) {
                    const float *a = tris + 9 * t;
                    float rl[3], q[3][3];
                    for (int k = 0; k < 3; k++) {
                        for (int c = 0; c < 3; c++) rl[c] = a[3 * k + c] - o[c];
                        mat_vec(r, rl, q[k]);
                    }
                    if (fmn(fmn(q[0][2], q[1][2]), q[2][2]) >= view_z[vi]) continue;
                    if (hm) tg.h = tri_h[t];
                    view_triangle(q[0], q[1], q[2], proj + 4 * view, kind[view], near[view], &tg);
                }
            }
        }
    }
    Rule rl = {0, 0.0f, 0.0f, NULL, NULL};
    float top_e[6] = {-BIG, -BIG, -BIG, -BIG, -BIG, -BIG}, top_f[6] = {BIG, BIG, BIG, BIG, BIG, BIG};
    float top_p[6] = {0, 0, 0, 0, 0, 0};
    if (grade) {
        rl.levels = (int)rule[0];
        rl.jump = rule[1];
        rl.r0 = rule[2];
        rl.c = rule + 3;
        rl.band = rule + 3 + rl.levels;
        for (int vi = 0; vi < n_views; vi++) {
            int view = first_view + vi;
            silhouettes(depth + vi * plane, hmap + vi * plane, leaves + 3 * vi * plane, tile_z + vi * tplane, size,
                        tiles, proj[4 * view], kind[view] == PERSPECTIVE, rl.jump, view_z[vi], pyrs + 3 * vi * pyr);
            if (vi < 6 && pyr_top) {
                const float *b = pyrs + 3 * (vi * pyr + pyr_off[pyr_top - 1]);
                top_e[vi] = b[0];
                top_f[vi] = b[1];
                top_p[vi] = b[2];
            }
        }
    }
    double t2 = now();
    int64_t asked = 0;
    for (int64_t i = 0; i < n_points; i++) {
        if (L && grade) grade[i] = 0;
        if (L) {
            int code = scratch_code[i];
            if (!code) continue;
            facing[i]++;
            if (code == 1) {
                for (int k = 0; k < 3; k++) radiance[3 * i + k] += scratch_rgb[3 * i + k];
                continue;
            }
            asked++;
        }
        float sx, sy, z, texel, moved[3];
        int hidden = 0;
        int local = locate(points + 3 * i, normals + 3 * i, cube, light, &v, first_view, size, offset, bias, &sx, &sy, &z,
                           &texel, grade ? moved : NULL);
        if (local < 0) {
            if (grade) grade[i] = 1;         /* outside every view: uncertain at every level */
            if (L && grade) continue;        /* handed back */
            if (L) {
                for (int k = 0; k < 3; k++) radiance[3 * i + k] += scratch_rgb[3 * i + k];
            } else {
                out[i] = 0;
            }
            continue;
        }
        float zc = z;
        float fx = sx - 0.5f, fy = sy - 0.5f;
        int i0 = ifloor(fx), j0 = ifloor(fy);
        float tx = fx - (float)i0, ty = fy - (float)j0;
        z = kind[first_view + local] == PERSPECTIVE ? 1.0f / z : -z;
        const float *m = depth + local * plane;
        int ia = iclamp(i0, 0, size - 1), ib = iclamp(i0 + 1, 0, size - 1);
        int ja = iclamp(j0, 0, size - 1), jb = iclamp(j0 + 1, 0, size - 1);
        float f = (1.0f - tx) * (1.0f - ty) * (m[ja * size + ia] > z ? 1.0f : 0.0f) +
                  tx * (1.0f - ty) * (m[ja * size + ib] > z ? 1.0f : 0.0f) +
                  (1.0f - tx) * ty * (m[jb * size + ia] > z ? 1.0f : 0.0f) +
                  tx * ty * (m[jb * size + ib] > z ? 1.0f : 0.0f);
        hidden = f > 0.5f;
        if (grade) {
            int persp = kind[first_view + local] == PERSPECTIVE;
            /* the depth band: each texel's occluder depth against the compared one, in texels */
            float band = BIG;
            const int ix[4] = {ia, ib, ia, ib}, jx[4] = {ja, ja, jb, jb};
            for (int k = 0; k < 4; k++) {
                float mk = m[jx[k] * size + ix[k]];
                if (mk > -0.5f * BIG) band = fmn(band, fabsf(zc - depth_of(mk, persp)) / texel);
            }
            int reached = least_level(leaves + 3 * local * plane, pyrs + 3 * local * pyr, size, pyr_off, pyr_side,
                                      pyr_top, sx, sy, z, persp ? 1.0f / (zc - rl.jump * texel) : -(zc - rl.jump * texel), &rl,
                                      rl.levels);
            if (cube && reached > 0) {
                /* the seam: the four neighbouring faces' silhouettes, the point projected into each (beyond its
                 * edge; the faces' texels meet there) and its compared depth along the same ray */
                float zq = zc + bias * texel;
                for (int f2 = 0; f2 < 6 && reached > 0; f2++) {
                    if (f2 == local || f2 == (local ^ 1) || !(top_p[f2] > 0.0f)) continue;
                    int view = first_view + f2;
                    const float *r2 = rot + 9 * view;
                    float rel[3] = {moved[0] - light[0], moved[1] - light[1], moved[2] - light[2]}, q2[3];
                    mat_vec(r2, rel, q2);
                    if (!(q2[2] > near[view])) continue;
                    float key2 = 1.0f / (q2[2] * (zc / zq)), key2_far = 1.0f / (q2[2] * ((zc - rl.jump * texel) / zq));
                    if (!(top_e[f2] > key2) || !(top_f[f2] < key2_far)) continue;
                    const float *pj = proj + 4 * view;
                    float x2 = pj[0] * q2[0] / q2[2] + pj[1], y2 = pj[2] * q2[1] / q2[2] + pj[3];
                    float fs = (float)size;
                    float out_x = fmx(0.0f, fmx(0.5f - x2, x2 - (fs - 0.5f)));
                    float out_y = fmx(0.0f, fmx(0.5f - y2, y2 - (fs - 0.5f)));
                    if (fmx(out_x, out_y) - rl.r0 > rl.c[reached - 1] * top_p[f2]) continue;
                    reached = least_level(leaves + 3 * f2 * plane, pyrs + 3 * f2 * pyr, size, pyr_off, pyr_side,
                                          pyr_top, x2, y2, key2, key2_far, &rl, reached);
                }
            }
            grade[i] = grade_of(&rl, reached, band);
            if (L) {
                if (grade[i] && grade[i] <= hand_level) continue;    /* handed back, its grade kept */
                grade[i] = 0;
            }
        }
        if (!L) {
            out[i] = (uint8_t)hidden;
        } else if (hidden) {
            blocked[i]++;
        } else {
            for (int k = 0; k < 3; k++) radiance[3 * i + k] += scratch_rgb[3 * i + k];
        }
    }
    if (queries) *queries += asked;
    double t3 = now();
    seconds[0] += t1 - t0;
    seconds[1] += t2 - t1;
    seconds[2] += t3 - t2;
}

/* an importable module, so that pip builds and installs it (its functions are called through ctypes) */
static struct PyModuleDef insm_module = {PyModuleDef_HEAD_INIT, "_insmr", "INSM per-light maps (ctypes)", -1, NULL};
PyMODINIT_FUNC PyInit__insmr(void) { return PyModule_Create(&insm_module); }
