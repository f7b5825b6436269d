"""Frames and file names per frame, as usdrecord does them.

**FrameSpec** (usdrecord's ``--frames``, ``UsdAppUtils.framesArgs``): a comma-separated list of
specs, each parsed by ``UsdUtils.TimeCodeRange.CreateFromFrameSpec``: ``123`` (one frame),
``101:148`` (start:end, both included, stride 1, or -1 when end < start), ``101:109x2`` (stride),
``101:104x0.5``. Frames are returned in the order given, repeats kept. usdml also strips
whitespace around each comma-separated part. Without ``--frames`` usdrecord renders only the
stage's start timecode.

**Frame placeholder** (``GetFramePlaceholder`` / ``ConvertFramePlaceholderToFloatSpec``): the
output path holds exactly one placeholder, one run of ``#`` optionally followed by ``.`` and a
second run of ``#``, and no other ``#`` anywhere in the path. The frame is formatted with Python's
``{:0W.Pf}``, W the placeholder's whole length (dot included) and P the number of ``#`` after the
dot (0 when there is no dot): zero-padded on the left to at least W characters, rounded to P
decimals. So ``out.####.exr`` with 12 -> ``out.0012.exr``, ``out.####.##.exr`` with 12.5 ->
``out.0012.50.exr``, ``out.#.exr`` with 1234 -> ``out.1234.exr`` (never truncated), ``out.####.exr``
with -3 -> ``out.-003.exr`` (the sign takes one of the W places).

**Validation** (usdrecord's ``ValidateCmdlineArgs``): with ``--frames`` the path must contain a
placeholder -- even for a single frame -- and its precision must be at least the largest number of
decimals in any stride of the FrameSpec (``1:2x0.25`` needs ``#.##``); without ``--frames`` the
path must *not* contain one. usdml adds one check usdrecord lacks: two frames that format to the
same file name (``--frames 1,1.25`` with ``#``) are an error, not a silent overwrite.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from numbers import Number

from usdml.errors import UsdmlError, tf_message

__all__ = [
    "FrameSpecError", "OutputPathError", "frame_spec", "frame_spec_precision", "timecodes",
    "frame_placeholder", "placeholder_precision", "format_frame", "output_paths", "MAX_FRAMES",
]

#: a FrameSpec producing more frames than this is refused (a typo such as ``1:1e9``)
MAX_FRAMES = 1_000_000

_PLACEHOLDER = re.compile(r"^[^#]*(?P<placeholder>#+(?:\.#+)?)[^#]*$")


class FrameSpecError(UsdmlError, ValueError):
    """A malformed ``--frames`` FrameSpec."""


class OutputPathError(UsdmlError, ValueError):
    """An output path whose frame placeholder does not fit the frames asked for."""


# --- FrameSpec ----------------------------------------------------------------------------------

def _parts(spec: str) -> list[str]:
    parts = [p.strip() for p in spec.split(",")]
    if any(not p for p in parts):
        raise FrameSpecError(f"--frames {spec!r}: empty FrameSpec in the comma-separated list")
    return parts


def frame_spec(spec: str | Sequence[float] | None, stage_start: float | None = None,
               stage_end: float | None = None, *, max_frames: int = MAX_FRAMES) -> list[float]:
    """The timecodes of a FrameSpec (``"101:148"``, ``"1:10x2"``, ``"1,5,10:12"``), in order; timecodes
    already (a list of numbers, the Python API's and a farm chunk's) are taken as they are, as floats.

    ``spec`` None or blank: ``[stage_start]``, usdrecord's default (FrameSpecError if
    ``stage_start`` is None too). ``stage_end`` is accepted so callers can pass the stage range;
    frames outside ``[stage_start, stage_end]`` are valid (USD holds the end samples), so it
    changes nothing. Raises :class:`FrameSpecError` naming the bad part.
    """
    del stage_end
    if spec is not None and not isinstance(spec, str):
        return timecodes(spec, max_frames=max_frames)
    if spec is None or not str(spec).strip():
        if stage_start is None:
            raise FrameSpecError("no --frames given and the stage has no start timecode; give --frames (e.g. "
                                 "--frames 1) or author the stage's startTimeCode")
        return [float(stage_start)]
    from pxr import Tf, UsdUtils

    frames: list[float] = []
    for part in _parts(str(spec)):
        try:
            r = UsdUtils.TimeCodeRange.CreateFromFrameSpec(part)
        except Tf.ErrorException as e:
            raise FrameSpecError(
                f"--frames: bad FrameSpec {part!r}: {tf_message(e)} (expected N, START:END or "
                f"START:ENDxSTRIDE, e.g. 101, 101:148, 1:10x2, 1:2x0.5; comma-separated lists)"
            ) from None
        if not r.IsValid():
            raise FrameSpecError(f"--frames: bad FrameSpec {part!r}")
        start, end, stride = (r.startTimeCode.GetValue(), r.endTimeCode.GetValue(), r.stride)
        count = math.floor((end - start) / stride + 1e-9) + 1
        if len(frames) + count > max_frames:
            raise FrameSpecError(f"--frames {spec!r} asks for more than {max_frames} frames")
        frames.extend(t.GetValue() for t in r)
    return frames


def timecodes(frames: Sequence[float], *, max_frames: int = MAX_FRAMES) -> list[float]:
    """``frames`` (numbers, not booleans, finite) as a list of floats; :class:`FrameSpecError` for
    anything else, an empty list or more than ``max_frames``."""
    items = list(frames)
    if not items or not all(isinstance(f, Number) and not isinstance(f, bool) and math.isfinite(f) for f in items):
        raise FrameSpecError(f"frames {frames!r}: give a FrameSpec ('101:148'), a timecode or a list of timecodes")
    if len(items) > max_frames:
        raise FrameSpecError(f"frames: {len(items)} timecodes, more than {max_frames}")
    return [float(f) for f in items]


def frame_spec_precision(spec: str | Sequence[float] | None) -> int:
    """Decimals the frame placeholder needs: the most digits after the dot in any stride (0 for
    timecodes given as numbers, as for a comma-separated list)."""
    if not isinstance(spec, str) or not spec.strip():
        return 0
    precision = 0
    for part in _parts(str(spec)):
        if "x" in part:
            stride = part.split("x", 1)[1].strip()
            if "." in stride:
                precision = max(precision, len(stride.split(".", 1)[1]))
    return precision


# --- placeholders -------------------------------------------------------------------------------

def frame_placeholder(pattern: str | None) -> str | None:
    """The ``###`` / ``###.##`` placeholder of ``pattern``, or None (none, or ``#`` used elsewhere)."""
    if not pattern:
        return None
    m = _PLACEHOLDER.match(str(pattern))
    return m.group("placeholder") if m else None


def placeholder_precision(placeholder: str) -> int:
    return len(placeholder.split(".", 1)[1]) if "." in placeholder else 0


def format_frame(pattern: str, frame: float) -> str:
    """``pattern`` with its placeholder replaced by ``frame`` (usdrecord's ``{:0W.Pf}``)."""
    placeholder = frame_placeholder(pattern)
    if placeholder is None:
        raise OutputPathError(_need_placeholder(pattern))
    frame = float(frame)
    if not math.isfinite(frame):
        raise OutputPathError(f"cannot name a file for frame {frame}")
    width, precision = len(placeholder), placeholder_precision(placeholder)
    text = format(frame, f"0{width}.{precision}f")
    if text.startswith("-") and float(text) == 0:       # -0.4 at precision 0: "-000" -> "0000"
        text = format(0.0, f"0{width}.{precision}f")
    return str(pattern).replace(placeholder, text, 1)


def _need_placeholder(pattern: str) -> str:
    hashes = str(pattern).count("#")
    why = ("has no frame placeholder" if hashes == 0 else
           "has '#' outside one placeholder (exactly one run of '#', or '#.#', is allowed)")
    return (f"output path {pattern!r} {why}; a frame range needs exactly one frame number "
            f"placeholder of the form '####' or '####.##', e.g. beauty.####.exr")


def output_paths(pattern: str, frames: Sequence[float], *, frames_given: bool = True,
                 min_precision: int = 0) -> list[str]:
    """One output path per frame, validated as usdrecord does (see the module doc).

    ``frames_given``: the user passed ``--frames`` (then a placeholder is required, even for one
    frame); False means the single default frame (then a placeholder is an error).
    ``min_precision``: :func:`frame_spec_precision` of the FrameSpec.
    Raises :class:`OutputPathError`.
    """
    placeholder = frame_placeholder(pattern)
    if not frames_given:
        if placeholder is not None or "#" in str(pattern):
            raise OutputPathError(f"output path {pattern!r} cannot contain a frame number placeholder "
                                  f"when not rendering a frame range (give --frames)")
        if len(frames) != 1:
            raise OutputPathError(f"output path {pattern!r}: {len(frames)} frames need --frames and "
                                  f"a frame number placeholder")
        return [str(pattern)]
    if placeholder is None:
        raise OutputPathError(_need_placeholder(pattern))
    precision = placeholder_precision(placeholder)
    if precision < min_precision:
        raise OutputPathError(
            f"the FrameSpec needs {min_precision} decimal(s) in frame numbers but the placeholder "
            f"{placeholder!r} of {pattern!r} has {precision}; use e.g. "
            f"{'#' * max(len(placeholder.split('.')[0]), 1)}.{'#' * min_precision}")
    paths: list[str] = []
    seen: dict[str, float] = {}
    for f in frames:
        p = format_frame(pattern, f)
        if p in seen and seen[p] != float(f):
            raise OutputPathError(
                f"frames {seen[p]:g} and {float(f):g} both write {p!r}: the placeholder "
                f"{placeholder!r} needs more decimals (e.g. {placeholder.split('.')[0]}.##)")
        seen[p] = float(f)
        paths.append(p)
    return paths
