"""User-facing errors and warnings.

A :class:`UsdmlError` is a mistake in the user's input (stage, flags): the CLI prints its one-line
message and exits non-zero without a traceback. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from contextlib import contextmanager

log = logging.getLogger("usdml")


class UsdmlError(Exception):
    """Bad input: the message names the file / prim / attribute and says what to do."""


#: a log record's attribute with the messages its line stands for (:class:`Warnings`)
EACH = "usdml_messages"
#: what stands for a prim path in a warning's cause (:func:`cause`)
PRIM = "<prim>"
#: an asset path (``@missing.usda@``), kept as it is in a cause; or a prim path: USD's ``</World/P9>``,
#: usdml's ``/World/P9``, ``/World/Tex.inputs:file`` (not a file's path, ``/tmp/a.usda``: its last name has an
#: extension, not a namespaced property)
_ASSET_OR_PRIM = re.compile(r"(@[^@]*@)|(?<![\w./])/[^\W\d]\w*(?:/[^\W\d]\w*)*(?![\w/]|\.\w+(?!:?\w))")


def cause(message: str) -> str:
    """What a warning says once its prim paths are taken out: warnings with the same cause are one problem
    met on several prims (a missing layer referenced by a thousand prims), printed once (:class:`Warnings`)."""
    return _ASSET_OR_PRIM.sub(lambda m: m.group(1) or PRIM, message)


class Warnings:
    """A command's warnings about its stage: every distinct message once, in :attr:`messages`, and on the
    ``usdml`` logger once per cause (:func:`cause`).

    Inside :meth:`grouped` (opening a stage, reading a frame) the messages wait until the block ends; then each
    cause is logged once, as its first message with a count of the others (``... (… and 999 more prims)``). A
    cause already logged is not logged again: later messages with it reach only :func:`collect_warnings`' lists,
    so a render's ``warnings`` (``--json``) hold every message.
    """

    def __init__(self) -> None:
        self.messages: list[str] = []
        self._seen: set[str] = set()
        self._logged: set[str] = set()          # causes
        self._waiting: list[str] = []
        self._depth = 0

    def __call__(self, message: str) -> None:
        if message in self._seen:
            return
        self._seen.add(message)
        self.messages.append(message)
        if self._depth:
            self._waiting.append(message)
        else:
            self._log(cause(message), [message])

    @contextmanager
    def grouped(self) -> Iterator[None]:
        """Hold the messages given inside the block (nested blocks: the outermost) and log them by cause at its end."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
            if not self._depth:
                waiting, self._waiting = self._waiting, []
                by_cause: dict[str, list[str]] = {}
                for message in waiting:
                    by_cause.setdefault(cause(message), []).append(message)
                for key, messages in by_cause.items():
                    self._log(key, messages)

    def _log(self, key: str, messages: list[str]) -> None:
        if key in self._logged:
            collect_quietly(messages)
            return
        self._logged.add(key)
        more = len(messages) - 1
        line = messages[0] + (f" (… and {more} more prim{'s' * (more > 1)})" if more else "")
        log.warning(line, extra={EACH: messages})


class _Collect(logging.Handler):
    """The ``usdml`` logger's warnings (and errors), as their messages (each message a grouped line stands for)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.extend(getattr(record, EACH, None) or [record.getMessage()])


_collectors: list[_Collect] = []       # collect_warnings' handlers, while their blocks run


def collect_quietly(messages: list[str]) -> None:
    """Add ``messages`` to the lists of :func:`collect_warnings` without logging them (a cause said already)."""
    if log.isEnabledFor(logging.WARNING):
        for collect in _collectors:
            collect.messages.extend(messages)


@contextmanager
def collect_warnings() -> Iterator[list[str]]:
    """The messages the ``usdml`` logger warns with while the block runs (a render's ``warnings``): every message,
    also those of a grouped line (:class:`Warnings`) and those not logged again."""
    collect = _Collect()
    log.addHandler(collect)
    _collectors.append(collect)
    try:
        yield collect.messages
    finally:
        _collectors.remove(collect)
        log.removeHandler(collect)


def tf_message(e: Exception) -> str:
    """The first diagnostic of a ``pxr.Tf.ErrorException``, without the C++ function and file names."""
    for block in re.split(r"\n\s*Error in ", "\n" + str(e)):
        _, sep, message = block.partition(" : '")
        if sep:
            return " ".join(message.strip().rstrip("'").split())
    return " ".join(str(e).split())
