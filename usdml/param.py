"""One row of usdml's parameter table (:mod:`usdml.params`): :class:`Param`, its :class:`Range`, the commands
that take a flag and the help's groups.

The table is assembled in :mod:`usdml.params` from its frame-wide rows and the rows each method declares in its
own folder (``usdml/visibility/voxel/params.py``, ``usdml/lighting/lgh/params.py`` ...); this module is what both
import, so a method's rows load without the table and the table without the method. A leaf module: nothing of
usdml, no ``pxr``.
"""

from __future__ import annotations

import inspect
import math
import numbers
from dataclasses import dataclass
from typing import Callable

#: commands whose flags come from this table (``info`` takes only the stage's options, no setting); a row
#: lists the ones that take its flag
RENDER, COMPARE, BENCH, BAKE, INFO = "render", "compare", "bench", "bake", "info"
COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
VOXEL_COMMANDS = (RENDER, COMPARE, BENCH, BAKE)
LIGHTING_COMMANDS = (RENDER, COMPARE)
#: the commands that read a stage (``--camera`` ...)
STAGE_COMMANDS = (RENDER, COMPARE, BENCH, BAKE, INFO)

#: the help's groups of flags (``Param.group``; None: the command's own options)
VISIBILITY = "visibility (usdml:visibility, usdml:voxel:*, usdml:svo:*, usdml:insm:*)"
LIGHTING = "lighting and sampling (usdml:gi, usdml:vpl:*, usdml:lgh:*, usdml:shadow:* ...)"
FARM = 'frames on Dask (docs/rendering.md, "Render farms")'

# a section's commands and help group
VIS = {"commands": VOXEL_COMMANDS, "group": VISIBILITY}
LIT = {"commands": LIGHTING_COMMANDS, "group": LIGHTING}


@dataclass(frozen=True)
class Range:
    """Closed interval ``[low, high]``, either end open-ended (None); ``low_open`` excludes ``low``.
    Float values must also be finite."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False

    def __contains__(self, value) -> bool:
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or value <= self.high

    def rule(self, kind: type) -> str:
        """What the range accepts, as an error message says it ("in [4, 2048]", "finite and > 0")."""
        if self.low is not None and self.high is not None:
            return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"
        bound = f"{'>' if self.low_open else '>='} {self.low:g}" if self.low is not None else f"<= {self.high:g}"
        return f"finite and {bound}" if kind is float else bound


def _camel(words: str) -> str:
    first, *rest = words.split("_")
    return first + "".join(w[:1].upper() + w[1:] for w in rest)


@dataclass(frozen=True)
class Param:
    """One setting (or, with ``attribute=None``, one render option): its field, value type and default,
    its one-line ``help``, the commands that take its flag and the help's ``group``; where it is set
    (``flag``, ``attribute``: derived from the field, module doc, unless given) and what it accepts.

    ``doc`` is the schema attribute's documentation, whose first sentence USD keeps (``userDocBrief``;
    default: ``help``). ``choices``, ``range`` and ``valid`` (a
    predicate, described by ``rule``) are what :func:`check` accepts; ``label`` is how its messages name
    the value (default: the field name in words). ``source`` says where the default comes from.
    A setting's flag help gets the default appended (:func:`default_help`); a render option's help says
    it itself (``%(default)s``), and its check is ``valid`` with the message ``give <rule>``.
    """

    field: str
    type: type
    default: object
    help: str
    commands: tuple[str, ...] = ()
    group: str | None = None
    flag: str = ""
    #: "" derives it from the field; None: a render option, no schema attribute
    attribute: str | None = ""
    source: str = ""
    choices: tuple = ()
    range: Range | None = None
    valid: Callable[[object], bool] | None = None
    rule: str = ""
    label: str = ""
    metavar: str | None = None
    doc: str = ""
    #: give argparse the choices (it refuses others itself); False leaves the refusal to check()
    parser_choices: bool = True
    #: when the setting is read: any of ``(field, values)`` holds (None: always); :func:`ignored` warns of a
    #: flag given where it is not read
    applies: tuple[tuple[str, tuple], ...] | None = None
    #: argparse action of a render option's flag (default: by its type)
    action: str | None = None

    def __post_init__(self) -> None:
        if not self.flag:
            object.__setattr__(self, "flag", "--" + self.field.replace("_", "-"))
        if self.attribute == "":
            head, _, rest = self.field.partition("_")
            object.__setattr__(self, "attribute", f"usdml:{head}" + (f":{_camel(rest)}" if rest else ""))

    @property
    def is_option(self) -> bool:
        """A render option (no schema attribute, not a settings field)."""
        return self.attribute is None

    @property
    def name(self) -> str:
        """How messages name the value."""
        return self.label or self.field.replace("_", " ")

    @property
    def where(self) -> str:
        """Where a user sets it: ``--voxel-resolution, usdml:voxel:resolution``."""
        return f"{self.flag}, {self.attribute}"

    @property
    def schema_doc(self) -> str:
        """The schema attribute's documentation, dedented (first sentence: the brief)."""
        if self.doc:
            return inspect.cleandoc(self.doc)
        text = self.help[0].upper() + self.help[1:]
        return text if text.endswith(".") else text + "."

    def accepts(self, value) -> bool:
        """A render option's check: ``valid``, else the type, choices and range."""
        if self.valid is not None:
            return self.valid(value)
        ok = isinstance(value, bool) if self.type is bool else _is_a(self.type, value)
        return ok and (not self.choices or value in self.choices) and (self.range is None or value in self.range)

    def problem(self, value) -> str | None:
        """Why ``value`` is refused (one clause naming the setting and what to use), or None."""
        if not _is_a(self.type, value):
            return f"{self.name} must be {_TYPE_WORDS[self.type]}, got {value!r}"
        if self.choices and value not in self.choices:
            listed = ", ".join(map(str, self.choices))
            if self.type is str:
                return f"unknown {self.name} {value!r}; use one of {listed}"
            return f"{self.name} must be one of {listed}, got {value!r}"
        if self.range is not None and value not in self.range:
            return f"{self.name} must be {self.range.rule(self.type)}, got {value!r}"
        if self.valid is not None and not self.valid(value):
            return f"{self.name} must be {self.rule}, got {value!r}"
        return None


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a name"}


def _is_a(kind: type, value) -> bool:
    if kind is bool:
        return isinstance(value, (bool, int)) and value in (0, 1)
    if isinstance(value, bool):
        return False
    if kind is int:
        return isinstance(value, numbers.Integral)
    if kind is float:
        return isinstance(value, numbers.Real)
    return isinstance(value, kind)
