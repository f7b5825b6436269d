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

__all__ = ["Recorder", "RecordResult", "UsdmlError", "__version__"]


def __getattr__(name: str):
    # the pipeline API, imported on first use (it brings the renderer: Embree, Warp)
    if name in ("Recorder", "RecordResult"):
        from usdml import recorder
        return getattr(recorder, name)
    raise AttributeError(f"module 'usdml' has no attribute {name!r}")
