/* Undefines the vector API of simd_avx2.h / simd_avx512.h (and simd_x2.h over either), so the next instruction set can define it. */
#undef W
#undef V
#undef VI
#undef M
#undef X2_INLINE
#undef SUFFIX
#undef TARGET
#undef X2CAT_
#undef X2CAT
#undef X2N
#undef X2V
#undef X2VI
#undef X2M
#include "simd_undef_ops.h"
