/* The vector API of the SIMD bodies for AVX-512 (16 lanes): W, SUFFIX, TARGET, V / VI / M and their operations.
 * Used by kernels/svoq.c (kernels/voxelq.c uses simd_avx512x2.h): define, include the SIMD body, then simd_undef.h. */
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
#define IOR _mm512_or_si512
#define IXOR _mm512_xor_si512
#define FLOOR(x) _mm512_roundscale_ps(x, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC)
#define MALL ((__mmask16)0xFFFF)
#define MFROMBITS(b) ((__mmask16)(b))

