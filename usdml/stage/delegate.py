"""The scene delegate: a USD stage in, a :class:`usdml.scene.Snapshot` per timecode out.

Instancing is kept, never flattened: every native prototype and every PointInstancer prototype
becomes one :class:`~usdml.scene.Prototype` in its own space with N instance transforms; nested
instancing (a PointInstancer inside a prototype, instances inside a PointInstancer prototype)
composes instance transforms, not geometry. Geometry that does not change over the shot is read
once and reused by later snapshots. A prototype with UsdSkel-skinned meshes is posed once per frame
in its own space and shared by its instances; instances whose bindings pose it differently (their
own ``skel:animationSource``) get one prototype per pose.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, UsdLux

from usdml.errors import UsdmlError, Warnings, tf_message
from usdml.params import MAX_IMPLICIT_DETAIL
from usdml.scene import Dome, Lights, Mesh, Prototype, RenderSettings, Snapshot
from usdml.scene.linking import group_of
from usdml.scene.mattes import MatteNames
from usdml.scene.mesh_light import triangle_lights
from usdml.stage.camera import find_cameras, framing_camera, read_camera, select_camera
from usdml.stage.diagnostics import composition_message, read_by_usdml, usd_diagnostics
from usdml.stage.dome import is_dome, read_dome
from usdml.stage.lights import LightParams, expand, read_light
from usdml.stage.linking import GROUP_ATTRIBUTE, LinkReader, group_name
from usdml.stage.materials import MaterialResolver
from usdml.stage.mattes import MatteReader
from usdml.stage.mesh import (DEFAULT_IMPLICIT_DETAIL, is_gprim, moves_by_velocity, points_vary, read_gprim,
                              read_mesh)
from usdml.stage.mesh_light import light_varies
from usdml.stage.render_settings import read_render_settings, read_usdml_settings, settings_prim
from usdml.stage.skel import SkelResolver

#: prims below a PointInstancer prototype root: active, loaded, not abstract (defined or not)
_PROTOTYPE_PREDICATE = Usd.PrimIsActive & Usd.PrimIsLoaded & ~Usd.PrimIsAbstract

#: imageable non-mesh geometry usdml does not draw (counted under "unsupported" by usdml info)
UNSUPPORTED = ("BasisCurves", "NurbsCurves", "HermiteCurves", "Points", "NurbsPatch", "TetMesh", "Volume")
_PI_ATTRS = ("positions", "orientations", "orientationsf", "scales", "velocities", "accelerations",
             "angularVelocities", "protoIndices", "invisibleIds", "inactiveIds", "ids")
_MESH_ATTRS = ("faceVertexCounts", "faceVertexIndices", "holeIndices", "normals",
               "primvars:normals", "primvars:normals:indices", "primvars:displayColor",
               "primvars:displayColor:indices", "orientation", "doubleSided")


def open_stage(path: str | os.PathLike) -> Usd.Stage:
    """Open a stage or raise a one-line :class:`UsdmlError` naming the file and what to do."""
    p = Path(path)
    if not p.exists():
        raise UsdmlError(f"{path}: no such file; check the stage path")
    if p.is_dir():
        raise UsdmlError(f"{path}: is a directory; give a .usd/.usda/.usdc/.usdz file")
    if not os.access(p, os.R_OK):
        raise UsdmlError(f"{path}: not readable (permission denied); fix its permissions")
    if not Sdf.FileFormat.FindByExtension(p.suffix.lstrip(".") or "_none_"):
        raise UsdmlError(f"{path}: {p.suffix or 'no extension'} is not a USD file format; use .usd/.usda/.usdc/.usdz")
    try:
        stage = Usd.Stage.Open(str(p), Usd.Stage.LoadAll)
    except Tf.ErrorException as e:
        raise UsdmlError(f"{path}: cannot open stage: {tf_message(e)}; fix the layer") from None
    if stage is None:
        raise UsdmlError(f"{path}: cannot open stage; is it a valid USD layer?")
    return stage


def stage_name(stage: Usd.Stage) -> str:
    """How messages and files name an open stage: its root layer's file, else its identifier (an
    in-memory stage's ``anon:...``)."""
    layer = stage.GetRootLayer()
    return layer.realPath or layer.identifier


def require_geometry(delegate: "StageDelegate", snap: Snapshot) -> None:
    """Raise the one-line error for a snapshot with nothing to render."""
    if not snap.meshes and not snap.prototypes:
        raise UsdmlError(f"{delegate.path}: no renderable geometry at time {snap.time:g} (no visible Mesh or "
                         "implicit gprim with purpose default/render); check visibility, purpose and "
                         "activation, or open the layer that holds the geometry")


def require_lights(delegate: "StageDelegate", snap: Snapshot, command: str) -> None:
    """Raise the one-line error for measuring shadow rays (``usdml bench`` / ``compare``) without lights."""
    if len(snap.lights) == 0:
        domes = " (dome lights are not measured)" if snap.domes else ""
        raise UsdmlError(f"{delegate.path}: no lights at time {snap.time:g}{domes}, so no shadow rays to "
                         f"{command}; give a --frame or a stage with UsdLux lights")


def _proxy(prim: Usd.Prim, root: Usd.Prim, space: Usd.Prim) -> Usd.Prim:
    """``prim`` of prototype ``root`` as seen below ``space``: its instance proxy under the native
    instance ``space``, or ``prim`` itself when ``space`` is ``root`` (a PointInstancer prototype)."""
    if space == root:
        return prim
    return space.GetStage().GetPrimAtPath(space.GetPath().AppendPath(prim.GetPath().MakeRelativePath(root.GetPath())))


def _matrix(m) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> (4, 4) float64 column-convention array."""
    return np.array(m, np.float64).T


@dataclass
class _InstanceSet:
    """Instances of one prototype found while walking some root, transforms relative to that root."""

    xforms: list[np.ndarray] = field(default_factory=list)       # each (n, 4, 4)
    ids: list[np.ndarray] = field(default_factory=list)
    instancers: list[str] = field(default_factory=list)
    animated: bool = False

    def add(self, xforms: np.ndarray, ids: np.ndarray, instancer: str, animated: bool) -> None:
        self.xforms.append(xforms)
        self.ids.append(ids)
        self.instancers.extend([instancer] * len(xforms))
        self.animated |= animated

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.xforms), np.concatenate(self.ids).astype(np.int64)


@dataclass
class _Content:
    """What a walk below one root found, in that root's space."""

    meshes: list[tuple[Usd.Prim, np.ndarray, bool]] = field(default_factory=list)   # prim, rel xform, xform animated
    lights: list[tuple[LightParams, np.ndarray]] = field(default_factory=list)
    instances: dict[str, _InstanceSet] = field(default_factory=dict)
    domes: list[Dome] = field(default_factory=list)


class StageDelegate:
    """Reads one stage; :meth:`snapshot` gives the render index at any timecode.

    Parameters
    ----------
    path : the stage's root layer.
    camera : ``--camera`` (prim path or name), else the RenderSettings camera, ``main_cam``, the
        first camera, or a camera framing the scene.
    render_settings_path : ``--renderSettingsPrimPath``, else the stage's ``renderSettingsPrimPath``.
    """

    def __init__(self, path: "str | os.PathLike | Usd.Stage", camera: str | None = None,
                 render_settings_path: str | None = None, warn: Warnings | None = None,
                 purposes: list[str] | None = None, implicit_detail: int = DEFAULT_IMPLICIT_DETAIL,
                 say_framing: bool = True):
        # say_framing: warn when a stage without a camera is framed by usdml's own camera (``usdml view`` draws
        # with a camera of its own and passes False)
        self._say_framing = say_framing
        # an open stage (a pipeline script's, with its session layer or in memory) is read as it is
        opened = path if isinstance(path, Usd.Stage) else None
        self.path = stage_name(opened) if opened is not None else str(path)
        if not 3 <= implicit_detail <= MAX_IMPLICIT_DETAIL:
            raise UsdmlError(f"implicit detail {implicit_detail}: use 3 to {MAX_IMPLICIT_DETAIL} segments")
        self.warn = warn or Warnings()
        self._gprim = {"detail": int(implicit_detail), "materials": MaterialResolver(self.warn)}
        self._purposes = None if purposes is None else {str(p) for p in purposes} | {"default"}
        self._unsupported_seen: set[str] = set()
        self._told_outside = False        # check_times' warning, once
        self.unsupported: dict[str, int] = {}
        with self._diagnostics():     # USD's warnings while opening and composing
            self.stage = opened if opened is not None else open_stage(path)
            # an open stage's were said when it was opened; a stage opened here says them again (the same lines)
            for err in sorted(self.stage.GetCompositionErrors(), key=lambda e: e.rootSite.path):
                if not read_by_usdml(str(err)):
                    self.warn(composition_message(str(err.rootSite.path), str(err).strip().splitlines()[0],
                                                  self.path))
            self.settings_prim = settings_prim(self.stage, render_settings_path)
            self.usdml_settings = read_usdml_settings(self.settings_prim)
            self.has_time_range = self.stage.HasAuthoredTimeCodeRange()
            self.start_time = self.stage.GetStartTimeCode()
            self.end_time = self.stage.GetEndTimeCode()
            if not self.has_time_range:
                # a stage without startTimeCode/endTimeCode is a single frame: USD reports 0 for both,
                # and any --time is accepted (USD evaluates time samples at it as usual)
                authored = self.stage.HasAuthoredMetadata("startTimeCode")
                self.start_time = self.end_time = self.start_time if authored else 0.0
            if self.end_time < self.start_time:
                # authored the wrong way round (usd-wg's start_end_timeCodes_swapped.usda): the frames between them
                self.warn(f"{self.path}: startTimeCode {self.start_time:g} is after endTimeCode {self.end_time:g}; "
                          f"using the range [{self.end_time:g}, {self.start_time:g}]")
                self.start_time, self.end_time = self.end_time, self.start_time
            self.time_codes_per_second = self.stage.GetTimeCodesPerSecond()
            self.meters_per_unit = UsdGeom.GetStageMetersPerUnit(self.stage)
            if not (np.isfinite(self.meters_per_unit) and self.meters_per_unit > 0):
                raise UsdmlError(f"{self.path}: metersPerUnit {self.meters_per_unit:g} must be positive; fix the root "
                                 "layer's metersPerUnit metadata (0.01 for centimetres, 1 for metres)")
            self.up_axis = str(UsdGeom.GetStageUpAxis(self.stage))
            self.cameras = find_cameras(self.stage)
            self._camera_request = camera
            self.skel = SkelResolver(self.warn)
            self._links = LinkReader(self.stage, self.warn)
            self._mesh_cache: dict[tuple[str, str], tuple[Mesh | None, np.ndarray]] = {}
            self._mesh_ids: dict[str, int] = {}
            self._first_instance: dict[str, Usd.Prim] = {}     # native prototype -> its instance posing it
            self._mattes: MatteReader | None = None             # made when a frame asks for Cryptomatte
            self._assign_mesh_ids()

    @property
    def materials(self):
        """The stage's :class:`usdml.stage.materials.MaterialResolver` (what each material authors that usdml does
        not render: its ``unsupported``)."""
        return self._gprim.get("materials")

    def mattes(self, snap: Snapshot) -> MatteNames:
        """The names of ``snap``'s geometry for Cryptomatte (:mod:`usdml.stage.mattes`)."""
        if self._mattes is None:
            self._mattes = MatteReader(self.stage, self.materials, self.warn)
        with self._diagnostics():
            return self._mattes.names(snap)

    @contextlib.contextmanager
    def _diagnostics(self) -> Iterator[None]:
        """usdml's warnings and USD's (:func:`usd_diagnostics`) of the block, each cause once (``Warnings.grouped``)."""
        with self.warn.grouped(), usd_diagnostics(self.warn, self.path):
            yield

    # ----------------------------------------------------------------------------------------------
    def _assign_mesh_ids(self) -> None:
        """primIds from one pass over the stage and its prototypes, so they do not depend on frames.

        USD names native-instancing prototypes (``/__Prototype_N``) in an order that changes from one
        process to the next, so prototypes are visited in the order of their first instance's path:
        the same stage gives the same primIds in every process and on every farm worker."""
        def first_instance(proto) -> str:
            return min((str(i.GetPath()) for i in proto.GetInstances()), default=str(proto.GetPath()))

        roots = [self.stage.GetPseudoRoot()] + sorted(self.stage.GetPrototypes(), key=first_instance)
        for root in roots:
            for prim in Usd.PrimRange(root):
                if is_gprim(prim):
                    self._mesh_ids.setdefault(str(prim.GetPath()), len(self._mesh_ids))

    def _mesh_id(self, path: str) -> int:
        return self._mesh_ids.setdefault(path, len(self._mesh_ids))

    def check_time(self, time: float) -> None:
        """:meth:`check_times` of one timecode."""
        self.check_times([time])

    def check_times(self, times: list[float]) -> None:
        """Raise for a timecode that is not finite. Any other renders, as usdrecord renders it: USD holds each
        attribute's first and last sample outside them, so a static stage (startTimeCode = endTimeCode) is the
        same picture at every frame. Frames outside an animated stage's range are one warning per stage."""
        for time in times:
            if not np.isfinite(time):
                raise UsdmlError(f"time {time} is not a finite timecode")
        lo, hi = self.start_time, self.end_time
        outside = [t for t in times if not lo - 1e-9 <= t <= hi + 1e-9]
        if outside and self.has_time_range and hi > lo and not self._told_outside:
            self._told_outside = True
            which = (f"time {outside[0]:g} is" if len(outside) == 1 else
                     f"{len(outside)} frames ({outside[0]:g} ... {outside[-1]:g}) are")
            self.warn(f"{self.path}: {which} outside the stage's range [{lo:g}, {hi:g}] (startTimeCode/endTimeCode); "
                      "rendered with the values USD holds there (each attribute's first or last time sample)")

    @property
    def camera_prim(self) -> Usd.Prim | None:
        request = self._camera_request
        if request is None and self.settings_prim is not None:
            rel = self.settings_prim.GetRelationship("camera")
            targets = rel.GetForwardedTargets() if rel else []
            if targets:
                prim = self.stage.GetPrimAtPath(targets[0])
                if not prim or not prim.IsA(UsdGeom.Camera):
                    raise UsdmlError(f"{self.settings_prim.GetPath()}.camera: target {targets[0]} is not a Camera")
                return prim
        return select_camera(self.stage, request, self.cameras)

    def light_groups(self) -> list[str]:
        """The light groups the stage's lights name (``usdml:lightGroup``, any time), sorted, with
        :data:`usdml.scene.linking.DEFAULT_GROUP` when some light names none: what ``--aovs 'lightgroup:*'`` writes."""
        groups = set()
        for prim in Usd.PrimRange.Stage(self.stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
            if prim.HasAPI(UsdLux.LightAPI):
                value = prim.GetAttribute(GROUP_ATTRIBUTE).Get() if prim.HasAttribute(GROUP_ATTRIBUTE) else None
                groups.add(group_of(group_name(value, str(prim.GetPath()), lambda _: None)))
        return sorted(groups)

    def render_settings(self, time: float) -> RenderSettings | None:
        """The stage's RenderSettings at ``time`` as plain data (each product's ``productName`` resolved
        there), None when the stage has none; :meth:`snapshot` carries the same."""
        if self.settings_prim is None:
            return None
        return read_render_settings(self.settings_prim, Usd.TimeCode(time))

    # ----------------------------------------------------------------------------------------------
    def snapshot(self, time: float) -> Snapshot:
        """The render index at ``time`` (a timecode of the stage)."""
        with self._diagnostics():
            return self._snapshot(time)

    def _snapshot(self, time: float) -> Snapshot:
        self.check_time(time)
        t = Usd.TimeCode(time)
        xf = UsdGeom.XformCache(t)
        rs = self.render_settings(time)
        purposes = self._purposes or set(rs.included_purposes if rs else ("default", "render")) | {"default"}
        self.unsupported = {}

        top = self._walk(self.stage.GetPseudoRoot(), t, xf, purposes)
        meshes: list[Mesh] = []
        prototypes: list[Prototype] = []
        light_parts: list[Lights] = []
        for prim, rel, animated in top.meshes:
            path = str(prim.GetPath())
            skinned = self.skel.query(prim) is not None
            deforming = skinned and self.skel.is_animated(prim) or points_vary(prim)
            if skinned:
                posed = self.skel.posed_points(prim, t, xf)
                mesh = read_mesh(prim, t, None, self._mesh_id(path), self.warn, points=posed,
                                 deforming=deforming, authored_normals=False,
                                 materials=self._gprim.get("materials"))
            elif animated and not deforming:
                mesh = self._cached_mesh(prim, t, None, "")
                if mesh is not None:
                    prototypes.append(Prototype(
                        path=path, name=path, kind="rigid", meshes=[mesh], xforms=rel[None],
                        instance_ids=np.zeros(1, np.int64), instancers=[path], animated=True))
                continue
            else:
                mesh = (read_gprim(prim, t, rel, self._mesh_id(path), self.warn, deforming=True, **self._gprim) if deforming
                        else self._cached_mesh(prim, t, rel, "/"))
            if mesh is not None:
                meshes.append(mesh)
        for params, rel in top.lights:
            light_parts.append(expand(params, rel[None], meters_per_unit=self.meters_per_unit))

        # Prototypes, breadth first: nested instance sets are composed with their outer instances.
        pending = dict(top.instances)
        contents: dict[str, _Content] = {}
        while pending:
            proto_path, inst = next(iter(pending.items()))
            del pending[proto_path]
            xforms, ids = inst.arrays()
            root = self.stage.GetPrimAtPath(proto_path)
            if proto_path not in contents:
                contents[proto_path] = self._walk(root, t, xf, purposes)
            content = contents[proto_path]
            deforming = False
            for k, (sel, space) in enumerate(self._pose_groups(root, inst, content, xf)):
                proto_meshes, varying = self._prototype_meshes(root, content, space, t, xf)
                deforming |= varying
                if not proto_meshes:
                    continue
                path = proto_path if k == 0 else f"{proto_path}[{space.GetPath()}]"
                instancers = [inst.instancers[i] for i in sel]
                existing = next((p for p in prototypes if p.path == path), None)
                if existing is not None:     # reached again through another nesting path
                    existing.xforms = np.concatenate([existing.xforms, xforms[sel]])
                    existing.instance_ids = np.concatenate([existing.instance_ids, ids[sel]])
                    existing.instancers += instancers
                    existing.animated |= inst.animated
                else:
                    name = instancers[0] if root.IsPrototype() else proto_path
                    prototypes.append(Prototype(
                        path=path, name=name, kind=self._kind(root), meshes=proto_meshes, xforms=xforms[sel],
                        instance_ids=ids[sel], instancers=instancers, animated=inst.animated,
                        deforming=varying))
            for params, rel in content.lights:
                light_parts.append(expand(params, xforms @ rel, ids, self.meters_per_unit))
            for nested_path, nested in content.instances.items():
                nx, nids = nested.arrays()
                composed = (xforms[:, None] @ nx[None]).reshape(-1, 4, 4)
                target = pending.setdefault(nested_path, _InstanceSet())
                target.add(composed, np.arange(len(composed)), proto_path,
                           inst.animated or nested.animated or deforming)

        light_parts += self._mesh_lights(meshes, prototypes)
        for p in prototypes:
            if not np.isfinite(p.xforms).all():
                raise UsdmlError(f"{p.instancers[0]}: non-finite (NaN/inf) instance transform; fix its "
                                 "xformOps or PointInstancer positions/orientations/scales")
        snap = Snapshot(
            time=float(time), stage_path=self.path, meshes=meshes, prototypes=prototypes,
            lights=Lights.concat(light_parts), camera=None, render_settings=rs, domes=top.domes,
            mesh_paths=sorted(self._mesh_ids, key=self._mesh_ids.get), start_time=self.start_time,
            end_time=self.end_time, time_codes_per_second=self.time_codes_per_second,
            meters_per_unit=self.meters_per_unit, up_axis=self.up_axis)
        snap.links = self._links.links(snap, snap.lights.paths + [d.path for d in snap.domes], t)
        snap.lights = snap.links.label(snap.lights)
        cam_prim = self.camera_prim
        if cam_prim is not None:
            snap.camera = read_camera(cam_prim, t)
            lens = snap.camera.f_stop > 0 and snap.camera.lens_radius == 0
            if lens and snap.camera.projection != "perspective":
                self.warn(f"{snap.camera.path}.fStop: depth of field is not rendered for an orthographic camera; "
                          "rendered sharp")
            elif lens:
                self.warn(f"{snap.camera.path}.focusDistance: 0 with fStop {snap.camera.f_stop:g} focuses nowhere; "
                          "rendered sharp (author focusDistance, in scene units, for depth of field)")
        else:
            bounds = snap.world_bounds()
            if bounds is not None:
                snap.camera = framing_camera(bounds, self.up_axis)
                if self._say_framing:
                    forward = "+Y" if self.up_axis == "Z" else "-Z"
                    self.warn(f"{self.path}: no camera; framing the scene with usdml's own camera (usdrecord's: a "
                              f"50 mm lens looking {forward} at the centre of its bounds); add a UsdGeom.Camera "
                              "(named main_cam, or chosen with --camera)")
        return snap

    # ----------------------------------------------------------------------------------------------
    def _pose_groups(self, root: Usd.Prim, inst: _InstanceSet, content: _Content,
                     xf: UsdGeom.XformCache) -> list[tuple[np.ndarray, Usd.Prim | None]]:
        """The instances of prototype ``root`` that pose its skinned meshes alike, as ``(instance
        indices, space)``: ``space`` is the prim whose frame posed points are given in and through
        which skel bindings are read (a native instance, the PointInstancer prototype root itself),
        None when nothing in the prototype is skinned.

        A native prototype's meshes are skinned through an instance's proxies, as UsdSkel binds them
        there; instances with equal :meth:`SkelResolver.binding_key` share one pose. Which meshes are
        skinned is read through the prototype's first instance (by path), and so is the pose of
        instances reached only through an outer prototype (nested instancing)."""
        everyone = [(np.arange(len(inst.instancers)), None)]
        if not root.IsPrototype():
            skinned = any(self.skel.query(prim) is not None for prim, _, _ in content.meshes)
            return [(everyone[0][0], root)] if skinned else everyone
        first = self._first_instance.get(str(root.GetPath()))
        if first is None:
            first = self._first_instance[str(root.GetPath())] = min(root.GetInstances(), key=lambda p: str(p.GetPath()))
        skinnable = [prim for prim, _, _ in content.meshes if self.skel.query(_proxy(prim, root, first)) is not None]
        if not skinnable:
            return everyone
        groups: dict[tuple, tuple[Usd.Prim, list[int]]] = {}
        keys: dict[str, tuple] = {}
        for i, path in enumerate(inst.instancers):
            if path not in keys:
                space = self.stage.GetPrimAtPath(path)
                if not (space and space.IsInstance() and space.GetPrototype() == root):
                    space = first
                key = tuple(self.skel.binding_key(_proxy(p, root, space), space, xf) for p in skinnable)
                keys[path] = (key, space)
            key, space = keys[path]
            groups.setdefault(key, (space, []))[1].append(i)
        if all(k is None for key in groups for k in key):
            return everyone
        return [(np.asarray(members), space) for space, members in groups.values()]

    def _prototype_meshes(self, root: Usd.Prim, content: _Content, space: Usd.Prim | None, t: Usd.TimeCode,
                          xf: UsdGeom.XformCache) -> tuple[list[Mesh], bool]:
        """The meshes of prototype ``root`` in its space, skinned ones posed through ``space`` (see
        :meth:`_pose_groups`), and whether any of them deforms over the shot."""
        meshes, deforming = [], False
        proto_path = str(root.GetPath())
        for prim, rel, animated in content.meshes:
            path = str(prim.GetPath())
            source = None if space is None else _proxy(prim, root, space)
            if source is not None and self.skel.query(source) is not None:
                varying = self.skel.is_animated(source, space) or points_vary(prim)
                mesh = read_mesh(prim, t, None, self._mesh_id(path), self.warn,
                                 points=self.skel.posed_points(source, t, xf, space), deforming=varying,
                                 authored_normals=False, materials=self._gprim.get("materials"))
            else:
                varying = animated or points_vary(prim)
                mesh = (read_gprim(prim, t, rel, self._mesh_id(path), self.warn, deforming=True, **self._gprim)
                        if varying else self._cached_mesh(prim, t, rel, proto_path))
            deforming |= varying
            if mesh is not None:
                meshes.append(mesh)
        return meshes, deforming

    def _mesh_lights(self, meshes: list[Mesh], prototypes: list[Prototype]) -> list[Lights]:
        """The TRIANGLE lights of every emitting mesh (``MeshLightAPI``), those of a prototype once per instance;
        a mesh light with no area is one warning (it emits nothing, the frame renders)."""
        placed = [(m, None, None) for m in meshes] + [
            (m, p.xforms, None if p.kind == "rigid" else p.instance_ids) for p in prototypes for m in p.meshes]
        parts = []
        for mesh, xforms, ids in placed:
            if mesh.light is None:
                continue
            lights = triangle_lights(mesh, xforms, ids, self.meters_per_unit)
            if not len(lights) and (xforms is None or len(xforms)):
                self.warn(f"{mesh.path}: mesh light with no area (every face is degenerate) emits nothing; "
                          "fix its points or remove its MeshLightAPI")
            parts.append(lights)
        return parts

    def _count_unsupported(self, kind: str, message: str) -> None:
        """One more ``kind`` usdml does not render (``usdml info``'s ``unsupported``), said in ``message``."""
        self.unsupported[kind] = self.unsupported.get(kind, 0) + 1
        self.warn(message)

    def _unsupported_lux(self, prim: Usd.Prim) -> None:
        """UsdLux inputs usdml does not render on ``prim``, each counted and said naming the prim: VolumeLightAPI,
        a LightFilter, a light's ``light:filters``."""
        path = prim.GetPath()
        if prim.HasAPI(UsdLux.VolumeLightAPI):
            self._count_unsupported("VolumeLightAPI", f"{path}: VolumeLightAPI is not supported; the volume "
                                    "emits no light")
        if prim.IsA(UsdLux.LightFilter):
            self._count_unsupported("LightFilter", f"{path}: LightFilter prims are not applied; this filter is "
                                    "ignored")
        if prim.HasAPI(UsdLux.LightAPI):
            targets = UsdLux.LightAPI(prim).GetFiltersRel().GetForwardedTargets()
            if targets:
                self._count_unsupported("light:filters", f"{path}.light:filters: light filters are not applied "
                                        f"({len(targets)} target(s)); the light renders unfiltered")

    @staticmethod
    def _kind(root: Usd.Prim) -> str:
        return "native" if root.IsPrototype() else "pointInstancer"

    def _cached_mesh(self, prim: Usd.Prim, t: Usd.TimeCode, rel: np.ndarray | None, space: str) -> Mesh | None:
        """Read a mesh whose topology and points do not vary; reuse it when its placement is unchanged."""
        mesh_attrs_vary = any(prim.GetAttribute(a).ValueMightBeTimeVarying()
                              for a in _MESH_ATTRS if prim.HasAttribute(a)) or light_varies(prim)
        key = (str(prim.GetPath()), space)
        cached = self._mesh_cache.get(key)
        if cached is not None and not mesh_attrs_vary and np.array_equal(cached[1], np.eye(4) if rel is None else rel):
            return cached[0]
        mesh = read_gprim(prim, t, rel, self._mesh_id(key[0]), self.warn, **self._gprim)
        if not mesh_attrs_vary:
            self._mesh_cache[key] = (mesh, np.eye(4) if rel is None else rel.copy())
        return mesh

    def _relative(self, prim: Usd.Prim, root: Usd.Prim, xf: UsdGeom.XformCache) -> np.ndarray:
        """``prim``'s local-to-``root`` transform (local-to-world below the pseudo-root)."""
        if root.IsPseudoRoot():
            m = _matrix(xf.GetLocalToWorldTransform(prim))
        else:
            m = _matrix(xf.ComputeRelativeTransform(prim, root)[0])
        if not np.isfinite(m).all():
            raise UsdmlError(f"{prim.GetPath()}: non-finite (NaN/inf) transform at time {xf.GetTime().GetValue()}; "
                             "fix its xformOps or those of its ancestors")
        return m

    def _walk(self, root: Usd.Prim, t: Usd.TimeCode, xf: UsdGeom.XformCache, purposes: set[str]) -> _Content:
        """Meshes, lights and instance sets below ``root`` (itself included), relative to ``root``."""
        content = _Content()
        animated: dict[Sdf.Path, bool] = {}
        purpose_of: dict[Sdf.Path, str] = {}
        # PointInstancer prototypes are often `def`s under an `over` (hidden from the plain traversal):
        # below a prototype root, walk prims that are not *defined* because of an ancestor over, but
        # skip pure overrides themselves, as usdImaging does
        inside_prototype = not root.IsPseudoRoot() and not root.IsPrototype()
        predicate = _PROTOTYPE_PREDICATE if inside_prototype else Usd.PrimDefaultPredicate
        it = iter(Usd.PrimRange(root, predicate))
        for prim in it:
            ppath = prim.GetPath()
            parent = ppath.GetParentPath()
            if prim.IsPseudoRoot():
                animated[ppath], purpose_of[ppath] = False, "default"
                continue
            if inside_prototype and prim.GetSpecifier() == Sdf.SpecifierOver:
                it.PruneChildren()
                continue
            inherited_anim = animated.get(parent, False) if prim != root else False
            xformable = UsdGeom.Xformable(prim)
            if xformable and prim != root:
                anim = inherited_anim or xformable.TransformMightBeTimeVarying()
            else:
                anim = inherited_anim
            animated[ppath] = anim
            imageable = UsdGeom.Imageable(prim)
            if imageable:
                if imageable.GetVisibilityAttr().Get(t) == UsdGeom.Tokens.invisible:
                    it.PruneChildren()
                    continue
                parent_purpose = purpose_of.get(parent, "default") if prim != root else "default"
                own = imageable.GetPurposeAttr().Get()
                purpose = parent_purpose if parent_purpose != "default" else str(own or "default")
                purpose_of[ppath] = purpose
                if purpose not in purposes:
                    it.PruneChildren()
                    continue
            else:
                purpose_of[ppath] = purpose_of.get(parent, "default")

            if prim.IsInstance():
                # a prototype root that is itself an instance (a PointInstancer prototype pointing at an
                # instanceable prim) sits at identity: the PointInstancer already applied its transform
                rel = np.eye(4) if prim == root else self._relative(prim, root, xf)
                iset = content.instances.setdefault(str(prim.GetPrototype().GetPath()), _InstanceSet())
                iset.add(rel[None], np.array([len(iset.instancers)]), str(ppath), anim)
                it.PruneChildren()
                continue
            if prim.IsA(UsdGeom.PointInstancer):
                self._point_instancer(prim, root, t, xf, anim, content)
                it.PruneChildren()
                continue
            self._unsupported_lux(prim)
            if is_gprim(prim):
                content.meshes.append((prim, self._relative(prim, root, xf), anim))
            elif prim.IsA(UsdGeom.Gprim) or prim.GetTypeName() in UNSUPPORTED:
                kind = prim.GetTypeName()
                self.unsupported[kind] = self.unsupported.get(kind, 0) + 1
                if kind not in self._unsupported_seen:
                    self._unsupported_seen.add(kind)
                    self.warn(f"{ppath}: {kind} prims are not rendered (this and every other {kind}); "
                              "convert them to meshes to see them")
            elif is_dome(prim):
                if root.IsPseudoRoot():
                    dome = read_dome(prim, t, self._relative(prim, root, xf), self.warn)
                    if dome is not None:
                        content.domes.append(dome)
                else:
                    self.warn(f"{ppath}: dome lights inside instance prototypes are ignored")
            elif prim.HasAPI(UsdLux.LightAPI):
                params = read_light(prim, t, self.warn)
                if params is None:      # said by read_light
                    kind = prim.GetTypeName() or "LightAPI"
                    self.unsupported[kind] = self.unsupported.get(kind, 0) + 1
                else:
                    content.lights.append((params, self._relative(prim, root, xf)))
        return content

    def _point_instancer(self, prim: Usd.Prim, root: Usd.Prim, t: Usd.TimeCode, xf: UsdGeom.XformCache,
                         anim: bool, content: _Content) -> None:
        pi = UsdGeom.PointInstancer(prim)
        path = str(prim.GetPath())
        targets = pi.GetPrototypesRel().GetForwardedTargets()
        indices = np.asarray(pi.GetProtoIndicesAttr().Get(t) or [], np.int64)
        if not len(indices):
            return
        xforms = pi.ComputeInstanceTransformsAtTime(t, t, UsdGeom.PointInstancer.IncludeProtoXform,
                                                    UsdGeom.PointInstancer.IgnoreMask)
        if xforms is None or len(xforms) != len(indices):
            self.warn(f"{path}: PointInstancer attributes are inconsistent (positions vs protoIndices) "
                      f"at time {t.GetValue()}; skipped")
            return
        m = np.transpose(np.asarray(xforms, np.float64), (0, 2, 1))
        if not np.isfinite(m).all():
            raise UsdmlError(f"{path}: non-finite (NaN/inf) positions/orientations/scales at time "
                             f"{t.GetValue()}; fix the PointInstancer")
        m = self._relative(prim, root, xf) @ m
        mask = np.asarray(pi.ComputeMaskAtTime(t) or [True] * len(indices), bool)
        ids_attr = pi.GetIdsAttr().Get(t)
        ids = np.asarray(ids_attr, np.int64) if ids_attr is not None and len(ids_attr) == len(indices) \
            else np.arange(len(indices), dtype=np.int64)
        bad = (indices < 0) | (indices >= len(targets))
        if bad.any():
            self.warn(f"{path}.protoIndices: {int(bad.sum())} index(es) outside the {len(targets)} "
                      "prototypes; those instances skipped")
        varying = anim or any(prim.GetAttribute(a).ValueMightBeTimeVarying()
                              for a in _PI_ATTRS if prim.HasAttribute(a))
        # one positions sample plus velocities still moves: USD extrapolates from the sample
        varying |= moves_by_velocity(prim, t, ("velocities", "accelerations", "angularVelocities"))
        for j, target in enumerate(targets):
            sel = (indices == j) & mask
            if not sel.any():
                continue
            proto = self.stage.GetPrimAtPath(target)
            if not proto:
                self.warn(f"{path}.prototypes: target {target} does not exist; its instances skipped")
                continue
            content.instances.setdefault(str(target), _InstanceSet()).add(m[sel], ids[sel], path, varying)
