"""``usdml compare --gi lgh`` / ``--direct lgh``: the frame's own error estimate beside the measured error
(issue 37 item 5), the measurement being brute force over every pixel, which shares no code with the estimate's
sampled brute force."""

import json
import sys

import pytest

from conftest import ROOT, STAGES
from usdml.cli import main

sys.path.insert(0, str(ROOT / "tools"))
import stage_suite  # noqa: E402


def _check(out: dict) -> None:
    lo, hi = out["estimated_rel_rmse_interval"]
    assert lo <= out["estimated_rel_rmse"] <= hi
    assert out["estimate_holds"] == (lo <= out["rel_rmse"] <= hi)
    assert out["estimate"]["pixels"] > 0


def test_gi_estimate_beside_the_measurement(capsys):
    assert main(["compare", str(STAGES / "cornell.usda"), "--gi", "lgh", "--against", "vpl-bruteforce",
                 "--vpls", "1000", "--imageWidth", "32", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    _check(out)
    assert out["estimate_holds"]
    assert out["lgh_split"] in ("none", "normal", "each")      # --lgh-split auto: what the frame chose
    assert main(["compare", str(STAGES / "cornell.usda"), "--gi", "lgh", "--vpls", "1000", "--imageWidth", "32"]) == 0
    assert "; estimated " in capsys.readouterr().out


def test_brute_force_carries_no_estimate(capsys):
    assert main(["compare", str(STAGES / "cornell.usda"), "--gi", "vpl-bruteforce", "--against", "lgh",
                 "--vpls", "300", "--imageWidth", "16", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "estimated_rel_rmse" not in out and "estimate_holds" not in out


@pytest.fixture(scope="module")
def open_stage(tmp_path_factory):
    return stage_suite.make_suite_stage(str(tmp_path_factory.mktemp("suite")), "open", 64, 0)["path"]


def test_direct_estimate_beside_the_measurement(open_stage, capsys):
    assert main(["compare", open_stage, "--direct", "lgh", "--against", "all", "--imageWidth", "48", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    _check(out)
