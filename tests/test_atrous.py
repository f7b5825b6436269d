"""Edge-avoiding à-trous filter (paper 004 §3.3): Warp kernel against the NumPy reference, edge stopping,
invalid pixels, and the interleaved-sampling helpers. Every Warp test runs once per device (cuda skipped
where there is none)."""

from __future__ import annotations

import numpy as np
import pytest

from usdml.lighting.atrous import (atrous_filter, atrous_filter_reference, deinterleave, interleave,
                                   pixel_footprint, tile_index)


def _gbuffer(h: int, w: int, rng: np.random.Generator, tilt: float = 0.15):
    """A bumpy plane z ≈ 0 seen from +Z: normals near +Z, positions on a 0.1-unit pixel grid far from the origin."""
    n = rng.normal(size=(h, w, 3)) * tilt + np.array([0.0, 0.0, 1.0])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    y, x = np.mgrid[0:h, 0:w]
    p = np.stack([x * 0.1, y * 0.1, rng.normal(size=(h, w)) * 0.03], axis=-1) + np.array([1e3, -2e3, 5e2])
    return n.astype(np.float32), p


def test_constant_image_unchanged(device):
    rng = np.random.default_rng(1)
    h, w = 20, 27
    n = rng.normal(size=(h, w, 3))                       # any normals, any positions
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    p = rng.normal(size=(h, w, 3)) * 10.0
    valid = rng.random((h, w)) > 0.25
    v = np.broadcast_to(np.array([0.3, 7.0], np.float32), (h, w, 2)).copy()
    out = atrous_filter(v, n.astype(np.float32), p, valid, device=device)
    np.testing.assert_allclose(out, v, rtol=1e-6)
    out1 = atrous_filter(np.full((h, w), 2.5, np.float32), n.astype(np.float32), p, valid, device=device)
    np.testing.assert_allclose(out1, 2.5, rtol=1e-6)


@pytest.mark.parametrize("channels", [None, 3])
@pytest.mark.parametrize("sigma_normal", [128.0, 8.0])
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "warp"])
def test_matches_numpy_reference(device, channels, sigma_normal, compiled):
    """On a CPU the step is kernels/lgh/lghq.c's where it is built (compiled) or the Warp kernel's; on CUDA Warp's."""
    rng = np.random.default_rng(2)
    h, w = 23, 37
    n, p = _gbuffer(h, w, rng)
    valid = rng.random((h, w)) > 0.2
    shape = (h, w) if channels is None else (h, w, channels)
    v = rng.random(shape).astype(np.float32)
    given = v.copy()
    ref = atrous_filter_reference(v, n, p, valid, sigma_normal=sigma_normal)
    assert np.abs(ref - v).max() > 0.1                   # it does filter
    for bands in (1, 3):
        out = atrous_filter(v, n, p, valid, sigma_normal=sigma_normal, device=device, bands=bands, compiled=compiled)
        assert out.shape == v.shape and out.dtype == np.float32
        np.testing.assert_allclose(out, ref, atol=1e-5)
        np.testing.assert_array_equal(v, given)          # the input is left as it was


def _corner(h: int, w: int, rng: np.random.Generator, sigma: float = 0.05):
    """Left half: a wall facing +X; right half: a floor facing +Y, meeting at a crease, 0.2 vs 0.8 plus noise."""
    y, x = np.mgrid[0:h, 0:w]
    left = x < w // 2
    s = 0.01
    p = np.where(left[..., None],
                 np.stack([np.zeros((h, w)), (w // 2 - x) * s, y * s], axis=-1),     # x = 0 plane
                 np.stack([(x - w // 2) * s, np.zeros((h, w)), y * s], axis=-1))      # y = 0 plane
    n = np.where(left[..., None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])).astype(np.float32)
    truth = np.where(left, 0.2, 0.8)
    noisy = (truth + rng.normal(size=(h, w)) * sigma).astype(np.float32)
    return noisy, truth, n, p, left


def test_edges_kept_noise_removed(device):
    rng = np.random.default_rng(3)
    h, w = 48, 64
    noisy, truth, n, p, left = _corner(h, w, rng)
    valid = np.ones((h, w), bool)
    out = atrous_filter(noisy, n, p, valid, device=device)
    # no bleeding across the normal discontinuity: the columns either side of the crease keep their level
    for col, level in ((w // 2 - 1, 0.2), (w // 2, 0.8)):
        assert abs(out[:, col].mean() - level) < 0.02, (col, out[:, col].mean())
    # i.i.d. noise within each half: variance down by more than 4x
    for half in (left, ~left):
        before = np.var(noisy[half] - truth[half])
        after = np.var(out[half] - truth[half])
        assert after * 4 < before, (before, after)


def test_depth_gap_stops_position_term(device):
    """Same normal on both sides, but the right half is 1 world unit (100 footprints) behind the left."""
    h, w = 32, 64
    y, x = np.mgrid[0:h, 0:w]
    p = np.stack([x * 0.01, y * 0.01, np.where(x < w // 2, 0.0, -1.0)], axis=-1)
    n = np.broadcast_to(np.array([0.0, 0.0, 1.0], np.float32), (h, w, 3)).copy()
    v = np.where(x < w // 2, 1.0, 0.0).astype(np.float32)
    valid = np.ones((h, w), bool)
    assert pixel_footprint(p, valid) == pytest.approx(0.01)
    out = atrous_filter(v, n, p, valid, sigma_value=np.inf, device=device)   # geometry alone must hold the step
    assert np.abs(out - v).max() < 1e-3
    # and without the position term it bleeds, so the test tests something
    out = atrous_filter(v, n, p, valid, sigma_value=np.inf, sigma_position=np.inf, device=device)
    assert np.abs(out - v).max() > 0.1


def test_invalid_pixels_untouched_and_ignored(device):
    rng = np.random.default_rng(4)
    h, w = 24, 30
    n, p = _gbuffer(h, w, rng)
    valid = rng.random((h, w)) > 0.3
    v = rng.random((h, w, 2)).astype(np.float32)
    a, b = v.copy(), v.copy()
    a[~valid] = np.nan                                    # garbage in the background, in every buffer
    b[~valid] = 1e6
    na, nb, pa, pb = n.copy(), n.copy(), p.copy(), p.copy()
    na[~valid], pa[~valid] = np.nan, np.nan
    nb[~valid], pb[~valid] = 0.0, -7.0
    out_a = atrous_filter(a, na, pa, valid, device=device)
    out_b = atrous_filter(b, nb, pb, valid, device=device)
    np.testing.assert_array_equal(out_a[~valid], a[~valid])   # left as they were
    np.testing.assert_array_equal(out_b[~valid], b[~valid])
    np.testing.assert_allclose(out_a[valid], out_b[valid], atol=1e-6)   # and never used as taps
    assert np.isfinite(out_a[valid]).all()
    ref = atrous_filter_reference(a, na, pa, valid)
    np.testing.assert_allclose(out_a[valid], ref[valid], atol=1e-5)


@pytest.mark.parametrize("n", [1, 2, 4])
@pytest.mark.parametrize("trailing", [(), (3,), (2, 2)])
def test_interleave_round_trip(n, trailing):
    rng = np.random.default_rng(5)
    img = rng.random((8, 12, *trailing))
    tiles = deinterleave(img, n)
    assert tiles.shape == (n * n, 8 // n, 12 // n, *trailing)
    np.testing.assert_array_equal(interleave(tiles, n), img)
    np.testing.assert_array_equal(deinterleave(interleave(tiles, n), n), tiles)
    # tile t holds exactly the pixels whose tile index is t
    t = deinterleave(tile_index(8, 12, n), n)
    for k in range(n * n):
        assert (t[k] == k).all()
    assert tiles[n * n - 1][0, 0].tolist() == img[n - 1, n - 1].tolist()


def test_interleave_rejects_bad_shapes():
    with pytest.raises(ValueError, match="multiple"):
        deinterleave(np.zeros((6, 8)), 4)
    with pytest.raises(ValueError, match="n²"):
        interleave(np.zeros((3, 2, 2)), 2)
