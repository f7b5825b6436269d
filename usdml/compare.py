"""``usdml compare``: one frame rendered two ways on the same pixels, the error of one against the other.

Global illumination: ``--gi lgh --against vpl-bruteforce`` renders the same VPLs (same seed) through
the lighting grid hierarchy and by gathering every VPL with exact visibility (``--gi svo``: a
sixteenth of them per pixel, paper 003, with SVO rays), and reports the
relative RMSE of the ``indirect`` AOV (RMSE over pixels that see geometry and over RGB, divided by
the reference's mean) with the seconds of each indirect pass and their ratio. Warp's kernels are
loaded before either pass is timed (``warmup_seconds``: a sequence render pays it once, not per frame).
"""

from __future__ import annotations

import time as _time
from dataclasses import replace

import numpy as np

from usdml.errors import UsdmlError
from usdml.render.frame import FrameRenderer
from usdml.stage import StageDelegate


def _render(delegate: StageDelegate, settings, frame: float, width: int, height: int, device: str,
            gi_visibility: str | None = None):
    # the light on surfaces is compared: a light the camera sees would hide a surface pixel of the test that the
    # reference's pixels (centre_gbuffer: the lights unseen) still shade
    renderer = FrameRenderer(delegate, replace(settings, visible_lights=False), device, gi_visibility=gi_visibility)
    try:
        t0 = _time.perf_counter()
        result = renderer.render(frame, width, height, {"direct", "indirect", "color", "depth"})
        return result, _time.perf_counter() - t0
    finally:
        renderer.close()


def indirect_error(test: dict, reference: dict) -> tuple[float, float]:
    """``(RMSE, reference mean)`` of the ``indirect`` AOV over the pixels where the reference's ``depth``
    is finite (buffers as :attr:`usdml.render.frame.FrameResult.buffers`)."""
    hit = np.isfinite(reference["depth"])
    a = test["indirect"][hit].astype(np.float64)
    b = reference["indirect"][hit].astype(np.float64)
    rmse = float(np.sqrt(np.mean((a - b) ** 2))) if a.size else 0.0
    return rmse, float(b.mean()) if b.size else 0.0


def _estimate_fields(stats, kind: str, measured: float) -> dict:
    """The frame's own estimate of its error (``usdml:estimate:<kind>:*``, :mod:`usdml.render.lighting_estimate`)
    beside the measured ``rel_rmse``: ``estimated_rel_rmse``, its 95 % interval and whether it holds the
    measurement; empty where the method reports none (brute force, ``--gi svo``)."""
    from usdml.render.lighting_estimate import frame_estimates

    e = frame_estimates(stats).get(kind)
    if e is None:
        return {}
    lo, hi = float(e.rel_rmse_lo), float(e.rel_rmse_hi)
    return {"estimated_rel_rmse": float(e.rel_rmse), "estimated_rel_rmse_interval": [lo, hi],
            "estimate_holds": bool(lo <= measured <= hi), "estimate": e.as_dict()}


def _estimate_text(r: dict) -> str:
    if "estimated_rel_rmse" not in r:
        return ""
    return "; estimated " + _percent_interval(r["estimated_rel_rmse"], r["estimated_rel_rmse_interval"])


def _warn_ignored(overrides: dict | None, settings) -> None:
    """A warning for each given setting the comparison does not read (:func:`usdml.params.ignored`)."""
    from usdml.errors import log
    from usdml.params import ignored

    for message in ignored(overrides or {}, settings):
        log.warning(message)


def png_names(prefix: str | None, names) -> list[str]:
    """``PREFIX_<name>.png`` of each of ``names`` (``--png PREFIX``), each checked writable before any
    render (:func:`usdml.outputs.check_output`)."""
    from usdml.outputs import check_output

    return [str(check_output(f"{prefix}_{n}.png", "--png")) for n in names] if prefix else []


def _write_pngs(prefix: str | None, hit: np.ndarray, images: dict) -> None:
    """``PREFIX_<name>.png`` of each linear RGB image of ``images`` (None: skipped), Reinhard-tone-mapped,
    black where ``hit`` is False."""
    if not prefix:
        return
    from usdml.aov.exr import write_png_preview

    for name, img in images.items():
        if img is not None:
            rgba = np.dstack([img, hit.astype(np.float32)]).astype(np.float32)
            write_png_preview(f"{prefix}_{name}.png", rgba, tonemap="reinhard", alpha=False)


def compare_gi(delegate: StageDelegate, gi: str, against: str, frame: float | None = None,
               image_width: int = 128, device: str = "cpu", png_prefix: str | None = None,
               overrides: dict | None = None, gi_visibility: str | None = None) -> dict:
    """Render ``frame`` with ``gi`` and with ``against``; JSON-able result (see the module doc).
    ``gi_visibility`` overrides the backend of ``--gi svo``'s rays (:class:`FrameRenderer`)."""
    for name in (gi, against):
        if name == "none":
            raise UsdmlError("--gi and --against must name a global illumination method (lgh, svo, vpl-bruteforce)")
    png_names(png_prefix, ("direct", "indirect", "color", "indirect_reference"))
    frame = delegate.start_time if frame is None else frame
    delegate.check_time(frame)
    base = delegate.usdml_settings.updated(**(overrides or {}))
    _warn_ignored(overrides, base.updated(gi=gi))
    snap = delegate.snapshot(frame)
    width, height = snap.camera.resolution(image_width)
    from usdml.lighting.gi import warm_up

    warm = warm_up(device)      # once per process in a sequence render; not the method's cost per frame
    test, test_s = _render(delegate, base.updated(gi=gi), frame, width, height, device, gi_visibility)
    ref, ref_s = _render(delegate, base.updated(gi=against), frame, width, height, device, gi_visibility)
    hit = np.isfinite(ref.buffers["depth"])
    rmse, mean = indirect_error(test.buffers, ref.buffers)
    gi_test = test.stats.gi_seconds or 0.0
    gi_ref = ref.stats.gi_seconds or 0.0
    _write_pngs(png_prefix, hit, {"direct": test.buffers["direct"], "indirect": test.buffers["indirect"],
                                  "color": test.buffers["color"][..., :3], "indirect_reference": ref.buffers["indirect"]})
    rel = rmse / mean if mean > 0 else 0.0
    return {
        "stage": delegate.path, "frame": frame, "resolution": [width, height], "pixels": int(hit.sum()),
        "gi": gi, "against": against, "vpls": (test.stats.gi or {}).get("vpls", 0),
        # auto (0): as the frame chose them
        "lgh_alpha": (test.stats.gi or {}).get("lgh_alpha", base.lgh_alpha),
        "shadow_samples": (test.stats.gi or {}).get("shadow_samples", base.shadow_samples),
        "interleave": base.interleave,
        "lgh_start_level": base.lgh_start_level, "shadow_targets": base.shadow_targets,
        "lgh_split": (test.stats.gi or {}).get("lgh_split", base.lgh_split),
        "rel_rmse": rel, "rmse": rmse, "reference_mean": mean, **_estimate_fields(test.stats, "gi", rel),
        "seconds": {gi: gi_test, against: gi_ref},
        "frame_seconds": {gi: test_s, against: ref_s},
        "speedup": gi_ref / gi_test if gi_test > 0 else float("inf"),
        # svo: building its visibility backend for the frame (not in "seconds", as no method's BVH is)
        "gi_update_seconds": {gi: test.stats.gi_update_seconds or 0.0,
                              against: ref.stats.gi_update_seconds or 0.0},
        "warmup_seconds": warm,
        "breakdown": {gi: test.stats.gi or {}, against: ref.stats.gi or {}},
    }


# ------------------------------------------------------------------------------------- direct light

def _reference_subset(delegate: StageDelegate, settings, frame: float, width: int, height: int, device: str,
                      pixels: int, seed: int) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Every-light direct light of ``pixels`` hit pixels drawn at random (``seed``) from the frame's
    G-buffer (pixel centres, as the test's one primary ray per pixel): ``(flat pixel indices, (S, 3)
    radiance, seconds of the shading, hit pixels)``; the frame set up as a render does
    (:meth:`FrameRenderer.advance`)."""
    from usdml.lighting.direct import shade_with
    from usdml.render.frame import centre_gbuffer

    renderer = FrameRenderer(delegate, settings, device)
    try:
        snap, lights, _ = renderer.advance(frame, width, height)
        _, gb = centre_gbuffer(snap, renderer.backends.primary, width, height)
        hit = np.flatnonzero(gb.hit.ravel())
        pick = np.sort(np.random.default_rng(seed).choice(hit, min(pixels, len(hit)), replace=False))
        t0 = _time.perf_counter()
        r = shade_with(renderer.backends.shadow, gb.position.reshape(-1, 3)[pick], gb.normal.reshape(-1, 3)[pick],
                       gb.albedo.reshape(-1, 3)[pick], lights, None, meters_per_unit=snap.meters_per_unit,
                       geometric=gb.geometric.reshape(-1, 3)[pick], light_samples=settings.light_samples,
                       seed=settings.seed)
        return pick, r.radiance, _time.perf_counter() - t0, len(hit)
    finally:
        renderer.close()


def compare_direct(delegate: StageDelegate, direct: str = "lgh", against: str = "all", frame: float | None = None,
                   image_width: int = 128, device: str = "cpu", png_prefix: str | None = None,
                   overrides: dict | None = None, reference_pixels: int = 0, image_height: int | None = None) -> dict:
    """``--direct lgh --against all``: the frame's ``direct`` AOV both ways, one primary ray per pixel
    (the pixel centre, the same G-buffer), with the relative RMSE of ``direct`` (over the pixels that
    see geometry and RGB, over the reference's mean), each way's seconds (the frame, and its direct
    light), and the speed-up. With ``reference_pixels`` N > 0 the reference shades only N hit pixels
    drawn at random, and its seconds are extrapolated to every hit pixel (``reference_extrapolated``):
    every-light shading of 100,000 lights costs minutes per 256-pixel frame. ``image_height``: the frame's height
    (the camera conformed to it, as a RenderSettings resolution does), default the camera's aspect."""
    choices = ("all", "lgh")
    if direct not in choices or against not in choices or direct == against:
        raise UsdmlError(f"--direct and --against must be two different direct-lighting methods ({', '.join(choices)})")
    png_names(png_prefix, ("direct", "direct_reference"))
    frame = delegate.start_time if frame is None else frame
    delegate.check_time(frame)
    base = delegate.usdml_settings.updated(**(overrides or {})).updated(pixel_samples=1, gi="none")
    _warn_ignored(overrides, base.updated(direct=direct))
    snap = delegate.snapshot(frame)
    width, height = snap.camera.resolution(image_width)
    height = height if image_height is None else int(image_height)
    from usdml.lighting.gi import warm_up

    warm = warm_up(device)
    test, test_s = _render(delegate, base.updated(direct=direct), frame, width, height, device)
    hit = np.isfinite(test.buffers["depth"])
    got = test.buffers["direct"].reshape(-1, 3)
    if reference_pixels > 0 and against == "all":
        pick, ref_px, ref_shading, n_hit = _reference_subset(delegate, base.updated(direct=against), frame, width,
                                                             height, device, reference_pixels, base.seed)
        a, b = got[pick].astype(np.float64), ref_px.astype(np.float64)
        ref_shading *= n_hit / max(len(pick), 1)
        ref_s = ref_shading + test.stats.gbuffer_seconds + test.stats.update_seconds
        ref_img = None
        compared = len(pick)
    else:
        ref, ref_s = _render(delegate, base.updated(direct=against), frame, width, height, device)
        ref_shading = ref.stats.shading_seconds
        a = got[hit.ravel()].astype(np.float64)
        b = ref.buffers["direct"].reshape(-1, 3)[hit.ravel()].astype(np.float64)
        ref_img = ref.buffers["direct"]
        compared = int(hit.sum())
    rmse = float(np.sqrt(np.mean((a - b) ** 2))) if a.size else 0.0
    mean = float(b.mean()) if b.size else 0.0
    _write_pngs(png_prefix, hit, {"direct": test.buffers["direct"], "direct_reference": ref_img})
    test_shading = test.stats.shading_seconds
    rel = rmse / mean if mean > 0 else 0.0
    return {
        "stage": delegate.path, "frame": frame, "resolution": [width, height], "pixels": int(hit.sum()),
        "compared_pixels": compared, "reference_extrapolated": bool(reference_pixels > 0 and against == "all"),
        "direct": direct, "against": against, "lights": test.stats.lights,
        "visibility": base.visibility,
        # auto (0): as the frame chose them
        "direct_shadow_samples": (test.stats.direct_lgh or {}).get("shadow_samples", base.direct_shadow_samples),
        "direct_alpha": base.direct_alpha,
        # each (every grid light its own light) or hierarchy, as the frame chose
        "direct_gather": (test.stats.direct_lgh or {}).get("gather", base.direct_gather if direct == "lgh" else None),
        "rel_rmse": rel, "rmse": rmse, "reference_mean": mean, **_estimate_fields(test.stats, "direct", rel),
        "seconds": {direct: test_s, against: ref_s},
        "direct_seconds": {direct: test_shading, against: ref_shading},
        "speedup": ref_s / test_s if test_s > 0 else float("inf"),
        "direct_speedup": ref_shading / test_shading if test_shading > 0 else float("inf"),
        "warmup_seconds": warm,
        "breakdown": {direct: test.stats.direct_lgh or {}},
    }


def format_direct_comparison(r: dict) -> str:
    s = r["seconds"]
    extra = f", reference on {r['compared_pixels']:,} pixels, its time extrapolated" if r["reference_extrapolated"] else ""
    how = " (every light its own light)" if r.get("direct_gather") == "each" else ""
    return (f"--direct {r['direct']}{how} vs {r['against']} on {r['pixels']:,} pixels, {r['lights']:,} lights "
            f"({r['visibility']} visibility{extra}): direct rel. RMSE {100 * r['rel_rmse']:.2f} %, "
            f"{s[r['direct']]:.2f} s vs {s[r['against']]:.2f} s per frame ({r['speedup']:.1f}x){_estimate_text(r)}")


# ---------------------------------------------------------------------------------------- visibility

#: the heat map's opacity per unit of signed error (paper 000 Fig. 6: x 10, full colour at 10 %)
HEATMAP_SCALE = 10.0


def error_heatmap(signed: np.ndarray, base: np.ndarray, hit: np.ndarray, scale: float = HEATMAP_SCALE) -> np.ndarray:
    """Paper 000 Fig. 6: the shadow image in grey, pixels the approximation makes darker in blue and
    brighter in red, with opacity ``scale × |error|``. ``signed`` = (wrongly hidden - wrongly visible)
    / lights per pixel. Returns (H, W, 3) uint8."""
    grey = np.clip(1.0 - base, 0.0, 1.0) * 0.8 * hit
    rgb = np.repeat(grey[..., None], 3, axis=2)
    a = np.clip(scale * np.abs(signed), 0.0, 1.0)[..., None]
    colour = np.where(signed[..., None] > 0, np.array([0.1, 0.3, 1.0]), np.array([1.0, 0.15, 0.1]))
    rgb = rgb * (1.0 - a) + colour * a
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def compare_visibility(delegate: StageDelegate, backend: str, against: str = "exact", frame: float | None = None,
                       image_width: int = 128, device: str = "cpu", heatmap: str | None = None,
                       overrides: dict | None = None, backend_options: dict | None = None,
                       plot: str | None = None) -> dict:
    """Paper 000 §6.1 on one frame: both backends answer the same shadow queries (every pixel that
    sees geometry against every light facing it); per pixel, ``ε_v`` = (wrongly visible + wrongly
    hidden) / lights and ``ε_s`` = |wrongly hidden - wrongly visible| / lights, averaged over pixels.

    Wrongly hidden queries are split into near-field (the approximation's first occupied voxel within
    ``NEAR_VOXELS`` of the ray's start) and far-field, the lever DESIGN.md points at.
    """
    from usdml.lighting.direct import facing_pairs
    from usdml.render.backends import QUERY_ROLES, Backends
    from usdml.render.estimate import estimate_visibility, frame_rng
    from usdml.render.frame import centre_gbuffer
    from usdml.scene import LightType, diff
    from usdml.stage.delegate import require_geometry, require_lights
    from usdml.visibility import ExactBackend, backend_names
    from usdml.visibility.base import HIT_DISTANCES, LIGHT_MAJOR

    if against != ExactBackend.name:
        raise UsdmlError(f"--against {against}: visibility is measured against exact (Embree) only")
    if backend == ExactBackend.name:
        approximate = [n for n in backend_names() if n != ExactBackend.name]
        raise UsdmlError(f"--visibility exact against exact: give an approximate backend ({', '.join(approximate)})")
    from usdml.outputs import IMAGE_EXTENSIONS, check_output

    if heatmap:
        check_output(heatmap, "--heatmap", IMAGE_EXTENSIONS)
    if plot:
        for suffix in ("heatmap", "hist"):
            check_output(f"{plot}.{suffix}.png", "--plot")
    frame = delegate.start_time if frame is None else frame
    delegate.check_time(frame)
    settings = delegate.usdml_settings.updated(**(overrides or {})).updated(visibility=backend)
    _warn_ignored(overrides, settings)
    snap = delegate.snapshot(frame)
    require_geometry(delegate, snap)
    require_lights(delegate, snap, "compare")
    width, height = snap.camera.resolution(image_width)
    # as a render's (usdml.render.backends), without --gi svo's rays; --error-budget on a backend that cannot
    # refine is one line naming those that can (Backends' unrefinable="raise")
    backends = Backends(settings, device, backend_options, roles=QUERY_ROLES, unrefinable="raise")
    exact, approx, refined = backends.primary, backends.configured, backends.refined
    from usdml.render.budget import choose_level

    near_far = approx.supports(HIT_DISTANCES) and refined is None
    try:
        build = backends.update(snap, diff(None, snap))["shadow"]
        _, gb = centre_gbuffer(snap, exact, width, height)
        hit = gb.hit.ravel()
        n_px = int(hit.sum())
        budget = None
        if refined is not None:
            # --error-budget: the frame's level from its own sample, as a render chooses it (usdml.render.budget);
            # its seconds count as the approximation's
            t0 = _time.perf_counter()
            budget = choose_level(refined, gb.position.reshape(-1, 3)[hit], gb.normal.reshape(-1, 3)[hit],
                                  gb.geometric.reshape(-1, 3)[hit], snap.lights, settings.error_budget, settings.seed,
                                  frame, delegate.path)
            budget_s = _time.perf_counter() - t0
            approx = refined
        # block by block (memory stays bounded on 10^8 pairs): per-pixel counts of facing, blocked,
        # wrongly hidden (near / far) and wrongly visible pairs, and each backend's query seconds
        counts = {k: np.zeros(n_px, np.int64) for k in ("facing", "blocked", "hidden", "visible")}
        hidden_near = 0
        ref_s = got_s = 0.0
        points, geometric = gb.position.reshape(-1, 3)[hit], gb.geometric.reshape(-1, 3)[hit]
        matrix = None
        if approx.supports(LIGHT_MAJOR):
            # per-light structures: every pixel against every light at once (P x L answers), the
            # facing pairs read from it
            t0 = _time.perf_counter()
            lights = snap.lights
            matrix = approx.occluded_matrix(points, geometric, lights.position, lights.type == LightType.DISTANT,
                                            lights.axis)
            got_s += _time.perf_counter() - t0
        for origin, target, normal, distant, pixel, light in facing_pairs(
                points, gb.normal.reshape(-1, 3)[hit], snap.lights, geometric):
            args = (origin, target)
            kw = dict(normals=normal, distant=distant.astype(bool))
            t0 = _time.perf_counter()
            ref = exact.occluded(*args, **kw)
            ref_s += _time.perf_counter() - t0
            t0 = _time.perf_counter()
            if matrix is not None:
                got = matrix[pixel, light]
            elif refined is not None:     # the rows' points, as a render's pass gives them (the blind zone's probes)
                got = approx.answer(*args, starts=pixel, **kw)[0]
            else:
                got = approx.occluded(*args, **kw)
            got_s += _time.perf_counter() - t0
            if near_far and (got & ~ref).any():
                dist = approx.hit_distances(*args, **kw)
                hidden_near += int((got & ~ref & (dist >= 0) & (dist < NEAR_VOXELS)).sum())
            for key, sel in (("facing", slice(None)), ("blocked", ref), ("hidden", got & ~ref),
                             ("visible", ~got & ref)):
                counts[key] += np.bincount(pixel[sel].astype(np.int64), minlength=n_px)
        # the estimate a render of this frame reports, on the same G-buffer and lights
        estimate = budget if budget is not None else estimate_visibility(points, gb.normal.reshape(-1, 3)[hit], geometric, snap.lights, exact, approx,
                                       frame_rng(settings.seed, frame),
                                       frame_pairs=n_px * len(snap.lights) * settings.pixel_samples)
        refinement = {"error_budget": settings.error_budget, "refined_fraction": 0.0, "near_fraction": 0.0,
                      "refine_level": 0}
        if refined is not None:
            got_s += budget_s
            refinement.update(refined.fractions(), refine_level=budget.level, budget_seconds=budget_s)
    finally:
        backends.close()
    n_l = len(snap.lights)
    wrong_hidden, wrong_visible = counts["hidden"], counts["visible"]
    eps_v = (wrong_hidden + wrong_visible) / max(n_l, 1)
    eps_s_signed = (wrong_hidden - wrong_visible) / max(n_l, 1)
    eps_s = np.abs(eps_s_signed)
    n_queries = int(counts["facing"].sum())
    if heatmap or plot:
        signed = np.zeros(width * height)
        signed[hit] = eps_s_signed
        shadow = np.zeros(width * height)
        shadow[hit] = counts["blocked"] / np.maximum(counts["facing"], 1)
        image = error_heatmap(signed.reshape(height, width), shadow.reshape(height, width), gb.hit, HEATMAP_SCALE)
    if heatmap:
        from usdml.outputs import write_image

        write_image(heatmap, image)
    if plot:
        from usdml.plots import error_map, histogram

        error_map(f"{plot}.heatmap.png", image, HEATMAP_SCALE, f"{backend} against {against}: blue darker, red brighter")
        histogram(f"{plot}.hist.png", {"ε_v (wrongly answered / lights)": 100 * eps_v,
                                       "signed ε_s (hidden − visible) / lights": 100 * eps_s_signed},
                  "per-pixel error (%)", f"{backend} against {against}, {n_px:,} pixels")
    nq = max(n_queries, 1)
    result = {
        "stage": delegate.path, "frame": frame, "resolution": [width, height], "pixels": n_px, "lights": n_l,
        "queries": n_queries, "visibility": backend, "against": against,
        "eps_v": float(eps_v.mean()) if n_px else 0.0, "eps_s": float(eps_s.mean()) if n_px else 0.0,
        "wrongly_hidden": float(wrong_hidden.sum() / nq), "wrongly_visible": float(wrong_visible.sum() / nq),
        "wrongly_hidden_near": float(hidden_near / nq),
        "wrongly_hidden_far": float((wrong_hidden.sum() - hidden_near) / nq),
        "near_voxels": NEAR_VOXELS,
        "seconds": {backend: got_s, against: ref_s}, "speedup": ref_s / got_s if got_s > 0 else float("inf"),
        "estimated_eps_v": estimate.eps_v, "estimated_eps_v_interval": [estimate.eps_v_lo, estimate.eps_v_hi],
        "estimated_eps_s": estimate.eps_s, "estimated_eps_s_interval": [estimate.eps_s_lo, estimate.eps_s_hi],
        "estimate": estimate.as_dict(),
        **refinement,
        "build_seconds": build, "heatmap": heatmap, "plot": None if not plot else [f"{plot}.heatmap.png", f"{plot}.hist.png"],
    }
    result.update(approx.describe())    # the backend's own fields (voxel: resolution, step, bytes, ...)
    return result


#: near-field: the first occupied voxel lies within this many voxels of the ray's (skipped) start
NEAR_VOXELS = 2.0


def format_visibility_comparison(r: dict) -> str:
    """One line of :func:`compare_visibility`'s result for the terminal."""
    s = r["seconds"]
    return (f"{r['visibility']} vs {r['against']} on {r['pixels']:,} pixels x {r['lights']:,} lights "
            f"({r['queries']:,} facing pairs): eps_v {100 * r['eps_v']:.2f} %, eps_s {100 * r['eps_s']:.2f} %; "
            f"wrongly hidden {100 * r['wrongly_hidden']:.2f} % of pairs ({100 * r['wrongly_hidden_near']:.2f} % "
            f"near the start), wrongly visible {100 * r['wrongly_visible']:.2f} %; queries "
            f"{s[r['visibility']]:.2f} s vs {s[r['against']]:.2f} s ({r['speedup']:.1f}x)"
            + (f"; --error-budget {r['error_budget']:g}: level {r['refine_level']}, {100 * r['refined_fraction']:.1f} % "
               f"re-asked of exact" if r.get("error_budget", 1.0) < 1.0 else "") + "; estimated eps_v "
            f"{_percent_interval(r['estimated_eps_v'], r['estimated_eps_v_interval'])}"
            + (f"; heat map {r['heatmap']}" if r["heatmap"] else ""))


def _percent_interval(value: float, interval) -> str:
    return f"{100 * value:.2f} % [{100 * interval[0]:.2f}, {100 * interval[1]:.2f}]"


def format_gi_comparison(r: dict) -> str:
    """One line of :func:`compare_gi`'s result for the terminal."""
    s = r["seconds"]
    how = ""                    # --gi lgh: what the frame lit with, every VPL its own light or a hierarchy at its α
    if r["gi"] == "lgh" and r.get("lgh_split") == "each":
        how = " (every VPL its own light)"
    elif r["gi"] == "lgh" and r.get("lgh_alpha") is not None:
        hierarchy = "one hierarchy per normal class" if r.get("lgh_split") == "normal" else "one hierarchy"
        how = f" ({hierarchy}, α {r['lgh_alpha']:g})"
    return (f"{r['gi']}{how} vs {r['against']} on {r['pixels']:,} pixels, {r['vpls']:,} VPLs: "
            f"relative RMSE of indirect {100 * r['rel_rmse']:.2f} %; indirect pass "
            f"{s[r['gi']]:.2f} s vs {s[r['against']]:.2f} s ({r['speedup']:.1f}x){_estimate_text(r)}")
