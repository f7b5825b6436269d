"""The preview surface's BRDF in the compiled kernels (issue 51): the compiled sums (``kernels/brdf/brdfsum.c``,
:mod:`usdml.lighting.brdf_sums`) against the NumPy reference (``kernels/brdf``), the voxel backend's fused
material shading (``vq_shade`` with rows) against NumPy shading over the same backend's shadows, and the
Lambertian path left as it was.

Agreement: the compiled sums round every product and sum as NumPy does, so they differ only where ``brdf.h``'s
square root and fifth power round apart and where it divides once per lobe, NumPy twice (measured: 3e-7 relative); the bound is the issue's 1e-5. The
voxel kernel's SIMD shading multiplies by reciprocals refined to about 23 bits and contracts a·b + c (measured:
1.4e-5 relative with AVX2, 2e-7 scalar), bound 1e-4.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from usdml.kernels.brdf import ALPHA, CLEARCOAT, CLEARCOAT_ALPHA, CLEARCOAT_F0, EYE, F0, F90, OCCLUSION, WIDTH
from usdml.lighting import brdf_sums as sums
from usdml.lighting import direct
from usdml.lighting.direct import shade_direct, shade_with
from usdml.scene import diff
from usdml.scene.shading import lambert_rows
from usdml.settings import UsdmlSettings
from usdml.visibility import make_backend
from usdml.visibility.voxel import native as voxel_native

from backend_scenes import lights, scene_frames, surface_points

#: CI sets USDML_REQUIRE_NATIVE=1 so that a failed build fails these tests instead of skipping them
if os.environ.get("USDML_REQUIRE_NATIVE") == "1":
    for what, lib, line in (("BRDF sums", sums.library(), sums.describe()),
                            ("voxel kernel", voxel_native.library(), voxel_native.describe())):
        if lib is None:
            raise RuntimeError(f"USDML_REQUIRE_NATIVE=1 but the compiled {what}: {line}")
needs_sums = pytest.mark.skipif(sums.library() is None, reason="the compiled BRDF sums were not built")
needs_voxel = pytest.mark.skipif(voxel_native.library() is None, reason="the compiled voxel kernel was not built")

SETTINGS = UsdmlSettings(voxel_resolution=32, direction_step=10.0)
#: the compiled voxel kernel's instruction sets this CPU runs (auto: the widest)
ISAS = ["auto"] + (["avx2"] if voxel_native.isa_width("avx2") == 8 and voxel_native.isa_width() > 8 else []) \
    + ["scalar"]


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path / "cache"))


def unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def glossy_rows(rng, eye: np.ndarray, sharp: float = 0.0) -> np.ndarray:
    """(P, WIDTH) float32 rows seen from unit directions ``eye``: dielectric to metallic F0, clearcoat, roughness
    0.001 (the smallest the rows hold) on a ``sharp`` share of them."""
    n = len(eye)
    rows = lambert_rows(n, eye)
    rows[:, F0:F0 + 3] = rng.uniform(0.02, 0.9, (n, 3))
    rows[:, F90:F90 + 3] = rng.uniform(0.5, 1.0, (n, 3))
    rough = rng.uniform(0.05, 1.0, n)
    rough[rng.random(n) < sharp] = 0.001
    rows[:, ALPHA] = rough ** 2
    rows[:, CLEARCOAT] = rng.uniform(0.0, 1.0, n)
    rows[:, CLEARCOAT_ALPHA] = np.where(rng.random(n) < sharp, 0.001, rng.uniform(0.05, 1.0, n)) ** 2
    rows[:, CLEARCOAT_F0] = 0.04
    rows[:, OCCLUSION] = rng.uniform(0.5, 1.0, n)
    return rows.astype(np.float32)


class _Table:
    """What the sums read of a :class:`usdml.scene.light_table.LightTable`: the lights' colours."""

    def __init__(self, rng, n: int):
        self.base = rng.uniform(0.0, 3.0, (n, 3)).astype(np.float32)
        self.focus_rgb = rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)


def block(rng, n_p: int = 400, n_l: int = 257):
    """A block's inputs: normals, eyes and light directions with grazing ones (n·l and n·e of 1e-3), eyes behind
    the shading normal, mirror directions (the peak of a sharp lobe) and roughness 0.001; ``g`` the clamped
    cosine (some pairs 0, as a shadow leaves them) and a focus factor."""
    n = unit(rng.normal(size=(n_p, 3)))
    e = unit(rng.normal(size=(n_p, 3)))
    e = np.where(((e * n).sum(1) < 0)[:, None], -e, e)
    tangent = unit(np.cross(n, rng.normal(size=(n_p, 3))))
    grazing_eye = rng.random(n_p) < 0.15
    e[grazing_eye] = unit(tangent + 1e-3 * n)[grazing_eye]
    behind = rng.random(n_p) < 0.05
    e[behind] = unit(tangent - 0.2 * n)[behind]
    w = unit(rng.normal(size=(n_p, n_l, 3)))
    graze = rng.random((n_p, n_l)) < 0.1
    side = unit(np.cross(n[:, None, :], rng.normal(size=(n_p, n_l, 3))))
    w[graze] = unit(side + 1e-3 * n[:, None, :])[graze]
    mirror = 2 * (e * n).sum(1, keepdims=True) * n - e
    w[:, 0] = mirror                                           # each point's mirror direction
    w[:, 1] = unit(mirror + 1e-4 * tangent)                    # and one just beside it
    g = np.maximum((w * n[:, None, :]).sum(-1), 0.0)
    g[rng.random((n_p, n_l)) < 0.3] = 0.0                      # shadowed
    rows = glossy_rows(rng, e, sharp=0.3)
    w = w.astype(np.float32)
    return (g.astype(np.float32), rng.uniform(0.0, 1.0, (n_p, n_l)).astype(np.float32),
            (w[..., 0], w[..., 1], w[..., 2]), _Table(rng, n_l), rows, n.astype(np.float32))


@needs_sums
@pytest.mark.parametrize("focus", [False, True])
def test_compiled_sums_equal_the_numpy_reference(focus):
    g, f, w, table, rows, n = block(np.random.default_rng(3))
    f = f if focus else None
    want = sums.reference(g, f, w, table, rows, n)
    got = sums.compiled(g, f, w, table, rows, n)
    for a, b, what in zip(got, want, ("E·kd", "E·ks")):
        assert a.dtype == np.float32 and a.shape == b.shape == (len(g), 3)
        assert np.all(np.isfinite(a)), what
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=0, err_msg=what)
    # the cases the block was built to hold: sharp peaks (a specular sum far above the diffuse one), eyes
    # behind the normal (no specular), shadowed pairs skipped
    assert (got[1].max(1) > 1e3 * got[0].max(1)).any()
    assert (got[1] == 0).all(1).any()


@needs_sums
def test_sums_skip_unlit_pairs_and_pick_the_compiled_path():
    g, f, w, table, rows, n = block(np.random.default_rng(4), 50, 33)
    g[:10] = 0.0
    d, s = sums.brdf_sums(g, f, w, table, rows, n)
    assert not d[:10].any() and not s[:10].any() and d[10:].all()
    assert sums.describe().startswith("compiled")
    with pytest.raises(ValueError, match="points x"):
        sums.compiled(g, f, w, table, rows[:-1], n)


def test_numpy_is_the_fallback(monkeypatch):
    """Without the compiled library the sums are the reference's, and shading with materials still works."""
    monkeypatch.setattr(sums.EXTENSION, "load", lambda: (None, "not built (no C compiler)"))
    g, f, w, table, rows, n = block(np.random.default_rng(5), 30, 20)
    for a, b in zip(sums.brdf_sums(g, f, w, table, rows, n), sums.reference(g, f, w, table, rows, n)):
        assert np.array_equal(a, b)
    assert sums.describe().startswith("NumPy") and "C compiler" in sums.describe()


def surface(rng, n: int):
    """Ground points with shading normals tilted from the geometric +Y, an eye above one side, their rows."""
    pts, geo = surface_points(rng, n)
    nrm = unit(geo + rng.normal(scale=0.25, size=geo.shape))
    eye = unit(np.array([0.0, 6.0, -14.0]) - pts)
    albedo = rng.uniform(0.2, 0.9, (n, 3)).astype(np.float32)
    return pts, nrm, geo, albedo, glossy_rows(rng, eye)


def frame_lights(rng):
    """backend_scenes' lights (points, a disk, a spot, distant ones) with one that casts no shadow and one
    focused."""
    lit = lights(rng, 40)
    lit.shadow[1] = False
    lit.focus[2] = 3.0
    return lit


@needs_voxel
@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("scene", ["occluder", "instances"])
def test_voxel_fused_material_shading_equals_numpy_over_its_shadows(scene, isa):
    """``vq_shade`` with rows against :func:`shade_direct` asking the same backend's ``occluded``: the same
    shadows, both lobes within the SIMD shading's rounding."""
    rng = np.random.default_rng(9)
    lit = frame_lights(rng)
    b = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="native", native_isa=isa, report=lambda line: None)
    try:
        snap = scene_frames(scene)[0]
        b.update(snap, diff(None, snap))
        pts, nrm, geo, albedo, rows = surface(rng, 700)
        got = shade_with(b, pts, nrm, albedo, lit, geometric=geo, material=rows)
        want = shade_direct(pts, nrm, albedo, lit, b.occluded, geometric=geo, material=rows)
        assert np.array_equal(got.facing, want.facing)
        assert np.array_equal(got.shadow, want.shadow) and 0.05 < got.shadow.mean() < 0.95
        for what in ("radiance", "specular"):
            np.testing.assert_allclose(getattr(got, what), getattr(want, what), rtol=1e-4, atol=1e-7, err_msg=what)
        assert (got.specular > 0.05 * got.radiance).any()
        # the fused kernel did the shading: NumPy's sums would agree to 1e-7
        assert not np.array_equal(got.radiance, want.radiance) or isa == "scalar"
    finally:
        b.close()


@needs_voxel
@pytest.mark.parametrize("isa", ISAS)
def test_voxel_material_rows_without_gloss_give_the_lambertian_sums_bit_for_bit(isa):
    """Lambertian rows (kd = 1, ks = 0) through the material kernel add the Lambertian kernel's terms in its order."""
    rng = np.random.default_rng(10)
    lit = frame_lights(rng)
    b = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="native", native_isa=isa, report=lambda line: None)
    try:
        snap = scene_frames("occluder")[0]
        b.update(snap, diff(None, snap))
        pts, nrm, geo, albedo, rows = surface(rng, 500)
        plain = shade_with(b, pts, nrm, albedo, lit, geometric=geo)
        lambert = shade_with(b, pts, nrm, albedo, lit, geometric=geo, material=lambert_rows(len(pts), rows[:, EYE:EYE + 3]))
        assert plain.specular is None and not lambert.specular.any()
        assert np.array_equal(plain.radiance, lambert.radiance) and np.array_equal(plain.shadow, lambert.shadow)
    finally:
        b.close()


def test_voxel_warp_kernels_hand_material_rows_to_numpy():
    """The voxel backend's Warp kernels sum no BRDF: with rows it shades by NumPy over its own ``occluded``."""
    rng = np.random.default_rng(11)
    lit = frame_lights(rng)
    b = make_backend("voxel", SETTINGS, "cpu", voxel_cpu_kernel="warp", report=lambda line: None)
    try:
        snap = scene_frames("occluder")[0]
        b.update(snap, diff(None, snap))
        pts, nrm, geo, albedo, rows = surface(rng, 200)
        got = shade_with(b, pts, nrm, albedo, lit, geometric=geo, material=rows)
        want = shade_direct(pts, nrm, albedo, lit, b.occluded, geometric=geo, material=rows)
        assert np.array_equal(got.radiance, want.radiance) and np.array_equal(got.specular, want.specular)
    finally:
        b.close()


@pytest.mark.parametrize("backend", ["exact", "voxel"])
def test_without_material_no_brdf_code_runs(backend, monkeypatch):
    """The Lambertian path (no rows) never reaches the BRDF: neither the sums nor the voxel kernel's material
    shading is called, and the result has no specular part."""
    def refuse(*args, **kwargs):
        raise AssertionError("the Lambertian path reached the BRDF")
    monkeypatch.setattr(direct, "brdf_sums", refuse)
    shade = voxel_native.NativeScene.shade

    def lambertian_only(self, *args, material=None, specular=None, **kwargs):
        assert material is None and specular is None
        return shade(self, *args, **kwargs)
    monkeypatch.setattr(voxel_native.NativeScene, "shade", lambertian_only)
    rng = np.random.default_rng(12)
    lit = frame_lights(rng)
    b = make_backend(backend, SETTINGS, "cpu", report=lambda line: None) if backend == "voxel" \
        else make_backend(backend)
    try:
        snap = scene_frames("occluder")[0]
        b.update(snap, diff(None, snap))
        pts, nrm, geo, albedo, _ = surface(rng, 300)
        r = shade_with(b, pts, nrm, albedo, lit, geometric=geo)
        assert r.specular is None and r.radiance.any()
    finally:
        b.close()


def test_layout_is_the_headers():
    """brdf.h's column enum is kernels/brdf's layout."""
    from pathlib import Path

    header = (Path(__file__).resolve().parents[1] / "kernels" / "include" / "brdf.h").read_text()
    for name, value in (("WIDTH", WIDTH), ("EYE", EYE), ("F0", F0), ("F90", F90), ("ALPHA", ALPHA),
                        ("CLEARCOAT", CLEARCOAT), ("CLEARCOAT_ALPHA", CLEARCOAT_ALPHA),
                        ("CLEARCOAT_F0", CLEARCOAT_F0), ("OCCLUSION", OCCLUSION)):
        assert f"BRDF_{name} = {value}," in header or f"BRDF_{name} = {value} " in header, name
