"""Paper 000 Alg. 3 in Warp: every surface point against every light, with the voxel shadow rays of
:mod:`usdml.kernels.voxel.query` (``shadow_ray``), in one kernel: the same shading as
``usdml.lighting.direct.shade_direct`` (launched by ``usdml.visibility.voxel.backend.VoxelBackend.shade_direct``).

A light is a row of :class:`LightTable`; its ``flags`` are the bits below, the ones
``usdml.scene.light_table`` composes per light.
"""

import warp as wp

from usdml.kernels.voxel.query import RayRule, VoxelScene, shadow_ray

# no gradients here; -O3 and fast math, as the query kernels it calls
wp.set_module_options({"enable_backward": False, "optimization_level": 3, "fast_math": True})

#: light flag bits (``LightTable.flags``)
DISTANT = wp.constant(1)          # a direction (``pos`` unused), no inverse square
ONE_SIDED = wp.constant(2)        # emits along ``-axis`` only, cosine-weighted (disk, rect)
SHAPED = wp.constant(4)           # a cone (``cone``: cos outer, smoothstep width)
FOCUSED = wp.constant(8)          # ``focus_rgb`` weighted by cos^focus
CASTS_SHADOWS = wp.constant(16)   # its rays are shadow-tested
CYLINDER = wp.constant(32)        # a cylinder seen from the side: irradiance times sin of the axis angle


@wp.struct
class LightTable:
    """Per-light constants of :func:`light_term` (as ``usdml.scene.light_table.LightTable``; ``flags`` holds its ``LightFlag`` bits)."""

    pos: wp.array(dtype=wp.vec3)
    axis: wp.array(dtype=wp.vec3)
    flags: wp.array(dtype=wp.int32)     # DISTANT | ONE_SIDED | SHAPED | FOCUSED | CASTS_SHADOWS | CYLINDER bits
    cylinder_axis: wp.array(dtype=wp.vec3)  # unit local X of the light (the axis of a cylinder light)
    cone: wp.array(dtype=wp.vec3)       # cos outer, smoothstep width (<= 0: hard), focus exponent
    base: wp.array(dtype=wp.vec3)
    focus_rgb: wp.array(dtype=wp.vec3)
    inv_m2: float
    min_d2: float


@wp.func
def light_term(p: wp.vec3, n: wp.vec3, ng: wp.vec3, l: int, lt: LightTable, rule: RayRule,
               vs: VoxelScene) -> wp.vec4:
    """Light ``l`` at surface point ``p`` with shading normal ``n`` and geometric normal ``ng``
    (Alg. 3, lines 6-8, with shading): the unshadowed irradiance as ``usdml.lighting.direct`` computes
    it (inverse square in metres, cosine of ``n``, one-sided disk/rect, a cylinder's side seen at
    sin θ, cone with smoothstep softness, focus; nothing from behind ``ng``), and a voxel shadow ray
    leaving along ``ng`` when the light faces ``p`` and casts shadows. Returns (RGB contribution,
    code): code 0 not facing, 1 facing and visible, 2 facing and blocked (RGB 0)."""
    flags = lt.flags[l]
    dist = flags & DISTANT
    dvec = lt.pos[l] - p
    d2 = wp.dot(dvec, dvec)
    if dist != 0:
        dvec = -lt.axis[l]
        d2 = 1.0
    if d2 <= 0.0:
        return wp.vec4(0.0)
    if wp.dot(ng, dvec) <= 0.0:
        return wp.vec4(0.0)
    inv_d = 1.0 / wp.sqrt(wp.max(d2, 1.0e-30))
    cos_s = wp.dot(n, dvec) * inv_d
    if cos_s <= 0.0:
        return wp.vec4(0.0)
    g = cos_s
    if dist == 0:
        g = g * lt.inv_m2 / wp.max(d2, lt.min_d2)
    if (flags & CYLINDER) != 0:
        cos_c = wp.dot(lt.cylinder_axis[l], dvec) * inv_d
        g = g * wp.sqrt(wp.max(1.0 - cos_c * cos_c, 0.0))
    f = float(0.0)
    if (flags & (ONE_SIDED | SHAPED | FOCUSED)) != 0:
        cos_l = -wp.dot(lt.axis[l], dvec) * inv_d
        if (flags & ONE_SIDED) != 0:
            g = g * wp.max(cos_l, 0.0)
        if (flags & SHAPED) != 0:
            cone = lt.cone[l]
            if cone[1] <= 0.0:
                if cos_l < cone[0]:
                    g = 0.0
            else:
                x = wp.clamp((cos_l - cone[0]) / cone[1], 0.0, 1.0)
                g = g * x * x * (3.0 - 2.0 * x)
        if (flags & FOCUSED) != 0:
            f = wp.pow(wp.clamp(cos_l, 0.0, 1.0), lt.cone[l][2])
    if g <= 0.0:
        return wp.vec4(0.0)
    if (flags & CASTS_SHADOWS) != 0:
        tgt = lt.pos[l]
        if dist != 0:
            tgt = dvec
        if shadow_ray(vs, rule, p, tgt, ng, dist, 0) >= 0.0:
            return wp.vec4(0.0, 0.0, 0.0, 2.0)
    c = lt.base[l] * g + lt.focus_rgb[l] * (g * f)
    return wp.vec4(c[0], c[1], c[2], 1.0)


@wp.kernel
def shade_tiles(points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                geometric: wp.array(dtype=wp.vec3), first: int, tile: int, lt: LightTable, rule: RayRule,
                vs: VoxelScene,
                radiance: wp.array(dtype=wp.vec3), blocked: wp.array(dtype=wp.int32),
                facing: wp.array(dtype=wp.int32)):
    """Alg. 3 over a tile of ``tile`` spatially coherent points (``first + tid * tile …``), lights in
    the outer loop: the rays of neighbouring points to one light share a direction bin and nearby
    rows, so one light's voxelization stays in cache while the tile sweeps it (DESIGN.md's loop
    order; the per-point kernel waited on memory for almost every ray at 128³ / 2°)."""
    i0 = first + wp.tid() * tile
    i1 = wp.min(i0 + tile, points.shape[0])
    for i in range(i0, i1):
        radiance[i] = wp.vec3(0.0)
        blocked[i] = 0
        facing[i] = 0
    for l in range(lt.pos.shape[0]):
        for i in range(i0, i1):
            r = light_term(points[i], normals[i], geometric[i], l, lt, rule, vs)
            if r[3] > 0.0:
                facing[i] = facing[i] + 1
                if r[3] > 1.5:
                    blocked[i] = blocked[i] + 1
                else:
                    radiance[i] = radiance[i] + wp.vec3(r[0], r[1], r[2])
