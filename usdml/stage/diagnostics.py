"""USD's own warnings (TF_WARN, TF_STATUS) as usdml warnings, so ``-q`` hides them and each names its prim.

Without a diagnostic delegate, Tf prints ``Warning: in <C++ function> at line N of <file> -- <message>``
straight to stderr. While :func:`usd_diagnostics` is active, a ``UsdUtils.CoalescingDiagnosticDelegate``
collects them instead (Tf prints nothing while a delegate is registered) and they are re-issued through
usdml's ``warn``, without the C++ location. Tf *errors* are untouched: that delegate ignores them, and
the Python bindings turn an error raised by a call into ``Tf.ErrorException`` as before.

A composition error is said twice by USD: as a warning while the stage is composed (``In </World/P9>: Could not
open asset @missing.usda@ ... (instantiating stage on stage @shot.usda@ <0x55...>)``) and in
``Usd.Stage.GetCompositionErrors``. Both become the same line, :func:`composition_message`'s, so a warning
collector that keeps each message once keeps one of them.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Callable, Iterator

from pxr import UsdUtils

#: UsdStage's report of its composition errors: ``In </Prim>: `` (none for a layer stack's), the error, and
#: what the stage was doing (``(instantiating stage on stage @shot.usda@ <0x55...>)``)
_COMPOSING = re.compile(r"^(?:In <(?P<path>[^<>]*)>: )?(?P<error>.*) \([^()]* on stage @[^@]*@ <[^<>]*>\)$")


_MTLX_ARC = re.compile(r"Could not open asset @(?P<asset>[^@]+\.mtlx)@")


def read_by_usdml(error: str) -> bool:
    """Whether a composition error is an arc to an existing ``.mtlx`` document, which usd-core cannot compose but
    usdml reads itself with the ``materialx`` package (:mod:`usdml.stage.materialx`): not a loss, so not said
    (a document that does not parse is said by that reader, a missing one still is here)."""
    import os

    found = _MTLX_ARC.search(error)
    if not found or not os.path.isabs(found["asset"]) or not os.path.isfile(found["asset"]):
        return False
    try:
        import MaterialX  # noqa: F401
    except ImportError:
        return False
    return True


def composition_message(path: str, error: str, where: str) -> str:
    """One composition error's line: ``/Prim: composition error: ...`` (``where``, the stage's file, for one
    at the pseudo-root: a sublayer that does not load)."""
    subject = path if path.startswith("/") and path != "/" else where
    return f"{subject}: composition error: {' '.join(error.split())}"


def usd_message(commentary: str, where: str) -> str:
    """One warning line: ``/Prim/Path: message`` for USD's ``/Prim/Path -- message``, a composition error as
    :func:`composition_message`, else ``where: message``."""
    text = " ".join(commentary.split())
    composing = _COMPOSING.match(text)
    if composing:
        return composition_message(composing["path"] or "", composing["error"], where)
    path, sep, rest = text.partition(" -- ")
    if sep and path.startswith("/") and " " not in path:
        return f"{path}: {rest}"
    return f"{where}: {text}"


@contextlib.contextmanager
def usd_diagnostics(warn: Callable[[str], None], where: str) -> Iterator[None]:
    """Route USD warnings and statuses issued inside the block (any thread) to ``warn``; ``where`` (the
    stage's file) names those that carry no prim path."""
    delegate = UsdUtils.CoalescingDiagnosticDelegate()
    try:
        yield
    finally:
        items = delegate.TakeUncoalescedDiagnostics()
        del delegate                      # unregisters it: Tf prints to stderr again
        for item in items:
            if not read_by_usdml(item.commentary):
                warn(usd_message(item.commentary, where))
