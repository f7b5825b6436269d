"""Lights of negative intensity, which take light away (UsdLux allows them; Karma renders them): shaded by
every direct-light path against a closed form, every-light under ``--direct lgh``, no VPLs under ``--gi``,
negative domes; NaN and infinities stay errors."""

import math

import numpy as np
import pytest
from pxr import UsdLux

from conftest import ALBEDO, ground_stage
from usdml.cli import main
from usdml.lighting.dome import dome_to_distant_lights
from usdml.render.frame import FrameRenderer
from usdml.scene import Dome
from usdml.settings import UsdmlSettings
from usdml.stage import StageDelegate

#: two point lights over the ground, +I and -I/2: (position, inputs:intensity); a treatAsPoint sphere of radius
#: RADIUS with normalize off has the radiant intensity intensity · π · RADIUS² (UsdLux, README "Light units")
BULBS = (((3.0, 4.0, -2.0), 4000.0), ((-3.0, 2.0, 1.0), -2000.0))
RADIUS = 0.1

#: the direct-light paths: exact (NumPy shading over Embree), voxel's compiled kernel (light_term.h), its Warp
#: kernel (kernels/voxel/shading.py) and its refined shading under a budget, svo (NumPy over its queries), insm
#: (its own fused shading)
PATHS = {
    "exact": {},
    "voxel": {"visibility": "voxel", "voxel_resolution": 32, "direction_step": 6.0},
    "voxel-warp": {"visibility": "voxel", "voxel_resolution": 32, "direction_step": 6.0, "voxel_cpu_kernel": "warp"},
    "voxel-budget": {"visibility": "voxel", "voxel_resolution": 32, "direction_step": 6.0, "error_budget": 0.001},
    "svo": {"visibility": "svo", "svo_resolution": 32},
    "insm": {"visibility": "insm", "insm_resolution": 64, "insm_light_resolution": 64},
}


def _bulbs(bulbs=BULBS):
    def light(stage):
        for i, (position, intensity) in enumerate(bulbs):
            s = UsdLux.SphereLight.Define(stage, f"/World/bulb{i}")
            s.CreateTreatAsPointAttr(True)
            s.CreateRadiusAttr(RADIUS)
            s.CreateIntensityAttr(intensity)
            s.AddTranslateOp().Set(position)
    return light


def _render(path, aovs=("direct", "P", "color", "lightCount"), width=32, **settings):
    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, **settings))
    try:
        return r.render(d.start_time, width, width, set(aovs))
    finally:
        r.close()


def _closed_form(p: np.ndarray, bulbs=BULBS) -> tuple[np.ndarray, np.ndarray]:
    """Lambert and inverse square on the ground (normal +Y) at ``(..., 3)`` points: the direct radiance and the
    sum of the lights' magnitudes (what a relative error of a signed sum is taken against)."""
    signed, magnitude = 0.0, 0.0
    for position, intensity in bulbs:
        to = np.asarray(position) - p
        d2 = (to ** 2).sum(-1)
        term = ALBEDO / math.pi * intensity * math.pi * RADIUS ** 2 * np.maximum(to[..., 1], 0) / np.sqrt(d2) / d2
        signed, magnitude = signed + term, magnitude + np.abs(term)
    return signed, magnitude


@pytest.mark.parametrize("name", PATHS)
def test_a_negative_light_takes_away_its_closed_form(new_stage, name):
    """Each pixel's direct light is the closed-form sum of +I and -I/2 to 1e-3 of its terms' magnitudes, under
    every path; color keeps the negative values (no clamp), and the negative light counts as a facing light."""
    b = _render(ground_stage(new_stage, _bulbs()), **PATHS[name]).buffers
    want, magnitude = _closed_form(b["P"].astype(np.float64))
    got = b["direct"].astype(np.float64)
    rel = np.abs(got - want[..., None]) / magnitude[..., None]
    assert rel.max() < 1e-3, (name, rel.max())
    assert (want < 0).mean() > 0.1 and (got[..., 0] < 0).mean() > 0.1      # under the negative light: below 0
    np.testing.assert_array_equal(b["color"][..., :3], b["direct"])
    assert (b["lightCount"] == 2).all()


def test_direct_lgh_shades_a_negative_light_every_light(new_stage):
    """``--direct lgh`` takes the negative light out of the hierarchy and shades it as ``--direct all`` does: the
    frame with it minus the frame without it is that light alone under ``--direct all``."""
    positive = [((x, 3.0, z), 3000.0) for x in (-4.0, 0.0, 4.0) for z in (-4.0, 4.0)]
    negative = [((1.0, 2.0, 0.5), -2500.0)]
    with_neg = _render(ground_stage(new_stage, _bulbs(positive + negative), "both.usda"), direct="lgh")
    assert with_neg.stats.direct_lgh["grid_lights"] == 6 and with_neg.stats.direct_lgh["every_light"] == 1
    without = _render(ground_stage(new_stage, _bulbs(positive), "positive.usda"), direct="lgh").buffers["direct"]
    alone = _render(ground_stage(new_stage, _bulbs(negative), "negative.usda")).buffers["direct"]
    assert alone.min() < 0
    np.testing.assert_allclose(with_neg.buffers["direct"] - without, alone, rtol=0, atol=1e-5 * np.abs(alone).max())


def test_negative_lights_emit_no_vpls_said_once(new_stage, tmp_path, capsys):
    def lights(stage):
        _bulbs()(stage)
        stage.SetEndTimeCode(2)

    gi = ["--imageWidth", "16", "--pixel-samples", "1", "--gi", "lgh", "--vpls", "200"]
    both = ground_stage(new_stage, lights, "both.usda")
    capsys.readouterr()
    assert main(["render", both, str(tmp_path / "g.####.exr"), "--frames", "1:2", *gi]) == 0
    err = capsys.readouterr().err
    assert err.count("1 light(s) of negative intensity at time 1 emit no VPLs") == 1 and "time 2" not in err
    negative = ground_stage(new_stage, _bulbs(BULBS[1:]), "negative.usda")
    assert main(["render", negative, str(tmp_path / "n.exr"), *gi]) == 0
    assert "no VPLs at time 1: its 1 light(s) have negative intensity; indirect is 0" in capsys.readouterr().err


@pytest.mark.parametrize("texture", [None, "map"])
def test_a_negative_dome_gives_the_negative_of_its_lights(texture):
    rng = np.random.default_rng(3)
    tex = None if texture is None else rng.random((8, 16, 3)).astype(np.float32)
    dome = Dome(path="/dome", radiance=np.array([0.5, 1.0, 2.0]), texture=tex, to_world=np.eye(3))
    neg = Dome(path="/dome", radiance=-dome.radiance, texture=tex, to_world=np.eye(3))
    a, b = dome_to_distant_lights(dome, 64, seed=5), dome_to_distant_lights(neg, 64, seed=5)
    assert len(a) == len(b) > 0 and b.negative().all()
    np.testing.assert_array_equal(a.axis, b.axis)
    np.testing.assert_array_equal(b.intensity, -a.intensity)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_intensity_is_an_error_naming_the_light(new_stage, tmp_path, capsys, value):
    def light(stage):
        UsdLux.SphereLight.Define(stage, "/World/key").CreateIntensityAttr(value)

    path = ground_stage(new_stage, light)
    capsys.readouterr()
    assert main(["render", path, str(tmp_path / "x.exr"), "--imageWidth", "8"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("usdml: error: /World/key.inputs:intensity: value ")
    assert "is not finite" in lines[0]
