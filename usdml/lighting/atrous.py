"""Edge-avoiding à-trous wavelet filter for noisy shadow images (paper 004 §3.3; Dammertz et al. 2010).

Paper 004 estimates each pixel's shadows from a few stochastic shadow rays and removes the resulting
noise with the wavelet filter of Dammertz et al. 2010 before using the result as a shadow-ratio
estimator (Heitz et al. 2018). Filter the shadowed and the unshadowed estimates together, as the
channels of one ``values`` image: every channel of a pixel gets the same weights, so their ratio stays
a weighted ratio of the same neighbourhood (and ≤ 1 where shadowed ≤ unshadowed).

The filter
----------
Iteration i = 0 .. iterations−1 convolves with the 5×5 cubic B-spline ``h = [1, 4, 6, 4, 1] / 16``
(outer product) whose taps are spread ``2^i`` pixels apart ("à trous": with holes), so five iterations
reach ±62 pixels for the cost of 5 × 25 taps. Each tap q of pixel p weighs

    w(p, q) = h(dy) h(dx) · w_n · w_x · w_v,     v'_p = Σ_q w(p, q) v_q / Σ_q w(p, q)

with the edge-stopping functions

* normal:   ``w_n = max(0, n_p · n_q) ^ sigma_normal`` (the power form of Schied et al. 2017 (SVGF),
  default 128, rather than Dammertz's ``exp(−|n_p − n_q|² / σ_n²)``: it is exactly 0 across creases of
  90° or more, and a single parameter with a known default). A tilt of 10° keeps 14 % of the weight;
  ``sigma_normal = 0`` disables the term.
* position: ``w_x = exp(−|x_p − x_q|² / σ_x,i²)`` with ``σ_x,i = sigma_position · footprint · 2^i``,
  where ``footprint`` is the median world distance between horizontally or vertically adjacent valid
  pixels (world units per pixel; pass it to fix it, e.g. from the camera). σ_x grows with the step,
  so a tap at its nominal offset on a surface facing the camera keeps the same weight at every level
  (with a σ_x fixed in world units, the coarse levels, whose taps are 16–32 pixels away, would do
  nothing); a depth gap of many footprints still cuts the weight: at the default 2 and step 16, a gap of
  64 footprints (an object 14 % of the depth in front of another at 512 px and 60° field of view) keeps
  exp(−4) at most.
* value:    ``w_v = exp(−d_v² / σ_v,i²)`` with ``σ_v,i = sigma_value · 2^−i`` (halved every iteration,
  as in Dammertz et al.: later levels see less noise, so they may stop at smaller differences) and
  ``d_v² = mean_c ((v_p,c − v_q,c) / s_c)²``, ``s_c`` the mean |v| of channel c over valid pixels, so
  sigma_value is relative and the same default serves visibility fractions and radiance. The default 4
  lets a 1-sample (0 / 1) shadow estimate be smoothed at the first levels (a 0 against a 1 at mean 0.5
  is d_v = 2: weight exp(−1/4) at level 0) while a true shadow edge stops bleeding from level 2 on.
  ``sigma_value = inf`` disables the term (a filter guided by the G-buffer alone).

Pixels where ``valid`` is False (no geometry) are copied unchanged and are never taps; taps outside the
image are skipped (the weights are renormalised), so nothing leaks in from the border or the background.

Devices and threads
-------------------
One iteration is one Warp kernel (:func:`usdml.kernels.atrous.atrous_step`). On ``cuda`` each iteration is
one launch. On ``cpu`` it is the same step in C (``kernels/lgh/lghq.c``'s ``lghq_atrous_step``, about a quarter
of the Warp kernel's time a tap on this CPU) where that extension is built, else the Warp kernel (Warp
runs a CPU launch on one thread); either way the image is split into ``bands`` row bands (default: one per
core), run concurrently from a thread pool (both let go of the GIL); every band reads the whole previous
iteration and writes only its own rows, and the bands of one iteration finish before the next starts.

Interleaved sampling (paper 004 §4)
-----------------------------------
To cut the shadow rays per pixel by n², split the frame into an n×n pattern of tiles: pixel (y, x)
belongs to tile ``t = (y % n) · n + (x % n)`` (:func:`tile_index`) and evaluates only the lights whose
index ``l`` has ``l % n² == t``, scaled by n² (an unbiased estimate of the sum over all lights, since
each light is in exactly one of the n² subsets). Neighbouring pixels then see different lights, a
structured noise of period n that the à-trous filter removes (its taps at steps ≥ n fall on every
tile). A renderer that prefers to work per tile, with contiguous tiles (each a coherent sub-image that
sees one light subset, as in the paper's GPU implementation), calls :func:`deinterleave` on its
G-buffer, shades tile ``t`` with light subset ``t``, and puts the tiles back with :func:`interleave`
before filtering.
"""

from __future__ import annotations

import math

import numpy as np

from usdml.parallel import cpu_workers, run_bands

SIGMA_NORMAL = 128.0    # Schied et al. 2017
SIGMA_POSITION = 2.0    # × median pixel footprint × 2^i
SIGMA_VALUE = 4.0       # × per-channel mean |value|, × 2^-i (Dammertz et al. 2010)
ITERATIONS = 5          # steps 1, 2, 4, 8, 16 (Dammertz et al. 2010)

_H = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0


# ---------------------------------------------------------------------------------------------------------
# parameters shared by the Warp path and the NumPy reference

def _as_channels(values: np.ndarray) -> np.ndarray:
    if values.ndim == 2:
        return values[:, :, None]
    if values.ndim == 3:
        return values
    raise ValueError(f"values must be (H, W) or (H, W, C), got shape {values.shape}")


def _check(values: np.ndarray, normal: np.ndarray, position: np.ndarray, valid: np.ndarray,
           iterations: int) -> None:
    hw = values.shape[:2]
    if normal.shape != (*hw, 3):
        raise ValueError(f"normal must be (H, W, 3) = {(*hw, 3)}, got {normal.shape}")
    if position.shape != (*hw, 3):
        raise ValueError(f"position must be (H, W, 3) = {(*hw, 3)}, got {position.shape}")
    if valid.shape != hw:
        raise ValueError(f"valid must be (H, W) = {hw}, got {valid.shape}")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")


def pixel_footprint(position: np.ndarray, valid: np.ndarray) -> float:
    """Median world distance between horizontally or vertically adjacent valid pixels.

    ``position`` (H, W, 3) world units, ``valid`` (H, W) bool. Returns world units per pixel, or 0.0 where
    no two adjacent pixels are valid (the position term is then disabled).
    """
    p = np.asarray(position, np.float64)
    v = np.asarray(valid, bool)
    dx = np.linalg.norm(p[:, 1:] - p[:, :-1], axis=-1)[v[:, 1:] & v[:, :-1]]
    dy = np.linalg.norm(p[1:] - p[:-1], axis=-1)[v[1:] & v[:-1]]
    d = np.concatenate([dx, dy])
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else 0.0


def _channel_inv_scale(v: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(C,) 1 / mean |v_c| over valid pixels, divided by sqrt(C) so that d_v² is a mean over channels."""
    c = v.shape[2]
    if not valid.any():
        return np.zeros(c, np.float64)
    mean = np.abs(v[valid].astype(np.float64)).mean(axis=0)
    inv = np.where(mean > 0, 1.0 / np.where(mean > 0, mean, 1.0), 0.0)
    return inv / math.sqrt(c)


def _level_params(i: int, sigma_position: float, footprint: float, sigma_value: float) -> tuple[float, float]:
    """(1 / σ_x,i², 1 / σ_v,i²) for iteration i; 0 disables a term."""
    sx = sigma_position * footprint * 2.0 ** i
    sv = sigma_value * 2.0 ** -i
    inv_sx2 = 1.0 / (sx * sx) if math.isfinite(sx) and sx > 0 else 0.0
    inv_sv2 = 1.0 / (sv * sv) if math.isfinite(sv) and sv > 0 else 0.0
    return inv_sx2, inv_sv2


def _prepare(values, normal, position, valid, iterations, footprint):
    values = np.asarray(values)
    normal = np.asarray(normal)
    position = np.asarray(position)
    valid = np.asarray(valid, bool)
    _check(values, normal, position, valid, iterations)
    v = _as_channels(values)
    if footprint is None:
        footprint = pixel_footprint(position, valid)
    # re-centre in float64 before any float32 cast: differences of large world coordinates keep their digits
    origin = position[valid].astype(np.float64).mean(axis=0) if valid.any() else np.zeros(3)
    return values, v, normal, position.astype(np.float64) - origin, valid, float(footprint)


# ---------------------------------------------------------------------------------------------------------
# Warp

def atrous_filter(values: np.ndarray, normal: np.ndarray, position: np.ndarray, valid: np.ndarray,
                  iterations: int = ITERATIONS, sigma_normal: float = SIGMA_NORMAL,
                  sigma_position: float = SIGMA_POSITION, sigma_value: float = SIGMA_VALUE,
                  device: str = "cpu", *, footprint: float | None = None,
                  bands: int | None = None, compiled: bool = True) -> np.ndarray:
    """Edge-avoiding à-trous filter of ``values`` guided by a G-buffer (see the module docstring).

    Parameters
    ----------
    values : (H, W) or (H, W, C) float
        Image to filter, e.g. shadowed and unshadowed estimates as channels (any units).
    normal : (H, W, 3) float
        Unit world (or camera) normals.
    position : (H, W, 3) float32 or float64
        World positions, world units.
    valid : (H, W) bool
        Pixels with geometry; the others are returned unchanged and never used as taps.
    iterations : int
        Number of levels; steps 1, 2, 4, … 2^(iterations−1) pixels.
    sigma_normal : float
        Exponent of ``max(0, n_p·n_q)``; 0 disables the normal term.
    sigma_position : float
        σ_x at level i in units of ``footprint · 2^i``; inf or 0 disables the position term.
    sigma_value : float
        σ_v at level i in units of each channel's mean |value|, times 2^−i; inf or 0 disables it.
    device : str
        Warp device: ``cpu``, ``cuda``, ``cuda:0`` ….
    footprint : float, optional
        World units per pixel; default :func:`pixel_footprint` of ``position``.
    bands : int, optional
        CPU only: row bands launched concurrently (default: one per core, ``usdml.parallel.cpu_workers``).
    compiled : bool
        CPU only: each iteration by ``kernels/lgh/lghq.c`` (``lghq_atrous_step``, the Warp kernel's weights in C)
        where that library is built; False: the Warp kernel.

    Returns
    -------
    (H, W) or (H, W, C) float32, the shape of ``values``.
    """
    from usdml.kernels import atrous as kernels
    from usdml.kernels import warp

    values, v, normal, pos, valid, footprint = _prepare(values, normal, position, valid, iterations, footprint)
    out_shape = values.shape
    if iterations == 0 or not valid.any():
        return values.astype(np.float32, copy=True)

    wp = warp()
    dev = wp.get_device(device)
    h, w, _ = v.shape
    if dev.is_cpu and compiled:
        from usdml.lighting.lgh import native as lgh_native

        if lgh_native.library() is not None:
            return _compiled_filter(v, normal, pos, valid, iterations, sigma_normal, sigma_position, sigma_value,
                                    footprint, cpu_workers(dev, bands)).reshape(out_shape)
    src = wp.array(np.ascontiguousarray(v, np.float32), dtype=float, device=dev)
    dst = wp.empty_like(src)
    n_wp = wp.array(np.ascontiguousarray(normal, np.float32), dtype=wp.vec3, device=dev)
    x_wp = wp.array(np.ascontiguousarray(pos, np.float32), dtype=wp.vec3, device=dev)
    valid_wp = wp.array(valid.astype(np.uint8), dtype=wp.uint8, device=dev)
    inv_scale = wp.array(_channel_inv_scale(v, valid).astype(np.float32), dtype=float, device=dev)

    bands = cpu_workers(dev, bands)
    # compile (or load from the kernel cache) once, before any thread launches
    wp.load_module(kernels, device=dev)

    def launch(i: int, a, b, r0: int, rows: int) -> None:
        inv_sx2, inv_sv2 = _level_params(i, sigma_position, footprint, sigma_value)
        wp.launch(kernels.atrous_step, dim=(rows, w), device=dev,
                  inputs=[a, n_wp, x_wp, valid_wp, inv_scale, 2 ** i, float(sigma_normal), inv_sx2, inv_sv2, r0],
                  outputs=[b])

    for i in range(iterations):
        # every band of level i is written before level i + 1 reads it
        run_bands(h, lambda r0, rows, i=i, a=src, b=dst: launch(i, a, b, r0, rows), bands, 1)
        src, dst = dst, src
    return src.numpy().reshape(out_shape)


def _compiled_filter(v: np.ndarray, normal: np.ndarray, pos: np.ndarray, valid: np.ndarray, iterations: int,
                     sigma_normal: float, sigma_position: float, sigma_value: float, footprint: float,
                     bands: int) -> np.ndarray:
    """:func:`atrous_filter`'s iterations on a CPU by ``lghq_atrous_step`` (row bands on the thread pool, every band
    of an iteration written before the next reads it): ``(H, W, C)`` float32. The Warp kernel cost about 50 ns a
    tap on this CPU (8 ms of a 96×54 frame's pass at 6 channels, two iterations)."""
    from usdml.lighting.lgh import native as lgh_native

    lib = lgh_native.library()
    h, w, c = v.shape
    src = np.array(v, np.float32, order="C")        # a copy: the iterations write into it, never into v
    dst = np.empty_like(src)
    n32 = np.ascontiguousarray(normal, np.float32)
    x32 = np.ascontiguousarray(pos, np.float32)
    ok = np.ascontiguousarray(valid, np.uint8)
    inv_scale = np.ascontiguousarray(_channel_inv_scale(v, valid), np.float32)
    for i in range(iterations):
        inv_sx2, inv_sv2 = _level_params(i, sigma_position, footprint, sigma_value)

        def band(r0, rows, a=src, b=dst, i=i, inv_sx2=inv_sx2, inv_sv2=inv_sv2):
            lib.lghq_atrous_step(a.ctypes.data, n32.ctypes.data, x32.ctypes.data, ok.ctypes.data,
                                 inv_scale.ctypes.data, h, w, c, 2 ** i, float(sigma_normal), inv_sx2, inv_sv2,
                                 r0, r0 + rows, b.ctypes.data)

        run_bands(h, band, bands, 1)
        src, dst = dst, src
    return src


# ---------------------------------------------------------------------------------------------------------
# NumPy reference (float64), for tests

def _shifted(a: np.ndarray, pad: int, dy: int, dx: int, h: int, w: int) -> np.ndarray:
    return a[pad + dy:pad + dy + h, pad + dx:pad + dx + w]


def atrous_filter_reference(values: np.ndarray, normal: np.ndarray, position: np.ndarray, valid: np.ndarray,
                            iterations: int = ITERATIONS, sigma_normal: float = SIGMA_NORMAL,
                            sigma_position: float = SIGMA_POSITION, sigma_value: float = SIGMA_VALUE,
                            *, footprint: float | None = None) -> np.ndarray:
    """The same filter as :func:`atrous_filter` in vectorised NumPy float64 (shifted views of padded arrays).

    Same parameters and shapes; returns float64 of the shape of ``values``.
    """
    values, v, normal, pos, valid, footprint = _prepare(values, normal, position, valid, iterations, footprint)
    h, w, _ = v.shape
    cur = v.astype(np.float64)
    n = normal.astype(np.float64)
    inv_scale = _channel_inv_scale(v, valid)
    for i in range(iterations):
        step = 2 ** i
        pad = 2 * step
        inv_sx2, inv_sv2 = _level_params(i, sigma_position, footprint, sigma_value)
        vp = np.pad(cur, ((pad, pad), (pad, pad), (0, 0)))
        np_ = np.pad(n, ((pad, pad), (pad, pad), (0, 0)))
        xp = np.pad(pos, ((pad, pad), (pad, pad), (0, 0)))
        okp = np.pad(valid, pad, constant_values=False)
        acc = np.zeros_like(cur)
        wsum = np.zeros((h, w))
        with np.errstate(invalid="ignore", over="ignore"):   # whatever invalid pixels hold is masked out
            for ky in range(-2, 3):
                for kx in range(-2, 3):
                    vq = _shifted(vp, pad, ky * step, kx * step, h, w)
                    nq = _shifted(np_, pad, ky * step, kx * step, h, w)
                    xq = _shifted(xp, pad, ky * step, kx * step, h, w)
                    okq = _shifted(okp, pad, ky * step, kx * step, h, w)
                    wgt = np.full((h, w), _H[ky + 2] * _H[kx + 2])
                    if sigma_normal > 0:
                        wgt = wgt * np.maximum(0.0, np.einsum("ijk,ijk->ij", n, nq)) ** sigma_normal
                    dx2 = np.sum((pos - xq) ** 2, axis=-1)
                    dv2 = np.sum(((cur - vq) * inv_scale) ** 2, axis=-1)
                    wgt = np.where(okq, wgt * np.exp(-dx2 * inv_sx2 - dv2 * inv_sv2), 0.0)
                    acc += wgt[..., None] * np.where(okq[..., None], vq, 0.0)
                    wsum += wgt
        keep = valid & (wsum > 0)
        nxt = cur.copy()
        nxt[keep] = acc[keep] / wsum[keep][:, None]
        cur = nxt
    return cur.reshape(values.shape)


# ---------------------------------------------------------------------------------------------------------
# interleaved sampling (paper 004 §4)

def tile_index(height: int, width: int, n: int) -> np.ndarray:
    """(height, width) int32: the interleaved tile of each pixel, ``(y % n) · n + (x % n)``, in 0 .. n²−1.

    A pixel of tile t shades the lights with ``index % n² == t``, scaled by n² (module docstring).
    """
    y, x = np.mgrid[0:height, 0:width]
    return ((y % n) * n + (x % n)).astype(np.int32)


def deinterleave(img: np.ndarray, n: int) -> np.ndarray:
    """(H, W, ...) -> (n², H/n, W/n, ...): tile ``t = ty · n + tx`` holds the pixels ``img[ty::n, tx::n]``.

    H and W must be multiples of n. Exact inverse of :func:`interleave`.
    """
    img = np.asarray(img)
    h, w = img.shape[:2]
    if n < 1 or h % n or w % n:
        raise ValueError(f"deinterleave: image {h}x{w} is not a multiple of n={n}; pad it to one")
    rest = img.shape[2:]
    a = img.reshape(h // n, n, w // n, n, *rest)
    a = np.moveaxis(a, (1, 3), (0, 1))      # (n, n, H/n, W/n, ...)
    return np.ascontiguousarray(a).reshape(n * n, h // n, w // n, *rest)


def interleave(tiles: np.ndarray, n: int) -> np.ndarray:
    """(n², h, w, ...) -> (n·h, n·w, ...): puts the tiles of :func:`deinterleave` back, pixel by pixel."""
    tiles = np.asarray(tiles)
    if n < 1 or tiles.ndim < 3 or tiles.shape[0] != n * n:
        raise ValueError(f"interleave: expected (n², h, w, ...) with n={n}, got {tiles.shape}")
    h, w = tiles.shape[1:3]
    rest = tiles.shape[3:]
    a = tiles.reshape(n, n, h, w, *rest)
    a = np.moveaxis(a, (0, 1), (1, 3))      # (h, n, w, n, ...)
    return np.ascontiguousarray(a).reshape(h * n, w * n, *rest)


__all__ = ["atrous_filter", "atrous_filter_reference", "pixel_footprint", "tile_index", "deinterleave",
           "interleave", "SIGMA_NORMAL", "SIGMA_POSITION", "SIGMA_VALUE", "ITERATIONS"]
