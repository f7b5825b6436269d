"""Content-addressed on-disk store for expensive per-prototype data (paper 000's voxel arrays, octrees).

An entry is one file ``<root>/<kind>/<key[:2]>/<key>.bin``:

* 8 bytes magic ``USDMLC02``, 8 bytes little-endian length ``H`` of the JSON header, ``H`` bytes of
  JSON (the caller's metadata plus ``dtype``, ``shape``, ``nbytes``, ``chunks`` and ``digest``), then
  the array compressed by zlib in chunks of ``ZCHUNK`` bytes (``chunks``: their compressed sizes), so
  that chunks are compressed and expanded on every core. ``digest`` is a blake2b of the stored
  (compressed) bytes, checked before anything is expanded. Callers whose data zlib alone would not
  shrink enough store a compact form of it (a voxel array: :mod:`usdml.visibility.voxel.codec`).
* The key is a hash the caller makes of everything the data depends on (geometry hash, parameters,
  format version), so a changed mesh or setting never reads a stale entry.
* Writes go to a temporary file in the same folder, then ``os.replace``: readers on any process or
  machine sharing the folder see a whole entry or none.
* Loads check the magic, header, sizes and digest; a damaged entry is reported (``CacheCorrupt``),
  removed, and the caller rebuilds it. An entry of the old uncompressed format (``USDMLC01``) is
  removed when read and built again.
* The folder holds at most :func:`size_limit` bytes (``$USDML_CACHE_SIZE``, default 4 GiB): after
  each write the least recently used entries (file mtime, touched on every load) are removed until
  the rest fit, never the entry just written.

The root is ``$USDML_CACHE_DIR``, else ``$XDG_CACHE_HOME/usdml``, else ``~/.cache/usdml``.
``usdml cache list`` and ``usdml cache clean`` show and empty it (:meth:`Cache.entries`,
:meth:`Cache.clean`).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate
import hashlib
import json
import logging
import os
from pathlib import Path
import re
import struct
import tempfile
import time
import zlib

import numpy as np

from usdml.errors import UsdmlError
from usdml.parallel import cpu_workers, run_parallel

__all__ = ["Cache", "CacheCorrupt", "Entry", "cache_key", "default_root", "parse_size", "size_limit"]

MAGIC = b"USDMLC02"
OLD_MAGICS = (b"USDMLC01",)
#: bytes of the array compressed as one zlib stream (chunks are compressed on every core)
ZCHUNK = 16 << 20
#: zlib level of the stored chunks. Measured on cornell's voxel array in its compact form (178 MiB,
#: 128³ / 2°): level 1: 20.0 MiB in 0.9 s, 3: 17.3 MiB in 1.4 s, 6: 14.0 MiB in 3.9 s (one core)
ZLEVEL = 6
#: the folder's size limit when ``$USDML_CACHE_SIZE`` is unset
DEFAULT_LIMIT = 4 << 30
_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}

log = logging.getLogger("usdml")


class CacheCorrupt(Exception):
    """An entry exists but cannot be trusted (the message says why)."""


def default_root() -> Path:
    env = os.environ.get("USDML_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "usdml"


def parse_size(text: str, name: str = "USDML_CACHE_SIZE") -> int:
    """Bytes of ``text``: a number of bytes or one with a binary suffix (``512M``, ``4G``, ``1.5GiB``)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*([kmgt]?)(?:i?b)?\s*", str(text), re.IGNORECASE)
    if not m:
        raise UsdmlError(f"{name}={text!r}: give a size in bytes or with a suffix, e.g. 4G or 512M")
    return int(float(m.group(1)) * _UNITS[m.group(2).lower()])


def size_limit() -> int:
    """The cache folder's size limit in bytes: ``$USDML_CACHE_SIZE``, else :data:`DEFAULT_LIMIT`."""
    env = os.environ.get("USDML_CACHE_SIZE", "").strip()
    return parse_size(env) if env else DEFAULT_LIMIT


def cache_key(*parts) -> str:
    """Hex key of ``parts`` (strings, numbers: anything with a stable ``repr``)."""
    h = hashlib.blake2b(digest_size=20)
    for p in parts:
        h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


def _on_cores(fn, items) -> list:
    """``fn`` over ``items`` on every core (zlib and hashlib release the GIL on large buffers)."""
    return run_parallel(fn, items, cpu_workers())


def _digest(chunks) -> str:
    h = hashlib.blake2b(digest_size=16)
    for c in chunks:
        h.update(c)
    return h.hexdigest()


@dataclass
class Entry:
    """One file of the cache folder, as ``usdml cache list`` shows it."""

    kind: str
    key: str
    path: Path
    bytes: int                  #: size on disk
    last_used: float            #: seconds since the epoch (mtime: written or last loaded)
    meta: dict                  #: the header (empty for an old or unreadable entry)
    format: str                 #: "USDMLC02", "USDMLC01" (old: rebuilt when next used), "unreadable" or "partial"

    def summary(self) -> dict:
        out = {"kind": self.kind, "key": self.key, "path": str(self.path), "bytes": self.bytes,
               "last_used": self.last_used, "format": self.format}
        for k in ("source", "resolution", "step", "depth", "nbytes"):
            if k in self.meta:
                out[k] = self.meta[k]
        return out


class Cache:
    """One cache folder (see module doc); ``limit``: its size limit in bytes (default :func:`size_limit`)."""

    def __init__(self, root: str | os.PathLike | None = None, limit: int | None = None):
        self.root = Path(root) if root is not None else default_root()
        self.limit = size_limit() if limit is None else int(limit)

    def path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}.bin"

    def contains(self, kind: str, key: str) -> bool:
        return self.path(kind, key).is_file()

    def put(self, kind: str, key: str, data: np.ndarray, meta: dict | None = None) -> Path:
        """Write ``data`` (any NumPy array) with ``meta`` atomically, then keep the folder within its
        limit (:meth:`evict`); returns the entry's path."""
        data = np.ascontiguousarray(data)
        raw = memoryview(data.reshape(-1)).cast("B")
        chunks = _on_cores(lambda lo: zlib.compress(raw[lo:lo + ZCHUNK], ZLEVEL), range(0, len(raw), ZCHUNK))
        header = dict(meta or {})
        header.update(dtype=data.dtype.str, shape=list(data.shape), nbytes=int(data.nbytes),
                      chunks=[len(c) for c in chunks], digest=_digest(chunks))
        blob = json.dumps(header, sort_keys=True).encode()
        dest = self.path(kind, key)
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=dest.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(MAGIC + struct.pack("<Q", len(blob)) + blob)
                for c in chunks:
                    f.write(c)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, dest)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        self.evict(keep=dest)
        return dest

    def load(self, kind: str, key: str) -> tuple[np.ndarray, dict] | None:
        """:meth:`get`, with a damaged entry reported (a warning naming it) and treated as absent, so
        the caller builds it anew."""
        try:
            return self.get(kind, key)
        except CacheCorrupt as e:
            log.warning(f"{kind} cache: {e}; rebuilding")
            return None

    def store(self, kind: str, key: str, data: np.ndarray, meta: dict | None = None) -> None:
        """:meth:`put`, with a failed write reported and the render going on without the entry."""
        try:
            self.put(kind, key, data, meta)
        except OSError as e:
            log.warning(f"{kind} cache: could not write {self.path(kind, key)} ({e}); continuing without it")

    def get(self, kind: str, key: str) -> tuple[np.ndarray, dict] | None:
        """``(data, meta)`` of an entry, None when absent (or of the old format: then removed);
        ``CacheCorrupt`` (entry removed) when damaged. A load marks the entry used (its mtime)."""
        path = self.path(kind, key)
        try:
            f = open(path, "rb")
        except FileNotFoundError:
            return None
        try:
            with f:
                magic = f.read(8)
                if magic in OLD_MAGICS:
                    log.info(f"{kind} cache: {path} has the old format {magic.decode()}; rebuilding it")
                    path.unlink()
                    return None
                meta, start = _read_header(f, magic, path)
                try:
                    dtype = np.dtype(meta["dtype"])
                    shape = tuple(int(s) for s in meta["shape"])
                    nbytes, sizes = int(meta["nbytes"]), [int(s) for s in meta["chunks"]]
                except (ValueError, KeyError, TypeError) as e:
                    raise CacheCorrupt(f"{path}: unreadable header ({e})") from None
                size = os.fstat(f.fileno()).st_size
                if size != start + sum(sizes) or int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != nbytes:
                    raise CacheCorrupt(f"{path}: {size} bytes on disk, header says {start + sum(sizes)} (truncated?)")
                stored = f.read()
            offsets = [0, *accumulate(sizes)]
            view = memoryview(stored)
            chunks = [view[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
            if _digest(chunks) != meta["digest"]:
                raise CacheCorrupt(f"{path}: checksum mismatch (damaged on disk)")
            data = np.empty(shape, dtype)
            out = memoryview(data.reshape(-1)).cast("B")

            def expand(i):
                got = zlib.decompress(chunks[i])
                if len(got) != min(ZCHUNK, nbytes - i * ZCHUNK):
                    raise CacheCorrupt(f"{path}: chunk {i} expands to {len(got)} bytes (damaged?)")
                out[i * ZCHUNK:i * ZCHUNK + len(got)] = got

            if len(chunks) != -(-nbytes // ZCHUNK):
                raise CacheCorrupt(f"{path}: {len(chunks)} chunks for {nbytes} bytes")
            _on_cores(expand, range(len(chunks)))
        except CacheCorrupt:
            _remove(path)
            raise
        except (OSError, struct.error, zlib.error) as e:
            raise CacheCorrupt(f"{path}: {e}") from None
        _touch(path)
        return data, meta

    # ------------------------------------------------------------------------- size and listing

    def entries(self) -> list[Entry]:
        """Every entry of the folder (and partial writes left by a killed process), oldest used first."""
        found = []
        if not self.root.is_dir():
            return found
        for kind_dir in sorted(p for p in self.root.iterdir() if p.is_dir()):
            for path in kind_dir.glob("*/*"):
                try:
                    st = path.stat()
                except OSError:
                    continue                    # removed meanwhile
                if path.name.endswith(".tmp"):
                    found.append(Entry(kind_dir.name, path.name.split(".")[1], path, st.st_size, st.st_mtime, {},
                                       "partial"))
                elif path.suffix == ".bin":
                    meta, fmt = _peek(path)
                    found.append(Entry(kind_dir.name, path.stem, path, st.st_size, st.st_mtime, meta, fmt))
        return sorted(found, key=lambda e: e.last_used)

    def evict(self, keep: Path | None = None) -> list[Entry]:
        """Remove the least recently used entries until the folder holds at most :attr:`limit` bytes
        (never ``keep``); returns those removed."""
        entries = [e for e in self.entries() if e.format != "partial"]
        total = sum(e.bytes for e in entries)
        removed = []
        for e in entries:
            if total <= self.limit:
                break
            if keep is not None and e.path == keep:
                continue
            if _remove(e.path):
                total -= e.bytes
                removed.append(e)
        if removed:
            log.info(f"cache {self.root}: removed {len(removed)} least recently used entr"
                     f"{'y' if len(removed) == 1 else 'ies'} to stay within {self.limit / 2**30:.2f} GiB")
        return removed

    def clean(self, older_than: float | None = None) -> list[Entry]:
        """Remove every entry (and partial write), or only those last used more than ``older_than``
        seconds ago; returns those removed."""
        now = time.time()
        gone = [e for e in self.entries() if older_than is None or now - e.last_used > older_than]
        return [e for e in gone if _remove(e.path)]


def _read_header(f, magic: bytes, path) -> tuple[dict, int]:
    """The JSON header of an entry whose first 8 bytes were ``magic`` and where its data starts."""
    if magic != MAGIC:
        raise CacheCorrupt(f"{path}: not a usdml cache entry (bad magic)")
    (hlen,) = struct.unpack("<Q", f.read(8))
    if hlen > 1 << 20:
        raise CacheCorrupt(f"{path}: header length {hlen} is implausible")
    try:
        meta = json.loads(f.read(hlen))
    except ValueError as e:
        raise CacheCorrupt(f"{path}: unreadable header ({e})") from None
    if not isinstance(meta, dict):
        raise CacheCorrupt(f"{path}: unreadable header (not an object)")
    return meta, 16 + hlen


def _peek(path: Path) -> tuple[dict, str]:
    """The header and format of an entry, without reading its data."""
    try:
        with open(path, "rb") as f:
            magic = f.read(8)
            if magic in OLD_MAGICS:
                return {}, magic.decode()
            return _read_header(f, magic, path)[0], MAGIC.decode()
    except (OSError, struct.error, CacheCorrupt):
        return {}, "unreadable"


def _touch(path: Path) -> None:
    """Mark ``path`` used now (least-recently-used eviction reads mtimes)."""
    try:
        os.utime(path)
    except OSError:
        pass


def _remove(path: Path) -> bool:
    try:
        path.unlink()
        return True
    except FileNotFoundError:
        return False
    except OSError as e:
        log.warning(f"cache: could not remove {path} ({e})")
        return False
