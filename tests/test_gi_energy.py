"""VPL indirect energy against references that share none of usdml's VPL code: the analytic furnace
(a closed diffuse sphere with a point light at its centre) and Mitsuba 3 path tracing of a closed box.

The stages are authored in USD by ``tools/gi_reference.py`` (also the figure tool); Mitsuba gets the same
scene as a dict. Before cosine-lobe VPLs (isotropic, flux / 4π) brute force carried 0.49 of the furnace's
indirect energy and 0.44 of Mitsuba's.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from conftest import ROOT

sys.path.insert(0, str(ROOT / "tools"))
import gi_reference as ref  # noqa: E402

RHO, BOUNCES, INTENSITY, RADIUS = 0.5, 3, 10.0, 2.0


@pytest.fixture(scope="module")
def furnace(tmp_path_factory):
    return ref.furnace_sphere(tmp_path_factory.mktemp("furnace") / "sphere.usda", RHO, RADIUS, INTENSITY)


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    return ref.closed_box(tmp_path_factory.mktemp("box") / "box.usda")


def _lum(image):
    return float((np.asarray(image, np.float64) @ ref.LUMA).sum())


@pytest.mark.parametrize("method,settings,low,high", [
    pytest.param("vpl-bruteforce", {}, 0.98, 1.02, marks=pytest.mark.slow),    # 6 s: every VPL, exact rays
    # the single hierarchy with an automatic alpha (3,000 VPLs: 1, from S0; measured 0.860, and 0.855 with the
    # paper's alpha 1 from S1): every point of a sphere sees all of it, so the coarse levels, whose grid lights
    # sit inside the sphere, carry most of the light
    ("lgh", {"lgh_split": "none"}, 0.82, 0.90),
    # the defaults: at 3,000 VPLs every VPL its own light, the hierarchy's limit (measured 0.997)
    ("lgh", {}, 0.98, 1.02),
    ("lgh", {"lgh_alpha": 4.0, "lgh_start_level": 0}, 0.96, 1.02),
    # paper 003's interleaved sixteenth of the VPLs per pixel, x 16, filtered, SVO rays (measured 0.971;
    # 0.997 with exact rays: the sphere's voxels hide some grazing rays)
    ("svo", {}, 0.95, 1.02),
])
def test_furnace_indirect_is_the_geometric_series(furnace, method, settings, low, high):
    """Every bounce adds rho times the last: indirect = direct (rho + rho^2 + rho^3); direct = rho/pi I/R^2."""
    got = ref.render_usdml(furnace, method, 3000, BOUNCES, 24, **settings)
    hit = got["direct"].max(axis=-1) > 0
    assert hit.all()                                           # the camera is inside: every pixel sees the shell
    direct = RHO / math.pi * INTENSITY / RADIUS ** 2
    np.testing.assert_allclose(got["direct"][hit].mean(), direct, rtol=0.01)
    ratio = _lum(got["indirect"]) / _lum(got["direct"]) / ref.furnace_expected(RHO, BOUNCES)
    assert low < ratio < high, ratio


@pytest.fixture(scope="module")
def mitsuba_box(box):
    pytest.importorskip("mitsuba")
    return ref.render_mitsuba(box, 32, BOUNCES, 64)


def test_mitsuba_max_depth_is_bounces_plus_two(furnace):
    """The reference's own furnace: max_depth = B + 2 minus max_depth = 2 is B indirect bounces."""
    pytest.importorskip("mitsuba")
    for bounces in (1, 3):
        r = ref.render_mitsuba(furnace, 16, bounces, 16)
        np.testing.assert_allclose(_lum(r["indirect"]) / _lum(r["direct"]), ref.furnace_expected(RHO, bounces),
                                   rtol=0.01)


@pytest.mark.parametrize("method,settings,energy,blocks", [
    pytest.param("vpl-bruteforce", {}, 0.04, 0.05, marks=pytest.mark.slow),      # 9 s: every VPL, exact rays
    ("lgh", {"lgh_split": "none"}, 0.1, 0.15), ("lgh", {}, 0.04, 0.05), ("svo", {}, 0.04, 0.05)])
def test_indirect_energy_matches_path_tracing(box, mitsuba_box, method, settings, energy, blocks):
    """Closed box, two point lights: direct within 1 %; indirect energy and median 16x16-block error within
    the targets (10 %, 15 %), tighter for brute force and for the defaults of ``--gi lgh``, which at this count
    take every VPL its own light (measured 5000 VPLs, 32 px: brute force 0.982 / 1.3 %, lgh's defaults 0.973 /
    2.5 %, its single hierarchy 0.967 / 3.7 % (0.945 / 5.7 % before α was chosen per frame), svo 0.982 / 2.1 %
    (exact rays: 0.989 / 1.1 %); isotropic VPLs: 0.44, 0.55)."""
    got = ref.render_usdml(box, method, 5000, BOUNCES, 32, **settings)
    assert abs(ref.energy_ratio(got["direct"], mitsuba_box["direct"]) - 1) < 0.01
    assert abs(ref.energy_ratio(got["indirect"], mitsuba_box["indirect"]) - 1) < energy
    assert ref.block_error(got["indirect"], mitsuba_box["indirect"]) <= blocks
