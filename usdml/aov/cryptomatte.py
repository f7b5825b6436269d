"""Cryptomatte (Psyop's specification, version 1.1.0): ids from names, the ranking pixel filter, the EXR header.

* **Ids.** A name's id is MurmurHash3_x86_32 (seed 0) of its UTF-8 bytes, stored as the 32-bit float whose bits are
  the hash with its exponent clamped to [1, 254] (sign and mantissa kept), so no id is 0, a NaN, an infinity or a
  denormal: the specification's ``uint32_to_float32``. In memory an id is that float's bit pattern as ``uint32``; 0
  means "nothing" (the specification's value for a sample with no object). Hashes come from the ``mmh3`` package
  (the reference C implementation, some 200 times faster than MurmurHash3 in pure Python, and an instanced
  stage can name 10⁵ things a frame).
* **Ranking.** Every pass (one primary ray per pixel) adds 1/passes to the id it hit; a miss adds nothing, so a
  pixel's coverages sum to the fraction of its rays that hit something named. Ids are ranked by coverage, ties by
  the smaller id (an order that does not depend on the order of the passes), and the first :data:`RANKS` are
  written as ``<layer>00`` .. ``<layer>02``: R = rank 2k id, G = its coverage, B = rank 2k + 1 id, A = its coverage.
  :class:`RankFilter` keeps, per pixel, a table of (id, count) slots that grows to the most distinct ids any pixel
  has seen: 6 bytes per slot and pixel.
* **Header.** Per layer, under the key of the first 7 hex digits of the layer name's MurmurHash3:
  ``cryptomatte/<key>/name`` (the layer name), ``/hash`` (``MurmurHash3_32``), ``/conversion``
  (``uint32_to_float32``) and ``/manifest`` (JSON ``{name: "8 hex digits of the id's float bits"}``, the names
  whose ids the frame's written ranks hold).
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import mmh3
import numpy as np

from usdml.aov.names import RANKS, find_aov

__all__ = ["RankFilter", "name_id", "name_ids", "float_bits", "layer_key", "header", "is_cryptomatte"]

_EXPONENT = np.uint32(0x7F800000)


def float_bits(hashes: np.ndarray) -> np.ndarray:
    """``(N,) uint32`` MurmurHash3 values as the bits of their Cryptomatte floats (exponent clamped to [1, 254])."""
    h = np.asarray(hashes, np.uint32)
    exponent = np.clip((h & _EXPONENT) >> np.uint32(23), 1, 254).astype(np.uint32)
    return (h & ~_EXPONENT) | (exponent << np.uint32(23))


def name_id(name: str) -> int:
    """The Cryptomatte id of ``name`` as the ``uint32`` bits of its float. Raises UnicodeEncodeError for a name
    with no UTF-8 form (a lone surrogate)."""
    return int(float_bits(np.array([mmh3.hash(name.encode("utf-8"), 0, signed=False)], np.uint32))[0])


def name_ids(names: list[str], bad=None) -> np.ndarray:
    """``(N,) uint32`` :func:`name_id` of each name; a name with no UTF-8 form gets 0 (no id) and is handed to
    ``bad(name)`` (the caller says it)."""
    out = np.zeros(len(names), np.uint32)
    for i, name in enumerate(names):
        try:
            out[i] = name_id(name)
        except UnicodeEncodeError:
            if bad is not None:
                bad(name)
    return out


def layer_key(layer: str) -> str:
    """The header key of a Cryptomatte layer: the first 7 hex digits of its name's MurmurHash3."""
    return f"{mmh3.hash(layer.encode('utf-8'), 0, signed=False):08x}"[:7]


def is_cryptomatte(aov: str) -> bool:
    spec = find_aov(aov)
    return spec is not None and spec.ranked


def header(layers: Mapping[str, str], manifests: Mapping[str, Mapping[str, int]]) -> dict[str, str]:
    """The Cryptomatte attributes of a file whose ``layers`` map layer names to AOVs: for each Cryptomatte layer its
    name, hash, conversion and manifest (``manifests``: AOV -> {name: id}, the frame's)."""
    out: dict[str, str] = {}
    for layer, aov in layers.items():
        if not is_cryptomatte(aov):
            continue
        key = f"cryptomatte/{layer_key(layer)}/"
        names = manifests.get(aov, {})
        out[key + "name"] = layer
        out[key + "hash"] = "MurmurHash3_32"
        out[key + "conversion"] = "uint32_to_float32"
        out[key + "manifest"] = json.dumps({n: f"{names[n]:08x}" for n in sorted(names)}, ensure_ascii=False)
    return out


class RankFilter:
    """The ranking pixel filter of one Cryptomatte AOV over a frame's passes (module doc).

    Slots are columns, ``(slots, P)``, filled left to right per pixel: a pass compares each hit with its pixel's
    first slot, and only the pixels not settled there (an edge's, a few per cent) with the next; most pixels see one
    id and are done in one gather."""

    def __init__(self, pixels: int):
        self.passes = 0
        self.ids = np.zeros((0, pixels), np.uint32)        # slot ids, 0: empty
        self.counts = np.zeros((0, pixels), np.uint16)     # passes that hit the slot's id

    def add(self, ids: np.ndarray) -> None:
        """One pass: ``ids`` (P,) uint32, the id each pixel's ray hit (0: nothing named)."""
        self.passes += 1
        ids = np.asarray(ids, np.uint32).ravel()
        rows = np.flatnonzero(ids)
        v = ids[rows]
        for col, count in zip(self.ids, self.counts):
            if not len(rows):
                return
            slot = col[rows]
            same, empty = slot == v, slot == 0
            count[rows[same]] += 1
            col[rows[empty]] = v[empty]
            count[rows[empty]] = 1
            rest = ~(same | empty)
            rows, v = rows[rest], v[rest]
        if len(rows):                   # some pixel has seen more ids than there are slots: one slot more
            self.ids = np.concatenate([self.ids, np.zeros((1, self.ids.shape[1]), np.uint32)])
            self.counts = np.concatenate([self.counts, np.zeros((1, self.ids.shape[1]), np.uint16)])
            self.ids[-1, rows] = v
            self.counts[-1, rows] = 1

    def ranked(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (P, RANKS) uint32, coverage (P, RANKS) float32)``: the first ranks of each pixel, by coverage
        then by the smaller id; 0 and 0 past a pixel's ids."""
        slots, p = self.ids.shape
        ids = np.zeros((p, RANKS), np.uint32)
        counts = np.zeros((p, RANKS), np.uint16)
        if slots:
            ids[:, 0], counts[:, 0] = self.ids[0], self.counts[0]
        # pixels with one id are ranked; the others (a second slot in use) are sorted by one uint64 key: the count
        # above, the id's complement below, so a descending sort is (count desc, id asc)
        many = np.flatnonzero(self.counts[1]) if slots > 1 else np.zeros(0, np.int64)
        if len(many):
            c, i = self.counts[:, many].T, self.ids[:, many].T
            key = (c.astype(np.uint64) << np.uint64(32)) | (~i).astype(np.uint64)
            key[c == 0] = 0
            order = np.argsort(~key, axis=1, kind="stable")[:, :RANKS]
            k = order.shape[1]
            ids[many, :k] = np.take_along_axis(i, order, axis=1)
            counts[many, :k] = np.take_along_axis(c, order, axis=1)
            ids[many, k:] = 0
            counts[many, k:] = 0
        ids[counts == 0] = 0
        return ids, (counts / np.float32(max(self.passes, 1))).astype(np.float32)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (P, 2·RANKS) float32 in the channel order of ``RANK_CHANNELS``, the ids written (K,) uint32)``."""
        ids, coverage = self.ranked()
        out = np.empty((len(ids), 2 * RANKS), np.float32)
        out[:, 0::2] = ids.view(np.float32)
        out[:, 1::2] = coverage
        return out, np.unique(ids[ids != 0])
