"""usdml's exact render of a stage against an independent one (Mitsuba 3, :mod:`usdml.reference`).

Two comparisons, both against code that shares nothing with usdml's renderer:

* **At pixel centres** (usdml with one primary ray per pixel): the ``shadow`` AOV against Mitsuba's
  own ray queries (mean absolute difference and bias), and ``direct`` against the Lambertian sum
  over the lights those queries find visible (mean ratio and per-pixel relative RMSE).
* **Pixel-integrated** (usdml at each ``--pixel-samples`` N): ``direct`` against a box-filtered
  Mitsuba render with ``--spp`` stratified samples per pixel, light by light, as per-pixel relative
  RMSE (the RMSE over pixels and channels divided by the reference's mean), with usdml's seconds per
  frame at each N.

    python tools/reference_compare.py stages/boxes.usda --imageWidth 160 --spp 1024 --pixel-samples 1,4,16
    python tools/reference_compare.py stages/boxes.usda --exr old.exr   # a render made elsewhere, at centres

Needs ``mitsuba`` (usdml's ``test`` extra). Prints one line per figure, or JSON with ``--json``.
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

from usdml.reference import relative_rmse


def render_usdml(stage: str, width: int, samples: int, out: str) -> float:
    """Render ``stage`` with the usdml command (exact visibility); returns its seconds per frame. The lights are
    unseen, as the reference hides its emitters: every pixel shows the surface its ray hits."""
    cmd = [sys.executable, "-m", "usdml.cli", "-q", "render", stage, out, "--imageWidth", str(width),
           "--visibility", "exact", "--pixel-samples", str(samples), "--aovs", "direct,shadow,lightCount",
           "--no-visible-lights", "--json"]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return float(json.loads(done.stdout)["secondsPerFrame"])


def centre_figures(buffers: dict, shadow: np.ndarray, facing: np.ndarray, direct: np.ndarray) -> dict:
    got_s, got_d = buffers["shadow"].astype(np.float64), buffers["direct"].astype(np.float64)
    return {"shadow_mean_abs_diff": float(np.abs(got_s - shadow).mean()),
            "shadow_bias": float((got_s - shadow).mean()),
            "facing_disagree": float((buffers["lightCount"] != facing).mean()) if "lightCount" in buffers else None,
            "direct_mean_ratio": float(got_d.mean() / direct.mean()),
            "direct_rel_rmse": relative_rmse(got_d, direct)}


def main(argv=None) -> int:
    from usdml import reference
    from usdml.aov.exr import read_exr

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--frame", type=float, default=1.0, help="timecode (default: %(default)g)")
    p.add_argument("--imageWidth", type=int, default=160)
    p.add_argument("--spp", type=int, default=1024, help="Mitsuba samples per pixel (default 1024)")
    p.add_argument("--pixel-samples", default="1,4,16", help="usdml's primary rays per pixel to compare")
    p.add_argument("--exr", help="compare this usdml EXR (shadow, direct, at pixel centres) instead of rendering")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    report: dict = {"stage": args.stage, "width": args.imageWidth}
    ref = reference.load(args.stage, args.frame, args.imageWidth)
    t0 = time.perf_counter()
    shadow, facing, direct = reference.shadow_fraction(ref)
    report["reference_centre_seconds"] = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        if args.exr:
            report["centres"] = centre_figures(read_exr(args.exr)[0], shadow, facing, direct)
        else:
            t0 = time.perf_counter()
            integrated = reference.render(ref, args.spp)
            report.update(spp=args.spp, reference_render_seconds=time.perf_counter() - t0, pixel_samples={})
            for n in (int(v) for v in args.pixel_samples.split(",")):
                out = os.path.join(tmp, f"n{n}.exr")
                seconds = render_usdml(args.stage, args.imageWidth, n, out)
                buffers = read_exr(out)[0]
                if n == 1:
                    report["centres"] = centre_figures(buffers, shadow, facing, direct)
                report["pixel_samples"][n] = {"direct_rel_rmse": relative_rmse(buffers["direct"], integrated),
                                              "direct_mean_ratio": float(buffers["direct"].mean() / integrated.mean()),
                                              "seconds_per_frame": seconds}
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    c = report.get("centres")
    if c:
        print(f"pixel centres: shadow |diff| {c['shadow_mean_abs_diff']:.5f} (bias {c['shadow_bias']:+.5f}), "
              f"direct mean ratio {c['direct_mean_ratio']:.4f}, per-pixel rel. RMSE {c['direct_rel_rmse']:.4f}")
    for n, f in report.get("pixel_samples", {}).items():
        print(f"N = {n:3d}: direct rel. RMSE vs pixel-integrated ({args.spp} spp) {f['direct_rel_rmse']:.4f}, "
              f"mean ratio {f['direct_mean_ratio']:.4f}, {f['seconds_per_frame']:.2f} s/frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
