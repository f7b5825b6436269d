#!/usr/bin/env python
"""A ``usdml render`` command timed as a user runs it, once per visibility backend: the whole command (start
to exit, seconds, and its CPU seconds) and each frame, with the cache empty (a first use: an approximate backend builds its
structures) and then full (a later run: they load). The README's sample render::

    python tools/command_timing.py --visibility exact,voxel --json -- \\
        stages/city.usda out/city.####.exr --frames 1:3 --imageWidth 320 --preview

A frame's seconds are the time between its files and the previous frame's being renamed into place (the first
frame's: the command's own ``secondsPerFrame`` times the frames, less the others), so the command runs as
written, with ``--json`` added for its summary. ``exact`` caches nothing and runs once. The figures are one
machine's: its CPU, cores, the widest vector instructions the compiled kernels use and the load average
before each run come with them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def machine() -> dict:
    """The CPU's model (``lscpu``), its cores, and AVX-512 or AVX2 (what the compiled kernels pick)."""
    cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), [])
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    except OSError:
        lscpu = ""
    model = next((line.split(":", 1)[1].strip() for line in lscpu.splitlines() if line.startswith("Model name")), "")
    return {"cpu": model, "cores": os.cpu_count(),
            "vector": "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "scalar"}


def run(argv: list[str], cache: str) -> dict:
    """``usdml render ARGV --json`` with ``cache`` as its cache folder: the command's seconds and CPU seconds,
    its summary's frames and secondsPerFrame, and each frame's seconds."""
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "usdml.cli", "render", *argv, "--json"], cwd=ROOT, check=True,
                          capture_output=True, text=True, env={**os.environ, "USDML_CACHE_DIR": cache})
    seconds = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    summary = json.loads(done.stdout)
    frames, per_frame = summary["frames"], summary["secondsPerFrame"]
    # the files in frame order, as many per frame; a frame's last one is renamed into place when it is done
    files, previews = summary["outputs"], summary["previews"]
    k, j = len(files) // len(frames), len(previews) // len(frames)
    done_at = [max((ROOT / f).stat().st_mtime for f in files[i * k:(i + 1) * k] + previews[i * j:(i + 1) * j])
               for i in range(len(frames))]
    later = [b - a for a, b in zip(done_at, done_at[1:])]
    return {"seconds": seconds, "cpu_seconds": cpu, "frames": frames, "seconds_per_frame": per_frame,
            "frame_seconds": [per_frame * len(frames) - sum(later)] + later, "load_average": load}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--visibility", default="exact,voxel", help="backends, comma-separated (default: %(default)s)")
    p.add_argument("--json", action="store_true")
    p.add_argument("command", nargs=argparse.REMAINDER, help="-- and usdml render's arguments, as a user types them")
    args = p.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    out = {"command": "usdml render " + " ".join(command), "machine": machine(), "runs": []}
    for name in args.visibility.split(","):
        flags = command + ([] if name == "exact" else ["--visibility", name])
        with tempfile.TemporaryDirectory() as cache:
            for state in ("empty",) if name == "exact" else ("empty", "full"):
                r = {"visibility": name, "cache": state, **run(flags, cache)}
                out["runs"].append(r)
                if not args.json:
                    print(f"{name}, cache {state}: {r['seconds']:.1f} s, frames "
                          + ", ".join(f"{s:.1f}" for s in r["frame_seconds"]) + " s", flush=True)
    exact = next((r for r in out["runs"] if r["visibility"] == "exact"), None)
    for r in out["runs"]:
        if exact is not None and r is not exact:
            r["command_speedup_vs_exact"] = exact["seconds"] / r["seconds"]
            r["cpu_speedup_vs_exact"] = exact["cpu_seconds"] / r["cpu_seconds"]
            if len(r["frame_seconds"]) > 1:     # the frames after the first: structures built or loaded
                r["later_frames_speedup_vs_exact"] = sum(exact["frame_seconds"][1:]) / sum(r["frame_seconds"][1:])
    if args.json:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
