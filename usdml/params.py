"""usdml's parameters, each declared once: one :class:`Param` row per setting and per render option.

Everything else follows from the table: the fields and defaults of
:class:`usdml.settings.UsdmlSettings` (the settings, :data:`PARAMS`) and of
:class:`usdml.settings.RenderOptions` (what a render takes besides them, :data:`OPTIONS`: camera, width,
AOVs, device, Dask ...), the ``UsdmlRenderSettingsAPI`` attributes of ``schemas/schema.usda`` (written by
``tools/gen_schema.py``), the command-line flags of each command (:func:`add_cmdline_args`, shaped like
usdrecord's ``UsdAppUtils.*Args.AddCmdlineArgs``) and the one validation, :func:`check`. A setting is
taken, in increasing priority, from the row's default (the paper's), the stage's attribute on its
RenderSettings prim, and the flag; so setting flags default to None.

Names follow from the field: the flag is ``--`` + the field with ``-`` for ``_`` (``voxel_max_skip`` ->
``--voxel-max-skip``) and the schema attribute ``usdml:`` + the field's first word + ``:`` + the rest in
camelCase (``voxel_max_skip`` -> ``usdml:voxel:maxSkip``; one word: ``gi`` -> ``usdml:gi``). A row names
its flag or attribute only where it differs (``vpl_count`` -> ``--vpls``); a render option has no attribute.

A method's rows are declared in its folder (``usdml/visibility/voxel/params.py``, ``usdml/lighting/lgh/params.py``
...) with :class:`usdml.param.Param`, as are denoising's (``usdml/render/denoise/params.py``); the frame-wide rows
stay here. A leaf module: it imports nothing of usdml but :mod:`usdml.errors`, :mod:`usdml.param`, the row modules
and the backend registry, and no ``pxr``.
The registry is read when a table is needed, not at import: a backend registered later is a ``visibility``
choice, and the parameter rows it declares (``register(..., params=...)``, or a built-in backend's
``usdml/visibility/<name>/params.py``) join the table.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

from usdml.errors import UsdmlError
from usdml.lighting.area import params as area
from usdml.lighting.lgh import params as lgh
from usdml.param import (BAKE, BENCH, COMMANDS, COMPARE, FARM, INFO, LIGHTING, LIGHTING_COMMANDS, LIT, RENDER,
                         STAGE_COMMANDS, VIS, VISIBILITY, VOXEL_COMMANDS, Param, Range)
from usdml.render.denoise import params as denoise
from usdml.visibility import registry

#: image width in pixels when neither ``--imageWidth`` nor a RenderSettings resolution gives one
DEFAULT_WIDTH = 960

#: widest image a render takes
MAX_WIDTH = 16384

#: most segments --implicit-detail accepts (a sphere is about 2·detail² triangles)
MAX_IMPLICIT_DETAIL = 1024

#: most primary rays per pixel (a 32 x 32 grid)
MAX_PIXEL_SAMPLES = 1024

#: argparse's namespace attribute listing the fields whose flags a parser was given
_ARGS_FIELDS = "usdml_settings_fields"
_ARGS_OPTIONS = "usdml_option_fields"


def _square(n: int) -> bool:
    s = math.isqrt(n) if n >= 0 else -1
    return s * s == n and 1 <= n <= MAX_PIXEL_SAMPLES


_SQUARE_RULE = f"a square number from 1 to {MAX_PIXEL_SAMPLES} (1, 4, 9, 16, ...: s x s rays)"


def _names(value) -> bool:
    """A name, or a list / tuple of names (``aovs``, ``purposes``)."""
    return isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value))


#: imageable purposes besides 'default' (always drawn) that ``--purposes`` may name
PURPOSES = ("render", "proxy", "guide", "default")


def purpose_list(value, name: str) -> list[str] | None:
    """``--purposes`` / ``purposes=`` as a list: a string (comma or space separated) or a list of names,
    each a UsdGeom purpose; else a one-line :class:`UsdmlError` starting with ``name`` (how the user gave it)."""
    if value is None:
        return None
    names = value.replace(",", " ").split() if isinstance(value, str) else list(value)
    unknown = [str(n) for n in names if n not in PURPOSES]
    if unknown:
        raise UsdmlError(f"{name}: unknown purpose(s) {', '.join(unknown)}; use render, proxy or guide "
                         "('default' is always drawn)")
    return names


def _or(names) -> str:
    names = list(names)
    return ", ".join(names[:-1]) + f" or {names[-1]}" if len(names) > 1 else "".join(names)


def _visibility(names: tuple[str, ...]) -> Param:
    """The ``visibility`` row: its choices and words are the registry's names at the time."""
    return Param("visibility", str, "exact", f"visibility backend for shadow rays ({', '.join(names)})",
                 (RENDER,), VISIBILITY, choices=names, label="visibility backend", metavar="NAME", parser_choices=False,
                 source="exact: the reference every approximate backend is checked against",
                 doc=f'''Visibility backend for shadow rays: {_or(names)}.

                 "exact" traces rays against the triangles (Embree) and is the reference
                 the approximate backends are checked against; "voxel" looks rays up in
                 the 2D array of per-direction voxelizations (paper 000).''')


# when the settings of one method are read (Param.applies)
_GI = (("gi", ("lgh", "svo", "vpl-bruteforce")),)
_GI_SVO = (("gi", ("svo",)),)
_APPROXIMATE = (("visibility", ("voxel", "svo", "insm")),)

# a section's commands and help group (VIS, LIT: usdml.param)
_STAGE = {"commands": STAGE_COMMANDS, "attribute": None}
_RUN = {"commands": (RENDER,), "attribute": None}
_DASK = {"commands": (RENDER,), "attribute": None, "group": FARM}

#: the frame's settings and the LGH's (``lgh``), in the order of UsdmlSettings' fields after ``visibility``
#: (:func:`_visibility`) and the backends' own rows (:func:`table`)
_SETTINGS = (
    # -- refinement of uncertain answers (issue 36)
    Param("error_budget", float, 1.0, "bound on each frame's estimated error of an approximate visibility backend: "
          "the fraction of facing pixel-light pairs answered wrongly (eps_v, 95 % upper bound), e.g. 0.003; "
          "uncertain answers are re-asked of exact until it holds (0: every answer exact; 1: no bound, no "
          "refinement)", commands=(RENDER, COMPARE, BENCH), group=VISIBILITY, range=Range(0, 1), metavar="E",
          applies=_APPROXIMATE, attribute="usdml:errorBudget", source="off (1) unless asked for"),
    # -- direct light from many lights (paper 004 over the stage's own lights)
    Param("direct", str, "all", "direct light: every pixel against every light (all), or the stage's point, "
          "sphere, disk and rect lights through a lighting grid hierarchy with stochastic, filtered shadows (lgh, "
          "paper 004; the other lights every-light)", **LIT, choices=("all", "lgh"), label="direct lighting",
          source="all: exact; lgh is for tens of thousands of lights and more (measured: docs/lgh-direct.md)"),
    *lgh.DIRECT,
    # -- global illumination (papers 004 and 003)
    Param("gi", str, "none", "indirect light: VPLs through a lighting grid hierarchy (lgh, paper 004), a "
          "sixteenth of the VPLs per pixel in 4x4 interleaved tiles with SVO shadow rays, filtered (svo, paper "
          "003), or every VPL with exact visibility (vpl-bruteforce, the reference)", **LIT,
          choices=("none", "lgh", "svo", "vpl-bruteforce"), label="global illumination",
          source="off unless asked for"),
    Param("vpl_count", int, 100000, "virtual point lights per frame", **LIT, flag="--vpls", range=Range(1),
          label="VPL count", metavar="N", applies=_GI, source="paper 004"),
    Param("vpl_bounces", int, 3, "diffuse bounces of the light paths that place VPLs", **LIT, range=Range(1),
          label="VPL bounces", metavar="N", applies=_GI, source="paper 004"),
    *lgh.HIERARCHY,
    Param("gi_svo_skip", float, 0.5, "--gi svo: pairs whose light is below this fraction of the pixel's mean cast "
          "no shadow ray and count as seen as much as the pixel's traced light (0 = trace every pair with G > 0)",
          **LIT, range=Range(0), metavar="FRACTION", applies=_GI_SVO,
          source="paper 003, Sec. 3.2 (skip faint VPLs); 0.5 measured (docs/gi.md)"),
    *lgh.SHADOWS,
    # -- sampling
    Param("dome_samples", int, 256, "distant lights each DomeLight is importance-sampled into per frame", **LIT,
          range=Range(1), metavar="K", source="measured (usdml.lighting.dome): 1.0 % mean irradiance error at 256"),
    *area.SAMPLING,
    Param("pixel_samples", int, 4, "primary rays per pixel, a square number s x s (correlated multi-jittered: "
          "one in each cell of an s x s grid and in each thin row and column; box filter); 1 = the pixel centre", (RENDER,), LIGHTING, attribute="usdml:pixelSamples", metavar="N",
          valid=_square, rule=_SQUARE_RULE, source="measured (usdml): halves edge error at 4"),
    Param("visible_lights", bool, True, "camera rays see the lights, as Karma and Cycles show them: the domes "
          "behind the geometry (the background AOV) and the rect, disk, sphere and cylinder lights in front of it "
          "(their radiance, in the emission AOV; rects and disks from the front), alpha 1 there; off: unseen, as "
          "Storm (alpha 0 where no surface)", (RENDER,), LIGHTING, attribute="usdml:visibleLights",
          source="Karma and Cycles (docs/visible-lights.md)"),
    Param("motion_blur", bool, True, "motion blur over the camera's shutter (shutter:open/close, in timecodes "
          "around the frame): each pixel sample a time slice of the shutter, the stage, lights and camera at that "
          "time; off (or RenderSettings disableMotionBlur): every sample at the frame's time",
          (RENDER,), LIGHTING, attribute="usdml:motionBlur", source="UsdGeom.Camera shutter (docs/motion-blur.md)"),
    Param("depth_of_field", bool, True, "depth of field: a thin lens of the camera's focalLength / fStop focused "
          "at focusDistance (fStop 0: a pinhole); off (or RenderSettings disableDepthOfField): a pinhole",
          (RENDER,), LIGHTING, attribute="usdml:depthOfField", source="UsdGeom.Camera lens (docs/depth-of-field.md)"),
    Param("seed", int, 0, "random seed (VPLs, shadow samples, dome light sampling)", **LIT, range=Range(0),
          metavar="N"),
    # -- after the frame: denoising (issue 53 item 4)
    *denoise.ROWS,
)

#: the options of a render beside the settings (``usdml render``'s own flags, :class:`usdml.Recorder`'s keywords,
#: :class:`usdml.render.sequence.RenderJob`'s fields); ``rule``: what the check's message asks for
_OPTIONS = (
    Param("image_width", int, None, "image width in pixels, height from the aspect ratio (default: the "
          f"RenderSettings' resolution, else {DEFAULT_WIDTH})", **_RUN, flag="--imageWidth", range=Range(1, MAX_WIDTH),
          metavar="W", rule=f"an integer from 1 to {MAX_WIDTH} (pixels)"),
    Param("camera", str, None, "camera prim path or name (default: RenderSettings camera, main_cam, the first "
          "camera, else a camera framing the scene)", **_STAGE, rule="a camera prim path or name"),
    Param("purposes", str, None, "imageable purposes to include besides 'default', as usdrecord (default: the "
          "RenderSettings' includedPurposes, else 'render' -- final-frame geometry; 'proxy' for usdview's interactive "
          "look)", **_STAGE, metavar="PURPOSE[,PURPOSE...]", valid=_names,
          rule="a list of purposes (render, proxy, guide)"),
    Param("aovs", str, None, "comma-separated AOVs to write (default: color, direct, indirect, shadow, depth, "
          "normal, P, albedo, primId, instanceId)", **_RUN, action="append", valid=_names, rule="a list of AOV names"),
    Param("render_settings", str, None, "RenderSettings prim (default: the stage's renderSettingsPrimPath metadata)",
          **_STAGE, flag="--renderSettingsPrimPath", rule="a RenderSettings prim path"),
    Param("device", str, "cpu", "Warp device: cpu or cuda (default: %(default)s)", VOXEL_COMMANDS, attribute=None,
          choices=("cpu", "cuda"), parser_choices=False, rule="cpu or cuda"),
    Param("implicit_detail", int, 10, "segments around implicit prims (Sphere, Cylinder ...); default %(default)s "
          "as usdImaging", **_STAGE, range=Range(3, MAX_IMPLICIT_DETAIL), metavar="N",
          rule=f"an integer from 3 to {MAX_IMPLICIT_DETAIL} (segments)"),
    Param("camera_light", bool, True, "no camera light for stages without lights (usdrecord's flag)", **_RUN,
          flag="--disableCameraLight", rule="True or False"),
    Param("preview", bool, False, "also write a PNG of the color AOV beside each EXR", **_RUN, rule="True or False"),
    # frames on Dask (usdml.render.farm): a local cluster of ``workers``, or a ``scheduler``
    Param("workers", int, None, "render frames on a local Dask cluster of N process workers", **_DASK,
          range=Range(1), metavar="N", rule="an integer of 1 or more"),
    Param("scheduler", str, None, "render frames on a running Dask cluster (tcp://HOST:PORT)", **_DASK,
          metavar="ADDRESS", rule="a scheduler address (tcp://HOST:PORT)"),
    Param("chunk_size", int, 1, "frames per task (default: %(default)s)", **_DASK, range=Range(1), metavar="K",
          rule="an integer of 1 or more (frames)"),
    Param("retries", int, 2, "attempts per chunk beyond the first (default: %(default)s)", **_DASK, range=Range(0),
          metavar="R", rule="an integer of 0 or more"),
    Param("nthreads", int, None, "threads each worker renders with (default: the machine's cores / --workers)",
          **_DASK, range=Range(1), metavar="T", rule="an integer of 1 or more"),
)

#: the schema attributes' documentation (``Param.doc``) where it says more than the flag's help
_DOCS = {
    "direct": """Direct lighting: all shades every pixel against every light; lgh puts the stage's point lights (and sphere, disk and rect lights of size 0) in a lighting grid hierarchy (paper 004) and shades it with importance-sampled, filtered shadow rays through the visibility backend.

    Distant and dome lights, cylinder lights, lights with a shaping cone or
    focus and lights with shadows off stay every-light under lgh. lgh pays
    from about ten thousand lights (docs/lgh-direct.md); it uses the
    usdml:lgh:alpha, usdml:lgh:levels and usdml:shadow:filterIterations
    settings, and usdml:direct:shadowSamples.""",
    "gi": """Global illumination: none, lgh (VPLs through a lighting grid hierarchy, paper 004), svo (each pixel of a 4x4 interleaved tile gathers a sixteenth of the VPLs with sparse voxel octree shadow rays, then a geometry-aware filter, paper 003) or vpl-bruteforce (every VPL with exact visibility, the reference).

    Indirect light lands in the indirect AOV and is added to color. Paper 003 (svo) gathers
    512 to 2,048 first-bounce VPLs: usdml:vpl:count 1024, usdml:vpl:bounces 1.""",
    "vpl_count": """Virtual point lights generated per frame (paper 004 uses 100K).""",
    "vpl_bounces": """Diffuse bounces of the light paths that place VPLs (paper 004 traces up to three).""",
    "gi_svo_skip": """--gi svo: (pixel, VPL) pairs whose unshadowed light is below this fraction of the mean of the pixel's pairs cast no shadow ray (paper 003 skips the V term for faint VPLs).

    Their light counts as visible in the proportion the pixel's traced
    light is. 0 traces every pair with G > 0.""",
    "dome_samples": """Distant lights each DomeLight is importance-sampled into per frame.

    Each becomes a distant light with the many-light visibility of every
    other light; at 256 the mean irradiance error of a sun-and-sky map is
    about 1 percent.""",
    "pixel_samples": """Primary rays per pixel, a square number n = s x s (correlated multi-jittered: one ray in each cell of an s x s grid over the pixel and in each of its n thin rows and columns), combined with a box filter: color, direct, indirect, shadow, albedo and lightCount are averaged; depth, positions, normals and ids come from the ray nearest the pixel centre.

    1 traces the pixel centre only (no anti-aliasing). The default 4 halves
    the per-pixel error of edges and shadow boundaries for about 4x the
    shading time; 16 comes within about 3.5 percent of a pixel-integrated
    render.""",
    "error_budget": """Bound on each frame's visibility error: the fraction of facing pixel-light pairs an approximate backend (voxel, svo, insm) may answer wrongly, as the frame's own estimate's 95 % upper bound (eps_v, usdml:estimate:eps_v_hi).

    Each query of the backend says whether its answer is certain by a rule of
    the method's geometry; uncertain ones are re-asked of the exact backend,
    the rule widened step by step until the frame's estimate is under the
    budget. 0: every answer exact (the exact backend's pixels); 1: no bound
    and no refinement (the backend as it is). With the exact backend it does
    nothing.""",
    "visible_lights": """Camera rays see the lights, as Karma and Cycles show them (Storm does not): the domes behind the geometry and the rect, disk, sphere and cylinder lights in front of it.

    A ray that reaches no surface shows the domes' radiance in its direction
    (their lat-long maps, in the background AOV); a ray that reaches an area
    light before any surface shows the light's radiance (rects and disks
    from their front only; in the emission AOV). Both are added to color
    with alpha 1. Point and distant lights are never seen. false: lights are
    unseen and alpha is 0 where no surface is hit.""",
    "seed": """Seed of usdml's random number generators (VPLs, shadow samples), for reproducible renders.""",
}

#: field name -> its row, settings only, in UsdmlSettings' field order (kept up to date by :func:`table`)
PARAMS: dict[str, Param] = {}
#: field name -> its row, the render options
OPTIONS: dict[str, Param] = {p.field: p for p in _OPTIONS}
_built_from = None      # the registry's state PARAMS was last built from


def table() -> dict[str, Param]:
    """:data:`PARAMS` as the registry stands now: ``visibility`` accepts every registered name, the rows
    each registered backend declares (the built-in ones' from their folders, ``usdml/visibility/voxel/params.py``
    ...) follow it, then the frame's own rows with the LGH's among them (updated in place, so every holder
    of ``PARAMS`` sees it)."""
    global _built_from
    state = registry.state()
    if state != _built_from:
        rows = (_visibility(registry.backend_names()), *registry.backend_params(), *_SETTINGS)
        PARAMS.clear()
        PARAMS.update((p.field, replace(p, doc=_DOCS[p.field]) if p.field in _DOCS else p) for p in rows)
        _built_from = state
    return PARAMS


table()


def check(name: str, value, keyword: bool = False):
    """``value`` if setting ``name`` (a :data:`PARAMS` field) accepts it; else a one-line
    :class:`UsdmlError` naming the setting by its flag and schema attribute (``keyword``: by the
    Python keyword, ``name``, and the attribute: a script's message)."""
    param = table().get(name)
    if param is None:
        raise UsdmlError(f"unknown setting {name!r}; settings: {', '.join(PARAMS)}")
    problem = param.problem(value)
    if problem:
        where = f"keyword {name}, stage attribute {param.attribute}" if keyword else param.where
        raise UsdmlError(f"{problem} ({where})")
    return value


def ignored(given, settings) -> list[str]:
    """A warning for each field of ``given`` (the settings a flag or keyword set) that ``settings`` (the
    effective ones, the stage's included) do not read: ``--gi-svo-skip`` without ``--gi svo``."""
    rows = table()
    out = []
    for name in given:
        p = rows[name]
        if p.applies is None or any(getattr(settings, f) in values for f, values in p.applies):
            continue
        need = " or ".join(_setting(rows[f], values) for f, values in p.applies)
        here = ", ".join(_setting(rows[f], (getattr(settings, f),)) for f in dict(p.applies))
        out.append(f"{p.flag} is ignored: it applies with {need} (here: {here})")
    return out


def _setting(row: Param, values: tuple) -> str:
    """A setting's values as a flag gives them: ``--gi lgh/svo``; a switch ``--denoise`` or ``--no-denoise``."""
    if row.type is bool:
        return row.flag if values == (True,) else f"--no-{row.flag[2:]}"
    return f"{row.flag} {'/'.join(map(str, values))}"


def default_help(param: Param) -> str:
    """Flag help ending in where the default comes from: the stage's attribute, else the table's."""
    default = param.default
    shown = ("on" if default else "off") if param.type is bool else f"{default:g}" if param.type is float else default
    return f"{param.help} (default: the stage's {param.attribute}, else {shown})".replace("%", "%%")


def _group(parser: argparse.ArgumentParser, title: str | None):
    """The parser itself (None), else its argument group ``title``, made the first time."""
    if title is None:
        return parser
    return next((g for g in parser._action_groups if g.title == title), None) or parser.add_argument_group(title)


def _flag_kwargs(p: Param) -> dict:
    if p.is_option:         # the option's own default; bool options are switches away from it
        kw = {"dest": p.field, "default": p.default, "help": p.help}
        if p.type is bool:
            return {**kw, "action": "store_false" if p.default else "store_true"}
    else:                   # None: the stage's value stays unless the flag is given
        kw = {"dest": p.field, "default": None, "help": default_help(p)}
        if p.type is bool:
            return {**kw, "action": argparse.BooleanOptionalAction}
    kw["type"] = p.type
    if p.action:
        kw["action"] = p.action
    if p.choices and p.parser_choices:
        kw["choices"] = p.choices
    if p.metavar:
        kw["metavar"] = p.metavar
    return kw


def add_cmdline_args(parser: argparse.ArgumentParser, command: str, *fields: str) -> None:
    """Add the flags of ``fields`` (render options or settings that ``command`` takes), or with none
    given of every setting ``command`` takes, each in its row's help group.

    A setting's flag stores into its field name and defaults to None, so the stage's value stays
    unless the flag is given (:func:`overrides_from_args` collects what was given); an option's flag
    stores its value or default (:func:`options_from_args`).
    """
    if command not in STAGE_COMMANDS:
        raise ValueError(f"unknown command {command!r}; the table knows {', '.join(STAGE_COMMANDS)}")
    rows = [p for p in table().values() if command in p.commands] if not fields else \
        [OPTIONS.get(f) or PARAMS[f] for f in fields]
    for p in rows:
        if command not in p.commands:
            raise ValueError(f"{p.flag} is not a flag of {command}")
        _group(parser, p.group).add_argument(p.flag, **_flag_kwargs(p))
    for key, kind in ((_ARGS_FIELDS, False), (_ARGS_OPTIONS, True)):
        given = tuple(p.field for p in rows if p.is_option is kind)
        if given:
            parser.set_defaults(**{key: (parser.get_default(key) or ()) + given})


def overrides_from_args(args: argparse.Namespace) -> dict:
    """The settings the command line gave (field -> value), for ``UsdmlSettings.updated``."""
    values = {f: getattr(args, f, None) for f in getattr(args, _ARGS_FIELDS, ())}
    return {f: v for f, v in values.items() if v is not None}


def options_from_args(args: argparse.Namespace) -> dict:
    """The render options of the command line (field -> value, defaults included), for ``Recorder``."""
    return {f: getattr(args, f) for f in getattr(args, _ARGS_OPTIONS, ())}


__all__ = ["COMMANDS", "DEFAULT_WIDTH", "FARM", "LIGHTING", "MAX_IMPLICIT_DETAIL", "MAX_PIXEL_SAMPLES", "MAX_WIDTH",
           "OPTIONS", "PARAMS", "Param", "Range", "VISIBILITY", "add_cmdline_args", "check", "default_help", "ignored",
           "options_from_args", "overrides_from_args", "table"]
