"""The compact on-disk form of a voxel array (what :func:`usdml.visibility.voxel.array.cached_array`
stores; the kernels read the dense words, this form is only for the cache).

A dense array is mostly empty words, and its set bits are where rows cross surfaces: a plane crosses
neighbouring rows of a direction at depths that change by a nearly constant step. So an array is
stored as its set bits, depth-coded:

* ``counts``: set bits per row (the rows inside the sphere, :class:`RowLayout`, direction after
  direction), ``(directions * rows,)`` uint8, or uint16 byte planes when a row holds 256 or more;
* ``residuals``: for each set bit in order (row, then depth ``l``), the second difference of its
  depth along the chain of the ``k``-th bits of consecutive rows (the first of a chain: ``l``; the
  second: its difference), zigzag coded, uint8 or uint16 byte planes.

The cache then deflates that (:mod:`usdml.cache`). Measured at 128³ / 2° (939 MiB dense): cornell
58 M set bits -> 14.0 MiB, the city 153 M -> 119.4 MiB (zlib 6; zlib alone on the dense words: 37
MiB for cornell at level 6, 69 MiB at 1). Chains restart at every direction (one kernel thread
each); ``DIRS_PER_CHUNK`` directions go to one launch, launches run on every core.

Two implementations write and read the same bytes: ``kernels/voxel/voxcodec.c`` (the optional extension
``usdml.kernels._voxcodec``: a row's chains in two small rolling buffers, byte planes and zigzag read in
the same pass) and the Warp kernels of ``kernels/voxel/codec.py``, used where no C compiler built the
former (``native=False`` picks them; the tests hold the two to the same bytes).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

import ctypes

from usdml.native import Extension
from usdml.parallel import cpu_workers, run_parallel
from usdml.visibility.voxel.grid import RowLayout

__all__ = ["CODEC", "EXTENSION", "decode", "encode"]

#: the ``codec`` an entry's metadata names (bump when the coding changes)
CODEC = "depth2"
#: directions coded together: chains restart at chunk starts (a few rows in 10⁵), chunks run in parallel
DIRS_PER_CHUNK = 128
#: bit index of ``(low * 0x077CB531) >> 27`` for ``low`` one bit (the encoder's lowest-bit lookup)
DEBRUIJN = np.zeros(32, np.int32)
DEBRUIJN[((np.uint64(1) << np.arange(32, dtype=np.uint64)) * np.uint64(0x077CB531) & np.uint64(0xFFFFFFFF)) >> np.uint64(27)] = np.arange(32)


_P, _i32, _i64 = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64
#: ``voxcodec.c``'s functions
EXTENSION = Extension("voxel._voxcodec", {
    "vc_count": (_i64, [_P, _i64, _P, _P, _i32, _i64, _P]),
    "vc_encode": (_i64, [_P, _i64, _P, _P, _P, _i32, _i64, _P]),
    "vc_decode": (ctypes.c_int, [_P, _P, _P, _P, _i64, _P, _P, _P, _i32, _i64, _P]),
})


def _native(native: bool | None):
    """The compiled coder when it is wanted (``native``: None or True) and was built, else None."""
    return EXTENSION.library() if native is not False else None


@lru_cache(maxsize=4)
def _tables(n: int) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, words_per_direction, row_word, row_nw, row_w0)`` at resolution ``n``: the rows inside
    the sphere (:class:`RowLayout`), their first packed word, packed words and first full-row word."""
    layout = RowLayout.make(n)
    inside = np.flatnonzero(layout.nw)
    return (len(inside), layout.words, *(np.ascontiguousarray(a[inside], np.int32)
                                         for a in (layout.offset, layout.nw, layout.w0)))


def _kernels():
    """``(warp, usdml.kernels.voxel.codec)``, imported on first use."""
    from usdml.kernels import warp

    wp = warp()
    from usdml.kernels.voxel import codec as voxel_codec

    return wp, voxel_codec


def _spans(n_dirs: int) -> list[tuple[int, int]]:
    return [(d0, min(n_dirs, d0 + DIRS_PER_CHUNK)) for d0 in range(0, n_dirs, DIRS_PER_CHUNK)]


def _encode_chunk_native(lib, words: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_encode_chunk` by ``voxcodec.c``."""
    rows, per, row_word, row_nw, row_w0 = _tables(n)
    words = np.ascontiguousarray(words, np.uint32)
    dirs = len(words) // per
    counts = np.empty(dirs * rows, np.uint16)
    total = lib.vc_count(words.ctypes.data, dirs, row_word.ctypes.data, row_nw.ctypes.data, rows, per,
                         counts.ctypes.data)
    res = np.empty(total, np.uint16)
    written = lib.vc_encode(words.ctypes.data, dirs, row_word.ctypes.data, row_nw.ctypes.data, row_w0.ctypes.data,
                            rows, per, res.ctypes.data)
    if written != total:
        raise MemoryError("voxcodec: no memory for a row's chains")
    return counts, res


def _encode_chunk(words: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(counts, zigzag residuals)`` of the directions of ``words``, both uint16."""
    wp, k = _kernels()
    rows, per, *tables = _tables(n)
    dirs = len(words) // per
    w = wp.array(words, dtype=wp.uint32, device="cpu", copy=False)
    row_word, row_nw, row_w0 = (wp.array(a, dtype=wp.int32, device="cpu", copy=False) for a in tables)
    counts = np.zeros(dirs * rows, np.int32)
    wp.launch(k.count_bits, dim=dirs, device="cpu",
              inputs=[w, row_word, row_nw, rows, per, wp.array(counts, dtype=wp.int32, device="cpu", copy=False)])
    per_dir = counts.reshape(dirs, rows).sum(axis=1, dtype=np.int64)
    first = (np.cumsum(per_dir) - per_dir).astype(np.int32)
    total = int(per_dir.sum())
    out = [np.empty(total, np.int32) for _ in range(3)]
    wp.launch(k.encode_depths, dim=dirs, device="cpu",
              inputs=[w, row_word, row_nw, row_w0, rows, per, wp.array(first, dtype=wp.int32, device="cpu")]
              + [wp.array(a, dtype=wp.int32, device="cpu", copy=False) for a in out + [DEBRUIJN]])
    res = out[2]
    # depths < 2048 and counts <= 2048 (RowLayout's resolutions): both fit 16 bits, zigzag coded
    return counts.astype(np.uint16), ((res << 1) ^ (res >> 31)).astype(np.uint16)


def _decode_chunk(counts: np.ndarray, residuals: np.ndarray, n: int, out: np.ndarray) -> None:
    """Set the bits of ``out`` (the chunk's words, zero) from its ``counts`` and zigzag ``residuals``."""
    wp, k = _kernels()
    rows, per, *tables = _tables(n)
    dirs = len(counts) // rows
    counts = counts.astype(np.int32)
    res = residuals.astype(np.int32)
    res = (res >> 1) ^ -(res & 1)
    per_dir = counts.reshape(dirs, rows).sum(axis=1, dtype=np.int64)
    first = (np.cumsum(per_dir) - per_dir).astype(np.int32)
    bad = np.zeros(1, np.int32)
    arrays = [res, counts, *tables]
    wp.launch(k.decode_depths, dim=dirs, device="cpu",
              inputs=[wp.array(a, dtype=wp.int32, device="cpu", copy=False) for a in arrays] + [rows, per]
              + [wp.array(a, dtype=wp.int32, device="cpu", copy=False)
                 for a in (first, np.empty(len(res), np.int32), np.empty(len(res), np.int32))]
              + [wp.array(out, dtype=wp.uint32, device="cpu", copy=False),
                 wp.array(bad, dtype=wp.int32, device="cpu", copy=False)])
    if bad[0]:
        raise ValueError("a decoded bit lies outside its row")


def _width(values: np.ndarray) -> int:
    """Bytes a value of ``values`` (>= 0, < 2¹⁶) takes in :func:`_pack`'s form: 1, or 2 as two byte planes."""
    return 1 if values.size == 0 or values.max() < 256 else 2


def _pack(values: np.ndarray, width: int, out: np.ndarray) -> None:
    """``values`` as ``width``-byte values into ``out`` (``width * len(values)`` bytes): uint8, or a plane of
    low bytes then one of high bytes (elementwise, contiguous: no strided copy of a transpose)."""
    n = values.size
    np.bitwise_and(values, 0xFF, out=out[:n], casting="unsafe")
    if width == 2:
        np.right_shift(values, 8, out=out[n:], casting="unsafe")


def _unpack(data: np.ndarray, width: int) -> np.ndarray:
    """:func:`_pack`'s values (uint8 or uint16)."""
    if width == 1:
        return data
    return data.reshape(2, -1).T.copy().view("<u2").reshape(-1)


def encode(words: np.ndarray, resolution: int, native: bool | None = None) -> tuple[np.ndarray, dict]:
    """The compact form of an array's ``words`` (``(directions * words_per_direction,)`` uint32) at
    ``resolution``: ``(bytes, meta)``, ``bytes`` a uint8 array, ``meta`` what :func:`decode` needs.
    ``native``: None the compiled coder where built, False the Warp kernels (the same bytes)."""
    _, per, *_ = _tables(resolution)
    n_dirs = len(words) // per
    lib = _native(native)
    chunk = (lambda w: _encode_chunk_native(lib, w, resolution)) if lib is not None else \
        (lambda w: _encode_chunk(w, resolution))
    parts = run_parallel(lambda s: chunk(words[s[0] * per:s[1] * per]), _spans(n_dirs), cpu_workers(),
                         first_on_caller=True)
    counts = np.concatenate([c for c, _ in parts]) if parts else np.zeros(0, np.uint16)
    res = np.concatenate([r for _, r in parts]) if parts else np.zeros(0, np.uint16)
    c_width, r_width = _width(counts), _width(res)
    out = np.empty(c_width * counts.size + r_width * res.size, np.uint8)
    _pack(counts, c_width, out[:c_width * counts.size])
    _pack(res, r_width, out[c_width * counts.size:])
    meta = {"codec": CODEC, "directions": n_dirs, "set_bits": int(res.size), "count_width": c_width,
            "residual_width": r_width, "chunk_directions": DIRS_PER_CHUNK}
    return out, meta


def decode(data: np.ndarray, meta: dict, resolution: int, native: bool | None = None) -> np.ndarray:
    """The dense words of an array from :func:`encode`'s ``(bytes, meta)``; ``ValueError`` when
    they do not fit together. ``native`` as :func:`encode`'s."""
    if meta.get("codec") != CODEC or int(meta.get("chunk_directions", 0)) != DIRS_PER_CHUNK:
        raise ValueError(f"codec {meta.get('codec')!r}, expected {CODEC!r}")
    rows, per, *_ = _tables(resolution)
    n_dirs, n_bits = int(meta["directions"]), int(meta["set_bits"])
    c_len = n_dirs * rows * int(meta["count_width"])
    if data.size != c_len + n_bits * int(meta["residual_width"]):
        raise ValueError(f"{data.size} bytes, expected {c_len + n_bits * int(meta['residual_width'])}")
    counts = _unpack(data[:c_len], int(meta["count_width"]))
    per_dir = counts.reshape(-1, rows).sum(axis=1, dtype=np.int64)
    if per_dir.sum() != n_bits:
        raise ValueError(f"{per_dir.sum()} bits counted, {n_bits} stored")
    out = np.zeros(n_dirs * per, np.uint32)
    bounds = np.concatenate([[0], np.cumsum(per_dir)])
    lib = _native(native)
    if lib is not None:
        planes = (data[:c_len], int(meta["count_width"])), (data[c_len:], int(meta["residual_width"]))
        run_parallel(lambda s: _decode_chunk_native(lib, planes, s, bounds, resolution, out), _spans(n_dirs),
                     cpu_workers(), first_on_caller=True)
        return out
    res = _unpack(data[c_len:], int(meta["residual_width"]))
    run_parallel(lambda s: _decode_chunk(counts[s[0] * rows:s[1] * rows], res[bounds[s[0]]:bounds[s[1]]], resolution,
                                         out[s[0] * per:s[1] * per]), _spans(n_dirs), cpu_workers(), first_on_caller=True)
    return out


def _decode_chunk_native(lib, planes, span: tuple[int, int], bounds: np.ndarray, n: int, out: np.ndarray) -> None:
    """Directions ``span`` of ``out`` (zero) by ``voxcodec.c``, read straight from the stored byte
    ``planes`` ((counts, width), (residuals, width)): value ``i`` of a 2-byte plane of ``m`` values is
    bytes ``i`` and ``m + i``."""
    rows, per, row_word, row_nw, row_w0 = _tables(n)
    d0, d1 = span
    ptrs = []
    for (data, width), first in (planes[0], d0 * rows), (planes[1], int(bounds[d0])):
        m = data.size // width
        base = data.ctypes.data
        ptrs += [base + first, base + m + first if width == 2 else None]
    bad = lib.vc_decode(*ptrs, d1 - d0, row_word.ctypes.data, row_nw.ctypes.data, row_w0.ctypes.data, rows, per,
                        out[d0 * per:].ctypes.data)
    if bad == 2:
        raise MemoryError("voxcodec: no memory for a row's chains")
    if bad:
        raise ValueError("a decoded bit lies outside its row")
