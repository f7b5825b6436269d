"""USD's own warnings (TF_WARN, TF_STATUS) as usdml warnings, so ``-q`` hides them and each names its prim.

Without a diagnostic delegate, Tf prints ``Warning: in <C++ function> at line N of <file> -- <message>``
straight to stderr. While :func:`usd_diagnostics` is active, a ``UsdUtils.CoalescingDiagnosticDelegate``
collects them instead (Tf prints nothing while a delegate is registered) and they are re-issued through
usdml's ``warn``, without the C++ location. Tf *errors* are untouched: that delegate ignores them, and
the Python bindings turn an error raised by a call into ``Tf.ErrorException`` as before.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from pxr import UsdUtils


def usd_message(commentary: str, where: str) -> str:
    """One warning line: ``/Prim/Path: message`` for USD's ``/Prim/Path -- message``, else ``where: message``."""
    text = " ".join(commentary.split())
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
            warn(usd_message(item.commentary, where))
