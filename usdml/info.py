"""``usdml info``: what usdml sees on a stage at one timecode, as text or JSON."""

from __future__ import annotations

import time as _time
from collections import Counter

from usdml.scene import Snapshot
from usdml.stage import StageDelegate
from usdml.stage.delegate import require_geometry
from usdml.visibility import backend_class, backend_names
from usdml.visibility.base import MEMORY_ESTIMATE


def _render_settings(snap: Snapshot) -> dict | None:
    rs = snap.render_settings
    if rs is None:
        return None
    return {
        "path": rs.path, "camera": rs.camera, "resolution": list(rs.resolution),
        "pixelAspectRatio": rs.pixel_aspect_ratio, "includedPurposes": rs.included_purposes,
        "products": [{
            "path": p.path, "productName": p.product_name, "productNameTimeVarying": p.name_time_varying,
            "productType": p.product_type, "camera": p.camera,
            "resolution": list(p.resolution) if p.resolution else None,
            "vars": [{"path": v.path, "name": v.name, "sourceName": v.source_name,
                      "sourceType": v.source_type, "dataType": v.data_type} for v in p.vars],
        } for p in rs.products],
    }


def _brdf_cpu_path() -> str:
    """How the preview surface's two sums per point run (``usdml.lighting.brdf_sums``)."""
    from usdml.lighting import brdf_sums

    return brdf_sums.describe()


def _lgh_cpu_path() -> str:
    """The CPU path of the LGH's gather and shadow targets (``--gi lgh``, ``--direct lgh``)."""
    from usdml.lighting.lgh import native as lgh_native

    return lgh_native.describe()


def stage_info(delegate: StageDelegate, time: float | None = None, started: float | None = None) -> dict:
    """Summary of ``delegate``'s stage at ``time`` (default: its start timecode) as a JSON-able dict.

    ``started`` is the ``time.perf_counter()`` before the stage was opened, so ``loadSeconds``
    covers opening and reading; without it only the snapshot is timed.
    """
    t0 = _time.perf_counter() if started is None else started
    time = delegate.start_time if time is None else time
    snap = delegate.snapshot(time)
    seconds = _time.perf_counter() - t0
    require_geometry(delegate, snap)
    settings = delegate.usdml_settings
    # what each backend that can say so would take at these settings ("voxelMemory", ...)
    memory = {f"{name}Memory": cls.memory_estimate(snap, settings) for name, cls in
              ((name, backend_class(name)) for name in backend_names()) if cls.supports(MEMORY_ESTIMATE)}
    kinds = Counter(p.kind for p in snap.prototypes)
    return {
        "stage": delegate.path,
        "time": snap.time,
        "startTimeCode": delegate.start_time,
        "endTimeCode": delegate.end_time,
        "timeCodesPerSecond": delegate.time_codes_per_second,
        "metersPerUnit": snap.meters_per_unit,
        "upAxis": snap.up_axis,
        "meshes": len(snap.meshes) + sum(len(p.meshes) * p.instance_count for p in snap.prototypes),
        "uniqueMeshes": len(snap.meshes) + sum(len(p.meshes) for p in snap.prototypes),
        "triangles": snap.triangle_count(),
        "uniqueTriangles": snap.unique_triangle_count(),
        "prototypes": len(snap.prototypes),
        "prototypeKinds": dict(sorted(kinds.items())),
        "instances": sum(p.instance_count for p in snap.prototypes),
        "animatedPrototypes": sum(p.animated for p in snap.prototypes),
        "deforming": len(snap.deforming_meshes) + sum(p.deforming for p in snap.prototypes),
        "lights": len(snap.lights) + len(snap.domes),
        "lightTypes": {**snap.lights.type_counts(), **({"dome": len(snap.domes)} if snap.domes else {})},
        "linkSets": len(snap.links) if snap.links is not None else 0,
        "lightGroups": delegate.light_groups(),
        "cryptomatteNames": _matte_counts(delegate.mattes(snap)),
        "cameras": [str(c.GetPath()) for c in delegate.cameras],
        "camera": snap.camera.path if snap.camera and snap.camera.path else ("(framing)" if snap.camera else None),
        "shutter": list(snap.camera.shutter) if snap.camera else None,
        "lens": {"fStop": snap.camera.f_stop, "focusDistance": snap.camera.focus_distance,
                 "radius": snap.camera.lens_radius} if snap.camera and snap.camera.lens_radius else None,
        "renderSettings": _render_settings(snap),
        "usdmlSettings": settings.as_dict(),
        "backends": {name: backend_class(name).summary for name in backend_names()},
        "backendCpuPaths": {name: backend_class(name).cpu_path() for name in backend_names()
                            if backend_class(name).cpu_path()},
        "lghCpuPath": _lgh_cpu_path(),
        "brdfCpuPath": _brdf_cpu_path(),
        **memory,
        "unsupported": dict(sorted({**delegate.unsupported, **_material_counts(delegate)}.items())),
        "unsupportedMaterials": dict(sorted(_materials(delegate).items())),
        "warnings": list(delegate.warn.messages),
        "loadSeconds": round(seconds, 3),
    }


def _lens_and_shutter(info: dict) -> str:
    """``; shutter -0.25..0.25; f/2.8 focused at 500`` where the camera blurs (motion blur, depth of field), else ""."""
    out = ""
    if info["shutter"] and info["shutter"][1] > info["shutter"][0]:
        out += f"; shutter {info['shutter'][0]:g}..{info['shutter'][1]:g}"
    if info["lens"]:
        out += f"; f/{info['lens']['fStop']:g} focused at {info['lens']['focusDistance']:g}"
    return out


def _matte_counts(names) -> dict[str, int]:
    """How many names each Cryptomatte AOV can write (:class:`usdml.scene.mattes.MatteNames`)."""
    return {"CryptoObject": len(names.objects), "CryptoMaterial": len(names.materials),
            "CryptoAsset": len(names.assets)}


def format_info(info: dict) -> str:
    """The human-readable summary printed by ``usdml info``."""
    n = "{:,}".format
    rs = info["renderSettings"]
    kinds = ", ".join(f"{k} {v}" for k, v in info["prototypeKinds"].items()) or "none"
    lines = [
        f"stage       {info['stage']}  ({info['upAxis']}-up, {info['metersPerUnit']:g} m/unit, timecodes "
        f"{info['startTimeCode']:g}-{info['endTimeCode']:g} @ {info['timeCodesPerSecond']:g}/s)",
        f"time        {info['time']:g}",
        f"geometry    {n(info['meshes'])} meshes, {n(info['triangles'])} triangles rendered "
        f"({n(info['uniqueMeshes'])} meshes, {n(info['uniqueTriangles'])} triangles unique)",
        f"instancing  {n(info['prototypes'])} prototypes ({kinds}), {n(info['instances'])} instances, "
        f"{info['animatedPrototypes']} with moving instances",
        f"deforming   {info['deforming']}",
        f"lights      {n(info['lights'])}" + (" (" + ", ".join(f"{k} {n(v)}" for k, v in info["lightTypes"].items()) + ")"
                                               if info["lightTypes"] else ""),
        f"camera      {info['camera']}  (cameras on stage: {len(info['cameras'])})" + _lens_and_shutter(info),
    ]
    if info["linkSets"] or info["lightGroups"] not in ([], ["default"]):
        lines.insert(-1, f"linking     {info['linkSets']} light/shadow link set(s); light groups "
                         + ", ".join(info["lightGroups"]))
    lines.insert(-1, "mattes      " + ", ".join(f"{n(v)} {k}" for k, v in info["cryptomatteNames"].items())
                 + " (Cryptomatte names, at most a frame's manifest)")
    if info["unsupported"]:
        lines.append("unsupported " + ", ".join(f"{k} {n(v)}" for k, v in info["unsupported"].items())
                     + " (not rendered)")
    if rs:
        res = "x".join(map(str, rs["resolution"]))
        lines.append(f"render      {rs['path']}: {res}, camera {rs['camera']}")
        for p in rs["products"]:
            names = ", ".join(v["name"] for v in p["vars"]) or "no vars"
            lines.append(f"  product   {p['productName']}{' (time-varying)' if p['productNameTimeVarying'] else ''}: {names}")
    else:
        lines.append("render      no RenderSettings")
    s = info["usdmlSettings"]
    alpha = format(s["lgh_alpha"], "g") if s["lgh_alpha"] > 0 else "auto"        # 0: chosen per frame
    samples = s["shadow_samples"] or "auto"
    lines.append(f"usdml       visibility {s['visibility']}, voxels {s['voxel_resolution']}^3 @ {s['direction_step']:g} deg, "
                 f"{n(s['vpl_count'])} VPLs, LGH alpha {alpha}, split {s['lgh_split']}, {samples} shadow samples, "
                 f"{s['pixel_samples']} pixel samples, seed {s['seed']}")
    lines.append("backends    " + "; ".join(f"{name}: {summary}" if summary else name
                                             for name, summary in info["backends"].items()))
    for name, line in info["backendCpuPaths"].items():
        lines.append(f"{name + ' cpu':<11} {line}")
    if info.get("lghCpuPath"):
        lines.append(f"{'lgh cpu':<11} {info['lghCpuPath']}")
    if info.get("brdfCpuPath"):
        lines.append(f"{'brdf cpu':<11} {info['brdfCpuPath']}")
    for name in backend_names():
        if info.get(f"{name}Memory"):
            lines.append(f"{name + ' mem':<11} {backend_class(name).memory_line(info[f'{name}Memory'])}")
    lines.append(f"loaded in   {info['loadSeconds']:.2f} s" + (f", {len(info['warnings'])} warning(s)" if info["warnings"] else ""))
    return "\n".join(lines)


def _materials(delegate) -> dict[str, list[str]]:
    """Material path -> what it authors that usdml does not render (usdml.stage.materials.MaterialResolver)."""
    resolver = getattr(delegate, "materials", None)
    return {k: list(v) for k, v in resolver.unsupported.items()} if resolver is not None else {}


def _material_counts(delegate) -> dict[str, int]:
    """``unsupported``'s count of materials with something usdml does not render."""
    n = len(_materials(delegate))
    return {"material inputs": n} if n else {}
