/* The UsdPreviewSurface BRDF of one light at a point for the compiled kernels: kernels/brdf.py's brdf_terms,
 * written once here (that module's docstring defines the row layout and every term). */

#ifndef USDML_BRDF_H
#define USDML_BRDF_H

#include <math.h>

enum { BRDF_WIDTH = 16, BRDF_EYE = 0, BRDF_F0 = 3, BRDF_F90 = 6, BRDF_ALPHA = 9, BRDF_CLEARCOAT = 10,
       BRDF_CLEARCOAT_ALPHA = 11, BRDF_CLEARCOAT_F0 = 12, BRDF_OCCLUSION = 13 };

/* s2 = |n x h|^2 = 1 - (n.h)^2 without its cancellation near n.h = 1 (a sharp lobe's peak) */
static inline float brdf_ggx(float alpha, float n_h, float s2) {
    float a2 = alpha * alpha, c2 = n_h * n_h;
    float d = fmaxf(s2 + c2 * a2, 1e-18f);              /* (n.h)^2 (a^2 - 1) + 1; no 0/0 at alpha 0 */
    return a2 / (3.14159265358979f * d * d);
}

static inline float brdf_vis(float alpha, float n_e, float n_l) {
    float k = alpha * 0.5f;
    return 1.0f / (4.0f * (n_e * (1.0f - k) + k) * (n_l * (1.0f - k) + k));
}

/* material row m (BRDF_WIDTH floats), unit shading normal n, unit direction l to the light:
 * kd = 1 - F and ks (occlusion-weighted specular + clearcoat), 3 floats each */
static inline void brdf_terms(const float *m, const float *n, const float *l, float kd[3], float ks[3]) {
    const float *e = m + BRDF_EYE;
    float h[3] = {e[0] + l[0], e[1] + l[1], e[2] + l[2]};
    float hl = sqrtf(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]);
    hl = 1.0f / (hl > 1e-30f ? hl : 1e-30f);
    h[0] *= hl; h[1] *= hl; h[2] *= hl;
    float n_l = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
    float n_e = n[0] * e[0] + n[1] * e[1] + n[2] * e[2];
    float n_h = n[0] * h[0] + n[1] * h[1] + n[2] * h[2];
    float e_h = e[0] * h[0] + e[1] * h[1] + e[2] * h[2];
    float cx = n[1] * h[2] - n[2] * h[1], cy = n[2] * h[0] - n[0] * h[2], cz = n[0] * h[1] - n[1] * h[0];
    float s2 = cx * cx + cy * cy + cz * cz;
    n_l = n_l > 0.0f ? n_l : 0.0f;
    n_h = n_h > 0.0f ? n_h : 0.0f;
    e_h = e_h > 0.0f ? e_h : 0.0f;
    float x = 1.0f - e_h, fresnel = x * x * x * x * x;
    float f[3];
    for (int k = 0; k < 3; k++) {
        f[k] = m[BRDF_F0 + k] + (m[BRDF_F90 + k] - m[BRDF_F0 + k]) * fresnel;
        kd[k] = 1.0f - f[k];
    }
    if (n_e <= 0.0f) {
        ks[0] = ks[1] = ks[2] = 0.0f;
        return;
    }
    float a = m[BRDF_ALPHA], ca = m[BRDF_CLEARCOAT_ALPHA], cf0 = m[BRDF_CLEARCOAT_F0], occ = m[BRDF_OCCLUSION];
    float spec = brdf_ggx(a, n_h, s2) * brdf_vis(a, n_e, n_l);
    float coat = m[BRDF_CLEARCOAT] * (cf0 + (1.0f - cf0) * fresnel) * brdf_ggx(ca, n_h, s2) * brdf_vis(ca, n_e, n_l);
    for (int k = 0; k < 3; k++) ks[k] = (f[k] * spec + coat) * occ;
}

#endif
