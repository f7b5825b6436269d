"""What a frame's pixels depend on, written to every EXR's header and checked by ``--resume``.

``usdml:settings`` holds it as readable JSON (sorted keys), ``usdml:settingsDigest`` as
``sha256:<hex>`` of that JSON. It holds:

* ``params``: the effective :class:`usdml.settings.UsdmlSettings` (defaults, the stage's ``usdml:*``
  attributes, then the command line's flags): visibility, GI, pixel samples, seed, every knob;
* ``resolution`` ``[width, height]``, ``camera`` (the prim rendered from, ``(framing)`` for the
  framing camera), ``renderSettings`` (the RenderSettings prim in force, or null), ``purposes``
  (``--purposes``, null: the RenderSettings' or the default), ``implicitDetail``, ``cameraLight``;
* ``layers``: the file's layers, layer name -> AOV;
* ``stage``: the root layer's file and a fingerprint of every layer the stage uses
  (:func:`usdml.stage.fingerprint.stage_fingerprint`).

Left out, on purpose: the device (CPU and CUDA render the same image up to rounding, and a farm may
mix them), usdml's version (``usdml:version`` says it; an upgrade does not make every frame stale),
and the timecode (each frame has its own file).
"""

from __future__ import annotations

import hashlib
import json

#: the header attributes (:func:`usdml.aov.exr.write_exr` writes ``usdml:settings``)
SETTINGS_ATTR = "usdml:settings"
DIGEST_ATTR = "usdml:settingsDigest"


def frame_settings(params: dict, *, resolution: tuple[int, int], camera: str | None, render_settings: str | None,
                   purposes: list[str] | None, implicit_detail: int, camera_light: bool, layers: dict[str, str],
                   stage: dict) -> dict:
    """Everything above as one JSON-ready dict (``params``: ``UsdmlSettings.as_dict()``, ``stage``:
    :func:`stage_fingerprint`)."""
    return {"params": dict(params), "resolution": [int(resolution[0]), int(resolution[1])],
            "camera": camera or "(framing)", "renderSettings": render_settings,
            "purposes": None if purposes is None else sorted({str(p) for p in purposes}),
            "implicitDetail": int(implicit_detail), "cameraLight": bool(camera_light),
            "layers": dict(sorted(layers.items())), "stage": dict(stage)}


def settings_json(settings: dict) -> str:
    """The readable form stored as ``usdml:settings``: sorted keys, so equal settings give equal text."""
    return json.dumps(settings, sort_keys=True, default=str)


def settings_digest(settings: dict) -> str:
    """``sha256:<hex>`` of :func:`settings_json`."""
    return "sha256:" + hashlib.sha256(settings_json(settings).encode()).hexdigest()
