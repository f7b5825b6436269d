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

A leaf module: it imports nothing of usdml but :mod:`usdml.errors` and the backend registry, and no
``pxr``. The registry is read when a table is needed, not at import: a backend registered later is a
``visibility`` choice, and the parameter rows it declares (``register(..., params=...)``) join the table.
"""

from __future__ import annotations

import argparse
import inspect
import math
import numbers
from dataclasses import dataclass
from typing import Callable

from usdml.errors import UsdmlError
from usdml.visibility import registry

#: commands whose flags come from this table (``info`` takes only the stage's options, no setting); a row
#: lists the ones that take its flag
RENDER, COMPARE, BENCH, BAKE, INFO = "render", "compare", "bench", "bake", "info"
COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
VOXEL_COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
LIGHTING_COMMANDS = (RENDER, COMPARE)
#: the commands that read a stage (``--camera`` ...)
STAGE_COMMANDS = (RENDER, COMPARE, BENCH, BAKE, INFO)

#: the help's groups of flags (``Param.group``; None: the command's own options)
VISIBILITY = "visibility (usdml:visibility, usdml:voxel:*, usdml:svo:*, usdml:insm:*)"
LIGHTING = "lighting and sampling (usdml:gi, usdml:vpl:*, usdml:lgh:*, usdml:shadow:* ...)"
FARM = 'frames on Dask (docs/rendering.md, "Render farms")'

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


@dataclass(frozen=True)
class Range:
    """Closed interval ``[low, high]``, either end open-ended (None); ``low_open`` excludes ``low``.
    Float values must also be finite."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False

    def __contains__(self, value) -> bool:
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or value <= self.high

    def rule(self, kind: type) -> str:
        """What the range accepts, as an error message says it ("in [4, 2048]", "finite and > 0")."""
        if self.low is not None and self.high is not None:
            return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"
        bound = f"{'>' if self.low_open else '>='} {self.low:g}" if self.low is not None else f"<= {self.high:g}"
        return f"finite and {bound}" if kind is float else bound


def _camel(words: str) -> str:
    first, *rest = words.split("_")
    return first + "".join(w[:1].upper() + w[1:] for w in rest)


@dataclass(frozen=True)
class Param:
    """One setting (or, with ``attribute=None``, one render option): its field, value type and default,
    its one-line ``help``, the commands that take its flag and the help's ``group``; where it is set
    (``flag``, ``attribute``: derived from the field, module doc, unless given) and what it accepts.

    ``doc`` is the schema attribute's documentation, whose first sentence USD keeps (``userDocBrief``;
    default: the table's ``_DOCS`` entry, else ``help``). ``choices``, ``range`` and ``valid`` (a
    predicate, described by ``rule``) are what :func:`check` accepts; ``label`` is how its messages name
    the value (default: the field name in words). ``source`` says where the default comes from.
    A setting's flag help gets the default appended (:func:`default_help`); a render option's help says
    it itself (``%(default)s``), and its check is ``valid`` with the message ``give <rule>``.
    """

    field: str
    type: type
    default: object
    help: str
    commands: tuple[str, ...] = ()
    group: str | None = None
    flag: str = ""
    #: "" derives it from the field; None: a render option, no schema attribute
    attribute: str | None = ""
    source: str = ""
    choices: tuple = ()
    range: Range | None = None
    valid: Callable[[object], bool] | None = None
    rule: str = ""
    label: str = ""
    metavar: str | None = None
    doc: str = ""
    #: give argparse the choices (it refuses others itself); False leaves the refusal to check()
    parser_choices: bool = True
    #: when the setting is read: any of ``(field, values)`` holds (None: always); :func:`ignored` warns of a
    #: flag given where it is not read
    applies: tuple[tuple[str, tuple], ...] | None = None
    #: argparse action of a render option's flag (default: by its type)
    action: str | None = None

    def __post_init__(self) -> None:
        if not self.flag:
            object.__setattr__(self, "flag", "--" + self.field.replace("_", "-"))
        if self.attribute == "":
            head, _, rest = self.field.partition("_")
            object.__setattr__(self, "attribute", f"usdml:{head}" + (f":{_camel(rest)}" if rest else ""))

    @property
    def is_option(self) -> bool:
        """A render option (no schema attribute, not a settings field)."""
        return self.attribute is None

    @property
    def name(self) -> str:
        """How messages name the value."""
        return self.label or self.field.replace("_", " ")

    @property
    def where(self) -> str:
        """Where a user sets it: ``--voxel-resolution, usdml:voxel:resolution``."""
        return f"{self.flag}, {self.attribute}"

    @property
    def schema_doc(self) -> str:
        """The schema attribute's documentation, dedented (first sentence: the brief)."""
        doc = self.doc or _DOCS.get(self.field, "")
        if doc:
            return inspect.cleandoc(doc)
        text = self.help[0].upper() + self.help[1:]
        return text if text.endswith(".") else text + "."

    def accepts(self, value) -> bool:
        """A render option's check: ``valid``, else the type, choices and range."""
        if self.valid is not None:
            return self.valid(value)
        ok = isinstance(value, bool) if self.type is bool else _is_a(self.type, value)
        return ok and (not self.choices or value in self.choices) and (self.range is None or value in self.range)

    def problem(self, value) -> str | None:
        """Why ``value`` is refused (one clause naming the setting and what to use), or None."""
        if not _is_a(self.type, value):
            return f"{self.name} must be {_TYPE_WORDS[self.type]}, got {value!r}"
        if self.choices and value not in self.choices:
            listed = ", ".join(map(str, self.choices))
            if self.type is str:
                return f"unknown {self.name} {value!r}; use one of {listed}"
            return f"{self.name} must be one of {listed}, got {value!r}"
        if self.range is not None and value not in self.range:
            return f"{self.name} must be {self.range.rule(self.type)}, got {value!r}"
        if self.valid is not None and not self.valid(value):
            return f"{self.name} must be {self.rule}, got {value!r}"
        return None


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a name"}


def _is_a(kind: type, value) -> bool:
    if kind is bool:
        return isinstance(value, (bool, int)) and value in (0, 1)
    if isinstance(value, bool):
        return False
    if kind is int:
        return isinstance(value, numbers.Integral)
    if kind is float:
        return isinstance(value, numbers.Real)
    return isinstance(value, kind)


def _square(n: int) -> bool:
    s = math.isqrt(n) if n >= 0 else -1
    return s * s == n and 1 <= n <= MAX_PIXEL_SAMPLES


_SQUARE_RULE = f"a square number from 1 to {MAX_PIXEL_SAMPLES} (1, 4, 9, 16, ...: an s x s stratified grid)"


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
_GI_LGH = (("gi", ("lgh",)),)
_DIRECT_LGH = (("direct", ("lgh",)),)
_ANY_LGH = _GI_LGH + _DIRECT_LGH
_GI = (("gi", ("lgh", "svo", "vpl-bruteforce")),)
_GI_SVO = (("gi", ("svo",)),)
_VOXEL = (("visibility", ("voxel",)),)
_SVO = (("visibility", ("svo",)), ("gi", ("svo",)))      # --gi svo casts its rays through an octree
_INSM = (("visibility", ("insm",)),)
_APPROXIMATE = (("visibility", ("voxel", "svo", "insm")),)

# a section's commands and help group
_VIS = {"commands": VOXEL_COMMANDS, "group": VISIBILITY}
_LIT = {"commands": LIGHTING_COMMANDS, "group": LIGHTING}
_STAGE = {"commands": STAGE_COMMANDS, "attribute": None}
_RUN = {"commands": (RENDER,), "attribute": None}
_DASK = {"commands": (RENDER,), "attribute": None, "group": FARM}

#: every setting, in the order of UsdmlSettings' fields (``visibility`` first: :func:`_visibility`)
_SETTINGS = (
    # -- voxel arrays (paper 000)
    Param("voxel_resolution", int, 128, "voxels per axis of each direction's voxelization", **_VIS,
          range=Range(4, 2048), metavar="N", applies=_VOXEL, source="paper 000"),
    Param("direction_step", float, 2.0, "degrees between direction bins (k in paper 000: 90 x 90 directions at 2)",
          **_VIS, attribute="usdml:voxel:directionStep", range=Range(0.1, 90), metavar="DEG", source="paper 000"),
    Param("fully_dynamic", bool, False, "voxelize the whole scene every frame (paper 000 Alg. 5) instead of a "
          "static array plus prototype arrays", **_VIS, attribute="usdml:voxel:fullyDynamic",
          source="paper 000 (Alg. 4 unless the scene asks for Alg. 5)"),
    Param("voxel_rebuild", str, "rotate", "per-frame voxel arrays (deforming meshes, fully dynamic scenes): "
          "rotate one voxelization (paper 000 Alg. 5) or voxelize every direction (Alg. 1)", **_VIS,
          choices=("rotate", "geometry"), applies=_VOXEL, source="paper 000, Alg. 5"),
    Param("voxel_mapping", str, "point", "Alg. 5: a rotated voxel sets the voxel of its centre (point, the paper) "
          "or every voxel it overlaps (conservative)", **_VIS, choices=("point", "conservative"), applies=_VOXEL,
          source="paper 000, Alg. 5"),
    # leaving the surface (usdml.visibility.voxel.backend's module doc): usdml's measured rule, not the paper's
    Param("voxel_normal_offset", float, 1.0, "voxels (of the static array) a shadow ray starts off its surface, "
          "along the normal turned toward the light", **_VIS, range=Range(0), metavar="VOXELS", applies=_VOXEL,
          source="measured (usdml)"),
    Param("voxel_skip", float, 1.0, "voxels a shadow ray ignores at its start to leave its own surface (more at "
          "grazing angles)", **_VIS, range=Range(0), metavar="VOXELS", applies=_VOXEL, source="measured (usdml)"),
    Param("voxel_slab", float, 1.0, "voxels above the tangent plane a grazing shadow ray skips to (slab / "
          "sin(angle) along the ray, at most the max skip)", **_VIS, range=Range(0), metavar="VOXELS", applies=_VOXEL,
          source="measured (usdml)"),
    Param("voxel_max_skip", float, 0.0, "most voxels a grazing shadow ray skips to leave its surface; 0 = "
          "automatic: 2, or 4 with the conservative mapping", **_VIS, range=Range(0), metavar="VOXELS",
          applies=_VOXEL, source="measured (usdml): 2 point, 4 conservative"),
    Param("voxel_end_skip", float, 1.0, "voxels a shadow ray ignores at the light's end, so a light mounted on a "
          "wall is not hidden by it", **_VIS, range=Range(0), metavar="VOXELS", applies=_VOXEL,
          source="measured (usdml)"),
    Param("voxel_segment", int, 32, "voxels a shadow ray looks up in one row before it picks its row anew (a "
          "divisor of 32)", **_VIS, choices=(1, 2, 4, 8, 16, 32), applies=_VOXEL, source="one 32-bit word of a row"),
    Param("voxel_cpu_kernel", str, "auto", "how voxel queries run on a CPU: auto (the compiled kernel, AVX2 where "
          "the CPU has it, else Warp), native (the compiled kernel; an error without it) or warp", **_VIS,
          choices=("auto", "native", "warp"), applies=_VOXEL, source="measured (usdml): docs/voxel.md"),
    Param("voxel_core", float, 0.0, "voxelization rule of the cached arrays: 0 rasterizes rows' centre lines; a "
          "fraction > 0 marks surface samples in that central part of a row", **_VIS, range=Range(0, 1),
          metavar="FRACTION", applies=_VOXEL, source="measured (usdml)"),
    # Alg. 1's per-frame arrays, measured at 128^3 / 2 deg (e_v / e_s, rebuild): low-poly creature (3,968 triangles)
    # 1: 1.85 / 1.19 %, 6.4 s; 0: 1.77 / 1.08 %, 1.3 s; park 1: 32.0 / 29.0 %, 3.0 s; 0: 19.0 / 9.6 %, 1.6 s
    Param("voxel_frame_core", float, 0.0, "the same rule for per-frame arrays rebuilt from geometry (voxel "
          "rebuild geometry)", **_VIS, range=Range(0, 1), metavar="FRACTION", applies=_VOXEL,
          source="measured (usdml)"),
    Param("voxel_memory_limit", float, 0.0, "GiB the voxel arrays may take; 0 = automatic: 80 % of the available "
          "memory", **_VIS, range=Range(0), metavar="GIB", applies=_VOXEL, source="the machine"),
    # -- sparse voxel octree (paper 003)
    Param("svo_resolution", int, 0, "voxels per axis of the sparse voxel octree, a power of two; 0 = automatic: "
          "128 for a room (at most 20 m across), else 256", **_VIS,
          choices=(0, 16, 32, 64, 128, 256, 512, 1024, 2048), applies=_SVO, source="paper 003"),
    Param("svo_cpu_kernel", str, "auto", "how SVO queries run on a CPU: auto (the compiled traversal when it was "
          "built, else Warp), native (the compiled traversal; an error without it) or warp", **_VIS,
          choices=("auto", "native", "warp"), applies=_SVO, source="measured (usdml): docs/svo.md"),
    # -- intermediate shadow maps (paper 001)
    Param("insm_count", int, 10, "depth images (intermediate shadow maps) per frame, from viewpoints on the "
          "scene's box", **_VIS, range=Range(1, 26), metavar="K", applies=_INSM, source="paper 001, Table 4"),
    Param("insm_resolution", int, 128, "pixels per side of each depth image", **_VIS, range=Range(8, 4096),
          metavar="W", applies=_INSM, source="paper 001, Table 2"),
    Param("insm_light_resolution", int, 512, "texels per side of each view of a light's shadow map (six views for "
          "a point light)", **_VIS, range=Range(16, 8192), metavar="S", applies=_INSM, source="paper 001, Table 3"),
    Param("insm_threshold", float, 2.0, "depth-discontinuity threshold of the triangulation, in pixel footprints "
          "of the depth image", **_VIS, range=Range(0, low_open=True), metavar="PIXELS", applies=_INSM,
          source="paper 001, Alg. 2 (scene-dependent there; measured: docs/insm.md)"),
    Param("insm_cpu_kernel", str, "auto", "how the per-light maps run on a CPU: auto (the compiled maps when they "
          "were built, else Warp), native (the compiled maps; an error without them) or warp", **_VIS,
          choices=("auto", "native", "warp"), applies=_INSM, source="measured (usdml): docs/insm.md"),
    # -- refinement of uncertain answers (issue 36)
    Param("error_budget", float, 1.0, "bound on each frame's estimated error of an approximate visibility backend: "
          "the fraction of facing pixel-light pairs answered wrongly (eps_v, 95 % upper bound), e.g. 0.003; "
          "uncertain answers are re-asked of exact until it holds (0: every answer exact; 1: no bound, no "
          "refinement)", commands=(RENDER, COMPARE, BENCH), group=VISIBILITY, range=Range(0, 1), metavar="E",
          applies=_APPROXIMATE, attribute="usdml:errorBudget", source="off (1) unless asked for"),
    # -- direct light from many lights (paper 004 over the stage's own lights)
    Param("direct", str, "all", "direct light: every pixel against every light (all), or the stage's point, "
          "sphere, disk and rect lights through a lighting grid hierarchy with stochastic, filtered shadows (lgh, "
          "paper 004; the other lights every-light)", **_LIT, choices=("all", "lgh"), label="direct lighting",
          source="all: exact; lgh is for tens of thousands of lights and more (measured: docs/lgh-direct.md)"),
    Param("direct_alpha", float, 4.0, "--direct lgh: blending radius factor alpha, r_l = alpha h_l (the lights "
          "themselves within alpha h_1)", **_LIT, range=Range(0, low_open=True), metavar="ALPHA", applies=_DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md (paper 004 uses 1 for VPLs)"),
    Param("direct_gather", str, "auto", "--direct lgh: what a pixel gathers from: the hierarchy (paper 004), "
          "every grid light itself summed exactly (each: the hierarchy's limit, on a CPU), or auto: per frame, "
          "each where its sum costs less than the hierarchy's gather", **_LIT,
          choices=("auto", "hierarchy", "each"), applies=_DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md, on stages it was not tuned on"),
    Param("direct_shadow_samples", int, 0, "--direct lgh: shadow rays per pixel (shared by its primary rays), "
          "importance-sampled from the lights that reach it; 0: chosen per frame so that the shadows' noise is "
          "about usdml:direct:shadowNoise", **_LIT, range=Range(0), metavar="N",
          applies=_DIRECT_LGH, source="measured (usdml): docs/lgh-direct.md, on stages it was not tuned on"),
    Param("direct_shadow_noise", float, 0.03125, "--direct lgh with usdml:direct:shadowSamples 0: the shadows' "
          "relative noise (RMS over the frame's mean light) the frame's shadow rays are chosen for", **_LIT,
          range=Range(0, 1, low_open=True), metavar="NOISE", applies=_DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md (5 % relative RMSE of every-light shading, issue 37)"),
    # -- global illumination (papers 004 and 003)
    Param("gi", str, "none", "indirect light: VPLs through a lighting grid hierarchy (lgh, paper 004), a "
          "sixteenth of the VPLs per pixel in 4x4 interleaved tiles with SVO shadow rays, filtered (svo, paper "
          "003), or every VPL with exact visibility (vpl-bruteforce, the reference)", **_LIT,
          choices=("none", "lgh", "svo", "vpl-bruteforce"), label="global illumination",
          source="off unless asked for"),
    Param("vpl_count", int, 100000, "virtual point lights per frame", **_LIT, flag="--vpls", range=Range(1),
          label="VPL count", metavar="N", applies=_GI, source="paper 004"),
    Param("vpl_bounces", int, 3, "diffuse bounces of the light paths that place VPLs", **_LIT, range=Range(1),
          label="VPL bounces", metavar="N", applies=_GI, source="paper 004"),
    Param("lgh_alpha", float, 0.0, "LGH blending radius factor alpha, r_l = alpha h_l; 0 = automatic per frame: "
          "the smallest of 1-4 whose gather a pilot of 256 pixels finds within 5 % of the VPLs' own sum, within a visit "
          "budget for the VPL count", **_LIT,
          range=Range(0), label="LGH alpha", metavar="ALPHA", applies=_GI_LGH,
          source="paper 004 uses 1; automatic: measured on the suite's tuning stages (docs/gi.md)"),
    Param("lgh_cpu_kernel", str, "auto", "how the LGH's gather and shadow-ray targets run on a CPU: auto (the "
          "compiled kernels when they were built, else Warp), native (compiled; an error without them) or warp",
          **_LIT, choices=("auto", "native", "warp"), applies=_ANY_LGH, source="measured (usdml): docs/gi.md"),
    Param("lgh_levels", int, 0, "LGH levels; 0 = the paper's rule (the most whose S1 has under half as many "
          "lights as VPLs)", **_LIT, range=Range(0), label="LGH levels", metavar="N", applies=_ANY_LGH,
          source="paper 004"),
    Param("lgh_start_level", int, 0, "finest LGH level lit from: 1 = S1 as the paper, 0 = the VPLs themselves (S0)",
          **_LIT, choices=(0, 1), label="LGH start level", applies=_GI_LGH,
          source="paper 004 starts from S1 (Sec. 4.1); S0 measured better on every tuning stage (docs/gi.md)"),
    Param("lgh_split", str, "auto", "one LGH over all VPLs (none, the paper), one per VPL normal class on one grid "
          "(normal: a coarse grid light never merges VPLs facing different ways), every VPL its own light (each: "
          "the hierarchy's limit, summed exactly), or auto: per frame, the cheapest of these whose pilot is "
          "within target (each where no hierarchy's alpha costs less)",
          **_LIT, choices=("auto", "none", "normal", "each"), label="LGH split", applies=_GI_LGH,
          source="paper 004 builds one; auto measured on the suite's tuning stages (docs/gi.md)"),
    Param("gi_svo_skip", float, 0.5, "--gi svo: pairs whose light is below this fraction of the pixel's mean cast "
          "no shadow ray and count as seen as much as the pixel's traced light (0 = trace every pair with G > 0)",
          **_LIT, range=Range(0), metavar="FRACTION", applies=_GI_SVO,
          source="paper 003, Sec. 3.2 (skip faint VPLs); 0.5 measured (docs/gi.md)"),
    Param("interleave", int, 1, "interleaved sampling tile size: each pixel of an n x n tile gathers 1/n^2 of the "
          "grid lights (1 = off)", **_LIT, attribute="usdml:lgh:interleave", choices=(1, 2, 4), applies=_GI_LGH,
          source="paper 004, Sec. 4 (off by default)"),
    Param("shadow_samples", int, 0, "stochastic shadow samples per pixel; 0 = automatic per frame: 4, 16 or 64, "
          "more for more VPLs", **_LIT, range=Range(0), metavar="N", applies=_GI_LGH,
          source="paper 004 uses 4; automatic: measured on the suite's tuning stages (docs/gi.md)"),
    Param("shadow_filter_iterations", int, -1, "a-trous iterations over the stochastic shadows; 0 = unfiltered, "
          "-1 = by the samples (3 at 4 per pixel, one fewer per 4x more, none from 256)", **_LIT, range=Range(-1, 10),
          metavar="N", applies=_ANY_LGH, source="paper 004, Sec. 3.3; -1: the best measured on cornell and city"),
    Param("shadow_targets", str, "member", "LGH shadow rays to a VPL of the chosen grid light, weighed by its own "
          "irradiance (member) or by the grid light's (cluster), or to the grid light's centre jittered by its "
          "variance (jitter, as paper 004)", **_LIT, choices=("member", "cluster", "jitter"), applies=_GI_LGH,
          source="measured (usdml): jitter over-occludes; member beats cluster on cornell and city"),
    # -- sampling
    Param("dome_samples", int, 256, "distant lights each DomeLight is importance-sampled into per frame", **_LIT,
          range=Range(1), metavar="K", source="measured (usdml.lighting.dome): 1.0 % mean irradiance error at 256"),
    Param("pixel_samples", int, 4, "primary rays per pixel, a square number (an s x s stratified grid, box "
          "filter); 1 = the pixel centre", (RENDER,), LIGHTING, attribute="usdml:pixelSamples", metavar="N",
          valid=_square, rule=_SQUARE_RULE, source="measured (usdml): halves edge error at 4"),
    Param("seed", int, 0, "random seed (VPLs, shadow samples, dome light sampling)", **_LIT, range=Range(0),
          metavar="N"),
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
    "voxel_resolution": """Voxels per axis of each direction voxelization (paper 000 uses 128).

    Each voxelization holds resolution^3 bits: at 128 and a 2 degree
    direction step, the 90 x 90 array takes just under 2 GB.""",
    "direction_step": """Angular increment k, in degrees, of the (theta, phi) grid of voxelization directions (paper 000 uses 2).

    theta and phi each run from 0 to 180 degrees in steps of k, so k = 2
    gives 90 x 90 voxelizations; a ray uses the voxelization whose row
    direction is closest to its own.""",
    "fully_dynamic": """Re-voxelize the whole scene every frame, for scenes where much moves or deforms (paper 000, Algorithm 5).

    Each frame one voxelization is computed and rotated with two degrees
    of freedom to approximate the whole array, as paper 000 does for its
    amusement park. When false, the static scene is voxelized once and
    rigid instances reuse their prototype's voxelizations by transforming
    rays into prototype space (paper 000, Algorithm 4).""",
    "voxel_rebuild": """How voxel arrays rebuilt every frame (deforming meshes, or the whole scene when fullyDynamic) are made: rotate or geometry.

    "rotate" voxelizes the frame's geometry once and fills every other
    direction by rotating it (paper 000, Algorithm 5); "geometry"
    voxelizes every direction from the geometry (Algorithm 1), slower
    and more accurate.""",
    "voxel_mapping": """How a rotated voxel marks the target voxelization in Algorithm 5: point or conservative.

    "point" (the paper) sets the voxel holding the rotated voxel's
    centre, leaving some holes in tilted surfaces; "conservative" sets
    every voxel the rotated voxel overlaps: no holes, thicker surfaces,
    slower.""",
    "voxel_normal_offset": """Voxels (of the static array, in world units) a shadow ray starts off its surface, along the normal turned toward the light.

    Occluders closer than about normalOffset + slab voxels to the shading
    point do not shadow.""",
    "voxel_cpu_kernel": """How voxel shadow queries run on a CPU: auto, native or warp.

    "native" is the compiled kernel built at install (8 queries at a
    time with AVX2 when the CPU has it, else one at a time); "warp" the
    Warp kernels (also what a GPU runs); "auto" the compiled kernel when
    it was built, else Warp.""",
    "voxel_frame_core": """Voxelization rule of per-frame arrays rebuilt from geometry (rebuild = geometry), as core.""",
    "svo_resolution": """Voxels per axis of the sparse voxel octree (svo backend), a power of two from 16 to 2048.

    0 picks the paper's: 128 for a room (a scene at most 20 m across by
    its metersPerUnit, like the paper's Cornell box), 256 for a larger
    scene (its Sponza).""",
    "insm_count": """Depth images (intermediate shadow maps) per frame, insm backend.

    10 are the paper's: the midpoints of the box's eight non-vertical
    edges and the centres of its left and right faces; other counts
    take a prefix of one fixed order of 26 (docs/insm.md).""",
    "direct": """Direct lighting: all shades every pixel against every light; lgh puts the stage's point, sphere, disk and rect lights in a lighting grid hierarchy (paper 004) and shades it with importance-sampled, filtered shadow rays through the visibility backend.

    Distant and dome lights, cylinder lights, lights with a shaping cone or
    focus and lights with shadows off stay every-light under lgh. lgh pays
    from about ten thousand lights (docs/lgh-direct.md); it uses the
    usdml:lgh:alpha, usdml:lgh:levels and usdml:shadow:filterIterations
    settings, and usdml:direct:shadowSamples.""",
    "direct_alpha": """--direct lgh: blending radius factor alpha of the hierarchy over the stage's lights, r_l = alpha h_l; the lights within alpha h_1 of a point light it themselves.

    Larger alpha: more lights exact and finer grid lights farther out (less
    error in the light and in its shadows), more lights visited per pixel.""",
    "direct_gather": """--direct lgh: what each pixel gathers its light from: the hierarchy over the grid lights (hierarchy, paper 004), every grid light itself (each), or a choice per frame (auto).

    each is the hierarchy's limit: every light's unshadowed term summed
    exactly (sixteen lights at a time, compiled), and the shadow rays
    drawn among the lights in proportion to each one's own light at the
    pixel, so only the shadows' noise is left. Its cost grows with the
    number of lights, the hierarchy's with the lights near each pixel:
    auto takes each on a CPU where a pixel's sum over every light costs
    less than the hierarchy's gather at usdml:direct:alpha (the lights it
    visits, counted on a few pixels of the frame), and the hierarchy on a
    GPU or where the extension is not built (docs/lgh-direct.md).""",
    "direct_shadow_samples": """--direct lgh: stochastic shadow rays per pixel, shared by its primary rays (usdml:pixelSamples 4: a quarter each), importance-sampled from the lights and grid lights that reach them (paper 004, Appendix A); 0 chooses them per frame.

    More samples, less shadow noise: it falls as one over the square root
    of the count, and most of lgh's error is this noise (the hierarchy's
    own is about a fifth of it at 64). How much noise a count leaves
    depends on the stage, so by default (0) the frame measures it: 512
    points of its first pass are shaded twice with 64 rays and other
    seeds, and the count k = 64 (noise / usdml:direct:shadowNoise)^2 is
    taken, at least 64 (the shadow AOV, the blocked fraction of the
    lights, stays as sharp as it was), at most one ray per 100 of the
    stage's grid lights (the speed headroom over every-light shading) and
    at most 1,024; under 6,400 grid lights 64 with no pilot. A value
    above 0 is used as given. The shadows are
    not filtered unless usdml:shadow:filterIterations is set: on the city
    at night the filter blurred more shadow than it removed noise
    (docs/lgh-direct.md).""",
    "direct_shadow_noise": """--direct lgh with usdml:direct:shadowSamples 0: the relative noise of the shadows (its RMS over the pixels and channels, over the frame's mean light) the shadow rays per pixel are chosen for.

    The default, 1/32 (about 3 %), keeps every-light shading within 5 %
    on the suite's stages; it is measured per frame from two pilot
    renders of the same points. The total error adds the hierarchy's own
    (about 1 % at alpha 4) in quadrature. Halving it costs four times the
    shadow rays.""",
    "gi": """Global illumination: none, lgh (VPLs through a lighting grid hierarchy, paper 004), svo (each pixel of a 4x4 interleaved tile gathers a sixteenth of the VPLs with sparse voxel octree shadow rays, then a geometry-aware filter, paper 003) or vpl-bruteforce (every VPL with exact visibility, the reference).

    Indirect light lands in the indirect AOV and is added to color. Paper 003 (svo) gathers
    512 to 2,048 first-bounce VPLs: usdml:vpl:count 1024, usdml:vpl:bounces 1.""",
    "vpl_count": """Virtual point lights generated per frame (paper 004 uses 100K).""",
    "vpl_bounces": """Diffuse bounces of the light paths that place VPLs (paper 004 traces up to three).""",
    "lgh_alpha": """Lighting grid hierarchy blending radius factor alpha, r_l = alpha h_l (paper 004 uses 1); 0 chooses it per frame.

    h_l is the grid size of level l. Larger alpha widens the blending
    functions: more grid lights per shading point, more accurate and
    slower. 0 (automatic): the smallest alpha from 1 to 4 whose
    unshadowed light at 256 of the frame's pixels is within 5 % (relative
    RMSE) of the VPLs' own sum there, among those whose gather visits at
    most a fixed share of the VPL count per pixel (counted on a few
    pixels of the frame), so that it stays a small part of what brute
    force costs; where none is within 5 %, the one that erred least
    (docs/gi.md).""",
    "lgh_levels": """Lighting grid hierarchy levels; 0 picks the largest count whose finest level S1 has under half as many lights as there are VPLs (paper 004).

    Any positive value forces that number of levels.""",
    "lgh_split": """One lighting grid hierarchy over all the VPLs (none, paper 004), one per VPL normal class on one grid (normal), every VPL its own light (each), or a choice per frame (auto).

    A coarse grid light over a ground and a wall merges VPLs facing up
    and sideways into one centre and one mean normal, which lights the
    ground from too low and too weakly. With normal, the VPLs facing
    along each of +-x, +-y and +-z get a hierarchy of their own on one
    grid, and the gather visits each: more accurate at the same alpha,
    and more lights to visit. With each, no grid lights: every point sums
    every VPL (the hierarchy's limit, with no error of its own) and draws
    its shadow rays among them in proportion to their light; a VPL's term
    costs about 1.5 % of a visited grid light's. auto (the
    default) takes, per frame, the cheapest alpha of the split one (then
    the single one) that a pilot finds within 5 % of every VPL's sum, and
    each where none costs less than it (on a CPU, from S0; docs/gi.md).""",
    "lgh_start_level": """Finest lighting grid hierarchy level lit from: 1 starts from S1 as paper 004 does (Sec. 4.1), 0 adds the VPLs themselves as level S0.

    S0 makes the near field exact (each pixel visits the VPLs within
    alpha h_1) at some extra lighting cost. Default 0: on the stages
    usdml was not tuned on, starting from S1 left most of the error
    (docs/gi.md).""",
    "gi_svo_skip": """--gi svo: (pixel, VPL) pairs whose unshadowed light is below this fraction of the mean of the pixel's pairs cast no shadow ray (paper 003 skips the V term for faint VPLs).

    Their light counts as visible in the proportion the pixel's traced
    light is. 0 traces every pair with G > 0.""",
    "interleave": """Interleaved sampling tile size n (1, 2 or 4): each pixel of an n x n tile gathers a different 1/n^2 of the grid lights (paper 004, Sec. 4).

    1 disables it.""",
    "shadow_samples": """Stochastic shadow samples per pixel (paper 004 uses 4); 0 chooses them per frame.

    Shadow rays are importance-sampled from the lights that contribute to
    the pixel and filtered before being used as shadow ratio estimators.
    0 (automatic): 4, 16 or 64, the most within one ray per 1,000 VPLs, so
    that they stay a small part of what brute force costs; with every VPL
    its own light (--lgh-split each), one ray per 4,000 VPLs, as its draws
    follow each VPL's own light (docs/gi.md).""",
    "shadow_filter_iterations": """Iterations of the edge-avoiding a-trous filter applied to the stochastic shadows before they are used as shadow ratio estimators (paper 004, Sec. 3.3); 0 leaves them unfiltered, -1 picks by the shadow samples.

    Each iteration doubles the filter's reach (3 iterations: +-14 pixels).
    -1: 3 iterations at 4 samples per pixel, one fewer for every 4x more
    samples, none from 256 (the best measured on cornell and city); one
    fewer again with every VPL its own light (--lgh-split each).""",
    "shadow_targets": """Where an LGH shadow ray goes and how it counts: member (a VPL of the chosen grid light, drawn by luminance, the sample weighed by that VPL's own irradiance at the pixel), cluster (the same VPL, weighed by the grid light's irradiance) or jitter (the grid light's centre jittered by its stored variance, as paper 004 does).

    Grid-light centres average surface points and often lie inside
    geometry, so jittered targets over-occlude; cluster avoids that, and
    member also leaves out the VPLs that face away from the pixel.""",
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
    "seed": """Seed of usdml's random number generators (VPLs, shadow samples), for reproducible renders.""",
}

#: field name -> its row, settings only, in UsdmlSettings' field order (kept up to date by :func:`table`)
PARAMS: dict[str, Param] = {}
#: field name -> its row, the render options
OPTIONS: dict[str, Param] = {p.field: p for p in _OPTIONS}
_built_from = None      # the registry's state PARAMS was last built from


def table() -> dict[str, Param]:
    """:data:`PARAMS` as the registry stands now: ``visibility`` accepts every registered name, and the
    rows registered backends declare follow the table's own (updated in place, so every holder of
    ``PARAMS`` sees it)."""
    global _built_from
    state = registry.state()
    if state != _built_from:
        rows = (_visibility(registry.backend_names()), *_SETTINGS, *registry.backend_params())
        PARAMS.clear()
        PARAMS.update((p.field, p) for p in rows)
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
        need = " or ".join(f"{rows[f].flag} {'/'.join(values)}" for f, values in p.applies)
        here = ", ".join(f"{rows[f].flag} {getattr(settings, f)}" for f in dict(p.applies))
        out.append(f"{p.flag} is ignored: it applies with {need} (here: {here})")
    return out


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
