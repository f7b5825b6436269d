/* Two registers per vector over the SIMD API defined just before (simd_avx2.h or simd_avx512.h): every
 * operation applied to both halves, so each instruction of kernels/voxel/voxelq_simd.h has an independent
 * twin (a query is one long chain of dependent instructions: set-up, direction bin, map, clip, row
 * lookups). The includer defines X2_TAG (the name of the doubled instruction set, e.g. avx512x2);
 * TARGET stays the base's. Then include the SIMD body and simd_undef.h. */
#define X2CAT_(a, b) a##_##b
#define X2CAT(a, b) X2CAT_(a, b)
#define X2N(name) X2CAT(name, X2_TAG)
#define X2_INLINE static inline __attribute__((always_inline)) TARGET
typedef V X2N(v1);
typedef VI X2N(vi1);
typedef M X2N(m1);
typedef struct { X2N(v1) a, b; } X2N(v2);
typedef struct { X2N(vi1) a, b; } X2N(vi2);
typedef struct { X2N(m1) a, b; } X2N(m2);
enum { X2N(half) = W };
#define X2V X2N(v2)
#define X2VI X2N(vi2)
#define X2M X2N(m2)
#define X2_F2(name, op) X2_INLINE X2V X2N(name)(X2V x, X2V y) { return (X2V){op(x.a, y.a), op(x.b, y.b)}; }
#define X2_F1(name, op) X2_INLINE X2V X2N(name)(X2V x) { return (X2V){op(x.a), op(x.b)}; }
#define X2_I2(name, op) X2_INLINE X2VI X2N(name)(X2VI x, X2VI y) { return (X2VI){op(x.a, y.a), op(x.b, y.b)}; }
#define X2_C2(name, op) X2_INLINE X2M X2N(name)(X2V x, X2V y) { return (X2M){op(x.a, y.a), op(x.b, y.b)}; }
#define X2_IC2(name, op) X2_INLINE X2M X2N(name)(X2VI x, X2VI y) { return (X2M){op(x.a, y.a), op(x.b, y.b)}; }
#define X2_M2(name, op) X2_INLINE X2M X2N(name)(X2M x, X2M y) { return (X2M){op(x.a, y.a), op(x.b, y.b)}; }
X2_INLINE X2V X2N(set)(float x) { X2N(v1) v = SET(x); return (X2V){v, v}; }
X2_INLINE X2VI X2N(iset)(int x) { X2N(vi1) v = ISET(x); return (X2VI){v, v}; }
X2_F2(add, ADD) X2_F2(sub, SUB) X2_F2(mul, MUL) X2_F2(div, DIV) X2_F2(min, MIN) X2_F2(max, MAX)
X2_F1(rcp, RCP) X2_F1(sqrt, SQRT) X2_F1(abs, ABS)
X2_INLINE X2V X2N(fma)(X2V x, X2V y, X2V z) { return (X2V){FMA(x.a, y.a, z.a), FMA(x.b, y.b, z.b)}; }
X2_C2(lt, LT) X2_C2(le, LE) X2_C2(gt, GT) X2_C2(ge, GE) X2_C2(eq, EQ)
X2_INLINE X2V X2N(sel)(X2M m, X2V x, X2V y) { return (X2V){SEL(m.a, x.a, y.a), SEL(m.b, x.b, y.b)}; }
X2_INLINE X2VI X2N(seli)(X2M m, X2VI x, X2VI y) { return (X2VI){SELI(m.a, x.a, y.a), SELI(m.b, x.b, y.b)}; }
X2_M2(mand, MAND) X2_M2(mor, MOR) X2_M2(mandn, MANDN)
X2_INLINE X2M X2N(mnone)(void) { return (X2M){MNONE, MNONE}; }
X2_INLINE unsigned X2N(mbits)(X2M m) { return MBITS(m.a) | MBITS(m.b) << W; }
X2_I2(iadd, IADD) X2_I2(isub, ISUB) X2_I2(imul, IMUL) X2_I2(imin, IMIN) X2_I2(imax, IMAX) X2_I2(iand, IAND)
X2_I2(isrlv, ISRLV) X2_I2(isllv, ISLLV)
X2_INLINE X2VI X2N(isrl)(X2VI x, int n) { return (X2VI){ISRL(x.a, n), ISRL(x.b, n)}; }
X2_INLINE X2VI X2N(isll)(X2VI x, int n) { return (X2VI){ISLL(x.a, n), ISLL(x.b, n)}; }
X2_IC2(igt, IGT) X2_IC2(ige, IGE) X2_IC2(ieq, IEQ)
X2_INLINE X2M X2N(inz)(X2VI x) { return (X2M){INZ(x.a), INZ(x.b)}; }
X2_INLINE X2VI X2N(cvtt)(X2V x) { return (X2VI){CVTT(x.a), CVTT(x.b)}; }
X2_INLINE X2V X2N(cvtf)(X2VI x) { return (X2V){CVTF(x.a), CVTF(x.b)}; }
X2_INLINE X2VI X2N(gather_i)(const void *p, X2VI i) { return (X2VI){GATHER_I(p, i.a), GATHER_I(p, i.b)}; }
X2_INLINE X2VI X2N(mgather_i)(const void *p, X2VI i, X2M m) { return (X2VI){MGATHER_I(p, i.a, m.a), MGATHER_I(p, i.b, m.b)}; }
X2_INLINE X2V X2N(load)(const float *p) { return (X2V){LOAD(p), LOAD(p + W)}; }
X2_INLINE X2V X2N(mload)(const float *p, X2M m) { return (X2V){MLOAD(p, m.a), MLOAD(p + W, m.b)}; }
X2_INLINE X2VI X2N(iload)(const int32_t *p) { return (X2VI){ILOAD(p), ILOAD(p + W)}; }
X2_INLINE X2VI X2N(miload)(const int32_t *p, X2M m) { return (X2VI){MILOAD(p, m.a), MILOAD(p + W, m.b)}; }
X2_INLINE void X2N(store)(float *p, X2V v) { STORE(p, v.a); STORE(p + W, v.b); }
X2_INLINE void X2N(istore)(int32_t *p, X2VI v) { ISTORE(p, v.a); ISTORE(p + W, v.b); }
X2_INLINE X2VI X2N(iota)(void) { return (X2VI){IOTA, IADD(IOTA, ISET(W))}; }
X2_INLINE int X2N(compress_f)(float *p, X2M m, X2V v) { int c = COMPRESS_F(p, m.a, v.a); return c + COMPRESS_F(p + c, m.b, v.b); }
X2_INLINE int X2N(compress_i)(int32_t *p, X2M m, X2VI v) { int c = COMPRESS_I(p, m.a, v.a); return c + COMPRESS_I(p + c, m.b, v.b); }
X2_INLINE void X2N(load_xyz)(const float *p, int m, X2M live, X2V *out) {
    X2N(v1) lo[3], hi[3];
    LOAD_XYZ(p, m < W ? m : W, live.a, lo);
    LOAD_XYZ(p + 3 * W, m > W ? m - W : 0, live.b, hi);
    for (int k = 0; k < 3; k++) out[k] = (X2V){lo[k], hi[k]};
}
X2_INLINE void X2N(load_xyz64)(const double *p, int m, X2M live, X2V *out) {
    X2N(v1) lo[3], hi[3];
    LOAD_XYZ64(p, m < W ? m : W, live.a, lo);
    LOAD_XYZ64(p + 3 * W, m > W ? m - W : 0, live.b, hi);
    for (int k = 0; k < 3; k++) out[k] = (X2V){lo[k], hi[k]};
}
X2_INLINE void X2N(rows12)(const float *tab, X2VI d, X2M m, X2V *F) {
    X2N(v1) lo[12], hi[12];
    GATHER_ROWS12(tab, d.a, m.a, lo);
    GATHER_ROWS12(tab, d.b, m.b, hi);
    for (int k = 0; k < 12; k++) F[k] = (X2V){lo[k], hi[k]};
}
X2_INLINE int X2N(ireduce_max)(X2VI v) { int a = IREDUCE_MAX(v.a), b = IREDUCE_MAX(v.b); return a > b ? a : b; }
#undef X2_F2
#undef X2_F1
#undef X2_I2
#undef X2_C2
#undef X2_IC2
#undef X2_M2
/* the doubled API */
#undef W
#undef SUFFIX
#undef V
#undef VI
#undef M
#define W (2 * X2N(half))
#define SUFFIX(f) X2CAT(f, X2_TAG)
#define V X2V
#define VI X2VI
#define M X2M
#include "simd_undef_ops.h"
#define SET X2N(set)
#define ISET X2N(iset)
#define ADD X2N(add)
#define SUB X2N(sub)
#define MUL X2N(mul)
#define DIV X2N(div)
#define RCP X2N(rcp)
#define FMA X2N(fma)
#define MIN X2N(min)
#define MAX X2N(max)
#define SQRT X2N(sqrt)
#define ABS X2N(abs)
#define LT X2N(lt)
#define LE X2N(le)
#define GT X2N(gt)
#define GE X2N(ge)
#define EQ X2N(eq)
#define SEL X2N(sel)
#define SELI X2N(seli)
#define MAND X2N(mand)
#define MOR X2N(mor)
#define MANDN X2N(mandn)
#define MNONE X2N(mnone)()
#define MBITS X2N(mbits)
#define IADD X2N(iadd)
#define ISUB X2N(isub)
#define IMUL X2N(imul)
#define IMIN X2N(imin)
#define IMAX X2N(imax)
#define IAND X2N(iand)
#define ISRL X2N(isrl)
#define ISLL X2N(isll)
#define ISRLV X2N(isrlv)
#define ISLLV X2N(isllv)
#define IGT X2N(igt)
#define IGE X2N(ige)
#define IEQ X2N(ieq)
#define INZ X2N(inz)
#define CVTT X2N(cvtt)
#define CVTF X2N(cvtf)
#define GATHER_I X2N(gather_i)
#define MGATHER_I X2N(mgather_i)
#define LOAD X2N(load)
#define MLOAD X2N(mload)
#define ILOAD X2N(iload)
#define MILOAD X2N(miload)
#define STORE X2N(store)
#define ISTORE X2N(istore)
#define IOTA X2N(iota)()
#define COMPRESS_F X2N(compress_f)
#define COMPRESS_I X2N(compress_i)
#define LOAD_XYZ X2N(load_xyz)
#define LOAD_XYZ64 X2N(load_xyz64)
#define GATHER_ROWS12 X2N(rows12)
#define IREDUCE_MAX X2N(ireduce_max)
