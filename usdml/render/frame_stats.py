"""What one rendered frame cost and counted (:attr:`usdml.render.frame.FrameResult.stats`)."""

from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:       # the estimates' modules import the lighting layer; the annotations only name them
    from usdml.lighting.area.shading import AreaEstimate
    from usdml.render.estimate import VisibilityEstimate
    from usdml.render.lighting_estimate import LightingEstimate


@dataclass
class FrameStats:
    """Seconds of each step of a frame (summed over its passes) and what it counted.

    A field that is None (or ``camera_light`` False) did not apply to the frame and is left out of
    :meth:`as_dict`, whose keys are the field names.
    """

    snapshot_seconds: float = 0.0           #: reading the stage at the timecode
    update_seconds: float = 0.0             #: the primary and shadow backends brought to the frame
    gi_update_seconds: float | None = None  #: ``--gi svo``'s own backend brought to the frame (None: shared, or none)
    gbuffer_seconds: float = 0.0            #: primary rays
    shading_seconds: float = 0.0            #: direct light (and the camera light)
    shadow_queries: int = 0                 #: the direct light's shadow rays
    gi_seconds: float | None = None         #: ``--gi``: VPLs and their LGH, and the gathers of every pass
    #: ``--direct lgh``: the frame's hierarchy (:func:`usdml.lighting.lgh.direct.prepare_direct`) and its
    #: shading, numbers summed over passes
    direct_lgh: dict | None = None
    camera_light: bool = False              #: lit by usdrecord's camera light (the stage had no lights)
    gi: dict | None = None                  #: ``--gi``: the last pass's gather (``GIResult.stats``, usdml.lighting.gi)
    #: approximate ``--visibility`` with ``--direct all``: ε_v and ε_s estimated from a sample of the first
    #: pass's pairs traced exactly, with 95 % intervals and the seconds it took
    #: (:class:`usdml.render.estimate.VisibilityEstimate`; under ``--error-budget`` a
    #: :class:`usdml.render.budget.BudgetEstimate`)
    estimate: VisibilityEstimate | None = None
    #: ``--gi lgh`` / ``--direct lgh``: the LGH's relative RMSE and bias against brute force estimated from a
    #: sample of pixels, with 95 % intervals
    estimate_gi: LightingEstimate | None = None
    estimate_direct: LightingEstimate | None = None
    #: lights with area: the relative RMSE of ``direct`` their sampling leaves, estimated from each point's samples
    #: (:class:`usdml.lighting.area.shading.AreaEstimate`)
    estimate_area: AreaEstimate | None = None
    #: ``--denoise``: what was denoised, by which denoiser, in how many seconds
    #: (:func:`usdml.render.denoise.oidn.denoise_frame`)
    denoise: dict | None = None
    lights: int = 0                         #: the frame's lights, a dome's samples included
    pixels: int = 0
    pixel_samples: int = 0                  #: primary rays per pixel
    #: motion blur: the times (timecodes) the frame's passes were rendered at, one per pass (None: the frame's time)
    shutter_times: list | None = None
    lens_radius: float | None = None        #: depth of field: the thin lens's radius in scene units (None: a pinhole)
    seconds: float = 0.0                    #: the whole frame

    def as_dict(self) -> dict:
        """JSON-able: the fields that applied (class doc), nested dicts copied, the estimates as their ``as_dict()``."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None or (f.name == "camera_light" and not value):
                continue
            out[f.name] = value.as_dict() if is_dataclass(value) else dict(value) if isinstance(value, dict) else value
        return out
