"""Every file a command writes goes through here: checked before the work, written atomically.

:func:`check_output` runs before a command spends time on a frame: the path is not a folder, its
folder exists or can be made (not under a regular file), a file can be created there, and its
extension is one the writer takes; otherwise a one-line :class:`UsdmlError` names the path and what
to do. :func:`atomic_write` writes under a hidden temporary name in the destination folder, flushes,
then renames onto the final name (``os.replace``), so a reader sees the previous file or the whole new
one. :func:`write_image` writes 8-bit pixels in the format the extension names (PNG, JPEG, TIFF, EXR
...) through OpenImageIO.

A leaf module: it imports nothing of usdml but :mod:`usdml.errors`.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from usdml.errors import UsdmlError

__all__ = ["IMAGE_EXTENSIONS", "atomic_write", "check_output", "make_output_folder", "write_image"]

#: extensions :func:`write_image` writes (OpenImageIO's writers shipped with the wheels)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")


def _temp_name(path: Path, suffix: str) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{suffix}")


def make_output_folder(folder: str | os.PathLike) -> Path:
    """Create ``folder`` and its parents for output files, or raise a one-line :class:`UsdmlError`
    naming what is in the way (a file where a folder must go, a read-only file system ...)."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
        why = f"{blocker} is a file, not a folder" if blocker is not None else (e.strerror or str(e))
        raise UsdmlError(f"{folder}: cannot create the output folder ({why}); choose another output path") from None
    return folder


def _cannot_create_in(folder: Path) -> str | None:
    """Why no file can be created in ``folder`` (a probe: permissions, read-only or full file system), else None."""
    probe = _temp_name(folder / "probe", "")
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL))
    except OSError as e:
        return e.strerror or str(e)
    with contextlib.suppress(OSError):
        probe.unlink()
    return None


def check_output(path: str | os.PathLike, flag: str, extensions: Iterable[str] | None = None) -> Path:
    """``path`` as a :class:`~pathlib.Path` once a file can be written there (its folder made);
    else a one-line :class:`UsdmlError` that starts with ``flag`` (how the user gave the path:
    ``--heatmap``, ``--png``) and says what to do. ``extensions`` (lower case, with the dot): the
    ones the writer takes."""
    path = Path(path)
    if path.is_dir():
        raise UsdmlError(f"{flag} {path}: is a folder; give a file name inside it")
    if extensions is not None:
        extensions = tuple(extensions)
        if path.suffix.lower() not in extensions:
            raise UsdmlError(f"{flag} {path}: {path.suffix or 'no extension'} is not an image format usdml "
                             f"writes; end the name in {', '.join(extensions)}")
    make_output_folder(path.parent)
    why = _cannot_create_in(path.parent)
    if why:
        raise UsdmlError(f"{flag} {path}: cannot write in {path.parent} ({why}); choose a writable output folder")
    return path


def atomic_write(path: str | os.PathLike, suffix: str, write: Callable[[Path], None]) -> Path:
    """``write(tmp)``, fsync, ``os.replace(tmp, path)``; the temp file never outlives a failure.

    ``suffix`` ends the temporary name (writers pick the format by it: ``.png``). A failure the disk
    explains (the folder takes no new file, or the OS refused a write) is a one-line
    :class:`UsdmlError` naming ``path``; any other failure of ``write`` propagates."""
    path = Path(path)
    make_output_folder(path.parent)
    tmp = _temp_name(path, suffix)
    try:
        write(tmp)
        if not tmp.is_file():
            raise OSError(f"{path}: the writer produced no file")
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(e, (OSError, RuntimeError)):      # OpenEXR reports I/O failures as RuntimeError
            why = _cannot_create_in(path.parent) or (e.strerror if isinstance(e, OSError) else None)
            if why:
                raise UsdmlError(f"{path}: cannot write the file ({why}); choose a writable output folder "
                                 "with free space") from None
        raise
    return path


def write_image(path: str | os.PathLike, pixels: np.ndarray, suffix: str | None = None) -> Path:
    """``pixels`` (``(H, W, C)`` uint8 sRGB, straight alpha, row 0 the top) to ``path`` atomically, in
    the format ``suffix`` names (default: the path's extension, :data:`IMAGE_EXTENSIONS`). Returns the path."""
    import OpenImageIO as oiio

    path = Path(path)
    pixels = np.ascontiguousarray(pixels, np.uint8)
    h, w, c = pixels.shape

    def write(tmp: Path) -> None:
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        spec.attribute("oiio:ColorSpace", "sRGB")
        if c == 4:
            spec.attribute("oiio:UnassociatedAlpha", 1)     # callers pass straight alpha
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"{path}: OpenImageIO cannot write {path.suffix} files ({oiio.geterror()})")
        try:
            if not out.open(str(tmp), spec) or not out.write_image(pixels):
                raise OSError(f"{path}: image write failed ({out.geterror()})")
        finally:
            out.close()

    return atomic_write(path, suffix or path.suffix.lower(), write)
