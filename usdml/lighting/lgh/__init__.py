"""The lighting grid hierarchy (paper 004) over VPLs (``--gi lgh``) and over the stage's own lights
(``--direct lgh``). docs/gi.md, docs/lgh-direct.md; kernels in ``kernels/lgh/``.

``build`` (the hierarchy, §3.1), ``shading`` (the gather with stochastic shadows, §3.2-3.3), ``choice`` (which
hierarchy a frame uses), ``each`` (every light summed, the hierarchy's limit), ``direct`` (``--direct lgh``),
``native`` (the compiled gather and sums, ``kernels/lgh/lghq.c``). The filter the shadows go through is
:mod:`usdml.lighting.atrous`, shared with ``--gi svo``.
"""
