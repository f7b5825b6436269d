"""What a render of a sequence did: one typed result, from :func:`usdml.render.sequence.render_sequence` and
:func:`usdml.render.farm.render_on_dask` (whose workers send theirs back pickled). The edges make from it
``usdml render --json``'s summary (:meth:`SequenceResult.as_json`) and :class:`usdml.RecordResult`; frames stay
timecodes (floats) and estimates their own dataclasses until then.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:       # the estimates' modules import the lighting layer; the annotations only name them
    from usdml.render.estimate import VisibilityEstimate
    from usdml.render.lighting_estimate import LightingEstimate

__all__ = ["SequenceResult", "DaskRun"]


@dataclass(frozen=True)
class DaskRun:
    """What a render on Dask adds (:mod:`usdml.render.farm`)."""

    failed: list[float]             #: timecodes whose chunk failed every attempt
    rerun: str | None               #: a FrameSpec of ``failed`` (None: none failed)
    errors: dict[float, str]        #: each failed timecode's message (its first line)
    startup_seconds: float          #: until the cluster's workers were ready
    workers: int | None             #: ``--workers`` (None: ``--scheduler``'s cluster)
    scheduler: str | None
    chunk_size: int
    retries: int
    threads_per_worker: int


@dataclass(frozen=True)
class SequenceResult:
    """One render of a sequence (module doc). Timecodes are floats, in the FrameSpec's order."""

    stage: str                      #: the stage's path (on Dask: absolute)
    frames: list[float]             #: rendered by this call (on Dask: with those a killed attempt finished)
    skipped: list[float]            #: ``resume``: complete with these settings, left alone
    stale: list[float]              #: ``resume``: complete with other settings, rendered again (also in ``frames``)
    recovered: list[float]          #: ``resume_since``: finished by an earlier attempt of this run (a farm chunk's)
    resolution: tuple[int, int]     #: width, height in pixels
    seconds_per_frame: float        #: the mean over the frames rendered (0: none)
    seconds: float                  #: the whole call
    visibility: str                 #: the shadow backend's name
    outputs: list[str]              #: the EXR files of ``frames`` and ``recovered``
    previews: list[str]             #: their PNGs (``preview``)
    skipped_outputs: list[str]      #: the files of ``skipped``
    settings_digest: list[str]      #: per product (:mod:`usdml.render.identity`)
    #: approximate visibility: each rendered frame's estimate of ε_v and ε_s (a ``BudgetEstimate`` under
    #: ``--error-budget``), by timecode
    estimates: dict[float, VisibilityEstimate] = field(default_factory=dict)
    #: ``--gi lgh`` / ``--direct lgh``: each rendered frame's ``{"gi": ..., "direct": ...}`` LGH estimates, by timecode
    lighting_estimates: dict[float, dict[str, LightingEstimate]] = field(default_factory=dict)   # and "area"
    warnings: list[str] = field(default_factory=list)   #: what the stage and the render warned about
    dask: DaskRun | None = None     #: rendered on Dask: what the run adds

    def estimate_fields(self) -> dict[float, dict]:
        """:attr:`estimates` as their fields (``VisibilityEstimate.as_dict``), by timecode."""
        return {f: e.as_dict() for f, e in self.estimates.items()}

    def lighting_estimate_fields(self) -> dict[float, dict[str, dict]]:
        """:attr:`lighting_estimates` as their fields, by timecode and kind."""
        return {f: {kind: e.as_dict() for kind, e in kinds.items()} for f, kinds in self.lighting_estimates.items()}

    def as_json(self) -> dict:
        """``usdml render --json``'s summary: camelCase keys, timecodes as FrameSpec text (``f"{f:g}"``) where
        they are keys; on Dask the run's keys (``failed``, ``rerun``, ``errors``, ``startupSeconds`` ...) in place
        of ``recovered`` and ``settingsDigest``; ``warnings`` every message, also those the command printed once
        for several prims."""
        files = {"outputs": list(self.outputs), "previews": list(self.previews),
                 "skippedOutputs": list(self.skipped_outputs)}
        estimates = {"estimates": {f"{f:g}": e for f, e in self.estimate_fields().items()},
                     "lightingEstimates": {f"{f:g}": e for f, e in self.lighting_estimate_fields().items()}}
        resolution = list(self.resolution)
        if self.dask is None:
            return {"stage": self.stage, "frames": list(self.frames), "skipped": list(self.skipped),
                    "stale": list(self.stale), "recovered": list(self.recovered), "resolution": resolution,
                    "secondsPerFrame": self.seconds_per_frame, "seconds": self.seconds, "visibility": self.visibility,
                    **files, "settingsDigest": list(self.settings_digest), **estimates, "warnings": list(self.warnings)}
        run = self.dask
        return {"stage": self.stage, "frames": list(self.frames), "failed": list(run.failed),
                "skipped": list(self.skipped), "stale": list(self.stale), "rerun": run.rerun,
                "errors": {f"{f:g}": message for f, message in run.errors.items()},
                "resolution": resolution, "visibility": self.visibility, "secondsPerFrame": self.seconds_per_frame,
                "seconds": self.seconds, "startupSeconds": run.startup_seconds, "workers": run.workers,
                "scheduler": run.scheduler, "chunkSize": run.chunk_size, "retries": run.retries,
                "threadsPerWorker": run.threads_per_worker, **files, **estimates, "warnings": list(self.warnings)}
