"""Warp kernels (installed as usdml.kernels): pure compute over arrays, runnable on cpu and cuda.

Warp prints a start-up banner and module-load lines to stdout, which ``usdml ... --json`` keeps
for JSON alone: :func:`warp` initializes Warp with only warnings and errors reported.
"""

import warp as _wp

# Warp >= 1.x reports through log levels; older releases had ``config.quiet``
if hasattr(_wp, "LOG_WARNING"):
    _wp.config.log_level = _wp.LOG_WARNING
_wp.config.quiet = True


def warp():
    """The initialized ``warp`` module, quiet."""
    _wp.init()
    return _wp
