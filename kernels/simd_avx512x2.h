/* The vector API of kernels/voxelq_simd.h for AVX-512 with two registers per vector (32 lanes): every
 * operation is applied to both halves, so each instruction has an independent twin. On the city's bench
 * rays one group of 16 was mostly waiting on its own chain of dependent instructions (the query is a
 * long chain: set-up, direction bin, map, clip, row lookups): two chains interleaved ran 7 % faster on
 * one thread and 10 % on two. Define, include the SIMD body, then simd_undef.h. */
#define W 32
#define SUFFIX(f) f##_avx512x2
#define TARGET __attribute__((target("avx512f,avx512dq,avx512vl,avx512bw,avx2,fma")))
#define X2_INLINE static inline __attribute__((always_inline, target("avx512f,avx512dq,avx512vl,avx512bw,avx2,fma")))
typedef struct { __m512 a, b; } V32;
typedef struct { __m512i a, b; } VI32;
typedef struct { __mmask16 a, b; } M32;
#define V V32
#define VI VI32
#define M M32
/* an operation on both halves */
X2_INLINE V32 x2_set(float x) { __m512 v = _mm512_set1_ps(x); return (V32){v, v}; }
X2_INLINE VI32 x2_iset(int x) { __m512i v = _mm512_set1_epi32(x); return (VI32){v, v}; }
#define SET x2_set
#define ISET x2_iset
#define X2F2(name, op) X2_INLINE V32 name(V32 x, V32 y) { return (V32){op(x.a, y.a), op(x.b, y.b)}; }
#define X2F1(name, op) X2_INLINE V32 name(V32 x) { return (V32){op(x.a), op(x.b)}; }
#define X2I2(name, op) X2_INLINE VI32 name(VI32 x, VI32 y) { return (VI32){op(x.a, y.a), op(x.b, y.b)}; }
X2F2(x2_add, _mm512_add_ps) X2F2(x2_sub, _mm512_sub_ps) X2F2(x2_mul, _mm512_mul_ps) X2F2(x2_div, _mm512_div_ps)
X2F2(x2_min, _mm512_min_ps) X2F2(x2_max, _mm512_max_ps) X2F1(x2_sqrt, _mm512_sqrt_ps) X2F1(x2_abs, _mm512_abs_ps)
X2I2(x2_iadd, _mm512_add_epi32) X2I2(x2_isub, _mm512_sub_epi32) X2I2(x2_imul, _mm512_mullo_epi32)
X2I2(x2_imin, _mm512_min_epi32) X2I2(x2_imax, _mm512_max_epi32) X2I2(x2_iand, _mm512_and_si512)
X2I2(x2_isrlv, _mm512_srlv_epi32) X2I2(x2_isllv, _mm512_sllv_epi32) X2I2(x2_ior, _mm512_or_si512) X2I2(x2_ixor, _mm512_xor_si512)
#define ADD x2_add
#define SUB x2_sub
#define MUL x2_mul
#define DIV x2_div
#define MIN x2_min
#define MAX x2_max
#define SQRT x2_sqrt
#define ABS x2_abs
#define IADD x2_iadd
#define ISUB x2_isub
#define IMUL x2_imul
#define IMIN x2_imin
#define IMAX x2_imax
#define IAND x2_iand
#define ISRLV x2_isrlv
#define ISLLV x2_isllv
#define IOR x2_ior
#define IXOR x2_ixor
X2_INLINE __m512 x16_rcp(__m512 x) { __m512 r = _mm512_rcp14_ps(x); return _mm512_mul_ps(r, _mm512_fnmadd_ps(x, r, _mm512_set1_ps(2.0f))); }
X2F1(x2_rcp, x16_rcp)
#define RCP x2_rcp
X2_INLINE V32 x2_fma(V32 x, V32 y, V32 z) { return (V32){_mm512_fmadd_ps(x.a, y.a, z.a), _mm512_fmadd_ps(x.b, y.b, z.b)}; }
#define FMA x2_fma
#define X2CMP(name, pred) X2_INLINE M32 name(V32 x, V32 y) { return (M32){_mm512_cmp_ps_mask(x.a, y.a, pred), _mm512_cmp_ps_mask(x.b, y.b, pred)}; }
X2CMP(x2_lt, _CMP_LT_OQ) X2CMP(x2_le, _CMP_LE_OQ) X2CMP(x2_gt, _CMP_GT_OQ) X2CMP(x2_ge, _CMP_GE_OQ) X2CMP(x2_eq, _CMP_EQ_OQ)
#define LT x2_lt
#define LE x2_le
#define GT x2_gt
#define GE x2_ge
#define EQ x2_eq
#define X2ICMP(name, op) X2_INLINE M32 name(VI32 x, VI32 y) { return (M32){op(x.a, y.a), op(x.b, y.b)}; }
X2ICMP(x2_igt, _mm512_cmpgt_epi32_mask) X2ICMP(x2_ige, _mm512_cmpge_epi32_mask) X2ICMP(x2_ieq, _mm512_cmpeq_epi32_mask)
#define IGT x2_igt
#define IGE x2_ige
#define IEQ x2_ieq
X2_INLINE M32 x2_inz(VI32 x) { return (M32){_mm512_test_epi32_mask(x.a, x.a), _mm512_test_epi32_mask(x.b, x.b)}; }
#define INZ x2_inz
X2_INLINE V32 x2_sel(M32 m, V32 x, V32 y) { return (V32){_mm512_mask_blend_ps(m.a, y.a, x.a), _mm512_mask_blend_ps(m.b, y.b, x.b)}; }
X2_INLINE VI32 x2_seli(M32 m, VI32 x, VI32 y) { return (VI32){_mm512_mask_blend_epi32(m.a, y.a, x.a), _mm512_mask_blend_epi32(m.b, y.b, x.b)}; }
#define SEL x2_sel
#define SELI x2_seli
X2_INLINE M32 x2_mand(M32 x, M32 y) { return (M32){(__mmask16)(x.a & y.a), (__mmask16)(x.b & y.b)}; }
X2_INLINE M32 x2_mor(M32 x, M32 y) { return (M32){(__mmask16)(x.a | y.a), (__mmask16)(x.b | y.b)}; }
X2_INLINE M32 x2_mandn(M32 x, M32 y) { return (M32){(__mmask16)(~x.a & y.a), (__mmask16)(~x.b & y.b)}; }
#define MAND x2_mand
#define MOR x2_mor
#define MANDN x2_mandn
#define MNONE ((M32){0, 0})
#define MBITS(m) ((unsigned)(m).a | (unsigned)(m).b << 16)
#define MALL ((M32){0xFFFF, 0xFFFF})
#define MFROMBITS(bits) ((M32){(__mmask16)(bits), (__mmask16)((unsigned)(bits) >> 16)})
X2_INLINE VI32 x2_isrl(VI32 x, int n) { __m128i c = _mm_cvtsi32_si128(n); return (VI32){_mm512_srl_epi32(x.a, c), _mm512_srl_epi32(x.b, c)}; }
X2_INLINE VI32 x2_isll(VI32 x, int n) { __m128i c = _mm_cvtsi32_si128(n); return (VI32){_mm512_sll_epi32(x.a, c), _mm512_sll_epi32(x.b, c)}; }
#define ISRL x2_isrl
#define ISLL x2_isll
X2_INLINE VI32 x2_cvtt(V32 x) { return (VI32){_mm512_cvttps_epi32(x.a), _mm512_cvttps_epi32(x.b)}; }
X2_INLINE V32 x2_cvtf(VI32 x) { return (V32){_mm512_cvtepi32_ps(x.a), _mm512_cvtepi32_ps(x.b)}; }
#define CVTT x2_cvtt
#define CVTF x2_cvtf
#define GATHER_I(p, i) ((VI32){_mm512_i32gather_epi32((i).a, (const void *)(p), 4), _mm512_i32gather_epi32((i).b, (const void *)(p), 4)})
#define GATHER_F(p, i) ((V32){_mm512_i32gather_ps((i).a, (const void *)(p), 4), _mm512_i32gather_ps((i).b, (const void *)(p), 4)})
#define MGATHER_I(p, i, m) ((VI32){_mm512_mask_i32gather_epi32(_mm512_setzero_si512(), (m).a, (i).a, (const void *)(p), 4), \
                                   _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), (m).b, (i).b, (const void *)(p), 4)})
#define LOAD(p) ((V32){_mm512_loadu_ps(p), _mm512_loadu_ps((p) + 16)})
#define MLOAD(p, m) ((V32){_mm512_maskz_loadu_ps((m).a, p), _mm512_maskz_loadu_ps((m).b, (p) + 16)})
#define ILOAD(p) ((VI32){_mm512_loadu_si512((const void *)(p)), _mm512_loadu_si512((const void *)((p) + 16))})
#define MILOAD(p, m) ((VI32){_mm512_maskz_loadu_epi32((m).a, (const void *)(p)), _mm512_maskz_loadu_epi32((m).b, (const void *)((p) + 16))})
#define STORE(p, v) do { V32 v_ = (v); _mm512_storeu_ps(p, v_.a); _mm512_storeu_ps((p) + 16, v_.b); } while (0)
#define ISTORE(p, v) do { VI32 v_ = (v); _mm512_storeu_si512((void *)(p), v_.a); _mm512_storeu_si512((void *)((p) + 16), v_.b); } while (0)
#define IOTA ((VI32){_mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), \
                     _mm512_setr_epi32(16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31)})
#define COMPRESS_F(p, m, v) ({ M32 m_ = (m); V32 v_ = (v); _mm512_mask_compressstoreu_ps(p, m_.a, v_.a); \
        _mm512_mask_compressstoreu_ps((p) + __builtin_popcount(m_.a), m_.b, v_.b); __builtin_popcount(m_.a) + __builtin_popcount(m_.b); })
#define COMPRESS_I(p, m, v) ({ M32 m_ = (m); VI32 v_ = (v); _mm512_mask_compressstoreu_epi32(p, m_.a, v_.a); \
        _mm512_mask_compressstoreu_epi32((p) + __builtin_popcount(m_.a), m_.b, v_.b); __builtin_popcount(m_.a) + __builtin_popcount(m_.b); })
/* x, y, z of 16 float triples held in three registers (a0 a1 a2: the 48 floats in order): six
 * two-source permutes */
X2_INLINE void x16_xyz_of3(__m512 a0, __m512 a1, __m512 a2, __m512 *out) {
    __m512i iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    for (int k = 0; k < 3; k++) {
        __m512i i1 = _mm512_add_epi32(_mm512_mullo_epi32(iota, _mm512_set1_epi32(3)), _mm512_set1_epi32(k));
        __m512 t = _mm512_permutex2var_ps(a0, i1, a1);
        __mmask16 hi = _mm512_cmpge_epi32_mask(i1, _mm512_set1_epi32(32));
        __m512i i2 = _mm512_mask_blend_epi32(hi, iota, _mm512_sub_epi32(i1, _mm512_set1_epi32(16)));
        out[k] = _mm512_permutex2var_ps(t, i2, a2);
    }
}
/* x, y, z of m <= 16 consecutive float triples */
X2_INLINE void x16_load_xyz(const float *p, int m, __m512 *out) {
    if (m == 16) {
        x16_xyz_of3(_mm512_loadu_ps(p), _mm512_loadu_ps(p + 16), _mm512_loadu_ps(p + 32), out);
        return;
    }
    __mmask64 all = m * 3 >= 64 ? ~(__mmask64)0 : (((__mmask64)1 << (m * 3)) - 1);
    x16_xyz_of3(_mm512_maskz_loadu_ps((__mmask16)all, p), _mm512_maskz_loadu_ps((__mmask16)(all >> 16), p + 16),
                _mm512_maskz_loadu_ps((__mmask16)(all >> 32), p + 32), out);
}
/* the same from double triples, rounded to float on the way in (no store and reload) */
X2_INLINE void x16_load_xyz64(const double *p, int m, __m512 *out) {
    __m256 h[6];
    __mmask64 all = m * 3 >= 64 ? ~(__mmask64)0 : (((__mmask64)1 << (m * 3)) - 1);
    for (int q = 0; q < 6; q++)
        h[q] = _mm512_cvtpd_ps(m == 16 ? _mm512_loadu_pd(p + 8 * q) : _mm512_maskz_loadu_pd((__mmask8)(all >> (8 * q)), p + 8 * q));
    x16_xyz_of3(_mm512_insertf32x8(_mm512_castps256_ps512(h[0]), h[1], 1), _mm512_insertf32x8(_mm512_castps256_ps512(h[2]), h[3], 1),
                _mm512_insertf32x8(_mm512_castps256_ps512(h[4]), h[5], 1), out);
}
/* 32 lanes: the first 16 triples, then the next */
#define LOAD_XYZ(p, m, live, out) do { __m512 lo_[3], hi_[3]; int m_ = (m); \
        x16_load_xyz(p, m_ < 16 ? m_ : 16, lo_); x16_load_xyz((p) + 48, m_ > 16 ? m_ - 16 : 0, hi_); \
        for (int k_ = 0; k_ < 3; k_++) (out)[k_] = (V32){lo_[k_], hi_[k_]}; \
        (void)(live); } while (0)
#define LOAD_XYZ64(p, m, live, out) do { __m512 lo_[3], hi_[3]; int m_ = (m); \
        x16_load_xyz64(p, m_ < 16 ? m_ : 16, lo_); x16_load_xyz64((p) + 48, m_ > 16 ? m_ - 16 : 0, hi_); \
        for (int k_ = 0; k_ < 3; k_++) (out)[k_] = (V32){lo_[k_], hi_[k_]}; \
        (void)(live); } while (0)
/* F[k] (k < 12) of 16 lanes from the 12-float rows tab + 12 d (rows of inactive lanes too: give them a
 * valid d): per lane three 16-byte loads, each block of four floats transposed 4 x 4 within the 128-bit
 * lanes; register lane 4 i + q is built from the rows of lanes q + 4 i, which that transpose puts back
 * in order (a group's rows meet about 7 bins per 16 lanes on the city's bench rays, so rows are read per
 * lane; this beat twelve 64-bit gathers a little: AVX2 28.2 -> 25.7 ns a query on one thread) */
X2_INLINE void x16_rows12(const float *tab, __m512i d, __m512 *F) {
    int li[16];
    _mm512_storeu_si512((void *)li, d);
    for (int j = 0; j < 3; j++) {
        __m512 z[4];
        for (int q = 0; q < 4; q++) {
            __m512 x = _mm512_castps128_ps512(_mm_loadu_ps(tab + 12 * (size_t)li[q] + 4 * j));
            x = _mm512_insertf32x4(x, _mm_loadu_ps(tab + 12 * (size_t)li[q + 4] + 4 * j), 1);
            x = _mm512_insertf32x4(x, _mm_loadu_ps(tab + 12 * (size_t)li[q + 8] + 4 * j), 2);
            z[q] = _mm512_insertf32x4(x, _mm_loadu_ps(tab + 12 * (size_t)li[q + 12] + 4 * j), 3);
        }
        __m512d t0 = _mm512_castps_pd(_mm512_unpacklo_ps(z[0], z[1])), t1 = _mm512_castps_pd(_mm512_unpackhi_ps(z[0], z[1]));
        __m512d t2 = _mm512_castps_pd(_mm512_unpacklo_ps(z[2], z[3])), t3 = _mm512_castps_pd(_mm512_unpackhi_ps(z[2], z[3]));
        F[4 * j] = _mm512_castpd_ps(_mm512_unpacklo_pd(t0, t2));
        F[4 * j + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(t0, t2));
        F[4 * j + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(t1, t3));
        F[4 * j + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(t1, t3));
    }
}
#define GATHER_ROWS12(tab, d, m, F) do { __m512 lo_[12], hi_[12]; VI32 d_ = (d); \
        x16_rows12(tab, d_.a, lo_); x16_rows12(tab, d_.b, hi_); \
        for (int k_ = 0; k_ < 12; k_++) (F)[k_] = (V32){lo_[k_], hi_[k_]}; \
        (void)(m); } while (0)
#define IREDUCE_MAX(v) ({ VI32 v_ = (v); int a_ = _mm512_reduce_max_epi32(v_.a), b_ = _mm512_reduce_max_epi32(v_.b); a_ > b_ ? a_ : b_; })
#define FLOOR(x) ((V32){_mm512_roundscale_ps((x).a, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC), _mm512_roundscale_ps((x).b, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC)})
#undef X2F2
#undef X2F1
#undef X2I2
#undef X2CMP
#undef X2ICMP
