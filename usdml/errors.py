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


class Warnings:
    """Collects warnings once per distinct message and forwards them to the ``usdml`` logger."""

    def __init__(self) -> None:
        self.messages: list[str] = []
        self._seen: set[str] = set()

    def __call__(self, message: str) -> None:
        if message in self._seen:
            return
        self._seen.add(message)
        self.messages.append(message)
        log.warning(message)


class _Collect(logging.Handler):
    """The ``usdml`` logger's warnings (and errors), as their messages."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextmanager
def collect_warnings() -> Iterator[list[str]]:
    """The messages the ``usdml`` logger warns with while the block runs (a render's ``warnings``)."""
    collect = _Collect()
    log.addHandler(collect)
    try:
        yield collect.messages
    finally:
        log.removeHandler(collect)


def tf_message(e: Exception) -> str:
    """The first diagnostic of a ``pxr.Tf.ErrorException``, without the C++ function and file names."""
    for block in re.split(r"\n\s*Error in ", "\n" + str(e)):
        _, sep, message = block.partition(" : '")
        if sep:
            return " ".join(message.strip().rstrip("'").split())
    return " ".join(str(e).split())
