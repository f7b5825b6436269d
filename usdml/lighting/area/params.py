"""The area lights' row of the parameter table (:mod:`usdml.params`). A leaf module: it imports only
:mod:`usdml.param`, so the table is built without importing the shading."""

from __future__ import annotations

from usdml.param import LIT, Param, Range

#: points sampled on each area light per shading point (docs/area-lights.md: measured against Mitsuba 3)
LIGHT_SAMPLES = 16

SAMPLING = (
    Param("light_samples", int, LIGHT_SAMPLES, "shadow rays per shading point to points sampled on each rect, disk, "
          "sphere, cylinder, mesh or angled distant light (stratified, seeded); point lights take one", **LIT,
          range=Range(1), metavar="K", source="measured (docs/area-lights.md): penumbrae within 6 % of Mitsuba 3",
          doc="""Shadow rays per shading point to points sampled on each light with area (rect, disk, sphere unless treatAsPoint, cylinder, mesh triangles, distant lights with an angle); lights without size keep one ray to their centre.

    The points are stratified over the light (a Fibonacci lattice with a
    random shift per shading point and light, seeded by usdml:seed), so
    the penumbrae are soft and their noise falls as the count grows
    (docs/area-lights.md measures it against Mitsuba 3's area emitters)."""),
)
