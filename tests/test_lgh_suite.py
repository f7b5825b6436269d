"""tools/lgh_suite.py: the LGH against brute force over the seeded suite's held-back half (issue 37)."""

import json
import subprocess
import sys

from conftest import ROOT

sys.path.insert(0, str(ROOT / "tools"))
import lgh_suite  # noqa: E402
import stage_suite  # noqa: E402


def test_report_split_only_and_rows_as_compare_measures(tmp_path):
    for seed in (0, 1):
        stage_suite.make_suite_stage(str(tmp_path), "open", 64, seed)
    assert [i["seed"] for _, i in lgh_suite.suite_stages(str(tmp_path), "report")] == [1]
    assert [i["seed"] for _, i in lgh_suite.suite_stages(str(tmp_path), "all")] == [0, 1]
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "lgh_suite.py"), str(tmp_path), "--imageWidth", "16",
                          "--gi-vpls", "300", "--json"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = json.loads(run.stdout)
    assert len(rows) == 1 and rows[0]["seed"] == 1 and rows[0]["split"] == "report" and rows[0]["mode"] == "gi"
    r = rows[0]
    assert r["vpls"] == 300 and r["rel_rmse"] > 0 and r["speedup"] > 0
    lo, hi = r["estimated_interval"]
    assert r["estimate_holds"] == (lo <= r["rel_rmse"] <= hi)
    assert "suite_open_64_s1.usda --gi lgh, 300 VPLs" in run.stderr


def test_an_empty_folder_is_a_one_line_error(tmp_path):
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "lgh_suite.py"), str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "no suite stage" in run.stderr and "Traceback" not in run.stderr


def test_direct_rows_at_a_height_of_their_own(tmp_path):
    """--direct-height: the frame conformed to that height (the suite's 16:9 cameras at 512x512, issue 37's frame)."""
    stage_suite.make_suite_stage(str(tmp_path), "interior", 64, 1)
    rows = lgh_suite.measure(str(tmp_path), "report", [], [], [64], 16, 16, 0, direct_height=16)
    assert len(rows) == 1 and rows[0]["mode"] == "direct" and list(rows[0]["resolution"]) == [16, 16]
    assert rows[0]["compared_pixels"] > 0
