/* The compiled CPU path of paper 001's per-light maps: kernels/insm.py's receiver tiles, cube and
 * view rasterization and lookups, the same rules in the same arithmetic (float32 view transforms,
 * float64 triangle setup), one light per call. Python calls it from its thread pool through ctypes
 * (usdml/visibility/insm_native.py), which releases the GIL, so the lights of a frame run on every
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

/* Where a lookup of p reads the light's maps: returns the local view (-1: none), x, y, depth. */
static int locate(const float *p, const float *nrm, int cube, const float *light, const Views *v, int first_view,
                  int size, float offset, float bias, float *sx, float *sy, float *zc) {
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
    return local;
}

/* One light: receiver tiles, its views rasterized from the triangles, every point looked up.
 * seconds[0..2] += receivers, rasterization, lookups. Without L: each point's answer into out (1:
 * blocked). With L (light l of the table; shading normals, two scratch arrays of P): Alg. 3 for this
 * light, fused: a point it faces (light_term) counts in facing; casting, it is looked up (queries)
 * and counts in blocked or adds its light to radiance (3 per point); only those points are receivers. */
void insm_light(const float *tris, int64_t n_tris, const int64_t *cl_first, const float *cl_box, int64_t n_clusters,
                const float *origin, const float *rot, const float *proj,
                const int32_t *kind, const float *near, int32_t first_view, int32_t n_views, int32_t cube,
                const float *light, int32_t size, float *depth, int32_t tiles, float *tile_z, float *view_z,
                const float *points, const float *normals, int64_t n_points, float offset, float bias,
                uint8_t *out, double *seconds, const VQLights *L, int32_t l, const float *shading,
                float *scratch_rgb, uint8_t *scratch_code, float *radiance, int32_t *blocked, int32_t *facing,
                int64_t *queries) {
    Views v = {origin, rot, proj, kind, near};
    const int64_t plane = (int64_t)size * size, tplane = (int64_t)tiles * tiles;
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
        int local = locate(points + 3 * i, normals + 3 * i, cube, light, &v, first_view, size, offset, bias, &sx, &sy, &z);
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
                Target tg = {size, tiles, depth + face * plane, tile_z + face * tplane};
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
                    Target tg = {size, tiles, depth + face * plane, tile_z + face * tplane};
                    view_triangle(q0, q1, q2, proj + 4 * view, PERSPECTIVE, near[view], &tg);
                }
            }
        }
    } else {
        for (int vi = 0; vi < n_views; vi++) {
            int view = first_view + vi;
            const float *o = origin + 3 * view, *r = rot + 9 * view;
            Target tg = {size, tiles, depth + vi * plane, tile_z + vi * tplane};
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
                    view_triangle(q[0], q[1], q[2], proj + 4 * view, kind[view], near[view], &tg);
                }
            }
        }
    }
    double t2 = now();
    int64_t asked = 0;
    for (int64_t i = 0; i < n_points; i++) {
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
        float sx, sy, z;
        int hidden = 0;
        int local = locate(points + 3 * i, normals + 3 * i, cube, light, &v, first_view, size, offset, bias, &sx, &sy, &z);
        if (local < 0) {
            if (L) {
                for (int k = 0; k < 3; k++) radiance[3 * i + k] += scratch_rgb[3 * i + k];
            } else {
                out[i] = 0;
            }
            continue;
        }
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
