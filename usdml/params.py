"""usdml's parameters, each declared once: one :class:`Param` row per setting.

Everything else follows from :data:`PARAMS`: the fields and defaults of
:class:`usdml.settings.UsdmlSettings`, the ``UsdmlRenderSettingsAPI`` attributes of
``schemas/schema.usda`` (written by ``tools/gen_schema.py``), the command-line flags of each command
(:func:`add_cmdline_args`, shaped like usdrecord's ``UsdAppUtils.*Args.AddCmdlineArgs``) and the one
validation, :func:`check`. A value is taken, in increasing priority, from the row's default (the
paper's), the stage's attribute on its RenderSettings prim, and the flag; so flags default to None.

A leaf module: it imports nothing of usdml but :mod:`usdml.errors` and the backend registry (for the
names ``visibility`` accepts), and no ``pxr``.
"""

from __future__ import annotations

import argparse
import inspect
import math
import numbers
from dataclasses import dataclass
from typing import Callable

from usdml.errors import UsdmlError
from usdml.visibility.registry import backend_names

#: commands whose flags come from this table; a row lists the ones that take its flag
RENDER, COMPARE, BENCH, BAKE = "render", "compare", "bench", "bake"
COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
VOXEL_COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
LIGHTING_COMMANDS = (RENDER, COMPARE)

#: image width in pixels when neither ``--imageWidth`` nor a RenderSettings resolution gives one
DEFAULT_WIDTH = 960

#: most segments --implicit-detail accepts (a sphere is about 2·detail² triangles)
MAX_IMPLICIT_DETAIL = 1024

#: most primary rays per pixel (a 32 x 32 grid)
MAX_PIXEL_SAMPLES = 1024

#: argparse's namespace attribute listing the settings fields whose flags a parser was given
_ARGS_FIELDS = "usdml_settings_fields"


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


@dataclass(frozen=True)
class Param:
    """One setting: its field, value type and default, where it is set (schema attribute, flag) and
    what it accepts.

    ``help`` is the flag's one line (argparse adds the default); ``doc`` is the schema attribute's
    documentation, whose first sentence USD keeps (``userDocBrief``; default: ``help``).
    ``choices``, ``range`` and ``valid`` (a predicate, described by ``rule``) are what :func:`check`
    accepts; ``label`` is how its messages name the value (default: the field name in words).
    ``source`` says where the default comes from.
    """

    field: str
    type: type
    default: object
    attribute: str
    flag: str
    help: str
    commands: tuple[str, ...]
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
        if self.doc:
            return inspect.cleandoc(self.doc)
        text = self.help[0].upper() + self.help[1:]
        return text if text.endswith(".") else text + "."

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


def _or(names) -> str:
    names = list(names)
    return ", ".join(names[:-1]) + f" or {names[-1]}" if len(names) > 1 else "".join(names)


_BACKENDS = backend_names()

# when the settings of one method are read (Param.applies)
_GI_LGH = (("gi", ("lgh",)),)
_DIRECT_LGH = (("direct", ("lgh",)),)
_ANY_LGH = _GI_LGH + _DIRECT_LGH
_GI = (("gi", ("lgh", "svo", "vpl-bruteforce")),)
_VOXEL = (("visibility", ("voxel",)),)
_SVO = (("visibility", ("svo",)), ("gi", ("svo",)))      # --gi svo casts its rays through an octree
_INSM = (("visibility", ("insm",)),)

#: every setting, in the order of UsdmlSettings' fields
_ROWS = (
    Param("visibility", str, "exact", "usdml:visibility", "--visibility",
          f"visibility backend for shadow rays ({', '.join(_BACKENDS)})", (RENDER,),
          choices=_BACKENDS, label="visibility backend", metavar="NAME", parser_choices=False,
          source="exact: the reference every approximate backend is checked against",
          doc=f'''Visibility backend for shadow rays: {_or(_BACKENDS)}.

          "exact" traces rays against the triangles (Embree) and is the reference
          the approximate backends are checked against; "voxel" looks rays up in
          the 2D array of per-direction voxelizations (paper 000).'''),

    # -- voxel arrays (paper 000)
    Param("voxel_resolution", int, 128, "usdml:voxel:resolution", "--voxel-resolution",
          "voxels per axis of each direction's voxelization", VOXEL_COMMANDS, source="paper 000",
          range=Range(4, 2048), metavar="N",
          doc='''Voxels per axis of each direction voxelization (paper 000 uses 128).

          Each voxelization holds resolution^3 bits: at 128 and a 2 degree
          direction step, the 90 x 90 array takes just under 2 GB.''', applies=_VOXEL),
    Param("direction_step", float, 2.0, "usdml:voxel:directionStep", "--direction-step",
          "degrees between direction bins (k in paper 000: 90 x 90 directions at 2)", VOXEL_COMMANDS,
          source="paper 000", range=Range(0.1, 90), metavar="DEG",
          doc='''Angular increment k, in degrees, of the (theta, phi) grid of voxelization directions (paper 000 uses 2).

          theta and phi each run from 0 to 180 degrees in steps of k, so k = 2
          gives 90 x 90 voxelizations; a ray uses the voxelization whose row
          direction is closest to its own.'''),
    Param("fully_dynamic", bool, False, "usdml:voxel:fullyDynamic", "--fully-dynamic",
          "voxelize the whole scene every frame (paper 000 Alg. 5) instead of a static array plus "
          "prototype arrays", VOXEL_COMMANDS, source="paper 000 (Alg. 4 unless the scene asks for Alg. 5)",
          doc='''Re-voxelize the whole scene every frame, for scenes where much moves or deforms (paper 000, Algorithm 5).

          Each frame one voxelization is computed and rotated with two degrees
          of freedom to approximate the whole array, as paper 000 does for its
          amusement park. When false, the static scene is voxelized once and
          rigid instances reuse their prototype's voxelizations by transforming
          rays into prototype space (paper 000, Algorithm 4).'''),
    Param("voxel_rebuild", str, "rotate", "usdml:voxel:rebuild", "--voxel-rebuild",
          "per-frame voxel arrays (deforming meshes, fully dynamic scenes): rotate one voxelization "
          "(paper 000 Alg. 5) or voxelize every direction (Alg. 1)", VOXEL_COMMANDS,
          source="paper 000, Alg. 5", choices=("rotate", "geometry"),
          doc='''How voxel arrays rebuilt every frame (deforming meshes, or the whole scene when fullyDynamic) are made: rotate or geometry.

          "rotate" voxelizes the frame's geometry once and fills every other
          direction by rotating it (paper 000, Algorithm 5); "geometry"
          voxelizes every direction from the geometry (Algorithm 1), slower
          and more accurate.''', applies=_VOXEL),
    Param("voxel_mapping", str, "point", "usdml:voxel:mapping", "--voxel-mapping",
          "Alg. 5: a rotated voxel sets the voxel of its centre (point, the paper) or every voxel it "
          "overlaps (conservative)", VOXEL_COMMANDS, source="paper 000, Alg. 5", choices=("point", "conservative"),
          doc='''How a rotated voxel marks the target voxelization in Algorithm 5: point or conservative.

          "point" (the paper) sets the voxel holding the rotated voxel's
          centre, leaving some holes in tilted surfaces; "conservative" sets
          every voxel the rotated voxel overlaps: no holes, thicker surfaces,
          slower.''', applies=_VOXEL),
    # leaving the surface (usdml.visibility.voxel's module doc): usdml's measured rule, not the paper's
    Param("voxel_normal_offset", float, 1.0, "usdml:voxel:normalOffset", "--voxel-normal-offset",
          "voxels (of the static array) a shadow ray starts off its surface, along the normal turned "
          "toward the light", VOXEL_COMMANDS, source="measured (usdml)", range=Range(0), metavar="VOXELS",
          doc='''Voxels (of the static array, in world units) a shadow ray starts off its surface, along the normal turned toward the light.

          Occluders closer than about normalOffset + slab voxels to the shading
          point do not shadow.''', applies=_VOXEL),
    Param("voxel_skip", float, 1.0, "usdml:voxel:skip", "--voxel-skip",
          "voxels a shadow ray ignores at its start to leave its own surface (more at grazing angles)",
          VOXEL_COMMANDS, source="measured (usdml)", range=Range(0), metavar="VOXELS", applies=_VOXEL),
    Param("voxel_slab", float, 1.0, "usdml:voxel:slab", "--voxel-slab",
          "voxels above the tangent plane a grazing shadow ray skips to (slab / sin(angle) along the ray, "
          "at most the max skip)", VOXEL_COMMANDS, source="measured (usdml)", range=Range(0), metavar="VOXELS", applies=_VOXEL),
    Param("voxel_max_skip", float, 0.0, "usdml:voxel:maxSkip", "--voxel-max-skip",
          "most voxels a grazing shadow ray skips to leave its surface; 0 = automatic: 2, or 4 with the "
          "conservative mapping", VOXEL_COMMANDS, source="measured (usdml): 2 point, 4 conservative",
          range=Range(0), metavar="VOXELS", applies=_VOXEL),
    Param("voxel_end_skip", float, 1.0, "usdml:voxel:endSkip", "--voxel-end-skip",
          "voxels a shadow ray ignores at the light's end, so a light mounted on a wall is not hidden by it",
          VOXEL_COMMANDS, source="measured (usdml)", range=Range(0), metavar="VOXELS", applies=_VOXEL),
    Param("voxel_segment", int, 32, "usdml:voxel:segment", "--voxel-segment",
          "voxels a shadow ray looks up in one row before it picks its row anew (a divisor of 32)",
          VOXEL_COMMANDS, source="one 32-bit word of a row", choices=(1, 2, 4, 8, 16, 32), applies=_VOXEL),
    Param("voxel_cpu_kernel", str, "auto", "usdml:voxel:cpuKernel", "--voxel-cpu-kernel",
          "how voxel queries run on a CPU: auto (the compiled kernel, AVX2 where the CPU has it, else Warp), "
          "native (the compiled kernel; an error without it) or warp", VOXEL_COMMANDS,
          source="measured (usdml): docs/voxel.md", choices=("auto", "native", "warp"),
          doc='''How voxel shadow queries run on a CPU: auto, native or warp.

          "native" is the compiled kernel built at install (8 queries at a
          time with AVX2 when the CPU has it, else one at a time); "warp" the
          Warp kernels (also what a GPU runs); "auto" the compiled kernel when
          it was built, else Warp.''', applies=_VOXEL),
    Param("voxel_core", float, 0.0, "usdml:voxel:core", "--voxel-core",
          "voxelization rule of the cached arrays: 0 rasterizes rows' centre lines; a fraction > 0 marks "
          "surface samples in that central part of a row", VOXEL_COMMANDS, source="measured (usdml)",
          range=Range(0, 1), metavar="FRACTION", applies=_VOXEL),
    Param("voxel_frame_core", float, 0.0, "usdml:voxel:frameCore", "--voxel-frame-core",
          "the same rule for per-frame arrays rebuilt from geometry (voxel rebuild geometry)",
          VOXEL_COMMANDS, source="measured (usdml)", range=Range(0, 1), metavar="FRACTION",
          doc="Voxelization rule of per-frame arrays rebuilt from geometry (rebuild = geometry), as core.", applies=_VOXEL),
    Param("voxel_memory_limit", float, 0.0, "usdml:voxel:memoryLimit", "--voxel-memory-limit",
          "GiB the voxel arrays may take; 0 = automatic: 80 % of the available memory", VOXEL_COMMANDS,
          source="the machine", range=Range(0), metavar="GIB", applies=_VOXEL),

    # -- sparse voxel octree (paper 003)
    Param("svo_resolution", int, 0, "usdml:svo:resolution", "--svo-resolution",
          "voxels per axis of the sparse voxel octree, a power of two; 0 = automatic: 128 for a room (at most "
          "20 m across), else 256", VOXEL_COMMANDS, source="paper 003",
          choices=(0, 16, 32, 64, 128, 256, 512, 1024, 2048),
          doc='''Voxels per axis of the sparse voxel octree (svo backend), a power of two from 16 to 2048.

          0 picks the paper's: 128 for a room (a scene at most 20 m across by
          its metersPerUnit, like the paper's Cornell box), 256 for a larger
          scene (its Sponza).''', applies=_SVO),
    Param("svo_cpu_kernel", str, "auto", "usdml:svo:cpuKernel", "--svo-cpu-kernel",
          "how SVO queries run on a CPU: auto (the compiled traversal when it was built, else Warp), native "
          "(the compiled traversal; an error without it) or warp", VOXEL_COMMANDS,
          source="measured (usdml): docs/svo.md", choices=("auto", "native", "warp"), applies=_SVO),

    # -- intermediate shadow maps (paper 001)
    Param("insm_count", int, 10, "usdml:insm:count", "--insm-count",
          "depth images (intermediate shadow maps) per frame, from viewpoints on the scene's box", VOXEL_COMMANDS,
          source="paper 001, Table 4", range=Range(1, 26), metavar="K",
          doc='''Depth images (intermediate shadow maps) per frame, insm backend.

          10 are the paper's: the midpoints of the box's eight non-vertical
          edges and the centres of its left and right faces; other counts
          take a prefix of one fixed order of 26 (docs/insm.md).''', applies=_INSM),
    Param("insm_resolution", int, 128, "usdml:insm:resolution", "--insm-resolution",
          "pixels per side of each depth image", VOXEL_COMMANDS, source="paper 001, Table 2",
          range=Range(8, 4096), metavar="W", applies=_INSM),
    Param("insm_light_resolution", int, 512, "usdml:insm:lightResolution", "--insm-light-resolution",
          "texels per side of each view of a light's shadow map (six views for a point light)", VOXEL_COMMANDS,
          source="paper 001, Table 3", range=Range(16, 8192), metavar="S", applies=_INSM),
    Param("insm_threshold", float, 2.0, "usdml:insm:threshold", "--insm-threshold",
          "depth-discontinuity threshold of the triangulation, in pixel footprints of the depth image",
          VOXEL_COMMANDS, source="paper 001, Alg. 2 (scene-dependent there; measured: docs/insm.md)",
          range=Range(0, low_open=True), metavar="PIXELS", applies=_INSM),

    Param("insm_cpu_kernel", str, "auto", "usdml:insm:cpuKernel", "--insm-cpu-kernel",
          "how the per-light maps run on a CPU: auto (the compiled maps when they were built, else Warp), native "
          "(the compiled maps; an error without them) or warp", VOXEL_COMMANDS,
          source="measured (usdml): docs/insm.md", choices=("auto", "native", "warp"), applies=_INSM),

    # -- direct light from many lights (paper 004 over the stage's own lights)
    Param("direct", str, "all", "usdml:direct", "--direct",
          "direct light: every pixel against every light (all), or the stage's point, sphere, disk and rect "
          "lights through a lighting grid hierarchy with stochastic, filtered shadows (lgh, paper 004; the "
          "other lights every-light)", LIGHTING_COMMANDS, choices=("all", "lgh"), label="direct lighting",
          source="all: exact; lgh is for tens of thousands of lights and more (measured: docs/lgh-direct.md)",
          doc='''Direct lighting: all shades every pixel against every light; lgh puts the stage's point, sphere, disk and rect lights in a lighting grid hierarchy (paper 004) and shades it with importance-sampled, filtered shadow rays through the visibility backend.

          Distant and dome lights, cylinder lights, lights with a shaping cone or
          focus and lights with shadows off stay every-light under lgh. lgh pays
          from about ten thousand lights (docs/lgh-direct.md); it uses the
          usdml:lgh:alpha, usdml:lgh:levels and usdml:shadow:filterIterations
          settings, and usdml:direct:shadowSamples.'''),
    Param("direct_alpha", float, 4.0, "usdml:direct:alpha", "--direct-alpha",
          "--direct lgh: blending radius factor alpha, r_l = alpha h_l (the lights themselves within alpha h_1)",
          LIGHTING_COMMANDS, source="measured (usdml): docs/lgh-direct.md (paper 004 uses 1 for VPLs)",
          range=Range(0, low_open=True), metavar="ALPHA",
          doc='''--direct lgh: blending radius factor alpha of the hierarchy over the stage's lights, r_l = alpha h_l; the lights within alpha h_1 of a point light it themselves.

          Larger alpha: more lights exact and finer grid lights farther out (less
          error in the light and in its shadows), more lights visited per pixel.''', applies=_DIRECT_LGH),
    Param("direct_shadow_samples", int, 64, "usdml:direct:shadowSamples", "--direct-shadow-samples",
          "--direct lgh: shadow rays per pixel (shared by its primary rays), importance-sampled from the lights "
          "that reach it",
          LIGHTING_COMMANDS, source="measured (usdml): docs/lgh-direct.md", range=Range(1), metavar="N",
          doc='''--direct lgh: stochastic shadow rays per pixel, shared by its primary rays (usdml:pixelSamples 4: a quarter each), importance-sampled from the lights and grid lights that reach them (paper 004, Appendix A).

          More samples, less shadow noise. The shadows are not filtered unless
          usdml:shadow:filterIterations is set: on the city at night the filter
          blurred more shadow than it removed noise (docs/lgh-direct.md).''', applies=_DIRECT_LGH),

    # -- global illumination (papers 004 and 003)
    Param("gi", str, "none", "usdml:gi", "--gi",
          "indirect light: VPLs through a lighting grid hierarchy (lgh, paper 004), a sixteenth of the VPLs "
          "per pixel in 4x4 interleaved tiles with SVO shadow rays, filtered (svo, paper 003), or every VPL "
          "with exact visibility (vpl-bruteforce, the reference)", LIGHTING_COMMANDS,
          choices=("none", "lgh", "svo", "vpl-bruteforce"), label="global illumination",
          source="off unless asked for",
          doc='''Global illumination: none, lgh (VPLs through a lighting grid hierarchy, paper 004), svo (each pixel of a 4x4 interleaved tile gathers a sixteenth of the VPLs with sparse voxel octree shadow rays, then a geometry-aware filter, paper 003) or vpl-bruteforce (every VPL with exact visibility, the reference).

          Indirect light lands in the indirect AOV and is added to color. Paper 003 (svo) gathers
          512 to 2,048 first-bounce VPLs: usdml:vpl:count 1024, usdml:vpl:bounces 1.'''),
    Param("vpl_count", int, 100_000, "usdml:vpl:count", "--vpls", "virtual point lights per frame",
          LIGHTING_COMMANDS, source="paper 004", range=Range(1), label="VPL count", metavar="N",
          doc="Virtual point lights generated per frame (paper 004 uses 100K).", applies=_GI),
    Param("vpl_bounces", int, 3, "usdml:vpl:bounces", "--vpl-bounces",
          "diffuse bounces of the light paths that place VPLs", LIGHTING_COMMANDS, source="paper 004",
          range=Range(1), label="VPL bounces", metavar="N",
          doc="Diffuse bounces of the light paths that place VPLs (paper 004 traces up to three).", applies=_GI),
    Param("lgh_alpha", float, 1.0, "usdml:lgh:alpha", "--lgh-alpha",
          "LGH blending radius factor alpha, r_l = alpha h_l", LIGHTING_COMMANDS, source="paper 004",
          range=Range(0, low_open=True), label="LGH alpha", metavar="ALPHA",
          doc='''Lighting grid hierarchy blending radius factor alpha, r_l = alpha h_l (paper 004 uses 1).

          h_l is the grid size of level l. Larger alpha widens the blending
          functions: more grid lights per shading point, more accurate and
          slower.''', applies=_GI_LGH),
    Param("lgh_cpu_kernel", str, "auto", "usdml:lgh:cpuKernel", "--lgh-cpu-kernel",
          "how the LGH's gather and shadow-ray targets run on a CPU: auto (the compiled kernels when they were "
          "built, else Warp), native (compiled; an error without them) or warp", LIGHTING_COMMANDS,
          source="measured (usdml): docs/gi.md", choices=("auto", "native", "warp"), applies=_ANY_LGH),
    Param("lgh_levels", int, 0, "usdml:lgh:levels", "--lgh-levels",
          "LGH levels; 0 = the paper's rule (the most whose S1 has under half as many lights as VPLs)",
          LIGHTING_COMMANDS, source="paper 004", range=Range(0), label="LGH levels", metavar="N",
          doc='''Lighting grid hierarchy levels; 0 picks the largest count whose finest level S1 has under half as many lights as there are VPLs (paper 004).

          Any positive value forces that number of levels.''', applies=_ANY_LGH),
    Param("lgh_start_level", int, 1, "usdml:lgh:startLevel", "--lgh-start-level",
          "finest LGH level lit from: 1 = S1 as the paper, 0 = the VPLs themselves (S0)", LIGHTING_COMMANDS,
          source="paper 004, Sec. 4.1", choices=(0, 1), label="LGH start level",
          doc='''Finest lighting grid hierarchy level lit from: 1 starts from S1 as paper 004 does (Sec. 4.1), 0 adds the VPLs themselves as level S0.

          S0 makes the near field exact (each pixel visits the VPLs within
          alpha h_1) at some extra lighting cost.''', applies=_GI_LGH),
    Param("gi_svo_skip", float, 0.5, "usdml:gi:svoSkip", "--gi-svo-skip",
          "--gi svo: pairs whose light is below this fraction of the pixel's mean cast no shadow ray and count "
          "as seen as much as the pixel's traced light (0 = trace every pair with G > 0)", LIGHTING_COMMANDS,
          source="paper 003, Sec. 3.2 (skip faint VPLs); 0.5 measured (docs/gi.md)", range=Range(0), metavar="FRACTION",
          doc='''--gi svo: (pixel, VPL) pairs whose unshadowed light is below this fraction of the mean of the pixel's pairs cast no shadow ray (paper 003 skips the V term for faint VPLs).

          Their light counts as visible in the proportion the pixel's traced
          light is. 0 traces every pair with G > 0.''', applies=(("gi", ("svo",)),)),
    Param("interleave", int, 1, "usdml:lgh:interleave", "--interleave",
          "interleaved sampling tile size: each pixel of an n x n tile gathers 1/n^2 of the grid lights "
          "(1 = off)", LIGHTING_COMMANDS, source="paper 004, Sec. 4 (off by default)", choices=(1, 2, 4),
          doc='''Interleaved sampling tile size n (1, 2 or 4): each pixel of an n x n tile gathers a different 1/n^2 of the grid lights (paper 004, Sec. 4).

          1 disables it.''', applies=_GI_LGH),
    Param("shadow_samples", int, 4, "usdml:shadow:samples", "--shadow-samples",
          "stochastic shadow samples per pixel", LIGHTING_COMMANDS, source="paper 004", range=Range(1),
          metavar="N",
          doc='''Stochastic shadow samples per pixel (paper 004 uses 4).

          Shadow rays are importance-sampled from the lights that contribute to
          the pixel and filtered before being used as shadow ratio estimators.''', applies=_GI_LGH),
    Param("shadow_filter_iterations", int, -1, "usdml:shadow:filterIterations", "--shadow-filter-iterations",
          "a-trous iterations over the stochastic shadows; 0 = unfiltered, -1 = by the samples (3 at 4 per "
          "pixel, one fewer per 4x more, none from 256)", LIGHTING_COMMANDS,
          source="paper 004, Sec. 3.3; -1: the best measured on cornell and city", range=Range(-1, 10), metavar="N",
          doc='''Iterations of the edge-avoiding a-trous filter applied to the stochastic shadows before they are used as shadow ratio estimators (paper 004, Sec. 3.3); 0 leaves them unfiltered, -1 picks by the shadow samples.

          Each iteration doubles the filter's reach (3 iterations: +-14 pixels).
          -1: 3 iterations at 4 samples per pixel, one fewer for every 4x more
          samples, none from 256 (the best measured on cornell and city).''', applies=_ANY_LGH),
    Param("shadow_targets", str, "member", "usdml:shadow:targets", "--shadow-targets",
          "LGH shadow rays to a VPL of the chosen grid light, weighed by its own irradiance (member) or by "
          "the grid light's (cluster), or to the grid light's centre jittered by its variance (jitter, as "
          "paper 004)", LIGHTING_COMMANDS,
          source="measured (usdml): jitter over-occludes; member beats cluster on cornell and city",
          choices=("member", "cluster", "jitter"),
          doc='''Where an LGH shadow ray goes and how it counts: member (a VPL of the chosen grid light, drawn by luminance, the sample weighed by that VPL's own irradiance at the pixel), cluster (the same VPL, weighed by the grid light's irradiance) or jitter (the grid light's centre jittered by its stored variance, as paper 004 does).

          Grid-light centres average surface points and often lie inside
          geometry, so jittered targets over-occlude; cluster avoids that, and
          member also leaves out the VPLs that face away from the pixel.''', applies=_GI_LGH),

    # -- sampling
    Param("dome_samples", int, 256, "usdml:dome:samples", "--dome-samples",
          "distant lights each DomeLight is importance-sampled into per frame", LIGHTING_COMMANDS,
          source="measured (usdml.lighting.dome): 1.0 % mean irradiance error at 256", range=Range(1),
          metavar="K",
          doc='''Distant lights each DomeLight is importance-sampled into per frame.

          Each becomes a distant light with the many-light visibility of every
          other light; at 256 the mean irradiance error of a sun-and-sky map is
          about 1 percent.'''),
    Param("pixel_samples", int, 4, "usdml:pixelSamples", "--pixel-samples",
          "primary rays per pixel, a square number (an s x s stratified grid, box filter); 1 = the pixel centre",
          (RENDER,), source="measured (usdml): halves edge error at 4", metavar="N",
          valid=_square, rule=f"a square number from 1 to {MAX_PIXEL_SAMPLES} (1, 4, 9, 16, ...: an s x s "
                              f"stratified grid)",
          doc='''Primary rays per pixel, a square number n = s x s (correlated multi-jittered: one ray in each cell of an s x s grid over the pixel and in each of its n thin rows and columns), combined with a box filter: color, direct, indirect, shadow, albedo and lightCount are averaged; depth, positions, normals and ids come from the ray nearest the pixel centre.

          1 traces the pixel centre only (no anti-aliasing). The default 4 halves
          the per-pixel error of edges and shadow boundaries for about 4x the
          shading time; 16 comes within about 3.5 percent of a pixel-integrated
          render.'''),
    Param("seed", int, 0, "usdml:seed", "--seed",
          "random seed (VPLs, shadow samples, dome light sampling)", LIGHTING_COMMANDS, range=Range(0), metavar="N",
          doc="Seed of usdml's random number generators (VPLs, shadow samples), for reproducible renders."),
)

#: field name -> its row, in UsdmlSettings' field order
PARAMS: dict[str, Param] = {p.field: p for p in _ROWS}


def check(name: str, value, keyword: bool = False):
    """``value`` if setting ``name`` (a :data:`PARAMS` field) accepts it; else a one-line
    :class:`UsdmlError` naming the setting by its flag and schema attribute (``keyword``: by the
    Python keyword, ``name``, and the attribute: a script's message)."""
    param = PARAMS.get(name)
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
    out = []
    for name in given:
        p = PARAMS[name]
        if p.applies is None or any(getattr(settings, f) in values for f, values in p.applies):
            continue
        need = " or ".join(f"{PARAMS[f].flag} {'/'.join(values)}" for f, values in p.applies)
        here = ", ".join(f"{PARAMS[f].flag} {getattr(settings, f)}" for f in dict(p.applies))
        out.append(f"{p.flag} is ignored: it applies with {need} (here: {here})")
    return out


def default_help(param: Param) -> str:
    """Flag help ending in where the default comes from: the stage's attribute, else the table's."""
    default = param.default
    shown = ("on" if default else "off") if param.type is bool else f"{default:g}" if param.type is float else default
    return f"{param.help} (default: the stage's {param.attribute}, else {shown})".replace("%", "%%")


#: the help's group of visibility flags: the backend and each backend's own settings
VISIBILITY_GROUP = "visibility (usdml:visibility, usdml:voxel:*, usdml:svo:*, usdml:insm:*)"
_VISIBILITY_ATTRS = ("usdml:voxel:", "usdml:svo:", "usdml:insm:")


def add_cmdline_args(parser: argparse.ArgumentParser, command: str) -> None:
    """Add the flags of every setting ``command`` takes, in groups (voxel arrays, lighting and sampling).

    Each flag stores into the setting's field name and defaults to None, so the stage's value stays
    unless the flag is given; :func:`overrides_from_args` collects what was given.
    """
    if command not in COMMANDS:
        raise ValueError(f"unknown command {command!r}; the table knows {', '.join(COMMANDS)}")
    rows = [p for p in PARAMS.values() if command in p.commands]
    groups = {}
    for p in rows:
        title = (VISIBILITY_GROUP if p.attribute == "usdml:visibility" or p.attribute.startswith(_VISIBILITY_ATTRS)
                 else "lighting and sampling (usdml:gi, usdml:vpl:*, usdml:lgh:*, usdml:shadow:* ...)")
        group = groups.get(title) or groups.setdefault(title, parser.add_argument_group(title))
        kw = {"dest": p.field, "default": None, "help": default_help(p)}
        if p.type is bool:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw["type"] = p.type
            if p.choices and p.parser_choices:
                kw["choices"] = p.choices
            if p.metavar:
                kw["metavar"] = p.metavar
        group.add_argument(p.flag, **kw)
    parser.set_defaults(**{_ARGS_FIELDS: tuple(p.field for p in rows)})


def overrides_from_args(args: argparse.Namespace) -> dict:
    """The settings the command line gave (field -> value), for ``UsdmlSettings.updated``."""
    values = {f: getattr(args, f, None) for f in getattr(args, _ARGS_FIELDS, ())}
    return {f: v for f, v in values.items() if v is not None}


__all__ = ["COMMANDS", "DEFAULT_WIDTH", "MAX_IMPLICIT_DETAIL", "MAX_PIXEL_SAMPLES", "PARAMS", "Param", "Range", "add_cmdline_args", "check",
           "default_help", "ignored", "overrides_from_args"]
