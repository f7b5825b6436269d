"""LGH lighting (paper 004 §3.2–3.3): blending functions, streaming shadow-sample selection."""

from types import SimpleNamespace

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from usdml.kernels.lgh_lighting import blend  # noqa: E402
from usdml.lighting.lgh_lighting import LUMA, lgh_lighting  # noqa: E402


@wp.kernel
def _blend_sum(d: wp.array(dtype=float), levels: int, alpha: float, h1: float, out: wp.array(dtype=float)):
    i = wp.tid()
    total = float(0.0)
    for l in range(levels):
        total = total + blend(l, levels - 1, d[i], alpha * h1 * wp.pow(2.0, float(l)))
    out[i] = total


@pytest.mark.parametrize("levels,alpha", [(1, 1.0), (2, 1.0), (4, 1.0), (6, 2.0), (5, 0.5)])
def test_blending_functions_are_a_partition_of_unity(levels, alpha):
    wp.init()
    d = np.concatenate([np.linspace(0, 200, 4001), [1e-6, 1e6]]).astype(np.float32)
    out = wp.zeros(len(d), dtype=float, device="cpu")
    wp.launch(_blend_sum, dim=len(d), inputs=[wp.array(d, dtype=float, device="cpu"), levels, alpha, 1.0, out],
              device="cpu")
    np.testing.assert_allclose(out.numpy(), 1.0, atol=1e-5)


def _one_level(positions, intensities, spacing=100.0):
    """A single-level hierarchy (blend == 1 everywhere) holding the given lights, one per vertex."""
    m = len(positions)
    return SimpleNamespace(h1=spacing, levels=[SimpleNamespace(
        level=1, spacing=spacing, origin=np.zeros(3), dims=np.array([m, 1, 1]),
        position=np.asarray(positions, np.float32), intensity=np.asarray(intensities, np.float32),
        variance=np.zeros(m, np.float32), vertex=np.arange(m))])


def test_streaming_sampler_picks_lights_in_proportion_to_their_contribution():
    rng = np.random.default_rng(1)
    lights = np.array([[0, 5, 0], [3, 4, 1], [-2, 6, 2], [1, 2, -3], [4, 9, 0]], np.float32)
    inten = rng.uniform(0.2, 3.0, (5, 3)).astype(np.float32)
    n = 20000
    points = np.zeros((n, 3), np.float32)
    normals = np.tile(np.float32([0, 1, 0]), (n, 1))
    lgh = _one_level(lights, inten)
    out = lgh_lighting(points, normals, lgh, alpha=1.0, samples=2, seed=3, clamp_distance=1e-3)
    # analytic contributions f_i = lum(I_i) cos / d²
    d2 = (lights ** 2).sum(1)
    f = (inten @ LUMA) * (lights[:, 1] / np.sqrt(d2)) / d2
    expected_e = (inten * ((lights[:, 1] / np.sqrt(d2)) / d2)[:, None]).sum(0)
    np.testing.assert_allclose(out.irradiance[0], expected_e, rtol=1e-5)
    assert out.sample_ok.all()
    picks = out.sample_pos.reshape(-1, 3)
    idx = np.argmin(((picks[:, None, :] - lights[None]) ** 2).sum(-1), axis=1)
    counts = np.bincount(idx, minlength=5)
    exp = f / f.sum() * len(idx)
    chi2 = ((counts - exp) ** 2 / exp).sum()
    assert chi2 < 18.5            # chi-square, 4 degrees of freedom, p = 0.001
    # deterministic for a seed
    again = lgh_lighting(points[:100], normals[:100], lgh, samples=2, seed=3, clamp_distance=1e-3)
    assert np.array_equal(again.sample_pos, out.sample_pos[:100])


def test_lights_behind_the_surface_are_not_sampled():
    lgh = _one_level([[0, -5, 0], [0, 5, 0]], [[1, 1, 1], [1, 1, 1]])
    out = lgh_lighting(np.zeros((50, 3)), np.tile([0.0, 1.0, 0.0], (50, 1)), lgh, samples=1, clamp_distance=1e-3)
    assert np.allclose(out.sample_pos[:, 0], [0, 5, 0])
    np.testing.assert_allclose(out.irradiance[:, 1], 1 / 25, rtol=1e-5)


def test_interleaved_sampling_is_unbiased_over_a_tile():
    """Each pixel of an n x n tile gathers 1/n² of the lights × n²: the tile average equals the full sum."""
    rng = np.random.default_rng(4)
    lights = rng.uniform([-5, 1, -5], [5, 6, 5], (37, 3)).astype(np.float32)
    inten = rng.uniform(0.1, 1.0, (37, 3)).astype(np.float32)
    lgh = _one_level(lights, inten)
    pts = np.zeros((16, 3), np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (16, 1))
    full = lgh_lighting(pts[:1], nrm[:1], lgh, samples=0, clamp_distance=1e-3).irradiance[0]
    tiled = lgh_lighting(pts, nrm, lgh, samples=0, clamp_distance=1e-3, tile=np.arange(16), tiles=16).irradiance
    np.testing.assert_allclose(tiled.mean(0), full, rtol=1e-5)
    assert not np.allclose(tiled[0], full)
