"""Charts (usdml.plots): every tool's ``--plot`` chart drawn from its committed table data, and
``usdml compare --plot``'s heat map and histogram; PNGs that are not blank."""

from __future__ import annotations

import importlib
import json
import sys

import numpy as np
import pytest

from conftest import ROOT, STAGES
from usdml.cli import main

pytest.importorskip("matplotlib")

sys.path.insert(0, str(ROOT / "tools"))

#: tool -> (docs/data table, what of the tool's JSON output its chart takes)
CHARTS = {
    "voxel_table": ("voxel-matrix", lambda out: out),
    "light_scaling": ("light-scaling", lambda out: out),
    "lgh_build_times": ("lgh-build", lambda out: out["rows"]),
    "gi_table": ("gi-lgh", lambda out: out["rows"]),
    "svo_gi_table": ("gi-svo", lambda out: out["rows"]),
    "insm_table": ("insm", lambda out: out["rows"]),
    "direct_lgh_scaling": ("direct-lgh", lambda out: out),
}


def _not_blank(path) -> None:
    import OpenImageIO as oiio
    img = oiio.ImageInput.open(str(path))
    data = np.asarray(img.read_image("uint8"))[..., :3]
    img.close()
    assert data.shape[0] > 100 and data.shape[1] > 100
    assert np.any(np.abs(data.astype(int) - data[0, 0]) > 30, axis=2).mean() > 0.01     # lines and labels drawn
    assert len(np.unique(data.reshape(-1, 3), axis=0)) > 20                          # more than one colour


@pytest.mark.parametrize("tool", sorted(CHARTS))
def test_every_tool_charts_its_table(tool, tmp_path):
    table, take = CHARTS[tool]
    data = json.loads((ROOT / "docs" / "data" / f"{table}.json").read_text())
    rows = [r for run in data["runs"] for r in (take(run["output"]) if run["output"] is not None else [])]
    assert rows
    module = importlib.import_module(tool)
    png = tmp_path / f"{tool}.png"
    module.chart(rows, str(png))
    _not_blank(png)


def test_compare_plots_its_heat_map_and_histogram(tmp_path, capsys):
    prefix = tmp_path / "cornell"
    assert main(["compare", str(STAGES / "cornell.usda"), "--visibility", "svo", "--imageWidth", "48", "--plot",
                 str(prefix), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["plot"] == [f"{prefix}.heatmap.png", f"{prefix}.hist.png"]
    _not_blank(f"{prefix}.hist.png")
    assert (tmp_path / "cornell.heatmap.png").stat().st_size > 0
