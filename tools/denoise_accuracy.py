"""What ``--denoise`` buys at 4 pixel samples, and what it costs (issue 53 item 4).

A seeded family of stages (:func:`write_stage`): a 40 x 40 ground split into two albedos along x = 0 (an albedo
edge from near to far), a box in the lens's focus 3 m from the camera and one or two more nearby, a rect light
above them (soft shadows), and a tall box 10 m away whose vertical edge stands against the dark beyond it. The
camera is a 70 mm lens (``focalLength`` 0.7 in tenths of a metre, a 36 mm film) at f/1 focused at 3 m, close to the issue's
case: the far edge is out of focus (about 4 pixels of blur at 128 wide). Seed s moves and
sizes the boxes and the light and picks the albedos.

Per stage: the noisy frame is ``color`` at 4 pixel samples and ``--light-samples`` 1 (the noise of sampling the
rect light and of the lens), rendered with the guides ``albedo`` and ``denoiseNormal``; the
denoised frame is the same buffers through :func:`usdml.render.denoise.oidn.denoise_frame`, the function the
frame's hook calls. The noise-free answer is the same stage at 64 pixel samples and 16 light samples (256 times
the samples of the noisy frame), rendered twice with other seeds: its noise is ``mean |a - b| / 2`` of the two,
stated per stage; the reference is their mean. The error is the mean over pixels and channels of
``|frame - reference|`` (color's RGB, linear), over the whole frame and over the far edge's band (the pixels
within 12 of its column on the box's rows).

Each ``--denoise-prefilter`` mode is measured on the same noisy buffers. Seeds 0-3 tune (they chose the default
mode), seeds 4-7 report. Cost: the seconds of the denoise step per megapixel at ``--cost-width`` (a frame of that
width, once warm, median of 3), and its share of the frame's render.

    .venv/bin/python tools/denoise_accuracy.py --seeds 0:4 --cost-width 0
    .venv/bin/python tools/denoise_accuracy.py --seeds 4:8 --json /tmp/denoise_accuracy.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile

import numpy as np

WIDTH = 128
#: the camera: 70 mm at f/1 on a 36 mm film (USD's lens units: tenths of a scene unit), focused at 3 m: the far
#: edge's circle of confusion is 1.2 mm on the film, 4 pixels of 128
FOCAL, APERTURE, FSTOP, FOCUS = 0.7, 0.36, 1.0, 3.0
CAMERA_AT, TILT = (0.0, 0.8, 3.0), -8.0
FAR = 10.0                  # the far box's front face, metres from the camera
FAR_ALBEDO = 0.95           # brighter than any ground: what finds the far edge in the albedo
PREFILTERS = ("accurate", "fast", "none")      # --denoise-prefilter's modes


def write_stage(path: str, seed: int) -> None:
    """Stage ``seed`` of the family (module doc), saved at ``path``."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    rng = np.random.default_rng(seed)
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    dark, light = rng.uniform(0.1, 0.3), rng.uniform(0.5, 0.7)
    for name, x0, albedo in (("left", -20.0, dark), ("right", 0.0, light)):
        half = UsdGeom.Mesh.Define(stage, f"/World/ground_{name}")
        half.CreatePointsAttr([(x0, 0, -20), (x0, 0, 20), (x0 + 20, 0, 20), (x0 + 20, 0, -20)])
        half.CreateFaceVertexCountsAttr([4])
        half.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        half.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        half.CreateDisplayColorPrimvar().Set([(albedo, albedo, albedo)])
    z_focus = CAMERA_AT[2] - FOCUS
    boxes = [(rng.uniform(-0.25, 0.25), z_focus, rng.uniform(0.25, 0.4))]
    boxes += [(rng.uniform(-0.6, 0.6), z_focus + rng.uniform(-1.0, 0.8), rng.uniform(0.1, 0.25))
              for _ in range(int(rng.integers(1, 3)))]
    for i, (x, z, size) in enumerate(boxes):
        cube = UsdGeom.Cube.Define(stage, f"/World/box{i}")
        cube.CreateSizeAttr(size)
        cube.AddTranslateOp().Set((x, size / 2, z))
        cube.CreateDisplayColorPrimvar().Set([tuple(rng.uniform(0.3, 0.9, 3))])
    far = UsdGeom.Cube.Define(stage, "/World/far_box")
    far.CreateSizeAttr(1.0)
    far.AddTranslateOp().Set((-0.9 + rng.uniform(-0.2, 0.2), 1.2, CAMERA_AT[2] - FAR - 0.5))
    far.AddScaleOp().Set((1.5, 2.4, 1.0))
    far.CreateDisplayColorPrimvar().Set([(FAR_ALBEDO,) * 3])
    cam = UsdGeom.Camera.Define(stage, "/World/main_cam")
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(APERTURE)
    cam.CreateVerticalApertureAttr(APERTURE * 0.75)
    cam.CreateFStopAttr(FSTOP)
    cam.CreateFocusDistanceAttr(FOCUS)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.05, 100))
    cam.AddTranslateOp().Set(CAMERA_AT)
    cam.AddRotateXOp().Set(TILT)
    rect = UsdLux.RectLight.Define(stage, "/World/panel")
    rect.CreateWidthAttr(float(rng.uniform(0.6, 1.2)))
    rect.CreateHeightAttr(float(rng.uniform(0.4, 0.8)))
    rect.CreateIntensityAttr(float(rng.uniform(15, 25)))
    rect.AddTranslateOp().Set((float(rng.uniform(-0.6, 0.6)), float(rng.uniform(1.2, 1.8)), z_focus - 0.3))
    rect.AddRotateXOp().Set(-90)       # its -Z (its emission) down
    fill = UsdLux.DistantLight.Define(stage, "/World/fill")        # light on the far box's face
    fill.CreateIntensityAttr(0.3)
    fill.CreateAngleAttr(0.0)
    fill.AddRotateXOp().Set(-30)
    stage.Save()


def render(path: str, pixel_samples: int, light_samples: int, seed: int, width: int = WIDTH):
    """``(buffers, seconds)``: color, color_noisy, albedo and denoiseNormal of the stage's frame 0."""
    from usdml.render.frame import FrameRenderer
    from usdml.settings import UsdmlSettings
    from usdml.stage import StageDelegate

    settings = UsdmlSettings(pixel_samples=pixel_samples, light_samples=light_samples, seed=seed)
    delegate = StageDelegate(path)
    renderer = FrameRenderer(delegate, settings)
    try:
        height = round(width * 0.75)
        result = renderer.render(delegate.start_time, width, height, {"color", "albedo", "denoiseNormal"})
    finally:
        renderer.close()
    return result.buffers, result.stats.seconds


def far_edge_band(albedo: np.ndarray) -> np.ndarray:
    """The pixels within 12 columns of the far box's right edge on the top quarter of the rows, where the box is
    (bool (H, W)); the edge is where the box's albedo (:data:`FAR_ALBEDO`) ends on the row an eighth of the way
    down."""
    h, w = albedo.shape[:2]
    box = np.flatnonzero(albedo[h // 8, :, 0] > FAR_ALBEDO - 0.05)
    band = np.zeros((h, w), bool)
    if len(box):
        band[: h // 4, max(0, box.max() - 12): box.max() + 13] = True
    return band


def measure(seed: int, prefilters=PREFILTERS, width: int = WIDTH) -> dict:
    from usdml.render.denoise.oidn import denoise_frame

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, f"denoise_{seed}.usda")
        write_stage(path, seed)
        noisy, seconds = render(path, 4, 1, seed, width)
        refs = [render(path, 64, 16, 1000 + seed + k, width)[0]["color"][..., :3].astype(np.float64) for k in (0, 1)]
    ref = (refs[0] + refs[1]) / 2
    band = far_edge_band(noisy["albedo"])
    row = {"seed": seed, "width": width, "frame_seconds": seconds,
           "reference_noise": float(np.abs(refs[0] - refs[1]).mean() / 2),
           "noisy_error": float(np.abs(noisy["color"][..., :3] - ref).mean()),
           "noisy_edge_error": float(np.abs(noisy["color"][..., :3] - ref)[band].mean()),
           # the edge's contrast in the reference (the far box against what is beyond it): the scale of its profile,
           # so that the edge's error reads as a fraction of the step, as the lens's profile does
           "edge_contrast": float(np.ptp(ref.mean(-1)[band]))}
    for prefilter in prefilters:
        buffers = dict(noisy)
        done = denoise_frame(buffers, ["color"], prefilter)
        diff = np.abs(buffers["color"][..., :3] - ref)
        row[prefilter] = {"error": float(diff.mean()), "edge_error": float(diff[band].mean()),
                          "edge_error_of_contrast": float(diff[band].mean()) / row["edge_contrast"],
                          "ratio": float(diff.mean()) / row["noisy_error"], "seconds": done["seconds"]}
        assert np.array_equal(buffers["color"][..., 3], noisy["color"][..., 3])      # alpha as rendered
    return row


def cost(width: int, prefilters) -> list[dict]:
    """Seconds of the denoise step per megapixel on a ``width`` x 3/4 ``width`` frame for each mode: the median
    of 3, the modes interleaved (the machine's load falls on each alike), warm."""
    from usdml.parallel import cpu_workers
    from usdml.render.denoise.oidn import denoise_frame

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "cost.usda")
        write_stage(path, 0)
        buffers, seconds = render(path, 4, 1, 0, width)
    times = {m: [] for m in prefilters}
    for rep in range(4):
        for m in prefilters:
            t = denoise_frame(dict(buffers), ["color"], m)["seconds"]
            if rep:                 # the first round loads OIDN's weights
                times[m].append(t)
    mp = buffers["color"].shape[0] * buffers["color"].shape[1] / 1e6
    out = []
    for m in prefilters:
        t = statistics.median(times[m])
        out.append({"width": width, "megapixels": mp, "threads": cpu_workers("cpu"), "prefilter": m, "seconds": t,
                    "seconds_per_megapixel": t / mp, "frame_seconds": seconds, "share_of_frame": t / (t + seconds)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="4:8", help="stages lo:hi (default %(default)s: the reporting half)")
    ap.add_argument("--width", type=int, default=WIDTH)
    ap.add_argument("--prefilters", default=",".join(PREFILTERS),
                    help="the --denoise-prefilter modes to measure (default %(default)s)")
    ap.add_argument("--cost-width", type=int, default=512, help="frame width of the cost figure (0: none)")
    ap.add_argument("--json", default=None, help="write the figures here")
    args = ap.parse_args(argv)
    lo, hi = map(int, args.seeds.split(":"))
    modes = tuple(args.prefilters.split(","))
    rows = []
    for seed in range(lo, hi):
        row = measure(seed, modes, args.width)
        rows.append(row)
        print(f"seed {seed}: reference noise {row['reference_noise']:.4f}; error noisy {row['noisy_error']:.4f}, "
              f"far edge {row['noisy_edge_error']:.4f}; denoised "
              + ", ".join(f"{m} {row[m]['error']:.4f} ({row[m]['ratio']:.2f}x, far edge {row[m]['edge_error']:.4f}, "
                          f"{row[m]['edge_error_of_contrast']:.3f} of its {row['edge_contrast']:.3f} step)"
                          for m in modes), flush=True)
    out = {"seeds": args.seeds, "width": args.width, "rows": rows, "modes": {}}
    for m in modes:
        ratios = [r[m]["ratio"] for r in rows]
        out["modes"][m] = {"mean_ratio": float(np.mean(ratios)), "worst_ratio": max(ratios),
                           "worst_edge_error": max(r[m]["edge_error"] for r in rows),
                           "worst_edge_error_of_contrast": max(r[m]["edge_error_of_contrast"] for r in rows)}
        print(f"{m}: denoised / noisy error mean {np.mean(ratios):.2f}, worst {max(ratios):.2f} (target <= 0.6); "
              f"far edge error worst {out['modes'][m]['worst_edge_error']:.4f}, "
              f"{out['modes'][m]['worst_edge_error_of_contrast']:.3f} of the edge's step (target <= 0.04)")
    if args.cost_width:
        out["cost"] = cost(args.cost_width, modes)
        for c in out["cost"]:
            print(f"cost {c['prefilter']} at {c['width']} px wide ({c['megapixels']:.2f} MP, {c['threads']} threads): "
                  f"{c['seconds']:.2f} s, {c['seconds_per_megapixel']:.1f} s/MP, {100 * c['share_of_frame']:.0f} % of "
                  f"the frame ({c['frame_seconds']:.2f} s to render)", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
