"""Denoising a frame's radiance AOVs with Intel Open Image Denoise (``--denoise``, ``usdml:denoise``).

What is denoised: the AOVs ``--denoise-aovs`` (``usdml:denoise:aovs``) names among those the frame writes,
``color`` by default; only radiance is denoisable (:data:`DENOISABLE`, and every ``lightgroup:NAME``) -- depth,
normals, positions, ids, ``shadow`` and ``lightCount`` are not images of light and are refused by the parameter
table. ``color``'s RGB is denoised as it is written (premultiplied), its alpha is kept as rendered; the noisy
beauty is the AOV ``color_noisy`` (written when asked for).

How: OIDN's ``RT`` filter in HDR mode, per frame, after the pixel filter, with two guides rendered with every
frame that denoises -- ``albedo`` and ``denoiseNormal`` (world-space shading normal), both box-filtered over the
pixel samples exactly as ``color`` is, as OIDN asks ("all feature images should use the same pixel reconstruction
filter as the color image"). Guides from primary hits are clean on still, sharp frames but noisy under depth of
field and motion blur (the lens and time samples of a pixel see different surfaces), so they are first denoised
by OIDN itself (an ``RT`` filter on the guide alone) and the beauty is then filtered with ``cleanAux`` on: OIDN's
documented way to its best quality for final frames. OIDN runs on the CPU device with usdml's thread count
(:func:`usdml.parallel.cpu_workers`: ``--nthreads`` / a farm worker's share), without pinning threads to
cores, as another worker may share the machine.

The frame's error estimates (``usdml:estimate:*``) are of the frame before denoising; the header says so
(:func:`headers`).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass

import numpy as np

from usdml.aov.names import EVERY_LIGHT_GROUP, is_light_group
from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers
from usdml.render.denoise.params import aov_list

#: the guide AOVs a denoising frame renders, box-filtered like color
GUIDES = ("albedo", "denoiseNormal")


def wanted(value: str, written) -> list[str]:
    """The AOVs of ``written`` (the frame's) that ``value`` (``denoise_aovs``) asks to denoise, in frame order."""
    names = set(aov_list(value))
    every_group = EVERY_LIGHT_GROUP in names
    return [a for a in written if a in names or (every_group and is_light_group(a))]


def require_denoiser(where: str) -> str:
    """Check, before any frame renders, that OIDN loads and runs on this CPU; returns its version (``2.5.1``).
    Otherwise a one-line :class:`UsdmlError` starting with ``where`` (how the user asked: ``--denoise``) that
    names the cause and what to do."""
    try:
        import pyoidn
    except ImportError as e:
        raise UsdmlError(f"{where}: Intel Open Image Denoise is not installed ({e}); install it with "
                         "pip install -c constraints.txt pyoidn, or render without denoising") from None
    try:
        supported = bool(pyoidn.Device.is_cpu_available())
    except OSError as e:      # the wheel's libOpenImageDenoise (or a library it needs) does not load
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise UsdmlError(f"{where}: pyoidn cannot load Open Image Denoise's library ({reason}); reinstall pyoidn "
                         "(pip install --force-reinstall -c constraints.txt pyoidn), or render without "
                         "denoising") from None
    if not supported:
        raise UsdmlError(f"{where}: Open Image Denoise does not run on this CPU (it needs x86-64 with SSE4.1, or "
                         "ARM64); render without denoising, or on another machine")
    return _denoiser(cpu_workers("cpu")).version


@dataclass
class _Oidn:
    """One OIDN CPU device of this process (made once per thread count: loading it costs about 0.1 s)."""

    device: object
    version: str
    threads: int

    def check(self, what: str) -> None:
        message = self.device.get_error()
        if message is not None:
            raise UsdmlError(f"--denoise: Open Image Denoise failed {what}: {message}")

    def filter(self, images: dict[str, np.ndarray], output: np.ndarray, clean_aux: bool = False) -> None:
        """Run one ``RT`` filter over ``images`` (slot -> (H, W, 3) float32) into ``output``: a beauty (``color``
        among them) in HDR mode at quality high; a guide alone at quality balanced (as good a beauty afterwards on
        the tuning stages of tools/denoise_accuracy.py, in half the time or less)."""
        import pyoidn

        flt = pyoidn.Filter(self.device, pyoidn.OIDN_FILTER_TYPE_RT)
        try:
            for slot, image in images.items():
                flt.set_image(slot, image, pyoidn.OIDN_FORMAT_FLOAT3)
            flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, output, pyoidn.OIDN_FORMAT_FLOAT3)
            if "color" in images:
                flt.set_bool("hdr", True)
                flt.set_bool("cleanAux", clean_aux)
            flt.set_quality(pyoidn.OIDN_QUALITY_HIGH if "color" in images else pyoidn.OIDN_QUALITY_BALANCED)
            flt.commit()
            self.check("to set up its filter")
            flt.execute()
            self.check("to filter the frame")
        finally:
            flt.release()


_DEVICES: dict[int, _Oidn] = {}


def _denoiser(threads: int) -> _Oidn:
    if threads not in _DEVICES:
        import pyoidn

        device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        device.set_int("numThreads", threads)
        device.set_bool("setAffinity", False)
        device.commit()
        v = device.get_int("version")
        oidn = _Oidn(device, f"{v // 10000}.{v // 100 % 100}.{v % 100}", threads)
        oidn.check("to start its CPU device")
        _DEVICES[threads] = oidn
    return _DEVICES[threads]


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(image[..., :3], dtype=np.float32)


def guides(buffers: dict[str, np.ndarray], oidn: _Oidn, prefilter: str) -> dict[str, np.ndarray]:
    """The frame's guides (``albedo``, ``normal``: (H, W, 3) float32), each first denoised by OIDN on its own
    where ``prefilter`` is ``accurate``."""
    out = {}
    for slot, name in zip(("albedo", "normal"), GUIDES):
        image = _rgb(buffers[name])
        if slot == "albedo":
            image = np.clip(image, 0.0, 1.0)      # OIDN's albedo is a reflectance in [0, 1]
        if prefilter == "accurate":
            clean = np.empty_like(image)
            oidn.filter({slot: image}, clean)
            image = clean
        out[slot] = image
    return out


def denoise_frame(buffers: dict[str, np.ndarray], names: list[str], prefilter: str,
                  threads: int | None = None) -> dict:
    """Denoise ``names`` (radiance AOVs of ``buffers``, (H, W, 3) or ``color``'s (H, W, 4)) in place, guided by
    :data:`GUIDES` (which ``buffers`` must hold), on ``threads`` (default :func:`usdml.parallel.cpu_workers`);
    alpha is left as it is. ``prefilter`` (``--denoise-prefilter``, Cycles' choices): ``accurate`` denoises the
    guides first and tells OIDN they are clean (``cleanAux``); ``fast`` hands them over as rendered for OIDN to
    clean inside its filter; ``none`` hands them over as rendered as clean. Returns what was done, for the
    frame's stats and header: ``{"aovs", "denoiser", "seconds"}``."""
    t0 = _time.perf_counter()
    oidn = _denoiser(cpu_workers("cpu", threads))
    aux = guides(buffers, oidn, prefilter)
    for name in names:
        noisy = buffers[name]
        clean = np.empty(noisy.shape[:2] + (3,), np.float32)
        oidn.filter({"color": _rgb(noisy), **aux}, clean, clean_aux=prefilter != "fast")
        out = noisy.astype(np.float32, copy=True)
        out[..., :3] = clean
        buffers[name] = out
    return {"aovs": list(names), "denoiser": describe(oidn, prefilter), "seconds": _time.perf_counter() - t0}


def describe(oidn: _Oidn, prefilter: str) -> str:
    """How a frame was denoised, for its header."""
    aux = {"accurate": "each prefiltered by OIDN at quality balanced, cleanAux", "fast": "as rendered, cleaned inside the filter",
           "none": "as rendered, cleanAux"}[prefilter]
    return (f"Intel Open Image Denoise {oidn.version} (CPU, {oidn.threads} threads; RT filter, HDR, quality high; "
            f"guides albedo and denoiseNormal {aux})")


def headers(done: dict | None) -> dict:
    """The EXR attributes of a frame's denoising (``done``: :func:`denoise_frame`'s result, None: not denoised)."""
    if not done:
        return {}
    return {"usdml:denoise": f"{', '.join(done['aovs'])}: {done['denoiser']}",
            "usdml:denoise:seconds": float(done["seconds"]),
            "usdml:estimate:denoised": "no: the usdml:estimate:* attributes measure the frame before denoising "
                                       "(color_noisy), not the denoised AOVs"}
