"""VPL generation (usdml.lighting.vpl): energy, determinism, emission profiles, VPLs as lights.

Snapshots are built directly from ``usdml.scene`` dataclasses; tracing uses the exact (Embree) backend.
"""

from __future__ import annotations

import numpy as np
import pytest

from usdml.lighting.direct import shade_direct
from usdml.lighting.vpl import VPLs, generate_vpls, light_power
from usdml.scene import Lights, LightType, Mesh

from vpl_scenes import backend_for, box, light, mesh, snapshot

pytest.importorskip("embreex")


# ---------------------------------------------------------------------------------------------- scenes

def quad(size: float, y: float = 0.0, albedo=(1.0, 1.0, 1.0), path: str = "/ground") -> Mesh:
    s = size / 2
    pts = [(-s, y, -s), (-s, y, s), (s, y, s), (s, y, -s)]
    return mesh(path, pts, [[0, 1, 2], [0, 2, 3]], albedo)


def rect_solid_angle(a: float, b: float, h: float) -> float:
    """Solid angle of a 2a × 2b rectangle seen from height h above its centre."""
    return 4.0 * np.arctan(a * b / (h * np.sqrt(h * h + a * a + b * b)))


# ---------------------------------------------------------------------------------------------- energy

def test_first_bounce_energy_above_plane():
    rho = np.array([0.8, 0.5, 0.25])
    size, h = 40.0, 2.0
    snap = snapshot([quad(size, 0.0, rho)], meters_per_unit=0.01)     # point-light power has no units
    intensity = np.array([3.0, 2.0, 1.0])
    lights = light(position=(0.0, h, 0.0), intensity=intensity)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=1, paths=100_000, seed=1)
    assert set(np.unique(v.bounce)) == {1}
    expected = rho * intensity * rect_solid_angle(size / 2, size / 2, h)
    np.testing.assert_allclose(v.total_flux(), expected, rtol=0.02)
    np.testing.assert_allclose(light_power(snap, lights)[0], 4 * np.pi * intensity, rtol=1e-6)
    # VPLs sit on the plane, normals face the light
    assert np.allclose(v.position[:, 1], 0.0, atol=1e-4)
    assert np.allclose(v.normal, [0.0, 1.0, 0.0], atol=1e-5)


@pytest.mark.parametrize("ltype", [LightType.POINT, LightType.RECT])
def test_closed_box_bounce_energy(ltype):
    rho = np.array([0.9, 0.6, 0.3])
    snap = snapshot([box((-1, -1, -1), (1, 1.5, 2), rho)])
    intensity = np.array([1.0, 2.0, 4.0])
    lights = light(ltype, position=(0.1, 0.2, -0.3), intensity=intensity)
    phi = (4 * np.pi if ltype == LightType.POINT else np.pi) * intensity
    np.testing.assert_allclose(light_power(snap, lights)[0], phi, rtol=1e-6)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=3, paths=20_000, seed=2)
    assert len(v) == 3 * 20_000          # closed: every path hits three times
    for b in (1, 2, 3):
        np.testing.assert_allclose(v.total_flux(b), phi * rho ** b, rtol=1e-4)
    # normals face into the box (toward where the light came from)
    centre = np.array([0.0, 0.25, 0.5])
    assert (np.einsum("ij,ij->i", v.normal, centre - v.position) > 0).all()


def test_soft_focused_spot_power_and_energy():
    """Soft cone and focus are integrated numerically; the path weights make VPL flux unbiased."""
    intensity = np.array([1.0, 1.0, 1.0])
    # focus without cone, tint 0: profile clip(c,0,1)^f, Φ = 2π I / (f + 1)
    snap = snapshot([box((-1, -1, -1), (1, 1, 1), (1, 1, 1))])
    f = 3.0
    lights = light(intensity=intensity, focus=f)
    np.testing.assert_allclose(light_power(snap, lights)[0], 2 * np.pi * intensity / (f + 1), rtol=1e-4)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=1, paths=50_000, seed=0)
    np.testing.assert_allclose(v.total_flux(1), 2 * np.pi * intensity / (f + 1), rtol=0.02)
    # focus tint: tint + (1 - tint) c^f over the front hemisphere, tint behind
    tint = np.array([0.5, 0.0, 1.0])
    lights = light(intensity=intensity, focus=f, tint=tint)
    expected = 2 * np.pi * (tint + (1 - tint) / (f + 1)) + 2 * np.pi * tint
    np.testing.assert_allclose(light_power(snap, lights)[0], expected, rtol=1e-4)
    # hard cone: 2π(1 - cos a) I; soft cone: numeric, between the inner and outer hard cones
    lights = light(intensity=intensity, cone=40.0)
    np.testing.assert_allclose(light_power(snap, lights)[0], 2 * np.pi * (1 - np.cos(np.radians(40))), rtol=1e-9)
    soft = light_power(snap, light(intensity=intensity, cone=40.0, softness=0.5))[0, 0]
    assert 2 * np.pi * (1 - np.cos(np.radians(40))) > soft > 2 * np.pi * (1 - np.cos(np.radians(20)))
    v = generate_vpls(snap, backend_for(snap), light(intensity=intensity, cone=40.0, softness=0.5),
                      bounces=1, paths=50_000, seed=0)
    np.testing.assert_allclose(v.total_flux(1)[0], soft, rtol=0.01)


def test_distant_light_energy_and_uniform_coverage():
    size, mpu = 10.0, 0.5
    rho = 0.5
    snap = snapshot([quad(size, 0.0, (rho, rho, rho))], meters_per_unit=mpu)
    e = np.array([2.0, 2.0, 2.0])
    lights = light(LightType.DISTANT, axis=(0.0, -1.0, 0.0), intensity=e)
    radius = np.sqrt(2) * size / 2        # bounding sphere of the flat 10 × 10 bounds
    np.testing.assert_allclose(light_power(snap, lights)[0], e * np.pi * (radius * mpu) ** 2, rtol=1e-6)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=1, paths=64_000, seed=3)
    np.testing.assert_allclose(v.total_flux(), rho * e * (size * mpu) ** 2, rtol=0.02)
    # uniform over the lit ground: 4 × 4 cells each hold 1/16 of the VPLs and of the flux
    cell = np.clip(((v.position[:, [0, 2]] + size / 2) / size * 4).astype(int), 0, 3)
    idx = cell[:, 0] * 4 + cell[:, 1]
    counts = np.bincount(idx, minlength=16)
    np.testing.assert_allclose(counts / len(v), 1 / 16, rtol=0.1)
    flux = np.bincount(idx, weights=v.flux[:, 0], minlength=16)
    np.testing.assert_allclose(flux / flux.sum(), 1 / 16, rtol=0.1)
    assert np.allclose(v.flux, v.flux[0])       # every distant path carries the same flux


def test_spot_vpls_inside_cone_footprint():
    h, cone = 3.0, 25.0
    snap = snapshot([quad(100.0, 0.0)])
    lights = light(position=(1.0, h, -2.0), axis=(0.0, -1.0, 0.0), cone=cone, softness=0.3, focus=2.0)
    v = generate_vpls(snap, backend_for(snap), lights, bounces=1, paths=20_000, seed=4)
    r = np.hypot(v.position[:, 0] - 1.0, v.position[:, 2] + 2.0)
    assert len(v) == 20_000
    assert r.max() <= h * np.tan(np.radians(cone)) * (1 + 1e-6)
    assert r.max() > 0.9 * h * np.tan(np.radians(cone))
    # a disk light facing up lights nothing on the ground below it
    up = light(LightType.DISK, position=(0.0, 1.0, 0.0), axis=(0.0, 1.0, 0.0))
    assert len(generate_vpls(snap, backend_for(snap), up, bounces=1, paths=1000)) == 0


# ---------------------------------------------------------------------------------------------- counts, seeds

def test_count_is_total_vpls_and_deterministic():
    snap = snapshot([quad(8.0, 0.0, (0.7, 0.7, 0.7)), quad(8.0, 3.0, (0.7, 0.7, 0.7), "/ceiling")])
    lights = Lights.concat([light(position=(0.0, 1.0, 0.0), intensity=(1.0, 1.0, 1.0)),
                            light(LightType.RECT, position=(1.0, 2.9, 0.0), intensity=(5.0, 4.0, 3.0))])
    b = backend_for(snap)
    a = generate_vpls(snap, b, lights, count=3000, bounces=3, seed=7)
    assert len(a) == 3000               # open scene: more paths are traced until the total is reached
    assert a.paths > 1000
    again = generate_vpls(snap, b, lights, count=3000, bounces=3, seed=7)
    for name in ("position", "normal", "flux", "bounce"):
        np.testing.assert_array_equal(getattr(a, name), getattr(again, name))
    other = generate_vpls(snap, b, lights, count=3000, bounces=3, seed=8)
    assert not np.array_equal(a.position[:100], other.position[:100])
    assert set(np.unique(a.bounce)) <= {1, 2, 3}
    # closed box: exactly count as well, with ceil(count / bounces) paths
    snap = snapshot([box((-1, -1, -1), (1, 1, 1), (0.5, 0.5, 0.5))])
    v = generate_vpls(snap, backend_for(snap), light(), count=1000, bounces=3)
    assert len(v) == 1000 and v.paths == 334
    assert len(generate_vpls(snap, backend_for(snap), Lights.empty(), count=10)) == 0


# ---------------------------------------------------------------------------------------------- as lights

def _one_vpl(flux=(2.0, 1.0, 0.5), normal=(0.0, 1.0, 0.0), position=(0.0, 0.0, 0.0)) -> VPLs:
    return VPLs(position=np.array([position], float), normal=np.array([normal], np.float32),
                flux=np.array([flux], np.float32), bounce=np.ones(1, np.int8), paths=1)


def test_as_lights_conserves_power():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = VPLs(position=rng.normal(size=(50, 3)), normal=n.astype(np.float32),
             flux=rng.random((50, 3)).astype(np.float32), bounce=np.ones(50, np.int8), paths=50)
    iso, cos = v.as_lights(True), v.as_lights(False)
    assert len(iso) == len(cos) == 50
    assert (iso.type == LightType.POINT).all() and (cos.type == LightType.DISK).all()
    np.testing.assert_allclose(4 * np.pi * iso.intensity, v.flux, rtol=1e-6)
    np.testing.assert_allclose(np.pi * cos.intensity, v.flux, rtol=1e-6)
    snap = snapshot([quad(1.0)])
    np.testing.assert_allclose(light_power(snap, iso), v.flux, rtol=1e-6)
    np.testing.assert_allclose(light_power(snap, cos), v.flux, rtol=1e-6)
    np.testing.assert_allclose(cos.axis, n, atol=1e-6)
    np.testing.assert_allclose(-cos.xform[:, :3, 2], n, atol=1e-6)      # the light's -Z is its axis
    assert iso.shadow.all() and (iso.radius == 0).all() and (iso.cone_angle == 180).all()


def test_cosine_vpl_direct_lighting_matches_analytic():
    flux = np.array([2.0, 1.0, 0.5])
    v = _one_vpl(flux)
    mpu = 0.5
    receivers = np.array([[1.0, 2.0, 0.0], [0.0, 3.0, 0.0], [-2.0, 0.5, 1.0], [1.0, -1.0, 0.0]])
    normals = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.6, -0.8, 0.0], [0.0, 1.0, 0.0]])
    albedo = np.full((4, 3), 0.5, np.float32)
    res = shade_direct(receivers, normals, albedo, v.as_lights(isotropic=False), None, meters_per_unit=mpu)
    d = receivers - v.position[0]
    dist = np.linalg.norm(d, axis=1)
    w = d / dist[:, None]
    cos_l = np.maximum(w @ v.normal[0].astype(float), 0.0)
    cos_r = np.maximum(np.einsum("ij,ij->i", normals, -w), 0.0)
    e = (flux / np.pi)[None] * (cos_l * cos_r / (dist * mpu) ** 2)[:, None]
    np.testing.assert_allclose(res.radiance, albedo / np.pi * e, rtol=1e-5, atol=1e-9)
    assert res.radiance[3].max() == 0.0         # behind the VPL's surface: nothing
    iso = shade_direct(receivers, normals, albedo, v.as_lights(isotropic=True), None, meters_per_unit=mpu)
    e_iso = (flux / (4 * np.pi))[None] * (cos_r / (dist * mpu) ** 2)[:, None]
    np.testing.assert_allclose(iso.radiance, albedo / np.pi * e_iso, rtol=1e-5, atol=1e-9)


def test_count_mode_keeps_energy_when_paths_escape():
    """Rounds of extra paths and the trimmed last round keep the flux unbiased (plane: ≤ 1 VPL per path)."""
    rho, size, h = 0.6, 20.0, 1.5
    snap = snapshot([quad(size, 0.0, (rho, rho, rho))])
    v = generate_vpls(snap, backend_for(snap), light(position=(0.0, h, 0.0)), count=40_000, bounces=3, seed=5)
    assert len(v) == 40_000 and (v.bounce == 1).all()
    assert v.paths > 40_000
    np.testing.assert_allclose(v.total_flux(), rho * rect_solid_angle(size / 2, size / 2, h), rtol=0.02)


def test_count_mode_keeps_tracing_when_the_first_round_hits_nothing():
    """A small object far from its light: the first round's paths all miss; later rounds trace
    MAX_PATH_FACTOR times more instead of giving up (it used to return no VPLs at all)."""
    rho, size, h = 0.6, 2.0, 20.0       # the quad subtends 1/1,250 of the light's sphere
    snap = snapshot([quad(size, 0.0, (rho, rho, rho))])
    b = backend_for(snap)
    lit = light(position=(0.0, h, 0.0))
    assert len(generate_vpls(snap, b, lit, bounces=1, paths=1000, seed=1)) == 0   # what round 1 traces
    v = generate_vpls(snap, b, lit, count=1000, bounces=1, seed=1)
    assert len(v) > 30 and v.paths > 1000
    np.testing.assert_allclose(v.total_flux(), rho * rect_solid_angle(size / 2, size / 2, h), rtol=0.3)
    # lights that reach nothing still end with none, after the rounds run out
    away = light(position=(0.0, h, 0.0), axis=(0.0, 1.0, 0.0), cone=10.0)
    assert len(generate_vpls(snap, b, away, count=100, bounces=1, seed=1)) == 0
