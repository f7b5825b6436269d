#!/usr/bin/env python
"""Survey how usdml handles a folder of USD stages authored elsewhere: rendered, refused (why), crashed.

Usage::

    python tools/survey_stages.py ROOT [ROOT ...] [--imageWidth 64] [--timeout 120] [--json out.json]
                                  [--render-args "--visibility voxel --voxel-resolution 32"]

Every ``.usd/.usda/.usdc/.usdz`` file under the roots is rendered once (start frame, ``--imageWidth``
pixels, into a temporary folder) with the installed ``usdml`` in a subprocess, as a user would run
it. A stage is *rendered* (exit 0), *refused* (exit 2 with a one-line ``usdml: error:``; the reason
is reported) or *crashed* (anything else: a traceback is a usdml bug). Prints a Markdown table and
per-outcome counts; ``--json`` also writes every row. ``--render-args`` are added to every render
(e.g. another visibility backend, or ``--gi lgh``).
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

EXTENSIONS = {".usd", ".usda", ".usdc", ".usdz"}


def survey_one(stage: Path, out_dir: Path, width: int, timeout: float, extra: list[str] | None = None) -> dict:
    cmd = [sys.executable, "-m", "usdml.cli", "render", str(stage), str(out_dir / f"{stage.stem}.exr"),
           "--imageWidth", str(width)] + list(extra or [])
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"stage": str(stage), "outcome": "timeout", "detail": f"over {timeout:g} s"}
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("usdml:")]
    warnings = [ln for ln in lines if ln.startswith("usdml: warning:")]
    if r.returncode == 0:
        outcome, detail = "rendered", ""
    elif r.returncode == 2 and any(ln.startswith("usdml: error:") for ln in lines):
        outcome = "refused"
        detail = next(ln for ln in lines if ln.startswith("usdml: error:"))[len("usdml: error: "):]
    else:
        outcome = "crashed"
        detail = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
    return {"stage": str(stage), "outcome": outcome, "detail": detail, "warnings": len(warnings),
            "first_warning": warnings[0][len("usdml: warning: "):] if warnings else ""}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("roots", nargs="+", type=Path)
    parser.add_argument("--imageWidth", type=int, default=64, metavar="W", help="image width in pixels (default: %(default)s)")
    parser.add_argument("--timeout", type=float, default=120)
    parser.add_argument("--json", type=Path, help="write all rows to this JSON file")
    parser.add_argument("--render-args", default="", help="more arguments for every render, one string")
    args = parser.parse_args(argv)
    stages = sorted(p for root in args.roots for p in ([root] if root.is_file() else root.rglob("*"))
                    if p.suffix in EXTENSIONS and p.is_file())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for stage in stages:
            rows.append(survey_one(stage, Path(tmp), args.imageWidth, args.timeout, shlex.split(args.render_args)))
            print(f"{rows[-1]['outcome']:>8}  {stage}", file=sys.stderr)
    print("| stage | outcome | reason / first warning |\n|---|---|---|")
    for r in rows:
        why = r["detail"] or r.get("first_warning", "")
        print(f"| {r['stage']} | {r['outcome']} | {why.replace('|', '/')[:160]} |")
    counts = Counter(r["outcome"] for r in rows)
    print("\n" + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) + f" (of {len(rows)})")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 1 if counts.get("crashed") else 0


if __name__ == "__main__":
    sys.exit(main())
