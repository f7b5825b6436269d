"""Content-addressed on-disk store for expensive per-prototype data (paper 000's voxel arrays).

An entry is one file ``<root>/<kind>/<key[:2]>/<key>.bin``:

* 8 bytes magic ``USDMLC01``, 8 bytes little-endian length ``H`` of the JSON header, ``H`` bytes of
  JSON (the caller's metadata plus ``dtype``, ``shape``, ``nbytes`` and ``digest``, a blake2b of the
  data), zero padding to a 4 KiB boundary, then the raw array.
* The key is a hash the caller makes of everything the data depends on (geometry hash, parameters,
  format version), so a changed mesh or setting never reads a stale entry.
* Writes go to a temporary file in the same folder, then ``os.replace``: readers on any process or
  machine sharing the folder see a whole entry or none.
* Loads check the magic, header, size and digest; a damaged entry is reported (``CacheCorrupt``),
  removed, and the caller rebuilds it.

The root is ``$USDML_CACHE_DIR``, else ``$XDG_CACHE_HOME/usdml``, else ``~/.cache/usdml``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import hashlib
import json
import logging
import os
from pathlib import Path
import struct
import tempfile

import numpy as np

__all__ = ["Cache", "CacheCorrupt", "default_root", "cache_key"]

MAGIC = b"USDMLC01"
ALIGN = 4096


class CacheCorrupt(Exception):
    """An entry exists but cannot be trusted (the message says why)."""


def default_root() -> Path:
    env = os.environ.get("USDML_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "usdml"


def cache_key(*parts) -> str:
    """Hex key of ``parts`` (strings, numbers: anything with a stable ``repr``)."""
    h = hashlib.blake2b(digest_size=20)
    for p in parts:
        h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()


def _digest(data: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(memoryview(np.ascontiguousarray(data)).cast("B"))
    return h.hexdigest()


#: bytes read (and hashed) at a time when loading an entry
READ_CHUNK = 64 << 20


def _read_and_digest(f, buf: memoryview, path) -> str:
    """Fill ``buf`` from ``f`` and return the blake2b of its bytes (as :func:`_digest`): chunk ``k`` is
    hashed on a second thread while chunk ``k + 1`` is read, so a load costs about the longer of the
    two (a 939 MiB array: 3.2 s read then hashed -> about 2 s)."""
    h = hashlib.blake2b(digest_size=16)
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = None
        for lo in range(0, len(buf), READ_CHUNK):
            chunk = buf[lo:lo + READ_CHUNK]
            got = 0
            while got < len(chunk):
                n = f.readinto(chunk[got:])
                if not n:
                    raise CacheCorrupt(f"{path}: ends early (truncated?)")
                got += n
            if pending is not None:
                pending.result()
            pending = pool.submit(h.update, chunk)      # hashlib releases the GIL on large buffers
        if pending is not None:
            pending.result()
    return h.hexdigest()


class Cache:
    """One cache folder (see module doc)."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else default_root()

    def path(self, kind: str, key: str) -> Path:
        return self.root / kind / key[:2] / f"{key}.bin"

    def contains(self, kind: str, key: str) -> bool:
        return self.path(kind, key).is_file()

    def put(self, kind: str, key: str, data: np.ndarray, meta: dict | None = None) -> Path:
        """Write ``data`` (any NumPy array) with ``meta`` atomically; returns the entry's path."""
        data = np.ascontiguousarray(data)
        header = dict(meta or {})
        header.update(dtype=data.dtype.str, shape=list(data.shape), nbytes=int(data.nbytes),
                      digest=_digest(data))
        blob = json.dumps(header, sort_keys=True).encode()
        head = MAGIC + struct.pack("<Q", len(blob)) + blob
        head += b"\0" * (-len(head) % ALIGN)
        dest = self.path(kind, key)
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=dest.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(head)
                f.write(memoryview(data).cast("B"))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, dest)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        return dest

    def load(self, kind: str, key: str) -> tuple[np.ndarray, dict] | None:
        """:meth:`get`, with a damaged entry reported (a warning naming it) and treated as absent, so
        the caller builds it anew."""
        try:
            return self.get(kind, key)
        except CacheCorrupt as e:
            logging.getLogger("usdml").warning(f"{kind} cache: {e}; rebuilding")
            return None

    def store(self, kind: str, key: str, data: np.ndarray, meta: dict | None = None) -> None:
        """:meth:`put`, with a failed write reported and the render going on without the entry."""
        try:
            self.put(kind, key, data, meta)
        except OSError as e:
            logging.getLogger("usdml").warning(f"{kind} cache: could not write {self.path(kind, key)} ({e}); "
                                               "continuing without it")

    def get(self, kind: str, key: str) -> tuple[np.ndarray, dict] | None:
        """``(data, meta)`` of an entry, None when absent; ``CacheCorrupt`` (entry removed) when damaged."""
        path = self.path(kind, key)
        try:
            f = open(path, "rb")
        except FileNotFoundError:
            return None
        try:
            with f:
                magic = f.read(8)
                if magic != MAGIC:
                    raise CacheCorrupt(f"{path}: not a usdml cache entry (bad magic)")
                (hlen,) = struct.unpack("<Q", f.read(8))
                if hlen > 1 << 20:
                    raise CacheCorrupt(f"{path}: header length {hlen} is implausible")
                try:
                    meta = json.loads(f.read(hlen))
                    dtype = np.dtype(meta["dtype"])
                    shape = tuple(int(s) for s in meta["shape"])
                    nbytes = int(meta["nbytes"])
                except (ValueError, KeyError, TypeError) as e:
                    raise CacheCorrupt(f"{path}: unreadable header ({e})") from None
                start = 16 + hlen
                start += -start % ALIGN
                size = os.fstat(f.fileno()).st_size
                if size != start + nbytes or int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != nbytes:
                    raise CacheCorrupt(f"{path}: {size} bytes on disk, header says {start + nbytes} (truncated?)")
                f.seek(start)
                data = np.empty(shape, dtype)
                if _read_and_digest(f, memoryview(data.reshape(-1)).cast("B"), path) != meta["digest"]:
                    raise CacheCorrupt(f"{path}: checksum mismatch (damaged on disk)")
                return data, meta
        except CacheCorrupt:
            try:
                path.unlink()
            except OSError:
                pass
            raise
        except (OSError, struct.error) as e:
            raise CacheCorrupt(f"{path}: {e}") from None
