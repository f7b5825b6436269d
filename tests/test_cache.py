"""The on-disk cache: compressed entries round-trip exactly, voxel arrays shrink to their set bits,
damage and the old format are rebuilt, the size limit evicts the least recently used, and
``usdml cache list|clean``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from usdml.cache import Cache, parse_size, size_limit
from usdml.cli import main
from usdml.errors import UsdmlError
from usdml.visibility.voxel import codec as voxel_codec
from usdml.visibility.voxel.array import cached_array

from voxel_reference import box, city_tris


def _tris_mesh(tris):
    tris = np.asarray(tris, np.float64)
    return tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3)


@pytest.mark.parametrize("data", [np.arange(10_000, dtype=np.uint32).reshape(100, 100),
                                  np.random.default_rng(1).random(3000),
                                  np.zeros(0, np.int32)])
def test_entries_round_trip_exactly(tmp_path, monkeypatch, data):
    import usdml.cache as cache_mod

    monkeypatch.setattr(cache_mod, "ZCHUNK", 4096)          # several zlib chunks
    cache = Cache(tmp_path)
    cache.put("t", "a" * 40, data, {"what": "x"})
    got, meta = cache.get("t", "a" * 40)
    assert got.dtype == data.dtype and got.shape == data.shape and np.array_equal(got, data)
    assert meta["what"] == "x"


def test_voxel_arrays_are_stored_as_their_set_bits(tmp_path):
    """A box city's array at 64³ / 10°: the compact entry decodes to the same words and is a small
    fraction of the dense array (cornell at 128³ / 2°: 939 MiB -> 14 MiB)."""
    points, tris = _tris_mesh(city_tris(np.random.default_rng(5)))
    cache = Cache(tmp_path)
    built = cached_array(points, tris, 64, 10.0, cache)
    loaded = cached_array(points, tris, 64, 10.0, cache)
    assert loaded.cached and np.array_equal(loaded.words, built.words) and built.words.any()
    size = cache.path("voxel", built.key).stat().st_size
    assert size < built.nbytes / 10, (size, built.nbytes)
    blob, meta = voxel_codec.encode(built.words, 64)
    assert np.array_equal(voxel_codec.decode(blob, meta, 64), built.words)


def test_codec_handles_full_rows_and_an_empty_array():
    """Rows with 256+ bits (uint16 counts) and an empty array round-trip; damaged streams are refused."""
    from usdml.visibility.voxel.grid import RowLayout

    layout = RowLayout.make(512)
    words = np.zeros(3 * layout.words, np.uint32)
    words[layout.words:2 * layout.words] = 0xFFFFFFFF       # every voxel of one direction set
    blob, meta = voxel_codec.encode(words, 512)
    assert meta["count_width"] == 2
    assert np.array_equal(voxel_codec.decode(blob, meta, 512), words)
    empty = np.zeros(2 * RowLayout.make(16).words, np.uint32)
    assert np.array_equal(voxel_codec.decode(*voxel_codec.encode(empty, 16), 16), empty)
    with pytest.raises(ValueError):
        voxel_codec.decode(blob[:-1], meta, 512)


@pytest.mark.parametrize("resolution", [64, 512])
def test_compiled_and_warp_coders_write_and_read_the_same_bytes(resolution):
    """kernels/voxel/voxcodec.c against the Warp kernels: the same stream from the same words (a box city's
    array, and rows of 256+ bits with uint16 counts), each decoding the other's, and each refusing a
    stream whose bit leaves its row."""
    if voxel_codec.EXTENSION.library() is None:
        if os.environ.get("USDML_REQUIRE_NATIVE") == "1":
            pytest.fail(f"kernels/voxel/voxcodec.c is not built: {voxel_codec.EXTENSION.load()[1]}")
        pytest.skip("the compiled coder is not built (no C compiler at install)")
    from usdml.visibility.voxel.grid import RowLayout

    if resolution == 64:
        points, tris = _tris_mesh(city_tris(np.random.default_rng(7)))
        words = cached_array(points, tris, 64, 10.0, None).words
    else:
        per = RowLayout.make(512).words
        words = np.random.default_rng(3).integers(0, 2**32, 2 * per, dtype=np.uint64).astype(np.uint32)
        words &= np.uint32(0xF0F0FFFF)      # dense rows, irregular depths
    assert words.any()
    c_blob, c_meta = voxel_codec.encode(words, resolution, native=True)
    w_blob, w_meta = voxel_codec.encode(words, resolution, native=False)
    assert c_meta == w_meta and np.array_equal(c_blob, w_blob)
    for native in (True, False):
        assert np.array_equal(voxel_codec.decode(c_blob, c_meta, resolution, native=native), words)
    damaged = c_blob.copy()
    damaged[-1] = 0xFF                       # the last residual's high byte: a depth far outside its row
    for native in (True, False):
        with pytest.raises(ValueError):
            voxel_codec.decode(damaged, c_meta, resolution, native=native)


def test_an_undecodable_or_old_entry_is_rebuilt(tmp_path, caplog):
    points, tris = _tris_mesh(box((-1, -1, -1), (1, 2, 1)))
    cache = Cache(tmp_path)
    first = cached_array(points, tris, 16, 20.0, cache)
    path = cache.path("voxel", first.key)
    cache.put("voxel", first.key, np.zeros(7, np.uint8), {"codec": voxel_codec.CODEC, "directions": 1})
    with caplog.at_level("WARNING", logger="usdml"):
        again = cached_array(points, tris, 16, 20.0, cache)
    assert not again.cached and "rebuilding" in caplog.text and np.array_equal(again.words, first.words)
    path.write_bytes(b"USDMLC01" + bytes(100))             # the old uncompressed format: absent
    assert cache.get("voxel", first.key) is None and not path.exists()


def _aged(cache, name, age_s, size=20_000):
    cache.put("t", name * 40, np.random.default_rng(len(name)).integers(0, 255, size, np.uint8))
    t = time.time() - age_s
    os.utime(cache.path("t", name * 40), (t, t))


def test_least_recently_used_entries_are_evicted(tmp_path):
    cache = Cache(tmp_path, limit=70_000)
    for name, age in (("a", 300), ("b", 200), ("c", 100)):
        _aged(cache, name, age)
    cache.get("t", "a" * 40)                                 # a is used: now the newest
    _aged(cache, "d", 0)                                     # over the limit: b, the least recently used, goes
    assert [cache.contains("t", k * 40) for k in "abcd"] == [True, False, True, True]
    Cache(tmp_path, limit=0).put("t", "e" * 40, np.zeros(10, np.uint8))    # never the entry just written
    assert [e.key[0] for e in cache.entries()] == ["e"]


def test_cache_size_parsing(monkeypatch):
    assert parse_size("4G") == 4 << 30 and parse_size("512M") == 512 << 20 and parse_size("1.5GiB") == 3 << 29
    assert parse_size("1000") == 1000 and parse_size(" 64 kb ") == 64 << 10
    monkeypatch.delenv("USDML_CACHE_SIZE", raising=False)
    assert size_limit() == 4 << 30
    monkeypatch.setenv("USDML_CACHE_SIZE", "lots")
    with pytest.raises(UsdmlError, match="USDML_CACHE_SIZE='lots'"):
        size_limit()


def test_usdml_cache_list_and_clean(tmp_path, monkeypatch, capsys):
    cache = Cache(tmp_path)
    _aged(cache, "a", 10 * 86400)
    _aged(cache, "b", 0)
    assert main(["cache", "list", "--cache", str(tmp_path), "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [e["key"][0] for e in listed["entries"]] == ["a", "b"] and listed["bytes"] > 40_000
    monkeypatch.setenv("USDML_CACHE_DIR", str(tmp_path))
    assert main(["cache", "list"]) == 0
    assert "2 entries" in capsys.readouterr().out
    assert main(["cache", "clean", "--older-than", "5"]) == 0
    assert "removed 1 entry" in capsys.readouterr().out and not cache.contains("t", "a" * 40)
    assert main(["cache", "clean"]) == 0
    assert "removed 1 entry" in capsys.readouterr().out and cache.entries() == []
    monkeypatch.setenv("USDML_CACHE_SIZE", "12 parsecs")
    assert main(["cache", "list"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("usdml: error: USDML_CACHE_SIZE=")


def test_usdml_cache_alone_lists(tmp_path):
    """Issue 55, item 7: ``usdml cache`` with no action refused ("the following arguments are required:
    action"); it lists, as ``usdml cache list`` does and the README describes."""
    _aged(Cache(tmp_path), "a", 0)
    env = {**os.environ, "USDML_CACHE_DIR": str(tmp_path)}
    alone, listed = (subprocess.run([sys.executable, "-m", "usdml.cli", "cache", *action], capture_output=True,
                                    text=True, env=env) for action in ([], ["list"]))
    assert alone.returncode == 0 and alone.stderr == ""
    assert alone.stdout == listed.stdout and alone.stdout.splitlines()[-1].startswith("1 entry, ")
