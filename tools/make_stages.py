#!/usr/bin/env python
"""Generate the usdml sample stages (deterministic, procedural).

Usage::

    python tools/make_stages.py [--out stages]

Writes eight top-level ``.usda`` stages plus binary ``.usdc`` layers::

    city.usda      static instanced city, 1,024 animated point lights
    planes.usda    sublayers city.usda, adds two airplanes flying over it
    creature.usda  UsdSkel-rigged bear (warp's bear.usd, 254k triangles) walking, 1,024 lights
    cornell.usda   classic Cornell box lit by two spot lights
    park.usda      amusement park, 112 moving rigid instances, 7,088 lights
    boxes.usda     25 plain boxes under 16 point lights, for independent renderers
    dragon.usda    Stanford dragon (48k triangles) on a ground, 1,024 static lights
                   on a dome (paper 001's Dragon scene)
    city_night.usda  sublayers city.usda, its bulbs off and 100,000 static street
                   lamps instead (paper 004's many lights)
    assets/*.usdc  heavy meshes (buildings, airplane, rigged bear, dragon)
    anim/*.usdc    heavy time samples (instancer positions / orientations),
                   sublayered under the .usda that defines the prims

The dragon is read from ``../shared/assets/meshes/dragon_vrip_res3.ply`` beside the
checkout; where that file is absent the dragon is skipped with a message (its
committed files are left as they are, and ``--check`` does not compare them).

Conventions shared by every stage (``stage_build.py``): metersPerUnit = 1, upAxis = Y, 24 fps,
defaultPrim </World>, camera </World/main_cam> (35 mm lens on a 36 x 20.25 mm
16:9 back), render settings at </Render/Settings> (named by the
``renderSettingsPrimPath`` stage metadata) with one product and six AOVs.

Lights: many-light sets are a UsdGeom.PointInstancer whose prototypes are
UsdLux.SphereLights with treatAsPoint = true and normalize = false, so
``intensity`` is the radiance L of a bulb of radius r, i.e. radiant intensity
I = L * pi * r^2.  Intensities are calibrated (``calibrate_intensity``) so the
*unshadowed* direct radiance leaving an albedo-0.5 Lambertian surface at
representative sample points averages a target (~0.3), rounded to 2
significant digits.

Everything is seeded; no timestamps are written, and every computed value is
rounded before it is written (``settled``: matrices to 1e-9, positions to 1e-5
scene units), so re-running reproduces the files with any numpy, on any machine.
``--check`` regenerates into a scratch folder and compares layer by layer: the same
specs and fields, numbers within ``CHECK_TOLERANCE`` (a last-digit flip of a settled
value passes; a moved point, light or frame does not).
"""
import argparse
import math
import os
import sys
import tempfile

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdSkel, Vt

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from stage_build import (BULBS, UP, MeshBuilder, add_anim_layer, axis_angle_quat, basis_quat,  # noqa: E402
                         calibrate_intensity, define_camera, define_light_instancer, define_mesh,
                         define_render_settings, frame_times, new_stage, quat_mul, regular_polygon, remove,
                         round_sig, set_camera_xform, set_display_color, set_instancer_xforms, settled,
                         settled_points, unit, write_asset, yaw_quats)


# --------------------------------------------------------------------------
# City: building assets
# --------------------------------------------------------------------------

GLASS = (0.10, 0.15, 0.22)


def add_facade(mb, origin, u, n, width, y0, floors, floor_h, bays, wall, reveal,
               glass=GLASS, win_w=0.6, win_h=0.55, sill=0.3, depth=0.25):
    """Facade grid with recessed windows.

    Each bay x floor cell is 4 wall strips framing the opening, 4 reveal
    quads (sill, head, jambs) stepping ``depth`` back, and a glass pane.
    Cells share edges so the facade is one watertight sheet.
    """
    origin, u, n = (np.asarray(a, dtype=float) for a in (origin, u, n))
    cw = width / bays
    s0, s1 = cw * (1 - win_w) / 2, cw * (1 + win_w) / 2
    t0, t1 = floor_h * sill, floor_h * (sill + win_h)
    for f in range(floors):
        for b in range(bays):
            base = origin + u * (b * cw) + UP * (y0 + f * floor_h)

            def p(s, t, d=0.0):
                return base + u * s + UP * t - n * d

            h = floor_h
            mb.add_poly([p(0, 0), p(cw, 0), p(cw, t0), p(0, t0)], wall, n)
            mb.add_poly([p(0, t1), p(cw, t1), p(cw, h), p(0, h)], wall, n)
            mb.add_poly([p(0, t0), p(s0, t0), p(s0, t1), p(0, t1)], wall, n)
            mb.add_poly([p(s1, t0), p(cw, t0), p(cw, t1), p(s1, t1)], wall, n)
            d = depth
            mb.add_poly([p(s0, t0), p(s1, t0), p(s1, t0, d), p(s0, t0, d)], reveal, UP)
            mb.add_poly([p(s0, t1), p(s1, t1), p(s1, t1, d), p(s0, t1, d)], reveal, -UP)
            mb.add_poly([p(s0, t0), p(s0, t1), p(s0, t1, d), p(s0, t0, d)], reveal, u)
            mb.add_poly([p(s1, t0), p(s1, t1), p(s1, t1, d), p(s1, t0, d)], reveal, -u)
            mb.add_poly([p(s0, t0, d), p(s1, t0, d), p(s1, t1, d), p(s0, t1, d)], glass, n)


def facade_sides(x0, x1, z0, z1):
    """(origin, u, outward normal, width) of the 4 sides of a footprint.

    u = up x n so that (u, up) is counter-clockwise seen from outside.
    """
    return [
        ((x0, 0, z1), (1, 0, 0), (0, 0, 1), x1 - x0),    # south (+Z)
        ((x1, 0, z0), (-1, 0, 0), (0, 0, -1), x1 - x0),  # north (-Z)
        ((x1, 0, z1), (0, 0, -1), (1, 0, 0), z1 - z0),   # east (+X)
        ((x0, 0, z0), (0, 0, 1), (-1, 0, 0), z1 - z0),   # west (-X)
    ]


def add_tier(mb, half_x, half_z, y0, floors, floor_h, bays, wall, reveal,
             roof=True, bottom=True, **kw):
    """Box tier: four recessed-window facades + roof slab + floor.

    Stacked tiers skip the hidden slab between them (roof/bottom = False) so
    no coincident back-to-back faces are generated.
    """
    x0, x1, z0, z1 = -half_x, half_x, -half_z, half_z
    for (ox, _, oz), u, n, width in facade_sides(x0, x1, z0, z1):
        nb = bays[0] if n[2] else bays[1]
        add_facade(mb, (ox, 0, oz), u, n, width, y0, floors, floor_h, nb, wall, reveal, **kw)
    top = y0 + floors * floor_h
    if roof:
        mb.add_poly([(x0, top, z0), (x1, top, z0), (x1, top, z1), (x0, top, z1)], wall, UP)
    if bottom:
        mb.add_poly([(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)], wall, -UP)
    return top


def add_parapet(mb, half_x, half_z, y, color, thick=0.25, height=1.1):
    """Thin roof-edge walls (detail thinner than a voxel)."""
    x0, x1, z0, z1 = -half_x, half_x, -half_z, half_z
    mb.add_box((x0, y, z1 - thick), (x1, y + height, z1), color)
    mb.add_box((x0, y, z0), (x1, y + height, z0 + thick), color)
    mb.add_box((x1 - thick, y, z0 + thick), (x1, y + height, z1 - thick), color)
    mb.add_box((x0, y, z0 + thick), (x0 + thick, y + height, z1 - thick), color)


def add_fins(mb, half_x, half_z, y0, y1, bays, color, thick=0.2, depth=0.6):
    """Vertical aluminium fins at every bay line, standing off the facade."""
    for (ox, _, oz), u, n, width in facade_sides(-half_x, half_x, -half_z, half_z):
        nb = bays[0] if n[2] else bays[1]
        o, u, n = np.array((ox, 0.0, oz)), np.array(u, float), np.array(n, float)
        for b in range(1, nb):
            c = o + u * (b * width / nb)
            a = c - u * thick / 2
            z = c + u * thick / 2 + n * depth
            lo, hi = np.minimum(a, z), np.maximum(a, z)
            mb.add_box((lo[0], y0, lo[2]), (hi[0], y1, hi[2]), color)


def add_shades(mb, half_x, half_z, y0, floors, floor_h, color, thick=0.12, depth=0.8):
    """Horizontal sun-shade blades above each window row, all four sides."""
    for f in range(floors):
        y = y0 + f * floor_h + floor_h * 0.88
        hx, hz = half_x + depth, half_z + depth
        mb.add_box((-hx, y, half_z), (hx, y + thick, hz), color)
        mb.add_box((-hx, y, -hz), (hx, y + thick, -half_z), color)
        mb.add_box((half_x, y, -half_z), (hx, y + thick, half_z), color)
        mb.add_box((-hx, y, -half_z), (-half_x, y + thick, half_z), color)


def add_balconies(mb, half_x, half_z, floors, floor_h, bays, slab, rail, depth=1.2):
    """Balconies on the +Z and -Z facades: slab + three glass-thin railings."""
    cw = 2 * half_x / bays
    for side in (1, -1):
        z_in = side * half_z
        z_out = side * (half_z + depth)
        zlo, zhi = min(z_in, z_out), max(z_in, z_out)
        for f in range(1, floors):
            y = f * floor_h
            for b in range(bays):
                x0 = -half_x + b * cw + 0.1 * cw
                x1 = x0 + 0.8 * cw
                mb.add_box((x0, y - 0.18, zlo), (x1, y, zhi), slab)
                zr = z_out - side * 0.05
                mb.add_box((x0, y, min(zr, z_out)), (x1, y + 1.0, max(zr, z_out)), rail)
                for x in (x0, x1 - 0.05):
                    mb.add_box((x, y, zlo), (x + 0.05, y + 1.0, zhi), rail)


def building_tower_fins():
    """16-storey office tower: fins, parapet, octagonal penthouse, antenna."""
    core, fins, roof = MeshBuilder(), MeshBuilder(), MeshBuilder()
    wall, reveal, metal = (0.62, 0.62, 0.60), (0.45, 0.45, 0.45), (0.72, 0.74, 0.78)
    h = 5.1
    top = add_tier(core, h, h, 0.0, 16, 3.5, (4, 4), wall, reveal, win_w=0.7)
    add_fins(fins, h, h, 0.0, top, (4, 4), metal)
    add_parapet(roof, h, h, top, wall)
    roof.add_cylinder((0, 0), 2.4, top, top + 3.5, 8, (0.5, 0.5, 0.52), phase=math.pi / 8)
    roof.add_cylinder((0, 0), 0.08, top + 3.5, top + 13.5, 6, metal)
    return {"facade": core, "fins": fins, "roof": roof}


def building_apartments():
    """9-storey brick apartments with balconies and a gabled stair house."""
    core, balc, roof = MeshBuilder(), MeshBuilder(), MeshBuilder()
    brick, reveal = (0.55, 0.28, 0.20), (0.62, 0.58, 0.52)
    hx, hz = 5.5, 3.9
    top = add_tier(core, hx, hz, 0.0, 9, 3.0, (4, 3), brick, reveal)
    add_balconies(balc, hx, hz, 9, 3.0, 4, (0.70, 0.70, 0.68), (0.20, 0.22, 0.24))
    add_parapet(roof, hx, hz, top, brick, thick=0.3, height=0.9)
    # Stair house: pentagonal (gable) profile extruded along X -> 5-gon caps.
    gable = [(-1.5, 0.0), (1.5, 0.0), (1.5, 2.6), (0.0, 3.6), (-1.5, 2.6)]
    roof.add_prism(gable, (-1.5, top, 0.5), (0, 0, -1), (0, 1, 0), -1.4, 1.4,
                   (0.58, 0.32, 0.24), cap_color=(0.58, 0.32, 0.24))
    return {"facade": core, "balconies": balc, "roof": roof}


def building_stepped_tower():
    """Art-deco setback tower: three tiers, parapets, hexagonal spire."""
    core, roof = MeshBuilder(), MeshBuilder()
    stone, reveal = (0.78, 0.72, 0.60), (0.60, 0.55, 0.46)
    glass = (0.10, 0.22, 0.24)
    y = 0.0
    for tier, (half, floors, bays) in enumerate(((5.3, 10, 4), (4.1, 7, 3), (2.9, 5, 2))):
        # Setback roofs are exposed; the floor of an upper tier is hidden.
        y = add_tier(core, half, half, y, floors, 3.4, (bays, bays), stone, reveal,
                     bottom=tier == 0, glass=glass, win_w=0.5, win_h=0.6)
        add_parapet(roof, half, half, y, stone, thick=0.28, height=0.8)
    roof.add_cylinder((0, 0), 1.6, y, y + 2.5, 6, stone)
    roof.add_pyramid((0, 0), 1.6, y + 2.5, 9.0, 6, (0.55, 0.58, 0.60))
    return {"facade": core, "roof": roof}


def building_shop():
    """3-storey shop house: big shop windows, awnings, heptagonal water tank."""
    core, awn, roof = MeshBuilder(), MeshBuilder(), MeshBuilder()
    stucco, reveal = (0.80, 0.62, 0.40), (0.55, 0.45, 0.35)
    h = 5.2
    add_tier(core, h, h, 0.0, 1, 4.5, (2, 2), stucco, reveal, roof=False,
             win_w=0.8, win_h=0.6, sill=0.1)
    top = add_tier(core, h, h, 4.5, 2, 3.2, (4, 4), stucco, reveal, bottom=False)
    red = (0.60, 0.12, 0.10)
    for (ox, _, oz), u, n, width in facade_sides(-h, h, -h, h):
        o, u, n = np.array((ox, 0.0, oz)), np.array(u, float), np.array(n, float)
        for b in range(2):
            # Sloped thin awning over each shop window.
            a = o + u * (width * (b * 0.5 + 0.05)) + UP * 3.7
            c = o + u * (width * (b * 0.5 + 0.45)) + UP * 3.7
            mid = (a + c) / 2
            # up_hint is the awning's normal, so the width runs along u.
            awn.add_beam(mid, mid + n * 1.4 - UP * 0.5, width * 0.4, 0.08, red,
                         up_hint=UP * 1.4 + n * 0.5)
    add_parapet(roof, h, h, top, stucco, thick=0.25, height=0.7)
    legs_top = top + 2.0
    for sx, sz in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        roof.add_box((sx * 1.2 - 0.08, top, sz * 1.2 - 0.08), (sx * 1.2 + 0.08, legs_top, sz * 1.2 + 0.08),
                     (0.3, 0.3, 0.3))
    wood = (0.45, 0.32, 0.20)
    roof.add_cylinder((0, 0), 1.6, legs_top, legs_top + 2.6, 7, wood)
    roof.add_pyramid((0, 0), 1.7, legs_top + 2.6, 0.9, 7, (0.3, 0.3, 0.3))
    return {"facade": core, "awnings": awn, "roof": roof}


def building_slab():
    """10-storey slab block wrapped in horizontal sun-shade blades."""
    core, shades, roof = MeshBuilder(), MeshBuilder(), MeshBuilder()
    panel, reveal = (0.85, 0.85, 0.82), (0.60, 0.60, 0.58)
    hx, hz = 5.0, 3.3
    top = add_tier(core, hx, hz, 0.0, 10, 3.2, (5, 2), panel, reveal, win_w=0.75)
    add_shades(shades, hx, hz, 0.0, 10, 3.2, (0.30, 0.32, 0.35))
    add_parapet(roof, hx, hz, top, panel, thick=0.2, height=1.0)
    roof.add_box((-3.5, top, -1.5), (-1.0, top + 2.2, 1.5), (0.5, 0.5, 0.5))
    roof.add_cylinder((2.5, 0), 1.0, top, top + 1.8, 5, (0.5, 0.5, 0.52))
    return {"facade": core, "shades": shades, "roof": roof}


BUILDINGS = {
    # name: (builder, relative frequency in the layout)
    "building_a": (building_tower_fins, 0.16),
    "building_b": (building_apartments, 0.28),
    "building_c": (building_stepped_tower, 0.08),
    "building_d": (building_shop, 0.28),
    "building_e": (building_slab, 0.20),
}


def write_building_assets(out_dir):
    """Write each building as its own .usdc; returns {name: (tris, half_extent)}."""
    info = {}
    for name, (builder, _) in BUILDINGS.items():
        meshes = builder()
        write_asset(os.path.join(out_dir, "assets", f"{name}.usdc"), name, meshes)
        pts = np.concatenate([np.array(m.points) for m in meshes.values()])
        half = float(np.max(np.abs(pts[:, [0, 2]])))
        info[name] = (sum(m.triangle_count for m in meshes.values()), half)
    return info


# --------------------------------------------------------------------------
# City stage
# --------------------------------------------------------------------------

BLOCKS, BLOCK, STREET, SIDEWALK = 6, 44.0, 14.0, 3.0
CITY = BLOCKS * BLOCK + (BLOCKS + 1) * STREET  # 362 m across
CURB = 0.15


def street_centers():
    return [-CITY / 2 + STREET / 2 + k * (BLOCK + STREET) for k in range(BLOCKS + 1)]


def block_origin(i):
    return -CITY / 2 + STREET + i * (BLOCK + STREET)


def layout_buildings(stage, info, rng):
    """Instance building assets on a 3x3 lot grid per block (some lots empty)."""
    names = list(BUILDINGS)
    weights = np.array([BUILDINGS[n][1] for n in names])
    weights /= weights.sum()
    lot = (BLOCK - 2 * SIDEWALK) / 3
    Usd.ModelAPI(UsdGeom.Xform.Define(stage, "/World/City").GetPrim()).SetKind("group")
    count, tris = 0, 0
    for bi in range(BLOCKS):
        for bj in range(BLOCKS):
            block_path = f"/World/City/Block_{bi * BLOCKS + bj:02d}"
            Usd.ModelAPI(UsdGeom.Xform.Define(stage, block_path).GetPrim()).SetKind("group")
            for li in range(3):
                for lj in range(3):
                    if rng.random() < 0.1:
                        continue  # plaza / parking lot
                    name = names[rng.choice(len(names), p=weights)]
                    jitter = rng.uniform(-2.0, 2.0)
                    yaw = 90.0 * rng.integers(4) + jitter
                    # Largest scale that keeps the rotated footprint in its lot.
                    half = info[name][1]
                    j = math.radians(abs(jitter))
                    max_s = (lot / 2 - 0.3) / (half * (math.cos(j) + math.sin(j)))
                    s_xz = min(rng.uniform(0.88, 1.08), max_s)
                    s_y = s_xz * rng.uniform(0.85, 1.2)
                    x = block_origin(bi) + SIDEWALK + (li + 0.5) * lot
                    z = block_origin(bj) + SIDEWALK + (lj + 0.5) * lot
                    prim = stage.DefinePrim(f"{block_path}/bldg_{count:03d}", "Xform")
                    prim.GetReferences().AddReference(f"./assets/{name}.usdc")
                    prim.SetInstanceable(True)
                    xf = UsdGeom.Xformable(prim)
                    xf.AddTranslateOp().Set(Gf.Vec3d(x, CURB, z))
                    xf.AddRotateYOp().Set(float(yaw))
                    xf.AddScaleOp().Set(Gf.Vec3f(s_xz, s_y, s_xz))
                    count += 1
                    tris += info[name][0]
    return count, tris


def city_ground_meshes():
    """Asphalt, terrain beyond the city, raised sidewalk blocks, lane dashes."""
    terrain, asphalt, walks, marks = MeshBuilder(), MeshBuilder(), MeshBuilder(), MeshBuilder()
    big, half = 700.0, CITY / 2
    terrain_c = (0.30, 0.36, 0.22)
    # Terrain: ring of four slabs around the city, top at ground level.
    for lo, hi in (((-big, -0.3, -big), (big, 0.0, -half)), ((-big, -0.3, half), (big, 0.0, big)),
                   ((-big, -0.3, -half), (-half, 0.0, half)), ((half, -0.3, -half), (big, 0.0, half))):
        terrain.add_box(lo, hi, terrain_c)
    asphalt.add_box((-half, -0.3, -half), (half, 0.0, half), (0.18, 0.18, 0.19))
    # One raised block (sidewalk + lots) per city block; its sides are curbs.
    for bi in range(BLOCKS):
        for bj in range(BLOCKS):
            x0, z0 = block_origin(bi), block_origin(bj)
            x1, z1 = x0 + BLOCK, z0 + BLOCK
            walks.add_box((x0, 0.0, z0), (x1, CURB, z1), (0.55, 0.54, 0.52))
            # Kerb stones: a lighter, slightly lower strip around the block.
            kerb, k, h = (0.68, 0.68, 0.66), 0.2, CURB - 0.02
            walks.add_box((x0 - k, 0.0, z0 - k), (x1 + k, h, z0), kerb)
            walks.add_box((x0 - k, 0.0, z1), (x1 + k, h, z1 + k), kerb)
            walks.add_box((x0 - k, 0.0, z0), (x0, h, z1), kerb)
            walks.add_box((x1, 0.0, z0), (x1 + k, h, z1), kerb)
    # Dashed centre lines between intersections.
    dash_c = (0.85, 0.80, 0.45)
    for c in street_centers():
        for i in range(BLOCKS):
            start = block_origin(i) + 1.5
            for k in range(int((BLOCK - 3.0) // 6.0) + 1):
                a = start + k * 6.0
                marks.add_box((c - 0.08, 0.0, a), (c + 0.08, 0.01, a + 3.0), dash_c)
                marks.add_box((a, 0.0, c - 0.08), (a + 3.0, 0.01, c + 0.08), dash_c)
    return {"Terrain": terrain, "Asphalt": asphalt, "Sidewalks": walks, "Markings": marks}


def city_light_positions(rng, n, times):
    """Lights drifting along the 14 streets, bobbing at 2-8 m.

    Start points keep a margin so no light wraps around within the shot.
    """
    centers = np.array(street_centers())
    street = rng.integers(0, 2 * len(centers), n)
    axis = street % 2  # 0: runs along X, 1: runs along Z
    line = centers[street // 2]
    speed = rng.uniform(0.5, 2.5, n) * rng.choice([-1.0, 1.0], n)
    margin = 3.0 * times[-1] + 2.0
    s0 = rng.uniform(-CITY / 2 + margin, CITY / 2 - margin, n)
    lateral = rng.uniform(-5.5, 5.5, n)
    h0 = rng.uniform(2.5, 7.5, n)
    bob_amp = rng.uniform(0.1, 0.4, n)
    bob_freq = rng.uniform(0.3, 1.0, n)
    phase = rng.uniform(0, 2 * math.pi, n)
    t = times[:, None]
    s = s0 + speed * t
    y = h0 + bob_amp * np.sin(2 * math.pi * bob_freq * t + phase)
    across = np.broadcast_to(line + lateral, s.shape)
    x = np.where(axis == 0, s, across)
    z = np.where(axis == 0, across, s)
    return np.stack([x, y, z], axis=-1)


def street_samples(rng, m=256):
    """Random points on the street surface (for intensity calibration)."""
    centers = np.array(street_centers())
    line = centers[rng.integers(0, len(centers), m)] + rng.uniform(-6, 6, m)
    along = rng.uniform(-CITY / 2, CITY / 2, m)
    flip = rng.random(m) < 0.5
    pts = np.stack([np.where(flip, line, along), np.zeros(m), np.where(flip, along, line)], -1)
    return pts, np.tile(UP, (m, 1))


def make_city(out_dir):
    rng = np.random.default_rng(1001)
    info = write_building_assets(out_dir)
    path = os.path.join(out_dir, "city.usda")
    stage = new_stage(path, 1, 48)
    anim = add_anim_layer(stage, out_dir, "city_lights")
    n_bldg, bldg_tris = layout_buildings(stage, info, rng)

    UsdGeom.Xform.Define(stage, "/World/Streets")
    street_tris = 0
    for name, mb in city_ground_meshes().items():
        define_mesh(stage, f"/World/Streets/{name}", mb)
        street_tris += mb.triangle_count
    total = bldg_tris + street_tris
    assert total >= 500_000, total

    frames, times = frame_times(1, 48)
    n = 1024
    positions = city_light_positions(rng, n, times)
    protos = ["warm", "cool", "white"]
    proto_idx = rng.choice(3, n, p=[0.5, 0.25, 0.25])
    samples, normals = street_samples(rng)
    # Streets are canyons: buildings block most lights and the bird's-eye view
    # mostly sees roofs above the 2-8 m bulbs.  An unshadowed street target of
    # 0.85 measured ~0.1 mean pixel (albedo 0.5, shadow rays) from main_cam.
    intensity = calibrate_intensity(positions[0], 0.1, samples, normals, target=0.85)
    define_light_instancer(stage, anim, "/World/Lights", protos, 0.1, intensity,
                           proto_idx, positions, frames)

    # Bird's-eye 3/4 view from the south-west corner, whole city in frame.
    el, az, dist = math.radians(36.0), math.radians(-45.0), 560.0
    target = np.array((0.0, 0.0, 0.0))
    eye = target + dist * np.array((math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)))
    define_camera(stage, eye, target, (1.0, 3000.0))
    define_render_settings(stage, "out/city.####.exr")
    stage.Save()
    return {"buildings": n_bldg, "expanded_tris": total, "intensity": intensity}


CITY_NIGHT_LIGHTS = 100_000


def make_city_night(out_dir, n=CITY_NIGHT_LIGHTS, name="city_night", city="./city.usda", seed=1002):
    """The city at night: its 1,024 drifting bulbs switched off (``active = false``) and ``n`` static
    street lamps in their place, a PointInstancer of point-like SphereLights (paper 004's case: far
    more lights than any pixel can afford to test). The lamps stand along the 14 streets at 2.5-7.5 m;
    together they give the street the light the 1,024 bulbs do (intensity x 1024/n), so images at
    any ``n`` are alike. ``city`` is the path of city.usda as the new layer sublayers it; the lamps'
    positions go in ``anim/<name>_lights.usdc`` (binary: 1.2 MB for 100k lamps)."""
    rng = np.random.default_rng(seed)
    path = os.path.join(out_dir, f"{name}.usda")
    stage = new_stage(path, 1, 1)
    lamps = add_anim_layer(stage, out_dir, f"{name}_lights")
    stage.GetRootLayer().subLayerPaths.append(city)
    stage.OverridePrim("/World/Lights").SetActive(False)
    positions = city_light_positions(rng, n, np.zeros(1))[0]
    proto_idx = rng.choice(3, n, p=[0.5, 0.25, 0.25])
    samples, normals = street_samples(rng)
    intensity = calibrate_intensity(city_light_positions(np.random.default_rng(1001), 1024, np.zeros(1))[0],
                                    0.1, samples, normals, target=0.85)
    intensity = round_sig(intensity * 1024.0 / n)
    with Usd.EditContext(stage, lamps):
        define_light_instancer(stage, None, "/World/StreetLamps", ["warm", "cool", "white"], 0.1, intensity,
                               proto_idx, positions, None)
    define_render_settings(stage, f"out/{name}.####.exr")
    lamps.Save()
    stage.Save()
    return {"lights": n, "intensity": intensity}


# --------------------------------------------------------------------------
# Planes stage
# --------------------------------------------------------------------------

PLANE_LENGTH = 30.0


def write_airplane_asset(out_dir):
    """pyvista's airplane.ply (inches-ish, nose at -Y, up +Z) -> 30 m, nose +Z, up +Y."""
    from pyvista import examples
    mesh = examples.load_airplane()
    pts = np.asarray(mesh.points, dtype=float)
    faces = np.asarray(mesh.regular_faces)
    # (X, Y, Z) = (x, z, -y) is a proper rotation: wings on X, up Y, nose +Z.
    pts = np.stack([pts[:, 0], pts[:, 2], -pts[:, 1]], axis=1)
    pts -= (pts.min(0) + pts.max(0)) / 2
    pts *= PLANE_LENGTH / (pts[:, 2].max() - pts[:, 2].min())
    mb = MeshBuilder()
    mb.points = [tuple(round(float(c), 5) for c in p) for p in pts]
    mb.counts = [3] * len(faces)
    mb.indices = [int(i) for i in faces.ravel()]
    mb.colors = [(0.80, 0.81, 0.84)] * len(faces)
    write_asset(os.path.join(out_dir, "assets", "airplane.usdc"), "airplane", {"body": mb})
    return mb.triangle_count


def plane_paths(times):
    """Two planes in formation on a gentle banked left turn over the city.

    The leader is over the city centre mid-shot; bank follows tan(phi) =
    v^2 / (g R) so the attitude is physically plausible.
    """
    speed, radius, alt = 75.0, 1500.0, 150.0  # tallest towers reach ~110 m
    center = np.array((radius, alt, 0.0))
    bank = math.atan(speed ** 2 / (9.81 * radius))
    theta = math.pi + speed / radius * (times - times[-1] / 2)
    offsets = [np.array((0.0, 0.0, 0.0)), np.array((-22.0, -4.0, 28.0))]  # (side, up, back)
    positions, orientations, headings = [], [], []
    for th in theta:
        p = center + radius * np.array((math.cos(th), 0.0, math.sin(th)))
        fwd = np.array((-math.sin(th), 0.0, math.cos(th)))
        inward = unit(np.array((center[0], 0, center[2])) - np.array((p[0], 0, p[2])))
        up = math.cos(bank) * UP + math.sin(bank) * inward
        right = np.cross(up, fwd)  # local +X (wing)
        q = basis_quat(right, up, fwd)
        positions.append([p + o[0] * right + o[1] * up - o[2] * fwd for o in offsets])
        orientations.append([q, q])
        headings.append(fwd)
    return np.array(positions), np.array(orientations), np.array(headings)


def make_planes(out_dir):
    tris = write_airplane_asset(out_dir)
    path = os.path.join(out_dir, "planes.usda")
    stage = new_stage(path, 1, 48)
    anim = add_anim_layer(stage, out_dir, "planes_anim")
    # City (and its animated lights) comes in as the weakest sublayer.
    stage.GetRootLayer().subLayerPaths.append("./city.usda")

    pi = UsdGeom.PointInstancer.Define(stage, "/World/Planes")
    UsdGeom.Scope.Define(stage, "/World/Planes/Prototypes")
    proto = stage.DefinePrim("/World/Planes/Prototypes/airplane", "Xform")
    proto.GetReferences().AddReference("./assets/airplane.usdc")
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr(Vt.IntArray([0, 0]))
    pi.CreateIdsAttr(Vt.Int64Array([0, 1]))
    frames, times = frame_times(1, 48)
    positions, orientations, headings = plane_paths(times)
    set_instancer_xforms(stage, anim, pi, frames, positions, orientations)

    # Chase camera: behind, above and to the right of the pair, looking a
    # little ahead of them so the city fills the lower part of the frame.
    mid = positions.mean(axis=1)
    right = np.cross(UP, headings)
    eyes = mid - 110.0 * headings + 40.0 * UP + 55.0 * right
    targets = mid + 30.0 * headings - 25.0 * UP
    set_camera_xform(UsdGeom.Camera(stage.OverridePrim("/World/main_cam")), eyes, targets, frames)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/main_cam"))
    cam.GetClippingRangeAttr().Set(Gf.Vec2f(1.0, 4000.0))

    UsdRender.Product(stage.GetPrimAtPath("/Render/Product")).GetProductNameAttr().Set("out/planes.####.exr")
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.Save()
    return {"plane_tris": tris}


# --------------------------------------------------------------------------
# Creature stage (UsdSkel bear)
# --------------------------------------------------------------------------

BEAR_SCALE = 0.25  # warp's bear is ~5.5 units tall; 0.25 -> 1.4 m at the ears
#: Loop subdivision levels of warp's 3,968-triangle bear: 3 -> 253,952 triangles, a production-like
#: deforming mesh (paper 000's bear has 1.5 M), where Alg. 1's cost (triangles x directions) dwarfs
#: Alg. 5's (occupied voxels x directions)
BEAR_SUBDIVISIONS = 3

# (joint path, parent index) - parents always precede children.
BEAR_JOINTS = [
    "root", "root/spine", "root/spine/head",
    "root/spine/leg_fl", "root/spine/leg_fl/knee_fl",
    "root/spine/leg_fr", "root/spine/leg_fr/knee_fr",
    "root/leg_bl", "root/leg_bl/knee_bl",
    "root/leg_br", "root/leg_br/knee_br",
    "root/tail",
]


def load_bear():
    """Points, topology and (faceVarying) normals of the first Mesh in warp's bundled bear.usd."""
    import warp.examples
    src = Usd.Stage.Open(os.path.join(warp.examples.get_asset_directory(), "bear.usd"))
    mesh = next(UsdGeom.Mesh(p) for p in src.Traverse() if p.IsA(UsdGeom.Mesh))
    xf = np.array(mesh.ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=float)
    pts = (np.c_[pts, np.ones(len(pts))] @ xf)[:, :3] * BEAR_SCALE
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    normals = np.array(mesh.GetNormalsAttr().Get(), dtype=float) @ np.linalg.inv(xf[:3, :3]).T
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return pts, counts, indices, normals


def loop_subdivide(pts, tris):
    """One level of Loop subdivision of a closed manifold triangle mesh: ``(V, 3)`` float points and
    ``(T, 3)`` int triangles -> ``(V + E, 3)`` points and ``(4 T, 3)`` triangles, winding kept.

    Edge points 3/8 (a + b) + 1/8 (c + d) (c, d opposite the edge); old points moved to
    (1 - n beta) v + beta * sum(neighbours), beta = (5/8 - (3/8 + cos(2 pi / n) / 4)^2) / n."""
    half = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], 1).reshape(-1, 2)
    opposite = tris[:, [2, 0, 1]].reshape(-1)
    edges, edge_of = np.unique(np.sort(half, 1), axis=0, return_inverse=True)
    edge_of = edge_of.reshape(-1)
    assert np.all(np.bincount(edge_of) == 2), "Loop subdivision needs a closed manifold mesh"
    opp_sum = np.zeros((len(edges), 3))
    np.add.at(opp_sum, edge_of, pts[opposite])
    edge_pts = 0.375 * (pts[edges[:, 0]] + pts[edges[:, 1]]) + 0.125 * opp_sum
    ring = np.zeros_like(pts)
    np.add.at(ring, edges[:, 0], pts[edges[:, 1]])
    np.add.at(ring, edges[:, 1], pts[edges[:, 0]])
    n = np.bincount(edges.ravel(), minlength=len(pts)).astype(float)
    beta = (0.625 - (0.375 + 0.25 * np.cos(2 * np.pi / n)) ** 2) / n
    moved = (1 - n * beta)[:, None] * pts + beta[:, None] * ring
    e = len(pts) + edge_of.reshape(-1, 3)          # midpoints of edges v0v1, v1v2, v2v0
    v0, v1, v2, e01, e12, e20 = tris[:, 0], tris[:, 1], tris[:, 2], e[:, 0], e[:, 1], e[:, 2]
    faces = np.stack([np.stack(f, 1) for f in ((v0, e01, e20), (v1, e12, e01), (v2, e20, e12), (e01, e12, e20))], 1)
    return np.concatenate([moved, edge_pts]), faces.reshape(-1, 3)


def vertex_normals(pts, tris):
    """Area-weighted unit vertex normals ``(V, 3)`` of a triangle mesh."""
    fn = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    vn = np.zeros_like(pts)
    for k in range(3):
        np.add.at(vn, tris[:, k], fn)
    return vn / np.linalg.norm(vn, axis=1, keepdims=True)


def bear_joints(pts):
    """Joint positions + bone segment ends, measured from the mesh.

    The bear faces +Z (ears/snout at +Z), left is +X.  Leg columns are found
    from the vertices between ankle and belly height in each quadrant.
    """
    y = pts[:, 1]
    col = pts[(y > 0.12) & (y < 0.5)]
    front_z = col[col[:, 2] > -0.15, 2].mean()
    back_z = col[col[:, 2] <= -0.15, 2].mean()
    legs = {}
    for name, front, side in (("fl", True, 1), ("fr", True, -1), ("bl", False, 1), ("br", False, -1)):
        sel = col[((col[:, 2] > -0.15) == front) & (np.sign(col[:, 0]) == side)]
        legs[name] = (sel[:, 0].mean(), sel[:, 2].mean())
    zmin, zmax = pts[:, 2].min(), pts[:, 2].max()
    pos = {
        "root": (0.0, 0.85, back_z), "root/spine": (0.0, 0.88, front_z),
        "root/spine/head": (0.0, 1.0, 0.62), "root/tail": (0.0, 0.95, zmin + 0.22),
    }
    ends = {"root": pos["root/spine"], "root/spine": pos["root/spine/head"],
            "root/spine/head": (0.0, 1.0, zmax), "root/tail": (0.0, 0.95, zmin)}
    for name, (x, z) in legs.items():
        parent = "root/spine" if name[0] == "f" else "root"
        hip, knee = f"{parent}/leg_{name}", f"{parent}/leg_{name}/knee_{name}"
        pos[hip], pos[knee] = (x, 0.62, z), (x, 0.30, z)
        ends[hip], ends[knee] = pos[knee], (x, 0.0, z)
    order = BEAR_JOINTS
    return (np.array([pos[j] for j in order]), np.array([ends[j] for j in order]))


def segment_distance(p, a, b):
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def skin_weights(pts, starts, ends, influences=4, falloff=0.03):
    """Smooth bone-distance weights, top-4, normalized.

    w_j = exp(-(d_j - d_min) / falloff); leg bones are additionally masked by
    a soft side test so the inner faces of the left and right legs (only a
    few cm apart) do not drag each other along.
    """
    d = np.stack([segment_distance(pts, a, b) for a, b in zip(starts, ends)], axis=1)
    w = np.exp(-(d - d.min(axis=1, keepdims=True)) / falloff)
    for j, name in enumerate(BEAR_JOINTS):
        side = {"l": 1.0, "r": -1.0}.get(name[-1]) if "leg_" in name or "knee_" in name else None
        if side is not None:
            w[:, j] *= 1.0 / (1.0 + np.exp(-side * pts[:, 0] / 0.02))
    # Stable sort so ties resolve the same way on every run.
    order = np.argsort(-w, axis=1, kind="stable")[:, :influences]
    top = np.take_along_axis(w, order, axis=1)
    top /= top.sum(axis=1, keepdims=True)
    return order.astype(np.int32), top.astype(np.float32)


def translation_matrix(t):
    return Gf.Matrix4d().SetTranslate(Gf.Vec3d(*[float(c) for c in settled(t, 9)]))


def write_bear_asset(out_dir):
    """Rigged bear: SkelRoot > Skeleton + skinned Mesh (bind pose = rest), the mesh warp's bear
    Loop-subdivided ``BEAR_SUBDIVISIONS`` times; the skeleton is measured from the source mesh, the
    weights computed on the subdivided points by the same rule."""
    pts, counts, indices, _ = load_bear()
    joints, ends = bear_joints(pts)
    tris = indices.reshape(-1, 3)
    for _ in range(BEAR_SUBDIVISIONS):
        pts, tris = loop_subdivide(pts, tris)
    pts = settled(pts, 5)
    counts, indices, normals = np.full(len(tris), 3), tris.ravel(), vertex_normals(pts, tris)
    jidx, jw = skin_weights(pts, joints, ends)

    path = os.path.join(out_dir, "assets", "bear.usdc")
    remove(path)
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdSkel.Root.Define(stage, "/bear")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root).SetKind("component")

    skel = UsdSkel.Skeleton.Define(stage, "/bear/Skel")
    skel.CreateJointsAttr(BEAR_JOINTS)
    parents = [BEAR_JOINTS.index(j.rsplit("/", 1)[0]) if "/" in j else -1 for j in BEAR_JOINTS]
    # Joint frames are axis-aligned: bind = world translation, rest = offset
    # from the parent, so rest composes exactly to bind.
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([translation_matrix(p) for p in joints]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([
        translation_matrix(joints[j] - (joints[p] if p >= 0 else 0.0)) for j, p in enumerate(parents)]))

    mesh = UsdGeom.Mesh.Define(stage, "/bear/Body")
    points = settled_points(pts)
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    # smooth rest-pose normals: skinning ignores them, but they say the bear shades smooth
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(settled(normals, 6).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    set_display_color(mesh, [(0.36, 0.24, 0.15)])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 4).Set(Vt.IntArray.FromNumpy(jidx.ravel()))
    binding.CreateJointWeightsPrimvar(False, 4).Set(Vt.FloatArray.FromNumpy(settled(jw, 7).astype(np.float32).ravel()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    stage.Save()
    return joints, parents, len(counts)


def walk_cycle(joints, parents, times, speed=0.9, period=1.0):
    """Per-frame local translations and rotations for a diagonal-pair walk."""
    rest = [joints[j] - (joints[p] if p >= 0 else 0.0) for j, p in enumerate(parents)]
    x_axis, y_axis, z_axis = (1, 0, 0), (0, 1, 0), (0, 0, 1)
    phase_of = {"fl": 0.0, "br": 0.0, "fr": math.pi, "bl": math.pi}
    trans, rots = [], []
    for t in times:
        ph = 2 * math.pi * t / period
        tr = [np.array(r, dtype=float) for r in rest]
        tr[0] = tr[0] + np.array((0.0, 0.03 * abs(math.sin(ph)), speed * t))
        rot = []
        for name in BEAR_JOINTS:
            leaf = name.rsplit("/", 1)[-1]
            if leaf == "root":
                q = axis_angle_quat(z_axis, math.radians(3) * math.sin(ph))
            elif leaf == "spine":
                q = axis_angle_quat(y_axis, math.radians(4) * math.sin(ph))
            elif leaf == "head":
                q = quat_mul(axis_angle_quat(x_axis, math.radians(6) * math.sin(2 * ph)),
                             axis_angle_quat(y_axis, math.radians(8) * math.sin(0.5 * ph)))
            elif leaf == "tail":
                q = axis_angle_quat(y_axis, math.radians(25) * math.sin(2 * ph))
            elif leaf.startswith("leg_"):
                q = axis_angle_quat(x_axis, math.radians(22) * math.sin(ph + phase_of[leaf[-2:]]))
            else:  # knee: bends only while the foot swings forward
                bend = max(0.0, math.sin(ph + phase_of[leaf[-2:]] + math.pi / 2))
                q = axis_angle_quat(x_axis, -math.radians(28) * bend)
            rot.append(q)
        trans.append(tr)
        rots.append(rot)
    return trans, rots


def creature_light_positions(rng, n, times, center):
    """Firefly swarm: slow orbits around the bear's path with bobbing."""
    r = np.sqrt(rng.uniform(2.5 ** 2, 10.0 ** 2, n))
    a0 = rng.uniform(0, 2 * math.pi, n)
    omega = rng.uniform(0.1, 0.5, n) * rng.choice([-1.0, 1.0], n)
    h0 = rng.uniform(0.4, 4.0, n)
    bob = rng.uniform(0.05, 0.3, n)
    freq = rng.uniform(0.3, 1.2, n)
    ph = rng.uniform(0, 2 * math.pi, n)
    t = times[:, None]
    a = a0 + omega * t
    x = center[0] + r * np.cos(a)
    z = center[2] + r * np.sin(a)
    y = h0 + bob * np.sin(2 * math.pi * freq * t + ph)
    return np.stack([x, y, z], axis=-1)


def ground_grid(size, quads, color, center=(0.0, 0.0)):
    mb = MeshBuilder()
    step = size / quads
    x0, z0 = center[0] - size / 2, center[1] - size / 2
    for i in range(quads):
        for j in range(quads):
            a, b = x0 + i * step, z0 + j * step
            mb.add_poly([(a, 0, b), (a + step, 0, b), (a + step, 0, b + step), (a, 0, b + step)], color, UP)
    return mb


def make_creature(out_dir):
    rng = np.random.default_rng(3003)
    joints, parents, bear_tris = write_bear_asset(out_dir)
    path = os.path.join(out_dir, "creature.usda")
    stage = new_stage(path, 1, 48)
    anim_layer = add_anim_layer(stage, out_dir, "creature_lights")
    frames, times = frame_times(1, 48)

    bear = UsdSkel.Root.Define(stage, "/World/Bear")
    bear.GetPrim().GetReferences().AddReference("./assets/bear.usdc")
    anim = UsdSkel.Animation.Define(stage, "/World/Bear/Walk")
    anim.CreateJointsAttr(BEAR_JOINTS)
    trans, rots = walk_cycle(joints, parents, times)
    scales = Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(BEAR_JOINTS))
    anim.CreateScalesAttr(scales)
    t_attr, r_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    for f, tr, rot in zip(frames, trans, rots):
        tc = Usd.TimeCode(float(f))
        t_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, v)) for v in settled(tr, 5)]), tc)
        # Rounding drops float noise (-0, 1e-17) from the authored text.
        r_attr.Set(Vt.QuatfArray([Gf.Quatf(*[round(float(c), 7) + 0.0 for c in q]) for q in rot]), tc)
    skel_prim = stage.OverridePrim("/World/Bear/Skel")
    UsdSkel.BindingAPI.Apply(skel_prim).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    center = np.array((0.0, 0.0, 0.9))  # middle of the 1.8 m walk
    ground = ground_grid(30.0, 40, (0.32, 0.40, 0.24), center=(center[0], center[2]))
    define_mesh(stage, "/World/Ground", ground)

    n = 1024
    positions = creature_light_positions(rng, n, times, center)
    proto_idx = rng.choice(3, n, p=[0.6, 0.2, 0.2])
    sx = rng.uniform(-6, 6, 256)
    sz = rng.uniform(-6, 6, 256) + center[2]
    samples = np.stack([sx, np.zeros(256), sz], -1)
    intensity = calibrate_intensity(positions[0], 0.05, samples, np.tile(UP, (256, 1)), target=0.3)
    define_light_instancer(stage, anim_layer, "/World/Lights", ["warm", "cool", "white"], 0.05,
                           intensity, proto_idx, positions, frames)

    # 3/4 front view tracking the bear's root.
    root_z = np.array([tr[0][2] for tr in trans])
    targets = np.stack([np.zeros_like(root_z), np.full_like(root_z, 0.65), root_z + 0.2], -1)
    eyes = targets + np.array((4.2, 1.6, 5.2))
    define_camera(stage, eyes, targets, (0.1, 200.0), frames)
    define_render_settings(stage, "out/creature.####.exr")
    stage.Save()
    return {"bear_tris": bear_tris, "intensity": intensity}


def check_skinning(path, frames=(1, 12, 24, 36, 48)):
    """Bake skinning on an in-memory flattened copy; points must move, not explode."""
    flat = Usd.Stage.Open(path).Flatten()
    stage = Usd.Stage.Open(flat)
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(1, 48)), "BakeSkinning failed"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Bear/Body"))
    pts = [np.array(mesh.GetPointsAttr().Get(f)) for f in frames]
    sizes = [p.max(0) - p.min(0) for p in pts]
    moved = max(float(np.abs(p - pts[0]).max()) for p in pts[1:])
    change = max(float(np.max(np.abs(s - sizes[0]) / sizes[0])) for s in sizes[1:])
    assert moved > 0.1, f"skinned points barely move ({moved})"
    assert change < 0.5, f"skinned bbox changes by {change:.0%}"
    return {"max_point_motion": round(moved, 3), "max_bbox_change": round(change, 3)}


# --------------------------------------------------------------------------
# Cornell box
# --------------------------------------------------------------------------

def cornell_point(x, y, z):
    """Original Cornell data (mm, camera at -Z) -> metres, turned 180 deg about
    Y so the open side faces +Z (USD cameras look down -Z) and red is on the
    left; a rotation keeps the winding/handedness intact."""
    return np.array((5.56 - x * 0.01, y * 0.01, -z * 0.01))


def make_cornell(out_dir):
    path = os.path.join(out_dir, "cornell.usda")
    stage = new_stage(path, 1, 1)
    white, red, green = (0.73, 0.73, 0.73), (0.63, 0.065, 0.05), (0.14, 0.45, 0.091)
    inside = cornell_point(278, 274, 280)
    walls = {
        "Floor": ([(552.8, 0, 0), (0, 0, 0), (0, 0, 559.2), (549.6, 0, 559.2)], white),
        "Ceiling": ([(556, 548.8, 0), (556, 548.8, 559.2), (0, 548.8, 559.2), (0, 548.8, 0)], white),
        "BackWall": ([(549.6, 0, 559.2), (0, 0, 559.2), (0, 548.8, 559.2), (556, 548.8, 559.2)], white),
        "GreenWall": ([(0, 0, 559.2), (0, 0, 0), (0, 548.8, 0), (0, 548.8, 559.2)], green),
        "RedWall": ([(552.8, 0, 0), (549.6, 0, 559.2), (556, 548.8, 559.2), (556, 548.8, 0)], red),
    }
    UsdGeom.Xform.Define(stage, "/World/Box")
    for name, (quad, color) in walls.items():
        mb = MeshBuilder()
        pts = [cornell_point(*p) for p in quad]
        mb.add_poly(pts, color, inside - sum(pts) / 4)  # walls face the interior
        define_mesh(stage, f"/World/Box/{name}", mb)

    blocks = {
        "ShortBlock": ([(130, 65), (82, 225), (240, 272), (290, 114)], 165.0),
        "TallBlock": ([(423, 247), (265, 296), (314, 456), (472, 406)], 330.0),
    }
    for name, (quad, height) in blocks.items():
        mb = MeshBuilder()
        pts = [cornell_point(x, 0, z) for x, z in quad]
        mb.add_prism([(p[0], p[2]) for p in pts], (0, 0, 0), (1, 0, 0), (0, 0, 1),
                     -height * 0.01, 0.0, white)
        define_mesh(stage, f"/World/Box/{name}", mb)

    top = cornell_point(185.5, 165, 169)
    sphere = MeshBuilder()
    sphere.add_uv_sphere(top + np.array((0, 0.45, 0)), 0.45, 32, 16, (0.80, 0.78, 0.70))
    define_mesh(stage, "/World/Box/Sphere", sphere)

    # Two spots hanging 0.25 m below the ceiling on thin cords.
    UsdGeom.Xform.Define(stage, "/World/Lights")
    cords = MeshBuilder()
    spot_pos = [np.array((1.95, 5.238, -2.6)), np.array((3.6, 5.238, -3.0))]
    floor_samples = np.array([(x, 0.0, z) for x in np.linspace(0.4, 5.1, 12)
                              for z in np.linspace(-5.2, -0.4, 12)])
    intensity = calibrate_intensity(np.array(spot_pos), 0.1, floor_samples,
                                    np.tile(UP, (len(floor_samples), 1)), target=0.35)
    for k, pos in enumerate(spot_pos):
        light = UsdLux.SphereLight.Define(stage, f"/World/Lights/Spot_{k}")
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(0.1)
        light.CreateNormalizeAttr(False)
        light.CreateIntensityAttr(intensity)
        light.CreateColorAttr(Gf.Vec3f(1.0, 0.85, 0.65))
        shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
        shaping.CreateShapingConeAngleAttr(40.0)
        shaping.CreateShapingConeSoftnessAttr(0.2)
        shaping.CreateShapingFocusAttr(1.0)
        light.AddTranslateOp().Set(Gf.Vec3d(*map(float, pos)))
        # Lights emit along local -Z; rotateX(-90) turns -Z into -Y (down).
        light.AddRotateXOp().Set(-90.0)
        cords.add_cylinder((pos[0], pos[2]), 0.01, pos[1] + 0.12, 5.488, 6, (0.1, 0.1, 0.1))
    define_mesh(stage, "/World/Lights/Cords", cords)

    define_camera(stage, (2.78, 2.74, 9.9), (2.78, 2.74, -2.8), (0.1, 50.0))
    define_render_settings(stage, "out/cornell.####.exr")
    stage.Save()
    return {"intensity": intensity}


# --------------------------------------------------------------------------
# Amusement park
# --------------------------------------------------------------------------

WHEEL_HUB = np.array((-35.0, 24.0, -25.0))
WHEEL_R, WHEEL_GONDOLAS = 20.0, 24
WHEEL_OMEGA = 2 * math.pi / 40.0  # rad/s, counter-clockwise seen from +Z
CAROUSEL = np.array((35.0, 0.0, -25.0))
CAROUSEL_OMEGA = 2 * math.pi / 12.0  # rad/s, clockwise seen from above
RINK = np.array((0.0, 0.0, 35.0))
RINK_HALF = (18.0, 11.0)
N_PARK_LIGHTS = 7088


def gondola_proto():
    """Cabin hanging from its pivot (the origin), pentagonal-roof profile."""
    mb = MeshBuilder()
    mb.add_beam((0, 0, 0), (0, -0.9, 0), 0.12, 0.12, (0.3, 0.3, 0.3))
    mb.add_box((-1.0, -2.8, -0.75), (1.0, -1.6, 0.75), (0.85, 0.25, 0.20))
    for sx in (-0.95, 0.9):  # corner posts around the open window band
        for sz in (-0.75, 0.7):
            mb.add_box((sx, -1.6, sz), (sx + 0.05, -1.1, sz + 0.05), (0.9, 0.9, 0.9))
    roof = [(-1.1, 0.0), (1.1, 0.0), (1.1, 0.15), (0.0, 0.45), (-1.1, 0.15)]
    mb.add_prism(roof, (0, -1.1, 0), (1, 0, 0), (0, 1, 0), -0.8, 0.8, (0.95, 0.85, 0.3))
    return mb


def horse_proto():
    """Blocky carousel horse facing +Z with its brass pole; origin at saddle."""
    mb = MeshBuilder()
    body, mane = (0.92, 0.90, 0.86), (0.55, 0.30, 0.15)
    mb.add_box((-0.2, -0.28, -0.6), (0.2, 0.22, 0.6), body)
    mb.add_beam((0, 0.1, 0.48), (0, 0.65, 0.78), 0.22, 0.26, body)                # neck
    mb.add_beam((0, 0.65, 0.66), (0, 0.52, 1.08), 0.2, 0.24, body)                # head
    mb.add_beam((0, 0.18, -0.56), (0, -0.32, -0.88), 0.08, 0.1, mane)             # tail
    for x in (-0.12, 0.12):
        mb.add_beam((x, -0.22, 0.48), (x, -0.62, 0.84), 0.09, 0.1, body)          # front legs, leaping
        mb.add_beam((x, -0.22, -0.48), (x, -0.76, -0.72), 0.09, 0.1, body)        # hind legs
    mb.add_box((-0.22, 0.22, -0.25), (0.22, 0.29, 0.18), (0.7, 0.1, 0.15))        # saddle
    mb.add_cylinder((0, 0), 0.04, -1.75, 3.1, 6, (0.85, 0.7, 0.3))                # pole
    return mb


def bumper_car_proto():
    """Bumper car facing +Z: octagonal rubber skirt, body, seat, trolley pole."""
    mb = MeshBuilder()
    skirt = [(0.75 * math.cos(a) * 1.0, 1.15 * math.sin(a)) for a in
             [math.pi / 8 + k * math.pi / 4 for k in range(8)]]
    mb.add_prism(skirt, (0, 0, 0), (1, 0, 0), (0, 0, 1), -0.35, -0.05, (0.1, 0.1, 0.1))
    mb.add_box((-0.62, 0.35, -0.95), (0.62, 0.75, 0.95), (0.15, 0.35, 0.85))
    mb.add_box((-0.45, 0.75, -0.8), (0.45, 1.25, -0.45), (0.9, 0.9, 0.2))          # seat back
    mb.add_beam((0, 0.75, 0.55), (0, 1.05, 0.35), 0.06, 0.06, (0.2, 0.2, 0.2))   # steering column
    mb.add_cylinder((0, 0.35), 0.16, 1.05, 1.09, 8, (0.2, 0.2, 0.2))             # steering wheel
    mb.add_cylinder((0, -0.85), 0.03, 0.75, 2.6, 6, (0.6, 0.6, 0.6))             # trolley pole
    return mb


def wheel_structure():
    """Rotating part of the ferris wheel, in hub-local coordinates."""
    mb = MeshBuilder()
    steel = (0.85, 0.86, 0.9)
    segs = 48
    for zc in (-1.5, 1.5):
        for k in range(segs):
            a0, a1 = 2 * math.pi * k / segs, 2 * math.pi * (k + 1) / segs
            p0 = (WHEEL_R * math.cos(a0), WHEEL_R * math.sin(a0), zc)
            p1 = (WHEEL_R * math.cos(a1), WHEEL_R * math.sin(a1), zc)
            mb.add_beam(p0, p1, 0.25, 0.35, steel, up_hint=(0, 0, 1))
        for k in range(WHEEL_GONDOLAS):
            a = 2 * math.pi * (k + 0.5) / WHEEL_GONDOLAS
            mb.add_beam((0, 0, zc * 0.6), (WHEEL_R * math.cos(a), WHEEL_R * math.sin(a), zc),
                        0.15, 0.15, steel, up_hint=(0, 0, 1))
    hub = regular_polygon(8, 1.6, math.pi / 8)
    mb.add_prism(hub, (0, 0, 0), (1, 0, 0), (0, 1, 0), -1.8, 1.8, (0.7, 0.2, 0.2))
    return mb


def carousel_top():
    """Rotating carousel: platform disc and 16-sided canopy with centre column."""
    mb = MeshBuilder()
    mb.add_cylinder((0, 0), 9.0, 0.3, 0.6, 16, (0.55, 0.35, 0.25))
    mb.add_cylinder((0, 0), 1.2, 0.6, 5.2, 8, (0.9, 0.8, 0.5))
    mb.add_cylinder((0, 0), 9.4, 5.2, 5.8, 16, (0.85, 0.2, 0.3), cap_color=(0.95, 0.9, 0.8))
    mb.add_pyramid((0, 0), 9.4, 5.8, 3.0, 16, (0.95, 0.9, 0.8))
    return mb


def park_static(pole_positions):
    """Ground, paths, rink, wheel supports, carousel base, stalls, light poles."""
    ground = ground_grid(200.0, 20, (0.30, 0.42, 0.22))
    paths = MeshBuilder()
    pave = (0.62, 0.58, 0.52)
    paths.add_box((-90, 0.0, -5), (90, 0.05, 5), pave)
    paths.add_box((-5, 0.0, -90), (5, 0.05, 90), pave)
    paths.add_cylinder((0, 0), 14.0, 0.0, 0.06, 8, pave)  # octagonal plaza

    rides = MeshBuilder()
    hx, hz = RINK_HALF
    cx, cz = RINK[0], RINK[2]
    rides.add_box((cx - hx, 0.0, cz - hz), (cx + hx, 0.2, cz + hz), (0.35, 0.36, 0.4))
    rail = (0.9, 0.75, 0.1)
    rides.add_box((cx - hx, 0.2, cz - hz), (cx + hx, 0.8, cz - hz + 0.3), rail)
    rides.add_box((cx - hx, 0.2, cz + hz - 0.3), (cx + hx, 0.8, cz + hz), rail)
    rides.add_box((cx - hx, 0.2, cz - hz + 0.3), (cx - hx + 0.3, 0.8, cz + hz - 0.3), rail)
    rides.add_box((cx + hx - 0.3, 0.2, cz - hz + 0.3), (cx + hx, 0.8, cz + hz - 0.3), rail)
    # Ferris wheel A-frame legs and base.
    hub = WHEEL_HUB
    for sz in (-1, 1):
        for sx in (-1, 1):
            rides.add_beam((hub[0] + sx * 9, 0, hub[2] + sz * 4.5), (hub[0], hub[1], hub[2] + sz * 2.0),
                           0.6, 0.6, (0.8, 0.8, 0.85))
    rides.add_box((hub[0] - 12, 0, hub[2] - 6), (hub[0] + 12, 0.4, hub[2] + 6), (0.5, 0.5, 0.55))
    rides.add_box((hub[0] - 0.3, hub[1] - 0.3, hub[2] - 2.2), (hub[0] + 0.3, hub[1] + 0.3, hub[2] + 2.2),
                  (0.4, 0.4, 0.45))  # axle
    rides.add_cylinder((CAROUSEL[0], CAROUSEL[2]), 9.6, 0.0, 0.3, 16, (0.4, 0.4, 0.42))

    stalls = MeshBuilder()
    gable = [(-2.2, 0.0), (2.2, 0.0), (2.2, 0.3), (0.0, 1.4), (-2.2, 0.3)]
    colors = [(0.9, 0.3, 0.3), (0.3, 0.5, 0.9), (0.95, 0.8, 0.2), (0.4, 0.75, 0.4)]
    for k, (x, z) in enumerate([(-25, 12), (-15, 12), (15, 12), (25, 12), (-25, -12), (25, -12)]):
        stalls.add_box((x - 2, 0, z - 1.5), (x + 2, 2.6, z + 1.5), (0.85, 0.8, 0.7))
        stalls.add_prism(gable, (x, 2.6, z), (1, 0, 0), (0, 1, 0), -1.8, 1.8, colors[k % 4])
    for x, z, h in pole_positions:
        stalls.add_cylinder((x, z), 0.08, 0.0, h, 6, (0.25, 0.25, 0.25))
    return {"Ground": ground, "Paths": paths, "RideStructures": rides, "Stalls": stalls}


def ride_instances(times):
    """Positions/orientations of gondolas, horses and bumper cars per frame."""
    n_t = len(times)
    pos, ori, proto = [], [], []

    # Gondolas: pivots on the rotating rim, cabins stay upright with a swing.
    k = np.arange(WHEEL_GONDOLAS)
    ang = 2 * math.pi * (k[None] + 0.5) / WHEEL_GONDOLAS + WHEEL_OMEGA * times[:, None]
    p = np.stack([WHEEL_HUB[0] + WHEEL_R * np.cos(ang), WHEEL_HUB[1] + WHEEL_R * np.sin(ang),
                  np.full_like(ang, WHEEL_HUB[2])], -1)
    swing = np.radians(4.0) * np.sin(2 * math.pi * 0.4 * times[:, None] + k[None])
    z = np.zeros_like(swing)
    pos.append(p)
    ori.append(np.stack([z, z, np.sin(swing / 2), np.cos(swing / 2)], -1))
    proto += [0] * WHEEL_GONDOLAS

    # Horses: 12 + 16 + 20 on three rings (~2.4 m apart), rotating with the
    # carousel and galloping up and down.
    for ring, (radius, count) in enumerate(((4.5, 12), (6.2, 16), (7.9, 20))):
        k = np.arange(count)
        a = 2 * math.pi * (k[None] + 0.5 * ring) / count - CAROUSEL_OMEGA * times[:, None]
        bob = 0.3 * np.sin(2 * math.pi * times[:, None] / 1.5 + k[None] * 1.7 + ring)
        p = np.stack([CAROUSEL[0] + radius * np.cos(a), 2.0 + bob, CAROUSEL[2] + radius * np.sin(a)], -1)
        pos.append(p)
        ori.append(yaw_quats(math.pi - a))  # face direction of travel (clockwise)
        proto += [1] * count

    # Bumper cars: 4 elliptic lanes x 10 cars, alternating direction.
    for lane, (a_r, b_r) in enumerate(((15.0, 8.6), (12.2, 6.4), (9.4, 4.2), (6.6, 2.0))):
        k = np.arange(10)
        direction = 1.0 if lane % 2 == 0 else -1.0
        w = direction * 3.2 / ((a_r + b_r) / 2)  # ~3.2 m/s
        th = 2 * math.pi * k[None] / 10 + lane * 0.3 + w * times[:, None]
        p = np.stack([RINK[0] + a_r * np.cos(th), np.full_like(th, 0.2), RINK[2] + b_r * np.sin(th)], -1)
        vx, vz = -a_r * np.sin(th) * w, b_r * np.cos(th) * w
        pos.append(p)
        ori.append(yaw_quats(np.arctan2(vx, vz)))
        proto += [2] * 10

    positions = np.concatenate(pos, axis=1)
    orientations = np.concatenate(ori, axis=1)
    assert positions.shape[:2] == (n_t, len(proto))
    return positions, orientations, np.array(proto)


def festoon_strings():
    """Spans (p0, p1, sag) of bulb strings between poles along the paths.

    Returns the spans and pole (x, z, height) list for the static geometry.
    """
    spans, poles = [], []
    for side in (-1, 1):
        # Main avenue (along X) and cross avenue (along Z), poles every 12 m.
        xs = np.arange(-84.0, 85.0, 12.0)
        for axis in (0, 1):
            pts = [(x, 6.0, side * 6.0) if axis == 0 else (side * 6.0, 6.0, x) for x in xs
                   if abs(x) > 15 and not (axis == 1 and x > 20)]
            for p in pts:
                poles.append((p[0], p[2], p[1]))
            for a, b in zip(pts, pts[1:]):
                if np.linalg.norm(np.subtract(a, b)) < 13:
                    spans.append((np.array(a), np.array(b), 0.7))
    # Zig-zag strings across the main avenue.
    for x in np.arange(-84.0, 85.0, 12.0):
        x_to = x + 12.0 if x < 0 else x - 12.0
        if abs(x) > 15 and abs(x_to) > 15:  # both ends on an existing pole
            spans.append((np.array((x, 6.0, -6.0)), np.array((x_to, 6.0, 6.0)), 1.0))
    # Perimeter fence strings (square of half-size 92 m, poles every 16 m).
    corners = [(-92, -92), (92, -92), (92, 92), (-92, 92)]
    for (x0, z0), (x1, z1) in zip(corners, corners[1:] + corners[:1]):
        n = 12
        for k in range(n):
            a = np.array((x0 + (x1 - x0) * k / n, 4.5, z0 + (z1 - z0) * k / n))
            b = np.array((x0 + (x1 - x0) * (k + 1) / n, 4.5, z0 + (z1 - z0) * (k + 1) / n))
            poles.append((a[0], a[2], 4.5))
            spans.append((a, b, 0.5))
    return spans, poles


def allocate(total, weights):
    """Split an integer total proportionally (largest remainder, deterministic)."""
    raw = np.asarray(weights, dtype=float) / np.sum(weights) * total
    counts = np.floor(raw).astype(int)
    rest = total - counts.sum()
    counts[np.argsort(-(raw - counts), kind="stable")[:rest]] += 1
    return counts


def park_light_positions(rng, times, spans, n_total=N_PARK_LIGHTS):
    """All 7,088 bulbs: wheel rims/spokes, carousel canopy, rink rail, festoons."""
    t = times[:, None]
    groups = []

    # Ferris wheel bulbs rotate rigidly with the wheel.
    local = []
    for zc in (-1.8, 1.8):
        a = 2 * math.pi * np.arange(160) / 160
        local.append(np.stack([WHEEL_R * np.cos(a), WHEEL_R * np.sin(a), np.full(160, zc)], -1))
        for k in range(WHEEL_GONDOLAS):
            a = 2 * math.pi * (k + 0.5) / WHEEL_GONDOLAS
            r = np.linspace(2.0, WHEEL_R - 0.6, 12)
            # Spoke axis z(r) runs 0.6*rim -> rim; sit 0.2 m outside the bar.
            z_axis = 0.6 * 1.5 * np.sign(zc) + 0.4 * 1.5 * np.sign(zc) * r / WHEEL_R
            local.append(np.stack([r * math.cos(a), r * math.sin(a), z_axis + 0.2 * np.sign(zc)], -1))
    local = np.concatenate(local)
    ang = WHEEL_OMEGA * t
    x = local[None, :, 0] * np.cos(ang) - local[None, :, 1] * np.sin(ang)
    y = local[None, :, 0] * np.sin(ang) + local[None, :, 1] * np.cos(ang)
    groups.append(np.stack([x + WHEEL_HUB[0], y + WHEEL_HUB[1],
                            np.broadcast_to(local[:, 2] + WHEEL_HUB[2], x.shape)], -1))

    # Carousel canopy bulbs rotate with the carousel (clockwise from above).
    rad, hgt = [], []
    for r, h in ((9.5, 5.3), (9.5, 5.7)):
        rad.append(np.full(96, r))
        hgt.append(np.full(96, h))
    a_c = [2 * math.pi * np.arange(96) / 96] * 2
    for k in range(16):
        s = np.linspace(0.1, 0.92, 12)
        rad.append(9.4 * s)
        hgt.append(5.8 + 3.0 * (1 - s) + 0.1)
        a_c.append(np.full(12, 2 * math.pi * k / 16))
    rad, hgt, a_c = np.concatenate(rad), np.concatenate(hgt), np.concatenate(a_c)
    a = a_c[None] - CAROUSEL_OMEGA * t
    groups.append(np.stack([CAROUSEL[0] + rad * np.cos(a), np.broadcast_to(hgt, a.shape),
                            CAROUSEL[2] + rad * np.sin(a)], -1))

    # Rink rail bulbs (every 0.5 m) with a gentle shimmer.
    hx, hz = RINK_HALF
    per = np.concatenate([np.linspace(-hx, hx, 72, endpoint=False), np.full(44, hx),
                          np.linspace(hx, -hx, 72, endpoint=False), np.full(44, -hx)])
    per_z = np.concatenate([np.full(72, -hz), np.linspace(-hz, hz, 44, endpoint=False),
                            np.full(72, hz), np.linspace(hz, -hz, 44, endpoint=False)])
    shimmer = 0.05 * np.sin(2 * math.pi * 1.5 * t + np.arange(len(per))[None] * 0.7)
    groups.append(np.stack([np.broadcast_to(RINK[0] + per, shimmer.shape), 1.0 + shimmer,
                            np.broadcast_to(RINK[2] + per_z, shimmer.shape)], -1))

    # Festoon strings get whatever is left, split by span length; they sway.
    used = sum(g.shape[1] for g in groups)
    lengths = [np.linalg.norm(b - a) for a, b, _ in spans]
    counts = allocate(n_total - used, lengths)
    wind_phase = rng.uniform(0, 2 * math.pi, len(spans))
    for (a, b, sag), n, ph in zip(spans, counts, wind_phase):
        s = (np.arange(n) + 0.5) / n
        belly = 4 * s * (1 - s)
        base = a[None] + (b - a)[None] * s[:, None] - np.outer(sag * belly, UP)
        side = unit(np.cross(UP, b - a))
        sway = 0.25 * belly[None] * np.sin(2 * math.pi * 0.5 * t + ph)
        lift = 0.06 * belly[None] * np.sin(2 * math.pi * 0.9 * t + ph)
        groups.append(base[None] + sway[..., None] * side + lift[..., None] * UP)
    positions = np.concatenate(groups, axis=1)
    assert positions.shape[1] == n_total, positions.shape
    return positions


def make_park(out_dir):
    rng = np.random.default_rng(5005)
    path = os.path.join(out_dir, "park.usda")
    stage = new_stage(path, 1, 48)
    anim = add_anim_layer(stage, out_dir, "park_anim")
    frames, times = frame_times(1, 48)

    spans, poles = festoon_strings()
    UsdGeom.Xform.Define(stage, "/World/Park")
    static_tris = 0
    for name, mb in park_static(poles).items():
        define_mesh(stage, f"/World/Park/{name}", mb)
        static_tris += mb.triangle_count

    # Rigidly rotating ride parts: plain Xforms with time-sampled rotation.
    wheel = UsdGeom.Xform.Define(stage, "/World/Park/FerrisWheel")
    wheel.AddTranslateOp().Set(Gf.Vec3d(*map(float, WHEEL_HUB)))
    rot = wheel.AddRotateZOp()
    wheel_mb = wheel_structure()
    define_mesh(stage, "/World/Park/FerrisWheel/Structure", wheel_mb)
    carousel = UsdGeom.Xform.Define(stage, "/World/Park/Carousel")
    carousel.AddTranslateOp().Set(Gf.Vec3d(*map(float, CAROUSEL)))
    rot_c = carousel.AddRotateYOp()
    carousel_mb = carousel_top()
    define_mesh(stage, "/World/Park/Carousel/Top", carousel_mb)
    for f, t in zip(frames, times):
        rot.Set(math.degrees(WHEEL_OMEGA * t), Usd.TimeCode(float(f)))
        # rotateY(+a) turns +X toward -Z, i.e. clockwise seen from above.
        rot_c.Set(math.degrees(CAROUSEL_OMEGA * t), Usd.TimeCode(float(f)))

    pi = UsdGeom.PointInstancer.Define(stage, "/World/Rides")
    UsdGeom.Scope.Define(stage, "/World/Rides/Prototypes")
    proto_paths, proto_tris = [], []
    for name, builder in (("gondola", gondola_proto), ("horse", horse_proto), ("bumper_car", bumper_car_proto)):
        UsdGeom.Xform.Define(stage, f"/World/Rides/Prototypes/{name}")
        mb = builder()
        define_mesh(stage, f"/World/Rides/Prototypes/{name}/Geom", mb)
        proto_paths.append(Sdf.Path(f"/World/Rides/Prototypes/{name}"))
        proto_tris.append(mb.triangle_count)
    positions, orientations, proto_idx = ride_instances(times)
    pi.CreatePrototypesRel().SetTargets(proto_paths)
    pi.CreateProtoIndicesAttr(Vt.IntArray(proto_idx.tolist()))
    pi.CreateIdsAttr(Vt.Int64Array(list(range(len(proto_idx)))))
    set_instancer_xforms(stage, anim, pi, frames, positions, orientations)

    lights = park_light_positions(rng, times, spans)
    protos = ["warm", "white", "pink", "cool"]
    light_idx = rng.choice(4, len(lights[0]), p=[0.55, 0.2, 0.15, 0.1])
    gx = rng.uniform(-90, 90, 400)
    gz = rng.uniform(-90, 90, 400)
    samples = np.stack([gx, np.zeros(400), gz], -1)
    intensity = calibrate_intensity(lights[0], 0.05, samples, np.tile(UP, (400, 1)), target=0.3)
    define_light_instancer(stage, anim, "/World/Lights", protos, 0.05, intensity,
                           light_idx, lights, frames)

    define_camera(stage, (105.0, 62.0, 115.0), (-2.0, 8.0, -8.0), (0.5, 2000.0))
    settings = define_render_settings(stage, "out/park.####.exr")
    settings.GetPrim().CreateAttribute("usdml:voxel:fullyDynamic", Sdf.ValueTypeNames.Bool).Set(True)
    stage.Save()
    ride_tris = int(sum(proto_tris[i] for i in proto_idx))
    return {"rides": len(proto_idx), "lights": lights.shape[1], "intensity": intensity,
            "expanded_tris": static_tris + wheel_mb.triangle_count + carousel_mb.triangle_count + ride_tris}


# --------------------------------------------------------------------------

def make_boxes(out_dir):
    """A block of plain boxes for checks against independent renderers: each box 8 shared corner
    points and 6 quads, ``subdivisionScheme = "none"``, no normals (as box-modelled city blocks are
    authored), on a ground slab, lit by 16 point lights between and above them."""
    path = os.path.join(out_dir, "boxes.usda")
    stage = new_stage(path, 1, 1)
    rng = np.random.default_rng(18)
    UsdGeom.Xform.Define(stage, "/World/Boxes")
    boxes = []      # (lo, hi) of every box, to keep the lights clear of them
    corners = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    for i in range(5):
        for j in range(5):
            w, d, h = rng.uniform(1.2, 2.2), rng.uniform(1.2, 2.2), rng.uniform(0.8, 4.0)
            x0, z0 = -8.0 + 3.4 * i + rng.uniform(0, 0.6), -8.0 + 3.4 * j + rng.uniform(0, 0.6)
            pts = settled([(x0 + cx * w, cy * h, z0 + cz * d) for cx, cy, cz in corners], 5)
            boxes.append((pts.min(0), pts.max(0)))
            mesh = UsdGeom.Mesh.Define(stage, f"/World/Boxes/box_{i}{j}")
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * 6))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([k for q in quads for k in q]))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            grey = round_sig(rng.uniform(0.35, 0.8))
            set_display_color(mesh, [(grey, grey, round_sig(grey * 0.9))])
    ground = MeshBuilder()
    ground.add_poly([(-12.0, 0.0, -12.0), (-12.0, 0.0, 12.0), (12.0, 0.0, 12.0), (12.0, 0.0, -12.0)],
                    (0.5, 0.5, 0.5), UP)
    define_mesh(stage, "/World/Ground", ground)
    UsdGeom.Xform.Define(stage, "/World/Lights")
    # at least 0.6 from every surface: a bulb grazing a wall makes a hot spot whose pixel integral a
    # reference renderer takes thousands of samples to settle
    positions = []
    while len(positions) < 16:
        pos = settled((rng.uniform(-9, 9), rng.uniform(0.6, 6.0), rng.uniform(-9, 9)), 3)
        if all(np.linalg.norm(pos - np.clip(pos, lo, hi)) >= 0.6 for lo, hi in boxes):
            positions.append(pos)
    for k, pos in enumerate(positions):
        light = UsdLux.SphereLight.Define(stage, f"/World/Lights/bulb_{k:02d}")
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(0.1)
        light.CreateIntensityAttr(2000.0)
        light.CreateColorAttr(Gf.Vec3f(*BULBS[("warm", "cool", "white", "pink")[k % 4]]))
        light.AddTranslateOp().Set(Gf.Vec3d(*map(float, pos)))
    define_camera(stage, (15.0, 16.0, 22.0), (0.0, 0.5, 0.0), (0.5, 200.0))
    define_render_settings(stage, "out/boxes.####.exr")
    stage.Save()
    return {"boxes": 25, "lights": 16}


# --------------------------------------------------------------------------
# Dragon (paper 001's Dragon scene: one scanned model under 1,024 lights)
# --------------------------------------------------------------------------

#: the Stanford dragon (res3), read from the shared test data beside the checkout (not committed here)
DRAGON_PLY = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          "..", "shared", "assets", "meshes", "dragon_vrip_res3.ply")
DRAGON_LENGTH = 2.0  # metres, nose to tail (the scan's 0.2 units scaled up 9.8x)
#: what make_dragon writes, relative to the output folder (what --check skips when the PLY is absent)
DRAGON_FILES = ("dragon.usda", os.path.join("assets", "dragon.usdc"))


def read_ply(path):
    """Points ``(V, 3)`` float and triangles ``(T, 3)`` int of an ASCII PLY file: a vertex element
    (``x``, ``y``, ``z`` among any other scalar properties) then a face element whose one property is
    a vertex-index list of 3 (the Stanford scans' layout); other properties are read past, not kept."""
    with open(path) as f:
        header = []
        for line in f:
            header.append(line.split())
            if header[-1] == ["end_header"]:
                break
        tokens = f.read().split()
    if header[:2] != [["ply"], ["format", "ascii", "1.0"]]:
        raise ValueError(f"{path}: not an ASCII PLY file")
    elements = []    # [name, count, property names]
    for words in header:
        if words[0] == "element":
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property":
            elements[-1][2].append(words[-1])
    if [e[0] for e in elements] != ["vertex", "face"] or len(elements[1][2]) != 1:
        raise ValueError(f"{path}: expected a vertex element then a face element of one index list")
    (_, n_verts, props), (_, n_faces, _) = elements
    verts = np.array(tokens[:n_verts * len(props)], dtype=float).reshape(n_verts, len(props))
    faces = np.array(tokens[n_verts * len(props):], dtype=np.int64).reshape(n_faces, -1)
    if faces.shape[1] != 4 or np.any(faces[:, 0] != 3):
        raise ValueError(f"{path}: faces must all be triangles")
    return verts[:, [props.index(c) for c in "xyz"]], faces[:, 1:]


def write_dragon_asset(out_dir):
    """The scan as one triangle mesh, topology unmodified: scaled to ``DRAGON_LENGTH`` along X, centred
    on the origin in X and Z, feet on y = 0.  No normals: the PLY's are not unit length (0 to 2 pi,
    199 of them zero), and a polygonal mesh without them shades each triangle with its own normal.
    Returns the triangle count."""
    pts, tris = read_ply(DRAGON_PLY)
    lo, hi = pts.min(0), pts.max(0)
    pts = (pts - [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]) * (DRAGON_LENGTH / (hi[0] - lo[0]))
    mb = MeshBuilder()
    mb.points = [tuple(p) for p in settled(pts, 5)]
    mb.counts = [3] * len(tris)
    mb.indices = [int(i) for i in tris.ravel()]
    mb.colors = [(0.72, 0.60, 0.38)] * len(tris)
    write_asset(os.path.join(out_dir, "assets", "dragon.usdc"), "dragon", {"body": mb})
    return mb.triangle_count


def dome_light_positions(rng, n, center, radii, elevations):
    """``(n, 3)`` points in a shell around ``center``: azimuth uniform, elevation between
    ``elevations`` (radians) uniform in solid angle, distance uniform in ``radii``."""
    az = rng.uniform(0, 2 * math.pi, n)
    el = np.arcsin(rng.uniform(math.sin(elevations[0]), math.sin(elevations[1]), n))
    r = rng.uniform(*radii, n)
    return center + r[:, None] * np.stack([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)], -1)


def make_dragon(out_dir):
    """Paper 001's Dragon: the Stanford dragon on an 8 m ground under 1,024 static point lights
    on a dome 3-5 m away, 10-70 degrees up, so each casts its shadow on the ground and on the dragon.
    Skipped, with a line saying so, when the PLY is absent (returns None)."""
    if not os.path.isfile(DRAGON_PLY):
        print(f"dragon    skipped: {os.path.normpath(DRAGON_PLY)} not found (shared test data beside the checkout)")
        return None
    rng = np.random.default_rng(6006)
    dragon_tris = write_dragon_asset(out_dir)
    path = os.path.join(out_dir, "dragon.usda")
    stage = new_stage(path, 1, 1)
    stage.DefinePrim("/World/Dragon", "Xform").GetReferences().AddReference("./assets/dragon.usdc")
    ground = ground_grid(8.0, 12, (0.5, 0.5, 0.5))
    define_mesh(stage, "/World/Ground", ground)

    n = 1024
    positions = dome_light_positions(rng, n, np.zeros(3), (3.0, 5.0), (math.radians(10), math.radians(70)))
    proto_idx = rng.choice(3, n, p=[0.5, 0.25, 0.25])
    sx, sz = rng.uniform(-3, 3, 256), rng.uniform(-3, 3, 256)
    samples = np.stack([sx, np.zeros(256), sz], -1)
    intensity = calibrate_intensity(positions, 0.05, samples, np.tile(UP, (256, 1)), target=0.3)
    define_light_instancer(stage, None, "/World/Lights", ["warm", "cool", "white"], 0.05, intensity,
                           proto_idx, positions, None)

    # 3/4 front view from above the head (the dragon faces -X): the coils and the soft shadows
    # pooling around its feet, on the ground and between the coils, in frame.
    define_camera(stage, (-1.9, 3.1, 3.7), (0.0, 0.45, 0.0), (0.1, 100.0))
    define_render_settings(stage, "out/dragon.####.exr")
    stage.Save()
    return {"dragon_tris": dragon_tris, "ground_tris": ground.triangle_count, "lights": n,
            "intensity": intensity}


#: absolute tolerance of ``--check`` on every number of a layer: twice the finest rounding ``settled`` writes
#: positions with (1e-5), so one last-digit flip passes and any real change fails
CHECK_TOLERANCE = 2e-5


def _same_value(a, b, tol: float) -> bool:
    """Whether two layer field values agree: numbers (scalars, Gf vectors/matrices, Vt arrays) within ``tol``,
    dictionaries and lists element by element, everything else exactly."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same_value(a[k], b[k], tol) for k in a)
    if isinstance(a, (bool, str)) or isinstance(b, (bool, str)) or a is None or b is None:
        return a == b
    try:
        x, y = np.asarray(a), np.asarray(b)
    except Exception:
        return a == b
    if x.dtype.kind in "fiu" and y.dtype.kind in "fiu":
        return x.shape == y.shape and bool(np.all(np.abs(x.astype(np.float64) - y.astype(np.float64)) <= tol))
    if x.dtype == object or y.dtype == object:
        if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
            return len(a) == len(b) and all(_same_value(u, v, tol) for u, v in zip(a, b))
        return a == b
    return x.shape == y.shape and bool(np.all(x == y))


def _info(layer, spec, key: str):
    """``spec``'s field ``key`` as Python values (the one field pxr's bindings cannot convert read another way)."""
    if key == "subLayerOffsets":
        return [(o.offset, o.scale) for o in layer.subLayerOffsets]
    return spec.GetInfo(key)


def layer_differences(path_a: str, path_b: str, tol: float = CHECK_TOLERANCE) -> list[str]:
    """What differs between two USD layers (one line each, naming the spec and field); ``[]`` when none."""
    a, b = Sdf.Layer.OpenAsAnonymous(path_a), Sdf.Layer.OpenAsAnonymous(path_b)
    specs_a, specs_b = [], []
    a.Traverse(Sdf.Path.absoluteRootPath, specs_a.append)
    b.Traverse(Sdf.Path.absoluteRootPath, specs_b.append)
    out = [f"<{p}> only in one of them" for p in sorted(set(specs_a) ^ set(specs_b))]
    for p in specs_a:
        if p not in set(specs_b):
            continue
        sa, sb = a.GetObjectAtPath(p), b.GetObjectAtPath(p)
        if sa is None or sb is None:     # a path with no spec of its own (a relationship target, a variant)
            continue
        keys_a, keys_b = set(sa.ListInfoKeys()), set(sb.ListInfoKeys())
        out += [f"<{p}>.{f} only in one of them" for f in sorted(keys_a ^ keys_b)]
        out += [f"<{p}>.{f} differs" for f in sorted(keys_a & keys_b)
                if not _same_value(_info(a, sa, f), _info(b, sb, f), tol)]
    return out


def stage_differences(committed: str, generated: str, tol: float = CHECK_TOLERANCE, skip=()) -> list[str]:
    """Every difference between two folders of generated stages: files on one side only, then layer differences;
    the files in ``skip`` (relative paths) are not compared."""
    def files(root):
        return sorted(rel for d, _, fs in os.walk(root) for f in fs
                      if (rel := os.path.relpath(os.path.join(d, f), root)) not in skip)
    fa, fb = files(committed), files(generated)
    out = [f"{f}: only in one of them" for f in sorted(set(fa) ^ set(fb))]
    for f in sorted(set(fa) & set(fb)):
        out += [f"{f}: {line}" for line in layer_differences(os.path.join(committed, f), os.path.join(generated, f), tol)]
    return out


def main(argv=None):
    default_out = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "stages")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("--out", default=default_out, help="output directory (default: <repo>/stages)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a scratch folder and compare with --out; exit 1 listing what differs")
    parser.add_argument("--suite", action="store_true",
                        help="write the seeded GI / many-light suite (tools/stage_suite.py) to --out instead")
    parser.add_argument("--kinds", default="open,canyon,interior", help="--suite: stage kinds")
    parser.add_argument("--lights", default="64,1024", help="--suite: light counts (64, 1024, 100000, ...)")
    parser.add_argument("--seeds", default="0-3", help="--suite: seeds, e.g. 0-5 or 1,3 (even tune, odd report)")
    args = parser.parse_args(argv)
    if args.suite:
        from stage_suite import make_suite, parse_seeds
        if args.out == default_out:
            parser.error("--suite needs --out DIR (the suite is not written into stages/)")
        for info in make_suite(os.path.abspath(args.out), args.kinds.split(","),
                               [int(n) for n in args.lights.split(",")], parse_seeds(args.seeds)):
            print(os.path.basename(info["path"]), ", ".join(f"{k}={v}" for k, v in info.items() if k != "path"))
        return 0
    if args.check:
        with tempfile.TemporaryDirectory() as scratch:
            skipped = generate(scratch)
            differences = stage_differences(os.path.abspath(args.out), scratch, skip=skipped)
        if skipped:
            print(f"not compared (not generated here): {', '.join(skipped)}", file=sys.stderr)
        for line in differences[:50]:
            print(line, file=sys.stderr)
        if differences:
            print(f"{len(differences)} difference(s): run tools/make_stages.py to regenerate", file=sys.stderr)
        return 1 if differences else 0
    generate(os.path.abspath(args.out))
    return 0


def generate(out: str) -> list[str]:
    """Write every sample stage under ``out`` and print what each holds; returns the files (relative
    to ``out``) of the stages skipped because their source data is absent."""
    for sub in ("", "assets", "anim"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)

    report = {"city": make_city(out), "planes": make_planes(out), "creature": make_creature(out)}
    report["creature"].update(check_skinning(os.path.join(out, "creature.usda")))
    report["cornell"] = make_cornell(out)
    report["park"] = make_park(out)
    report["boxes"] = make_boxes(out)
    report["dragon"] = make_dragon(out)
    report["city_night"] = make_city_night(out)
    for name, info in report.items():
        if info is not None:
            print(f"{name:9s}", ", ".join(f"{k}={v}" for k, v in info.items()))
    return [] if report["dragon"] is not None else list(DRAGON_FILES)


if __name__ == "__main__":
    sys.exit(main())
