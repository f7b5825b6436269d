#!/usr/bin/env python
"""Generate an "unseen city": a seeded family of procedural city stages (issue 36).

Usage::

    python tools/make_city.py --seed N --out DIR [--triangles 200000]

writes ``DIR/unseen_city_<N>.usda`` (one ASCII layer, nothing else) and prints its triangle count,
what the seed chose and how long it took.

The city is deliberately *not* the sample ``stages/city.usda`` (tools/make_stages.py), on which the
renderer's defaults were tuned: no repeated building assets, no regular grid, no bird's-eye view.

* Street grid, chosen by the seed: ``irregular`` (blocks of random sizes, streets of two widths),
  ``offset`` (north-south streets run through; each column of blocks has its own east-west streets,
  so they meet in T junctions), ``diagonal`` (irregular grid cut by an avenue at 25-65 degrees) or
  ``offset_diagonal``. Raised sidewalks with kerb stones, lane dashes, zebra crossings.
* Buildings, each one plain flattened mesh (its own points, no instancing): extruded boxes on
  rectangle, L and U footprints (shops with awnings on the ground floor, balconies, parapets or roof
  railings, roof units, water tanks), towers with two to four setback tiers (railed terraces, spire
  or antenna), gable-roofed houses with chimneys; parks with trees and benches, parking lots.
  Windows are recessed, flush or ribbon, per building.
* Props: lamp posts, trees (cones, firs, boxes), parked cars (boxes), benches. The seed picks one or
  two of these kinds to be native instances (``instanceable`` Xforms referencing prototypes under the
  class prim </World/Prototypes>); the others are flattened into one mesh per block.
* The triangle budget (``--triangles``, default 200,000, counted after instancing) sets the city's
  size (its side grows with the square root of the budget); what the streets, roofs, features and
  props leave is spent on facade windows, whose bay width is solved so that the total lands within
  about 1 % of the request. A city that would need windows far denser or sparser than usual for
  that (``DETAIL_RANGE``) is planned again, larger or smaller.
* 1,024 point lights (a PointInstancer of SphereLights, ``treatAsPoint``, ``normalize = false``,
  intensity by ``calibrate_intensity``: 0.6 mean unshadowed radiance on the streets) drift 2-10 m
  above the streets (clear of kerbs, trees and lamp arms) and the roofs (above everything standing
  on them) over frames 1-24, none within 6 m of the lens; the camera </World/main_cam> stands
  1.6-2.4 m above a street, near one end, looking down it and dollying 2-4 m over the shot (no
  parked car within 9 m of it).

Conventions are stage_build.py's (imported from it, as make_stages.py does): metersPerUnit 1, upAxis Y,
24 fps, defaultPrim </World>, a 35 mm lens on a 36 x 20.25 mm back, </Render/Settings> named by
``renderSettingsPrimPath``.
Deterministic: the same seed and budget give the same bytes (no timestamps, every value rounded).

Seeds: **even seeds are for tuning, odd seeds for reporting** (issues 36/37: tune on one half,
report on the other). Pick parameters by looking at even-seeded cities only; quote results on
odd-seeded ones, which nothing was tuned on.
"""
import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from make_stages import add_facade  # noqa: E402
from stage_build import (UP, MeshBuilder, calibrate_intensity, define_camera, define_light_instancer,  # noqa: E402
                         define_mesh, define_render_settings, frame_times, new_stage, regular_polygon, settled)

DEFAULT_TRIANGLES = 200_000
#: side of the city (m) at the default budget; it scales with the square root of the budget
BASE_SIZE = 300.0
MIN_SIZE = 70.0
N_LIGHTS = 1024
FIRST, LAST = 1, 24
LIGHT_RADIUS = 0.1
CURB = 0.15
GRID_MODES = ("irregular", "offset", "diagonal", "offset_diagonal")
PROP_KINDS = ("lamp", "tree", "car", "bench")
BUILDING_KINDS = ("tower", "box", "gable")
#: triangles of one facade cell (a window and the wall around it) of each window style
CELL_TRIS = {"recessed": 18, "flush": 10, "ribbon": 6, "blank": 2}


def rgb(r, g, b):
    return (round(r, 3), round(g, 3), round(b, 3))


def shade(c, k):
    return rgb(*(min(1.0, x * k) for x in c))


WALLS = [rgb(0.55, 0.28, 0.20), rgb(0.62, 0.36, 0.26), rgb(0.78, 0.72, 0.60), rgb(0.85, 0.84, 0.80),
         rgb(0.60, 0.60, 0.58), rgb(0.72, 0.58, 0.42), rgb(0.50, 0.52, 0.56), rgb(0.82, 0.70, 0.52),
         rgb(0.66, 0.70, 0.66), rgb(0.40, 0.42, 0.45)]
GLASSES = [rgb(0.10, 0.15, 0.22), rgb(0.12, 0.20, 0.20), rgb(0.16, 0.16, 0.18), rgb(0.20, 0.24, 0.30)]
ROOFS = [rgb(0.45, 0.20, 0.16), rgb(0.30, 0.30, 0.32), rgb(0.38, 0.26, 0.20), rgb(0.25, 0.32, 0.30)]
AWNINGS = [rgb(0.60, 0.12, 0.10), rgb(0.15, 0.35, 0.20), rgb(0.16, 0.24, 0.50), rgb(0.80, 0.62, 0.16)]
CARS = [rgb(0.62, 0.08, 0.08), rgb(0.14, 0.22, 0.48), rgb(0.85, 0.85, 0.85), rgb(0.30, 0.32, 0.34)]
GREY, METAL, DARK = rgb(0.50, 0.50, 0.52), rgb(0.72, 0.74, 0.78), rgb(0.22, 0.23, 0.25)
LEAF, BARK, GRASS = rgb(0.20, 0.38, 0.16), rgb(0.35, 0.25, 0.16), rgb(0.26, 0.40, 0.20)


# --------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------

class Builder(MeshBuilder):
    """stage_build's MeshBuilder with a pure-Python polygon add (the city has ~100k polygons) and
    ``append`` to flatten a prop into a bigger mesh."""

    def add_poly(self, pts, color, outward):
        pts = [(float(p[0]), float(p[1]), float(p[2])) for p in pts]
        nx = ny = nz = 0.0
        for (ax, ay, az), (bx, by, bz) in zip(pts, pts[1:] + pts[:1]):
            nx += ay * bz - az * by
            ny += az * bx - ax * bz
            nz += ax * by - ay * bx
        if nx * outward[0] + ny * outward[1] + nz * outward[2] < 0:
            pts = pts[::-1]
        self.counts.append(len(pts))
        self.indices.extend(self._vertex(p) for p in pts)
        self.colors.append(tuple(color))

    def append(self, other, yaw_deg=0.0, scale=1.0, offset=(0.0, 0.0, 0.0)):
        """``other``'s polygons scaled, turned ``yaw_deg`` about +Y (as xformOp:rotateY) and moved."""
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        ox, oy, oz = offset
        base = len(self.points)
        for x, y, z in other.points:
            x, y, z = x * scale, y * scale, z * scale
            self.points.append((round(c * x + s * z + ox, 5), round(y + oy, 5), round(-s * x + c * z + oz, 5)))
        self.counts.extend(other.counts)
        self.indices.extend(i + base for i in other.indices)
        self.colors.extend(other.colors)


def vec(x, z, y=0.0):
    return np.array((x, y, z), dtype=float)


def add_slab(mb, poly, y0, y1, color):
    """Vertical extrusion of a convex (x, z) polygon from y0 to y1."""
    mb.add_prism(poly, (0, 0, 0), (1, 0, 0), (0, 0, 1), -y1, -y0, color)


def add_box_between(mb, p, q, y0, y1, color):
    """Axis-aligned box spanning points p and q (3D, any order) in x/z, y0..y1 in height."""
    mb.add_box((min(p[0], q[0]), y0, min(p[2], q[2])), (max(p[0], q[0]), y1, max(p[2], q[2])), color)


def signed_area(poly):
    return 0.5 * sum(x0 * z1 - x1 * z0 for (x0, z0), (x1, z1) in zip(poly, poly[1:] + poly[:1]))


def outline_edges(poly):
    """(origin, u, outward normal, width) of each edge of a simple (x, z) polygon, as 3D arrays."""
    sgn = 1.0 if signed_area(poly) > 0 else -1.0
    out = []
    for (ax, az), (bx, bz) in zip(poly, poly[1:] + poly[:1]):
        length = math.hypot(bx - ax, bz - az)
        ux, uz = (bx - ax) / length, (bz - az) / length
        out.append((vec(ax, az), vec(ux, uz), vec(sgn * uz, -sgn * ux), length))
    return out


def clip_half(poly, n, c):
    """The part of convex polygon ``poly`` where n . p >= c (Sutherland-Hodgman, one plane)."""
    out = []
    for p, q in zip(poly, poly[1:] + poly[:1]):
        dp, dq = n[0] * p[0] + n[1] * p[1] - c, n[0] * q[0] + n[1] * q[1] - c
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            t = dp / (dp - dq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def inset_convex(poly, delta):
    """Convex (x, z) polygon with every edge moved ``delta`` inwards."""
    sgn = 1.0 if signed_area(poly) > 0 else -1.0
    lines = []
    for (ax, az), (bx, bz) in zip(poly, poly[1:] + poly[:1]):
        length = math.hypot(bx - ax, bz - az)
        nx, nz = -sgn * (bz - az) / length, sgn * (bx - ax) / length     # inward
        lines.append((nx, nz, nx * ax + nz * az + delta))
    out = []
    for (n1x, n1z, c1), (n2x, n2z, c2) in zip(lines[-1:] + lines[:-1], lines):
        det = n1x * n2z - n1z * n2x
        out.append(((c1 * n2z - c2 * n1z) / det, (n1x * c2 - n2x * c1) / det))
    return out


def rect_poly(x0, x1, z0, z1):
    return [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]


# --------------------------------------------------------------------------
# Street grid
# --------------------------------------------------------------------------

@dataclass
class Street:
    a: tuple
    b: tuple
    width: float
    kind: str            # "x" (runs along X), "z" (along Z) or "avenue"

    @property
    def length(self):
        return math.hypot(self.b[0] - self.a[0], self.b[1] - self.a[1])

    @property
    def dir(self):
        return ((self.b[0] - self.a[0]) / self.length, (self.b[1] - self.a[1]) / self.length)

    def contains(self, x, z, pad=0.0):
        dx, dz = self.dir
        rx, rz = x - self.a[0], z - self.a[1]
        along, lat = rx * dx + rz * dz, -rx * dz + rz * dx
        return -pad <= along <= self.length + pad and abs(lat) <= self.width / 2 + pad


@dataclass
class Grid:
    mode: str
    size: float
    streets: list
    blocks: list         # (x0, x1, z0, z1) between the streets
    avenue: tuple = None  # (unit normal (nx, nz), offset c, half width): the strip |n . p - c| < hw


def split_line(rng, length, period, main_p):
    """Street centres, widths and the block spans between them along one axis of ``length``."""
    n = max(2, int(round(length / period)))
    widths = np.where(rng.random(n + 1) < main_p, rng.uniform(15.0, 19.0, n + 1), rng.uniform(9.5, 12.5, n + 1))
    widths = settled(widths * min(1.0, 0.4 * length / widths.sum()), 2)
    blocks = rng.uniform(0.6, 1.5, n)
    blocks = blocks * (length - widths.sum()) / blocks.sum()
    pos, centers, spans = -length / 2, [], []
    for k in range(n + 1):
        centers.append(round(pos + widths[k] / 2, 3))
        pos += widths[k]
        if k < n:
            spans.append((round(pos, 3), round(pos + blocks[k], 3)))
            pos += blocks[k]
    return centers, [float(w) for w in widths], spans


def street_grid(rng, size):
    mode = GRID_MODES[int(rng.integers(len(GRID_MODES)))]
    period = min(62.0, size / 2.2)
    h = size / 2
    xc, xw, xspans = split_line(rng, size, period, 0.3)
    streets = [Street((x, -h), (x, h), w, "z") for x, w in zip(xc, xw)]
    blocks = []
    if mode.startswith("offset"):
        for ci, (x0, x1) in enumerate(xspans):
            zc, zw, zspans = split_line(rng, size, period * rng.uniform(0.7, 1.3), 0.2)
            streets += [Street((xc[ci], z), (xc[ci + 1], z), w, "x") for z, w in zip(zc, zw)]
            blocks += [(x0, x1, z0, z1) for z0, z1 in zspans]
    else:
        zc, zw, zspans = split_line(rng, size, period, 0.3)
        streets += [Street((-h, z), (h, z), w, "x") for z, w in zip(zc, zw)]
        blocks = [(x0, x1, z0, z1) for x0, x1 in xspans for z0, z1 in zspans]
    avenue = None
    if mode.endswith("diagonal"):
        theta = math.radians(rng.uniform(25.0, 65.0)) * (1 if rng.random() < 0.5 else -1)
        d = (math.cos(theta), math.sin(theta))
        p0 = rng.uniform(-size / 6, size / 6, 2)
        width = round(min(22.0, 0.22 * size) * rng.uniform(0.85, 1.0), 2)
        # the line p0 + t d clipped to the square
        ts = sorted([(-h - p0[0]) / d[0], (h - p0[0]) / d[0]])
        tz = sorted([(-h - p0[1]) / d[1], (h - p0[1]) / d[1]])
        t0, t1 = max(ts[0], tz[0]), min(ts[1], tz[1])
        a = (round(p0[0] + t0 * d[0], 3), round(p0[1] + t0 * d[1], 3))
        b = (round(p0[0] + t1 * d[0], 3), round(p0[1] + t1 * d[1], 3))
        streets.append(Street(a, b, width, "avenue"))
        n = (-d[1], d[0])
        avenue = (n, n[0] * p0[0] + n[1] * p0[1], width / 2)
    return Grid(mode, size, streets, blocks, avenue)


def block_pieces(grid, rect):
    """The sidewalk polygons of a block: its rectangle, or the parts of it either side of the avenue."""
    poly = rect_poly(*rect)
    if grid.avenue is None:
        return [poly]
    (nx, nz), c, hw = grid.avenue
    pieces = [clip_half(poly, (nx, nz), c + hw), clip_half(poly, (-nx, -nz), -(c - hw))]
    return [p for p in pieces if len(p) >= 3 and abs(signed_area(p)) > 30.0]


def clear_of_avenue(grid, corners, margin):
    """Whether all ``corners`` lie on one side of the avenue, ``margin`` beyond its edge."""
    if grid.avenue is None:
        return True
    (nx, nz), c, hw = grid.avenue
    dists = [nx * x + nz * z - c for x, z in corners]
    return all(d >= hw + margin for d in dists) or all(d <= -(hw + margin) for d in dists)


# --------------------------------------------------------------------------
# Lots and buildings
# --------------------------------------------------------------------------

@dataclass
class Lot:
    """A lot: ``width`` along its street front, ``depth`` inwards; to_world maps (s, t) to (x, z)."""
    origin: tuple
    eu: tuple
    et: tuple
    width: float
    depth: float

    def to_world(self, s, t):
        return (round(self.origin[0] + s * self.eu[0] + t * self.et[0], 4),
                round(self.origin[1] + s * self.eu[1] + t * self.et[1], 4))

    def rect(self, s0, s1, t0, t1):
        (ax, az), (bx, bz) = self.to_world(s0, t0), self.to_world(s1, t1)
        return (min(ax, bx), max(ax, bx), min(az, bz), max(az, bz))

    @property
    def center(self):
        return self.to_world(self.width / 2, self.depth / 2)


def lot_frame(side, x0, x1, z0, z1):
    """(origin, eu, et, width, depth) of a lot in rect x0..x1, z0..z1 whose front is ``side``."""
    if side == "z0":
        return (x0, z0), (1, 0), (0, 1), x1 - x0, z1 - z0
    if side == "z1":
        return (x0, z1), (1, 0), (0, -1), x1 - x0, z1 - z0
    if side == "x0":
        return (x0, z0), (0, 1), (1, 0), z1 - z0, x1 - x0
    return (x1, z0), (0, 1), (-1, 0), z1 - z0, x1 - x0


def subdivide(rng, inner):
    """Lots of an inner block rectangle: one or two rows facing the long sides, cut at random widths."""
    x0, x1, z0, z1 = inner
    along_x = (x1 - x0) >= (z1 - z0)
    long0, long1 = (x0, x1) if along_x else (z0, z1)
    short0, short1 = (z0, z1) if along_x else (x0, x1)
    fronts = ("z0", "z1") if along_x else ("x0", "x1")
    if short1 - short0 > 34.0:
        cut = short0 + (short1 - short0) * rng.uniform(0.4, 0.6)
        rows = [(short0, cut, fronts[0]), (cut, short1, fronts[1])]
    else:
        rows = [(short0, short1, fronts[int(rng.integers(2))])]
    lots = []
    for s0, s1, front in rows:
        pos = long0
        while long1 - pos > 1e-6:
            w = rng.uniform(10.0, 26.0)
            if long1 - pos - w < 9.0:
                w = long1 - pos
            a, b = pos, pos + w
            pos = b
            rect = (a, b, s0, s1) if along_x else (s0, s1, a, b)
            lots.append(Lot(*lot_frame(front, *rect)))
    return lots


def clear_lot(grid, lot, margin, min_side=8.0):
    """``lot``, or the largest part of it clear of the avenue (trimmed at one end or at the back,
    keeping its street front), or None."""
    def clear(s0, s1, t1):
        return clear_of_avenue(grid, [lot.to_world(s, t) for s in (s0, s1) for t in (0.0, t1)], margin)

    if clear(0.0, lot.width, lot.depth):
        return lot
    for cut in np.arange(0.5, max(lot.width, lot.depth), 0.5):
        fits = [((s1 - s0) * t1, s0, s1, t1) for s0, s1, t1 in
                ((cut, lot.width, lot.depth), (0.0, lot.width - cut, lot.depth), (0.0, lot.width, lot.depth - cut))
                if s1 - s0 >= min_side and t1 >= min_side and clear(s0, s1, t1)]
        if fits:
            _, s0, s1, t1 = max(fits)
            return Lot(lot.to_world(s0, 0.0), lot.eu, lot.et, s1 - s0, t1)
    return None


@dataclass
class Band:
    """Floors of one window style on every edge of a facade outline."""
    y0: float
    floors: int
    floor_h: float
    style: str
    win: tuple           # (win_w, win_h, sill, depth) as fractions of a cell, depth in m
    bay_w: float
    fixed: bool = False  # bays set by bay_w alone, not by the solved detail


@dataclass
class Facade:
    outline: list
    bands: list
    wall: tuple
    trim: tuple
    glass: tuple
    widths: list = field(default_factory=list)

    def __post_init__(self):
        self.widths = [w for _, _, _, w in outline_edges(self.outline)]


def edge_bays(width, band, detail):
    if width < 2.0:
        return 1
    per = band.bay_w if band.fixed else band.bay_w / detail
    return max(1, min(int(width / 0.9), int(round(width / per))))


def facade_tris(f, detail):
    return sum(b.floors * edge_bays(w, b, detail) * CELL_TRIS["blank" if w < 2.0 else b.style]
               for w in f.widths for b in f.bands)


def add_cells(mb, origin, u, n, width, band, bays, wall, trim, glass):
    """One band of facade cells on one edge: ``CELL_TRIS[style]`` triangles a cell."""
    win_w, win_h, sill, depth = band.win
    style = "blank" if width < 2.0 else band.style
    if style == "recessed":
        add_facade(mb, origin, u, n, width, band.y0, band.floors, band.floor_h, bays, wall, trim,
                   glass=glass, win_w=win_w, win_h=win_h, sill=sill, depth=depth)
        return
    cw, h = width / bays, band.floor_h
    s0, s1 = cw * (1 - win_w) / 2, cw * (1 + win_w) / 2
    t0, t1 = h * sill, h * (sill + win_h)
    for f in range(band.floors):
        for b in range(bays):
            base = origin + u * (b * cw) + UP * (band.y0 + f * h)

            def quad(sa, sb, ta, tb, color):
                mb.add_poly([base + u * sa + UP * ta, base + u * sb + UP * ta,
                             base + u * sb + UP * tb, base + u * sa + UP * tb], color, n)

            if style == "blank":
                quad(0, cw, 0, h, wall)
            elif style == "ribbon":
                quad(0, cw, 0, t0, wall)
                quad(0, cw, t0, t1, glass)
                quad(0, cw, t1, h, trim)
            else:                                   # flush
                quad(0, cw, 0, t0, wall)
                quad(0, cw, t1, h, wall)
                quad(0, s0, t0, t1, wall)
                quad(s1, cw, t0, t1, wall)
                quad(s0, s1, t0, t1, glass)


def build_facade(mb, f, detail):
    for (origin, u, n, width) in outline_edges(f.outline):
        for band in f.bands:
            add_cells(mb, origin, u, n, width, band, edge_bays(width, band, detail), f.wall, f.trim, f.glass)


@dataclass
class Building:
    path: str
    kind: str
    mb: Builder
    facades: list
    top: float
    bbox: tuple          # (x0, x1, z0, z1) of the footprint


def window_style(rng, kinds=("recessed", "flush", "ribbon"), p=(0.5, 0.3, 0.2)):
    style = str(rng.choice(kinds, p=p))
    if style == "recessed":
        return style, (round(rng.uniform(0.45, 0.7), 2), round(rng.uniform(0.45, 0.6), 2), 0.3,
                       round(rng.uniform(0.15, 0.3), 2))
    if style == "flush":
        return style, (round(rng.uniform(0.5, 0.75), 2), 0.5, 0.3, 0.0)
    return style, (1.0, round(rng.uniform(0.4, 0.6), 2), 0.3, 0.0)


def add_parapet_outline(mb, outline, y, color, thick=0.25, height=0.9):
    for origin, u, n, width in outline_edges(outline):
        add_box_between(mb, origin, origin + u * width - n * thick, y, y + height, color)


def add_railing_outline(mb, outline, y, color, inset=0.3, height=1.0, spacing=1.6):
    """Thin posts and a top rail along every edge: detail far below a voxel."""
    for origin, u, n, width in outline_edges(outline):
        a = origin - n * inset
        posts = max(1, int(width / spacing))
        for k in range(posts + 1):
            p = a + u * (width * k / posts)
            add_box_between(mb, p - u * 0.03 - n * 0.03, p + u * 0.03 + n * 0.03, y, y + height, color)
        add_box_between(mb, a - n * 0.025, a + u * width + n * 0.025, y + height, y + height + 0.05, color)


def add_roof(mb, rects, y, color):
    for x0, x1, z0, z1 in rects:
        mb.add_poly([(x0, y, z0), (x1, y, z0), (x1, y, z1), (x0, y, z1)], color, UP)


def add_roof_units(rng, mb, rect, y):
    """Air-handling boxes and maybe a water tank on stilts, inside ``rect``."""
    x0, x1, z0, z1 = rect
    if x1 - x0 < 5 or z1 - z0 < 5:
        return
    for _ in range(int(rng.integers(1, 4))):
        w, d, h = rng.uniform(1.2, 3.0), rng.uniform(1.2, 3.0), rng.uniform(0.8, 2.2)
        cx, cz = rng.uniform(x0 + 1 + w / 2, max(x0 + 1 + w / 2, x1 - 1 - w / 2)), \
            rng.uniform(z0 + 1 + d / 2, max(z0 + 1 + d / 2, z1 - 1 - d / 2))
        mb.add_box((cx - w / 2, y, cz - d / 2), (cx + w / 2, y + h, cz + d / 2), GREY)
    if rng.random() < 0.35:
        cx, cz = (x0 + x1) / 2 + rng.uniform(-1, 1), (z0 + z1) / 2 + rng.uniform(-1, 1)
        legs = y + rng.uniform(1.5, 2.5)
        for sx, sz in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            mb.add_box((cx + sx * 1.0 - 0.06, y, cz + sz * 1.0 - 0.06), (cx + sx * 1.0 + 0.06, legs, cz + sz * 1.0 + 0.06),
                       DARK)
        mb.add_cylinder((cx, cz), 1.4, legs, legs + 2.4, 8, rgb(0.45, 0.32, 0.20))
        mb.add_pyramid((cx, cz), 1.5, legs + 2.4, 0.8, 8, DARK)


def add_balconies_edge(rng, mb, edge, y0, floors, floor_h, slab, rail):
    """Balconies (slab + three thin glass panels) on floors 1.. of one facade edge, fixed spacing."""
    origin, u, n, width = edge
    slots = max(1, int(width / rng.uniform(3.6, 5.0)))
    depth = rng.uniform(1.0, 1.4)
    for f in range(1, floors):
        y = y0 + f * floor_h
        for k in range(slots):
            c = (k + 0.5) * width / slots
            half = min(1.6, 0.32 * width / slots)
            a, b = origin + u * (c - half), origin + u * (c + half)
            add_box_between(mb, a, b + n * depth, y - 0.15, y, slab)
            add_box_between(mb, a + n * (depth - 0.04), b + n * depth, y, y + 1.0, rail)
            add_box_between(mb, a, a + u * 0.04 + n * depth, y, y + 1.0, rail)
            add_box_between(mb, b - u * 0.04, b + n * depth, y, y + 1.0, rail)


def add_awnings(mb, edge, y, cells, color):
    """A sloped thin awning over each of ``cells`` shop windows of one edge."""
    origin, u, n, width = edge
    for k in range(cells):
        mid = origin + u * ((k + 0.5) * width / cells) + UP * y
        mb.add_beam(mid, mid + n * 1.5 - UP * 0.55, 0.8 * width / cells, 0.06, color, up_hint=UP * 1.5 + n * 0.55)


def plan_box(rng, lot, g, mb):
    """Extruded block on a rectangle, L or U footprint, its features into ``mb``: (facades, bbox)."""
    W, D = lot.width, lot.depth
    side0, side1 = (rng.uniform(0.0, 1.2, 2) if W > 14 else (0.3, 0.3))
    setback = rng.uniform(0.0, 1.5)
    fw = W - side0 - side1
    fd = max(min(8.0, D - setback - 0.3), min(D - setback - rng.uniform(0.5, 3.0), rng.uniform(10.0, 24.0)))
    shapes, p = ["rect"], [0.5]
    if fw >= 12 and fd >= 10:
        shapes.append("L")
        p.append(0.3)
    if fw >= 16 and fd >= 14:
        shapes.append("U")
        p.append(0.25)
    shape = str(rng.choice(shapes, p=np.array(p) / sum(p)))
    if shape == "rect":
        local = [(0, 0), (fw, 0), (fw, fd), (0, fd)]
        roofs = [(0, fw, 0, fd)]
    elif shape == "L":
        a, b = fw * rng.uniform(0.4, 0.65), fd * rng.uniform(0.4, 0.65)
        local = [(0, 0), (fw, 0), (fw, b), (a, b), (a, fd), (0, fd)]
        roofs = [(0, fw, 0, b), (0, a, b, fd)]
        if rng.random() < 0.5:                      # the notch on the other side
            local = [(fw - s, t) for s, t in local]
            roofs = [(fw - s1, fw - s0, t0, t1) for s0, s1, t0, t1 in roofs]
    else:
        a1, a2, b = fw * rng.uniform(0.3, 0.38), fw * rng.uniform(0.62, 0.7), fd * rng.uniform(0.35, 0.55)
        local = [(0, 0), (fw, 0), (fw, fd), (a2, fd), (a2, b), (a1, b), (a1, fd), (0, fd)]
        roofs = [(0, fw, 0, b), (0, a1, b, fd), (a2, fw, b, fd)]
    outline = [lot.to_world(side0 + s, setback + t) for s, t in local]
    roof_rects = [lot.rect(side0 + s0, side0 + s1, setback + t0, setback + t1) for s0, s1, t0, t1 in roofs]
    floors = int(rng.integers(3, 7 + int(7 * g)))
    floor_h = rng.uniform(3.0, 3.5)
    wall = WALLS[int(rng.integers(len(WALLS)))]
    trim, glass = shade(wall, 0.75), GLASSES[int(rng.integers(len(GLASSES)))]
    style, win = window_style(rng)
    bay_w = rng.uniform(2.6, 4.0)
    bands, y = [], CURB
    front = outline_edges(outline)[0]
    if rng.random() < 0.55:                          # shops on the ground floor
        shop_w = rng.uniform(4.0, 6.5)
        bands.append(Band(y, 1, 4.2, "recessed", (0.82, 0.62, 0.1, 0.2), shop_w, fixed=True))
        add_awnings(mb, front, y + 3.55, max(1, int(round(front[3] / shop_w))),
                    AWNINGS[int(rng.integers(len(AWNINGS)))])
        y += 4.2
        floors -= 1
    bands.append(Band(y, floors, floor_h, style, win, bay_w))
    if rng.random() < 0.4:
        add_balconies_edge(rng, mb, front, y, floors, floor_h, rgb(0.70, 0.70, 0.68), DARK)
    top = y + floors * floor_h
    roof_c = shade(wall, 0.85)
    add_roof(mb, roof_rects, top, roof_c)
    if rng.random() < 0.65:
        add_parapet_outline(mb, outline, top, wall, height=rng.uniform(0.6, 1.2))
    else:
        add_railing_outline(mb, outline, top, METAL)
    add_roof_units(rng, mb, roof_rects[0], top)
    xs, zs = [p[0] for p in outline], [p[1] for p in outline]
    return [Facade(outline, bands, wall, trim, glass)], (min(xs), max(xs), min(zs), max(zs))


def plan_tower(rng, lot, g, mb):
    """Tower of 2-4 setback tiers: railed terraces, a lobby floor, a spire, antenna or plant room."""
    W, D = lot.width, lot.depth
    side = rng.uniform(0.5, 2.0, 2)
    setback = rng.uniform(0.5, 3.0)
    s0, s1 = side[0], W - side[1]
    t0, t1 = setback, setback + min(D - setback - 1.0, 34.0)
    floors_total = int(np.clip(10 + g * 26 * rng.uniform(0.6, 1.15), 10, 38))
    tiers = int(rng.integers(2, 5))
    floor_h = rng.uniform(3.3, 3.8)
    wall = WALLS[int(rng.integers(len(WALLS)))]
    trim, glass = shade(wall, 0.7), GLASSES[int(rng.integers(len(GLASSES)))]
    style, win = window_style(rng, p=(0.3, 0.3, 0.4))
    bay_w = rng.uniform(2.8, 4.2)
    facades, y = [], CURB
    bbox = lot.rect(s0, s1, t0, t1)
    left = floors_total
    for k in range(tiers):
        rect = lot.rect(s0, s1, t0, t1)
        outline = rect_poly(*rect)
        last = k == tiers - 1 or min(s1 - s0, t1 - t0) < 14.0
        nf = left if last else max(3, int(left * rng.uniform(0.35, 0.6)))
        bands = []
        if k == 0:                                   # tall glazed lobby
            bands.append(Band(y, 1, 5.0, "recessed", (0.85, 0.7, 0.08, 0.3), rng.uniform(4.0, 6.0), fixed=True))
            y += 5.0
            nf -= 1
        bands.append(Band(y, nf, floor_h, style, win, bay_w))
        y += nf * floor_h
        left -= nf + (1 if k == 0 else 0)
        facades.append(Facade(outline, bands, wall, trim, glass))
        add_roof(mb, [rect], y, shade(wall, 0.8))
        if last or left <= 0:
            break
        if rng.random() < 0.7:                       # the terrace this tier leaves
            add_railing_outline(mb, outline, y, METAL)
        else:
            add_parapet_outline(mb, outline, y, wall, height=0.8)
        cuts = rng.uniform(1.5, 4.0, 4) * (rng.random(4) < 0.75)
        s0, s1, t0, t1 = s0 + cuts[0], s1 - cuts[1], t0 + cuts[2], t1 - cuts[3]
    add_parapet_outline(mb, outline, y, wall, height=1.0)
    cx, cz = (rect[0] + rect[1]) / 2, (rect[2] + rect[3]) / 2
    r = min(rect[1] - rect[0], rect[3] - rect[2]) / 2
    crown = int(rng.integers(3))
    if crown == 0:                                   # spire
        mb.add_cylinder((cx, cz), 0.55 * r, y, y + 3.0, 6, wall)
        mb.add_pyramid((cx, cz), 0.55 * r, y + 3.0, 2.5 * r, 6, METAL)
    elif crown == 1:                                 # antenna mast with two cross bars
        h = rng.uniform(8.0, 16.0)
        mb.add_box((cx - 1.5, y, cz - 1.5), (cx + 1.5, y + 2.5, cz + 1.5), GREY)
        mb.add_cylinder((cx, cz), 0.1, y + 2.5, y + 2.5 + h, 6, METAL)
        for k in (0.5, 0.8):
            yy = y + 2.5 + k * h
            mb.add_box((cx - 1.2, yy, cz - 0.04), (cx + 1.2, yy + 0.08, cz + 0.04), METAL)
    else:
        add_roof_units(rng, mb, rect, y)
    return facades, bbox


def plan_gable(rng, lot, mb):
    """House of 2-3 floors under a pitched roof, with a chimney and a porch canopy."""
    W, D = lot.width, lot.depth
    side = rng.uniform(0.5, 2.0, 2) if W > 9 else (0.3, 0.3)
    setback = rng.uniform(1.0, 3.5)
    fw = W - side[0] - side[1]
    fd = min(D - setback - 0.5, rng.uniform(7.0, 12.0))
    x0, x1, z0, z1 = lot.rect(side[0], side[0] + fw, setback, setback + fd)
    floors, floor_h = int(rng.integers(2, 4)), rng.uniform(2.8, 3.1)
    wall = WALLS[int(rng.integers(len(WALLS)))]
    trim, glass = shade(wall, 0.75), GLASSES[int(rng.integers(len(GLASSES)))]
    style, win = window_style(rng, ("recessed", "flush"), (0.6, 0.4))
    outline = rect_poly(x0, x1, z0, z1)
    facade = Facade(outline, [Band(CURB, floors, floor_h, style, win, rng.uniform(2.4, 3.4))], wall, trim, glass)
    eave = CURB + floors * floor_h
    ridge_x = (rng.random() < 0.5) == ((x1 - x0) >= (z1 - z0))   # ridge along the long side, mostly
    ridge_x = ridge_x if rng.random() < 0.8 else not ridge_x
    # (r, c): along and across the ridge; to 3D by axis
    if ridge_x:
        r0, r1, c0, c1 = x0, x1, z0, z1
        along, across = vec(1, 0), vec(0, 1)
    else:
        r0, r1, c0, c1 = z0, z1, x0, x1
        along, across = vec(0, 1), vec(1, 0)
    half = (c1 - c0) / 2
    cm = (c0 + c1) / 2
    pitch = math.tan(math.radians(rng.uniform(28.0, 45.0)))
    ridge = eave + half * pitch
    roof_c = ROOFS[int(rng.integers(len(ROOFS)))]

    def P(r, y, c):
        return along * r + across * c + UP * y

    for r in (r0, r1):                               # gable triangles over the end walls
        mb.add_poly([P(r, eave, c0), P(r, eave, c1), P(r, ridge, cm)], wall, along * (1 if r == r1 else -1))
    over, th = 0.45, 0.18
    w = np.cross(across, UP)                         # add_prism's extrusion axis for (u, v) = (across, up)
    w_lo, w_hi = sorted((float(np.dot(w, along)) * (r0 - 0.35), float(np.dot(w, along)) * (r1 + 0.35)))
    for sgn, ce in ((-1, c0), (1, c1)):
        ye = eave - over * pitch
        prof = [(ce + sgn * over, ye), (cm, ridge), (cm, ridge + th), (ce + sgn * over, ye + th)]
        mb.add_prism(prof, (0, 0, 0), across, (0, 1, 0), w_lo, w_hi, roof_c)
    # chimney through one slope
    cr = r0 + (r1 - r0) * rng.uniform(0.2, 0.8)
    cc = cm + (rng.uniform(0.25, 0.6) * half) * (1 if rng.random() < 0.5 else -1)
    p, q = P(cr - 0.35, 0, cc - 0.35), P(cr + 0.35, 0, cc + 0.35)
    add_box_between(mb, p, q, eave, ridge + 0.9, rgb(0.50, 0.30, 0.24))
    add_box_between(mb, P(cr - 0.45, 0, cc - 0.45), P(cr + 0.45, 0, cc + 0.45), ridge + 0.9, ridge + 1.05, DARK)
    # porch canopy on two thin posts in front of the street side
    front = outline_edges(outline)[[i for i, e in enumerate(outline_edges(outline))
                                    if abs(e[2][0] * -lot.et[0] + e[2][2] * -lot.et[1]) > 0.5
                                    and e[2][0] * -lot.et[0] + e[2][2] * -lot.et[1] > 0][0]]
    origin, u, n, width = front
    c = width * rng.uniform(0.3, 0.7)
    a, b = origin + u * (c - 1.2), origin + u * (c + 1.2)
    add_box_between(mb, a, b + n * 1.4, CURB + 2.5, CURB + 2.62, roof_c)
    for e in (a, b - u * 0.08):
        add_box_between(mb, e + n * 1.3, e + u * 0.08 + n * 1.38, CURB, CURB + 2.5, rgb(0.85, 0.85, 0.82))
    return [facade], (x0, x1, z0, z1)


# --------------------------------------------------------------------------
# Props
# --------------------------------------------------------------------------

PROP_VARIANTS = {
    "lamp": ["arm", "lantern"],
    "tree": ["cone", "fir", "box"],
    "car": ["sedan_red", "sedan_blue", "van_white", "hatch_grey"],
    "bench": ["wood"],
}


def prop_mesh(kind, variant):
    """A prop in its own space: on y = 0, facing +Z (lamp arm, bench front, car nose)."""
    mb = Builder()
    if kind == "lamp":
        pole = rgb(0.22, 0.24, 0.26)
        mb.add_box((-0.18, 0.0, -0.18), (0.18, 0.5, 0.18), pole)
        if variant == "arm":
            mb.add_cylinder((0, 0), 0.08, 0.5, 6.0, 6, pole)
            mb.add_beam((0.0, 5.8, 0.0), (0.0, 6.1, 1.5), 0.08, 0.08, pole)
            mb.add_box((-0.18, 5.85, 1.3), (0.18, 6.05, 1.9), rgb(0.85, 0.85, 0.80))
        else:
            mb.add_cylinder((0, 0), 0.07, 0.5, 3.8, 6, pole)
            mb.add_box((-0.22, 3.8, -0.22), (0.22, 4.4, 0.22), rgb(0.85, 0.82, 0.70))
            mb.add_pyramid((0, 0), 0.32, 4.4, 0.3, 4, pole, phase=math.pi / 4)
    elif kind == "tree":
        mb.add_cylinder((0, 0), 0.15, 0.0, 2.2, 5, BARK)
        if variant == "cone":
            mb.add_pyramid((0, 0), 1.6, 1.8, 4.6, 8, LEAF)
        elif variant == "fir":
            mb.add_pyramid((0, 0), 1.7, 1.6, 3.4, 7, shade(LEAF, 0.8))
            mb.add_pyramid((0, 0), 1.2, 3.6, 3.2, 7, shade(LEAF, 0.8))
        else:
            mb.add_box((-1.3, 2.2, -1.3), (1.3, 4.4, 1.3), shade(LEAF, 1.15))
            mb.add_box((-0.8, 4.4, -0.8), (0.8, 5.3, 0.8), shade(LEAF, 1.15))
    elif kind == "car":
        shape, colour = variant.split("_")
        color = {"red": CARS[0], "blue": CARS[1], "white": CARS[2], "grey": CARS[3]}[colour]
        length, width = {"sedan": (4.4, 1.8), "van": (4.8, 1.95), "hatch": (3.9, 1.75)}[shape]
        hl, hw = length / 2, width / 2
        if shape == "van":
            mb.add_box((-hw, 0.3, -hl), (hw, 1.85, hl), color)
            mb.add_box((-hw + 0.05, 1.1, hl - 0.02), (hw - 0.05, 1.7, hl + 0.01), GLASSES[0])
        else:
            mb.add_box((-hw, 0.3, -hl), (hw, 1.0, hl), color)
            back = -hl + (0.5 if shape == "sedan" else 0.15)
            cabin = [(back, 1.0), (hl - 1.3, 1.0), (hl - 1.8, 1.5), (back + 0.35, 1.5)]
            # (u, v) = (+Z, +Y): extrusion along -X
            mb.add_prism(cabin, (0, 0, 0), (0, 0, 1), (0, 1, 0), -(hw - 0.08), hw - 0.08, GLASSES[2])
        wheel = regular_polygon(6, 0.33, math.pi / 6)
        for zc in (-hl + 0.8, hl - 0.8):
            prof = [(zc + a, 0.33 + b) for a, b in wheel]
            for x_lo, x_hi in ((hw - 0.22, hw + 0.02), (-hw - 0.02, -hw + 0.22)):
                mb.add_prism(prof, (0, 0, 0), (0, 0, 1), (0, 1, 0), -x_hi, -x_lo, DARK)
    else:                                            # bench
        wood, iron = rgb(0.48, 0.34, 0.22), DARK
        mb.add_box((-0.9, 0.42, -0.22), (0.9, 0.48, 0.22), wood)
        mb.add_box((-0.9, 0.55, -0.26), (0.9, 0.9, -0.22), wood)
        for x in (-0.75, 0.75):
            mb.add_box((x - 0.04, 0.0, -0.24), (x + 0.04, 0.55, 0.2), iron)
    return mb


@dataclass
class Placement:
    kind: str
    variant: str
    pos: tuple
    yaw: float           # degrees about +Y (xformOp:rotateY)
    scale: float = 1.0


def place(kind, variant, x, y, z, yaw, scale=1.0):
    return Placement(kind, variant, (round(x, 4), round(y, 4), round(z, 4)), round(yaw % 360.0, 2), round(scale, 3))


def facing(nx, nz):
    """rotateY (degrees) that turns +Z onto (nx, nz)."""
    return math.degrees(math.atan2(nx, nz))


def sidewalk_props(rng, piece, sw, trees_here, parked, keep_clear):
    """Lamps, trees, benches along the curb of one sidewalk polygon, cars parked beside it; no car
    within 9 m of a point of ``keep_clear`` (the camera's path)."""
    out = []
    for origin, u, n, width in outline_edges(piece):
        ux, uz, nx, nz = u[0], u[2], n[0], n[2]     # n: outwards, towards the street

        def at(s, off):                             # off > 0: into the street
            return origin[0] + ux * s + nx * off, origin[2] + uz * s + nz * off

        if width < 6.0:
            continue
        lamp_step = rng.uniform(18.0, 26.0)
        lamps = [s for s in np.arange(2.0 + rng.uniform(0, 4), width - 2.0, lamp_step)]
        for s in lamps:
            x, z = at(s, -0.6)
            out.append(place("lamp", "arm" if rng.random() < 0.7 else "lantern", x, CURB, z, facing(nx, nz)))
        if trees_here:
            variant = PROP_VARIANTS["tree"][int(rng.integers(3))]
            for s in np.arange(3.0 + rng.uniform(0, 3), width - 3.0, rng.uniform(8.0, 13.0)):
                if min((abs(s - l) for l in lamps), default=99) < 2.5:
                    continue
                x, z = at(s, -min(1.9, sw * 0.5))
                out.append(place("tree", variant, x, CURB, z, rng.uniform(0, 360), rng.uniform(0.8, 1.15)))
                if rng.random() < 0.15 and sw > 3.2:
                    x, z = at(s + 3.0, -(sw - 0.9))
                    out.append(place("bench", "wood", x, CURB, z, facing(nx, nz)))
        if parked and width > 16.0:
            s = 6.0 + rng.uniform(0, 2)
            while s < width - 6.0:
                x, z = at(s, 1.25)
                if rng.random() < 0.7 and all(math.hypot(x - a, z - b) > 9.0 for a, b in keep_clear):
                    flip = 180.0 if rng.random() < 0.5 else 0.0
                    variant = PROP_VARIANTS["car"][int(rng.integers(4))]
                    out.append(place("car", variant, x, 0.0, z, facing(ux, uz) + flip))
                s += rng.uniform(5.6, 7.0)
    return out


def plan_park(rng, lot, mb):
    x0, x1, z0, z1 = lot.rect(0.5, lot.width - 0.5, 0.5, lot.depth - 0.5)
    mb.add_box((x0, CURB, z0), (x1, CURB + 0.1, z1), GRASS)
    y = CURB + 0.1
    out, pts = [], []
    for _ in range(int(max(2, (x1 - x0) * (z1 - z0) / 45.0))):
        x, z = rng.uniform(x0 + 1.5, x1 - 1.5), rng.uniform(z0 + 1.5, z1 - 1.5)
        if all(math.hypot(x - a, z - b) > 3.8 for a, b in pts):
            pts.append((x, z))
            out.append(place("tree", PROP_VARIANTS["tree"][int(rng.integers(3))], x, y, z, rng.uniform(0, 360),
                             rng.uniform(0.8, 1.2)))
    for _ in range(int(rng.integers(1, 4))):
        x, z = rng.uniform(x0 + 1, x1 - 1), rng.uniform(z0 + 1, z1 - 1)
        if all(math.hypot(x - a, z - b) > 2.2 for a, b in pts):
            out.append(place("bench", "wood", x, y, z, 90.0 * int(rng.integers(4))))
    return out


def plan_parking(rng, lot, mb):
    x0, x1, z0, z1 = lot.rect(0.3, lot.width - 0.3, 0.3, lot.depth - 0.3)
    mb.add_box((x0, CURB, z0), (x1, CURB + 0.02, z1), rgb(0.16, 0.16, 0.17))
    y = CURB + 0.02
    out = []
    # rows of stalls 2.6 m wide, 5.2 m deep, cars nose-in, along the lot's front
    for t in np.arange(1.0, lot.depth - 6.0, 7.0):
        for s in np.arange(1.0, lot.width - 2.6, 2.6):
            line = [lot.to_world(s, t), lot.to_world(s + 0.12, t), lot.to_world(s + 0.12, t + 5.2),
                    lot.to_world(s, t + 5.2)]
            mb.add_poly([(x, y + 0.005, z) for x, z in line], rgb(0.8, 0.8, 0.78), UP)
            if rng.random() < 0.65:
                cx, cz = lot.to_world(s + 1.3, t + 2.6)
                out.append(place("car", PROP_VARIANTS["car"][int(rng.integers(4))], cx, y, cz,
                                 facing(lot.et[0], lot.et[1]) + (180.0 if rng.random() < 0.3 else 0.0)))
    return out


# --------------------------------------------------------------------------
# Ground
# --------------------------------------------------------------------------

def ground_meshes(grid, pieces):
    terrain, asphalt, walks, marks = Builder(), Builder(), Builder(), Builder()
    h, big = grid.size / 2, max(1500.0, 4 * grid.size)
    for x0, x1, z0, z1 in ((-big, big, -big, -h), (-big, big, h, big), (-big, -h, -h, h), (h, big, -h, h)):
        terrain.add_poly([(x0, 0, z0), (x1, 0, z0), (x1, 0, z1), (x0, 0, z1)], rgb(0.28, 0.33, 0.22), UP)
    asphalt.add_poly([(-h, 0, -h), (h, 0, -h), (h, 0, h), (-h, 0, h)], rgb(0.17, 0.17, 0.18), UP)
    for piece in pieces:
        add_slab(walks, piece, 0.0, CURB - 0.015, rgb(0.70, 0.70, 0.68))      # kerb stones
        add_slab(walks, inset_convex(piece, 0.25), 0.0, CURB, rgb(0.52, 0.51, 0.49))
    paint, white = rgb(0.85, 0.80, 0.45), rgb(0.85, 0.85, 0.83)
    y = 0.01

    def strip(cx, cz, dx, dz, half_len, half_w, color):
        px, pz = -dz, dx
        marks.add_poly([(cx - dx * half_len - px * half_w, y, cz - dz * half_len - pz * half_w),
                        (cx + dx * half_len - px * half_w, y, cz + dz * half_len - pz * half_w),
                        (cx + dx * half_len + px * half_w, y, cz + dz * half_len + pz * half_w),
                        (cx - dx * half_len + px * half_w, y, cz - dz * half_len + pz * half_w)], color, UP)

    for st in grid.streets:
        dx, dz = st.dir
        others = [o for o in grid.streets if o is not st]
        for s in np.arange(2.0, st.length - 2.0, 6.0):
            cx, cz = st.a[0] + dx * s, st.a[1] + dz * s
            if not any(o.contains(cx, cz, 3.5) for o in others):
                strip(cx, cz, dx, dz, 1.5, 0.08, paint)
        if st.kind == "avenue":
            continue
        for o in others:                            # zebra crossings before each crossing street
            if o.kind == st.kind or o.kind == "avenue":
                continue
            ox, oz = (o.a[0], st.a[1]) if st.kind == "x" else (st.a[0], o.a[1])
            if not (o.contains(ox, oz, 0.1) and st.contains(ox, oz, 0.1)):
                continue
            s_c = (ox - st.a[0]) * dx + (oz - st.a[1]) * dz
            for sgn in (-1, 1):
                s = s_c + sgn * (o.width / 2 + 1.8)
                if not 0 <= s <= st.length:
                    continue
                for k in np.arange(-st.width / 2 + 1.0, st.width / 2 - 0.7, 1.1):
                    cx, cz = st.a[0] + dx * s - dz * (k + 0.25), st.a[1] + dz * s + dx * (k + 0.25)
                    strip(cx, cz, dx, dz, 1.25, 0.25, white)
    return {"Terrain": terrain, "Asphalt": asphalt, "Sidewalks": walks, "Markings": marks}


# --------------------------------------------------------------------------
# Lights and camera
# --------------------------------------------------------------------------

def street_light_positions(rng, streets, n, times):
    lengths = np.array([s.length for s in streets])
    pick = rng.choice(len(streets), n, p=lengths / lengths.sum())
    speed = rng.uniform(0.5, 4.0, n) * rng.choice([-1.0, 1.0], n)
    u0 = rng.random(n)
    lat0 = rng.uniform(-1.0, 1.0, n)
    h0 = rng.uniform(2.5, 9.5, n)
    amp, freq, ph = rng.uniform(0.05, 0.4, n), rng.uniform(0.3, 1.0, n), rng.uniform(0, 2 * math.pi, n)
    out = np.zeros((len(times), n, 3))
    travel = np.abs(speed) * times[-1]
    for i in range(n):
        st = streets[pick[i]]
        dx, dz = st.dir
        margin = 4.0 + travel[i]
        s0 = margin + u0[i] * max(0.0, st.length - 2 * margin)
        lat = lat0[i] * (st.width / 2 - 2.5)
        s = s0 + speed[i] * times
        out[:, i, 0] = st.a[0] + dx * s - dz * lat
        out[:, i, 2] = st.a[1] + dz * s + dx * lat
        out[:, i, 1] = h0[i] + amp[i] * np.sin(2 * math.pi * freq[i] * times + ph[i])
    return out


def roof_light_positions(rng, buildings, n, times):
    areas = np.array([(b.bbox[1] - b.bbox[0]) * (b.bbox[3] - b.bbox[2]) for b in buildings])
    pick = rng.choice(len(buildings), n, p=areas / areas.sum())
    fx, fz = rng.random(n), rng.random(n)
    h0 = rng.uniform(2.5, 9.5, n)
    r, w, ph = rng.uniform(0.3, 1.5, n), rng.uniform(0.5, 2.0, n) * rng.choice([-1.0, 1.0], n), \
        rng.uniform(0, 2 * math.pi, n)
    out = np.zeros((len(times), n, 3))
    for i in range(n):
        b = buildings[pick[i]]
        x0, x1, z0, z1 = b.bbox
        cx = x0 + 2.0 + fx[i] * max(0.0, x1 - x0 - 4.0) if x1 - x0 > 4.0 else (x0 + x1) / 2
        cz = z0 + 2.0 + fz[i] * max(0.0, z1 - z0 - 4.0) if z1 - z0 > 4.0 else (z0 + z1) / 2
        a = ph[i] + w[i] * times
        out[:, i, 0] = cx + r[i] * np.cos(a) - r[i] * math.cos(ph[i])
        out[:, i, 2] = cz + r[i] * np.sin(a) - r[i] * math.sin(ph[i])
        out[:, i, 1] = b.top + h0[i] + 0.3 * np.sin(a)
    return out


def street_camera(rng, grid, times):
    """Eye 1.6-2.4 m over an interior through street near one end, looking down it, dollying."""
    h = grid.size / 2
    cands = [s for s in grid.streets if s.kind != "avenue" and s.length > 0.95 * grid.size
             and abs(s.a[0] if s.kind == "z" else s.a[1]) < h - s.width]
    st = cands[int(rng.integers(len(cands)))]
    dx, dz = st.dir
    start, sgn = (st.a, 1.0) if rng.random() < 0.5 else (st.b, -1.0)
    dx, dz = dx * sgn, dz * sgn
    px, pz = -dz, dx
    lat = rng.uniform(-0.25, 0.25) * st.width
    s0 = rng.uniform(0.08, 0.14) * st.length
    eye_h = rng.uniform(1.6, 2.4)
    dolly = rng.uniform(2.0, 4.0)
    look_up = rng.uniform(4.0, 9.0)
    look_side = rng.uniform(-4.0, 4.0)
    sway = rng.uniform(-0.6, 0.6)
    k = times / times[-1]
    s = s0 + dolly * k
    ex, ez = start[0] + dx * s + px * (lat + 0.3 * sway * k), start[1] + dz * s + pz * (lat + 0.3 * sway * k)
    eyes = np.stack([ex, np.full_like(k, eye_h), ez], -1)
    ahead = 90.0
    tx, tz = ex + dx * ahead + px * (look_side + sway * k), ez + dz * ahead + pz * (look_side + sway * k)
    targets = np.stack([tx, eye_h + look_up + 0.5 * k, tz], -1)
    return settled(eyes, 4), settled(targets, 4), st


# --------------------------------------------------------------------------
# The stage
# --------------------------------------------------------------------------

def solve_detail(facades, goal):
    """Detail factor whose facade triangle total is nearest ``goal`` (bays = round(width * detail / bay_w))."""
    def total(d):
        return sum(facade_tris(f, d) for f in facades)
    lo, hi = 0.05, 8.0
    if total(hi) <= goal:
        return hi
    if total(lo) >= goal:
        return lo
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if total(mid) < goal else (lo, mid)
    return lo if goal - total(lo) <= total(hi) - goal else hi


def plan_city(seed, size):
    """Everything of the city of ``seed`` and side ``size`` but its facades and lights: the grid, the
    camera, buildings with their roofs and features, lots, props, ground; ``fixed`` counts their triangles."""
    rng = np.random.default_rng([36, seed])
    grid = street_grid(rng, size)
    n_inst = 1 + int(rng.random() < 0.5)
    instanced = sorted(str(k) for k in rng.choice(PROP_KINDS, n_inst, replace=False))
    downtown = rng.uniform(-0.25, 0.25, 2) * size
    frames, times = frame_times(FIRST, LAST)
    eyes, targets, cam_street = street_camera(rng, grid, times)
    keep_clear = [(e[0], e[2]) for e in eyes[::6]]

    buildings, lots_meshes, placements, pieces_all = [], {}, {}, []
    kinds = BUILDING_KINDS + ("park", "parking")
    for bi, rect in enumerate(grid.blocks):
        block = f"/World/City/Block_{bi:02d}"
        pieces = block_pieces(grid, rect)
        pieces_all += pieces
        sw = rng.uniform(3.2, 5.0)
        props = []
        trees_here = rng.random() < 0.6
        for piece in pieces:
            props += sidewalk_props(rng, piece, sw, trees_here, rng.random() < 0.65, keep_clear)
        inner = (rect[0] + sw, rect[1] - sw, rect[2] + sw, rect[3] - sw)
        lot_mb = Builder()
        for li, lot in enumerate(subdivide(rng, inner)):
            lot = clear_lot(grid, lot, sw)
            if lot is None:
                continue
            cx, cz = lot.center
            g = math.exp(-math.hypot(cx - downtown[0], cz - downtown[1]) / (0.3 * size))
            ok_tower = lot.width >= 16 and lot.depth >= 16
            p = np.array([0.6 * g * g * ok_tower, 0.45, 0.35 * (1 - g) * (lot.width < 22), 0.06, 0.05])
            kind = kinds[int(rng.choice(5, p=p / p.sum()))] if min(lot.width, lot.depth) >= 8 else "park"
            if kind in ("park", "parking"):
                props += (plan_park if kind == "park" else plan_parking)(rng, lot, lot_mb)
                continue
            mb = Builder()
            if kind == "tower":
                facades, bbox = plan_tower(rng, lot, g, mb)
            elif kind == "box":
                facades, bbox = plan_box(rng, lot, g, mb)
            else:
                facades, bbox = plan_gable(rng, lot, mb)
            top = round(max(p[1] for p in mb.points), 3)      # roofs and what stands on them
            buildings.append(Building(f"{block}/{kind}_{li:02d}", kind, mb, facades, top, bbox))
        lots_meshes[block] = lot_mb
        placements[block] = props

    ground = ground_meshes(grid, pieces_all)
    protos = {}
    for props in placements.values():
        for p in props:
            if (p.kind, p.variant) not in protos:
                protos[(p.kind, p.variant)] = prop_mesh(p.kind, p.variant)
    prop_mbs, n_instances, inst_tris = {}, 0, 0
    for block, props in placements.items():
        mb = Builder()
        for p in props:
            if p.kind in instanced:
                n_instances += 1
                inst_tris += protos[(p.kind, p.variant)].triangle_count
            else:
                mb.append(protos[(p.kind, p.variant)], p.yaw, p.scale, p.pos)
        prop_mbs[block] = mb
    fixed = (sum(m.triangle_count for m in ground.values()) + sum(b.mb.triangle_count for b in buildings)
             + sum(m.triangle_count for m in lots_meshes.values()) + sum(m.triangle_count for m in prop_mbs.values())
             + inst_tris)
    return SimpleNamespace(rng=rng, grid=grid, instanced=instanced, frames=frames, times=times, eyes=eyes,
                           targets=targets, cam_street=cam_street, buildings=buildings, lots_meshes=lots_meshes,
                           placements=placements, ground=ground, protos=protos, prop_mbs=prop_mbs,
                           n_instances=n_instances, inst_tris=inst_tris, fixed=fixed,
                           facades=[f for b in buildings for f in b.facades])


#: facade detail (window bays per metre, relative) a city is accepted at; outside it the city is
#: planned again, larger (too few facades to spend the budget on) or smaller (too many)
DETAIL_RANGE = (0.6, 2.5)


def make_city(seed, out_dir, triangles=DEFAULT_TRIANGLES):
    """Write ``out_dir/unseen_city_<seed>.usda``; returns what it holds (a dict for the report)."""
    t_start = time.perf_counter()
    size = round(max(MIN_SIZE, BASE_SIZE * math.sqrt(triangles / DEFAULT_TRIANGLES)), 1)
    for attempt in range(8):
        city = plan_city(seed, size)
        detail = solve_detail(city.facades, triangles - city.fixed)
        if DETAIL_RANGE[0] <= detail <= DETAIL_RANGE[1] or attempt == 7:
            break
        size = round(max(MIN_SIZE, size * min(1.4, max(0.7, math.sqrt(detail / 1.2)))), 1)
    rng, grid, buildings, times, eyes = city.rng, city.grid, city.buildings, city.times, city.eyes
    facades, instanced, placements, protos = city.facades, city.instanced, city.placements, city.protos
    lots_meshes, prop_mbs, inst_tris = city.lots_meshes, city.prop_mbs, city.inst_tris
    for b in buildings:
        for f in b.facades:
            build_facade(b.mb, f, detail)

    # lights
    n_street = int(round(N_LIGHTS * rng.uniform(0.6, 0.8)))
    pos = np.concatenate([street_light_positions(rng, grid.streets, n_street, times),
                          roof_light_positions(rng, buildings, N_LIGHTS - n_street, times)], axis=1)
    for _ in range(20):      # no bulb within 6 m of the lens at any frame
        near = (_eye_distance(pos, eyes) < 6.0).any(axis=0)
        if not near.any():
            break
        k = int(near.sum())
        repl = street_light_positions(rng, grid.streets, k, times)
        pos[:, near] = repl
    pos = settled(pos, 4)
    proto_names = ["warm", "cool", "white", "pink"]
    proto_idx = rng.choice(4, N_LIGHTS, p=[0.45, 0.25, 0.2, 0.1])
    samples = street_light_positions(rng, grid.streets, 256, times[:1])[0]
    samples[:, 1] = 0.0
    intensity = calibrate_intensity(pos[0], LIGHT_RADIUS, samples, np.tile(UP, (256, 1)), target=0.6)

    # author
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"unseen_city_{seed}.usda")
    stage = new_stage(path, FIRST, LAST)
    stage.GetRootLayer().documentation = (f"unseen city, seed {seed} ({'tuning' if seed % 2 == 0 else 'reporting'}"
                                          f" seed), {triangles} triangles requested: tools/make_city.py")
    Usd.ModelAPI(UsdGeom.Xform.Define(stage, "/World/City").GetPrim()).SetKind("group")
    UsdGeom.Xform.Define(stage, "/World/Ground")
    for name, mb in city.ground.items():
        define_mesh(stage, f"/World/Ground/{name}", mb)
    proto_root = stage.DefinePrim("/World/Prototypes", "Xform")
    proto_root.SetSpecifier(Sdf.SpecifierClass)
    for (kind, variant), mb in sorted(protos.items()):
        if kind in instanced:
            stage.DefinePrim(f"/World/Prototypes/{kind}_{variant}", "Xform")
            define_mesh(stage, f"/World/Prototypes/{kind}_{variant}/geom", mb)
    for bi in range(len(grid.blocks)):
        block = f"/World/City/Block_{bi:02d}"
        Usd.ModelAPI(UsdGeom.Xform.Define(stage, block).GetPrim()).SetKind("group")
    for b in buildings:
        define_mesh(stage, b.path, b.mb)
    for block in placements:
        if lots_meshes[block].counts:
            define_mesh(stage, f"{block}/lots", lots_meshes[block])
        if prop_mbs[block].counts:
            define_mesh(stage, f"{block}/props", prop_mbs[block])
        k = 0
        for p in placements[block]:
            if p.kind not in instanced:
                continue
            prim = stage.DefinePrim(f"{block}/{p.kind}_{k:03d}", "Xform")
            k += 1
            prim.GetReferences().AddInternalReference(f"/World/Prototypes/{p.kind}_{p.variant}")
            prim.SetInstanceable(True)
            xf = UsdGeom.Xformable(prim)
            xf.AddTranslateOp().Set(Gf.Vec3d(*p.pos))
            xf.AddRotateYOp().Set(float(p.yaw))
            if p.scale != 1.0:
                xf.AddScaleOp().Set(Gf.Vec3f(p.scale, p.scale, p.scale))
    define_light_instancer(stage, stage.GetRootLayer(), "/World/Lights", proto_names, LIGHT_RADIUS, intensity,
                           proto_idx, pos, city.frames)
    define_camera(stage, eyes, city.targets, (0.1, 3000.0), city.frames)
    define_render_settings(stage, f"out/unseen_city_{seed}.####.exr")
    stage.Save()
    flat = city.fixed - inst_tris + sum(facade_tris(f, detail) for f in facades)
    return {"path": path, "mode": grid.mode, "size_m": size, "attempts": attempt + 1, "blocks": len(grid.blocks),
            "buildings": len(buildings), "kinds": {k: sum(b.kind == k for b in buildings) for k in BUILDING_KINDS},
            "instanced": instanced, "instances": city.n_instances, "triangles": flat + inst_tris,
            "flattened_tris": flat, "instanced_tris": inst_tris, "detail": round(detail, 3),
            "lights": N_LIGHTS, "street_lights": n_street, "intensity": intensity,
            "camera_street": city.cam_street.kind, "seconds": round(time.perf_counter() - t_start, 2)}


def _eye_distance(pos, eyes):
    """(frames, lights) distance of each bulb to the camera eye of its frame."""
    return np.linalg.norm(pos - eyes[:, None, :], axis=-1)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    parser.add_argument("--seed", type=int, required=True, help="city seed (even: tuning, odd: reporting)")
    parser.add_argument("--out", required=True, help="output folder; writes unseen_city_<seed>.usda there")
    parser.add_argument("--triangles", type=int, default=DEFAULT_TRIANGLES,
                        help=f"triangle budget after instancing (default {DEFAULT_TRIANGLES})")
    args = parser.parse_args(argv)
    if args.triangles < 5000:
        parser.error("--triangles: at least 5000")
    info = make_city(args.seed, os.path.abspath(args.out), args.triangles)
    print(f"{info.pop('path')}: " + ", ".join(f"{k}={v}" for k, v in info.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
