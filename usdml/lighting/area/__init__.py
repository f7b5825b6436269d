"""Lights with area (issue 52 item 3): rect, disk, sphere, cylinder (or its line), distant lights with an angle and
mesh-light triangles cast soft shadows, their light and shadow rays going to points sampled on them
(docs/area-lights.md).

``params`` (the parameter row, a leaf), ``sampling`` (the points on each shape, stratified and seeded per shading
point), ``shading`` (the sampled lights' direct light, :func:`usdml.lighting.area.shading.shade_area`).
"""
