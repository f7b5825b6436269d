"""The lighting grid hierarchy (paper 004)'s rows of the parameter table (:mod:`usdml.params`): its settings, declared with the method
and placed in the table by :mod:`usdml.params` among the lighting rows (its three parts keep the flags' order). A leaf module: it imports only :mod:`usdml.param`, so the table is built without
importing the hierarchy."""

from __future__ import annotations

from usdml.param import LIT, Param, Range

#: when the hierarchy is read: over VPLs (``--gi lgh``), over the stage's lights (``--direct lgh``), either
GI_LGH = (("gi", ("lgh",)),)
DIRECT_LGH = (("direct", ("lgh",)),)
ANY_LGH = GI_LGH + DIRECT_LGH

#: ``--direct lgh``: the hierarchy over the stage's own lights
DIRECT = (
    Param("direct_alpha", float, 4.0, "--direct lgh: blending radius factor alpha, r_l = alpha h_l (the lights "
          "themselves within alpha h_1)", **LIT, range=Range(0, low_open=True), metavar="ALPHA", applies=DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md (paper 004 uses 1 for VPLs)",
          doc="""--direct lgh: blending radius factor alpha of the hierarchy over the stage's lights, r_l = alpha h_l; the lights within alpha h_1 of a point light it themselves.

    Larger alpha: more lights exact and finer grid lights farther out (less
    error in the light and in its shadows), more lights visited per pixel."""),
    Param("direct_gather", str, "auto", "--direct lgh: what a pixel gathers from: the hierarchy (paper 004), "
          "every grid light itself summed exactly (each: the hierarchy's limit, on a CPU), or auto: per frame, "
          "each where its sum costs less than the hierarchy's gather", **LIT,
          choices=("auto", "hierarchy", "each"), applies=DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md, on stages it was not tuned on",
          doc="""--direct lgh: what each pixel gathers its light from: the hierarchy over the grid lights (hierarchy, paper 004), every grid light itself (each), or a choice per frame (auto).

    each is the hierarchy's limit: every light's unshadowed term summed
    exactly (sixteen lights at a time, compiled), and the shadow rays
    drawn among the lights in proportion to each one's own light at the
    pixel, so only the shadows' noise is left. Its cost grows with the
    number of lights, the hierarchy's with the lights near each pixel:
    auto takes each on a CPU where a pixel's sum over every light costs
    less than the hierarchy's gather at usdml:direct:alpha (the lights it
    visits, counted on a few pixels of the frame), and the hierarchy on a
    GPU or where the extension is not built (docs/lgh-direct.md)."""),
    Param("direct_shadow_samples", int, 0, "--direct lgh: shadow rays per pixel (shared by its primary rays), "
          "importance-sampled from the lights that reach it; 0: chosen per frame so that the shadows' noise is "
          "about usdml:direct:shadowNoise", **LIT, range=Range(0), metavar="N",
          applies=DIRECT_LGH, source="measured (usdml): docs/lgh-direct.md, on stages it was not tuned on",
          doc="""--direct lgh: stochastic shadow rays per pixel, shared by its primary rays (usdml:pixelSamples 4: a quarter each), importance-sampled from the lights and grid lights that reach them (paper 004, Appendix A); 0 chooses them per frame.

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
    (docs/lgh-direct.md)."""),
    Param("direct_shadow_noise", float, 0.03125, "--direct lgh with usdml:direct:shadowSamples 0: the shadows' "
          "relative noise (RMS over the frame's mean light) the frame's shadow rays are chosen for", **LIT,
          range=Range(0, 1, low_open=True), metavar="NOISE", applies=DIRECT_LGH,
          source="measured (usdml): docs/lgh-direct.md (5 % relative RMSE of every-light shading, issue 37)",
          doc="""--direct lgh with usdml:direct:shadowSamples 0: the relative noise of the shadows (its RMS over the pixels and channels, over the frame's mean light) the shadow rays per pixel are chosen for.

    The default, 1/32 (about 3 %), keeps every-light shading within 5 %
    on the suite's stages; it is measured per frame from two pilot
    renders of the same points. The total error adds the hierarchy's own
    (about 1 % at alpha 4) in quadrature. Halving it costs four times the
    shadow rays."""),
)

#: the hierarchy and its gather
HIERARCHY = (
    Param("lgh_alpha", float, 0.0, "LGH blending radius factor alpha, r_l = alpha h_l; 0 = automatic per frame: "
          "the smallest of 1-4 whose gather a pilot of 256 pixels finds within 5 % of the VPLs' own sum, within a visit "
          "budget for the VPL count", **LIT,
          range=Range(0), label="LGH alpha", metavar="ALPHA", applies=GI_LGH,
          source="paper 004 uses 1; automatic: measured on the suite's tuning stages (docs/gi.md)",
          doc="""Lighting grid hierarchy blending radius factor alpha, r_l = alpha h_l (paper 004 uses 1); 0 chooses it per frame.

    h_l is the grid size of level l. Larger alpha widens the blending
    functions: more grid lights per shading point, more accurate and
    slower. 0 (automatic): the smallest alpha from 1 to 4 whose
    unshadowed light at 256 of the frame's pixels is within 5 % (relative
    RMSE) of the VPLs' own sum there, among those whose gather visits at
    most a fixed share of the VPL count per pixel (counted on a few
    pixels of the frame), so that it stays a small part of what brute
    force costs; where none is within 5 %, the one that erred least
    (docs/gi.md)."""),
    Param("lgh_cpu_kernel", str, "auto", "how the LGH's gather and shadow-ray targets run on a CPU: auto (the "
          "compiled kernels when they were built, else Warp), native (compiled; an error without them) or warp",
          **LIT, choices=("auto", "native", "warp"), applies=ANY_LGH, source="measured (usdml): docs/gi.md"),
    Param("lgh_levels", int, 0, "LGH levels; 0 = the paper's rule (the most whose S1 has under half as many "
          "lights as VPLs)", **LIT, range=Range(0), label="LGH levels", metavar="N", applies=ANY_LGH,
          source="paper 004",
          doc="""Lighting grid hierarchy levels; 0 picks the largest count whose finest level S1 has under half as many lights as there are VPLs (paper 004).

    Any positive value forces that number of levels."""),
    Param("lgh_start_level", int, 0, "finest LGH level lit from: 1 = S1 as the paper, 0 = the VPLs themselves (S0)",
          **LIT, choices=(0, 1), label="LGH start level", applies=GI_LGH,
          source="paper 004 starts from S1 (Sec. 4.1); S0 measured better on every tuning stage (docs/gi.md)",
          doc="""Finest lighting grid hierarchy level lit from: 1 starts from S1 as paper 004 does (Sec. 4.1), 0 adds the VPLs themselves as level S0.

    S0 makes the near field exact (each pixel visits the VPLs within
    alpha h_1) at some extra lighting cost. Default 0: on the stages
    usdml was not tuned on, starting from S1 left most of the error
    (docs/gi.md)."""),
    Param("lgh_split", str, "auto", "one LGH over all VPLs (none, the paper), one per VPL normal class on one grid "
          "(normal: a coarse grid light never merges VPLs facing different ways), every VPL its own light (each: "
          "the hierarchy's limit, summed exactly), or auto: per frame, the cheapest of these whose pilot is "
          "within target (each where no hierarchy's alpha costs less)",
          **LIT, choices=("auto", "none", "normal", "each"), label="LGH split", applies=GI_LGH,
          source="paper 004 builds one; auto measured on the suite's tuning stages (docs/gi.md)",
          doc="""One lighting grid hierarchy over all the VPLs (none, paper 004), one per VPL normal class on one grid (normal), every VPL its own light (each), or a choice per frame (auto).

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
    each where none costs less than it (on a CPU, from S0; docs/gi.md)."""),
)

#: its stochastic shadows and their filter
SHADOWS = (
    Param("interleave", int, 1, "interleaved sampling tile size: each pixel of an n x n tile gathers 1/n^2 of the "
          "grid lights (1 = off)", **LIT, attribute="usdml:lgh:interleave", choices=(1, 2, 4), applies=GI_LGH,
          source="paper 004, Sec. 4 (off by default)",
          doc="""Interleaved sampling tile size n (1, 2 or 4): each pixel of an n x n tile gathers a different 1/n^2 of the grid lights (paper 004, Sec. 4).

    1 disables it."""),
    Param("shadow_samples", int, 0, "stochastic shadow samples per pixel; 0 = automatic per frame: 4, 16 or 64, "
          "more for more VPLs", **LIT, range=Range(0), metavar="N", applies=GI_LGH,
          source="paper 004 uses 4; automatic: measured on the suite's tuning stages (docs/gi.md)",
          doc="""Stochastic shadow samples per pixel (paper 004 uses 4); 0 chooses them per frame.

    Shadow rays are importance-sampled from the lights that contribute to
    the pixel and filtered before being used as shadow ratio estimators.
    0 (automatic): 4, 16 or 64, the most within one ray per 1,000 VPLs, so
    that they stay a small part of what brute force costs; with every VPL
    its own light (--lgh-split each), one ray per 4,000 VPLs, as its draws
    follow each VPL's own light (docs/gi.md)."""),
    Param("shadow_filter_iterations", int, -1, "a-trous iterations over the stochastic shadows; 0 = unfiltered, "
          "-1 = by the samples (3 at 4 per pixel, one fewer per 4x more, none from 256)", **LIT, range=Range(-1, 10),
          metavar="N", applies=ANY_LGH, source="paper 004, Sec. 3.3; -1: the best measured on cornell and city",
          doc="""Iterations of the edge-avoiding a-trous filter applied to the stochastic shadows before they are used as shadow ratio estimators (paper 004, Sec. 3.3); 0 leaves them unfiltered, -1 picks by the shadow samples.

    Each iteration doubles the filter's reach (3 iterations: +-14 pixels).
    -1: 3 iterations at 4 samples per pixel, one fewer for every 4x more
    samples, none from 256 (the best measured on cornell and city); one
    fewer again with every VPL its own light (--lgh-split each)."""),
    Param("shadow_targets", str, "member", "LGH shadow rays to a VPL of the chosen grid light, weighed by its own "
          "irradiance (member) or by the grid light's (cluster), or to the grid light's centre jittered by its "
          "variance (jitter, as paper 004)", **LIT, choices=("member", "cluster", "jitter"), applies=GI_LGH,
          source="measured (usdml): jitter over-occludes; member beats cluster on cornell and city",
          doc="""Where an LGH shadow ray goes and how it counts: member (a VPL of the chosen grid light, drawn by luminance, the sample weighed by that VPL's own irradiance at the pixel), cluster (the same VPL, weighed by the grid light's irradiance) or jitter (the grid light's centre jittered by its stored variance, as paper 004 does).

    Grid-light centres average surface points and often lie inside
    geometry, so jittered targets over-occlude; cluster avoids that, and
    member also leaves out the VPLs that face away from the pixel."""),
)
