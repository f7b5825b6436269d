/* The UsdPreviewSurface BRDF of one light at a point (kernels/brdf's brdf_terms, whose docstring defines
 * every term and the row layout), written once against the vector API of the SIMD bodies (V, M, SET, ADD, SUB,
 * MUL, DIV, SQRT, MAX, GT, SEL, SUFFIX, TARGET): brdf.h includes it with a scalar API (brdf_terms), and
 * kernels/voxel/voxelq_simd.h once per instruction set, W points at a time. No include guard: included once per
 * API. Branch-free: where n.e <= 0 the specular lobes are multiplied by 0 (their terms stay finite, alpha > 0). */

/* one lobe, D V: GGX D times G / (4 (n.l)(n.e)) with Smith-Schlick G, k = alpha / 2, as one quotient (SIMD
 * division is slow); s2 = |n x h|^2 = 1 - (n.h)^2 without its cancellation near n.h = 1 (a sharp lobe's peak) */
TARGET static inline V SUFFIX(brdf_lobe)(V alpha, V n_h, V s2, V n_e, V n_l) {
    V a2 = MUL(alpha, alpha), c2 = MUL(n_h, n_h);
    V d = MAX(ADD(s2, MUL(c2, a2)), SET(1e-18f));      /* (n.h)^2 (a^2 - 1) + 1; no 0/0 at alpha 0 */
    V k = MUL(alpha, SET(0.5f)), j = SUB(SET(1.0f), k);
    V vis = MUL(MUL(SET(4.0f), ADD(MUL(n_e, j), k)), ADD(MUL(n_l, j), k));
    return DIV(a2, MUL(MUL(MUL(SET(3.14159265358979f), d), d), vis));
}

/* kd = 1 - F and ks (occlusion-weighted specular + clearcoat) of rows m (BRDF_WIDTH columns, m[c] column c) at
 * unit shading normals n toward unit light directions l */
TARGET static inline void SUFFIX(brdf_lobes)(const V *m, const V n[3], const V l[3], V kd[3], V ks[3]) {
    const V *e = m + BRDF_EYE;
    V zf = SET(0.0f), one = SET(1.0f);
    V h[3] = {ADD(e[0], l[0]), ADD(e[1], l[1]), ADD(e[2], l[2])};
    /* divided, not multiplied by a reciprocal: at a sharp lobe's peak D follows h's last bits (NumPy divides) */
    V hl = MAX(SQRT(ADD(ADD(MUL(h[0], h[0]), MUL(h[1], h[1])), MUL(h[2], h[2]))), SET(1e-30f));
    for (int k = 0; k < 3; k++) h[k] = DIV(h[k], hl);
    V n_l = MAX(ADD(ADD(MUL(n[0], l[0]), MUL(n[1], l[1])), MUL(n[2], l[2])), zf);
    V n_e = ADD(ADD(MUL(n[0], e[0]), MUL(n[1], e[1])), MUL(n[2], e[2]));
    V n_h = MAX(ADD(ADD(MUL(n[0], h[0]), MUL(n[1], h[1])), MUL(n[2], h[2])), zf);
    V e_h = MAX(ADD(ADD(MUL(e[0], h[0]), MUL(e[1], h[1])), MUL(e[2], h[2])), zf);
    V cx = SUB(MUL(n[1], h[2]), MUL(n[2], h[1])), cy = SUB(MUL(n[2], h[0]), MUL(n[0], h[2]));
    V cz = SUB(MUL(n[0], h[1]), MUL(n[1], h[0]));
    V s2 = ADD(ADD(MUL(cx, cx), MUL(cy, cy)), MUL(cz, cz));
    V x = SUB(one, e_h), x2 = MUL(x, x), fresnel = MUL(MUL(x2, x2), x);
    V f[3];
    for (int k = 0; k < 3; k++) {
        f[k] = ADD(m[BRDF_F0 + k], MUL(SUB(m[BRDF_F90 + k], m[BRDF_F0 + k]), fresnel));
        kd[k] = SUB(one, f[k]);
    }
    V occ = SEL(GT(n_e, zf), m[BRDF_OCCLUSION], zf);
    n_e = MAX(n_e, zf);
    V a = m[BRDF_ALPHA], ca = m[BRDF_CLEARCOAT_ALPHA], cf0 = m[BRDF_CLEARCOAT_F0];
    V spec = SUFFIX(brdf_lobe)(a, n_h, s2, n_e, n_l);
    V coat = MUL(MUL(m[BRDF_CLEARCOAT], ADD(cf0, MUL(SUB(one, cf0), fresnel))), SUFFIX(brdf_lobe)(ca, n_h, s2, n_e, n_l));
    for (int k = 0; k < 3; k++) ks[k] = MUL(ADD(MUL(f[k], spec), coat), occ);
}
