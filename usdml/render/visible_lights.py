"""Lights the camera sees: the dome behind the geometry and the area lights in front of it (docs/visible-lights.md).

usdml follows Karma and Cycles, whose camera rays see lights (Storm's do not; ``--no-visible-lights`` gives
its images):

* a camera ray that reaches a rect, disk, sphere or cylinder light before any surface ends there and shows the
  light's radiance L toward the camera (nits, after ``normalize``, times its shaping cone and focus, as a
  surface at the camera would receive it). Rects and disks emit from their front only (the side their axis, the
  light's -Z, points to); from behind, like a cylinder's open ends, they are not there: usdml's lights cast no
  shadow and hide nothing, so the ray goes on. Point and distant lights have no area and stay unseen; lights of
  negative intensity (they take light away) too;
* a camera ray that reaches nothing shows the domes' radiance L(ω) in its direction
  (:meth:`usdml.scene.Dome.radiance_at`: the lat-long map and transform the dome lighting samples).

The light shapes are intersected analytically, each light only with the rays through the pixels its box (the
shape's extent along the light's axes) covers on screen, so thousands of small lights cost about as many
ray-shape tests as they cover pixels.
"""

from __future__ import annotations

import numpy as np

from usdml.scene import Camera, Lights, LightType
from usdml.scene.light_table import smoothstep_cone

__all__ = ["SEEN_TYPES", "dome_seen", "lights_seen"]

#: the light types a camera ray can hit (the others have no area)
SEEN_TYPES = (LightType.SPHERE, LightType.DISK, LightType.RECT, LightType.CYLINDER)

#: most (light, ray) pairs tested at once
_CHUNK = 1 << 20


def dome_seen(domes: list, dirs: np.ndarray, links=None) -> np.ndarray:
    """``(N, 3) float32`` radiance of every dome seen along world directions ``dirs (N, 3)`` (unit, away from the
    camera), summed over the domes: their own, without the lobe factor their radiance carries (``links``: the
    snapshot's :class:`usdml.scene.linking.LinkSets`, whose labels hold it)."""
    out = np.zeros((len(dirs), 3), np.float64)
    for dome in domes:
        label = None if links is None else links.labels.get(dome.path)
        out += dome.radiance_at(dirs) / (1.0 if label is None else label.scale)
    return out.astype(np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of ``(K, 3)`` arrays, column by column (sooner than ``einsum`` on long rows)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _half_extents(lights: Lights) -> np.ndarray:
    """``(N, 3)`` half sizes of a box around each light's shape along its unit X, Y, Z axes, centred on its
    position: rect (w/2, h/2, 0), disk (r, r, 0), sphere (r, r, r), cylinder (length/2, r, r)."""
    t, r = lights.type, lights.radius
    x = np.where((t == LightType.RECT) | (t == LightType.CYLINDER), 0.5 * lights.width, r)
    y = np.where(t == LightType.RECT, 0.5 * lights.height, r)
    return np.stack([x, y, np.where((t == LightType.RECT) | (t == LightType.DISK), 0.0, r)], axis=1)


def _pixel_boxes(camera: Camera, width: int, height: int, centres: np.ndarray, frames: np.ndarray,
                 half: np.ndarray) -> np.ndarray:
    """``(N, 4) int64`` pixel rectangles ``x0, x1, y0, y1`` (ends excluded) whose rays can reach the boxes
    ``centres (N, 3)``, unit axes ``frames (N, 3, 3)`` (:func:`_unit_columns`), half sizes ``half (N, 3)``: the
    screen box of each box's 8 corners, the whole image where a corner is not in front of the eye, empty where
    every corner is behind it."""
    world_to_cam = np.linalg.inv(camera.xform)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    corners = centres[:, None, :] + signs @ (half[:, :, None] * frames)     # (N, 8, 3) world
    corners = corners @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    projection = camera.projection_matrix()
    clip = corners @ projection[:, :3].T + projection[:, 3]
    w = clip[..., 3]
    front = w > 1e-9
    ndc = clip[..., :2] / np.where(front, w, 1.0)[..., None]
    x = (ndc[..., 0] + 1.0) * 0.5 * width
    y = (1.0 - ndc[..., 1]) * 0.5 * height
    boxes = np.stack([np.floor(x.min(1)), np.floor(x.max(1)) + 1, np.floor(y.min(1)), np.floor(y.max(1)) + 1], axis=1)
    boxes = np.where(front.all(1)[:, None], boxes, [0, width, 0, height])
    boxes[~front.any(1)] = 0
    lo = np.clip(boxes[:, [0, 2]], 0, [width, height])
    hi = np.clip(boxes[:, [1, 3]], 0, [width, height])
    return np.stack([lo[:, 0], np.maximum(hi[:, 0], lo[:, 0]), lo[:, 1], np.maximum(hi[:, 1], lo[:, 1])],
                    axis=1).astype(np.int64)


def _unit_columns(xform: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` the light frames' unit X, Y and Z axes in world space (``[:, k]`` is axis k)."""
    axes = np.swapaxes(xform[:, :3, :3], 1, 2)
    n = np.linalg.norm(axes, axis=2, keepdims=True)
    return axes / np.where(n > 0, n, 1.0)


def _shape_table(lights: Lights, frames: np.ndarray, half: np.ndarray) -> np.ndarray:
    """``(N, 14)`` what a ray test reads of each light, one row to gather per (light, ray) pair: its unit X, Y, Z
    axes (columns 0-8, ``frames``), position (9-11) and the first two of its :func:`_half_extents` ``half`` (12,
    13: a rect's half width and height, a disk's or sphere's radius, a cylinder's half length and radius)."""
    return np.concatenate([frames.reshape(-1, 9), lights.position, half[:, :2]], axis=1)


def _hit_distance(kind: LightType, rows: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``(K,)`` ray parameter where rays ``o + t·d`` (unit ``d``) enter the emitting surface of lights of type
    ``kind`` whose :func:`_shape_table` rows are ``rows``, inf where they miss it or see its back. In the light's
    frame: the ray's origin ``(ox, oy, oz)`` and direction ``(dx, dy, dz)`` along its unit axes."""
    oc = o - rows[:, 9:12]
    ox, oy, oz = (_dot(oc, rows[:, 3 * k:3 * k + 3]) for k in range(3))
    dx, dy, dz = (_dot(d, rows[:, 3 * k:3 * k + 3]) for k in range(3))
    half_x, half_y = rows[:, 12], rows[:, 13]
    if kind in (LightType.RECT, LightType.DISK):
        facing = dz > 0                             # the ray travels against the axis (-Z): it sees the front
        t = -oz / np.where(facing, dz, 1.0)
        u, v = ox + t * dx, oy + t * dy
        if kind == LightType.RECT:
            inside = (np.abs(u) <= half_x) & (np.abs(v) <= half_y)
        else:
            inside = u * u + v * v <= half_x * half_x
        ok = facing & inside
    elif kind == LightType.SPHERE:
        b = ox * dx + oy * dy + oz * dz
        disc = b * b - (ox * ox + oy * oy + oz * oz - half_x * half_x)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        ok = disc >= 0
    else:                                           # cylinder: its side, around its X axis
        a = dy * dy + dz * dz
        b = oy * dy + oz * dz
        disc = b * b - a * (oy * oy + oz * oz - half_y * half_y)
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / np.where(a > 0, a, 1.0)
        ok = (disc >= 0) & (a > 0) & (np.abs(ox + t * dx) <= half_x)
    return np.where(ok & (t >= 0), t, np.inf)


def _radiance_toward(lights: Lights, li: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``(K, 3)`` radiance lights ``li`` send back along rays of direction ``d``: L times the UsdLux shaping cone
    and focus at the angle between the light's axis and the direction to the camera."""
    cos_l = -_dot(lights.axis[li], d)
    scale = smoothstep_cone(cos_l, lights.cone_angle[li], lights.cone_softness[li]).astype(np.float64)
    focus, tint = lights.focus[li], lights.focus_tint[li].astype(np.float64)
    profile = np.where((focus > 0)[:, None], tint + (1 - tint) * (np.maximum(cos_l, 0.0) ** focus)[:, None], 1.0)
    # the light's own radiance: without the lobe factor its stored radiance carries (Lights.scale)
    own = lights.radiance[li].astype(np.float64) / lights.scale[li].astype(np.float64)[:, None]
    return own * scale[:, None] * profile


def lights_seen(lights: Lights, camera: Camera, width: int, height: int, origins: np.ndarray, dirs: np.ndarray,
                tmax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest area light along each camera ray of a ``width`` × ``height`` image (row-major from the top-left
    pixel, one ray per pixel, anywhere in it: :func:`usdml.render.gbuffer.camera_rays`).

    ``origins``, ``dirs`` : (H·W, 3) float64, unit ``dirs``; ``tmax`` : (H·W,) float64 ray length. Returns
    ``(t (H·W,) float64, inf where no light is hit before tmax; radiance (H·W, 3) float32 of the light hit)``.
    Of lights at the same distance, the first tested (by :data:`SEEN_TYPES`, then in order) is seen.
    """
    n = width * height
    best = np.array(tmax, np.float64, copy=True)
    seen = np.full(n, -1, np.int64)
    chosen = np.flatnonzero(np.isin(lights.type, [int(k) for k in SEEN_TYPES]) & ~lights.negative())
    if len(chosen):
        seen_lights = lights.subset(chosen)
        frames = _unit_columns(seen_lights.xform)
        half = _half_extents(seen_lights)
        table = np.zeros((len(lights), 14))
        table[chosen] = _shape_table(seen_lights, frames, half)
        boxes = _pixel_boxes(camera, width, height, seen_lights.position, frames, half)
        wide = boxes[:, 1] - boxes[:, 0]
        counts = wide * (boxes[:, 3] - boxes[:, 2])
        keep = counts > 0
        chosen, boxes, wide, counts = chosen[keep], boxes[keep], wide[keep], counts[keep]
        for kind in SEEN_TYPES:
            of = np.flatnonzero(lights.type[chosen] == int(kind))
            total = np.cumsum(counts[of])
            start = 0
            while start < len(of):          # lights in chunks of about _CHUNK pairs
                done = total[start - 1] if start else 0
                stop = max(start + 1, int(np.searchsorted(total, done + _CHUNK, side="right")))
                part = of[start:stop]
                start = stop
                _nearest(kind, table, chosen[part], boxes[part], wide[part], counts[part], width, origins, dirs,
                         best, seen)
    t = np.where(seen >= 0, best, np.inf)
    radiance = np.zeros((n, 3), np.float32)
    rays = np.flatnonzero(seen >= 0)
    radiance[rays] = _radiance_toward(lights, seen[rays], dirs[rays])
    return t, radiance


def _nearest(kind: LightType, table: np.ndarray, li: np.ndarray, boxes: np.ndarray, wide: np.ndarray,
             counts: np.ndarray, width: int, origins: np.ndarray, dirs: np.ndarray, best: np.ndarray,
             seen: np.ndarray) -> None:
    """Test lights ``li`` (one type) against the rays of their pixel ``boxes``; where one is nearer than
    ``best``, write its distance to ``best`` and its index to ``seen`` (in place)."""
    pair_light = np.repeat(np.arange(len(li)), counts)
    j = np.arange(len(pair_light)) - np.repeat(np.cumsum(counts) - counts, counts)
    col = boxes[pair_light, 0] + j % wide[pair_light]
    row = boxes[pair_light, 2] + j // wide[pair_light]
    ray = row * width + col
    light = li[pair_light]
    t = _hit_distance(kind, table[light], origins[ray], dirs[ray])
    hit = t < best[ray]
    ray, light, t = ray[hit], light[hit], t[hit]
    order = np.lexsort((light, t, ray))         # per ray: nearest first, ties by light order
    ray, light, t = ray[order], light[order], t[order]
    first = np.ones(len(ray), bool)
    first[1:] = ray[1:] != ray[:-1]
    best[ray[first]] = t[first]
    seen[ray[first]] = light[first]
