"""What paper 000's per-direction voxel arrays cost, said before anything is built.

An array holds one bit-packed voxelization per direction bin. The paper's (theta, phi) grid over
[0, 180) x [0, 180) has 90 x 90 bins at 2 deg and a voxelization at 128^3 takes 256 KiB: about 2 GB
per array. usdml bins one hemisphere in rings at the same step (5,357 bins at 2 deg) and stores
only the row words inside the array's bounding sphere (70 % at 128^3): 0.98 GB per array
(:mod:`usdml.visibility.voxel_grid`).
"""

from __future__ import annotations

from usdml.scene import Snapshot
from usdml.settings import UsdmlSettings
from usdml.visibility.voxel_grid import DirectionBins, array_bytes  # noqa: F401  (re-exported)


def direction_count(step_deg: float) -> int:
    return DirectionBins.make(step_deg).count


def plan_arrays(snap: Snapshot, settings: UsdmlSettings) -> list[tuple[str, str]]:
    """The arrays the voxel backend would hold for ``snap``: ``(role, source)`` pairs.

    One for the static part (static meshes and instances that never move, baked in world space),
    one per prototype whose instances move (shared by all its instances, paper 000 Alg. 4), and one
    rebuilt per frame for deforming geometry (Alg. 5) -- or a single per-frame array when the
    scene is marked fully dynamic.
    """
    if settings.fully_dynamic:
        return [("dynamic", "whole scene, rebuilt per frame")]
    plan = []
    if snap.static_meshes or any(not p.animated and not p.deforming for p in snap.prototypes):
        plan.append(("static", "static meshes and unmoving instances"))
    plan += [("prototype", p.name) for p in snap.prototypes if p.animated and not p.deforming]
    if snap.deforming_meshes or any(p.deforming for p in snap.prototypes):
        plan.append(("deforming", "deforming meshes, rebuilt per frame"))
    return plan


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} TiB"
