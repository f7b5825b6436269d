"""usdml: render OpenUSD stages with thousands of lights.

Importing usdml registers its codeless USD schemas (``schemas/``) with USD's plugin system, so the
stage's ``UsdmlRenderSettingsAPI`` attributes get their fallbacks. Register before anything else
builds ``Usd.SchemaRegistry``: once built, USD does not look at plugins registered later.
"""

__version__ = "0.1.0"

from usdml.errors import UsdmlError  # noqa: E402

try:
    from usdml import schemas as _schemas

    _schemas.register()
except ImportError:  # the schema package is optional for plain-NumPy users of usdml.scene
    pass

__all__ = ["UsdmlError", "__version__"]
