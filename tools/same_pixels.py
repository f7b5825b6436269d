"""Render every sample stage with every visibility backend (and the LGH's indirect and direct light) to
a folder, or compare two such folders pixel by pixel: the check that a restructuring changed no pixel.

::

    python tools/same_pixels.py render before/            # at the commit before the change
    python tools/same_pixels.py render after/             # at the commit after it
    python tools/same_pixels.py compare before/ after/    # exit 1 if any AOV of any render differs

Renders are small (``--imageWidth``, one primary ray per pixel, small voxel / octree / shadow-map
resolutions) so the whole set takes minutes on two cores; each is an EXR per (stage, variant). The
comparison reads the pixels only (headers name the stage's modification time and differ by design).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: variant -> the Recorder's keywords beside the common ones
VARIANTS = {
    "exact": {"visibility": "exact"},
    "voxel": {"visibility": "voxel", "voxel_resolution": 32, "direction_step": 6.0},
    "svo": {"visibility": "svo", "svo_resolution": 32},
    "insm": {"visibility": "insm", "insm_resolution": 64, "insm_light_resolution": 64},
    "gi-lgh": {"visibility": "exact", "gi": "lgh", "vpl_count": 2000},
    "direct-lgh": {"visibility": "exact", "direct": "lgh"},
}


def render(folder: Path, width: int, stages: list[Path], variants: list[str], skip: set[str] = frozenset()) -> int:
    import usdml

    folder.mkdir(parents=True, exist_ok=True)
    for stage in stages:
        for name in variants:
            if f"{stage.stem}.{name}" in skip:
                continue
            out = folder / f"{stage.stem}.{name}.exr"
            t0 = time.perf_counter()
            rec = usdml.Recorder(image_width=width, pixel_samples=1, seed=1, **VARIANTS[name])
            rec.record(str(stage), _start(stage), str(out))
            print(f"{out.name}: {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


def _start(stage: Path) -> float:
    from pxr import Usd

    s = Usd.Stage.Open(str(stage))
    return s.GetStartTimeCode() if s.HasAuthoredTimeCodeRange() else 0.0


def compare(a: Path, b: Path) -> int:
    import numpy as np

    from usdml.aov.exr import read_exr

    names = sorted(p.name for p in a.glob("*.exr"))
    missing = sorted(set(names) ^ {p.name for p in b.glob("*.exr")})
    rows, differ = [], 0
    for name in names:
        if name in missing:
            continue
        x, _ = read_exr(a / name)
        y, _ = read_exr(b / name)
        for aov in sorted(set(x) | set(y)):
            if aov not in x or aov not in y:
                rows.append({"file": name, "aov": aov, "max_abs": None, "pixels": None})
                differ += 1
                continue
            u, v = np.asarray(x[aov], np.float64), np.asarray(y[aov], np.float64)
            same = np.array_equal(u, v, equal_nan=True)
            d = 0.0 if same else float(np.nanmax(np.abs(u - v)))
            rows.append({"file": name, "aov": aov, "max_abs": d,
                         "pixels": 0 if same else int((~np.isclose(u, v, 0, 0, equal_nan=True)).any(-1).sum()
                                                      if u.ndim == 3 else (~np.isclose(u, v, 0, 0, equal_nan=True)).sum())})
            differ += not same
    print(json.dumps({"files": len(names), "missing": missing, "differing_aovs": differ,
                      "differences": [r for r in rows if r["max_abs"] != 0.0]}, indent=2))
    return 1 if differ or missing else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("render", allow_abbrev=False, help="render the set into FOLDER")
    r.add_argument("folder", type=Path)
    r.add_argument("--imageWidth", type=int, default=32, help="image width in pixels (default: %(default)s)")
    r.add_argument("--stages", nargs="*", type=Path, help="stages (default: every stages/*.usda)")
    r.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated (default: %(default)s)")
    r.add_argument("--skip", default="", metavar="STAGE.VARIANT,...",
                   help="renders to leave out, e.g. city_night.insm (100,000 shadow-mapped lights: minutes)")
    c = sub.add_parser("compare", allow_abbrev=False, help="compare two folders' pixels")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = p.parse_args(argv)
    if args.what == "compare":
        return compare(args.a, args.b)
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"unknown variant(s) {', '.join(unknown)}; use {', '.join(VARIANTS)}")
    return render(args.folder, args.imageWidth, args.stages or sorted((ROOT / "stages").glob("*.usda")), variants,
                  {s for s in args.skip.split(",") if s})


if __name__ == "__main__":
    sys.exit(main())
