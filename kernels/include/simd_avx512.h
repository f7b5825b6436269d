/* The vector API of the SIMD bodies for AVX-512 (16 lanes): W, SUFFIX, TARGET, V / VI / M and their operations.
 * Shared by kernels/voxel/voxelq.c (doubled by simd_x2.h) and kernels/svo/svoq.c: define, include the SIMD body, then simd_undef.h. */
/* AVX-512: masks are k registers */
#define W 16
#define SUFFIX(f) f##_avx512
#define TARGET __attribute__((target("avx512f,avx512dq,avx512vl,avx512bw,avx2,fma")))
typedef __m512 V16;
typedef __m512i VI16;
typedef __mmask16 M16;
#define V V16
#define VI VI16
#define M M16
#define SET _mm512_set1_ps
#define ISET _mm512_set1_epi32
#define ADD _mm512_add_ps
#define SUB _mm512_sub_ps
#define MUL _mm512_mul_ps
#define DIV _mm512_div_ps
/* 1 / x to about 23 bits: the 14-bit estimate and one Newton step */
#define RCP(x) ({ V x_ = (x), r_ = _mm512_rcp14_ps(x_); _mm512_mul_ps(r_, _mm512_fnmadd_ps(x_, r_, _mm512_set1_ps(2.0f))); })
#define FMA _mm512_fmadd_ps
#define MIN _mm512_min_ps
#define MAX _mm512_max_ps
#define SQRT _mm512_sqrt_ps
#define ABS _mm512_abs_ps
#define LT(a, b) _mm512_cmp_ps_mask(a, b, _CMP_LT_OQ)
#define LE(a, b) _mm512_cmp_ps_mask(a, b, _CMP_LE_OQ)
#define GT(a, b) _mm512_cmp_ps_mask(a, b, _CMP_GT_OQ)
#define GE(a, b) _mm512_cmp_ps_mask(a, b, _CMP_GE_OQ)
#define EQ(a, b) _mm512_cmp_ps_mask(a, b, _CMP_EQ_OQ)
#define SEL(m, a, b) _mm512_mask_blend_ps(m, b, a)
#define SELI(m, a, b) _mm512_mask_blend_epi32(m, b, a)
#define MAND(a, b) ((__mmask16)((a) & (b)))
#define MOR(a, b) ((__mmask16)((a) | (b)))
#define MANDN(a, b) ((__mmask16)(~(a) & (b)))
#define MNONE ((__mmask16)0)
#define MBITS(m) ((unsigned)(m))
#define IADD _mm512_add_epi32
#define ISUB _mm512_sub_epi32
#define IMUL _mm512_mullo_epi32
#define IMIN _mm512_min_epi32
#define IMAX _mm512_max_epi32
#define IAND _mm512_and_si512
#define ISRL(a, n) _mm512_srl_epi32(a, _mm_cvtsi32_si128(n))
#define ISLL(a, n) _mm512_sll_epi32(a, _mm_cvtsi32_si128(n))
#define ISRLV _mm512_srlv_epi32
#define ISLLV _mm512_sllv_epi32
#define IGT _mm512_cmpgt_epi32_mask
#define IGE _mm512_cmpge_epi32_mask
#define IEQ _mm512_cmpeq_epi32_mask
#define INZ(x) _mm512_test_epi32_mask(x, x)
#define CVTT _mm512_cvttps_epi32
#define CVTF _mm512_cvtepi32_ps
#define GATHER_I(p, i) _mm512_i32gather_epi32(i, (const void *)(p), 4)
#define GATHER_F(p, i) _mm512_i32gather_ps(i, (const void *)(p), 4)
#define MGATHER_I(p, i, m) _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), m, i, (const void *)(p), 4)
#define LOAD _mm512_loadu_ps
#define MLOAD(p, m) _mm512_maskz_loadu_ps(m, p)
#define ILOAD(p) _mm512_loadu_si512((const void *)(p))
#define MILOAD(p, m) _mm512_maskz_loadu_epi32(m, (const void *)(p))
#define STORE _mm512_storeu_ps
#define ISTORE(p, v) _mm512_storeu_si512((void *)(p), v)
#define IOTA _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#define COMPRESS_F(p, m, v) ({ _mm512_mask_compressstoreu_ps(p, m, v); __builtin_popcount(m); })
#define COMPRESS_I(p, m, v) ({ _mm512_mask_compressstoreu_epi32(p, m, v); __builtin_popcount(m); })
/* x, y, z of 16 float triples held in three registers (a0 a1 a2: the 48 floats in order): six two-source
 * permutes */
#define XYZ_OF3(a0, a1, a2, out) do { \
        for (int k_ = 0; k_ < 3; k_++) { \
            VI i1_ = _mm512_add_epi32(_mm512_mullo_epi32(IOTA, _mm512_set1_epi32(3)), _mm512_set1_epi32(k_)); \
            __m512 t_ = _mm512_permutex2var_ps(a0, i1_, a1); /* lanes with index < 32 */ \
            __mmask16 hi_ = _mm512_cmpge_epi32_mask(i1_, _mm512_set1_epi32(32)); \
            VI i2_ = _mm512_mask_blend_epi32(hi_, IOTA, _mm512_sub_epi32(i1_, _mm512_set1_epi32(16))); \
            (out)[k_] = _mm512_permutex2var_ps(t_, i2_, a2); \
        } \
    } while (0)
/* x, y, z of m <= 16 consecutive float triples: three loads and six two-source permutes */
#define LOAD_XYZ(p, m, live, out) do { \
        __m512 a0_, a1_, a2_; \
        if ((m) == 16) { a0_ = _mm512_loadu_ps(p); a1_ = _mm512_loadu_ps((p) + 16); a2_ = _mm512_loadu_ps((p) + 32); } \
        else { \
            __mmask64 all_ = (m) * 3 >= 64 ? ~(__mmask64)0 : (((__mmask64)1 << ((m) * 3)) - 1); \
            a0_ = _mm512_maskz_loadu_ps((__mmask16)all_, p); \
            a1_ = _mm512_maskz_loadu_ps((__mmask16)(all_ >> 16), (p) + 16); \
            a2_ = _mm512_maskz_loadu_ps((__mmask16)(all_ >> 32), (p) + 32); \
        } \
        XYZ_OF3(a0_, a1_, a2_, out); \
        (void)(live); \
    } while (0)
/* the same from m <= 16 consecutive double triples, rounded to float on the way in (six loads and
 * conversions, no store and reload) */
#define LOAD_XYZ64(p, m, live, out) do { \
        __m256 h_[6]; \
        __mmask64 all_ = (m) * 3 >= 64 ? ~(__mmask64)0 : (((__mmask64)1 << ((m) * 3)) - 1); \
        for (int q_ = 0; q_ < 6; q_++) \
            h_[q_] = _mm512_cvtpd_ps((m) == 16 ? _mm512_loadu_pd((p) + 8 * q_) \
                                               : _mm512_maskz_loadu_pd((__mmask8)(all_ >> (8 * q_)), (p) + 8 * q_)); \
        __m512 a0_ = _mm512_insertf32x8(_mm512_castps256_ps512(h_[0]), h_[1], 1); \
        __m512 a1_ = _mm512_insertf32x8(_mm512_castps256_ps512(h_[2]), h_[3], 1); \
        __m512 a2_ = _mm512_insertf32x8(_mm512_castps256_ps512(h_[4]), h_[5], 1); \
        XYZ_OF3(a0_, a1_, a2_, out); \
        (void)(live); \
    } while (0)
#define IREDUCE_MAX _mm512_reduce_max_epi32
#define IOR _mm512_or_si512
#define IXOR _mm512_xor_si512
#define FLOOR(x) _mm512_roundscale_ps(x, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC)
#define MALL ((__mmask16)0xFFFF)
#define MFROMBITS(b) ((__mmask16)(b))

/* F[k] (k < 12) of every lane from the 12-float rows tab + 12 d (rows of the inactive lanes too: give
 * them a valid d): per lane three 16-byte loads, each block of four floats transposed 4 x 4 within the
 * 128-bit lanes; register lane 4 i + q is built from the rows of lanes q + 4 i, which that transpose
 * puts back in order (a group's rows meet about 7 bins per 16 lanes on the city's bench rays, so rows
 * are read per lane) */
#define GATHER_ROWS12(tab, d, m, F) do { \
        int li_[16]; \
        _mm512_storeu_si512((void *)li_, d); \
        for (int j_ = 0; j_ < 3; j_++) { \
            __m512 z_[4]; \
            for (int q_ = 0; q_ < 4; q_++) { \
                __m512 z = _mm512_castps128_ps512(_mm_loadu_ps((tab) + 12 * (size_t)li_[q_] + 4 * j_)); \
                z = _mm512_insertf32x4(z, _mm_loadu_ps((tab) + 12 * (size_t)li_[q_ + 4] + 4 * j_), 1); \
                z = _mm512_insertf32x4(z, _mm_loadu_ps((tab) + 12 * (size_t)li_[q_ + 8] + 4 * j_), 2); \
                z_[q_] = _mm512_insertf32x4(z, _mm_loadu_ps((tab) + 12 * (size_t)li_[q_ + 12] + 4 * j_), 3); \
            } \
            __m512d t0_ = _mm512_castps_pd(_mm512_unpacklo_ps(z_[0], z_[1])); \
            __m512d t1_ = _mm512_castps_pd(_mm512_unpackhi_ps(z_[0], z_[1])); \
            __m512d t2_ = _mm512_castps_pd(_mm512_unpacklo_ps(z_[2], z_[3])); \
            __m512d t3_ = _mm512_castps_pd(_mm512_unpackhi_ps(z_[2], z_[3])); \
            (F)[4 * j_] = _mm512_castpd_ps(_mm512_unpacklo_pd(t0_, t2_)); \
            (F)[4 * j_ + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(t0_, t2_)); \
            (F)[4 * j_ + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(t1_, t3_)); \
            (F)[4 * j_ + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(t1_, t3_)); \
        } \
        (void)(m); \
    } while (0)
