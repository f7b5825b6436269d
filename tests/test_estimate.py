"""A frame's own estimate of its visibility error (usdml.render.estimate, issue 36 item 2): its interval
holds the measured ε_v and ε_s (``usdml compare``) on every sample stage, on an analytic scene, and it
reaches the EXR header, ``render --json`` and ``Recorder``'s result."""

import json
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest

from conftest import STAGES, add_quad, ground_stage
from pxr import UsdLux
from usdml.cli import main
from usdml.compare import compare_visibility
from usdml.render.estimate import HEADER_KEYS, mean_interval, sample_pixels, subsets, t95, wilson
from usdml.stage import StageDelegate

#: small grids so the default suite stays fast (the docs' resolutions: test_estimate_docs_resolutions)
SMALL = {"voxel": dict(voxel_resolution=32, direction_step=6.0), "svo": dict(svo_resolution=64), "insm": {}}
#: (stage, width): the big ones slow
STAGE_WIDTHS = [("cornell", 48), ("boxes", 48)]
SLOW_STAGES = [("planes", 32), ("city", 32), ("park", 32), ("creature", 32), ("dragon", 32)]


def _contains(r: dict) -> None:
    for eps in ("eps_v", "eps_s"):
        lo, hi = r[f"estimated_{eps}_interval"]
        assert lo <= r[eps] <= hi, (eps, r[eps], lo, hi)
        assert lo <= r[f"estimated_{eps}"] <= hi


@pytest.mark.parametrize("backend", sorted(SMALL))
@pytest.mark.parametrize("stage,width", STAGE_WIDTHS + [pytest.param(*s, marks=pytest.mark.slow) for s in SLOW_STAGES])
def test_interval_holds_measured(stage, width, backend, capsys):
    """``compare --json``: the estimate's 95 % interval holds the measured ε_v and ε_s on every sample stage."""
    args = ["compare", str(STAGES / f"{stage}.usda"), "--visibility", backend, "--imageWidth", str(width), "--json"]
    for k, v in SMALL[backend].items():
        args += [f"--{k.replace('_', '-')}", str(v)]
    assert main(args) == 0
    r = json.loads(capsys.readouterr().out)
    _contains(r)
    assert min(128, r["pixels"]) <= r["estimate"]["pixels"] <= 256


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["city", "planes"])
def test_estimate_docs_resolutions(stage):
    """docs/benchmarks.md's voxel table: 128 × 72 pixels, 32³/6° to 128³/2° (the corners)."""
    d = StageDelegate(str(STAGES / f"{stage}.usda"))
    for res, step in ((32, 6.0), (128, 2.0)):
        _contains(compare_visibility(d, "voxel", image_width=128,
                                     overrides=dict(voxel_resolution=res, direction_step=step)))


def _floating_square(new_stage):
    """A 40 × 40 ground seen from above, an 8 × 8 square 3 units over it, a point-like light 10 units up:
    the ground point (x, z) is in shadow exactly when |x| and |z| < 4 · 10 / 7."""

    def light(stage):
        add_quad(stage, "/World/square", size=8, y=3)
        s = UsdLux.SphereLight.Define(stage, "/World/light")
        s.CreateRadiusAttr(0.001)
        s.CreateIntensityAttr(1e6)
        s.AddTranslateOp().Set((0.3, 10, 0.2))
    return ground_stage(new_stage, light)


def test_analytic_square(new_stage):
    """The measured ε_v agrees with the shadow's closed form, and the estimate's interval holds it."""
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer
    from usdml.scene import diff
    from usdml.visibility import ExactBackend, make_backend

    path = _floating_square(new_stage)
    d = StageDelegate(path)
    over = dict(voxel_resolution=8, direction_step=6.0)
    r = compare_visibility(d, "voxel", image_width=64, overrides=over)
    # the closed form on the same G-buffer (primary rays only; no shadow ray from the tested code)
    snap = d.snapshot(1)
    w, h = snap.camera.resolution(64)
    ex = ExactBackend()
    vox = make_backend("voxel", d.usdml_settings.updated(**over), "cpu")
    try:
        ex.update(snap, diff(None, snap))
        vox.update(snap, diff(None, snap))
        gb = build_gbuffer(replace(snap, camera=conform_camera(snap.camera, w, h)), ex, w, h)
        hit = gb.hit.ravel()
        p = gb.position.reshape(-1, 3)[hit].astype(np.float64)
        n = gb.geometric.reshape(-1, 3)[hit]
        light = np.array([0.3, 10.0, 0.2])
        ground = p[:, 1] < 1.0
        t = (3.0 - p[:, 1]) / (light[1] - p[:, 1])           # where the ray to the light crosses y = 3
        cross = p + t[:, None] * (light - p)
        truth = ground & (np.abs(cross[:, 0]) < 4) & (np.abs(cross[:, 2]) < 4)
        got = vox.occluded(p, np.repeat(light[None], len(p), 0), normals=n)
    finally:
        ex.close()
        vox.close()
    edge = ground & (np.abs(np.abs(cross[:, [0, 2]]) - 4).min(1) < 0.05)     # rays grazing the square's edge
    wrong = (got != truth) & ground
    measured = wrong.mean()
    assert measured > 0.005                       # the 8³ grid errs along the shadow's edge
    assert abs(r["eps_v"] - measured) <= edge.mean() + 1e-9
    _contains(r)


def test_exact_writes_no_estimate(tmp_path, cornell_path=STAGES / "cornell.usda"):
    from usdml import Recorder

    res = Recorder(image_width=24).record(str(cornell_path), 1, str(tmp_path / "c.exr"))
    assert res.estimates == {} and res.summary["estimates"] == {}
    from usdml.aov.exr import read_exr

    header = read_exr(str(tmp_path / "c.exr"))[1]
    assert not any(k.startswith("usdml:estimate:") for k in header)


def test_estimate_in_header_json_and_recorder(tmp_path, capsys):
    from usdml import Recorder
    from usdml.aov.exr import read_exr

    stage = str(STAGES / "boxes.usda")
    res = Recorder(image_width=32, visibility="voxel", **SMALL["voxel"]).record(stage, 1, str(tmp_path / "b.exr"))
    e = res.estimates[1.0]
    assert e["eps_v_lo"] <= e["eps_v"] <= e["eps_v_hi"] and e["eps_s_lo"] <= e["eps_s"] <= e["eps_s_hi"]
    assert e["seconds"] > 0 and e["queries"] > 0
    header = read_exr(str(tmp_path / "b.exr"))[1]
    for k in HEADER_KEYS:
        assert header[f"usdml:estimate:{k}"] == pytest.approx(e[k])
    args = ["render", stage, str(tmp_path / "j.exr"), "--imageWidth", "32", "--visibility", "voxel",
            "--voxel-resolution", "32", "--direction-step", "6", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    got = summary["estimates"]["1"]
    for k in ("eps_v", "eps_v_lo", "eps_v_hi", "eps_s", "eps_s_lo", "eps_s_hi", "pixels", "pairs"):
        assert got[k] == e[k]          # the same seed and frame: the same estimate


def test_estimator_pieces():
    rng = np.random.default_rng(0)
    pick = sample_pixels(1000, 100, rng)
    assert len(pick) == 100 and np.all(np.diff(pick) > 0) and np.all(pick // 10 == np.arange(100))
    assert np.array_equal(sample_pixels(50, 100, rng), np.arange(50))
    assert t95(10) == pytest.approx(2.228, abs=2e-3) and t95(1000) == pytest.approx(1.962, abs=1e-3)
    lo, hi = wilson(0.0, 256)
    assert lo == 0 and 0.01 < hi < 0.02
    x = np.zeros(256)
    assert mean_interval(x, 1.0)[2] == pytest.approx(hi)          # no nonzero pixel: Wilson's upper end
    assert mean_interval(x, 0.0) == (0.0, 0.0, 0.0)               # every pixel sampled: the value itself


def test_which_frames_estimate():
    """Approximate shadow rays with ``--direct all`` and lights: yes; exact, ``--direct lgh``, no lights: no."""
    from usdml.render.frame import FrameRenderer
    from usdml.scene import Lights

    d = StageDelegate(str(STAGES / "cornell.usda"))
    lights = d.snapshot(1).lights
    for settings, want in ((dict(visibility="voxel"), True), (dict(visibility="exact"), False),
                           (dict(visibility="voxel", direct="lgh"), False)):
        r = FrameRenderer(d, d.usdml_settings.updated(**settings))
        try:
            assert r.estimates(lights) is want
            assert not r.estimates(Lights.empty())
        finally:
            r.close()


@contextmanager
def _boxes_frame(backend: str, width: int, over: dict):
    """boxes.usda's frame 1 at ``width``: ``(lights, exact, approx, points, normals, geometric)`` of its hit
    pixels, the backends brought to the frame (closed after)."""
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer
    from usdml.scene import diff
    from usdml.visibility import ExactBackend, make_backend

    d = StageDelegate(str(STAGES / "boxes.usda"))
    snap = d.snapshot(1)
    w, h = snap.camera.resolution(width)
    ex, ap = ExactBackend(), make_backend(backend, d.usdml_settings.updated(visibility=backend, **over), "cpu")
    try:
        ex.update(snap, diff(None, snap))
        ap.update(snap, diff(None, snap))
        gb = build_gbuffer(replace(snap, camera=conform_camera(snap.camera, w, h)), ex, w, h)
        hit = gb.hit.ravel()
        yield (snap.lights, ex, ap, *(getattr(gb, a).reshape(-1, 3)[hit] for a in ("position", "normal", "geometric")))
    finally:
        ex.close()
        ap.close()


def test_shared_lights_interval():
    """A ``LIGHT_MAJOR`` backend's estimate (lights drawn once for every sampled pixel) over many draws:
    its interval holds the measured values nearly always (95 % nominal, pixels and lights both sampled)."""
    from usdml.render.estimate import estimate_visibility

    r = compare_visibility(StageDelegate(str(STAGES / "boxes.usda")), "insm", image_width=40)
    held = []
    with _boxes_frame("insm", 40, {}) as (lights, ex, ap, p, n, g):
        for seed in range(20):
            e = estimate_visibility(p, n, g, lights, ex, ap, np.random.default_rng(seed), pixels=128,
                                    shared_lights=8)
            assert e.pairs == 128 * 8 and not e.exact_per_pixel
            held.append((e.eps_v_lo <= r["eps_v"] <= e.eps_v_hi, e.eps_s_lo <= r["eps_s"] <= e.eps_s_hi))
    assert np.mean(held, axis=0).min() >= 0.85, np.mean(held, axis=0)


def test_facing_pairs_among_is_the_filtered_list():
    """``facing_pairs(among=)`` (the budget's sample: each pixel's drawn lights) yields the very queries of
    filtering every facing pair by the mask, in the same order (the city's 1,024 lights, random points)."""
    from usdml.lighting.direct import facing_pairs

    snap = StageDelegate(str(STAGES / "city.usda")).snapshot(1.0)
    rng = np.random.default_rng(5)
    n = 3000
    pts = rng.uniform(-40, 40, (n, 3)) * [1, 0, 1] + [0, 0.5, 0]
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    among = rng.random((n, len(snap.lights))) < 0.05
    every = [np.concatenate(a) for a in zip(*facing_pairs(pts, nrm, snap.lights))]
    keep = among[every[4], every[5]]
    got = [np.concatenate(a) for a in zip(*facing_pairs(pts, nrm, snap.lights, among=among))]
    assert 1000 < len(got[0]) < keep.size
    for want, have in zip(every, got):
        np.testing.assert_array_equal(want[keep], have)


def test_a_frame_sampled_whole_is_measured():
    """A frame whose every pair fits the sample (every hit pixel sampled, pixels × lights within the sample's
    pairs) is traced whole: its estimate is the measured ε_v and ε_s themselves, with no interval around them
    (a bound of about 4 / pixels would refuse a budget a small frame meets), more lights than a pixel's draw."""
    from usdml.render.estimate import estimate_visibility

    over = dict(voxel_resolution=16, direction_step=6.0)
    r = compare_visibility(StageDelegate(str(STAGES / "boxes.usda")), "voxel", image_width=24, overrides=over)
    with _boxes_frame("voxel", 24, over) as (lights, ex, ap, p, n, g):
        n_hit, n_l = len(p), len(lights)
        per_pixel = n_l // 4
        assert n_l > per_pixel
        # the sample's pairs (pixels × lights a pixel) hold the frame's: more pixels asked than it has
        whole = estimate_visibility(p, n, g, lights, ex, ap, np.random.default_rng(0),
                                    pixels=-(-n_hit * n_l // per_pixel), lights_per_pixel=per_pixel)
        drawn = estimate_visibility(p, n, g, lights, ex, ap, np.random.default_rng(0), pixels=n_hit,
                                    lights_per_pixel=per_pixel)
    assert r["eps_v"] > 0.01 and r["pixels"] == n_hit
    assert whole.exact_per_pixel and whole.pairs == n_hit * n_l
    assert whole.eps_v_lo == whole.eps_v == whole.eps_v_hi == pytest.approx(r["eps_v"], rel=1e-9)
    assert whole.eps_s_lo == whole.eps_s == whole.eps_s_hi == pytest.approx(r["eps_s"], rel=1e-9)
    # a pixel's draw of fewer lights than the frame has: a sample, and an interval
    assert not drawn.exact_per_pixel and drawn.eps_v_hi > drawn.eps_v_lo


def test_subsets_are_uniform():
    """The budget's light draw (Floyd's algorithm over rows): distinct lights a row, every 4-subset of 10 about
    equally often over 210,000 rows (chi-square over the 210 subsets, 209 degrees of freedom: 184 here; a
    draw that redraws a repeated element from ``range(j + 1)`` instead of taking ``j`` scores 92,000)."""
    from itertools import combinations

    got = subsets(np.random.default_rng(3), 210_000, 10, 4)
    assert got.min() >= 0 and got.max() <= 9
    rows = np.sort(got, axis=1)
    assert (np.diff(rows, axis=1) > 0).all()
    index = {c: i for i, c in enumerate(combinations(range(10), 4))}
    counts = np.bincount([index[tuple(r)] for r in rows.tolist()], minlength=len(index))
    chi2 = float(((counts - 1000) ** 2 / 1000).sum())
    assert chi2 < 270, chi2
    np.testing.assert_array_equal(np.sort(subsets(np.random.default_rng(0), 3, 5, 5), axis=1), [list(range(5))] * 3)
