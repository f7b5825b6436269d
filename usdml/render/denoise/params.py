"""Denoising's rows of the parameter table (:mod:`usdml.params`) and what they accept. A leaf module: it imports
only :mod:`usdml.param`, so the table is built without loading OIDN."""

from __future__ import annotations

from usdml.param import LIGHTING, RENDER, Param

#: the radiance AOVs a user may ask to denoise; besides them every light group's (``lightgroup:NAME``, and
#: ``lightgroup:*`` for all the frame writes)
DENOISABLE = ("color", "direct", "indirect", "diffuse", "specular", "emission", "background")
_GROUP = "lightgroup:"      # usdml.aov.names.LIGHT_GROUP (the aov layer is not a leaf's to import)


def aov_list(value: str) -> list[str]:
    """``--denoise-aovs`` / ``usdml:denoise:aovs`` as names: comma- or space-separated."""
    return [n for n in value.replace(",", " ").split() if n]


def denoisable(name: str) -> bool:
    """Whether AOV ``name`` is radiance OIDN may denoise."""
    return name in DENOISABLE or (name.startswith(_GROUP) and len(name) > len(_GROUP))


def _valid(value) -> bool:
    return isinstance(value, str) and bool(aov_list(value)) and all(denoisable(n) for n in aov_list(value))


_ON = (("denoise", (True,)),)
#: ``denoise_prefilter``'s choices, Cycles' (``denoising_prefilter``) names
PREFILTERS = ("accurate", "fast", "none")

ROWS = (
    Param("denoise", bool, False, "denoise the radiance AOVs of --denoise-aovs with Intel Open Image Denoise "
          "(pyoidn: RT filter, HDR, albedo and denoiseNormal guides), per frame; color_noisy keeps color as rendered",
          (RENDER,), LIGHTING, source="off unless asked for (docs/denoising.md)",
          doc="""Denoise each frame's radiance AOVs named by usdml:denoise:aovs with Intel Open Image Denoise (pyoidn): its RT filter in HDR mode, guided by the albedo and denoiseNormal AOVs box-filtered over the pixel samples like color.

    Alpha is kept as rendered; the AOV color_noisy holds color before
    denoising. The frame's usdml:estimate:* attributes measure the frame
    before denoising (docs/denoising.md)."""),
    Param("denoise_aovs", str, "color", "the AOVs --denoise denoises, comma-separated: radiance only (color, direct, "
          "indirect, diffuse, specular, emission, background, lightgroup:NAME, lightgroup:* for every group); "
          "those the frame does not write are skipped", (RENDER,), LIGHTING, metavar="AOV[,AOV...]", valid=_valid,
          rule="a comma-separated list of radiance AOVs (color, direct, indirect, diffuse, specular, emission, "
               "background, lightgroup:NAME); depth, normals, positions, ids, shadow and lightCount are not "
               "denoised", applies=_ON, source="color: the beauty"),
    Param("denoise_prefilter", str, "accurate", "how --denoise treats its guides (Cycles' choices): accurate "
          "denoises them first and hands them over as clean (cleanAux), fast hands them over as rendered for OIDN to "
          "clean inside its filter (several times faster), none hands them over as rendered as clean",
          (RENDER,), LIGHTING, choices=PREFILTERS, metavar="MODE", applies=_ON,
          source="accurate: the least error on every tuning stage of tools/denoise_accuracy.py (docs/CHANGELOG.md), "
                 "OIDN's and Cycles' choice for final frames",
          doc="""How --denoise treats its guides, with Cycles' names: accurate denoises the albedo and denoiseNormal guides with OIDN first and tells the beauty's filter they are clean (cleanAux); fast hands them over as rendered and OIDN cleans them inside the beauty's filter; none hands them over as rendered and tells OIDN they are clean.

    accurate is OIDN's recommendation for final frames and had the least
    error on every tuning stage; fast is several times faster; none suits
    guides that are truly noise-free (no depth of field, no motion blur)
    (docs/denoising.md, docs/CHANGELOG.md)."""),
)
