"""The voxel cache's sizes and times per stage: each array's bytes in memory and on disk, how long coding,
storing and loading it take, against reading the same words raw (the peer: the uncompressed format
before USDMLC02, a file read plus its digest), and the first render with an empty cache, voxel against
exact, in the same run.

::

    python tools/cache_bench.py stages/cornell.usda stages/city.usda --json > docs/data/cache.json

Every timing is the median of ``--rounds`` runs; the cache lives in a temporary folder.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _median(f, rounds: int) -> float:
    out = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        f()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def _raw_load(path: Path, nbytes: int) -> None:
    """The peer: the words read into a fresh array and hashed, as the uncompressed entries were."""
    data = np.empty(nbytes, np.uint8)
    with open(path, "rb") as f:
        f.readinto(memoryview(data))
    hashlib.blake2b(memoryview(data), digest_size=16).hexdigest()


def first_renders(stage: str, width: int, settings: list[str]) -> dict:
    """Seconds of a first ``usdml render`` of ``stage`` (the whole command, as a user runs it), exact and
    voxel (``settings``: its flags), each with an empty cache."""
    import subprocess

    out = {}
    for visibility in ("exact", "voxel"):
        with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as folder:
            argv = [sys.executable, "-m", "usdml.cli", "render", stage, str(Path(folder) / "f.exr"), "--imageWidth",
                    str(width), "--visibility", visibility, "-q", *(settings if visibility == "voxel" else [])]
            t0 = time.perf_counter()
            subprocess.run(argv, check=True, env={**os.environ, "USDML_CACHE_DIR": cache}, stdout=subprocess.DEVNULL)
            out[visibility] = time.perf_counter() - t0
    return out


def stage_arrays(stage: str, resolution: int, step: float, rounds: int) -> list[dict]:
    from usdml.cache import Cache
    from usdml.render.sequence import build_messages
    from usdml.stage import StageDelegate
    from usdml.visibility import make_backend
    from usdml.visibility.voxel import codec as voxel_codec
    from usdml.scene import diff

    delegate = StageDelegate(stage)
    settings = delegate.usdml_settings.updated(voxel_resolution=resolution, direction_step=step)
    rows = []
    with tempfile.TemporaryDirectory() as root:
        cache = Cache(root)
        backend = make_backend("voxel", settings, "cpu", cache=cache, **build_messages())
        t0 = time.perf_counter()
        backend.update(delegate.snapshot(delegate.start_time), diff(None, delegate.snapshot(delegate.start_time)))
        bake = time.perf_counter() - t0
        for arr in backend.arrays:
            if not arr.key:
                continue
            path = cache.path("voxel", arr.key)
            encode = _median(lambda: voxel_codec.encode(arr.words, arr.resolution), rounds)
            packed, meta = cache.get("voxel", arr.key)
            read = _median(lambda: cache.get("voxel", arr.key), rounds)
            decode = _median(lambda: voxel_codec.decode(packed, meta, arr.resolution), rounds)
            raw = Path(root) / "raw.bin"
            arr.words.tofile(raw)
            raw_load = _median(lambda: _raw_load(raw, arr.words.nbytes), rounds)
            raw.unlink()
            rows.append({"source": arr.source, "dense_bytes": int(arr.words.nbytes),
                         "disk_bytes": path.stat().st_size, "set_bits": int(meta["set_bits"]),
                         "build_seconds": arr.build_seconds, "bake_seconds": bake, "encode_seconds": encode,
                         "read_inflate_seconds": read, "decode_seconds": decode, "load_seconds": read + decode,
                         "raw_load_seconds": raw_load, "load_vs_raw": (read + decode) / raw_load})
        backend.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stages", nargs="+")
    p.add_argument("--voxel-resolution", type=int, default=128, help="(default: %(default)s)")
    p.add_argument("--direction-step", type=float, default=2.0, help="degrees (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="runs per timing, the median kept (default: %(default)s)")
    p.add_argument("--imageWidth", type=int, default=128,
                   help="the first renders' width in pixels (default: %(default)s; 0: no renders)")
    p.add_argument("--json", action="store_true", help="print JSON")
    args = p.parse_args(argv)
    out = {"command": "python tools/cache_bench.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "cpus": os.cpu_count(), "voxel_resolution": args.voxel_resolution, "direction_step": args.direction_step,
           "stages": []}
    for stage in args.stages:
        row = {"stage": stage, "arrays": stage_arrays(stage, args.voxel_resolution, args.direction_step, args.rounds)}
        if args.imageWidth:
            seconds = first_renders(stage, args.imageWidth, ["--voxel-resolution", str(args.voxel_resolution),
                                                             "--direction-step", str(args.direction_step)])
            row["first_render_seconds"] = seconds
            row["first_render_voxel_vs_exact"] = seconds["voxel"] / seconds["exact"]
        out["stages"].append(row)
        if not args.json:
            for a in row["arrays"]:
                print(f"{stage} {a['source']}: {a['dense_bytes'] / 2**20:.1f} MiB -> {a['disk_bytes'] / 2**20:.1f} MiB "
                      f"on disk; load {a['load_seconds']:.2f} s (read+inflate {a['read_inflate_seconds']:.2f}, "
                      f"decode {a['decode_seconds']:.2f}) against raw {a['raw_load_seconds']:.2f} s")
            if "first_render_seconds" in row:
                s = row["first_render_seconds"]
                print(f"{stage} first render: voxel {s['voxel']:.2f} s, exact {s['exact']:.2f} s "
                      f"({row['first_render_voxel_vs_exact']:.1f}x)")
    if args.json:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
