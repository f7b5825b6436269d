"""tools/lgh_pathtrace.py (issue 37 items 4-5): a usdml frame against Mitsuba on a stage, a check that can fail.

A closed Cornell-style box (``tools/gi_reference.py``: much of its light indirect) at 32 px: usdml's frame with
brute-force VPL gathering passes issue 37's ``color`` targets against Mitsuba; the same frame with its indirect
light halved misses them. ``usdml.reference`` reads PointInstancer lights where usdml's stage delegate puts them.
"""

import sys

import numpy as np
import pytest

from conftest import ROOT

pytest.importorskip("mitsuba")
sys.path.insert(0, str(ROOT / "tools"))
import gi_reference  # noqa: E402
import lgh_pathtrace  # noqa: E402
import stage_suite  # noqa: E402


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    stage = gi_reference.closed_box(tmp_path_factory.mktemp("box") / "box.usda")
    got = lgh_pathtrace.render_lgh(stage, 32, ["--gi", "vpl-bruteforce", "--vpls", "2000"])
    ref = lgh_pathtrace.render_reference(stage, 32, int(got["params"]["vpl_bounces"]), spp=16, groups=2)
    return got, ref


def test_a_right_frame_passes_and_a_frame_with_half_its_indirect_light_fails(box):
    got, ref = box
    right = lgh_pathtrace.against_reference(got, ref)
    assert right["holds"], right
    assert abs(right["indirect_ratio"] - 1) < 0.1
    assert right["color_ref_noise"] < 0.01 and right["color_ref_block_noise"] < 0.03
    half = dict(got, indirect=0.5 * got["indirect"], color=got["direct"] + 0.5 * got["indirect"])
    wrong = lgh_pathtrace.against_reference(half, ref)
    assert not wrong["holds"], wrong
    assert wrong["color_ratio"] < 0.9 and abs(wrong["indirect_ratio"] - 0.5) < 0.05


def test_the_reference_reads_pointinstancer_lights_where_usdml_does(tmp_path):
    from usdml import reference
    from usdml.stage import StageDelegate

    path = stage_suite.make_suite_stage(str(tmp_path), "open", 1024, 1)["path"]
    ref = reference.load(path, None, 16)
    d = StageDelegate(path)
    lights = d.snapshot(d.start_time).lights
    mine, theirs = np.lexsort(ref.lights.T), np.lexsort(np.asarray(lights.position, np.float64).T)
    assert len(ref.lights) == 1024
    assert np.allclose(ref.lights[mine], np.asarray(lights.position)[theirs], atol=1e-4)
    assert np.allclose(ref.intensity[mine], np.asarray(lights.intensity)[theirs], rtol=1e-5)
    groups = ref.light_groups(32)
    assert len(groups) == 32 and sorted(i for g in groups for i in g) == list(range(1024))


def test_a_kept_compare_is_reused_only_by_the_code_that_made_it(tmp_path, monkeypatch):
    """``--compare-cache``: the same arguments and code reuse the kept result; other code runs the compare again."""
    import json

    stage = str(tmp_path / "suite_open_64_s1.usda")
    args = ["compare", stage, "--gi", "lgh", "--against", "vpl-bruteforce", "--imageWidth", "16", "--json", "-q"]
    result = {"rel_rmse": 0.1, "estimated_rel_rmse": 0.1, "estimated_rel_rmse_interval": [0.05, 0.2], "vpls": 1,
              "speedup": 2.0}
    kept = tmp_path / "cache" / "suite_open_64_s1.w16.json"
    kept.parent.mkdir()
    ran = []
    monkeypatch.setattr(lgh_pathtrace, "_usdml", lambda a: ran.append(a) or dict(result, rel_rmse=0.3))
    kept.write_text(json.dumps({"args": args, "code": lgh_pathtrace.code_digest(), "result": result}))
    assert lgh_pathtrace.compare_estimate(stage, 16, (), str(kept.parent))["measured_rel_rmse"] == 0.1 and not ran
    kept.write_text(json.dumps({"args": args, "code": "older code", "result": result}))
    assert lgh_pathtrace.compare_estimate(stage, 16, (), str(kept.parent))["measured_rel_rmse"] == 0.3 and ran
