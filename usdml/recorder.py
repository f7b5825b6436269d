"""The Python API for pipeline scripts, shaped like OpenUSD's ``UsdAppUtils.FrameRecorder``.

::

    import usdml

    rec = usdml.Recorder(image_width=128, visibility="voxel", aovs=["color", "shadow"])
    result = rec.record("stages/park.usda", 12, "out/park.####.exr")     # a path or an open Usd.Stage
    print(result.files, result.seconds, result.warnings)
    rec.record_sequence("stages/park.usda", "12:14", "out/park.####.exr", resume=True)   # 12 is done: 13, 14

(from the repository's root: frames 12 to 14 of the sample park).

``usdrecord``'s ``FrameRecorder.Record(stage, usdCamera, timeCode, outputImagePath)`` takes the camera
per call; here the camera is a setting (``camera=``, a prim path or name, as ``--camera``), because
usdml's renderer keeps its visibility structures from frame to frame. ``usd-core`` has no
``UsdAppUtils``, so nothing of it is imported.

Settings are the command line's, as keyword arguments: the render options (``image_width``, ``camera``,
``purposes``, ``aovs``, ``render_settings``, ``device``, ``implicit_detail``, ``camera_light``,
``preview``; ``workers``, ``scheduler``, ``chunk_size``, ``retries``, ``nthreads`` for frames on Dask,
:mod:`usdml.render.farm`) and every field of the parameter table (:data:`usdml.params.PARAMS`: ``visibility``,
``gi``, ``pixel_samples``, ``seed``, the voxel, svo, insm and LGH parameters ...). They are checked
when the recorder is made, by the validation the command line uses (:func:`usdml.params.check`),
with the same one-line :class:`usdml.UsdmlError` messages. The ``usdml render`` command is this
class (:func:`usdml.cli.main` makes one), so a script and the command line render alike.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable
from numbers import Number

from usdml import params
from usdml.errors import UsdmlError

__all__ = ["Recorder", "RecordResult", "RENDER_OPTIONS"]

#: the options of a render beside the parameter table's fields, with their defaults
RENDER_OPTIONS = {"image_width": None, "camera": None, "purposes": None, "aovs": None, "render_settings": None,
                  "device": "cpu", "implicit_detail": 10, "camera_light": True, "preview": False,
                  # frames on Dask (usdml.render.farm): a local cluster of ``workers``, or a ``scheduler``
                  "workers": None, "scheduler": None, "chunk_size": 1, "retries": 2, "nthreads": None}
#: widest image a render takes
MAX_WIDTH = 16384
_WIDTH_RULE = f"an integer from 1 to {MAX_WIDTH} (pixels)"


@dataclass
class RecordResult:
    """What one :meth:`Recorder.record` or :meth:`Recorder.record_sequence` did."""

    files: list[str]                 #: the EXR files this call wrote, in frame order (not the skipped frames')
    frames: list[float]              #: the timecodes rendered
    skipped: list[float]             #: timecodes already complete with these settings (``resume``), not rendered
    seconds: float                   #: the whole call
    seconds_per_frame: float
    resolution: list[int]
    warnings: list[str] = field(default_factory=list)   #: what the stage and the render warned about
    failed: list[float] = field(default_factory=list)   #: on Dask: timecodes whose chunk failed every attempt
    rerun: str | None = None                            #: a FrameSpec of ``failed``
    summary: dict = field(default_factory=dict)         #: ``usdml render --json``'s summary
    #: timecodes whose files were complete but made with other settings or stage content (``resume``): rendered
    #: again, so also in ``frames``
    stale: list[float] = field(default_factory=list)
    previews: list[str] = field(default_factory=list)   #: the PNG previews this call wrote (``preview``)
    skipped_files: list[str] = field(default_factory=list)   #: the files of ``skipped``, left as they were


def check_width(width: int | None, name: str = "--imageWidth") -> None:
    """A one-line error for an image width outside ``1 .. MAX_WIDTH`` (``name``: how the user gave it)."""
    if width is not None and not 1 <= width <= MAX_WIDTH:
        raise UsdmlError(f"{name} {width}: give {_WIDTH_RULE}")


def _names(value) -> bool:
    """A name, or a list / tuple of names (``aovs``, ``purposes``)."""
    return isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value))


def _int_from(low: int, high: int | None = None) -> Callable[[object], bool]:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= low and (high is None or v <= high)


#: each render option: (its flag, what it accepts, that in words); None is always accepted (the default)
_OPTION_RULES = {
    "image_width": ("--imageWidth", _int_from(1, MAX_WIDTH), _WIDTH_RULE),
    "camera": ("--camera", lambda v: isinstance(v, str), "a camera prim path or name"),
    "purposes": ("--purposes", _names, "a list of purposes (render, proxy, guide)"),
    "aovs": ("--aovs", _names, "a list of AOV names"),
    "render_settings": ("--renderSettingsPrimPath", lambda v: isinstance(v, str), "a RenderSettings prim path"),
    "device": ("--device", lambda v: v in ("cpu", "cuda"), "cpu or cuda"),
    "implicit_detail": ("--implicit-detail", _int_from(3, params.MAX_IMPLICIT_DETAIL),
                        f"an integer from 3 to {params.MAX_IMPLICIT_DETAIL} (segments)"),
    "camera_light": ("--disableCameraLight", lambda v: isinstance(v, bool), "True or False"),
    "preview": ("--preview", lambda v: isinstance(v, bool), "True or False"),
    "workers": ("--workers", _int_from(1), "an integer of 1 or more"),
    "scheduler": ("--scheduler", lambda v: isinstance(v, str), "a scheduler address (tcp://HOST:PORT)"),
    "chunk_size": ("--chunk-size", _int_from(1), "an integer of 1 or more (frames)"),
    "retries": ("--retries", _int_from(0), "an integer of 0 or more"),
    "nthreads": ("--nthreads", _int_from(1), "an integer of 1 or more"),
}


def _unknown_keywords(unknown: list[str], known: list[str]) -> str:
    """``Recorder``'s one line for misspelt keywords: each with the nearest known one, if any is close."""
    import difflib

    said = []
    for k in unknown:
        near = difflib.get_close_matches(k, known, n=1, cutoff=0.6)
        said.append(f"{k} (did you mean {near[0]}?)" if near else k)
    return (f"Recorder: unknown keyword(s) {', '.join(said)}; the keywords are the render options "
            f"({', '.join(RENDER_OPTIONS)}) and the settings of usdml.params.PARAMS")


def frames_text(frames) -> str | None:
    """A FrameSpec string from ``frames``: a FrameSpec (``"101:148"``, ``"1:10x2"``), one timecode, a list of
    them, or None (the stage's start frame)."""
    if frames is None or isinstance(frames, str):
        return frames
    if isinstance(frames, Number):
        return f"{float(frames):g}"
    items = list(frames)
    if not items or not all(isinstance(f, Number) for f in items):
        raise UsdmlError(f"frames {frames!r}: give a FrameSpec ('101:148'), a timecode or a list of timecodes")
    return ",".join(f"{float(f):g}" for f in items)


class _Collect(logging.Handler):
    """The ``usdml`` logger's warnings during one call."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


class Recorder:
    """Renders frames of a stage to EXR (module doc). Keyword arguments: :data:`RENDER_OPTIONS` and the
    parameter table's fields; a stage's own ``usdml:*`` attributes apply where a keyword is not given,
    as on the command line."""

    def __init__(self, *, _flags: bool = False, **settings) -> None:
        # _flags: made by ``usdml render``, whose messages name the flags; a script's name its keywords
        unknown = sorted(k for k in settings if k not in RENDER_OPTIONS and k not in params.PARAMS)
        if unknown:
            raise UsdmlError(_unknown_keywords(unknown, list(RENDER_OPTIONS) + list(params.PARAMS)))
        self.options = {k: settings.get(k, v) for k, v in RENDER_OPTIONS.items()}
        for name, value in self.options.items():
            flag, accepts, rule = _OPTION_RULES[name]
            if value is not None and not accepts(value):
                raise UsdmlError(f"{flag if _flags else 'Recorder: ' + name} {value!r}: give {rule}")
        self.overrides = {k: v for k, v in settings.items() if k in params.PARAMS and v is not None}
        for name, value in self.overrides.items():
            params.check(name, value, keyword=not _flags)
        aovs = self.options["aovs"]
        if isinstance(aovs, str):
            self.options["aovs"] = [a for a in aovs.split(",") if a]
        if self.options["purposes"] is not None:
            self.options["purposes"] = list(self.options["purposes"])

    def record(self, stage, time_code: float, output_path: str | None) -> RecordResult:
        """Render ``time_code`` of ``stage`` (a path or an open ``Usd.Stage``) to ``output_path``: that
        file, or with ``#`` placeholders the frame's (None: the stage's RenderSettings products)."""
        return self.record_sequence(stage, [time_code], output_path, single_file=True)

    def record_sequence(self, stage, frames=None, output_path: str | None = None, resume: bool = False,
                        single_file: bool = False) -> RecordResult:
        """Render ``frames`` (a FrameSpec such as ``"101:148"`` or ``"1:10x2"``, timecodes, or None: the
        start frame) of ``stage`` to ``output_path``, whose frame placeholders follow usdrecord's rule
        (one is needed when frames are given); ``resume`` skips frames whose files are complete;
        ``single_file``: one frame to ``output_path`` as it is (:meth:`record`). A file counts as complete
        when it decodes in full and its ``usdml:settingsDigest`` matches this render's settings and stage
        (:mod:`usdml.render.identity`); one with other settings is rendered again and listed in ``stale``."""
        from usdml.render.sequence import RenderJob, render_sequence

        o = self.options
        job = RenderJob(stage=stage, output=output_path, frames=frames_text(frames), camera=o["camera"],
                        image_width=o["image_width"], render_settings=o["render_settings"], aovs=o["aovs"],
                        device=o["device"], resume=resume, preview=o["preview"], purposes=o["purposes"],
                        implicit_detail=o["implicit_detail"], camera_light=o["camera_light"],
                        overrides=dict(self.overrides), single_file=single_file)
        collect = _Collect()
        logger = logging.getLogger("usdml")
        logger.addHandler(collect)
        try:
            if o["workers"] is not None or o["scheduler"] is not None:
                summary = self._on_dask(job)
            else:
                summary = render_sequence(job)
        finally:
            logger.removeHandler(collect)
        return RecordResult(files=list(summary["outputs"]), frames=list(summary["frames"]),
                            skipped=list(summary["skipped"]), seconds=summary["seconds"],
                            seconds_per_frame=summary["secondsPerFrame"], resolution=list(summary["resolution"]),
                            warnings=collect.messages, failed=list(summary.get("failed", [])),
                            rerun=summary.get("rerun"), summary=summary, stale=list(summary["stale"]),
                            previews=list(summary["previews"]), skipped_files=list(summary["skippedOutputs"]))

    def _on_dask(self, job) -> dict:
        """The job's frames as chunks on Dask (:mod:`usdml.render.farm`)."""
        from usdml.aov.naming import frame_spec
        from usdml.render.farm import render_on_dask
        from usdml.stage import StageDelegate

        delegate = StageDelegate(job.stage, camera=job.camera, render_settings_path=job.render_settings,
                                 purposes=job.purposes, implicit_detail=job.implicit_detail)
        frames = frame_spec(job.frames, delegate.start_time, delegate.end_time)
        for f in frames:
            delegate.check_time(f)
        o = self.options
        return render_on_dask(job, frames, workers=o["workers"], scheduler=o["scheduler"], chunk_size=o["chunk_size"],
                              retries=o["retries"], nthreads=o["nthreads"])

