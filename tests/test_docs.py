"""The docs follow from what produced them, and their examples run as written."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def bench_tables_check(root: Path) -> subprocess.CompletedProcess:
    """``tools/bench_tables.py --check`` run on the checkout at ``root``."""
    return subprocess.run([sys.executable, str(root / "tools" / "bench_tables.py"), "--check"], cwd=root,
                          capture_output=True, text=True)


def test_benchmark_tables_and_figures_are_current():
    """Every table and every marked figure of README.md and docs/*.md is what docs/data/*.json hold, and
    no page states more measured figures outside markers than it may (tools/bench_tables.py)."""
    run = bench_tables_check(ROOT)
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.fixture
def docs_copy(tmp_path) -> Path:
    """A copy of what bench_tables.py reads: README.md, docs/*.md, docs/data/ and the tool."""
    (tmp_path / "tools").mkdir()
    shutil.copy(ROOT / "tools" / "bench_tables.py", tmp_path / "tools")
    shutil.copy(ROOT / "README.md", tmp_path)
    shutil.copytree(ROOT / "docs", tmp_path / "docs", ignore=shutil.ignore_patterns("images"))
    assert bench_tables_check(tmp_path).returncode == 0
    return tmp_path


def test_a_figure_edited_by_hand_fails_the_check(docs_copy):
    readme = docs_copy / "README.md"
    text = readme.read_text()
    m = re.search(r"(<!-- fig: city-voxel-frame-vs-exact -->)([^<]*)(<!-- /fig -->)", text)
    assert m, "README.md states the city's voxel frame speed-up through a marker"
    readme.write_text(text.replace(m.group(0), m.group(1) + "99.9×" + m.group(3)))
    run = bench_tables_check(docs_copy)
    assert run.returncode == 1 and "99.9×" in run.stdout


def test_changed_data_fails_the_check(docs_copy):
    data = docs_copy / "docs" / "data" / "frame-speed.json"
    data.write_text(re.sub(r'"voxel_speedup_vs_exact": [\d.]+', '"voxel_speedup_vs_exact": 3.0', data.read_text()))
    run = bench_tables_check(docs_copy)
    assert run.returncode == 1 and "3.0×" in run.stdout


def test_an_untied_figure_in_the_readme_fails_the_check(docs_copy):
    readme = docs_copy / "README.md"
    readme.write_text(readme.read_text().replace("## Commands\n", "## Commands\n\nA frame takes 58 s.\n", 1))
    run = bench_tables_check(docs_copy)
    assert run.returncode == 1 and "README.md:" in run.stderr and "58 s" in run.stderr


def test_an_untied_figure_in_a_design_page_fails_the_check(docs_copy):
    """No page but the changelog may state a measured figure that docs/data does not hold."""
    page = docs_copy / "docs" / "svo.md"
    page.write_text(page.read_text().replace("## Traversal (Fig. 3)\n", "## Traversal (Fig. 3)\n\nA walk takes 9.5 ns.\n", 1))
    run = bench_tables_check(docs_copy)
    assert run.returncode == 1 and "docs/svo.md:" in run.stderr and "9.5 ns" in run.stderr


def test_the_changelog_is_not_checked(docs_copy):
    page = docs_copy / "docs" / "CHANGELOG.md"
    page.write_text(page.read_text() + "\n## A run\n\nA walk took 9.5 ns.\n")
    assert bench_tables_check(docs_copy).returncode == 0


def test_a_paper_or_chosen_figure_is_marked_and_holds_one_figure(docs_copy):
    """``<!-- paper -->``, ``<!-- set -->`` and ``<!-- calc -->`` exempt exactly one figure each: a marked
    figure passes, a marker around two figures or none fails."""
    page = docs_copy / "docs" / "svo.md"
    text = page.read_text()
    page.write_text(text.replace("## Traversal (Fig. 3)\n", "## Traversal (Fig. 3)\n\nThe paper's walk: "
                                 "<!-- paper -->9.5 ns<!-- /paper -->.\n", 1))
    assert bench_tables_check(docs_copy).returncode == 0
    for body in ("9.5 ns and 3 ms", "fast"):
        page.write_text(text.replace("## Traversal (Fig. 3)\n", "## Traversal (Fig. 3)\n\nThe paper's walk: "
                                     f"<!-- paper -->{body}<!-- /paper -->.\n", 1))
        run = bench_tables_check(docs_copy)
        assert run.returncode == 1 and "must hold exactly one figure" in run.stderr, body


def test_readme_is_an_entry_point():
    """The README stays short (what, the two commands, the commands, conventions); detail is in docs/."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


def readme_python(section: str) -> str:
    """The first ```python block of README.md's ``## section``."""
    text = (ROOT / "README.md").read_text()
    body = text.split(f"\n## {section}\n", 1)[1].split("\n## ", 1)[0]
    return re.search(r"```python\n(.*?)```", body, re.S).group(1)


def test_the_pipeline_example_names_a_committed_stage():
    code = readme_python("From a pipeline script")
    compile(code, "README.md", "exec")
    paths = re.findall(r'"(stages/[^"]+)"', code)
    assert paths and all((ROOT / p).is_file() for p in paths)


@pytest.mark.slow      # 30-45 s on two cores: three voxel frames of the park
def test_the_pipeline_example_runs_as_written(tmp_path):
    """README's "From a pipeline script" example, run where ``stages/`` is the repository's: it writes
    the frames it says."""
    (tmp_path / "stages").symlink_to(ROOT / "stages")
    env = {**os.environ, "USDML_CACHE_DIR": str(tmp_path / "cache")}
    run = subprocess.run([sys.executable, "-c", readme_python("From a pipeline script")], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "['out/park.0012.exr']" in run.stdout
    assert sorted(p.name for p in (tmp_path / "out").glob("*.exr")) == [f"park.00{f}.exr" for f in (12, 13, 14)]


def test_the_readme_s_speed_up_is_measured_with_its_command_as_written():
    """Issue 55, item 10: the README's figure for its sample render is what that command gives, run as written
    with and without ``--visibility voxel`` (tools/command_timing.py), on the machine the data names; editing
    the command in the README asks for a new measurement."""
    import json

    text = (ROOT / "README.md").read_text()
    command = re.search(r"```sh\n\.venv/bin/(usdml render [^\n]*)\n", text).group(1)
    data = json.loads((ROOT / "docs" / "data" / "readme-render.json").read_text())
    (run,) = data["runs"]
    assert run["output"]["command"] == command and run["command"].endswith("-- " + command.removeprefix("usdml render "))
    machine = run["output"]["machine"]
    assert machine["cpu"] and machine["cores"] >= 1 and machine["vector"]
    assert {(r["visibility"], r["cache"]) for r in run["output"]["runs"]} == {
        ("exact", "empty"), ("voxel", "empty"), ("voxel", "full")}


def test_command_timing_times_each_frame_of_a_command(new_stage, tmp_path):
    """tools/command_timing.py on a two-frame render: the command's seconds and CPU seconds, each frame's, the
    machine."""
    import json

    from conftest import add_quad
    from pxr import UsdLux

    stage = new_stage(start=1, end=2)
    add_quad(stage, "/World/ground", size=4)
    UsdLux.SphereLight.Define(stage, "/World/bulb").AddTranslateOp().Set((0, 2, 0))
    stage.Save()
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "command_timing.py"), "--visibility", "exact", "--json",
                          "--", stage.GetRootLayer().realPath, str(tmp_path / "f.####.exr"), "--frames", "1:2",
                          "--imageWidth", "8", "--preview"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    (r,) = out["runs"]
    assert r["frames"] == [1.0, 2.0] and len(r["frame_seconds"]) == 2 and min(r["frame_seconds"]) > 0
    assert r["seconds"] > sum(r["frame_seconds"]) * 0.5 and r["cpu_seconds"] > 0
    assert out["machine"]["cores"] == os.cpu_count()
