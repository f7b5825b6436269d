"""Depth coding of voxel arrays for the on-disk cache (the format: :mod:`usdml.visibility.voxel.codec`).

One thread per direction walks its rows in order (``rows`` rows inside the sphere; row ``r`` holds
``row_nw[r]`` packed words from word ``row_word[r]`` of the direction, its first word being word
``row_w0[r]`` of the full row). The ``k``-th set bit of a row (depth ``l``) is predicted from the
``k``-th bit of the row before: ``residual = (l - l') - (l' - l'')`` along that chain, ``l`` itself
at a chain's start, ``l - l'`` at its second bit. A direction's bits are ``first_bit[t] …`` of the
launch's arrays; ``depth`` and ``step`` keep each bit's ``l`` and ``l - l'`` for the next row.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "optimization_level": 3})


@wp.kernel
def count_bits(words: wp.array(dtype=wp.uint32), row_word: wp.array(dtype=wp.int32),
               row_nw: wp.array(dtype=wp.int32), rows: int, per_dir: int, counts: wp.array(dtype=wp.int32)):
    t = wp.tid()
    for r in range(rows):
        c = int(0)
        for q in range(row_nw[r]):
            w = words[t * per_dir + row_word[r] + q]
            while w != wp.uint32(0):
                c += 1
                w = w & (w - wp.uint32(1))
        counts[t * rows + r] = c


@wp.kernel
def encode_depths(words: wp.array(dtype=wp.uint32), row_word: wp.array(dtype=wp.int32),
                  row_nw: wp.array(dtype=wp.int32), row_w0: wp.array(dtype=wp.int32), rows: int, per_dir: int,
                  first_bit: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.int32),
                  step: wp.array(dtype=wp.int32), residual: wp.array(dtype=wp.int32),
                  debruijn: wp.array(dtype=wp.int32)):
    t = wp.tid()
    i = first_bit[t]
    c1 = int(0)        # bits of the row before
    c2 = int(0)        # and of the one before that
    for r in range(rows):
        k = int(0)
        for q in range(row_nw[r]):
            w = words[t * per_dir + row_word[r] + q]
            while w != wp.uint32(0):
                low = w & (~w + wp.uint32(1))
                # the lowest bit's index: a de Bruijn sequence (no count-trailing-zeros builtin)
                l = 32 * (row_w0[r] + q) + debruijn[int((low * wp.uint32(0x077CB531)) >> wp.uint32(27))]
                d1 = l
                d2 = l
                if k < c1:
                    p = i - c1
                    d1 = l - depth[p]
                    d2 = d1
                    if k < c2:
                        d2 = d1 - step[p]
                depth[i] = l
                step[i] = d1
                residual[i] = d2
                i += 1
                k += 1
                w = w & (w - wp.uint32(1))
        c2 = c1
        c1 = k


@wp.kernel
def decode_depths(residual: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32),
                  row_word: wp.array(dtype=wp.int32), row_nw: wp.array(dtype=wp.int32),
                  row_w0: wp.array(dtype=wp.int32), rows: int, per_dir: int, first_bit: wp.array(dtype=wp.int32),
                  depth: wp.array(dtype=wp.int32), step: wp.array(dtype=wp.int32),
                  words: wp.array(dtype=wp.uint32), bad: wp.array(dtype=wp.int32)):
    t = wp.tid()
    i = first_bit[t]
    c1 = int(0)
    c2 = int(0)
    for r in range(rows):
        c = counts[t * rows + r]
        for k in range(c):
            v = residual[i]
            l = v
            d1 = v
            if k < c1:
                p = i - c1
                if k < c2:
                    d1 = v + step[p]
                l = depth[p] + d1
            depth[i] = l
            step[i] = d1
            q = l / 32 - row_w0[r]
            if l < 0 or q < 0 or q >= row_nw[r]:
                bad[0] = 1                  # damaged data: a bit outside its row
            else:
                w = t * per_dir + row_word[r] + q
                words[w] = words[w] | (wp.uint32(1) << wp.uint32(l % 32))
            i += 1
        c2 = c1
        c1 = c
