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
    cam = UsdGeom.Camera(prim).GetCamera(time)
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
    return Camera(
        path=path, xform=xform, focal_length=cam.focalLength,
        horizontal_aperture=cam.horizontalAperture, vertical_aperture=cam.verticalAperture,
        horizontal_aperture_offset=cam.horizontalApertureOffset,
        vertical_aperture_offset=cam.verticalApertureOffset, clipping_range=(near, far),
        projection="orthographic" if cam.projection == cam.Orthographic else "perspective")


def framing_camera(bounds: tuple[np.ndarray, np.ndarray], up_axis: str, aspect: float = 16 / 9) -> Camera:
    """A perspective camera looking at the bounds' centre from above and in front, seeing all of it."""
    lo, hi = bounds
    center = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    focal, h_ap = 35.0, 36.0
    v_ap = h_ap / aspect
    half_fov = np.arctan(min(h_ap, v_ap) / (2 * focal))
    dist = radius / np.sin(half_fov) * 1.05
    up = np.array([0.0, 0.0, 1.0]) if up_axis == "Z" else np.array([0.0, 1.0, 0.0])
    side = np.array([1.0, 0.0, 0.0])
    front = np.cross(side, up)      # +Z for Y-up, -Y for Z-up
    view = 0.7 * front + 0.45 * up + 0.55 * side
    eye = center + dist * view / np.linalg.norm(view)
    back = (eye - center) / np.linalg.norm(eye - center)           # camera +Z
    x = np.cross(up, back)
    x /= np.linalg.norm(x)
    y = np.cross(back, x)
    xform = np.eye(4)
    xform[:3, 0], xform[:3, 1], xform[:3, 2], xform[:3, 3] = x, y, back, eye
    return Camera(path="", xform=xform, focal_length=focal, horizontal_aperture=h_ap,
                  vertical_aperture=v_ap, clipping_range=(max(dist - radius, 1e-3) * 0.5, (dist + radius) * 2))
