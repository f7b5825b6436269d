"""``--direct lgh`` with the preview surface (issue 51): each grid light (and every light of the every-light sum)
adds ``E·(ρ/π·kd + ks)`` with the BRDF toward the light, its shadow rays drawn by that radiance."""

from __future__ import annotations

import numpy as np
import pytest

from usdml.kernels.brdf import ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0, F0, F90, OCCLUSION, WIDTH
from usdml.lighting.direct import shade_direct
from usdml.lighting.lgh.direct import prepare_direct, shade_lgh_direct
from usdml.lighting.lgh.each import EachLight
from usdml.lighting.lgh.native import library
from usdml.settings import UsdmlSettings

from test_lgh_direct import _lights


def rows(points: np.ndarray, eye, f0=0.04, f90=1.0, roughness=0.3, clearcoat=1.0, coat_roughness=0.1) -> np.ndarray:
    """Material rows at ``points`` seen from ``eye``: by default a clearcoated plastic."""
    m = np.zeros((len(points), WIDTH), np.float32)
    e = np.asarray(eye, np.float64) - points
    m[:, 0:3] = e / np.linalg.norm(e, axis=1, keepdims=True)
    m[:, F0:F0 + 3] = f0
    m[:, F90:F90 + 3] = f90
    m[:, ALPHA] = max(roughness, 0.001) ** 2
    m[:, CLEARCOAT] = clearcoat
    m[:, CLEARCOAT_ALPHA] = max(coat_roughness, 0.001) ** 2
    m[:, CLEARCOAT_F0] = 0.04
    m[:, OCCLUSION] = 1.0
    return m


def _scene(count: int, seed: int = 0, n: int = 600):
    rng = np.random.default_rng(seed)
    positions = rng.uniform([-2, 1.5, -2], [2, 3.0, 2], (count, 3))
    lights = _lights(positions, rng.uniform(0.5, 3.0, (count, 3)).astype(np.float32))
    pts = rng.uniform(-6, 6, (n, 3)) * [1, 0, 1]
    nrm = np.tile([0.0, 1.0, 0.0], (n, 1))
    return lights, pts, nrm


def occluded(origins, targets, normals=None, distant=None):      # a wall at x = 0.5 up to y = 1 (analytic)
    dx = targets[:, 0] - origins[:, 0]
    t = (0.5 - origins[:, 0]) / np.where(dx == 0, 1e-30, dx)
    y = origins[:, 1] + t * (targets[:, 1] - origins[:, 1])
    return (t > 0) & (t < 1) & (y < 1.0)


def rel_rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(((a - b) ** 2).mean()) / np.sqrt((b ** 2).mean()))


@pytest.mark.parametrize("gather", ["hierarchy", "each"])
@pytest.mark.parametrize("material", ["plastic", "metal"])
def test_a_few_lights_against_every_light(gather, material):
    """Eight lights over a plane and a wall: ``--direct lgh``'s radiance with material rows within the 6 % the
    Lambertian frames are held to (tests/test_lgh_direct.py) of every-light shading with the same rows, its specular
    part on a metal (a plastic's shares the ratio of its point's radiance, mostly diffuse); unshadowed, within 2e-4 where only the lights themselves (S0) and the sum of every light shade."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    lights, pts, nrm = _scene(8)
    eye = (0.0, 4.0, 9.0)
    if material == "metal":
        m, alb = rows(pts, eye, f0=(0.9, 0.6, 0.2), f90=(0.9, 0.6, 0.2), roughness=0.25, clearcoat=0.0), \
            np.zeros((len(pts), 3), np.float32)
        m[:, F0:F0 + 3], m[:, F90:F90 + 3] = (0.9, 0.6, 0.2), (0.9, 0.6, 0.2)
    else:
        m, alb = rows(pts, eye), np.full((len(pts), 3), 0.5, np.float32)
    field = prepare_direct(lights)
    settings = UsdmlSettings(direct_shadow_samples=64, shadow_filter_iterations=0, pixel_samples=1,
                             direct_gather=gather, direct_alpha=64.0 if gather == "hierarchy" else 4.0)
    open_, stats = shade_lgh_direct(pts, nrm, alb, field, None, None, settings, material=m)
    assert stats["gather"] == gather
    want_open = shade_direct(pts, nrm, alb, lights, None, material=m)
    np.testing.assert_allclose(open_.radiance, want_open.radiance, rtol=2e-4, atol=1e-7)
    np.testing.assert_allclose(open_.specular, want_open.specular, rtol=2e-4, atol=1e-7)
    field = prepare_direct(lights)
    got, _ = shade_lgh_direct(pts, nrm, alb, field, occluded, None, settings, material=m)
    want = shade_direct(pts, nrm, alb, lights, occluded, material=m)
    assert (want.shadow > 0).mean() > 0.1
    assert rel_rmse(got.radiance, want.radiance) < 0.06, rel_rmse(got.radiance, want.radiance)
    if material == "metal":         # (a plastic's specular part shares its point's shadow ratio, the diffuse's)
        assert rel_rmse(got.specular, want.specular) < 0.06, rel_rmse(got.specular, want.specular)
        assert (got.specular.max(1) > 0).mean() > 0.5
        np.testing.assert_allclose(got.radiance, got.specular, rtol=1e-5)


def test_compiled_and_numpy_sums_agree_on_material_rows():
    """Every light its own light with material rows, compiled (``lghq_each_brdf``) and by NumPy: the same radiance,
    specular and counts, and the same draws but where rounding moves a threshold; the weights are each drawn light's
    radiance over its luminance."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    rng = np.random.default_rng(4)
    q = rng.uniform([-5, 1, -5], [5, 4, 5], (700, 3))
    inten = rng.uniform(0.1, 2.0, (700, 3)).astype(np.float32)
    normal = np.zeros((700, 3), np.float32)
    normal[::3] = (0.0, -1.0, 0.0)                  # a third one-sided (disk-like), the rest isotropic
    pts = (rng.uniform(-6, 6, (90, 3)) * [1, 0, 1]).astype(np.float32)
    pn = np.tile(np.float32([0.0, 1.0, 0.0]), (90, 1))
    m = rows(pts.astype(np.float64), (1.0, 3.0, 8.0), roughness=0.2)
    alb = np.full((90, 3), 0.4, np.float32)
    lights = EachLight((q, inten, normal))
    a = lights.gather(16, 3, 1.0, 1e-3, compiled=True)(pts, pn, first=5, material=m, albedo=alb)
    b = lights.gather(16, 3, 1.0, 1e-3, compiled=False)(pts, pn, first=5, material=m, albedo=alb)
    np.testing.assert_allclose(a.irradiance, b.irradiance, rtol=1e-4)
    np.testing.assert_allclose(a.specular, b.specular, rtol=1e-4)
    np.testing.assert_array_equal(a.count, b.count)
    assert (a.specular > 0).all() and a.sample_ok.all()
    assert (a.sample_light == b.sample_light).mean() > 0.99
    np.testing.assert_allclose(a.sample_weight * a.sample_lum[..., None], b.sample_weight * b.sample_lum[..., None],
                               rtol=1e-3, atol=1e-9)
    # drawn by radiance: the lights of the points' highlights are drawn more often than their irradiance says
    plain = lights.gather(16, 3, 1.0, 1e-3, compiled=True)(pts, pn, first=5)
    assert (plain.sample_light != a.sample_light).mean() > 0.1


def test_the_hierarchy_gathers_what_every_light_sums():
    """With the lights themselves as the near field (alpha large enough that S0 covers the stage) the compiled
    hierarchy's radiance and specular are every light's sum (NumPy)."""
    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    lights, pts, nrm = _scene(12, seed=3, n=200)
    m = rows(pts, (0.0, 5.0, 7.0))
    alb = np.full((len(pts), 3), 0.3, np.float32)
    field = prepare_direct(lights)
    settings = UsdmlSettings(direct_shadow_samples=16, shadow_filter_iterations=0, pixel_samples=1,
                             direct_gather="hierarchy", direct_alpha=64.0)
    got, _ = shade_lgh_direct(pts, nrm, alb, field, None, None, settings, material=m)
    each = EachLight(field.sources).gather(0, 0, 1.0, float(1e-6 * field.lgh.h1), compiled=False)
    want = each(pts.astype(np.float32), nrm.astype(np.float32), material=m, albedo=alb)
    np.testing.assert_allclose(got.radiance, want.irradiance, rtol=1e-4)
    np.testing.assert_allclose(got.specular, want.specular, rtol=1e-4)


@pytest.mark.parametrize("gather", ["hierarchy", "each"])
def test_lambertian_rows_shade_as_no_material(gather):
    """Rows of a Lambertian surface (F0 = F90 = 0: kd = 1, ks = 0) give what no rows give, up to rounding; no rows give
    no specular part."""
    from usdml.scene.shading import lambert_rows

    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    lights, pts, nrm = _scene(30, seed=5, n=300)
    alb = np.full((len(pts), 3), 0.6, np.float32)
    settings = UsdmlSettings(direct_shadow_samples=32, shadow_filter_iterations=0, pixel_samples=1,
                             direct_gather=gather)
    plain, _ = shade_lgh_direct(pts, nrm, alb, prepare_direct(lights), occluded, None, settings)
    lam, _ = shade_lgh_direct(pts, nrm, alb, prepare_direct(lights), occluded, None, settings,
                              material=lambert_rows(len(pts)))
    assert plain.specular is None and not lam.specular.any()
    np.testing.assert_allclose(lam.radiance, plain.radiance, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(lam.shadow, plain.shadow, atol=1e-5)
