"""A stage's identity for ``--resume``: its root layer's file and a fingerprint of every layer it uses.

A frame on disk counts as complete only if it was rendered from the same stage content
(:mod:`usdml.render.identity`). Hashing the layers' bytes would cost seconds on a large ``.usdc`` at
every start, so a file-backed layer is fingerprinted by what ``make`` trusts: its resolved path, its
size and its modification time (ns). A layer with unsaved edits (a pipeline script's open stage) and an
anonymous layer (the session layer, an in-memory stage) have no file that says so, so theirs is the
SHA-256 of the layer's text; an anonymous layer's identifier (``anon:0x...``) changes from one process to
the next and is left out. Files the layers only point at (textures) are not part of it.
"""

from __future__ import annotations

import hashlib
import os

from pxr import Usd


def _layer_entry(layer) -> str:
    """One line for ``layer``: its file's path, size and mtime, or a hash of its text."""
    real = layer.realPath
    if real and not layer.dirty and not layer.anonymous:
        try:
            st = os.stat(real.split("[", 1)[0])        # a layer inside a .usdz: the package's file
            return f"{real}\t{st.st_size}\t{st.st_mtime_ns}"
        except OSError:
            pass
    text = hashlib.sha256(layer.ExportToString().encode()).hexdigest()
    return f"{real or '(anonymous)'}\t{text}"


def stage_fingerprint(stage: Usd.Stage) -> dict:
    """``{"path": the root layer's file (or "(in memory)"), "layers": "sha256:<hex>"}``: the same for
    the same stage content in any process (layers in sorted order, as :func:`_layer_entry` describes),
    different after any used layer is saved or edited in memory."""
    entries = sorted(_layer_entry(layer) for layer in stage.GetUsedLayers())
    digest = hashlib.sha256("\n".join(entries).encode()).hexdigest()
    return {"path": stage.GetRootLayer().realPath or "(in memory)", "layers": f"sha256:{digest}"}
