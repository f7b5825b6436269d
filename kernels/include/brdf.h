/* The UsdPreviewSurface BRDF of one light at a point for the compiled kernels: kernels/brdf's
 * brdf_terms, written once in brdf_lobes.h (that module's docstring defines the row layout and every term), here
 * one point at a time. Include it before any SIMD vector API (its scalar API is defined and undefined here). */

#ifndef USDML_BRDF_H
#define USDML_BRDF_H

#include <math.h>

enum { BRDF_WIDTH = 16, BRDF_EYE = 0, BRDF_F0 = 3, BRDF_F90 = 6, BRDF_ALPHA = 9, BRDF_CLEARCOAT = 10,
       BRDF_CLEARCOAT_ALPHA = 11, BRDF_CLEARCOAT_F0 = 12, BRDF_OCCLUSION = 13 };

/* brdf_lobes.h over plain floats */
#define V float
#define M int
#define SUFFIX(f) f##_scalar
#define TARGET
#define SET(x) (x)
#define ADD(a, b) ((a) + (b))
#define SUB(a, b) ((a) - (b))
#define MUL(a, b) ((a) * (b))
#define DIV(a, b) ((a) / (b))
#define SQRT sqrtf
#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define GT(a, b) ((a) > (b))
#define SEL(m, a, b) ((m) ? (a) : (b))
#include "brdf_lobes.h"
#include "simd_undef.h"

/* material row m (BRDF_WIDTH floats), unit shading normal n, unit direction l to the light:
 * kd = 1 - F and ks (occlusion-weighted specular + clearcoat), 3 floats each */
static inline void brdf_terms(const float *m, const float *n, const float *l, float kd[3], float ks[3]) {
    brdf_lobes_scalar(m, n, l, kd, ks);
}

#endif
