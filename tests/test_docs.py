"""The docs follow from what produced them."""


def test_benchmark_tables_are_current():
    """docs/benchmarks.md's tables are what docs/data/*.json hold (tools/bench_tables.py rewrites them)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    run = subprocess.run([sys.executable, str(root / "tools" / "bench_tables.py"), "--check"], cwd=root,
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
