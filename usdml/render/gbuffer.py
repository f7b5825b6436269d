"""The G-buffer: what each pixel's camera ray hits first (paper 000, Alg. 3 input).

Pixel (x, y) spans ``[x, x + 1) / W × [y, y + 1) / H`` of the film, row 0 at the top; a ray goes
through the point ``offsets`` places in it (the centre, ``(½, ½)``, unless
:func:`usdml.render.sampling.pixel_offsets` asks for correlated multi-jittered sub-pixel positions) and, with
depth of field, from the lens point ``lens`` places (:mod:`usdml.render.lens`). Rays start on the near clipping
plane and end on the far one, so clipping is honoured. Each hit has two normals: the geometric normal of the
triangle hit (Embree's), turned to face the camera (usdml shades both sides of every surface), and the shading
normal interpolated from the mesh's per-corner normals (instanced ones through the inverse transpose of their
instance transform), turned to the geometric normal's side. Which lights face a point, and where its shadow rays start, follow the
geometric normal; only the cosine of shading follows the shading normal, so tilted authored normals
never let a light behind the surface light it. With ``visible_lights`` the camera rays also see the lights
(:mod:`usdml.render.visible_lights`): an area light in front of every surface ends the ray (no surface there),
and a ray that reaches nothing sees the dome.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdml.render.lens import thin_lens_rays
from usdml.render.visible_lights import dome_seen, lights_seen
from usdml.scene import Camera, Snapshot
from usdml.scene.surface import surface_at_hits


@dataclass
class GBuffer:
    width: int
    height: int
    hit: np.ndarray         #: (H, W) bool, a surface was hit
    position: np.ndarray    #: (H, W, 3) float64 world position (0 on a miss)
    normal: np.ndarray      #: (H, W, 3) float32 unit world shading normal, on the geometric normal's side
    geometric: np.ndarray   #: (H, W, 3) float32 unit world geometric normal, facing the camera
    albedo: np.ndarray      #: (H, W, 3) float32 linear RGB diffuse reflectance (diffuseColor·(1 − metallic)·occlusion)
    depth: np.ndarray       #: (H, W) float32 camera-space depth (distance along the view axis), inf on a miss
    prim_id: np.ndarray     #: (H, W) int32 ``Mesh.id``, -1 on a miss
    instance_id: np.ndarray  #: (H, W) int64 instance id, -1 on a miss or a non-instanced mesh
    #: (H, W) int32 the primary backend's geometry source hit (its ``source``), -1 on a miss; and (H, W) int32 the
    #: triangle of that source's mesh (Cryptomatte's names: :mod:`usdml.render.mattes`)
    geom: np.ndarray | None = None
    triangle: np.ndarray | None = None
    #: (H·W, WIDTH) float32 BRDF rows of the hits (``kernels/brdf``), or None when every surface is Lambertian
    material: np.ndarray | None = None
    emission: np.ndarray | None = None   #: (H, W, 3) float32 emitted radiance (emissiveColor), or None
    #: (H, W, 3) float32 radiance of the area light a ray ends on before any surface (0 elsewhere), or None
    light: np.ndarray | None = None
    #: (H, W, 3) float32 the domes' radiance seen by rays that reach nothing (0 elsewhere), or None
    background: np.ndarray | None = None
    #: (H, W) bool the ray ends on a visible light or the dome (no surface), or None: nowhere
    emitter: np.ndarray | None = None

    @property
    def pixels(self) -> int:
        return self.width * self.height


@dataclass(frozen=True)
class PixelPass:
    """One primary ray per pixel: where in the pixel it goes and, with depth of field, where on the lens it
    leaves (:mod:`usdml.render.lens`)."""

    offsets: np.ndarray                 #: (H·W, 2) sub-pixel positions (:func:`usdml.render.sampling.pixel_offsets`)
    lens: np.ndarray | None = None      #: (H·W, 2) unit-disk lens points, or None: a pinhole


def camera_rays(camera: Camera, width: int, height: int, offsets: np.ndarray | None = None,
                lens: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World-space rays through every pixel, at its centre or at ``offsets``
    (:func:`usdml.render.sampling.pixel_offsets`); with
    ``lens`` (``(H·W, 2)`` unit-disk points, :func:`usdml.render.lens.lens_points`) and a camera with a lens
    (:attr:`~usdml.scene.Camera.lens_radius`), from those points of a thin lens (:mod:`usdml.render.lens`).

    Returns ``(origins (H·W, 3), unit directions (H·W, 3), tmax (H·W,))`` as float64, row-major from
    the top-left pixel; ``origins`` lie on the near plane, ``tmax`` reaches the far plane.
    """
    if offsets is None:
        offsets = np.full((width * height, 2), 0.5)
    col, row = np.meshgrid(np.arange(width), np.arange(height))
    nx = (col.ravel() + offsets[:, 0]) / width * 2.0 - 1.0
    ny = 1.0 - (row.ravel() + offsets[:, 1]) / height * 2.0
    inv = np.linalg.inv(camera.projection_matrix())

    def unproject(z: float) -> np.ndarray:
        ndc = np.stack([nx.ravel(), ny.ravel(), np.full(nx.size, z), np.ones(nx.size)], axis=1)
        p = ndc @ inv.T
        return p[:, :3] / p[:, 3:]

    near, far = unproject(-1.0), unproject(1.0)
    seg = far - near
    length = np.linalg.norm(seg, axis=1)
    d_cam = seg / length[:, None]
    radius = camera.lens_radius
    if lens is not None and radius > 0:
        near, d_cam, length = thin_lens_rays(d_cam, lens, radius, camera.focus_distance, camera.clipping_range)
    m = camera.xform
    origins = near @ m[:3, :3].T + m[:3, 3]
    dirs = d_cam @ m[:3, :3].T
    scale = np.linalg.norm(dirs, axis=1)        # camera transforms with scale stretch the ray
    return origins, dirs / scale[:, None], length * scale


def face_forward(v: np.ndarray, toward: np.ndarray) -> np.ndarray:
    """Rows of ``v`` negated where they point away from the matching rows of ``toward``."""
    return np.where((np.einsum("ij,ij->i", v, toward) < 0)[:, None], -v, v)


def build_gbuffer(snapshot: Snapshot, backend, width: int, height: int, offsets: np.ndarray | None = None,
                  visible_lights: bool = False, lens: np.ndarray | None = None) -> GBuffer:
    """Trace primary rays with ``backend.intersect`` (the exact backend) and fill the G-buffer; rays
    through pixel centres, or through ``offsets`` and ``lens`` (:func:`camera_rays`); ``visible_lights``: the
    rays see the snapshot's area lights and domes too (module doc)."""
    camera = snapshot.camera
    origins, dirs, tmax = camera_rays(camera, width, height, offsets, lens)
    n = width * height
    if visible_lights:
        t_light, light = lights_seen(snapshot.lights, camera, width, height, origins, dirs, tmax)
        tmax = np.minimum(tmax, t_light)        # a light in front hides the surfaces behind it
    h = surface_at_hits(snapshot, backend, origins, dirs, tmax)
    shape = (height, width)
    seen = emitter = background = None
    if visible_lights:
        on_light = np.isfinite(t_light) & ~h.hit
        emitter = on_light.copy()
        if on_light.any():
            seen = np.where(on_light[:, None], light, np.float32(0.0)).reshape(shape + (3,))
        if snapshot.domes:
            sky = ~h.hit & ~on_light
            background = np.zeros((n, 3), np.float32)
            background[sky] = dome_seen(snapshot.domes, dirs[sky], snapshot.links)
            background = background.reshape(shape + (3,))
            emitter |= sky
        emitter = emitter.reshape(shape) if emitter.any() else None
    geometric = face_forward(h.geometric, -dirs)
    normal = face_forward(h.normal, geometric)
    world_to_cam = np.linalg.inv(camera.xform)
    depth = np.full(n, np.inf, np.float32)
    depth[h.hit] = -(h.position[h.hit] @ world_to_cam[2, :3] + world_to_cam[2, 3])
    prim_id, instance_id = backend.ids(h.geom)
    return GBuffer(
        width=width, height=height, hit=h.hit.reshape(shape), position=h.position.reshape(shape + (3,)),
        normal=normal.astype(np.float32).reshape(shape + (3,)),
        geometric=geometric.astype(np.float32).reshape(shape + (3,)), albedo=h.albedo.reshape(shape + (3,)),
        depth=depth.reshape(shape), prim_id=prim_id.reshape(shape), instance_id=instance_id.reshape(shape),
        geom=h.geom.reshape(shape), triangle=h.triangle.reshape(shape),
        material=h.material, emission=None if h.emission is None else h.emission.reshape(shape + (3,)),
        light=seen, background=background, emitter=emitter)
