/* The vector API of the SIMD bodies for AVX2 (8 lanes): W, SUFFIX, TARGET, V / VI / M and their operations.
 * Shared by kernels/voxel/voxelq.c (doubled by simd_x2.h) and kernels/svo/svoq.c: define, include the SIMD body, then simd_undef.h. */
/* AVX2: masks are float vectors of all-ones / zero lanes */
#define W 8
#define SUFFIX(f) f##_avx2
#define TARGET __attribute__((target("avx2,fma")))
typedef __m256 V;
typedef __m256i VI;
typedef __m256 M;
#define SET _mm256_set1_ps
#define ISET _mm256_set1_epi32
#define ADD _mm256_add_ps
#define SUB _mm256_sub_ps
#define MUL _mm256_mul_ps
#define DIV _mm256_div_ps
/* 1 / x to about 23 bits: the 12-bit estimate and one Newton step */
#define RCP(x) ({ V x_ = (x), r_ = _mm256_rcp_ps(x_); _mm256_mul_ps(r_, _mm256_fnmadd_ps(x_, r_, _mm256_set1_ps(2.0f))); })
#define FMA _mm256_fmadd_ps
#define MIN _mm256_min_ps
#define MAX _mm256_max_ps
#define SQRT _mm256_sqrt_ps
#define ABS(x) _mm256_andnot_ps(_mm256_set1_ps(-0.0f), x)
#define LT(a, b) _mm256_cmp_ps(a, b, _CMP_LT_OQ)
#define LE(a, b) _mm256_cmp_ps(a, b, _CMP_LE_OQ)
#define GT(a, b) _mm256_cmp_ps(a, b, _CMP_GT_OQ)
#define GE(a, b) _mm256_cmp_ps(a, b, _CMP_GE_OQ)
#define EQ(a, b) _mm256_cmp_ps(a, b, _CMP_EQ_OQ)
#define SEL(m, a, b) _mm256_blendv_ps(b, a, m)
#define SELI(m, a, b) _mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(b), _mm256_castsi256_ps(a), m))
#define MAND _mm256_and_ps
#define MOR _mm256_or_ps
#define MANDN _mm256_andnot_ps
#define MNONE _mm256_setzero_ps()
#define MBITS(m) ((unsigned)_mm256_movemask_ps(m))
#define IADD _mm256_add_epi32
#define ISUB _mm256_sub_epi32
#define IMUL _mm256_mullo_epi32
#define IMIN _mm256_min_epi32
#define IMAX _mm256_max_epi32
#define IAND _mm256_and_si256
#define ISRL(a, n) _mm256_srl_epi32(a, _mm_cvtsi32_si128(n))
#define ISLL(a, n) _mm256_sll_epi32(a, _mm_cvtsi32_si128(n))
#define ISRLV _mm256_srlv_epi32
#define ISLLV _mm256_sllv_epi32
#define IGT(a, b) _mm256_castsi256_ps(_mm256_cmpgt_epi32(a, b))
#define IEQ(a, b) _mm256_castsi256_ps(_mm256_cmpeq_epi32(a, b))
#define IGE(a, b) _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(b, a)), _mm256_castsi256_ps(_mm256_set1_epi32(-1)))
#define INZ(x) _mm256_andnot_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(x, _mm256_setzero_si256())), _mm256_castsi256_ps(_mm256_set1_epi32(-1)))
#define CVTT _mm256_cvttps_epi32
#define CVTF _mm256_cvtepi32_ps
#define GATHER_I(p, i) _mm256_i32gather_epi32((const int *)(p), i, 4)
#define GATHER_F(p, i) _mm256_i32gather_ps(p, i, 4)
#define MGATHER_I(p, i, m) _mm256_mask_i32gather_epi32(_mm256_setzero_si256(), (const int *)(p), i, _mm256_castps_si256(m), 4)
#define LOAD _mm256_loadu_ps
#define MLOAD(p, m) _mm256_maskload_ps(p, _mm256_castps_si256(m))
#define ILOAD(p) _mm256_loadu_si256((const __m256i *)(p))
#define MILOAD(p, m) _mm256_maskload_epi32((const int *)(p), _mm256_castps_si256(m))
#define STORE _mm256_storeu_ps
#define ISTORE(p, v) _mm256_storeu_si256((__m256i *)(p), v)
#define IOTA _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)
/* the lanes of m stored one after another from p; returns how many */
#define COMPRESS_F(p, m, v) ({ float t_[8]; _mm256_storeu_ps(t_, v); int c_ = 0; \
        for (unsigned b_ = MBITS(m); b_; b_ &= b_ - 1) { (p)[c_++] = t_[__builtin_ctz(b_)]; } c_; })
#define COMPRESS_I(p, m, v) ({ int t_[8]; _mm256_storeu_si256((__m256i *)t_, v); int c_ = 0; \
        for (unsigned b_ = MBITS(m); b_; b_ &= b_ - 1) { (p)[c_++] = t_[__builtin_ctz(b_)]; } c_; })
/* x, y, z of m <= 8 consecutive float triples */
#define LOAD_XYZ(p, m, live, out) do { \
        VI i3_ = _mm256_mullo_epi32(IOTA, _mm256_set1_epi32(3)); \
        for (int k_ = 0; k_ < 3; k_++) \
            (out)[k_] = _mm256_mask_i32gather_ps(_mm256_setzero_ps(), (p) + k_, i3_, live, 4); \
    } while (0)
/* the same from double triples, rounded to float: per coordinate two 64-bit gathers of 4 lanes */
#define LOAD_XYZ64(p, m, live, out) do { \
        __m128i i3_ = _mm_mullo_epi32(_mm_setr_epi32(0, 1, 2, 3), _mm_set1_epi32(3)); \
        __m256i li_ = _mm256_castps_si256(live); \
        __m256d mlo_ = _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm256_castsi256_si128(li_))); \
        __m256d mhi_ = _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm256_extracti128_si256(li_, 1))); \
        for (int k_ = 0; k_ < 3; k_++) { \
            __m128 lo_ = _mm256_cvtpd_ps(_mm256_mask_i32gather_pd(_mm256_setzero_pd(), (p) + k_, i3_, mlo_, 8)); \
            __m128 hi_ = _mm256_cvtpd_ps(_mm256_mask_i32gather_pd(_mm256_setzero_pd(), (p) + 12 + k_, i3_, mhi_, 8)); \
            (out)[k_] = _mm256_set_m128(hi_, lo_); \
        } \
        (void)(m); \
    } while (0)
/* the largest of the 8 lanes */
#define IREDUCE_MAX(v) ({ __m256i v_ = (v), m_ = _mm256_max_epi32(v_, _mm256_permute2x128_si256(v_, v_, 1)); \
        m_ = _mm256_max_epi32(m_, _mm256_shuffle_epi32(m_, _MM_SHUFFLE(1, 0, 3, 2))); \
        m_ = _mm256_max_epi32(m_, _mm256_shuffle_epi32(m_, _MM_SHUFFLE(2, 3, 0, 1))); \
        _mm256_cvtsi256_si32(m_); })
#define IOR _mm256_or_si256
#define IXOR _mm256_xor_si256
#define FLOOR _mm256_floor_ps
#define MALL _mm256_castsi256_ps(_mm256_set1_epi32(-1))
/* the mask whose lane k is bit k of the integer b */
#define MFROMBITS(b) _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_and_si256(_mm256_set1_epi32((int)(b)), \
        _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128)), _mm256_setzero_si256()))

/* F[k] (k < 12) of every lane from the 12-float rows tab + 12 d (rows of the inactive lanes too: give
 * them a valid d): per lane three 16-byte loads, each block of four floats transposed 4 x 4 within the
 * 128-bit lanes; register lane 4 i + q is built from the rows of lanes q + 4 i, which that transpose
 * puts back in order (this beat twelve 64-bit gathers a little: 28.2 -> 25.7 ns a query on the city's bench
 * rays, one thread) */
#define GATHER_ROWS12(tab, d, m, F) do { \
        int li_[8]; \
        _mm256_storeu_si256((__m256i *)li_, d); \
        for (int j_ = 0; j_ < 3; j_++) { \
            __m256 z_[4]; \
            for (int q_ = 0; q_ < 4; q_++) \
                z_[q_] = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps((tab) + 12 * (size_t)li_[q_] + 4 * j_)), \
                                              _mm_loadu_ps((tab) + 12 * (size_t)li_[q_ + 4] + 4 * j_), 1); \
            __m256d t0_ = _mm256_castps_pd(_mm256_unpacklo_ps(z_[0], z_[1])); \
            __m256d t1_ = _mm256_castps_pd(_mm256_unpackhi_ps(z_[0], z_[1])); \
            __m256d t2_ = _mm256_castps_pd(_mm256_unpacklo_ps(z_[2], z_[3])); \
            __m256d t3_ = _mm256_castps_pd(_mm256_unpackhi_ps(z_[2], z_[3])); \
            (F)[4 * j_] = _mm256_castpd_ps(_mm256_unpacklo_pd(t0_, t2_)); \
            (F)[4 * j_ + 1] = _mm256_castpd_ps(_mm256_unpackhi_pd(t0_, t2_)); \
            (F)[4 * j_ + 2] = _mm256_castpd_ps(_mm256_unpacklo_pd(t1_, t3_)); \
            (F)[4 * j_ + 3] = _mm256_castpd_ps(_mm256_unpackhi_pd(t1_, t3_)); \
        } \
        (void)(m); \
    } while (0)
