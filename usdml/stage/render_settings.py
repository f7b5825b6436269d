"""``UsdRender`` settings, products and vars as plain data, plus usdml's own schema attributes."""

from __future__ import annotations

from pxr import Sdf, Usd, UsdRender

from usdml.errors import UsdmlError
from usdml.scene import RenderProduct, RenderSettings, RenderVar
from usdml.settings import SCHEMA_ATTRIBUTES, UsdmlSettings


def settings_prim(stage: Usd.Stage, explicit: str | None) -> Usd.Prim | None:
    """The RenderSettings prim named by ``explicit`` or the stage's ``renderSettingsPrimPath`` metadata."""
    path = explicit or stage.GetMetadata("renderSettingsPrimPath") or ""
    if not path:
        return None
    where = "--renderSettingsPrimPath" if explicit else "the stage's renderSettingsPrimPath metadata"
    if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
        raise UsdmlError(f"{where}: {path!r} is not an absolute prim path; {_settings_choices(stage, explicit)}")
    prim = stage.GetPrimAtPath(path)
    if not prim or not prim.IsA(UsdRender.Settings):
        kind = f"a prim of type {prim.GetTypeName()}" if prim and prim.GetTypeName() else "a typeless prim"
        what = f"{path} is {kind}, not RenderSettings" if prim else f"no RenderSettings prim at {path}"
        raise UsdmlError(f"{where}: {what}; {_settings_choices(stage, explicit)}")
    return prim


def _settings_choices(stage: Usd.Stage, explicit: str | None) -> str:
    """What to do about a RenderSettings path that names none: give one of the stage's (listed as
    ``--camera`` lists cameras), or do without."""
    found = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
    if found:
        return f"RenderSettings on the stage: {', '.join(found[:8])} (give one with --renderSettingsPrimPath)"
    return "the stage has no RenderSettings prim (" + ("omit --renderSettingsPrimPath)" if explicit else
                                                        "fix or remove its renderSettingsPrimPath metadata)")


def _target(rel) -> str | None:
    targets = rel.GetForwardedTargets() if rel else []
    return str(targets[0]) if targets else None


def _authored(attr) -> bool:
    return bool(attr) and attr.HasAuthoredValue()


def read_render_settings(prim: Usd.Prim, time: Usd.TimeCode) -> RenderSettings:
    stage = prim.GetStage()
    rs = UsdRender.Settings(prim)
    res = rs.GetResolutionAttr().Get(time)
    resolution = (int(res[0]), int(res[1]))
    products = []
    for ppath in rs.GetProductsRel().GetForwardedTargets():
        pprim = stage.GetPrimAtPath(ppath)
        if not pprim or not pprim.IsA(UsdRender.Product):
            raise UsdmlError(f"{prim.GetPath()}.products: target {ppath} is not a RenderProduct")
        product = UsdRender.Product(pprim)
        name_attr = product.GetProductNameAttr()
        rvars = []
        for vpath in product.GetOrderedVarsRel().GetForwardedTargets():
            vprim = stage.GetPrimAtPath(vpath)
            if not vprim or not vprim.IsA(UsdRender.Var):
                raise UsdmlError(f"{ppath}.orderedVars: target {vpath} is not a RenderVar")
            var = UsdRender.Var(vprim)
            rvars.append(RenderVar(
                path=str(vpath), name=vprim.GetName(), source_name=str(var.GetSourceNameAttr().Get(time) or ""),
                source_type=str(var.GetSourceTypeAttr().Get(time) or "raw"),
                data_type=str(var.GetDataTypeAttr().Get(time) or "color3f")))
        pres = product.GetResolutionAttr()
        products.append(RenderProduct(
            path=str(ppath), product_name=str(name_attr.Get(time) or pprim.GetName()),
            product_type=str(product.GetProductTypeAttr().Get(time) or "raster"), vars=rvars,
            camera=_target(product.GetCameraRel()),
            resolution=tuple(int(v) for v in pres.Get(time)) if _authored(pres) else None,
            name_time_varying=name_attr.ValueMightBeTimeVarying()))
    for w, h in [resolution] + [p.resolution for p in products if p.resolution]:
        if w < 1 or h < 1 or w * h > 1 << 28:
            raise UsdmlError(f"{prim.GetPath()}.resolution: ({w}, {h}) is not a renderable image size")
    purposes = rs.GetIncludedPurposesAttr().Get(time)
    return RenderSettings(
        path=str(prim.GetPath()), camera=_target(rs.GetCameraRel()), resolution=resolution,
        pixel_aspect_ratio=float(rs.GetPixelAspectRatioAttr().Get(time) or 1.0), products=products,
        included_purposes=[str(p) for p in purposes] if purposes is not None else ["default", "render"],
        disable_motion_blur=bool(rs.GetDisableMotionBlurAttr().Get(time)),
        disable_depth_of_field=bool(rs.GetDisableDepthOfFieldAttr().Get(time)))


def read_usdml_settings(prim: Usd.Prim | None) -> UsdmlSettings:
    """usdml parameters authored (or given fallbacks by the registered schema) on a RenderSettings prim:
    every attribute of the parameter table (:data:`usdml.params.PARAMS`)."""
    if prim is None:
        return UsdmlSettings()
    values = {}
    for name, field in SCHEMA_ATTRIBUTES.items():
        attr = prim.GetAttribute(name)
        value = attr.Get() if attr else None
        if value is not None:
            values[field] = value if not hasattr(value, "GetText") else str(value)
    try:
        return UsdmlSettings().updated(**values)
    except UsdmlError as e:
        raise UsdmlError(f"{prim.GetPath()}: {e}") from None
