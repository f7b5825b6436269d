"""Warp kernel: the exact backend's shadow-ray set-up (:meth:`usdml.visibility.exact.ExactBackend.shadow_rays`)
compiled, bit for bit the same float32 arithmetic.

The NumPy rule made ~60 passes over each chunk (eps at both ends, the lift along the normal, the
re-aim, the normalisation): on the city bench (7.3 M rays) 0.25 s of a 1.3 s query, 28 % on top of
Embree. A per-element Warp kernel did it in 25 ns per ray (each ray is one long chain of dependent
``sqrt`` and divisions); this C++ loop over blocks of 64 rays, transposed into columns, lets the
compiler run four rays at a time (SSE2, which every x86-64 has) in 10-14 ns per ray on one core.

Exactness: the same operations in the same order as the NumPy rule (sums left to right, ``1 / x``
then a product where NumPy does that), no fused multiply-add (``fuse_fp`` off, and the generic
x86-64 target has none), ``max`` that lets NaN through as ``np.maximum`` does. IEEE float32 ``+ - *
/ sqrt`` are correctly rounded, so every output equals NumPy's; ``tests/test_visibility_exact.py`` checks it on
edge cases (zero normals, distant rows, zero-length segments) and random rays.
"""

import warp as wp

# forward only; fuse_fp off: a fused multiply-add would round differently from NumPy's ``a * b + c``
wp.set_module_options({"enable_backward": False, "fuse_fp": False, "optimization_level": 3})

#: rays per block of the native loop (columns of this many floats stay in L1)
BLOCK = 64

_SNIPPET = r"""
    const double* po = (const double*)origins.data;
    const double* pt = (const double*)targets.data;
    const float* pn = (const float*)normals.data;
    const bool* pf = (const bool*)distant.data;
    float* ro = (float*)ray_o.data;
    float* rd = (float*)ray_d.data;
    float* tf = (float*)tfar.data;
    const float E = epsilon, M = margin, INF = infinity;
    const int B = BLOCK_SIZE;
    float P[3][B], L[3][B], N[3][B], O[3][B], D[3][B], T[B];
    bool F[B];
    for (int base = first; base < end; base += B) {
        const int m = end - base < B ? end - base : B;
        for (int j = 0; j < m; ++j) {
            const long long i = (long long)base + j;
            for (int k = 0; k < 3; ++k) {
                P[k][j] = (float)po[3 * i + k];
                L[k][j] = (float)pt[3 * i + k];
                N[k][j] = has_normals ? pn[3 * i + k] : 0.0f;
            }
            F[j] = has_distant ? pf[i] : false;
        }
        for (int j = 0; j < m; ++j) {
            const float p0 = P[0][j], p1 = P[1][j], p2 = P[2][j];
            const float l0 = L[0][j], l1 = L[1][j], l2 = L[2][j];
            const bool far = F[j];
            /* eps = max(epsilon, |x|_max * margin); NaN wins as in np.maximum */
            const float ap0 = p0 < 0 ? -p0 : p0, ap1 = p1 < 0 ? -p1 : p1, ap2 = p2 < 0 ? -p2 : p2;
            float ep = (ap0 != ap0 || ap0 > ap1) ? ap0 : ap1;
            ep = (ep != ep || ep > ap2) ? ep : ap2;
            ep = ep * M;
            ep = (ep != ep || ep > E) ? ep : E;
            const float al0 = l0 < 0 ? -l0 : l0, al1 = l1 < 0 ? -l1 : l1, al2 = l2 < 0 ? -l2 : l2;
            float el = (al0 != al0 || al0 > al1) ? al0 : al1;
            el = (el != el || el > al2) ? el : al2;
            el = el * M;
            el = (el != el || el > E) ? el : E;
            const float d0 = far ? l0 : l0 - p0, d1 = far ? l1 : l1 - p1, d2 = far ? l2 : l2 - p2;
            const float len = wp::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
            float o0, o1, o2, e0, e1, e2, len2, t;
            if (has_normals) {
                const float n0 = N[0][j], n1 = N[1][j], n2 = N[2][j];
                const float nn = n0 * n0 + n1 * n1 + n2 * n2;
                const bool hn = nn > 0.0f;
                /* lift by eps along the normal, flipped to the light's side */
                float lift = hn ? ep / wp::sqrt(nn) : 0.0f;
                lift = (n0 * d0 + n1 * d1 + n2 * d2) < 0.0f ? -lift : lift;
                o0 = p0 + lift * n0; o1 = p1 + lift * n1; o2 = p2 + lift * n2;
                /* zero normal: step along the ray instead */
                const bool bare = !hn && len > 0.0f;
                const float s = ep / len;
                o0 = bare ? o0 + s * d0 : o0; o1 = bare ? o1 + s * d1 : o1; o2 = bare ? o2 + s * d2 : o2;
                e0 = far ? d0 : l0 - o0; e1 = far ? d1 : l1 - o1; e2 = far ? d2 : l2 - o2;
                len2 = wp::sqrt(e0 * e0 + e1 * e1 + e2 * e2);
                t = hn ? len2 - el : len - ep - el;
            } else {
                const float inv = len > 0.0f ? 1.0f / len : 0.0f;
                const float s = ep * inv;
                o0 = p0 + s * d0; o1 = p1 + s * d1; o2 = p2 + s * d2;
                e0 = d0; e1 = d1; e2 = d2;
                len2 = len;
                t = len - ep - el;
            }
            const float sc = len2 > 0.0f ? 1.0f / len2 : 0.0f;
            t = far ? INF : t;
            t = (!(t > 0.0f) || !(len > 0.0f)) ? 0.0f : t;
            O[0][j] = o0; O[1][j] = o1; O[2][j] = o2;
            D[0][j] = e0 * sc; D[1][j] = e1 * sc; D[2][j] = e2 * sc;
            T[j] = t;
        }
        for (int j = 0; j < m; ++j) {
            const long long i = (long long)base + j - first;
            for (int k = 0; k < 3; ++k) {
                ro[3 * i + k] = O[k][j];
                rd[3 * i + k] = D[k][j];
            }
            tf[i] = T[j];
        }
    }
""".replace("BLOCK_SIZE", str(BLOCK))


def _reading(snippet: str, origins: str, targets: str) -> str:
    """The rule reading ``origins`` and ``targets`` as C type ``float`` or ``double`` (float32 ->
    float64 -> float32 is exact: the same rays), so float32 targets (the LGH's shadow rays, 13 M
    at 256 px: 317 MB as float64) are not copied to float64 first."""
    return snippet.replace("const double* po = (const double*)origins.data;",
                           f"const {origins}* po = (const {origins}*)origins.data;").replace(
        "const double* pt = (const double*)targets.data;", f"const {targets}* pt = (const {targets}*)targets.data;")


@wp.func_native(_SNIPPET)
def _rays(origins: wp.array(dtype=wp.vec3d), targets: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3f),
          distant: wp.array(dtype=wp.bool), has_normals: int, has_distant: int, epsilon: float, margin: float,
          first: int, end: int, ray_o: wp.array(dtype=wp.vec3f), ray_d: wp.array(dtype=wp.vec3f),
          tfar: wp.array(dtype=float), infinity: float):
    ...


@wp.kernel
def shadow_rays(origins: wp.array(dtype=wp.vec3d), targets: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3f),
                distant: wp.array(dtype=wp.bool), has_normals: int, has_distant: int, epsilon: float, margin: float,
                first: int, end: int, ray_o: wp.array(dtype=wp.vec3f), ray_d: wp.array(dtype=wp.vec3f),
                tfar: wp.array(dtype=float)):
    """Rays of segments ``first .. end - 1`` (one thread, CPU): ``(n, 3)`` float64 ``origins`` P and
    ``targets`` L (unit directions toward the light on ``distant`` rows), float32 ``normals`` (read
    when ``has_normals``), bool ``distant`` (read when ``has_distant``), float32 ``epsilon`` (scene
    units) and ``margin`` (relative); writes ``ray_o``, ``ray_d`` (unit) and ``tfar`` (0: do not
    trace) at rows ``0 .. end - first - 1``, the exact backend's rule."""
    _rays(origins, targets, normals, distant, has_normals, has_distant, epsilon, margin, first, end, ray_o, ray_d, tfar,
          wp.inf)


@wp.func_native(_reading(_SNIPPET, "double", "float"))
def _rays_df(origins: wp.array(dtype=wp.vec3d), targets: wp.array(dtype=wp.vec3f), normals: wp.array(dtype=wp.vec3f),
             distant: wp.array(dtype=wp.bool), has_normals: int, has_distant: int, epsilon: float, margin: float,
             first: int, end: int, ray_o: wp.array(dtype=wp.vec3f), ray_d: wp.array(dtype=wp.vec3f),
             tfar: wp.array(dtype=float), infinity: float):
    ...


@wp.kernel
def shadow_rays_df(origins: wp.array(dtype=wp.vec3d), targets: wp.array(dtype=wp.vec3f),
                   normals: wp.array(dtype=wp.vec3f), distant: wp.array(dtype=wp.bool), has_normals: int,
                   has_distant: int, epsilon: float, margin: float, first: int, end: int,
                   ray_o: wp.array(dtype=wp.vec3f), ray_d: wp.array(dtype=wp.vec3f), tfar: wp.array(dtype=float)):
    """:func:`shadow_rays` of float64 ``origins`` and float32 ``targets`` (the same rays)."""
    _rays_df(origins, targets, normals, distant, has_normals, has_distant, epsilon, margin, first, end, ray_o, ray_d,
             tfar, wp.inf)
