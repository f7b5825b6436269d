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

from dataclasses import dataclass, field, replace
from numbers import Number
from typing import TYPE_CHECKING

from usdml import params
from usdml.aov.naming import timecodes
from usdml.errors import UsdmlError, collect_warnings

if TYPE_CHECKING:       # the render layer is imported when a recorder renders, not with ``import usdml``
    from usdml.render.result import SequenceResult

__all__ = ["Recorder", "RecordResult", "RENDER_OPTIONS"]

#: the options of a render beside the parameter table's fields, with their defaults (:data:`usdml.params.OPTIONS`)
RENDER_OPTIONS = {p.field: p.default for p in params.OPTIONS.values()}
#: widest image a render takes
MAX_WIDTH = params.MAX_WIDTH


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
    #: approximate visibility: each rendered frame's estimate of ε_v and ε_s with 95 % intervals
    #: (:class:`usdml.render.estimate.VisibilityEstimate`'s fields), by timecode
    estimates: dict[float, dict] = field(default_factory=dict)
    #: ``--gi lgh`` / ``--direct lgh``: each rendered frame's ``{"gi": ..., "direct": ...}`` estimates of the LGH's
    #: relative RMSE and bias against brute force (:class:`usdml.render.lighting_estimate.LightingEstimate`'s
    #: fields), by timecode
    lighting_estimates: dict[float, dict] = field(default_factory=dict)

    @classmethod
    def of(cls, result: SequenceResult) -> RecordResult:
        """The record of a render (:class:`usdml.render.result.SequenceResult`), ``summary`` its JSON."""
        run = result.dask
        return cls(files=list(result.outputs), frames=list(result.frames), skipped=list(result.skipped),
                   seconds=result.seconds, seconds_per_frame=result.seconds_per_frame,
                   resolution=list(result.resolution), warnings=list(result.warnings),
                   failed=list(run.failed) if run else [], rerun=run.rerun if run else None,
                   summary=result.as_json(), stale=list(result.stale), previews=list(result.previews),
                   skipped_files=list(result.skipped_outputs), estimates=result.estimate_fields(),
                   lighting_estimates=result.lighting_estimate_fields())


def check_width(width: int | None, name: str = "--imageWidth") -> None:
    """A one-line error for an image width outside ``1 .. MAX_WIDTH`` (``name``: how the user gave it)."""
    row = params.OPTIONS["image_width"]
    if width is not None and not row.accepts(width):
        raise UsdmlError(f"{name} {width}: give {row.rule}")


def _unknown_keywords(unknown: list[str], known: list[str]) -> str:
    """``Recorder``'s one line for misspelt keywords: each with the nearest known one, if any is close."""
    import difflib

    said = []
    for k in unknown:
        near = difflib.get_close_matches(k, known, n=1, cutoff=0.6)
        said.append(f"{k} (did you mean {near[0]}?)" if near else k)
    return (f"Recorder: unknown keyword(s) {', '.join(said)}; the keywords are the render options "
            f"({', '.join(RENDER_OPTIONS)}) and the settings of usdml.params.PARAMS")


def job_frames(frames) -> str | list[float] | None:
    """``frames`` as :class:`usdml.render.sequence.RenderJob` takes them: a FrameSpec (``"101:148"``,
    ``"1:10x2"``) as it is, one timecode or a list of them as floats (never through FrameSpec text), or
    None (the stage's start frame)."""
    if frames is None or isinstance(frames, str):
        return frames
    return timecodes([frames] if isinstance(frames, Number) else frames)


def _one_way_to_run(options: dict, flags: bool) -> None:
    """A one-line error for both ``workers`` and ``scheduler``: two ways of running the frames, refused when
    the recorder is made, before a stage is read or a scheduler waited for."""
    if options["workers"] is None or options["scheduler"] is None:
        return
    workers, scheduler = params.OPTIONS["workers"], params.OPTIONS["scheduler"]
    if flags:
        given = f"{workers.flag} {options['workers']} and {scheduler.flag} {options['scheduler']}"
        choose = f"{workers.flag} N (a local cluster) or {scheduler.flag} ADDRESS (a running one)"
    else:
        given = f"Recorder: workers={options['workers']!r} and scheduler={options['scheduler']!r}"
        choose = "workers (a local cluster) or scheduler (a running one)"
    raise UsdmlError(f"{given}: two ways of running the frames; give {choose}, not both")


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
            row = params.OPTIONS[name]
            if value is not None and not row.accepts(value):
                raise UsdmlError(f"{row.flag if _flags else 'Recorder: ' + name} {value!r}: give {row.rule}")
        _one_way_to_run(self.options, _flags)
        self.overrides = {k: v for k, v in settings.items() if k in params.PARAMS and v is not None}
        for name, value in self.overrides.items():
            params.check(name, value, keyword=not _flags)
        aovs = self.options["aovs"]         # "a,b" or names, each of them comma-separated (--aovs a,b --aovs c)
        if aovs is not None:
            self.options["aovs"] = [a for spec in ([aovs] if isinstance(aovs, str) else aovs)
                                    for a in spec.split(",") if a] or None
        self.options["purposes"] = params.purpose_list(self.options["purposes"],
                                                       "--purposes" if _flags else "Recorder: purposes")

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

        job = RenderJob(**self.options, stage=stage, output=output_path, frames=job_frames(frames), resume=resume,
                        overrides=dict(self.overrides), single_file=single_file)
        on_dask = job.workers is not None or job.scheduler is not None
        return RecordResult.of(self._on_dask(job) if on_dask else render_sequence(job))

    def _on_dask(self, job) -> SequenceResult:
        """The job's frames as chunks on Dask (:mod:`usdml.render.farm`); the warnings of reading the stage here
        before the run's."""
        from usdml.aov.naming import frame_spec
        from usdml.render.denoise.oidn import require_denoiser
        from usdml.render.farm import render_on_dask
        from usdml.stage import StageDelegate

        with collect_warnings() as warnings:
            delegate = StageDelegate(job.stage, camera=job.camera, render_settings_path=job.render_settings,
                                     purposes=job.purposes, implicit_detail=job.implicit_detail)
            frames = frame_spec(job.frames, delegate.start_time, delegate.end_time)
            delegate.check_times(frames)
        if delegate.usdml_settings.updated(**job.overrides).denoise:     # here, not in the first worker's task
            require_denoiser(params.PARAMS["denoise"].where)
        result = render_on_dask(job, frames)
        return replace(result, warnings=warnings + result.warnings)

