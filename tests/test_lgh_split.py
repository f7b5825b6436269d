"""One LGH per VPL normal class on one grid (``--lgh-split normal``, usdml.lighting.lgh.build.build_lgh_split):
the hierarchy's own invariants, the gather against a window-free NumPy sum over every entry, the shadow
rays' member draws, and a ground beside a wall lit against the exact sum of its cosine emitters."""

import numpy as np
import pytest

pytest.importorskip("warp")

from usdml.lighting.lgh.build import NORMAL_CLASSES, build_lgh, build_lgh_split, normal_class  # noqa: E402
from usdml.lighting.lgh.shading import ClusterSampler, lgh_lighting  # noqa: E402
from test_lgh_lighting import _blend_np  # noqa: E402  (NumPy copy of the kernel's blending)


def _unit(v):
    v = np.asarray(v, np.float64)
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _random_vpls(seed: int, n: int):
    rng = np.random.default_rng(seed)
    pos = rng.uniform([-3, 0, -3], [3, 2, 3], (n, 3)).astype(np.float32)
    inten = rng.uniform(0.1, 1.0, (n, 3)).astype(np.float32)
    return pos, inten, _unit(rng.normal(size=(n, 3)))


def test_normal_classes_are_the_axis_and_sign_a_normal_leans_along():
    n = np.array([[0.1, 0.9, 0.2], [0, -1, 0], [-0.8, 0.5, 0.3], [0.2, 0.1, -0.97], [1, 0, 0], [0, 0.3, 0.9]],
                 np.float32)
    assert normal_class(n).tolist() == [2, 3, 1, 5, 0, 4]


def test_a_split_hierarchy_conserves_every_level_on_one_grid():
    pos, inten, nrm = _random_vpls(3, 3000)
    one = build_lgh(pos, inten, levels=4, normal=nrm)
    split = build_lgh_split(pos, inten, nrm, levels=4)
    assert split.depth == one.depth == 4 and len(split.levels) == 4 * NORMAL_CLASSES
    assert split.h1 == pytest.approx(one.h1)
    klass = normal_class(nrm)
    for level in range(1, 5):
        entries = [lv for lv in split.levels if lv.level == level]
        ref = one.levels[level - 1]
        for lv in entries:      # every class on the unsplit level's grid
            assert lv.spacing == pytest.approx(ref.spacing) and (lv.dims == ref.dims).all()
            np.testing.assert_allclose(lv.origin, ref.origin)
        # the classes partition the lights, and each class's grid lights carry all of its intensity
        members = np.concatenate([lv.members for lv in entries])
        assert sorted(members.tolist()) == list(range(len(pos)))
        for lv in entries:
            assert (klass[lv.members] == klass[lv.members[0]]).all()
            np.testing.assert_allclose(lv.intensity.sum(0), inten[lv.members].sum(0), rtol=2e-4)
            np.testing.assert_allclose(lv.count.sum(), len(lv.members), rtol=1e-4)
            # a class's grid lights emit about its own normals: their mean normal leans the class's way
            lean = np.einsum("ij,j->i", lv.lobe, np.eye(3)[klass[lv.members[0]] // 2]) * \
                (1 - 2 * (klass[lv.members[0]] % 2))
            assert (lean > 0).all()
    # the merged arrays are the entries', in order
    np.testing.assert_array_equal(split.position[split.offsets[5]:split.offsets[6]], split.levels[5].position)
    assert split.level_lights(2)[0].shape[0] == sum(len(lv.position) for lv in split.levels if lv.level == 2)


@pytest.mark.parametrize("alpha,s0", [(1.0, False), (1.5, True)])
def test_the_gather_blends_every_class_as_its_level(alpha, s0, device):
    """The kernel visits the vertices near a point of every class's entry; its sum must equal the sum,
    without any window, over every grid light of every entry blended as its level (and every VPL as S0),
    with each grid light's lobe 1 - |nu| + 4 max(0, -nu . w)."""
    pos, inten, nrm = _random_vpls(11, 2000)
    lgh = build_lgh_split(pos, inten, nrm, levels=4)
    rng = np.random.default_rng(5)
    pts = rng.uniform([-3.5, -0.5, -3.5], [3.5, 2.5, 3.5], (300, 3)).astype(np.float32)
    pn = _unit(rng.normal(size=(300, 3)))
    clamp = 0.05
    got = lgh_lighting(pts, pn, lgh, device=device, alpha=alpha, samples=0, clamp_distance=clamp,
                       s0=(pos, inten, nrm) if s0 else None).irradiance
    layers = ([(pos, inten, nrm, 0.5 * lgh.h1, 0)] if s0 else []) + \
        [(lv.position, lv.intensity, lv.lobe, lv.spacing, lv.level - 1 + int(s0)) for lv in lgh.levels]
    top = lgh.depth - 1 + int(s0)
    want = np.zeros((300, 3))
    for q, inte, nu, h, level in layers:
        w = q[None].astype(np.float64) - pts[:, None]
        d2 = (w ** 2).sum(-1)
        d = np.sqrt(d2)
        cos = np.maximum((w * pn[:, None]).sum(-1) / d, 0)
        lobe = 4 * np.maximum(-(w * nu[None]).sum(-1) / d, 0)
        if level > 0 or not s0:      # grid lights: their mean normal's lobe; S0 VPLs are pure cosines
            lobe = lobe + 1 - np.linalg.norm(nu, axis=1)[None]
        g = _blend_np(level, top, d, alpha * h) * cos * np.maximum(lobe, 0) / np.maximum(d2, clamp ** 2)
        want += (g[..., None] * inte[None]).sum(1)
    np.testing.assert_allclose(got, want, rtol=3e-4, atol=1e-6 * want.max())


def test_member_draws_stay_in_the_chosen_grid_lights_class(device):
    pos, inten, nrm = _random_vpls(4, 1500)
    lgh = build_lgh_split(pos, inten, nrm, levels=3)
    sampler = ClusterSampler(lgh, pos, inten, nrm)
    klass = normal_class(nrm)
    base = 0
    for lv in lgh.levels:
        for g in range(base, base + len(lv.position)):
            drawn = sampler.member[sampler.start[g]:sampler.stop[g]]
            assert (klass[drawn] == klass[lv.members[0]]).all()     # (a vertex no light is nearest to: none)
        base += len(lv.position)
    # every light is drawn from exactly one grid light per level
    assert len(sampler.member) == len(pos) * lgh.depth


def _ground_and_wall(n: int, seed: int = 2):
    """VPLs on a ground patch (y = 0, facing up) and on a wall rising from its edge (x = 0, facing +x), as
    a corner's first bounce leaves them, and receivers 10-30 patch sizes away on every side above the
    ground, facing the corner (far enough that where a grid light sits matters little, and how it
    emits, everything)."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 1, n), np.zeros(n), rng.uniform(-0.5, 0.5, n)])
    wall = np.column_stack([np.zeros(n), rng.uniform(0, 1, n), rng.uniform(-0.5, 0.5, n)])
    pos = np.concatenate([ground, wall]).astype(np.float32)
    nrm = np.concatenate([np.tile([0, 1, 0], (n, 1)), np.tile([1, 0, 0], (n, 1))]).astype(np.float32)
    inten = np.full((2 * n, 3), 0.5, np.float32)
    way = rng.normal(size=(300, 3))
    way[:, 1] = np.abs(way[:, 1]) + 0.2
    way /= np.linalg.norm(way, axis=1, keepdims=True)
    pts = (way * rng.uniform(10, 30, (300, 1))).astype(np.float32)
    return pos, inten, nrm, pts, (-way).astype(np.float32)


def test_a_corner_is_lit_as_its_vpls_light_it_when_split(device):
    """The exact sum of the VPLs as cosine emitters (I = Φ/4π, 4 I max(0, cos θ_l) cos θ_s / d²). One
    hierarchy merges the ground's and the wall's VPLs into grid lights with one mean normal between
    up and +x, which lights a point above the ground's far side as if the wall faced it half-way;
    one per normal class keeps each class's lobe."""
    pos, inten, nrm, pts, pn = _ground_and_wall(2000)
    clamp = 0.05
    w = pos[None].astype(np.float64) - pts[:, None]
    d2 = (w ** 2).sum(-1)
    d = np.sqrt(d2)
    cos_s = np.maximum((w * pn[:, None]).sum(-1) / d, 0)
    cos_l = np.maximum(-(w * nrm[None]).sum(-1) / d, 0)
    exact = ((4 * cos_l * cos_s / np.maximum(d2, clamp ** 2))[..., None] * inten[None]).sum(1)
    err = {}
    for name, lgh in (("one", build_lgh(pos, inten, levels=4, normal=nrm)),
                      ("split", build_lgh_split(pos, inten, nrm, levels=4))):
        got = lgh_lighting(pts, pn, lgh, device=device, alpha=1.0, samples=0, clamp_distance=clamp).irradiance
        err[name] = float(np.sqrt(np.mean((got - exact) ** 2)) / exact.mean())
    assert err["one"] > 0.1, err          # the case the split is for
    assert err["split"] < 0.1 * err["one"], err


@pytest.mark.parametrize("compiled", [True, False])
def test_the_pilot_sum_is_a_cosine_emitter(compiled):
    """vpl_irradiance (kernels/lgh/lghq.c's and NumPy's) against the analytic Lambertian emitters
    E = Σ Φ cos θ_l cos θ_s / (π d²), I = Φ/4π: thirteen lights, so the compiled sum's lanes of eight and its
    remainder both count."""
    from usdml.lighting.lgh.choice import vpl_irradiance
    from usdml.lighting.lgh.native import library

    if compiled and library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    rng = np.random.default_rng(8)
    q = (np.array([[0.3, 0.2, -0.1]]) + rng.normal(size=(13, 3)) * 0.5).astype(np.float32)
    n_l = _unit(rng.normal(size=(13, 3)))
    flux = rng.uniform(0.5, 2.0, size=(13, 3)).astype(np.float32)
    pts = (q[:1] + rng.normal(size=(300, 3)) * 3).astype(np.float32)
    pn = _unit(rng.normal(size=(300, 3)))
    got = vpl_irradiance(pts, pn, q, flux / np.float32(4 * np.pi), n_l, clamp_distance=1e-4, meters_per_unit=2.0,
                         compiled=compiled)
    w = q[None].astype(np.float64) - pts[:, None]                      # (P, L, 3)
    d = np.linalg.norm(w, axis=2)
    cos_l = np.maximum(-((w / d[..., None]) * n_l[None]).sum(2), 0.0)
    cos_s = np.maximum(((w / d[..., None]) * pn[:, None]).sum(2), 0.0)
    want = (cos_l * cos_s / (np.pi * d ** 2)) @ flux.astype(np.float64) / 4.0
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-12)
    assert (got == 0).any() and (got > 0).any()


def test_the_compiled_pilot_sum_is_numpys_with_clamped_and_coincident_lights():
    """kernels/lgh/lghq.c's sum (lanes of eight, four threads' blocks) and the NumPy one, where lights sit on points
    and within the clamp distance of them."""
    from usdml.lighting.lgh.choice import vpl_irradiance
    from usdml.lighting.lgh.native import library

    if library() is None:
        pytest.skip("the compiled LGH kernels are not built here")
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, size=(97, 3)).astype(np.float32)
    pn = _unit(rng.normal(size=(97, 3)))
    q = rng.uniform(-1, 1, size=(1003, 3)).astype(np.float32)
    q[:10] = pts[:10]                                      # on the point: adds nothing
    q[10:20] = pts[10:20] + np.float32(0.01) * pn[10:20]    # within the clamp
    n_l = _unit(rng.normal(size=(1003, 3)))
    inten = rng.uniform(0, 1, size=(1003, 3)).astype(np.float32)
    a = vpl_irradiance(pts, pn, q, inten, n_l, clamp_distance=0.05, meters_per_unit=0.01)
    b = vpl_irradiance(pts, pn, q, inten, n_l, clamp_distance=0.05, meters_per_unit=0.01, compiled=False)
    np.testing.assert_allclose(a, b, rtol=1e-9)
    assert np.isfinite(a).all() and (a > 0).any()


def test_auto_split_is_not_built_where_it_cannot_fit_the_budget():
    """A split hierarchy visits more lights than the single one: where the single one's smallest alpha
    already nears the visit budget, ``--lgh-split auto`` keeps it without building the split one; forced
    splits are used as asked."""
    from usdml.lighting.lgh.choice import choose

    pos, inten, nrm, pts, pn = _ground_and_wall(500)
    one = build_lgh(pos, inten, normal=nrm)

    def refuse():
        raise AssertionError("the split hierarchy was built")

    tight = choose(one, refuse, pts, pn, (pos, inten, nrm), clamp_distance=0.05, fraction=1e-4)
    assert tight.split == "none" and tight.lgh is one and set(tight.candidates) == {"none"}
    assert not tight.candidates["none"]["within_budget"] and tight.alpha == 1.0
    split = build_lgh_split(pos, inten, nrm)
    forced = choose(None, lambda: split, pts, pn, (pos, inten, nrm), alpha=1.5, split="normal", clamp_distance=0.05)
    assert forced.split == "normal" and forced.lgh is split and forced.alpha == 1.5
    # a budget every alpha fits: the split hierarchy, which lights this corner as its VPLs do
    # (test_a_corner_is_lit_as_its_vpls_light_it_when_split), at the first alpha the pilot finds within target
    from usdml.lighting.lgh.choice import PILOT_TARGET

    wide = choose(one, lambda: split, pts, pn, (pos, inten, nrm), clamp_distance=0.05, fraction=10.0)
    assert wide.split == "normal" and wide.lgh is split, wide.candidates
    tried = wide.candidates["normal"]["pilot"]
    assert tried[-1]["alpha"] == wide.alpha and tried[-1]["rel_rmse"] <= PILOT_TARGET
    assert all(t["rel_rmse"] > PILOT_TARGET for t in tried[:-1])
    # a target nothing meets: the alpha that erred least, every alpha tried
    strict = choose(one, lambda: split, pts, pn, (pos, inten, nrm), clamp_distance=0.05, fraction=10.0, target=0.0)
    tried = strict.candidates["normal"]["pilot"]
    assert len(tried) == 9 and strict.alpha == min(tried, key=lambda t: t["rel_rmse"])["alpha"]
    # no shading points (a frame that sees no geometry): nothing to compare on, the single hierarchy
    empty = choose(one, lambda: split, pts[:0], pn[:0], (pos, inten, nrm), clamp_distance=0.05, fraction=10.0)
    assert empty.split == "none" and empty.lgh is one
