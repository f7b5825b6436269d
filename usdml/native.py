"""The one loader of usdml's compiled CPU kernels (``kernels/*.c``), through ctypes.

``pip install`` builds each C file as an optional extension ``usdml.kernels.<name>`` (setup.py); without a
C compiler it is skipped and the backends run their Warp kernels instead. A wrapper module
(:mod:`usdml.visibility.voxel.native`, :mod:`usdml.visibility.svo.native`,
:mod:`usdml.visibility.insm.native`, :mod:`usdml.lighting.lgh.native`) declares its extension's C
functions as an :class:`Extension` and wraps them; opening the library, declaring the signatures once and
saying why a library is missing happen here, as do the instruction-set names the kernels share (each C
file picks AVX-512, AVX2 or scalar code at run time, so one build serves every x86-64 CPU).
"""

from __future__ import annotations

import ctypes
from pathlib import Path
import importlib
import threading
from typing import Callable, Mapping, Sequence

__all__ = ["Extension", "ISAS", "WIDTH_NAMES", "kernel_label", "open_extension", "path_line"]

#: the compiled kernels' instruction sets, widest first, by the number their ``pick`` takes (voxelq.c's,
#: svoq.c's): ``auto`` the widest this CPU has, ``avx2`` at most AVX2, ``scalar`` plain C
ISAS = {"auto": 0, "avx2": 2, "scalar": 1}
#: instruction sets by the lanes of one register
WIDTH_NAMES = {16: "AVX-512", 8: "AVX2", 1: "scalar"}


def open_extension(name: str) -> tuple[ctypes.CDLL | None, str]:
    """The compiled extension ``usdml.kernels.<name>`` as a ctypes library, or None and why not."""
    try:
        mod = importlib.import_module(f"usdml.kernels.{name}")
    except ImportError as e:
        return None, f"not built ({e}{_stale(name)})"
    return ctypes.CDLL(mod.__file__), ""


def _stale(name: str) -> str:
    """``; ...`` where an install made before the kernels had a folder per method left the library beside the
    folders (``kernels/_voxelq*.so`` for ``voxel._voxelq``): built, but where nothing looks for it."""
    leaf = name.rpartition(".")[2]
    folders = importlib.import_module("usdml.kernels").__path__       # imported already by the failed import
    old = [f for folder in folders for f in Path(folder).glob(f"{leaf}.*") if f.suffix in (".so", ".pyd")]
    return f"; {old[0].name} was built for the layout before kernels/{name.partition('.')[0]}/" if old and "." in name else ""


class Extension:
    """One compiled extension and the C functions a wrapper module calls in it.

    Parameters
    ----------
    name : the extension's module name under ``usdml.kernels`` (``"voxel._voxelq"``: the folder of its method, then its name).
    functions : ``{C name: (restype, [argtypes])}``, set on the library when it is first opened.
    on_load : called once with the opened library (a setting the library keeps, say).
    """

    def __init__(self, name: str, functions: Mapping[str, tuple[object, Sequence[object]]],
                 on_load: Callable[[ctypes.CDLL], None] | None = None):
        self.name = name
        self.functions = dict(functions)
        self.on_load = on_load
        self._opened: tuple[ctypes.CDLL | None, str] | None = None
        self._lock = threading.Lock()

    def load(self) -> tuple[ctypes.CDLL | None, str]:
        """``(library, "")`` with every declared function's signature set, or ``(None, why not)``; opened
        once per process."""
        with self._lock:
            if self._opened is None:
                lib, why = open_extension(self.name)
                if lib is not None:
                    for fn, (restype, argtypes) in self.functions.items():
                        c = getattr(lib, fn)
                        c.argtypes, c.restype = list(argtypes), restype
                    if self.on_load is not None:
                        self.on_load(lib)
                self._opened = lib, why
            return self._opened

    def library(self) -> ctypes.CDLL | None:
        """The library, or None where it was not built (no C compiler at install)."""
        return self.load()[0]


def kernel_label(width: int) -> str:
    """A compiled kernel's name in ``usdml bench`` / ``compare`` results by the lanes of one register
    of its instruction set: ``native-avx512``, ``native-avx2`` or ``native-scalar``."""
    return "native-" + WIDTH_NAMES[width].replace("-", "").lower()


def path_line(what: str, why: str, width: int, unit: str, register: int | None = None) -> str:
    """``usdml info``'s line for a compiled CPU path ``what`` (``why``: why it is missing, "" when
    built) running ``width`` ``unit`` at a time, on an instruction set of ``register`` lanes a register
    (default ``width``)."""
    if why:
        return f"Warp kernels (the {what} is {why}; reinstall with a C compiler for the fast path)"
    if width == 1:
        return f"{what}, scalar (no AVX2 on this CPU)"
    return f"{what}, {WIDTH_NAMES[register or width]} ({width} {unit} at a time)"
