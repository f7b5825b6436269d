/* Which SIMD width a compiled kernel may use on this CPU, shared by kernels/voxel/voxelq.c and kernels/svo/svoq.c:
 * 16 (AVX-512 F/DQ/VL/BW), 8 (AVX2 and FMA) or 1 (plain C), for a request ``kernel``: 0 the widest
 * this CPU has, 1 scalar, 2 at most AVX2 (usdml.visibility.voxel.native.ISAS). */
#ifndef USDML_SIMD_PICK_H
#define USDML_SIMD_PICK_H

static inline int simd_lanes(int kernel) {
#if defined(__x86_64__) || defined(_M_X64)
    __builtin_cpu_init();
    if (kernel == 0 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
        __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bw"))
        return 16;
    if (kernel != 1 && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return 8;
#endif
    (void)kernel;
    return 1;
}

#endif
