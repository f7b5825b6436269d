#!/usr/bin/env python
"""``--gi lgh`` against path tracing, and its own error estimate against brute force, on suite stages (issue 37,
items 4 and 5).

Usage::

    python tools/make_stages.py --suite --out /tmp/suite --seeds 0-3 --lights 64,1024
    python tools/lgh_pathtrace.py /tmp/suite [--seeds 1,3] [--imageWidth 96] [--spp 32] [--groups 32]
        [--estimate-width 64] [--no-estimate | --no-reference] [--compare-cache DIR] [--json] [--check]
        [-- USDML-FLAGS...]

For each stage, with usdml's and the stage's defaults (plus any ``usdml render`` flags after ``--``):

* **Path tracing** (item 4): ``usdml render STAGE --gi lgh`` and Mitsuba 3 (:mod:`usdml.reference`, the stage
  read with pxr alone) at the same camera and width, Mitsuba's ``max_depth`` set from the render's
  ``vpl_bounces`` (``bounces + 2``; direct light is ``max_depth = 2`` of the same samples, so ``indirect`` is
  their difference). Lights are rendered in ``--groups`` groups of neighbours (one light each up to that many),
  a path picking a light of its group by power: one render of every light is dominated by light-selection
  noise. Reported: the ratio of means (Rec. 709 luminance) of ``color`` and of ``indirect``, the median
  16×16-block relative error of each, and the reference's own noise: the same two figures between two halves
  of its samples (different seeds), halved (the error of their mean). Target: ``color`` within 10 % in mean and
  at most 12 % block error.
* **The estimate** (item 5): ``usdml compare STAGE --gi lgh --against vpl-bruteforce --json`` at
  ``--estimate-width`` on the same VPLs and seed: the measured relative RMSE of ``indirect``, the frame's own
  estimate (``usdml:estimate:gi:*``) and its 95 % interval, and whether the interval holds the measurement.
  ``--compare-cache DIR`` keeps each compare's JSON with its arguments and reuses it when they and the
  renderer's code (:func:`code_digest`) match.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gi_reference import block_error, energy_ratio  # noqa: E402
from stage_suite import parse_seeds  # noqa: E402

#: issue 37 item 4: color's mean within this fraction, its median block error at most this
MEAN_TOLERANCE, BLOCK_TOLERANCE = 0.10, 0.12
#: the render's settings a row keeps (the LGH's, whatever their defaults were when it ran)
SETTINGS = ("gi", "lgh_", "vpl_", "shadow_", "interleave", "seed")
USDML = ("-c", "from usdml.cli import main; raise SystemExit(main())")


def _usdml(args: list[str]) -> dict:
    """``usdml ARGS`` with this interpreter; its ``--json`` summary."""
    p = subprocess.run([sys.executable, *USDML, *args], capture_output=True, text=True)
    if p.returncode:
        raise RuntimeError(f"usdml {' '.join(args)} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    return json.loads(p.stdout)


def render_lgh(stage: str, width: int, flags=()) -> dict:
    """usdml's ``--gi lgh`` frame: ``color``, ``direct``, ``indirect`` (H, W, 3) float32, its ``params``, its
    ``estimate`` (the header's ``usdml:estimate:gi:*``) and ``seconds``."""
    from usdml.aov.exr import read_exr

    with tempfile.TemporaryDirectory() as tmp:
        exr = os.path.join(tmp, "frame.exr")
        summary = _usdml(["render", stage, exr, "--gi", "lgh", "--imageWidth", str(width),
                          "--aovs", "color,direct,indirect", "--json", "-q", *flags])
        aovs, header = read_exr(exr)
    out = {aov: np.ascontiguousarray(aovs[aov][..., :3], dtype=np.float32) for aov in ("color", "direct", "indirect")}
    prefix = "usdml:estimate:gi:"
    out["estimate"] = {k[len(prefix):]: v for k, v in header.items() if k.startswith(prefix)}
    out["params"] = json.loads(header["usdml:settings"])["params"]
    out["seconds"] = summary["secondsPerFrame"]
    return out


def render_reference(stage: str, width: int, bounces: int, spp: int, groups: int, seed: int = 0) -> dict:
    """Mitsuba's ``color`` and ``indirect`` (H, W, 3) float64, each as two halves of ``spp`` samples per pixel
    and light group (seeds ``seed`` and ``seed + 1``): ``{"color": (a, b), "indirect": (a, b), "seconds"}``."""
    from usdml import reference

    mi = reference.mitsuba()
    mi.set_log_level(mi.LogLevel.Error)
    t0 = time.perf_counter()
    ref = reference.load(stage, None, width)
    ref.definition["sensor"]["sampler"] = {"type": "independent", "sample_count": max(1, spp // 2)}
    integrators = [mi.load_dict({"type": "path", "max_depth": d, "hide_emitters": True}) for d in (2, bounces + 2)]
    direct, total = (np.zeros((2, ref.height, ref.width, 3)) for _ in range(2))
    for k, lights in enumerate(ref.light_groups(groups)):
        scene = ref.scene(lights, weighted=True)
        for half in (0, 1):
            s = 2 * (seed + k) + half
            direct[half] += np.array(mi.render(scene, integrator=integrators[0], spp=max(1, spp // 2), seed=s))
            total[half] += np.array(mi.render(scene, integrator=integrators[1], spp=max(1, spp // 2), seed=s))
    return {"color": tuple(total), "indirect": tuple(total - direct), "seconds": time.perf_counter() - t0}


def against_reference(got: dict, ref: dict) -> dict:
    """Ratio of means and median 16×16-block error of ``color`` and ``indirect`` against the mean of the
    reference's halves, the reference's own noise in both, and whether ``color`` meets issue 37's targets."""
    row = {}
    for aov in ("color", "indirect"):
        a, b = ref[aov]
        mean = 0.5 * (a + b)
        row[f"{aov}_ratio"] = energy_ratio(got[aov], mean)
        row[f"{aov}_block_error"] = block_error(got[aov], mean)
        # the error of the halves' mean: half their difference
        row[f"{aov}_ref_noise"] = 0.5 * abs(energy_ratio(a, b) - 1.0)
        row[f"{aov}_ref_block_noise"] = 0.5 * block_error(a, b)
    row["holds"] = bool(abs(row["color_ratio"] - 1.0) <= MEAN_TOLERANCE and row["color_block_error"] <= BLOCK_TOLERANCE)
    return row


def code_digest() -> str:
    """A digest of the renderer's code (``usdml/`` and ``kernels/`` sources): a kept compare is reused only by the
    code that made it."""
    import hashlib
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha1()
    for f in sorted([*root.glob("usdml/**/*.py"), *root.glob("kernels/*.[ch]"), *root.glob("kernels/*.py")]):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def compare_estimate(stage: str, width: int, flags=(), cache: str | None = None) -> dict:
    """``usdml compare --gi lgh --against vpl-bruteforce --json``: measured and estimated relative RMSE of
    ``indirect``, the estimate's interval, whether it holds the measurement, the speed-up."""
    args = ["compare", stage, "--gi", "lgh", "--against", "vpl-bruteforce", "--imageWidth", str(width), "--json",
            "-q", *flags]
    path = cache and os.path.join(cache, os.path.splitext(os.path.basename(stage))[0] + f".w{width}.json")
    kept = json.load(open(path)) if path and os.path.exists(path) else {}
    code = code_digest() if path else ""
    if kept.get("args") == args and kept.get("code") == code:
        r = kept["result"]
    else:
        r = _usdml(args)
        if path:
            os.makedirs(cache, exist_ok=True)
            with open(path, "w") as f:
                json.dump({"args": args, "code": code, "result": r}, f, indent=1)
    lo, hi = r["estimated_rel_rmse_interval"]
    return {"estimate_width": width, "vpls": r["vpls"], "measured_rel_rmse": r["rel_rmse"],
            "estimated_rel_rmse": r["estimated_rel_rmse"], "estimated_interval": [lo, hi],
            "interval_holds": bool(lo <= r["rel_rmse"] <= hi), "speedup": r["speedup"],
            "compare_settings": {k: r[k] for k in ("lgh_alpha", "shadow_samples", "interleave", "lgh_start_level",
                                                   "shadow_targets") if k in r}}


def pathtrace(stage: str, width: int, spp: int, groups: int, flags=()) -> dict:
    """Item 4 on one stage: usdml's ``--gi lgh`` frame against Mitsuba's."""
    got = render_lgh(stage, width, flags)
    bounces = int(got["params"]["vpl_bounces"])
    ref = render_reference(stage, width, bounces, spp, groups, int(got["params"]["seed"]))
    return {"resolution": list(got["color"].shape[1::-1]), "spp": spp, "groups": groups, "bounces": bounces,
            "vpls": int(got["params"]["vpl_count"]), **against_reference(got, ref), "lgh_seconds": got["seconds"],
            "reference_seconds": ref["seconds"], "frame_estimate": got["estimate"],
            "settings": {k: v for k, v in got["params"].items() if k.startswith(SETTINGS)}}


def stage_paths(paths: list[str], seeds: str | None) -> list[str]:
    """Stage files, a folder standing for its ``suite_*_s<seed>.usda`` stages (of ``seeds`` when given),
    odd seeds (the reported half) first."""
    out = []
    for path in paths:
        if not os.path.isdir(path):
            out.append(path)
            continue
        wanted = parse_seeds(seeds) if seeds else None
        found = []
        for name in sorted(os.listdir(path)):
            stem = os.path.splitext(name)[0]
            if name.startswith("suite_") and name.endswith(".usda"):
                seed = int(stem.rsplit("_s", 1)[1])
                if wanted is None or seed in wanted:
                    found.append((seed % 2 == 0, seed, name))
        out += [os.path.join(path, name) for *_, name in sorted(found)]
    return out


def _git() -> str:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    run = lambda *a: subprocess.run(["git", "-C", root, *a], capture_output=True, text=True).stdout.strip()  # noqa: E731
    dirty = run("status", "--porcelain", "--", "usdml", "kernels")
    return run("rev-parse", "--short", "HEAD") + (" (usdml/ or kernels/ modified)" if dirty else "")


def _print(r: dict) -> None:
    parts = [r["stage"]]
    if "color_ratio" in r:
        parts.append(f"color {r['color_ratio']:.3f}x, block {100 * r['color_block_error']:.1f} % "
                     f"({'holds' if r['holds'] else 'MISSES'}); indirect {r['indirect_ratio']:.3f}x, block "
                     f"{100 * r['indirect_block_error']:.1f} %; reference noise {100 * r['color_ref_noise']:.2f} % / "
                     f"{100 * r['color_ref_block_noise']:.1f} % ({r['reference_seconds']:.0f} s)")
    if "measured_rel_rmse" in r:
        lo, hi = r["estimated_interval"]
        parts.append(f"estimate {100 * r['estimated_rel_rmse']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}] vs measured "
                     f"{100 * r['measured_rel_rmse']:.1f} % ({'holds' if r['interval_holds'] else 'MISSES'})")
    print("; ".join(parts), file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    flags = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("stages", nargs="+", help="USD stages (a Mesh/SphereLight subset usdml.reference reads), or "
                   "folders of suite stages (tools/make_stages.py --suite)")
    p.add_argument("--seeds", help="with a folder: the suite seeds to take, e.g. 1,3 or 0-3 (default: all)")
    p.add_argument("--imageWidth", type=int, default=96)
    p.add_argument("--spp", type=int, default=32, help="Mitsuba samples per pixel for each light group")
    p.add_argument("--groups", type=int, default=32, help="Mitsuba renders per image, of neighbouring lights")
    p.add_argument("--estimate-width", type=int, default=64, help="usdml compare's width for the estimate")
    p.add_argument("--no-estimate", action="store_true", help="item 4 only (no brute-force compare)")
    p.add_argument("--no-reference", action="store_true", help="item 5 only (no path tracing)")
    p.add_argument("--compare-cache", metavar="DIR", help="keep and reuse usdml compare's JSON here")
    p.add_argument("--json", action="store_true", help="print every row as JSON at the end")
    p.add_argument("--check", action="store_true", help="exit 1 when a stage's color misses the targets")
    a = p.parse_args(argv)
    rows = []
    for stage in stage_paths(a.stages, a.seeds):
        rows.append({"stage": os.path.basename(stage)})
        if not a.no_reference:
            rows[-1].update(pathtrace(stage, a.imageWidth, a.spp, a.groups, flags))
        if not a.no_estimate:
            rows[-1].update(compare_estimate(stage, a.estimate_width, flags, a.compare_cache))
        _print(rows[-1])
    if a.json:
        print(json.dumps({"commit": _git(), "flags": flags, "mean_tolerance": MEAN_TOLERANCE,
                          "block_tolerance": BLOCK_TOLERANCE, "rows": rows}, indent=1))
    return 1 if a.check and not all(r.get("holds", True) for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
