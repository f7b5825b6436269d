"""AOV buffers, names and types, OpenEXR writing with metadata, file naming per frame.

* :mod:`usdml.aov.names` -- the AOV registry (channels, pixel types, clear values) and the
  ``UsdRenderVar`` -> AOV mapping.
* :mod:`usdml.aov.exr` -- atomic multi-channel EXR writing / reading, completeness checks for
  ``--resume``, sRGB PNG previews, OpenEXR camera-matrix conventions.
* :mod:`usdml.aov.naming` -- usdrecord's FrameSpec and ``#`` frame-number rule.
* :mod:`usdml.aov.cryptomatte` -- Cryptomatte ids (MurmurHash3), the ranking pixel filter, the header's manifests.
"""

from usdml.aov.exr import (
    ExrError, camera_matrices, is_complete_exr, read_exr, usdml_world_to_camera,
    usdml_world_to_ndc, write_exr, write_png_preview,
)
from usdml.aov.names import ALIASES, AOVS, NO_ID, AovSpec, aov_for_render_var, data_type_matches, find_aov, get_aov
from usdml.aov.naming import (
    FrameSpecError, OutputPathError, format_frame, frame_placeholder, frame_spec,
    frame_spec_precision, output_paths,
)

__all__ = [
    "ALIASES", "AOVS", "NO_ID", "AovSpec", "ExrError", "FrameSpecError", "OutputPathError",
    "aov_for_render_var", "camera_matrices", "data_type_matches", "find_aov", "format_frame",
    "frame_placeholder", "frame_spec", "frame_spec_precision", "get_aov", "is_complete_exr",
    "output_paths", "read_exr", "usdml_world_to_camera", "usdml_world_to_ndc", "write_exr",
    "write_png_preview",
]
