"""User-facing errors and warnings.

A :class:`UsdmlError` is a mistake in the user's input (stage, flags): the CLI prints its one-line
message and exits non-zero without a traceback. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import logging

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
