"""A seeded suite of small stages for GI and many lights (issue 37), the LGH's held-back test set.

Written by ``python tools/make_stages.py --suite [--kinds open,canyon,interior] [--lights 64,1024]
[--seeds 0-5] --out DIR``; each stage is ``DIR/suite_<kind>_<lights>_s<seed>.usda``, one layer.

Kinds (the seed picks every size, count and position; a scale factor of 0.3-5 for the whole stage,
so that nothing tuned in metres carries over):

* ``open``: a ground plane and 6-16 boxes of varied footprint and height, lights between and above
  them, the camera looking down at 20-40 degrees.
* ``canyon``: a street 6-14 m wide between two rows of blocks 8-40 m tall with alleys between them,
  awnings and ledges over the pavement, lights along the street and over the roofs, the camera at
  eye level looking down the street.
* ``interior``: a closed room (walls, floor, ceiling as boxes 0.2 m thick) with one window, 4-8
  pieces of furniture; most lights outside beyond the window, a few dim ones inside, the camera in a
  corner.

Lights: point-like SphereLights (``treatAsPoint``, ``normalize = false``) of varied power: eight
intensities over two decades, log-spaced, drawn per light, and four colours. 64 lights are authored
as separate prims; more as a PointInstancer of eight prototypes. The whole set is scaled
(``calibrate_intensity``) so that the unshadowed light leaving a grey surface averages about 0.3.

Even seeds are for tuning, odd seeds for reporting (``split``). Deterministic: the same arguments
give the same files.
"""
import math
import os
import sys

import numpy as np
from pxr import Gf, UsdGeom, UsdLux, Vt

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from stage_build import (BULBS, MeshBuilder, calibrate_intensity, define_camera, define_mesh,  # noqa: E402
                         define_render_settings, new_stage, settled, settled_points)

KINDS = ("open", "canyon", "interior")
LIGHT_COUNTS = (64, 1024, 100000)
POWER_LEVELS = 8            # intensities 10^(2 k / 7) apart: two decades from the dimmest to the brightest
MARGIN = 0.4                # a light keeps this far (scaled) from every box


def split(seed: int) -> str:
    """``tune`` for even seeds, ``report`` for odd ones."""
    return "tune" if seed % 2 == 0 else "report"


def stage_name(kind: str, lights: int, seed: int) -> str:
    return f"suite_{kind}_{lights}_s{seed}.usda"


def _grey(rng, lo=0.35, hi=0.8):
    g = float(rng.uniform(lo, hi))
    return (round(g, 2), round(g * float(rng.uniform(0.85, 1.0)), 2), round(g * float(rng.uniform(0.8, 1.0)), 2))


def _clear(points, boxes, margin):
    """Mask of the points at least ``margin`` from every (lo, hi) box."""
    ok = np.ones(len(points), bool)
    for lo, hi in boxes:
        d = np.linalg.norm(points - np.clip(points, lo, hi), axis=1)
        ok &= d >= margin
    return ok


def _sample(rng, n, lo, hi, boxes, margin, inside=None):
    """n points uniform in the box [lo, hi], clear of ``boxes`` (and within ``inside`` if given)."""
    out = []
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    while sum(len(o) for o in out) < n:
        pts = rng.uniform(lo, hi, size=(max(256, 2 * n), 3))
        pts = pts[_clear(pts, boxes, margin)]
        out.append(pts)
    return np.concatenate(out)[:n]


def _open(rng, s):
    mb = MeshBuilder()
    half = 20.0 * s
    mb.add_poly([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)], (0.5, 0.5, 0.5), (0, 1, 0))
    boxes = []
    for _ in range(int(rng.integers(6, 17))):
        for _try in range(50):
            w, d = rng.uniform(0.6, 5.0, size=2) * s
            h = float(rng.uniform(0.4, 6.0)) * s
            x, z = rng.uniform(-12, 12, size=2) * s
            lo, hi = np.array((x - w / 2, 0.0, z - d / 2)), np.array((x + w / 2, h, z + d / 2))
            if all(np.any(hi[[0, 2]] + 0.3 * s < b[0][[0, 2]]) or np.any(lo[[0, 2]] - 0.3 * s > b[1][[0, 2]])
                   for b in boxes):
                break
        boxes.append((lo, hi))
        mb.add_box(lo, hi, _grey(rng))
    region = ((-14 * s, 0.3 * s, -14 * s), (14 * s, 8 * s, 14 * s))
    yaw = float(rng.uniform(0, 2 * math.pi))
    pitch = math.radians(float(rng.uniform(20, 40)))
    dist = 34.0 * s
    eye = np.array((math.cos(yaw) * math.cos(pitch), math.sin(pitch), math.sin(yaw) * math.cos(pitch))) * dist
    return mb, boxes, [(region, 1.0)], eye, np.array((0.0, 1.0 * s, 0.0))


def _canyon(rng, s):
    mb = MeshBuilder()
    street = float(rng.uniform(6, 14)) * s
    length = 120.0 * s
    depth = 14.0 * s
    mb.add_poly([(-street / 2 - depth, 0, -length / 2), (-street / 2 - depth, 0, length / 2),
                 (street / 2 + depth, 0, length / 2), (street / 2 + depth, 0, -length / 2)], (0.45, 0.45, 0.47), (0, 1, 0))
    boxes = []
    tops = []
    for side in (-1, 1):
        z = -length / 2
        while z < length / 2 - 4 * s:
            w = min(float(rng.uniform(8, 24)) * s, length / 2 - z)
            h = float(rng.uniform(8, 40)) * s
            x0 = side * street / 2
            x1 = side * (street / 2 + depth)
            lo = np.array((min(x0, x1), 0.0, z))
            hi = np.array((max(x0, x1), h, z + w))
            boxes.append((lo, hi))
            tops.append(h)
            mb.add_box(lo, hi, _grey(rng))
            if rng.random() < 0.6:      # an awning or a ledge over the pavement
                y = float(rng.uniform(2.5, 6.0)) * s
                out = float(rng.uniform(0.8, 2.5)) * s
                alo = np.array((min(x0, x0 - side * out), y, z + 0.5 * s))
                ahi = np.array((max(x0, x0 - side * out), y + 0.15 * s, z + w - 0.5 * s))
                boxes.append((alo, ahi))
                mb.add_box(alo, ahi, _grey(rng, 0.3, 0.9))
            z += w + float(rng.uniform(2, 6)) * s       # an alley
    street_region = ((-street / 2 + 0.5 * s, 1.5 * s, -length / 2), (street / 2 - 0.5 * s, 9 * s, length / 2))
    roof_region = ((-street / 2 - depth, max(tops) + 1 * s, -length / 2),
                   (street / 2 + depth, max(tops) + 8 * s, length / 2))
    eye = np.array((float(rng.uniform(-0.3, 0.3)) * street, 1.7 * s, -length / 2 + 4 * s))
    target = np.array((0.0, float(rng.uniform(3, 8)) * s, length / 4))
    return mb, boxes, [(street_region, 0.75), (roof_region, 0.25)], eye, target


def _interior(rng, s):
    mb = MeshBuilder()
    lx, lz = rng.uniform(6, 12, size=2) * s
    ly = float(rng.uniform(2.8, 4.0)) * s
    t = 0.2 * s
    wall = _grey(rng, 0.6, 0.85)
    pieces = [((-lx / 2 - t, -t, -lz / 2 - t), (lx / 2 + t, 0, lz / 2 + t)),          # floor
              ((-lx / 2 - t, ly, -lz / 2 - t), (lx / 2 + t, ly + t, lz / 2 + t)),     # ceiling
              ((-lx / 2 - t, 0, -lz / 2 - t), (-lx / 2, ly, lz / 2 + t)),             # west
              ((lx / 2, 0, -lz / 2 - t), (lx / 2 + t, ly, lz / 2 + t)),               # east
              ((-lx / 2, 0, -lz / 2 - t), (lx / 2, ly, -lz / 2))]                     # south
    # the north wall (z = +lz/2) has the window: a hole of ww x wh, sill at wy
    ww = float(rng.uniform(0.25, 0.5)) * lx
    wh = float(rng.uniform(0.35, 0.55)) * ly
    wy = float(rng.uniform(0.2, 0.35)) * ly
    wx = float(rng.uniform(-0.5, 0.5)) * (lx - ww - 0.4 * s)
    z0, z1 = lz / 2, lz / 2 + t
    pieces += [((-lx / 2, 0, z0), (wx - ww / 2, ly, z1)), ((wx + ww / 2, 0, z0), (lx / 2, ly, z1)),
               ((wx - ww / 2, 0, z0), (wx + ww / 2, wy, z1)), ((wx - ww / 2, wy + wh, z0), (wx + ww / 2, ly, z1))]
    boxes = []
    for lo, hi in pieces:
        lo, hi = np.array(lo, float), np.array(hi, float)
        boxes.append((lo, hi))
        mb.add_box(lo, hi, wall)
    ground = 60.0 * s
    mb.add_poly([(-ground, -t, -ground), (-ground, -t, ground), (ground, -t, ground), (ground, -t, -ground)],
                (0.4, 0.42, 0.4), (0, 1, 0))
    for _ in range(int(rng.integers(4, 9))):
        w, d = rng.uniform(0.4, 2.0, size=2) * s
        h = float(rng.uniform(0.4, 2.0)) * s
        x = float(rng.uniform(-lx / 2 + w / 2 + 0.1 * s, lx / 2 - w / 2 - 0.1 * s))
        z = float(rng.uniform(-lz / 2 + d / 2 + 0.1 * s, lz / 2 - d / 2 - 0.1 * s))
        lo, hi = np.array((x - w / 2, 0.0, z - d / 2)), np.array((x + w / 2, h, z + d / 2))
        boxes.append((lo, hi))
        mb.add_box(lo, hi, _grey(rng, 0.2, 0.9))
    outside = ((-3 * lx, 0.5 * s, lz / 2 + 2 * s), (3 * lx, 4 * ly, lz / 2 + 20 * s))
    inside = ((-lx / 2 + 0.3 * s, 0.3 * s, -lz / 2 + 0.3 * s), (lx / 2 - 0.3 * s, ly - 0.3 * s, lz / 2 - 0.3 * s))
    eye = np.array((-lx / 2 + 0.5 * s, 0.75 * ly, -lz / 2 + 0.5 * s))
    if rng.random() < 0.5:
        eye[0] = -eye[0]
    target = np.array((wx * 0.5, 0.4 * ly, lz / 2))
    return mb, boxes, [(outside, 0.85), (inside, 0.15)], eye, target


BUILDERS = {"open": _open, "canyon": _canyon, "interior": _interior}


def make_suite_stage(out_dir: str, kind: str, lights: int, seed: int) -> dict:
    """Write one suite stage; returns what it holds (path, scale, triangles, lights)."""
    if kind not in BUILDERS:
        raise ValueError(f"unknown suite kind {kind!r}: one of {', '.join(KINDS)}")
    rng = np.random.default_rng([37, seed, KINDS.index(kind), lights])
    scale = float(10 ** rng.uniform(math.log10(0.3), math.log10(5.0)))
    mb, boxes, regions, eye, target = BUILDERS[kind](rng, scale)
    path = os.path.join(out_dir, stage_name(kind, lights, seed))
    stage = new_stage(path, 1, 1)
    define_mesh(stage, "/World/Geometry", mb)

    counts = rng.multinomial(lights, [w for _, w in regions])
    pos = np.concatenate([_sample(rng, int(c), lo, hi, boxes, MARGIN * scale)
                          for (lo, hi), c in zip((r for r, _ in regions), counts) if c])
    rng.shuffle(pos)
    power = rng.integers(0, POWER_LEVELS, size=lights)
    colour = rng.integers(0, 4, size=lights)
    if kind == "interior":      # the lights inside are the dim ones
        inside_lo, inside_hi = (np.array(v) for v in regions[1][0])
        inside = np.all((pos >= inside_lo) & (pos <= inside_hi), axis=1)
        power[inside] = np.minimum(power[inside], 2)
    rel = 10.0 ** (2.0 * np.arange(POWER_LEVELS) / (POWER_LEVELS - 1))
    radius = 0.05 * scale
    # calibrate on points of the ground / floor under the camera's view
    probe = _sample(rng, 64, (target[0] - 6 * scale, 0.0, target[2] - 6 * scale),
                    (target[0] + 6 * scale, 0.0, target[2] + 6 * scale), [], 0.0)
    sub = rng.choice(lights, size=min(lights, 4096), replace=False)
    base = calibrate_intensity(pos[sub], radius, probe + np.array((0, 1e-3, 0)), np.tile((0.0, 1.0, 0.0), (64, 1)))
    intensity = [float(f"{base * r / rel.mean():.3g}") for r in rel]
    names = ("warm", "cool", "white", "pink")
    UsdGeom.Xform.Define(stage, "/World/Lights")
    if lights <= 64:
        for k in range(lights):
            light = UsdLux.SphereLight.Define(stage, f"/World/Lights/bulb_{k:03d}")
            light.CreateTreatAsPointAttr(True)
            light.CreateRadiusAttr(radius)
            light.CreateNormalizeAttr(False)
            light.CreateIntensityAttr(intensity[power[k]])
            light.CreateColorAttr(Gf.Vec3f(*BULBS[names[colour[k]]]))
            light.AddTranslateOp().Set(Gf.Vec3d(*map(float, settled(pos[k], 4))))
    else:
        pi = UsdGeom.PointInstancer.Define(stage, "/World/Lights/lamps")
        UsdGeom.Scope.Define(stage, "/World/Lights/lamps/Prototypes")
        protos = []
        for p in range(POWER_LEVELS):
            for c, name in enumerate(names):
                light = UsdLux.SphereLight.Define(stage, f"/World/Lights/lamps/Prototypes/bulb_{p}_{name}")
                light.CreateTreatAsPointAttr(True)
                light.CreateRadiusAttr(radius)
                light.CreateNormalizeAttr(False)
                light.CreateIntensityAttr(intensity[p])
                light.CreateColorAttr(Gf.Vec3f(*BULBS[name]))
                protos.append(light.GetPath())
        pi.CreatePrototypesRel().SetTargets(protos)
        pi.CreateProtoIndicesAttr(Vt.IntArray((power * 4 + colour).astype(int).tolist()))
        pi.CreatePositionsAttr().Set(settled_points(pos))
    far = float(np.linalg.norm(eye - target)) * 8 + 200 * scale
    define_camera(stage, tuple(eye), tuple(target), (0.05 * scale, far))
    define_render_settings(stage, f"out/{os.path.splitext(os.path.basename(path))[0]}.####.exr")
    stage.GetRootLayer().customLayerData = {"suite": {"kind": kind, "lights": int(lights), "seed": int(seed),
                                                      "split": split(seed), "scale": round(scale, 3)}}
    stage.Save()
    return {"path": path, "kind": kind, "lights": lights, "seed": seed, "split": split(seed),
            "scale": round(scale, 3), "triangles": mb.triangle_count, "base_intensity": base}


def parse_seeds(text: str) -> list[int]:
    """``"0-5"`` or ``"1,3,5"`` (or a mix) to a list of seeds."""
    seeds = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part[1:]:
            a, b = part.split("-", 1)
            seeds.extend(range(int(a), int(b) + 1))
        elif part:
            seeds.append(int(part))
    return seeds


def make_suite(out_dir: str, kinds=KINDS, lights=(64, 1024), seeds=(0, 1)) -> list[dict]:
    os.makedirs(out_dir, exist_ok=True)
    made = []
    for seed in seeds:
        for kind in kinds:
            for n in lights:
                made.append(make_suite_stage(out_dir, kind, int(n), int(seed)))
    return made
