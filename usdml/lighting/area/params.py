"""The area lights' row of the parameter table (:mod:`usdml.params`). A leaf module: it imports only
:mod:`usdml.param`, so the table is built without importing the shading."""

from __future__ import annotations

from usdml.param import LIT, Param, Range

#: points sampled on each area light per shading point: at the default 4 primary rays per pixel, 16 left a median
#: error of 2.6-3.4 % over the penumbrae against Mitsuba 3's area emitters, 8 left 3.8 % on a rect, 4 up to 10 %
#: (docs/CHANGELOG.md, "Lights with area")
LIGHT_SAMPLES = 16

SAMPLING = (
    Param("light_samples", int, LIGHT_SAMPLES, "shadow rays per shading point to points sampled on each rect, disk, "
          "sphere, cylinder, mesh or angled distant light (stratified, seeded); point lights take one", **LIT,
          range=Range(1), metavar="K",
          source="measured against Mitsuba 3 (docs/CHANGELOG.md): penumbrae within 3.4 % at 16, 10 % at 4",
          doc="""Shadow rays per shading point to points sampled on each light with area (rect, disk, sphere unless treatAsPoint, cylinder, mesh triangles, distant lights with an angle); lights without size keep one ray to their centre.

    The points are stratified over the light (a Fibonacci lattice with a
    random shift per shading point and light, seeded by usdml:seed), so
    the penumbrae are soft and their noise falls as the count grows
    (docs/area-lights.md; the changelog measures it against Mitsuba 3's
    area emitters). Each sample is a shadow ray: the cost grows with it."""),
)
