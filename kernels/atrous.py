"""One iteration of the edge-avoiding à-trous wavelet filter (Dammertz et al. 2010; paper 004 §3.3).

Pure: arrays in, arrays out. Orchestration (iterations, σ per iteration, CPU row bands, device) lives in
:mod:`usdml.lighting.atrous`, which also documents the edge-stopping functions.
"""

from __future__ import annotations

import warp as wp

# forward only: nothing here is differentiated, and the adjoint code was most of the compile
# (cold cache, this CPU: 7.7 -> 2.6 s for CPU, 24 -> 1.9 s for CUDA)
wp.set_module_options({"enable_backward": False})


@wp.func
def bspline_tap(k: int) -> float:
    # 1D cubic B-spline h = [1/16, 1/4, 3/8, 1/4, 1/16], indexed by |k| in 0..2
    if k == 0:
        return 0.375
    if k == 1 or k == -1:
        return 0.25
    return 0.0625


@wp.kernel
def atrous_step(
    values: wp.array3d(dtype=float),        # (H, W, C) input of this iteration
    normal: wp.array2d(dtype=wp.vec3),      # (H, W) unit normals
    position: wp.array2d(dtype=wp.vec3),    # (H, W) world positions (already re-centred by the caller)
    valid: wp.array2d(dtype=wp.uint8),      # (H, W) 1 where the pixel has geometry
    inv_scale: wp.array(dtype=float),       # (C,) per-channel scale of value differences
    step: int,                              # tap spacing 2^i in pixels
    sigma_normal: float,                    # w_n = max(0, n_p·n_q)^sigma_normal; 0 disables
    inv_sigma_position2: float,             # w_x = exp(-|x_p - x_q|² · this); 0 disables
    inv_sigma_value2: float,                # w_v = exp(-Σ_c ((v_p - v_q)_c · inv_scale_c)² · this); 0 disables
    row0: int,                              # first image row of this launch (CPU row bands)
    out: wp.array3d(dtype=float),           # (H, W, C) output; only rows row0 .. row0 + dim[0] are written
):
    i, x = wp.tid()
    y = row0 + i
    h = values.shape[0]
    w = values.shape[1]
    nc = values.shape[2]

    if valid[y, x] == wp.uint8(0):
        for c in range(nc):
            out[y, x, c] = values[y, x, c]
        return

    n_p = normal[y, x]
    x_p = position[y, x]
    for c in range(nc):
        out[y, x, c] = 0.0
    wsum = float(0.0)

    for dy in range(-2, 3):
        yq = y + dy * step
        if yq < 0 or yq >= h:
            continue
        hy = bspline_tap(dy)
        for dx in range(-2, 3):
            xq = x + dx * step
            if xq < 0 or xq >= w:
                continue
            if valid[yq, xq] == wp.uint8(0):
                continue
            # one exp per tap: max(0, n·n')^σ_n · exp(-a) = exp(σ_n log(n·n') - a)
            logw = float(0.0)
            if sigma_normal > 0.0:
                cos_nq = wp.dot(n_p, normal[yq, xq])
                if cos_nq <= 0.0:
                    continue
                logw = sigma_normal * wp.log(cos_nq)
            d = x_p - position[yq, xq]
            dv2 = float(0.0)
            for c in range(nc):
                dv = (values[y, x, c] - values[yq, xq, c]) * inv_scale[c]
                dv2 += dv * dv
            wgt = hy * bspline_tap(dx) * wp.exp(logw - wp.dot(d, d) * inv_sigma_position2 - dv2 * inv_sigma_value2)
            if wgt > 0.0:
                wsum += wgt
                for c in range(nc):
                    out[y, x, c] = out[y, x, c] + wgt * values[yq, xq, c]

    # the centre tap weighs 9/64 for a unit normal; a zero normal can leave nothing: keep the input
    if wsum > 0.0:
        inv = 1.0 / wsum
        for c in range(nc):
            out[y, x, c] = out[y, x, c] * inv
    else:
        for c in range(nc):
            out[y, x, c] = values[y, x, c]
