"""Camera selection (as usdrecord does) and reading ``UsdGeom.Camera`` into :class:`usdml.scene.Camera`."""

from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdml.errors import UsdmlError
from usdml.scene import Camera

DEFAULT_CAMERA_NAME = "main_cam"


def find_cameras(stage: Usd.Stage) -> list[Usd.Prim]:
    """Every active, defined camera prim in traversal order (instance proxies included)."""
    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Camera)]


def select_camera(stage: Usd.Stage, requested: str | None, cameras: list[Usd.Prim] | None = None) -> Usd.Prim | None:
    """``requested`` as a prim path or a prim name; else ``main_cam``; else the first camera; else None."""
    cameras = find_cameras(stage) if cameras is None else cameras
    if requested:
        if requested.startswith("/"):
            if not Sdf.Path.IsValidPathString(requested):
                raise UsdmlError(f"--camera {requested!r} is not a valid prim path" + _choices(cameras))
            prim = stage.GetPrimAtPath(requested)
            if not prim or not prim.IsA(UsdGeom.Camera):
                raise UsdmlError(f"camera {requested!r} not found on the stage"
                                 + _choices(cameras))
            return prim
        named = [c for c in cameras if c.GetName() == requested]
        if not named:
            raise UsdmlError(f"no camera named {requested!r} on the stage" + _choices(cameras))
        return named[0]
    named = [c for c in cameras if c.GetName() == DEFAULT_CAMERA_NAME]
    if named:
        return named[0]
    return cameras[0] if cameras else None


def _choices(cameras: list[Usd.Prim]) -> str:
    if not cameras:
        return "; the stage has no camera (omit --camera for a framing camera)"
    return "; cameras: " + ", ".join(str(c.GetPath()) for c in cameras[:8])


def read_camera(prim: Usd.Prim, time: Usd.TimeCode) -> Camera:
    """The camera at ``time``; its lens (``fStop``, ``focusDistance``) and shutter (``shutter:open``/``close``)
    checked: negative, non-finite or a shutter that closes before it opens is a one-line error."""
    camera = UsdGeom.Camera(prim)
    cam = camera.GetCamera(time)
    path = str(prim.GetPath())
    xform = np.array(cam.transform, np.float64).T
    if not np.isfinite(xform).all():
        raise UsdmlError(f"{path}: non-finite (NaN/inf) camera transform; fix its xformOps")
    # a zero scale on the camera (or an ancestor) leaves no view to invert
    linear = xform[:3, :3]
    if abs(np.linalg.det(linear)) <= 1e-9 * max(np.abs(linear).max(), 1e-300) ** 3:
        raise UsdmlError(f"{path}: camera transform is singular at time {time.GetValue():g} (a zero scale?); "
                         "fix its xformOps or those of its ancestors")
    values = [cam.focalLength, cam.horizontalAperture, cam.verticalAperture]
    if not np.isfinite(values).all() or min(values) <= 0:
        raise UsdmlError(f"{path}: focalLength/horizontalAperture/verticalAperture must be positive "
                         f"and finite, got {values}")
    near, far = cam.clippingRange.min, cam.clippingRange.max
    if not (0 < near < far):
        raise UsdmlError(f"{path}.clippingRange: ({near}, {far}) must satisfy 0 < near < far")
    f_stop, focus = float(cam.fStop), float(cam.focusDistance)
    for name, value in (("fStop", f_stop), ("focusDistance", focus)):
        if not np.isfinite(value) or value < 0:
            raise UsdmlError(f"{path}.{name}: {value:g} at time {time.GetValue():g} must be finite and >= 0 "
                             "(0: no depth of field)")
    shutter = (float(camera.GetShutterOpenAttr().Get(time)), float(camera.GetShutterCloseAttr().Get(time)))
    if not np.isfinite(shutter).all():
        raise UsdmlError(f"{path}: shutter:open/close {shutter} must be finite (timecodes around the frame)")
    if shutter[1] < shutter[0]:
        raise UsdmlError(f"{path}: shutter:close ({shutter[1]:g}) is before shutter:open ({shutter[0]:g}); "
                         "the shutter closes after it opens (in timecodes around the frame; equal: no motion blur)")
    return Camera(
        path=path, xform=xform, focal_length=cam.focalLength, f_stop=f_stop, focus_distance=focus, shutter=shutter,
        horizontal_aperture=cam.horizontalAperture, vertical_aperture=cam.verticalAperture,
        horizontal_aperture_offset=cam.horizontalApertureOffset,
        vertical_aperture_offset=cam.verticalApertureOffset, clipping_range=(near, far),
        projection="orthographic" if cam.projection == cam.Orthographic else "perspective")


#: usdrecord's camera for a stage without one is a default ``GfCamera``: a 50 mm lens on the 35 mm
#: Academy film back (UsdAppUtils' FrameRecorder, ``_ComputeCameraToFrameStage``)
FRAMING_FOCAL_LENGTH = 50.0
FRAMING_APERTURE = (20.955, 15.2908)


def framing_camera(bounds: tuple[np.ndarray, np.ndarray], up_axis: str) -> Camera:
    """usdrecord's framing camera for ``bounds`` (``(3,)`` world min and max corners, scene units).

    As UsdAppUtils' FrameRecorder frames a stage without a camera: a 50 mm lens on a 20.955 × 15.2908 film
    back (:data:`FRAMING_APERTURE`), looking at the bounds' centre along the stage's forward axis (down -Z
    from +Z for Y up; along +Y from -Y for Z up, Z up in the image), from where the half diagonal of the
    bounds' face toward it fills half the horizontal field of view, backed off by half the bounds' depth.
    The subject is centred and fills the width to ``w / diagonal`` of the face (a cube: 1/√2 of the
    width, 0.97 of the height)."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    center = (lo + hi) / 2
    dim = hi - lo
    z_up = up_axis == "Z"
    width, height, depth = (dim[0], dim[2], dim[1]) if z_up else (dim[0], dim[1], dim[2])
    h_ap, v_ap = FRAMING_APERTURE
    plane_radius = max(float(np.hypot(width, height)) / 2, 1e-3)
    # tan(half horizontal field of view) = h_ap / (2 f)
    dist = plane_radius * 2 * FRAMING_FOCAL_LENGTH / h_ap + depth / 2
    xform = np.eye(4)
    if z_up:        # rotated 90° about X: the camera's -Z looks along +Y, its +Y is the world's +Z
        xform[:3, 1], xform[:3, 2] = (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)
        xform[:3, 3] = center - (0.0, dist, 0.0)
    else:
        xform[:3, 3] = center + (0.0, 0.0, dist)
    radius = max(float(np.linalg.norm(dim)) / 2, 1e-3)      # the bounds' sphere, for the clipping range
    return Camera(path="", xform=xform, focal_length=FRAMING_FOCAL_LENGTH, horizontal_aperture=h_ap,
                  vertical_aperture=v_ap, clipping_range=(max(dist - radius, 1e-3 * dist) * 0.5, (dist + radius) * 2))
