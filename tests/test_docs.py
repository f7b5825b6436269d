"""The docs follow from what produced them, and their examples run as written."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_tables_are_current():
    """docs/benchmarks.md's tables are what docs/data/*.json hold (tools/bench_tables.py rewrites them)."""
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "bench_tables.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr


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
