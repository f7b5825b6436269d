"""UsdLux ``MeshLightAPI`` on a gprim: its inputs read into a :class:`usdml.scene.mesh_light.MeshLight` (the
render index makes its triangles lights, :func:`usdml.scene.mesh_light.triangle_lights`).

Read as every UsdLux light is (:func:`usdml.stage.lights.emitted_radiance`: intensity, exposure, color,
colorTemperature; ``normalize``; ``inputs:diffuse``; ``inputs:shadow:enable``). Not modelled, each said in one
warning naming the attribute: ``ShapingAPI`` (cone, focus, IES: a mesh light emits as a Lambertian surface) and
``light:materialSyncMode`` (the camera sees the light's own radiance, plus a bound material's emissiveColor).
"""

from __future__ import annotations

from typing import Callable

from pxr import Usd, UsdLux

from usdml.scene.mesh_light import MeshLight
from usdml.stage.lights import attribute_value, emitted_radiance, lobe_scale

__all__ = ["light_varies", "read_mesh_light"]


def read_mesh_light(prim: Usd.Prim, time: Usd.TimeCode, warn: Callable[[str], None]) -> MeshLight | None:
    """The ``MeshLightAPI`` applied to gprim ``prim`` at ``time``, None where none is. Raises
    :class:`usdml.errors.UsdmlError` for a light input that is not finite or out of range, as every light."""
    if not prim.HasAPI(UsdLux.MeshLightAPI):
        return None
    path = str(prim.GetPath())
    radiance = emitted_radiance(prim, time, with_diffuse=False)
    if prim.HasAPI(UsdLux.ShapingAPI):
        warn(f"{path}: ShapingAPI on a mesh light is not applied; it emits as a Lambertian surface")
    sync = prim.GetAttribute("light:materialSyncMode")
    if sync and sync.HasAuthoredValue():
        warn(f"{path}.light:materialSyncMode: {sync.Get(time)!r} is not modelled; the camera sees the light's "
             "radiance plus the bound material's emissiveColor, and only the light lights the scene")
    return MeshLight(radiance=tuple(float(c) for c in radiance),
                     diffuse=lobe_scale(prim, time)[0],
                     normalize=bool(UsdLux.LightAPI(prim).GetNormalizeAttr().Get(time)),
                     shadow=bool(attribute_value(prim, "inputs:shadow:enable", time, True)))


def light_varies(prim: Usd.Prim) -> bool:
    """Whether a mesh light's inputs (``inputs:*``) might change over time: its mesh is then read every frame."""
    return prim.HasAPI(UsdLux.MeshLightAPI) and any(
        a.ValueMightBeTimeVarying() for a in prim.GetAttributes() if a.GetName().startswith("inputs:"))
