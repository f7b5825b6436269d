"""``usdml view``: a stage's frame in 3-D with pyvista: geometry shaded by its albedo, instances of each
prototype told apart, cameras as frusta (the render camera highlighted), lights as glyphs coloured by
their emitted colour and sized by their intensity, distant lights as arrows, a dome light as the sky;
on request the sparse voxel octree's occupied voxels, the frame's VPLs and an LGH level's grid lights.

Off-screen to a PNG by default; an interactive window with ``--interactive`` where a display exists.
With no display, VTK renders through EGL (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``, set here
when ``DISPLAY`` is unset, so VTK skips its failed X attempt). A machine without EGL or OSMesa makes
VTK crash rather than raise, so :func:`probe` renders a tiny scene in a subprocess first and turns a
failure into one line.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from usdml.errors import UsdmlError

__all__ = ["LAYERS", "probe", "view"]

#: what ``--show`` can draw
LAYERS = ("geometry", "cameras", "lights", "instances", "voxels", "vpls", "lgh")
#: an instance's colour: the golden-angle hue of its prototype, its lightness by instance
_GOLDEN = 0.381966

_PROBE = ("import pyvista as pv; p = pv.Plotter(off_screen=True, window_size=(16, 16)); "
          "p.add_mesh(pv.Sphere()); p.screenshot(None); p.close()")


def _offscreen_env() -> dict:
    env = dict(os.environ)
    if not env.get("DISPLAY"):
        env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    return env


def probe() -> str | None:
    """None when pyvista can render off-screen here, else why not (one line); run in a subprocess, since
    VTK without EGL or OSMesa aborts the process instead of raising."""
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=60,
                              env=_offscreen_env())
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"pyvista's off-screen rendering did not start ({e})"
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        return f"pyvista cannot render off-screen here ({last}); install EGL or OSMesa drivers, or run with a display"
    return None


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    import colorsys
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def _mesh(points: np.ndarray, triangles: np.ndarray):
    import pyvista as pv
    faces = np.hstack([np.full((len(triangles), 1), 3), triangles]).astype(np.int64).ravel()
    return pv.PolyData(np.asarray(points, np.float64), faces)


def _frustum(cam, length: float):
    """The camera's frustum (:class:`usdml.scene.Camera`, camera-to-world in column convention, looking
    down its -Z) as line segments ``length`` long in world units."""
    import pyvista as pv
    m = np.asarray(cam.xform, np.float64)
    apex = m[:3, 3]
    right, up, back = (m[:3, k] / max(np.linalg.norm(m[:3, k]), 1e-300) for k in range(3))
    hw = 0.5 * cam.horizontal_aperture / max(cam.focal_length, 1e-9)
    hh = 0.5 * cam.vertical_aperture / max(cam.focal_length, 1e-9)
    corners = [apex + length * (-back + sx * hw * right + sy * hh * up) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 2, 1, 2, 2, 2, 3, 2, 3, 4, 2, 4, 1]
    return pv.PolyData(np.array([apex, *corners]), lines=np.array(lines))


def occupied_voxels(snap, resolution: int, bounds: tuple | None = None) -> tuple[np.ndarray, float]:
    """``(K, 3)`` world centres of the voxels the sparse voxel octree (paper 003) sets for the frame's
    geometry at ``resolution``³ over the scene's detail box (``bounds``, when the caller has it), and
    the voxel size."""
    from usdml.scene import world_geometry
    from usdml.visibility.base import all_members
    from usdml.visibility.svo.tree import cube_grid, svo_bounds, voxelize_bricks

    members = all_members(snap)
    pts, tris = world_geometry(snap, members)
    if not len(tris):
        return np.zeros((0, 3)), 1.0
    depth = int(resolution).bit_length() - 1
    lo, hi = bounds if bounds is not None else svo_bounds(pts, tris)[:2]
    corner, h = cube_grid(np.asarray(lo), np.asarray(hi), depth)
    bricks = voxelize_bricks(pts, tris, corner, h, depth).view(np.uint64)
    nb = (1 << depth) // 4
    idx = np.flatnonzero(bricks)
    bz, by, bx = np.unravel_index(idx, (nb, nb, nb))
    bits = (bricks[idx, None] >> np.arange(64, dtype=np.uint64)[None, :]) & np.uint64(1)
    b, k = np.nonzero(bits)
    x, y, z = 4 * bx[b] + (k & 3), 4 * by[b] + ((k >> 2) & 3), 4 * bz[b] + (k >> 4)
    return corner + (np.stack([x, y, z], axis=1) + 0.5) * h, float(h)


def view(stage: str, png: str | None, *, frame: float | None = None, camera: str | None = None,
         show: tuple[str, ...] = ("geometry", "cameras", "lights"), window_size: tuple[int, int] = (1280, 720),
         interactive: bool = False, octree_resolution: int = 64, lgh_level: int = 1, settings=None) -> dict:
    """Draw ``show`` (:data:`LAYERS`) of ``stage`` at ``frame`` (default: its start) to ``png``, or in a
    window; returns what was drawn (counts) and where.

    ``voxels``: the sparse voxel octree's occupied voxels at ``octree_resolution``³ (a power of two from 8
    up; not the voxel arrays' ``voxel_resolution`` of ``usdml render``); ``vpls``: the frame's VPLs
    (``settings``' VPL count, bounces and seed; the stage's when None) coloured by flux; ``lgh``: the grid
    lights of LGH level ``lgh_level`` (1 = S1) built over them."""
    unknown = [s for s in show if s not in LAYERS]
    if unknown:
        raise UsdmlError(f"--show {','.join(unknown)}: usdml view draws {', '.join(LAYERS)}")
    if octree_resolution < 8 or octree_resolution & (octree_resolution - 1):
        raise UsdmlError(f"--octree-resolution {octree_resolution}: give a power of two from 8 up, e.g. 64")
    if png is None and not interactive:
        raise UsdmlError("give --png OUT.png (or --interactive where a display exists)")
    if png is not None and not interactive:
        from usdml.outputs import IMAGE_EXTENSIONS, check_output

        check_output(png, "--png", [e for e in IMAGE_EXTENSIONS if e != ".exr"])
    if not interactive:
        why = probe()
        if why:
            raise UsdmlError(why)
        os.environ.update({k: v for k, v in _offscreen_env().items() if k == "VTK_DEFAULT_OPENGL_WINDOW"})
    import pyvista as pv
    from pxr import Usd

    from usdml.scene import LightType, world_geometry
    from usdml.stage import StageDelegate
    from usdml.stage.camera import find_cameras, read_camera

    delegate = StageDelegate(stage, camera=camera, say_framing=False)      # drawn with pyvista's own camera
    t = delegate.start_time if frame is None else float(frame)
    delegate.check_time(t)
    snap = delegate.snapshot(t)
    # framed on the scene's detail: a ground to the horizon does not shrink the rest to a speck
    from usdml.visibility.insm.backend import insm_box
    bounds = insm_box(snap)
    lo, hi = (np.zeros(3), np.ones(3)) if bounds is None else (np.asarray(bounds[0]), np.asarray(bounds[1]))
    if "cameras" in show and snap.camera is not None:       # and the render camera, to see where it looks from
        eye = np.asarray(snap.camera.xform, np.float64)[:3, 3]
        lo, hi = np.minimum(lo, eye), np.maximum(hi, eye)
    size = float(np.linalg.norm(hi - lo)) or 1.0
    plotter = pv.Plotter(off_screen=not interactive, window_size=list(window_size))
    plotter.set_background("#20242a")
    if "lights" in show and snap.domes:
        # a dome light as the sky: its mean colour over a dark ground colour (a texture's mean, else its own)
        dome = snap.domes[0]
        rgb = np.asarray(dome.texture, np.float64).reshape(-1, 3).mean(0) if dome.texture is not None \
            else np.asarray(dome.radiance, np.float64)
        sky = np.clip(0.15 + 0.6 * rgb / max(float(rgb.max()), 1e-12), 0, 1)
        plotter.set_background(tuple(sky), top=tuple(np.clip(sky * 1.2, 0, 1)))
    drawn = {"stage": delegate.path, "frame": t, "png": png}
    if "geometry" in show:
        for m in snap.meshes:
            if len(m.triangles):
                mesh = _mesh(m.points, m.triangles)
                mesh.cell_data["albedo"] = np.clip(np.asarray(m.albedo)[:, 0], 0, 1)
                plotter.add_mesh(mesh, scalars="albedo", rgb=True, smooth_shading=False)
        drawn["meshes"] = len(snap.meshes)
    if ("geometry" in show or "instances" in show) and snap.prototypes:
        n_inst = 0
        for k, proto in enumerate(snap.prototypes):
            pts, tris = world_geometry(snap, (("proto", proto.path),))
            if not len(tris):
                continue
            mesh = _mesh(np.asarray(pts).reshape(-1, 3), np.asarray(tris).reshape(-1, 3))
            n = len(proto.xforms)
            per_instance = len(tris) // max(n, 1)
            if "instances" in show and per_instance * n == len(tris):
                # world_geometry: mesh-major, every instance of a mesh in turn
                which = np.arange(len(tris))
                sizes = [len(pm.triangles) for pm in proto.meshes]
                inst = np.concatenate([np.repeat(np.arange(n), s) for s in sizes]) if sum(sizes) * n == len(tris) \
                    else which // max(per_instance, 1)
                shade = 0.55 + 0.45 * ((inst * 0.618034) % 1.0)
                mesh.cell_data["colour"] = np.clip(_hsv(k * _GOLDEN, 0.65, 1.0)[None, :] * shade[:, None], 0, 1)
            else:
                mesh.cell_data["colour"] = np.tile(np.clip(np.asarray(proto.meshes[0].albedo)[0, 0], 0, 1),
                                                   (len(tris), 1)) if proto.meshes else np.full((len(tris), 3), 0.7)
            plotter.add_mesh(mesh, scalars="colour", rgb=True)
            n_inst += n
        drawn["instances"] = n_inst
    if "cameras" in show:
        render_path = snap.camera.path if snap.camera is not None else ""
        cams = find_cameras(delegate.stage)
        for prim in cams:
            cam = read_camera(prim, Usd.TimeCode(t))
            main = prim.GetPath().pathString == render_path
            plotter.add_mesh(_frustum(cam, 0.08 * size), color="#ffd84a" if main else "#8fa3b8",
                             line_width=4 if main else 2)
        if snap.camera is not None and not snap.camera.path:      # a synthesized framing camera
            plotter.add_mesh(_frustum(snap.camera, 0.08 * size), color="#ffd84a", line_width=4)
        drawn["cameras"] = len(cams)
    if "lights" in show and len(snap.lights):
        L = snap.lights
        point = L.type != LightType.DISTANT
        rgb = np.abs(np.asarray(L.radiance, np.float64))     # a negative light (it takes light away) by its magnitude
        colour = np.clip(rgb / np.maximum(rgb.max(axis=1, keepdims=True), 1e-12), 0, 1)
        if point.any():
            power = np.abs(np.asarray(L.intensity, np.float64)[point]).mean(axis=1)
            scale = np.log1p(power / max(np.median(power), 1e-12))
            radius = 0.006 * size * (0.5 + scale / max(scale.max(), 1e-12))
            cloud = pv.PolyData(np.asarray(L.position, np.float64)[point])
            cloud["radius"] = radius
            cloud["colour"] = colour[point]
            glyphs = cloud.glyph(scale="radius", orient=False, geom=pv.Sphere(radius=1.0, theta_resolution=8,
                                                                              phi_resolution=8))
            plotter.add_mesh(glyphs, scalars="colour", rgb=True)
        centre = 0.5 * (lo + hi)
        for i in np.flatnonzero(~point):
            d = -np.asarray(L.axis[i], np.float64)
            start = centre + d / np.linalg.norm(d) * 0.6 * size
            # keywords: positional ones are deprecated in pyvista 0.49 and refused from 0.50
            arrow = pv.Arrow(start=start, direction=-d / np.linalg.norm(d), scale=0.25 * size)
            plotter.add_mesh(arrow, color=colour[i])
        drawn["lights"] = int(len(L))
    if "voxels" in show:
        centres, h = occupied_voxels(snap, octree_resolution, bounds)
        if len(centres):
            cubes = pv.PolyData(centres).glyph(geom=pv.Cube(x_length=h, y_length=h, z_length=h), scale=False,
                                               orient=False)
            plotter.add_mesh(cubes, color="#5ec8f2", opacity=0.55, show_edges=False)
        drawn["voxels"] = int(len(centres))
    if "vpls" in show or "lgh" in show:
        from usdml.lighting.gi import prepare_vpls
        from usdml.visibility import ExactBackend

        base = delegate.usdml_settings if settings is None else settings
        with ExactBackend() as exact:
            exact.update(snap)
            field = prepare_vpls(snap, exact, snap.lights, base.updated(gi="lgh"))
        vpls = field.vpls
        if "vpls" in show and len(vpls):
            flux = np.asarray(vpls.flux, np.float64).mean(axis=1)
            cloud = pv.PolyData(np.asarray(vpls.position, np.float64))
            cloud["log10 flux"] = np.log10(np.maximum(flux, 1e-12))
            plotter.add_mesh(cloud, scalars="log10 flux", cmap="inferno", point_size=5, render_points_as_spheres=True,
                             scalar_bar_args={"title": "VPL flux (log10)", "position_y": 0.04})
        drawn["vpls"] = int(len(vpls))
        if "lgh" in show and field.lgh is not None:
            depth = field.lgh.depth
            if not 1 <= lgh_level <= depth:
                raise UsdmlError(f"--lgh-level {lgh_level}: this frame's LGH has levels 1 to {depth}")
            position, intensity = field.lgh.level_lights(lgh_level)
            grid = pv.PolyData(np.asarray(position, np.float64))
            grid["log10 intensity"] = np.log10(np.maximum(np.asarray(intensity, np.float64).mean(axis=1), 1e-12))
            plotter.add_mesh(grid, scalars="log10 intensity", cmap="viridis", point_size=10,
                             render_points_as_spheres=True,
                             scalar_bar_args={"title": f"LGH level {lgh_level} intensity (log10)", "position_y": 0.86})
            drawn["lgh_level"], drawn["lgh_lights"] = lgh_level, int(len(position))
    plotter.add_axes()
    # a three-quarter view from above, the stage's up axis up (pyvista's own "iso" assumes Z up)
    up = np.array([0.0, 0.0, 1.0]) if str(snap.up_axis).upper() == "Z" else np.array([0.0, 1.0, 0.0])
    centre = 0.5 * (lo + hi)
    side = np.array([1.0, 0.0, 0.0]) + (np.array([0.0, 1.0, 0.0]) if up[2] else np.array([0.0, 0.0, 1.0]))
    eye = 0.55 * side + 0.45 * up
    plotter.camera_position = [tuple(centre + 1.3 * size * eye / np.linalg.norm(eye)), tuple(centre), tuple(up)]
    plotter.renderer.ResetCameraClippingRange()     # not reset_camera(): that frames the whole ground again
    if interactive:
        plotter.show()
    else:
        from usdml.outputs import write_image

        write_image(png, plotter.screenshot(None, return_img=True))    # in the format png's extension names
    plotter.close()
    return drawn
