"""Every light its own light (``--lgh-split each``, ``--direct-gather each``): the lighting grid hierarchy's limit,
summed exactly.

Paper 004's hierarchy stands a grid light in for the lights near each vertex so that a point visits a few
hundred lights instead of all of them. From S0 with α growing, a point visits more of the lights themselves; at
the limit it visits every one, and the hierarchy's own error is gone. A point's visit through the compiled gather
costs 24-36 ns for VPLs (a grid light's blend, lobe and a streaming draw for each of the k shadow samples), while a
light's term in a plain sum over all of them costs about 0.25-0.4 ns on two cores (``kernels/lgh/lghq.c``,
``lghq_each``: sixteen lights at a time, float): so where the hierarchy would visit more than a few hundredths of
the lights per point, the limit itself is the cheaper way there: for VPLs where the pilot finds no α within
target at fewer visits than about 1.5 % of them with AVX-512 (:mod:`usdml.lighting.lgh.choice`), for the stage's
own lights where the gather at ``usdml:direct:alpha`` visits more than about 3 % of them
(:func:`usdml.lighting.lgh.direct.choose_gather`). The hierarchy's cost does not grow with the light count, the
sum's does.

The lights are the LGH's: an isotropic share ``a = 1 - |normal|`` plus a one-sided cosine lobe ``4 max(0, cos θ_l)``
about the normal (VPLs and disk lights ``a = 0``, the stage's point lights ``a = 1`` with no normal). What a point
gets, as :class:`usdml.lighting.lgh.shading.LGHShading`: the unshadowed irradiance of every light (for VPLs the
cosine emitters brute force gathers, with its clamp), the lights that reach it, and k shadow samples drawn among
the lights with probability in proportion to their luminance at the point (systematic sampling: one uniform per
point, along the lights in Morton order, so that a point's draws spread over space), each with its RGB irradiance
over its luminance. :func:`usdml.lighting.lgh.shading.shadow_fraction`'s ``F · mean(V · e / f)`` over them (or
its inclusion-probability form, for the stage's lights) is then an unbiased estimate of brute force's shadowed
sum, and the frame's à-trous filter and shadow ratio do the rest as for a hierarchy. Shadow rays go to the lights
themselves, as brute force's do.
"""

from __future__ import annotations

import numpy as np

from usdml.kernels.brdf import WIDTH
from usdml.lighting.lgh.shading import LUMA, LGHShading
from usdml.lighting.lgh.native import isotropic_share
from usdml.parallel import cpu_workers, run_parallel, spans

#: lights a NumPy block holds at once, times its points (the fallback's memory: about 40 bytes each); with material
#: rows (each pair's BRDF row and terms: some 200 bytes)
_PAIRS = 1 << 21
_BRDF_PAIRS = 1 << 18

#: the fewest lights that share one unit normal, bit for bit, to be a normal class (:func:`light_order`)
CLASS_LIGHTS = 256


def light_order(position: np.ndarray, normal: np.ndarray | None) -> np.ndarray:
    """The order :class:`EachLight` takes its lights in: each class of at least :data:`CLASS_LIGHTS` lights that share
    one unit normal (the VPLs on one flat floor or wall), the largest first, then every other light; within each,
    Morton order of the positions. A point on such a floor gets nothing from the floor's own VPLs (one of its
    cosines is at most 0 wherever its normal is theirs), and ``lghq_each`` skips a group of lights whose shared
    normal is the point's (``EachLights``' group normals); in Morton order alone the open suite stages' floors mixed
    with their boxes' faces in most groups (32 % of the pairs skippable at 10,000 VPLs, 56 % by classes)."""
    from usdml.zorder import morton_order

    if not len(position):
        return np.zeros(0, np.int64)
    morton = morton_order(np.asarray(position, np.float32))
    if normal is None:
        return morton
    nrm = np.ascontiguousarray(np.asarray(normal, np.float32).reshape(-1, 3)[morton])
    keys, inverse, counts = np.unique(nrm.view(np.dtype((np.void, 12))).ravel(), return_inverse=True,
                                      return_counts=True)
    unit = isotropic_share(keys.view(np.float32).reshape(-1, 3)) == 0.0
    big = np.flatnonzero((counts >= CLASS_LIGHTS) & unit)
    if not len(big):
        return morton
    rank = np.full(len(keys), len(big), np.int64)                  # the rest after the classes
    rank[big[np.argsort(-counts[big], kind="stable")]] = np.arange(len(big))
    return morton[np.argsort(rank[inverse.ravel()], kind="stable")]


class EachLight:
    """The lights as a hierarchy of one level of themselves: what :func:`usdml.lighting.lgh.shading.lgh_indirect`
    gathers from in place of a hierarchy (``sources = (positions, intensities, normals or None)`` as the LGH
    takes them: VPLs with intensity Φ/4π and unit normals, the stage's point lights with none)."""

    each = True
    levels: tuple = ()

    def __init__(self, sources: tuple):
        position = np.asarray(sources[0], np.float64).reshape(-1, 3)
        normal = sources[2] if len(sources) > 2 else None
        #: the lights by normal class, each in Morton order of their positions (:func:`light_order`): the systematic
        #: draws run through them in this order, so a point's k draws are spread over space as a grid's would be (in
        #: the order given, often random, they were as noisy as independent draws)
        self.order = light_order(position, normal)
        self.position = position[self.order]
        self.position32 = self.position.astype(np.float32)
        self.intensity = np.asarray(sources[1], np.float32).reshape(-1, 3)[self.order]
        self.normal = (np.zeros_like(self.intensity) if normal is None else
                       np.asarray(normal, np.float32).reshape(-1, 3)[self.order])
        #: each light's isotropic share, the LGH lobe's 1 - |normal| (0 for a VPL, 1 for a point light)
        self.isotropic = isotropic_share(self.normal)
        self._sums = None

    def __len__(self) -> int:
        return len(self.position)

    def compiled_sums(self):
        """The lights as ``lghq_each`` takes them (:class:`usdml.lighting.lgh.native.EachLights`), made once: a
        frame's passes and its pilot gather from the same lights (0.28 s at a million lights)."""
        from usdml.lighting.lgh import native as lgh_native

        if self._sums is None:
            self._sums = lgh_native.EachLights(self.position, self.intensity, self.normal)
        return self._sums

    def gather(self, samples: int, seed: int, meters_per_unit: float, clamp_distance: float,
               compiled: bool = True) -> "EachGather":
        return EachGather(self, samples, seed, meters_per_unit, clamp_distance, compiled)


class EachGather:
    """``gather(points, normals, tile=None, first=0) -> LGHShading`` over every light of an :class:`EachLight`
    (the interface of :class:`usdml.lighting.lgh.shading.LGHGather`; ``tile`` is not used: every point sums
    every light). Compiled (``lghq_each``) where the extension is built and ``compiled``, else NumPy with the
    same random numbers (the same draws but where float rounding puts a threshold on the other side of a
    light). The shading's ``count`` is the lights that reach each point (their luminance there above 0)."""

    def __init__(self, lights: EachLight, samples: int, seed: int, meters_per_unit: float, clamp_distance: float,
                 compiled: bool = True):
        from usdml.lighting.lgh import native as lgh_native

        self.vpls = lights
        self.k = max(int(samples), 0)
        self.seed = int(seed)
        self.inv_m2 = 1.0 / float(meters_per_unit) ** 2
        self.clamp_d2 = float(clamp_distance) ** 2
        self.lights = lights.compiled_sums() if compiled and lgh_native.library() is not None else None

    compiled = True     # (a gather of every light takes material rows compiled or by NumPy)

    def __call__(self, points: np.ndarray, normals: np.ndarray, tile: np.ndarray | None = None,
                 first: int = 0, material: np.ndarray | None = None, albedo: np.ndarray | None = None) -> LGHShading:
        p = np.ascontiguousarray(np.asarray(points).reshape(-1, 3), np.float32)
        nrm = np.ascontiguousarray(np.asarray(normals).reshape(-1, 3), np.float32)
        n, k = len(p), self.k
        out = (np.zeros((n, 3), np.float32), np.zeros(n, np.float32), np.full((n, k), -1, np.int32),
               np.zeros((n, k, 3), np.float32), np.zeros((n, k), np.float32), np.zeros((n, k), np.uint8))
        specular = None
        if material is not None:
            # the preview surface: every light's outgoing radiance (its BRDF toward the light), drawn by it
            specular = np.zeros((n, 3), np.float32)
            rows = np.ascontiguousarray(material, np.float32).reshape(-1, WIDTH)
            rho = np.ascontiguousarray(albedo, np.float32).reshape(-1, 3)
            if n and len(self.vpls):
                if self.lights is not None:
                    full = (out[0], specular, *out[1:])
                    run_parallel(lambda span: self.lights.gather_brdf(p, nrm, rows, rho, self.clamp_d2, self.inv_m2,
                                                                      k, self.seed, first, *span, full),
                                 spans(n, 4 * cpu_workers()), cpu_workers())
                else:
                    self._numpy(p, nrm, first, out, rows, rho, specular)
        elif n and len(self.vpls):
            if self.lights is not None:
                run_parallel(lambda span: self.lights.gather(p, nrm, self.clamp_d2, self.inv_m2, k, self.seed,
                                                             first, *span, out),
                             spans(n, 4 * cpu_workers()), cpu_workers())
            else:
                self._numpy(p, nrm, first, out)
        irradiance, count, light, weight, lum, ok = out
        ok = ok.view(bool)
        # the drawn lights' positions and their places in the order given (row gathers by np.take, the unchosen
        # samples set apart after: a boolean mask over the n·k samples cost 1.5 s of a million-light frame)
        if len(self.vpls):
            at = np.maximum(light, 0)
            pos = np.take(self.vpls.position32, at, axis=0)
            index = np.take(self.vpls.order, at).astype(np.int64, copy=False)
        else:
            pos, index = np.zeros((n, k, 3), np.float32), np.full((n, k), -1, np.int64)
        if n and k and not ok.all():
            pos[~ok] = 0.0
            index[~ok] = -1
        return LGHShading(irradiance, pos, ok, index, weight, None, count, lum, np.ones(len(self.vpls), np.float32),
                          specular)

    def _numpy(self, p: np.ndarray, nrm: np.ndarray, first: int, out: tuple, material: np.ndarray | None = None,
               albedo: np.ndarray | None = None, specular: np.ndarray | None = None) -> None:
        """:meth:`__call__`'s sums and draws by NumPy, block by block of points, in float64 (the BRDF's terms in
        float32, :func:`usdml.kernels.brdf.brdf_terms`). With ``material`` rows the sums are each light's outgoing
        radiance ``E·(ρ/π·kd + ks)`` (``albedo`` ρ) and ``specular`` gets ``Σ E·ks``; the draws follow the radiance."""
        irradiance, count, light, weight, lum, ok = out
        q = self.vpls.position
        nq = self.vpls.normal.astype(np.float64)
        iso = self.vpls.isotropic
        inten = self.vpls.intensity.astype(np.float64)
        luma = np.maximum(inten @ LUMA, 0.0)
        k = self.k
        u = uniform(self.seed, first + np.arange(len(p), dtype=np.int64)) if k else None
        step = max(1, (_PAIRS if material is None else _BRDF_PAIRS) // max(len(q), 1))
        for lo in range(0, len(p), step):
            hi = min(len(p), lo + step)
            w = q[None, :, :] - p[lo:hi, None, :].astype(np.float64)           # (B, V, 3)
            d2 = (w * w).sum(-1)
            cs = np.maximum(np.einsum("bvc,bc->bv", w, nrm[lo:hi].astype(np.float64)), 0.0)
            cl = np.maximum(-np.einsum("bvc,vc->bv", w, nq), 0.0)
            lobe = 4.0 * cl + (iso[None, :] * np.sqrt(d2) if iso.any() else 0.0)
            den = d2 * np.maximum(d2, self.clamp_d2)
            g = np.where(den > 0, cs * lobe / np.where(den > 0, den, 1.0), 0.0) * self.inv_m2
            count[lo:hi] = (g * luma[None, :] > 0).sum(axis=1)
            if material is None:
                irradiance[lo:hi] = g @ inten
                rgb = None
                f = g * luma[None, :]
            else:
                rgb, spec = _brdf_radiance(g, w, inten, nrm[lo:hi], material[lo:hi], albedo[lo:hi])
                irradiance[lo:hi] = rgb.sum(axis=1)
                specular[lo:hi] = spec.sum(axis=1)
                f = np.maximum(rgb @ LUMA, 0.0)
            if not k:
                continue
            cum = np.cumsum(f, axis=1)
            for b in range(hi - lo):
                total = cum[b, -1]
                if not total > 0:
                    continue
                t = (np.arange(k) + u[lo + b]) / k * total
                j = np.minimum(np.searchsorted(cum[b], t, side="right"), len(q) - 1)
                fj = f[b, j]
                good = fj > 0
                row = lo + b
                ok[row] = good
                light[row] = np.where(good, j, -1)
                lum[row] = np.where(good, fj, 0.0)
                e = g[b, j][:, None] * inten[j] if rgb is None else rgb[b, j]
                weight[row] = np.where(good[:, None], e / np.where(good, fj, 1.0)[:, None], 0.0)


def _brdf_radiance(g: np.ndarray, w: np.ndarray, inten: np.ndarray, normals: np.ndarray, rows: np.ndarray,
                   albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(radiance, specular)`` ``(B, V, 3)`` float64 of V lights at B points: irradiance ``g·I`` (``g`` (B, V), ``I``
    (V, 3)) times ``ρ/π·kd + ks`` and ``ks`` of the points' material ``rows`` toward each light (``w`` (B, V, 3), point
    to light), as ``lghq.c``'s ``brdf_radiance``."""
    from usdml.kernels.brdf import brdf_terms

    b, v = g.shape
    e = g[:, :, None] * inten[None, :, :]
    rad = np.zeros((b, v, 3))
    spec = np.zeros((b, v, 3))
    pi, li = np.nonzero(g > 0)
    if len(pi):
        d = w[pi, li]
        ll = d / np.sqrt((d * d).sum(axis=1))[:, None]
        kd, ks = brdf_terms(rows[pi], normals[pi], ll)
        rp = np.asarray(albedo, np.float32)[pi] / np.float32(np.pi)
        spec[pi, li] = e[pi, li] * ks
        rad[pi, li] = e[pi, li] * (rp * kd + ks)
    return rad, spec


def _pcg(state: np.ndarray) -> np.ndarray:
    """Warp's PCG hash on uint32 (``kernels/lgh/lghq.c``'s ``pcg``), element-wise."""
    with np.errstate(over="ignore"):
        b = state * np.uint32(747796405) + np.uint32(2891336453)
        c = ((b >> ((b >> np.uint32(28)) + np.uint32(4))) ^ b) * np.uint32(277803737)
    return (c >> np.uint32(22)) ^ c


def uniform(seed: int, offsets: np.ndarray) -> np.ndarray:
    """The first uniform of each stream ``rand_init(seed, offset)`` as ``lghq.c`` draws it (float64 of the same
    float32 value)."""
    off = np.asarray(offsets).astype(np.int64).astype(np.int32).view(np.uint32)
    with np.errstate(over="ignore"):
        state = _pcg(np.uint32(seed & 0xFFFFFFFF) + _pcg(off))
    state = _pcg(state)
    return ((state >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / 16777216.0)).astype(np.float64)
