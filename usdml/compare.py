"""``usdml compare``: one frame rendered two ways on the same pixels, the error of one against the other.

Global illumination: ``--gi lgh --against vpl-bruteforce`` renders the same VPLs (same seed) through
the lighting grid hierarchy and by gathering every VPL with exact visibility, and reports the
relative RMSE of the ``indirect`` AOV (RMSE over pixels that see geometry and over RGB, divided by
the reference's mean) with the seconds of each indirect pass and their ratio.
"""

from __future__ import annotations

import time as _time

import numpy as np

from usdml.errors import UsdmlError
from usdml.render.frame import FrameRenderer
from usdml.stage import StageDelegate


def _render(delegate: StageDelegate, settings, frame: float, width: int, height: int, device: str):
    renderer = FrameRenderer(delegate, settings, device)
    try:
        t0 = _time.perf_counter()
        result = renderer.render(frame, width, height, {"direct", "indirect", "color", "depth"})
        return result, _time.perf_counter() - t0
    finally:
        renderer.close()


def compare_gi(delegate: StageDelegate, gi: str, against: str, frame: float | None = None,
               image_width: int = 128, device: str = "cpu", png_prefix: str | None = None,
               overrides: dict | None = None) -> dict:
    """Render ``frame`` with ``gi`` and with ``against``; JSON-able result (see the module doc)."""
    for name in (gi, against):
        if name == "none":
            raise UsdmlError("--gi and --against must name a global illumination method (lgh, vpl-bruteforce)")
    frame = delegate.start_time if frame is None else frame
    delegate.check_time(frame)
    base = delegate.usdml_settings.updated(**(overrides or {}))
    snap = delegate.snapshot(frame)
    width, height = snap.camera.resolution(image_width)
    test, test_s = _render(delegate, base.updated(gi=gi), frame, width, height, device)
    ref, ref_s = _render(delegate, base.updated(gi=against), frame, width, height, device)
    hit = np.isfinite(ref.buffers["depth"])
    a = test.buffers["indirect"][hit].astype(np.float64)
    b = ref.buffers["indirect"][hit].astype(np.float64)
    rmse = float(np.sqrt(np.mean((a - b) ** 2))) if a.size else 0.0
    mean = float(b.mean()) if b.size else 0.0
    gi_test = test.stats.get("gi_seconds", 0.0)
    gi_ref = ref.stats.get("gi_seconds", 0.0)
    if png_prefix:
        from usdml.aov.exr import write_png_preview

        for name, img in (("direct", test.buffers["direct"]), ("indirect", test.buffers["indirect"]),
                          ("color", test.buffers["color"][..., :3]), ("indirect_reference", ref.buffers["indirect"])):
            rgba = np.dstack([img, hit.astype(np.float32)]).astype(np.float32)
            write_png_preview(f"{png_prefix}_{name}.png", rgba, tonemap="reinhard", alpha=False)
    return {
        "stage": delegate.path, "frame": frame, "resolution": [width, height], "pixels": int(hit.sum()),
        "gi": gi, "against": against, "vpls": test.stats.get("gi", {}).get("vpls", 0),
        "lgh_alpha": base.lgh_alpha, "shadow_samples": base.shadow_samples, "interleave": base.interleave,
        "rel_rmse": rmse / mean if mean > 0 else 0.0, "rmse": rmse, "reference_mean": mean,
        "seconds": {gi: gi_test, against: gi_ref},
        "frame_seconds": {gi: test_s, against: ref_s},
        "speedup": gi_ref / gi_test if gi_test > 0 else float("inf"),
        "breakdown": {gi: test.stats.get("gi", {}), against: ref.stats.get("gi", {})},
    }
