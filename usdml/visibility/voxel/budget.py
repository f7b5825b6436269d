"""What paper 000's per-direction voxel arrays cost, said before anything is built: the voxel
backend's ``MEMORY_ESTIMATE`` capability (``usdml info``, and the arrays a snapshot needs,
:func:`array_roles`, which :meth:`usdml.visibility.voxel.backend.VoxelBackend.update` builds).

An array holds one bit-packed voxelization per direction bin. The paper's (theta, phi) grid over
[0, 180) x [0, 180) has 90 x 90 bins at 2 deg and a voxelization at 128^3 takes 256 KiB: about 2 GB
per array. usdml bins one hemisphere in rings at the same step (5,357 bins at 2 deg) and stores
only the row words inside the array's bounding sphere (70 % at 128^3): 0.98 GB per array
(:mod:`usdml.visibility.voxel.grid`).
"""

from __future__ import annotations

from usdml.scene import Snapshot
from usdml.settings import UsdmlSettings
from usdml.visibility.base import static_members
from usdml.visibility.voxel.grid import DirectionBins, array_bytes


def direction_count(step_deg: float) -> int:
    return DirectionBins.make(step_deg).count


def array_roles(snap: Snapshot, fully_dynamic: bool) -> list[tuple[str, tuple]]:
    """The arrays the voxel backend holds for ``snap``: ``(role, members)``, members ``("mesh" |
    "proto", path)``; role ``static`` (static meshes and instances that never move, baked in world
    space), ``prototype <path>`` (one per prototype whose instances move, shared by all of them,
    paper 000 Alg. 4), ``deforming`` (rebuilt per frame, Alg. 5) -- or, ``fully_dynamic``, just
    ``dynamic`` (every mesh and prototype, rebuilt per frame)."""
    if fully_dynamic:
        everything = tuple([("mesh", m.path) for m in snap.meshes]
                           + [("proto", p.path) for p in snap.prototypes if p.triangle_count])
        return [("dynamic", everything)] if everything else []
    static = static_members(snap)
    deforming = tuple([("mesh", m.path) for m in snap.meshes if m.deforming]
                      + [("proto", p.path) for p in snap.prototypes if p.deforming])
    out = [("static", static)] if static else []
    out += [(f"prototype {p.path}", (("proto", p.path),)) for p in snap.prototypes
            if p.animated and not p.deforming and p.triangle_count]
    if deforming:
        out.append(("deforming", deforming))
    return out


_SOURCES = {"static": "static meshes and unmoving instances", "deforming": "deforming meshes, rebuilt per frame",
            "dynamic": "whole scene, rebuilt per frame"}


def plan_arrays(snap: Snapshot, settings: UsdmlSettings) -> list[tuple[str, str]]:
    """:func:`array_roles` at ``settings``, as ``(role, what it holds)`` pairs for ``usdml info``."""
    names = {p.path: p.name for p in snap.prototypes}
    out = []
    for role, _ in array_roles(snap, settings.fully_dynamic):
        kind, _, path = role.partition(" ")
        out.append((kind, names[path] if path else _SOURCES[kind]))
    return out


def memory_estimate(snap: Snapshot, settings: UsdmlSettings) -> dict:
    """The arrays :func:`plan_arrays` lists and their bytes at ``settings`` (``usdml info``'s ``voxelMemory``)."""
    plan = plan_arrays(snap, settings)
    per_array = array_bytes(settings.voxel_resolution, settings.direction_step)
    return {
        "resolution": settings.voxel_resolution, "directionStep": settings.direction_step,
        "directions": direction_count(settings.direction_step), "bytesPerArray": per_array,
        "arrays": len(plan), "totalBytes": per_array * len(plan),
        "plan": [{"role": r, "source": s} for r, s in plan],
    }


def memory_line(vm: dict) -> str:
    """:func:`memory_estimate`'s result as one line."""
    return (f"{vm['arrays']} array(s) x {human_bytes(vm['bytesPerArray'])} = {human_bytes(vm['totalBytes'])} "
            f"({vm['directions']:,} directions at {vm['resolution']}^3)")


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} TiB"
