"""Where in each pixel a frame's primary rays go: correlated multi-jittered sub-pixel positions, one array per pass,
also the stratified square the lens points are mapped from (:mod:`usdml.render.lens`)."""

from __future__ import annotations

import numpy as np

#: the sub-pixel positions' stream of random numbers
PIXEL_STREAM = 0x5A4D


def pixel_offsets(width: int, height: int, samples: int, seed: int, stream: int = PIXEL_STREAM,
                  shifted: bool = False):
    """Yield ``samples`` (an s × s square) arrays ``(H·W, 2)`` float64 of where in each pixel a
    primary ray goes, ``(x right, y down)`` in [0, 1), one array per pass.

    Correlated multi-jittered sampling (Kensler 2013, after Chiu, Shirley and Wang 1994): pass
    ``k = (i, j)`` puts one ray in cell (i, j) of an s × s grid over the pixel, and the rays' x (and
    y) also fall one in each of the s² thin columns (rows), so a vertical or horizontal edge is
    resolved in s² steps, not s; per pixel a random permutation of the sub-columns (sub-rows) and a
    jitter inside them, drawn from ``seed`` and ``stream`` (and the pass for the jitter). ``shifted``: pass
    ``k`` of a pixel takes cell ``(k + c) mod samples`` with ``c`` seeded per pixel, so what else varies by pass
    (the pass's time under motion blur, its lens point) is paired with the cells differently in every pixel. A
    single sample is the pixel centre, unjittered.
    """
    s = round(samples ** 0.5)
    n = width * height
    if s == 1:
        yield np.full((n, 2), 0.5)
        return
    rng = np.random.default_rng([seed, stream])
    perm_x = np.argsort(rng.random((n, s)), axis=1)     # sub-column of the ray in grid row j
    perm_y = np.argsort(rng.random((n, s)), axis=1)     # sub-row of the ray in grid column i
    shift = rng.integers(0, samples, n) if shifted else 0
    rows = np.arange(n)
    for k in range(samples):
        m = (k + shift) % samples
        i, j = m % s, m // s
        jitter = np.random.default_rng([seed, stream, k]).random((n, 2))
        x = (i + (perm_x[rows, j] + jitter[:, 0]) / s) / s
        y = (j + (perm_y[rows, i] + jitter[:, 1]) / s) / s
        yield np.stack([x, y], axis=1)
