"""Motion blur: the times a frame's passes are rendered at, spread over the camera's shutter.

``UsdGeom.Camera``'s ``shutter:open`` and ``shutter:close`` are timecodes relative to the frame's (``-0.25, 0.25``:
a 180° shutter centred on the frame); open == close (USD's default, 0 and 0) is an instant and no blur. Motion
blur is on unless ``--no-motion-blur`` (``usdml:motionBlur false``) or the RenderSettings' standard
``disableMotionBlur`` turn it off.

Each pass of the frame (one primary ray per pixel, :class:`usdml.render.gbuffer.PixelPass`) is a time slice:
the stage is read at its time, the backends, lights and camera brought there, and its rays traced and shaded
there, shadows included. Every moving thing then moves as USD says it is at that time: transforms and points
interpolated between their time samples, ``velocities``/``accelerations`` (meshes and PointInstancers) and
``angularVelocities`` extrapolated, skeletons posed, cameras and lights moved. The ``samples`` passes take one
time each from ``samples`` equal strata of the shutter, jittered, in a seeded order, so each pixel's samples are
stratified in time; each pixel pairs its sub-pixel cells with the passes by a seeded shift
(:func:`usdml.render.sampling.pixel_offsets` ``shifted``), so no pairing of times and cells is shared by every pixel.

Every pixel of a pass shares its time (an accumulation buffer, not a time per ray): a fast object at few samples
shows as faint copies rather than noise. A time per ray needs geometry at every time in one structure (Embree's
motion blur: several time steps per geometry and a time in every ray), which ``embreex`` does not expose; measured
through Embree's own library (``tools/embree_motion_blur.py``) it pays for heavy deformers only, its slower
traversal outweighing the saved rebuilds when there are many lights. Slices need nothing of a backend but its
update (docs/motion-blur.md).
"""

from __future__ import annotations

import numpy as np

from usdml.scene import Snapshot
from usdml.settings import UsdmlSettings

#: the pass times' stream of random numbers
_TIME_STREAM = 0x5348


def blurs(snapshot: Snapshot, settings: UsdmlSettings) -> bool:
    """Whether the frame of ``snapshot`` is motion-blurred: an open shutter, and not turned off (module doc)."""
    camera = snapshot.camera
    rs = snapshot.render_settings
    return (camera is not None and camera.shutter[1] > camera.shutter[0] and settings.motion_blur
            and not (rs is not None and rs.disable_motion_blur))


def pass_times(snapshot: Snapshot, settings: UsdmlSettings, samples: int) -> list[float] | None:
    """The timecode of each of a frame's ``samples`` passes (module doc), or None: no motion blur, every pass at
    the frame's time. Seeded by ``settings.seed`` and the frame's time."""
    if not blurs(snapshot, settings):
        return None
    open_, close = snapshot.camera.shutter
    rng = np.random.default_rng([settings.seed, _TIME_STREAM, int(np.float64(snapshot.time).view(np.uint64))])
    strata = rng.permutation(samples)
    u = (strata + rng.random(samples)) / samples
    return [float(snapshot.time + open_ + (close - open_) * x) for x in u]


def camera_headers(stats, camera) -> dict:
    """The EXR attributes of what the frame's camera blurred (:class:`usdml.render.frame_stats.FrameStats`):
    ``usdml:shutter:open``/``close`` (timecodes around the frame) and ``usdml:shutter:slices`` with motion blur,
    ``usdml:lens:fStop``/``focusDistance``/``radius`` (scene units) with depth of field; empty for a sharp frame."""
    out = {}
    if stats.shutter_times:
        out.update({"usdml:shutter:open": float(camera.shutter[0]), "usdml:shutter:close": float(camera.shutter[1]),
                    "usdml:shutter:slices": len(stats.shutter_times)})
    if stats.lens_radius:
        out.update({"usdml:lens:fStop": float(camera.f_stop), "usdml:lens:focusDistance": float(camera.focus_distance),
                    "usdml:lens:radius": float(stats.lens_radius)})
    return out
