"""One frame of a stage as the paper 004 figure tools need it (``gi_table.py``, ``lgh_build_times.py``)."""

from __future__ import annotations


def open_frame(stage: str, frame: float | None = None):
    """``(delegate, frame, snapshot, renderer, lights)`` of ``frame`` (default: the stage's start): the
    renderer's exact backend holds the frame's geometry, ``lights`` are the frame's lights with any
    dome light sampled into distant lights, as a render sees them."""
    from usdml.render.frame import FrameRenderer
    from usdml.scene import diff
    from usdml.stage import StageDelegate

    delegate = StageDelegate(stage)
    frame = delegate.start_time if frame is None else frame
    delegate.check_time(frame)
    snap = delegate.snapshot(frame)
    renderer = FrameRenderer(delegate, delegate.usdml_settings)
    renderer.backends.primary.update(snap, diff(None, snap))
    return delegate, frame, snap, renderer, renderer.frame_lights(snap)
