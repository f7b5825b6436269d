"""Warp kernels (installed as usdml.kernels): pure compute over arrays, runnable on cpu and cuda.

Warp prints a start-up banner and module-load lines to stdout, which ``usdml ... --json`` keeps
for JSON alone: :func:`warp` initializes Warp with only warnings and errors reported. On a machine
without an NVIDIA driver Warp's native start-up also writes "Could not find or load the NVIDIA CUDA
driver" to the process's standard error: that line is dropped (a CPU machine is usdml's usual
one; ``--device cuda`` there is refused with usdml's own message); any other line Warp's start-up writes
becomes a warning of the ``usdml`` logger (``usdml: warning: Warp: ...``), so that no line on usdml's
standard error is in another form. The first call initializes, once, whichever thread makes it.
"""

import ctypes as _ctypes
import logging as _logging
import os as _os
import sys as _sys
import tempfile as _tempfile
import threading as _threading

import warp as _wp

# Warp >= 1.x reports through log levels; older releases had ``config.quiet``
if hasattr(_wp, "LOG_WARNING"):
    _wp.config.log_level = _wp.LOG_WARNING
_wp.config.quiet = True


#: the native start-up line dropped on machines without a CUDA driver
NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def _flush_c_streams() -> None:
    """``fflush(NULL)``: what native code left in a C stdio buffer is written now, not after descriptor 2 is
    given back."""
    try:
        _ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):    # no C library to ask (not a POSIX process): nothing buffered to lose
        pass


def _init_quietly() -> None:
    """``warp.init()`` with file descriptor 2 captured: its native code writes with ``fprintf``, which
    no Python-level redirection sees. Captured lines but :data:`NO_DRIVER`'s are warnings of the ``usdml``
    logger."""
    try:
        _sys.stderr.flush()
        saved = _os.dup(2)
    except (OSError, ValueError):       # no usable descriptor 2 (an embedding host): as Warp does
        _wp.init()
        return
    with _tempfile.TemporaryFile() as sink:
        _os.dup2(sink.fileno(), 2)
        try:
            _wp.init()
        finally:
            _flush_c_streams()
            _os.dup2(saved, 2)
            _os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace")
    for line in text.splitlines():
        if line.strip() and NO_DRIVER not in line:
            _logging.getLogger("usdml").warning(f"Warp: {line.strip()}")


def warp():
    """The initialized ``warp`` module, quiet. Threads that ask at once wait for one initialization: two
    capturing descriptor 2 together would give it back in the wrong order (Warp's lines on the terminal, or
    the terminal lost)."""
    global _ready
    if not _ready:
        with _init_lock:
            if not _ready:
                _init_quietly()
                _ready = True
    return _wp


_ready = False
_init_lock = _threading.Lock()
