/* The preview surface's two sums per point over its visible lights, compiled: usdml.lighting.brdf_sums's NumPy
 * reference (E·kd and E·ks of kernels/include/brdf.h, summed in light order), for the shading of any backend
 * without a fused material kernel. Loaded with ctypes by usdml.lighting.brdf_sums; called from a thread pool
 * (ctypes releases the GIL). Built without contracting a * b + c (setup.py), so that every product and sum
 * rounds as NumPy's do. */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

#include "brdf.h"

/* points 0 .. n_points - 1 against lights 0 .. n_lights - 1, every (point, light) array row-major (n_points,
 * n_lights) float32: g the irradiance factor after shadows (lights with g <= 0 skipped), f the focus factor (NULL:
 * none), wx, wy, wz the unit direction to the light; base and focus_rgb (n_lights, 3) the lights' colours (E = g
 * base + g f focus_rgb); rows (n_points, BRDF_WIDTH) and normals (n_points, 3) the points' materials and unit
 * shading normals. diffuse and specular (n_points, 3): the sums of E kd and E ks, added in double in light order
 * (as NumPy's bincount) and rounded to float. */
void bs_sums(int64_t n_points, int32_t n_lights, const float *g, const float *f, const float *wx, const float *wy,
             const float *wz, const float *base, const float *focus_rgb, const float *rows, const float *normals,
             float *diffuse, float *specular) {
    for (int64_t i = 0; i < n_points; i++) {
        const float *m = rows + (size_t)BRDF_WIDTH * i, *n = normals + 3 * i;
        const size_t row = (size_t)i * n_lights;
        double sd[3] = {0.0, 0.0, 0.0}, ss[3] = {0.0, 0.0, 0.0};
        for (int32_t l = 0; l < n_lights; l++) {
            float gv = g[row + l];
            if (!(gv > 0.0f)) continue;
            float e[3], kd[3], ks[3];
            for (int k = 0; k < 3; k++) e[k] = gv * base[3 * (size_t)l + k];
            if (f) {
                float gf = gv * f[row + l];
                for (int k = 0; k < 3; k++) e[k] += gf * focus_rgb[3 * (size_t)l + k];
            }
            float lv[3] = {wx[row + l], wy[row + l], wz[row + l]};
            brdf_terms(m, n, lv, kd, ks);
            for (int k = 0; k < 3; k++) {
                sd[k] += (double)(e[k] * kd[k]);
                ss[k] += (double)(e[k] * ks[k]);
            }
        }
        for (int k = 0; k < 3; k++) {
            diffuse[3 * i + k] = (float)sd[k];
            specular[3 * i + k] = (float)ss[k];
        }
    }
}

/* an importable module, so that the import system finds the library (usdml.lighting.brdf_sums) */
static struct PyModuleDef bs_module = {PyModuleDef_HEAD_INIT, .m_name = "_brdfsum",
                                       .m_doc = "Compiled BRDF sums of the preview surface; called through ctypes.",
                                       .m_size = -1};

PyMODINIT_FUNC PyInit__brdfsum(void) { return PyModule_Create(&bs_module); }
