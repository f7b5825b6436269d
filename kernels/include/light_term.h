/* The UsdLux rules of direct shading for the compiled kernels (voxelq.c, insmr.c): one light's
 * unshadowed contribution at a point, kernels/voxel/shading.py's light_term, written once here.
 * The table is usdml.visibility.voxel.native's compiled_lights. */

#ifndef USDML_LIGHT_TERM_H
#define USDML_LIGHT_TERM_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
    int32_t n;
    const float *pos, *axis, *cylinder_axis, *cone, *base, *focus_rgb;  /* 3 floats per light */
    const int32_t *flags;
    float inv_m2, min_d2;
    const float *target;    /* 3 floats per light: where its shadow rays end (NULL: pos; a mesh light's triangle:
                             * off its surface, usdml/visibility/emitter_ends.py) */
} VQLights;

enum { DISTANT = 1, ONE_SIDED = 2, SHAPED = 4, FOCUSED = 8, CASTS_SHADOWS = 16, CYLINDER = 32 };

static inline float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* light l at p (shading normal n, geometric ng): kernels/voxel/shading.py's light_term without the
 * shadow ray; returns 0 not facing, 1 lit (rgb set), 2 lit if its shadow ray (to tgt) is free */
static inline int light_term(const VQLights *L, int l, const float *p, const float *n, const float *ng, float rgb[3],
                             float tgt[3]) {
    int flags = L->flags[l], dist = flags & DISTANT;
    const float *lp = L->pos + 3 * (size_t)l, *ax = L->axis + 3 * (size_t)l;
    float dv[3] = {lp[0] - p[0], lp[1] - p[1], lp[2] - p[2]};
    float d2 = dot3(dv, dv);
    if (dist) { dv[0] = -ax[0]; dv[1] = -ax[1]; dv[2] = -ax[2]; d2 = 1.0f; }
    if (d2 <= 0.0f) return 0;
    if (dot3(ng, dv) <= 0.0f) return 0;
    float inv_d = 1.0f / sqrtf(d2 > 1.0e-30f ? d2 : 1.0e-30f);
    float cos_s = dot3(n, dv) * inv_d;
    if (cos_s <= 0.0f) return 0;
    float g = cos_s;
    if (!dist) g = g * L->inv_m2 / (d2 > L->min_d2 ? d2 : L->min_d2);
    if (flags & CYLINDER) {
        float cc = dot3(L->cylinder_axis + 3 * (size_t)l, dv) * inv_d, x = 1.0f - cc * cc;
        g = g * sqrtf(x > 0.0f ? x : 0.0f);
    }
    float f = 0.0f;
    if (flags & (ONE_SIDED | SHAPED | FOCUSED)) {
        float cos_l = -dot3(ax, dv) * inv_d;
        const float *cone = L->cone + 3 * (size_t)l;
        if (flags & ONE_SIDED) g = g * (cos_l > 0.0f ? cos_l : 0.0f);
        if (flags & SHAPED) {
            if (cone[1] <= 0.0f) {
                if (cos_l < cone[0]) g = 0.0f;
            } else {
                float x = (cos_l - cone[0]) / cone[1];
                x = x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x);
                g = g * x * x * (3.0f - 2.0f * x);
            }
        }
        if (flags & FOCUSED) f = powf(cos_l < 0.0f ? 0.0f : (cos_l > 1.0f ? 1.0f : cos_l), cone[2]);
    }
    if (g <= 0.0f) return 0;
    const float *bs = L->base + 3 * (size_t)l, *fc = L->focus_rgb + 3 * (size_t)l;
    for (int k = 0; k < 3; k++) rgb[k] = bs[k] * g + fc[k] * (g * f);
    const float *tp = L->target ? L->target + 3 * (size_t)l : lp;
    for (int k = 0; k < 3; k++) tgt[k] = dist ? dv[k] : tp[k];
    return (flags & CASTS_SHADOWS) ? 2 : 1;
}

#endif
