"""Paper 000 Alg. 5: rotation tables against NumPy, rotated arrays against directly voxelized ones,
per-frame rebuilds driven by what changed, fully dynamic scenes, the CLI on a deforming stage.

Small grids (<= 32³, >= 10°) so the suite stays fast.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from usdml.errors import UsdmlError
from usdml.scene import Lights, diff
from usdml.visibility import ExactBackend, VoxelBackend
from usdml.visibility.voxel.array import array_cube, build_array
from usdml.visibility.voxel.grid import DirectionBins, RowLayout
from usdml.visibility.voxel.rotate import RotationTables, reference_occupied, rotate_array

from plain_scenes import prototype, rot_y, snapshot, soup, translate
from voxel_reference import box, centre_line_voxels, ground_queries, set_voxels

pytest.importorskip("embreex")

QUIET = dict(cache=False, report=lambda line: None)


def bits(words: np.ndarray) -> int:
    return int(np.bitwise_count(words).sum(dtype=np.int64))


def rotated_object() -> tuple[np.ndarray, np.ndarray]:
    """An L-shaped pair of boxes turned off every axis: points and triangles."""
    tris = np.concatenate([box((-2, -0.5, -0.5), (2, 0.5, 0.5)), box((-2, -0.5, 0.5), (-1, 0.5, 2.5))])
    m = rot_y(27) @ np.array([[1, 0, 0, 0], [0, np.cos(0.4), -np.sin(0.4), 0], [0, np.sin(0.4), np.cos(0.4), 0],
                              [0, 0, 0, 1]])
    pts = tris.reshape(-1, 3) @ m[:3, :3].T
    return pts, np.arange(len(pts)).reshape(-1, 3)


# ------------------------------------------------------------------------------------------ tables

def test_rotation_tables_match_numpy_rotations():
    n, step = 24, 10.0
    tables = RotationTables.make(n, step)
    frames = DirectionBins.make(step).frames.astype(np.float64)
    assert tables.rotations.shape == (len(frames), 3, 3)
    assert np.allclose(tables.rotations[0], np.eye(3), atol=1e-6)
    # orthonormal, and M_d = R_d M_0
    assert np.allclose(tables.rotations @ tables.rotations.transpose(0, 2, 1), np.eye(3), atol=1e-6)
    assert np.allclose(tables.rotations @ frames[0], frames, atol=1e-6)
    rng = np.random.default_rng(0)
    ijl = rng.integers(0, n, size=(500, 3))
    for d in rng.integers(0, len(frames), size=12):
        want = (ijl + 0.5 - n / 2) @ tables.rotations[d].T + n / 2
        # 16.16 fixed point: three roundings of 2^-17 each
        assert np.abs(tables.position(d, ijl) - want).max() < 3e-5
    # the conservative constants: extent of a rotated voxel and of a grid voxel on the other's axes
    assert np.allclose(tables.reach, 0.5 * np.abs(tables.rotations).sum(2), atol=1e-6)
    assert np.allclose(tables.radius, 0.5 * np.abs(tables.rotations).sum(1), atol=1e-6)


def test_reference_voxelization_in_warp_matches_numpy_centre_lines(device):
    """V0 rasterized in Warp holds the voxels NumPy's three-axis centre lines cross (float32
    against float64 rounding of a crossing on a voxel face aside)."""
    n = 24
    pts, tris = rotated_object()
    frame = DirectionBins.make(15.0).frames[0]
    pts_c, tris_c, centre, half = array_cube(pts, tris)
    got, count = reference_occupied(pts_c, tris_c, centre, half, n, frame, workers=2, device=device)
    want, crossings = centre_line_voxels(pts_c, tris_c, centre, half, n, frame)
    assert len(want) > 100
    g = set(map(tuple, got.tolist()))
    assert len(g ^ want) <= 0.01 * len(want)
    # a crossing on a shared edge is counted by both triangles
    assert crossings <= count <= crossings * 1.05
    # every core gives the same grid: one worker sets the same voxels
    one, _ = reference_occupied(pts_c, tris_c, centre, half, n, frame, workers=1, device=device)
    assert np.array_equal(one, got)


def test_point_mapping_kernel_sets_exactly_the_numpy_voxels(device):
    """Each direction holds exactly the voxels of V0's rotated centres (read from the tables)."""
    n, step = 24, 15.0
    pts, tris = rotated_object()
    bins, layout, tables = DirectionBins.make(step), RowLayout.make(n), RotationTables.make(n, step)
    arr = rotate_array(pts, tris, n, step, mapping="point", device=device)
    pts_c, tris_c, centre, half = array_cube(pts, tris)
    occ, _ = reference_occupied(pts_c, tris_c, centre, half, n, bins.frames[0], layout, device=device)
    assert arr.occupied == len(occ) > 100
    want = np.zeros_like(arr.words)
    for d in range(bins.count):
        q = np.floor(tables.position(d, occ)).astype(np.int64)
        set_voxels(want, d, q[np.all((q >= 0) & (q < n), axis=1)], layout)
    assert np.array_equal(arr.words, want)


def test_rigid_object_rotated_by_alg5_is_bounded_by_its_direct_voxelization(device):
    """The rotated arrays against Alg. 1 on the same object with every voxel the surface touches
    (core 1, the envelope of a thinner voxelization): conservative holds almost all of them and no
    more than twice as many; point sets fewer, none farther than one voxel from Alg. 1's."""
    n, step = 32, 10.0
    pts, tris = rotated_object()
    direct = build_array(pts, tris, n, step, core=1.0, device=device)
    cons = rotate_array(pts, tris, n, step, mapping="conservative", device=device)
    point = rotate_array(pts, tris, n, step, mapping="point", device=device)
    total = bits(direct.words)
    assert total > 10_000
    # conservative: rotated cubes of a V0 one voxel thick cover the touched voxels but a corner clip
    assert bits(direct.words & ~cons.words) <= total * 0.02
    assert bits(cons.words) < 2.5 * total
    # point: thinner than the envelope (a bounded share of it missing), every bit next to a direct one
    missing = bits(direct.words & ~point.words) / total
    assert 0.2 < missing < 0.6
    assert bits(point.words) < 0.8 * total
    layout = RowLayout.make(n)
    dense_d, dense_p = _dense(direct.words, layout, n), _dense(point.words, layout, n)
    near = np.zeros_like(dense_d)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                near |= np.roll(dense_d, (dx, dy, dz), axis=(1, 2, 3))
    assert not (dense_p & ~near).any()


def _dense(words: np.ndarray, layout: RowLayout, n: int) -> np.ndarray:
    """(directions, n, n, n) bool voxels of packed ``words``."""
    per = words.reshape(-1, layout.words)
    out = np.zeros((per.shape[0], n * n, layout.words_per_row * 32), bool)
    for r in np.nonzero(layout.nw)[0]:
        w = per[:, layout.offset[r]:layout.offset[r] + layout.nw[r]]
        b = np.unpackbits(w.view(np.uint8).reshape(per.shape[0], -1), axis=1, bitorder="little")
        out[:, r, layout.w0[r] * 32:(layout.w0[r] + layout.nw[r]) * 32] = b
    return out[:, :, :n].reshape(per.shape[0], n, n, n)


def test_rotated_arrays_answer_shadow_rays_close_to_exact(device):
    """The whole path: a deforming object over a ground, Alg. 5 (both mappings) and Alg. 1."""
    rng = np.random.default_rng(5)
    ground = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)
    blob = soup("/blob", np.concatenate([box((-3, 1, -3), (3, 2, 3)), box((-1, 2, -1), (1, 5, 1))]), id=2,
                deforming=True)
    snap = snapshot([ground, blob])
    o, t, nrm = ground_queries(rng, 3000)
    t[:, 1] += 4
    exact = ExactBackend()
    exact.update(snap)
    ref = exact.occluded(o, t, normals=nrm)
    assert 0.1 < ref.mean() < 0.9
    errors = {}
    for rebuild, mapping in (("geometry", "point"), ("rotate", "point"), ("rotate", "conservative")):
        b = VoxelBackend(voxel_resolution=32, direction_step=10.0, voxel_rebuild=rebuild, voxel_mapping=mapping, **QUIET,
                         device=device)
        b.update(snap)
        assert b.built == ["static scene", "deforming geometry"]
        got = b.occluded(o, t, normals=nrm)
        errors[rebuild, mapping] = (got != ref).mean()
        if mapping == "conservative":
            # thicker surfaces: its errors are over-occlusion
            assert (got & ~ref).sum() > 5 * (~got & ref).sum()
    # measured 2.8 / 4.1 / 8.4 % at 32³ / 10°
    assert errors["geometry", "point"] < 0.05 and errors["rotate", "point"] < 0.07, errors
    assert errors["rotate", "conservative"] < 0.12, errors


# ----------------------------------------------------------------------------- what is rebuilt

def _lights(x: float) -> Lights:
    from usdml.scene import LightType

    n = 3
    return Lights(type=np.full(n, LightType.SPHERE, np.int8), position=np.array([[x, 5.0, 0.0]] * n),
                  axis=np.tile([0.0, 0.0, -1.0], (n, 1)), xform=np.tile(np.eye(4), (n, 1, 1)),
                  radiance=np.ones((n, 3), np.float32), intensity=np.ones((n, 3), np.float32),
                  radius=np.zeros(n), width=np.zeros(n), height=np.zeros(n), angle=np.zeros(n),
                  cone_angle=np.full(n, 180.0), cone_softness=np.zeros(n), focus=np.zeros(n),
                  focus_tint=np.ones((n, 3), np.float32), shadow=np.ones(n, bool), paths=["/l"] * n,
                  instance_ids=np.full(n, -1, np.int64))


def test_a_static_scene_rebuilds_nothing_on_its_second_frame_even_with_moving_lights():
    from dataclasses import replace

    ground = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)
    tower = soup("/tower", box((-1, 0, -1), (1, 4, 1)), id=2)
    one = replace(snapshot([ground, tower]), lights=_lights(0.0))
    two = replace(snapshot([ground, tower], time=2.0), lights=_lights(3.0))
    b = VoxelBackend(voxel_resolution=16, direction_step=15.0, **QUIET)
    b.update(one, diff(None, one))
    assert b.built == ["static scene"]
    words = b.words
    b.update(two, diff(one, two))
    assert b.built == [] and b.stats["builds"] == 1 and b.words is words


def test_a_deforming_scene_rebuilds_only_its_deforming_mesh_in_place(device):
    ground = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)
    plane = prototype("/plane", [soup("/plane/m", box((-2, -0.2, -0.5), (2, 0.2, 0.5)))], [translate(0, 3, 0)],
                      animated=True)

    def frame(t):
        blob = soup("/blob", box((-1 + t, 1, -1), (1 + t, 2 + t, 1)), id=2, deforming=True)
        return snapshot([ground, blob], [prototype("/plane", plane.meshes, [translate(t, 3, 0)], animated=True)],
                        time=t)

    b = VoxelBackend(voxel_resolution=16, direction_step=15.0, **QUIET, device=device)
    one, two, three = frame(1.0), frame(2.0), frame(3.0)
    b.update(one, diff(None, one))
    assert sorted(b.built) == ["deforming geometry", "prototype /plane", "static scene"]
    words = b.words
    b.update(two, diff(one, two))
    assert b.built == ["deforming geometry"]
    assert b.words is words                  # written in its slot: nothing reallocated
    # the in-place array is the one a fresh backend builds for frame two
    fresh = VoxelBackend(voxel_resolution=16, direction_step=15.0, **QUIET, device=device)
    fresh.update(two, diff(None, two))
    assert np.array_equal(b.words.numpy(), fresh.words.numpy())
    o, t, nrm = ground_queries(np.random.default_rng(2), 2000)
    assert np.array_equal(b.occluded(o, t, normals=nrm), fresh.occluded(o, t, normals=nrm))
    # the same geometry again: nothing to do
    b.update(two, diff(two, two))
    assert b.built == []
    b.update(three, diff(two, three))
    assert b.built == ["deforming geometry"] and b.stats["dynamic_rebuilds"] == 3


def test_fully_dynamic_puts_everything_in_one_per_frame_array():
    ground = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)
    plane = [soup("/plane/m", box((-2, -0.2, -0.5), (2, 0.2, 0.5)))]

    def frame(t):
        return snapshot([ground], [prototype("/plane", plane, [translate(t, 3, 0), translate(-t, 4, 2)],
                                             animated=True)], time=t)

    one, two = frame(1.0), frame(2.0)
    b = VoxelBackend(voxel_resolution=16, direction_step=15.0, fully_dynamic=True, **QUIET)
    assert [role for role, _ in b.plan(one)] == ["dynamic"]
    b.update(one, diff(None, one))
    assert b.built == ["dynamic scene"] and len(b.arrays) == 1
    b.update(two, diff(one, two))
    assert b.built == ["dynamic scene"]
    timing = b.per_frame_rebuild_seconds(two)
    assert timing["rebuild_seconds"] > 0 and timing["full_rebuild_seconds"] > 0 and timing["mapping"] == "point"
    # against exact: one world array is coarser for the small moving objects than Alg. 4's
    # prototype arrays (measured 7.9 % against 1.4 % at 32³ / 10°), and errs by over-occlusion
    flat = snapshot([ground] + [soup(f"/p{i}", (plane[0].points.reshape(-1, 3) + xf[:3, 3]).reshape(-1, 3, 3))
                                for i, xf in enumerate((translate(2, 3, 0), translate(-2, 4, 2)))])
    exact = ExactBackend()
    exact.update(flat)
    o, t, nrm = ground_queries(np.random.default_rng(3), 3000)
    t[:, 1] += 3
    ref = exact.occluded(o, t, normals=nrm)
    errors = {}
    for fully in (True, False):
        v = VoxelBackend(voxel_resolution=32, direction_step=10.0, fully_dynamic=fully, **QUIET)
        v.update(two)
        got = v.occluded(o, t, normals=nrm)
        errors[fully] = (got != ref).mean()
        if fully:
            assert (got & ~ref).sum() > 2 * (~got & ref).sum()
    assert errors[False] < errors[True] < 0.15, errors


def test_unknown_rebuild_or_mapping_is_refused():
    with pytest.raises(UsdmlError, match="rebuild"):
        VoxelBackend(voxel_rebuild="depth-peel", **QUIET)
    with pytest.raises(UsdmlError, match="mapping"):
        VoxelBackend(voxel_mapping="nearest", **QUIET)
    with pytest.raises(UsdmlError, match="core"):
        VoxelBackend(voxel_core=-1.0, **QUIET)


def test_conservative_mapping_keeps_the_longer_skip():
    """Thin surfaces skip at most MAX_SKIP voxels to leave the surface; the conservative mapping's
    thicker per-frame surfaces need CONSERVATIVE_MAX_SKIP; a given max_skip wins."""
    from usdml.visibility.voxel.backend import CONSERVATIVE_MAX_SKIP, MAX_SKIP

    assert VoxelBackend(**QUIET).max_skip == MAX_SKIP < CONSERVATIVE_MAX_SKIP
    assert VoxelBackend(voxel_mapping="conservative", **QUIET).max_skip == CONSERVATIVE_MAX_SKIP
    assert VoxelBackend(voxel_mapping="conservative", voxel_max_skip=3.0, **QUIET).max_skip == 3.0


# ---------------------------------------------------------------------------------------- CLI

@pytest.fixture
def deforming_stage(new_stage):
    """A ground, a mesh whose points are time-sampled over frames 1-3, three sphere lights above."""
    from pxr import Gf, UsdGeom, UsdLux, Vt

    stage = new_stage("deform.usda", 1, 3)
    ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
    ground.CreatePointsAttr([(-5, 0, -5), (5, 0, -5), (5, 0, 5), (-5, 0, 5)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    blob = UsdGeom.Mesh.Define(stage, "/World/Blob")
    cube = [(-1, 1, -1), (1, 1, -1), (1, 3, -1), (-1, 3, -1), (-1, 1, 1), (1, 1, 1), (1, 3, 1), (-1, 3, 1)]
    points = blob.CreatePointsAttr()
    for t in (1, 2, 3):
        points.Set(Vt.Vec3fArray([Gf.Vec3f(x * (1 + 0.2 * t), y, z) for x, y, z in cube]), t)
    blob.CreateFaceVertexCountsAttr([4] * 6)
    blob.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 7, 6, 5, 0, 4, 5, 1, 3, 2, 6, 7, 0, 3, 7, 4, 1, 5, 6, 2])
    for i, x in enumerate((-3, 0, 3)):
        light = UsdLux.SphereLight.Define(stage, f"/World/Light{i}")
        light.CreateIntensityAttr(50.0)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(x, 6, x / 2))
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    xf = UsdGeom.Xformable(cam)
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 9, 12))
    xf.AddRotateXOp().Set(-35.0)
    stage.GetRootLayer().Save()
    return stage.GetRootLayer().realPath


def test_cli_renders_compares_and_benches_a_deforming_stage(deforming_stage, tmp_path, monkeypatch, capsys):
    from usdml.cli import main

    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path / "cache"))
    small = ["--voxel-resolution", "16", "--direction-step", "15"]
    out = tmp_path / "f.####.exr"
    assert main(["render", deforming_stage, str(out), "--frames", "1:3", "--visibility", "voxel", "--imageWidth", "32",
                 *small]) == 0
    assert sorted(p.name for p in tmp_path.glob("f.*.exr")) == ["f.0001.exr", "f.0002.exr", "f.0003.exr"]
    capsys.readouterr()
    # ε_v bounds: measured 0.061, 0.016, 0.109 at 16³ / 15°, 32 px
    for flags, bound in ((["--voxel-mapping", "conservative"], 0.09), (["--voxel-rebuild", "geometry"], 0.03),
                         (["--fully-dynamic"], 0.15)):
        assert main(["compare", deforming_stage, "--visibility", "voxel", "--imageWidth", "32", "--json",
                     *small, *flags]) == 0
        r = json.loads(capsys.readouterr().out)
        assert r["queries"] > 0 and 0.0 <= r["eps_v"] < bound, (flags, r["eps_v"])
    assert main(["bench", deforming_stage, "--visibility", "voxel", "--imageWidth", "16", "--json", *small,
                 "--voxel-mapping", "conservative"]) == 0
    rows = json.loads(capsys.readouterr().out)
    voxel = [r for r in rows if r["backend"] == "voxel"][0]
    assert voxel["mapping"] == "conservative" and voxel["voxel_resolution"] == 16
    assert voxel["rebuild_seconds"] > 0 and voxel["full_rebuild_seconds"] > 0
    assert voxel["rebuild_speedup"] == pytest.approx(voxel["full_rebuild_seconds"] / voxel["rebuild_seconds"])
    # a fully dynamic scene has nothing to cache
    assert main(["bake", deforming_stage, "--fully-dynamic", "--json", *small]) == 0
    said = capsys.readouterr()
    assert json.loads(said.out)["arrays"] == [] and "nothing to bake" in said.err
    assert main(["render", deforming_stage, str(out), "--visibility", "voxel", "--voxel-mapping", "nearest"]) == 2
    assert "usdml: error: usdml render: argument --voxel-mapping: invalid choice: 'nearest'" in capsys.readouterr().err


def test_a_deforming_mesh_that_empties_and_comes_back():
    ground = soup("/ground", box((-10, -0.5, -10), (10, 0, 10)), id=1)

    def frame(t, tris):
        return snapshot([ground, soup("/blob", tris, id=2, deforming=True)], time=t)

    full = box((-2, 1, -2), (2, 3, 2))
    frames = [frame(1.0, full), frame(2.0, np.zeros((0, 3, 3))), frame(3.0, full + 0.5)]
    o, t, nrm = ground_queries(np.random.default_rng(6), 1500)
    b = VoxelBackend(voxel_resolution=16, direction_step=15.0, **QUIET)
    previous = None
    for snap in frames:
        b.update(snap, diff(previous, snap))
        previous = snap
        fresh = VoxelBackend(voxel_resolution=16, direction_step=15.0, **QUIET)
        fresh.update(snap)
        assert np.array_equal(b.occluded(o, t, normals=nrm), fresh.occluded(o, t, normals=nrm))
    assert len(b.arrays) == 2


def test_voxel_packing_round_trips_up_to_the_largest_resolution():
    from usdml.visibility.voxel.rotate import MAX_RESOLUTION, row_groups

    ijl = np.array([[0, 0, 0], [MAX_RESOLUTION - 1] * 3, [5, MAX_RESOLUTION - 1, 7], [5, MAX_RESOLUTION - 1, 2]])
    row_ij, row_start, depth = (a.astype(np.int64) for a in row_groups(ijl))
    assert (row_ij >= 0).all() and len(row_ij) == 3 and row_start[-1] == len(ijl)
    back = [(r >> 10, r & 1023, l) for k, r in enumerate(row_ij) for l in depth[row_start[k]:row_start[k + 1]]]
    assert sorted(back) == sorted(map(tuple, ijl.tolist()))
    blob = snapshot([soup("/blob", box((0, 0, 0), (1, 1, 1)), deforming=True)])
    with pytest.raises(UsdmlError, match="voxel-rebuild geometry"):
        VoxelBackend(voxel_resolution=MAX_RESOLUTION * 2, **QUIET).update(blob)
