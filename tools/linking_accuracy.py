#!/usr/bin/env python
"""Light linking and light groups against an independent reference (issue 52, items 1 and 2; "Targets").

For each stage (``four``: :func:`linking_reference.four_light_stage`; ``instanced``: 1,000 lights instanced
from two linked prototype lights, :func:`linking_reference.instanced_stage`), seed and mode (``exact``:
``--visibility exact``; ``voxel``: ``--visibility voxel``; ``voxel-budget``: the same with ``--error-budget
0.003``; ``lgh``: ``--direct lgh``, exact shadow rays),
usdml renders the stage at one ray per pixel (the pixel centre) and the reference of tools/linking_reference.py
(no usdml code) renders it twice, with the collections and without them. Reported:

* **linking**: the per-pixel relative colour error ``|got − want|₁ / max(|want|₁, floor)`` (sums over RGB;
  ``floor`` is 1 % of the unlinked reference's mean over the geometry, so a pixel linking turns black counts
  its light against the frame's scale) on the pixels the rules change (where the reference with linking differs
  from the reference without it by more than 10⁻⁴ of the larger): median and 95th percentile; and on the same pixels
  usdml's frame of the stage written without the collections against the reference without them (``unlinked``:
  the mode's own error, which linking did not add); and the first measure on the changed pixels where that
  unlinked frame is within the mode's median target of its reference (``right``: what linking alone adds where
  the mode's own answers, a voxel backend's shadow edges for one, are not wrong);
* **groups**: each ``lightgroup:NAME`` against the reference's group (the same measure, on the pixels either
  lights), and ``max |Σ groups − direct|₁ / max(|direct|₁, floor)`` over the frame (target 0.5 %).

Targets (the issue's): median ≤ 1 % and p95 ≤ 5 % exact, 2 % / 8 % voxel (with or without a budget), 3 % /
15 % lgh; the table marks a row that misses them. Seeds: even seeds were used while writing the stages and the
measure, odd seeds are for reporting.

Usage::

    .venv/bin/python tools/linking_accuracy.py                       # seeds 1,3,5; 96 px; every stage and mode
    .venv/bin/python tools/linking_accuracy.py --seeds 0,2 --stages four --modes exact --width 48
    .venv/bin/python tools/linking_accuracy.py --json rows.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import linking_reference as ref  # noqa: E402

#: mode -> usdml settings
MODES = {"exact": {"visibility": "exact", "direct": "all"},
         "voxel": {"visibility": "voxel", "direct": "all"},
         "voxel-budget": {"visibility": "voxel", "direct": "all", "error_budget": 0.003},
         "lgh": {"visibility": "exact", "direct": "lgh"}}
#: mode -> (median, p95) bounds of the linking error (issue 52's targets; a budgeted voxel frame is held to voxel's)
TARGETS = {"exact": (0.01, 0.05), "voxel": (0.02, 0.08), "voxel-budget": (0.02, 0.08), "lgh": (0.03, 0.15)}
#: the bound on Σ lightgroup:* against direct
GROUP_SUM_TARGET = 0.005
FLOOR = 0.01            # of the unlinked reference's mean over the geometry
CHANGED = 1e-4          # a pixel the rules change: relative difference above this


def write_stage(kind: str, folder: Path, seed: int, lights: int, linked: bool = True) -> str:
    path = folder / f"{kind}_{seed}_{lights}_{int(linked)}.usda"
    if kind == "four":
        return ref.four_light_stage(path, seed, linked)
    return ref.instanced_stage(path, seed, lights, linked)


def usdml_frame(path: str, width: int, height: int, mode: str, aovs) -> dict[str, np.ndarray]:
    """usdml's buffers ``aovs`` of ``path``'s first frame, one ray per pixel centre, ``mode``'s settings."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    d = StageDelegate(path)
    r = FrameRenderer(d, UsdmlSettings(pixel_samples=1, **MODES[mode]), backend_options={"report": lambda s: None})
    try:
        return r.render(d.start_time, width, height, set(aovs)).buffers
    finally:
        r.close()


def relative_error(got: np.ndarray, want: np.ndarray, floor: float) -> np.ndarray:
    """``(H, W)`` per-pixel ``|got − want|₁ / max(|want|₁, floor)`` of ``(H, W, 3)`` images."""
    return np.abs(got - want).sum(2) / np.maximum(np.abs(want).sum(2), floor)


def stats(e: np.ndarray) -> dict:
    if not e.size:
        return {"pixels": 0, "median": None, "p95": None}
    return {"pixels": int(e.size), "median": float(np.median(e)), "p95": float(np.percentile(e, 95))}


def compare(linked_path: str, unlinked_path: str, width: int, mode: str) -> dict:
    """Render the stage ``linked_path`` and the same stage without its collections (``unlinked_path``) with usdml
    in ``mode`` and with the reference; the measures of the module doc."""
    scene = ref.read_scene(linked_path)
    height = scene.height(width)
    linked, unlinked = ref.render(scene, width), ref.render(scene, width, linked=False)
    geometry = linked.box >= 0
    a, b = np.abs(linked.color).sum(2), np.abs(unlinked.color).sum(2)
    floor = FLOOR * float(b[geometry].mean())
    changed = geometry & (np.abs(linked.color - unlinked.color).sum(2) > CHANGED * np.maximum(np.maximum(a, b), floor))
    groups = [f"lightgroup:{g}" for g in scene.groups]
    got = usdml_frame(linked_path, width, height, mode, ["color", "direct", *groups])
    plain = usdml_frame(unlinked_path, width, height, mode, ["color"])
    e = relative_error(got["color"][..., :3].astype(np.float64), linked.color, floor)
    e_plain = relative_error(plain["color"][..., :3].astype(np.float64), unlinked.color, floor)
    right = e_plain <= TARGETS[mode][0]
    row = {"mode": mode, "lights": len(scene.light_pos), "boxes": len(scene.paths), "resolution": [width, height],
           "changed": stats(e[changed]), "unlinked": stats(e_plain[changed]),
           "changed_where_unlinked_right": stats(e[changed & right]), "groups": {}}
    for g, name in zip(scene.groups, groups):
        mine = got[name].astype(np.float64)
        want = linked.groups[g]
        lit = geometry & ((np.abs(want).sum(2) > 0) | (np.abs(mine).sum(2) > 0))
        row["groups"][g] = stats(relative_error(mine, want, floor)[lit])
    total = sum(got[name].astype(np.float64) for name in groups)
    row["group_sum"] = float(relative_error(total, got["direct"].astype(np.float64), floor)[geometry].max())
    med, p95 = TARGETS[mode]
    c = row["changed"]
    row["meets"] = bool(c["pixels"] and c["median"] <= med and c["p95"] <= p95 and row["group_sum"] <= GROUP_SUM_TARGET)
    return row


def measure(kind: str, seed: int, mode: str, width: int, lights: int = 1000) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        paths = [write_stage(kind, Path(tmp), seed, lights, linked) for linked in (True, False)]
        return {"stage": kind, "seed": seed, **compare(*paths, width, mode)}


def _pct(x) -> str:
    return "    -" if x is None else f"{100 * x:6.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--seeds", default="1,3,5", help="stage seeds, comma-separated (odd: reporting; "
                    "default: %(default)s)")
    ap.add_argument("--stages", default="four,instanced", help="four, instanced (default: %(default)s)")
    ap.add_argument("--modes", default="exact,voxel,lgh", help=f"of {', '.join(MODES)} (default: %(default)s)")
    ap.add_argument("--lights", type=int, default=1000, help="the instanced stage's lights (default: %(default)s)")
    ap.add_argument("--width", type=int, default=96, help="image width, a multiple of 3 (default: %(default)s)")
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    rows = []
    print("relative colour error, %: on the pixels linking changes (px, median, p95); there, the same stage unlinked "
          "(unl.); where that is right (right px, median, p95); each group (median/p95); max |Σ groups − direct|",
          flush=True)
    print(f"{'stage':9s} {'seed':>4s} {'mode':12s} {'px':>5s} {'median':>7s} {'p95':>7s} {'unl.med':>7s} "
          f"{'unl.p95':>7s} {'right px':>8s} {'median':>7s} {'p95':>7s} {'Σgroups':>7s}  groups", flush=True)
    for kind in args.stages.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            for mode in args.modes.split(","):
                row = measure(kind, seed, mode, args.width, args.lights)
                rows.append(row)
                c, u, r = row["changed"], row["unlinked"], row["changed_where_unlinked_right"]
                groups = " ".join(f"{g} {_pct(s['median']).strip()}/{_pct(s['p95']).strip()}"
                                  for g, s in row["groups"].items())
                print(f"{kind:9s} {seed:4d} {mode:12s} {c['pixels']:5d} {_pct(c['median']):>7s} {_pct(c['p95']):>7s} "
                      f"{_pct(u['median']):>7s} {_pct(u['p95']):>7s} {r['pixels']:8d} {_pct(r['median']):>7s} "
                      f"{_pct(r['p95']):>7s} {_pct(row['group_sum']):>7s}  {groups}  "
                      f"{'met' if row['meets'] else 'MISSED'}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv[1:] if argv is None else argv, "targets": TARGETS,
                                               "rows": rows}, indent=1))
    return 0 if all(r["meets"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
