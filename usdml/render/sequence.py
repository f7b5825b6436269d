"""Render a sequence of timecodes to EXR products: what to write where, resume, progress.

Products come from the OUTPUT argument (one product, ``--aovs`` or :data:`DEFAULT_AOVS`) or, when
there is none, from the stage's RenderSettings (each product's ``productName`` at each frame, its
ordered RenderVars mapped to usdml AOVs). Every file is written under a temporary name and renamed;
``resume`` skips frames whose files are all complete and were rendered with the same settings from the
same stage (``usdml:settingsDigest``, :mod:`usdml.render.identity`), so an interrupted sequence loses at
most the frame in flight; a complete file with other settings is *stale* and rendered again.
"""

from __future__ import annotations

import os
import sys
import time as _time
from dataclasses import dataclass, field, replace

from tqdm import tqdm

from usdml.aov.cryptomatte import header as cryptomatte_header
from usdml.aov.exr import camera_matrices, exr_attribute, is_complete_exr, write_exr, write_png_preview
from usdml.aov.names import AOVS, EVERY_LIGHT_GROUP, LIGHT_GROUP, aov_for_render_var, data_type_matches, find_aov
from usdml.aov.naming import format_frame, frame_placeholder, frame_spec, frame_spec_precision, output_paths
from usdml.errors import UsdmlError, collect_warnings, log
from usdml.outputs import make_output_folder
from usdml.params import DEFAULT_WIDTH, PARAMS, ignored
from usdml.render.denoise.oidn import headers as denoise_headers
from usdml.render.denoise.oidn import require_denoiser
from usdml.render.estimate import VisibilityEstimate
from usdml.render.estimate import header as estimate_header
from usdml.render.lighting_estimate import LightingEstimate, frame_estimates, frame_headers
from usdml.render.shutter import camera_headers
from usdml.render.frame import DEFAULT_AOVS, FrameRenderer
from usdml.render.identity import DIGEST_ATTR, frame_settings, settings_digest, settings_json
from usdml.render.result import SequenceResult
from usdml.settings import RenderOptions, UsdmlSettings
from usdml.stage import StageDelegate
from usdml.stage.delegate import require_geometry
from usdml.stage.fingerprint import stage_fingerprint


@dataclass
class Product:
    """One output file per frame: its path per frame and the layers (EXR layer name -> AOV name) it holds."""

    paths: dict[float, str]
    layers: dict[str, str]
    source: str = "OUTPUT"      #: "OUTPUT" or the RenderProduct prim path


@dataclass(kw_only=True)
class RenderJob(RenderOptions):
    """A render: the stage, where to, which frames, and the render options (:class:`usdml.settings.RenderOptions`,
    from the parameter table)."""

    stage: object                       #: a path, or an open ``Usd.Stage``
    output: str | None = None
    #: a FrameSpec (``--frames``), timecodes (the API's, a farm chunk's), or None: the stage's start frame
    frames: str | list[float] | None = None
    resume: bool = False
    overrides: dict = field(default_factory=dict)   #: UsdmlSettings fields set on the command line
    #: one frame (``frames``) written to ``output`` as it is: no frame placeholder needed (the API's record)
    single_file: bool = False
    #: skip frames whose files are complete, rendered with these settings and written since this time
    #: (``time.time()``): a farm chunk's retry skips what its killed attempt finished, and nothing older
    resume_since: float | None = None


def _resolution(snap, job: RenderJob) -> tuple[int, int]:
    """The image size. ``--imageWidth`` wins for the width; the RenderSettings in force (``--renderSettingsPrimPath``
    or the stage's ``renderSettingsPrimPath``) give the aspect, and the width when ``--imageWidth`` is not given:
    the first product's resolution when the products are written (no OUTPUT), the RenderSettings' own with an
    OUTPUT path. Without RenderSettings: width ``DEFAULT_WIDTH`` and the camera's aspect."""
    rs = snap.render_settings
    if rs is not None:
        w, h = rs.resolution
        if not job.output and rs.products:
            w, h = rs.products[0].resolution or rs.resolution
        if job.image_width:
            return int(job.image_width), max(1, round(job.image_width * h / w))
        return int(w), int(h)
    width = int(job.image_width or DEFAULT_WIDTH)
    return snap.camera.resolution(width)


def plan_products(delegate: StageDelegate, job: RenderJob, frames: list[float]) -> list[Product]:
    """Where each frame's AOVs go, checked before any rendering starts."""
    frames_given = job.frames is not None and not (job.single_file and frame_placeholder(job.output or "") is None
                                                   and "#" not in (job.output or ""))
    precision = frame_spec_precision(job.frames)
    if job.output:
        names = job.aovs or list(DEFAULT_AOVS)
        if EVERY_LIGHT_GROUP in names:      # one lightgroup:NAME per group the stage's lights name
            at = names.index(EVERY_LIGHT_GROUP)
            groups = [LIGHT_GROUP + g for g in delegate.light_groups() if LIGHT_GROUP + g not in names]
            names = names[:at] + groups + names[at + 1:]
        unknown = [n for n in names if find_aov(n) is None]
        if unknown:
            raise UsdmlError(f"--aovs: unknown AOV(s) {', '.join(unknown)}; usdml writes {', '.join(AOVS)}")
        if not job.output.lower().endswith(".exr"):
            raise UsdmlError(f"output {job.output!r}: usdml writes multi-channel OpenEXR; give a .exr path "
                             "(--preview adds a PNG of color beside it)")
        paths = output_paths(job.output, frames, frames_given=frames_given, min_precision=precision)
        return [Product(dict(zip(frames, paths)), {find_aov(n).name: find_aov(n).name for n in names})]
    first = delegate.render_settings(frames[0])
    if first is None:
        raise UsdmlError(f"{delegate.path}: give an OUTPUT path (e.g. out/beauty.####.exr) or author "
                         "RenderSettings with a RenderProduct (renderSettingsPrimPath)")
    products: list[Product] = []
    wanted = {find_aov(a).name for a in job.aovs or [] if find_aov(a)}
    if not first.products:
        raise UsdmlError(f"{first.path}.products: no RenderProduct; give an OUTPUT path instead")
    for k, rp in enumerate(first.products):
        if rp.camera and rp.camera != first.camera and not job.camera:
            log.warning(f"{rp.path}.camera: per-product cameras are not supported; every product is "
                        f"rendered from {first.camera or 'the default camera'}")
        layers: dict[str, str] = {}
        for var in rp.vars:
            aov = aov_for_render_var(var.source_name, var.source_type)
            if aov is None:
                log.warning(f"{var.path}: sourceName {var.source_name!r} ({var.source_type}) is not an AOV "
                            "usdml renders; skipped")
                continue
            if not data_type_matches(aov, var.data_type):
                log.warning(f"{var.path}: dataType {var.data_type} does not match AOV {aov.name}; "
                            f"written as {aov.pixel_type}")
            if wanted and aov.name not in wanted:
                continue
            layers[var.name] = aov.name
        if not layers:
            layers = {"color": "color"}
            log.warning(f"{rp.path}: no RenderVar usdml renders; writing color")
        if rp.name_time_varying:
            paths = {}
            for f in frames:
                name = delegate.render_settings(f).products[k].product_name
                paths[f] = format_frame(name, f) if frame_placeholder(name) else name
            if len(set(paths.values())) != len(paths):
                raise UsdmlError(f"{rp.path}.productName: several frames write the same file")
        else:
            name = rp.product_name
            if frame_placeholder(name) is None and len(frames) == 1:
                paths = {frames[0]: name}
            else:
                paths = dict(zip(frames, output_paths(name, frames, frames_given=True, min_precision=precision)))
        if any(not p.lower().endswith(".exr") for p in paths.values()):
            shown = next(iter(paths.values()))
            log.warning(f"{rp.path}.productName: {shown!r} is not OpenEXR, the only format usdml writes; "
                        f"writing {os.path.splitext(shown)[0] + '.exr'!r}")
            paths = {f: os.path.splitext(p)[0] + ".exr" for f, p in paths.items()}
        products.append(Product(paths, layers, rp.path))
    return products


def _frame_state(products: list[Product], digests: list[str], frame: float) -> str:
    """``done``: every file of ``frame`` is a complete EXR whose ``usdml:settingsDigest`` is its product's in
    ``digests``; ``stale``: every file is complete but one was rendered with other settings or from other stage
    content (or by a usdml that wrote no digest); ``missing``: a file is absent, partial or corrupt."""
    paths = [p.paths[frame] for p in products]
    if not all(is_complete_exr(path) for path in paths):
        return "missing"
    return "done" if all(exr_attribute(path, DIGEST_ATTR) == d for path, d in zip(paths, digests)) else "stale"


def _written_since(products: list[Product], frame: float, since: float) -> bool:
    return all(os.path.getmtime(p.paths[frame]) >= since for p in products)


def check_device(device: str) -> None:
    """``cpu`` always works; ``cuda`` needs a CUDA device visible to Warp."""
    if device == "cpu":
        return
    if device != "cuda":
        raise UsdmlError(f"--device {device!r}: use cpu or cuda")
    from usdml.kernels import warp

    if warp().get_cuda_device_count() == 0:
        raise UsdmlError("--device cuda: no CUDA device found; use --device cpu")


def build_messages() -> dict:
    """The ``report`` and ``progress`` options every visibility backend accepts
    (:mod:`usdml.visibility.base`), telling the user on stderr what a backend's structures cost and
    how their build goes."""

    def report(line: str) -> None:
        print(f"usdml: {line}", file=sys.stderr, flush=True)

    last = {"t": 0.0}
    # a terminal gets one line redrawn twice a second; a log file (CI, a render farm) a full line
    # every 10 s and at the end, not a run of carriage returns
    tty = sys.stderr.isatty()
    every = 0.5 if tty else 10.0

    def progress(done: int, total: int, label: str, unit: str = "steps") -> None:
        now = _time.perf_counter()
        if done < total and now - last["t"] < every:
            return
        last["t"] = now
        line = f"usdml: building {label}: {done}/{total} {unit} {100 * done // max(total, 1)} %"
        if tty:
            print("\r" + line, end="\n" if done >= total else "", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)
    return {"report": report, "progress": progress}


def render_sequence(job: RenderJob) -> SequenceResult:
    """Render every frame of ``job``; returns what it did (:class:`usdml.render.result.SequenceResult`: the
    frames rendered, skipped, stale and recovered, the files, the seconds, the estimates, and the warnings
    the ``usdml`` logger gave meanwhile)."""
    with collect_warnings() as warnings:
        result = _render_sequence(job)
    return replace(result, warnings=list(warnings))


def _render_sequence(job: RenderJob) -> SequenceResult:
    started = _time.perf_counter()
    delegate = StageDelegate(job.stage, camera=job.camera, render_settings_path=job.render_settings,
                             purposes=job.purposes, implicit_detail=job.implicit_detail)
    # validated here, once, by the parameter table (UsdmlSettings' construction: a backend name among the registry's)
    settings: UsdmlSettings = delegate.usdml_settings.updated(**job.overrides)
    for message in ignored(job.overrides, settings):
        log.warning(message)
    check_device(job.device)
    if settings.denoise:
        require_denoiser(PARAMS["denoise"].where)     # one line before any frame renders, not after the first
    frames = frame_spec(job.frames, delegate.start_time, delegate.end_time)
    delegate.check_times(frames)
    products = plan_products(delegate, job, frames)
    t_first = _time.perf_counter()
    first = delegate.snapshot(frames[0])
    first_seconds = _time.perf_counter() - t_first     # the first frame's: it renders from this snapshot
    require_geometry(delegate, first)
    width, height = _resolution(first, job)
    wanted = {aov for p in products for aov in p.layers.values()}
    for folder in sorted({os.path.dirname(path) or "." for p in products for path in p.paths.values()}):
        make_output_folder(folder)       # before the first frame renders, not after it
    renderer = FrameRenderer(delegate, settings, job.device, camera_light=job.camera_light,
                             backend_options=build_messages())
    stage_file = os.path.abspath(delegate.path) if os.path.exists(delegate.path) else delegate.path
    common = dict(resolution=(width, height), camera=first.camera.path,
                  render_settings=str(delegate.settings_prim.GetPath()) if delegate.settings_prim else None,
                  purposes=job.purposes, implicit_detail=job.implicit_detail, camera_light=job.camera_light,
                  stage=stage_fingerprint(delegate.stage))
    identities = [frame_settings(settings.as_dict(), layers=p.layers, **common) for p in products]
    digests = [settings_digest(i) for i in identities]
    written, skipped, stale, recovered, seconds = [], [], [], [], []
    estimates: dict[float, VisibilityEstimate] = {}     # frame -> its visibility error estimate
    lighting: dict[float, dict[str, LightingEstimate]] = {}     # frame -> {gi, direct}: its LGH error estimates
    since = job.resume_since
    try:
        with tqdm(total=len(frames), desc="frames", unit="frame", disable=None, file=sys.stderr) as bar:
            for f in frames:
                state = _frame_state(products, digests, f) if job.resume or since is not None else "missing"
                ours = state == "done" and since is not None and _written_since(products, f, since)
                if ours or (state == "done" and job.resume):
                    (recovered if ours else skipped).append(f)
                    bar.update(1)
                    continue
                if state == "stale" and job.resume:
                    stale.append(f)
                t0 = _time.perf_counter()
                with tqdm(total=width * height, desc=f"frame {f:g}", unit="px", leave=False, disable=None,
                          file=sys.stderr) as px:
                    # the first frame renders from the stage as read above (a million lights: 1.8 s to read again)
                    # and counts that read in its seconds
                    reuse = first if f == frames[0] and first is not None else None
                    result = renderer.render(f, width, height, wanted, progress=px.update, snapshot=reuse)
                    if reuse is not None:
                        t0 -= first_seconds
                    first = None
                w2c, w2n = camera_matrices(result.camera)
                for product, identity, digest in zip(products, identities, digests):
                    path = product.paths[f]
                    aovs = {layer: result.buffers[aov] for layer, aov in product.layers.items()}
                    write_exr(path, aovs, layers=product.layers, world_to_camera=w2c, world_to_ndc=w2n,
                              timecode=f, stage=stage_file, settings=settings_json(identity),
                              metadata={"usdml:renderProduct": product.source, DIGEST_ATTR: digest,
                                        "usdml:camera": result.camera.path or "(framing)",
                                        **(estimate_header(result.stats.estimate) if result.stats.estimate is not None
                                           else {}), **frame_headers(result.stats),
                                        **camera_headers(result.stats, result.camera),
                                        **cryptomatte_header(product.layers, result.manifests),
                                        **denoise_headers(result.stats.denoise)})
                    if job.preview and "color" in result.buffers:
                        write_png_preview(_preview_path(path), result.buffers["color"], tonemap="reinhard")
                seconds.append(_time.perf_counter() - t0)
                if result.stats.estimate is not None:
                    estimates[f] = result.stats.estimate
                if frame_estimates(result.stats):
                    lighting[f] = frame_estimates(result.stats)
                written.append(f)
                bar.update(1)
    finally:
        renderer.close()
    total = _time.perf_counter() - started
    order = {f: i for i, f in enumerate(frames)}
    mine = sorted(written + recovered, key=order.get)        # the frames whose files this run wrote
    return SequenceResult(
        stage=delegate.path, frames=written, skipped=skipped, stale=stale, recovered=recovered,
        resolution=(width, height), seconds_per_frame=(sum(seconds) / len(seconds)) if seconds else 0.0,
        seconds=total, visibility=settings.visibility,
        outputs=[p.paths[f] for f in mine for p in products],
        previews=[q for f in mine for p in products if os.path.isfile(q := _preview_path(p.paths[f]))]
        if job.preview else [],
        skipped_outputs=[p.paths[f] for f in skipped for p in products],
        settings_digest=digests, estimates=estimates, lighting_estimates=lighting)


def _preview_path(exr_path: str) -> str:
    """``--preview``'s PNG beside an EXR."""
    return os.path.splitext(exr_path)[0] + ".png"
