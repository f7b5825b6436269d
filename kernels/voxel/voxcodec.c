/* The depth coding of voxel arrays for the on-disk cache, compiled: the same format and the same bits as
 * the Warp kernels of kernels/voxel/codec.py (the format: usdml/visibility/voxel/codec.py).
 *
 * Why compiled: Warp runs a CPU launch on one thread through bounds-checked arrays, and the coding is a
 * serial walk per direction over every set bit (the city's array: 153 M of them); here the chains of one
 * row are kept in two small rolling buffers instead of whole-array depth and step arrays, the zigzag and
 * the byte planes are read and written in the same pass, and the lowest set bit is __builtin_ctz.
 *
 * A direction's rows are the rows inside the sphere: row r holds row_nw[r] packed words from word
 * row_word[r] of the direction, its first word being word row_w0[r] of the full row. The k-th set bit of
 * a row (depth l) is predicted from the k-th bit of the row before: residual = (l - l') - (l' - l''),
 * l itself at a chain's start, l - l' at its second bit. Chains restart at every direction.
 *
 * Counts and residuals are uint16 values stored as one byte (hi == NULL) or as a low and a high byte
 * plane (hi[i] the high byte of value i); residuals are zigzag coded.
 */
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>

static inline uint32_t get16(const uint8_t *lo, const uint8_t *hi, int64_t i) {
    return hi ? (uint32_t)lo[i] | ((uint32_t)hi[i] << 8) : (uint32_t)lo[i];
}

static int32_t max_bits(const int32_t *row_nw, int32_t rows) {
    int32_t m = 1;
    for (int32_t r = 0; r < rows; r++)
        if (row_nw[r] > m) m = row_nw[r];
    return 32 * m;
}

/* The row just done becomes the row before: its chains' (depth, step) buffers swap with the current
 * ones, and the bit counts shift (c1: the row before, c2: the one before that). */
static inline void next_row(int32_t **pdepth, int32_t **pstep, int32_t **cdepth, int32_t **cstep, int32_t *c1,
                            int32_t *c2, int32_t done) {
    int32_t *t = *pdepth; *pdepth = *cdepth; *cdepth = t;
    t = *pstep; *pstep = *cstep; *cstep = t;
    *c2 = *c1;
    *c1 = done;
}

/* counts[d * rows + r] = set bits of row r of direction d, d < dirs; returns the sum. */
int64_t vc_count(const uint32_t *words, int64_t dirs, const int32_t *row_word, const int32_t *row_nw,
                 int32_t rows, int64_t per, uint16_t *counts) {
    int64_t total = 0;
    for (int64_t d = 0; d < dirs; d++) {
        const uint32_t *w = words + d * per;
        for (int32_t r = 0; r < rows; r++) {
            int32_t c = 0;
            for (int32_t q = 0; q < row_nw[r]; q++) c += __builtin_popcount(w[row_word[r] + q]);
            counts[d * rows + r] = (uint16_t)c;
            total += c;
        }
    }
    return total;
}

/* The zigzag residuals of every set bit of directions [0, dirs), in order, into res (sized by vc_count);
 * returns the bits written, -1 when the rolling buffers cannot be had. */
int64_t vc_encode(const uint32_t *words, int64_t dirs, const int32_t *row_word, const int32_t *row_nw,
                  const int32_t *row_w0, int32_t rows, int64_t per, uint16_t *res) {
    int32_t cap = max_bits(row_nw, rows);
    int32_t *buf = (int32_t *)malloc(4 * (size_t)cap * sizeof(int32_t));
    if (!buf) return -1;
    int32_t *pdepth = buf, *pstep = buf + cap, *cdepth = buf + 2 * cap, *cstep = buf + 3 * cap;
    int64_t i = 0;
    for (int64_t d = 0; d < dirs; d++) {
        const uint32_t *w = words + d * per;
        int32_t c1 = 0, c2 = 0;            /* bits of the row before, and of the one before that */
        for (int32_t r = 0; r < rows; r++) {
            int32_t k = 0;
            for (int32_t q = 0; q < row_nw[r]; q++) {
                uint32_t x = w[row_word[r] + q];
                while (x) {
                    int32_t l = 32 * (row_w0[r] + q) + __builtin_ctz(x);
                    int32_t d1 = l, d2 = l;
                    if (k < c1) {
                        d1 = l - pdepth[k];
                        d2 = d1;
                        if (k < c2) d2 = d1 - pstep[k];
                    }
                    cdepth[k] = l;
                    cstep[k] = d1;
                    res[i++] = (uint16_t)(((uint32_t)d2 << 1) ^ (uint32_t)(d2 >> 31));
                    k++;
                    x &= x - 1;
                }
            }
            next_row(&pdepth, &pstep, &cdepth, &cstep, &c1, &c2, k);
        }
    }
    free(buf);
    return i;
}

/* Set the bits of words (directions [0, dirs), zero) from their counts and zigzag residuals (byte planes:
 * c_hi / r_hi NULL for one byte a value). Returns 0, or 1 when the data do not fit the rows (damaged), 2
 * when the rolling buffers cannot be had. */
int vc_decode(const uint8_t *c_lo, const uint8_t *c_hi, const uint8_t *r_lo, const uint8_t *r_hi, int64_t dirs,
              const int32_t *row_word, const int32_t *row_nw, const int32_t *row_w0, int32_t rows, int64_t per,
              uint32_t *words) {
    int32_t cap = max_bits(row_nw, rows);
    int32_t *buf = (int32_t *)malloc(4 * (size_t)cap * sizeof(int32_t));
    if (!buf) return 2;
    int32_t *pdepth = buf, *pstep = buf + cap, *cdepth = buf + 2 * cap, *cstep = buf + 3 * cap;
    int64_t i = 0;
    int bad = 0;
    for (int64_t d = 0; d < dirs && !bad; d++) {
        uint32_t *w = words + d * per;
        int32_t c1 = 0, c2 = 0;
        for (int32_t r = 0; r < rows; r++) {
            int32_t c = (int32_t)get16(c_lo, c_hi, d * rows + r);
            if (c > 32 * row_nw[r]) { bad = 1; break; }
            for (int32_t k = 0; k < c; k++, i++) {
                uint32_t z = get16(r_lo, r_hi, i);
                int32_t v = (int32_t)(z >> 1) ^ -(int32_t)(z & 1);
                int32_t l = v, d1 = v;
                if (k < c1) {
                    if (k < c2) d1 = v + pstep[k];
                    l = pdepth[k] + d1;
                }
                cdepth[k] = l;
                cstep[k] = d1;
                int32_t q = l / 32 - row_w0[r];
                if (l < 0 || q < 0 || q >= row_nw[r]) { bad = 1; break; }
                w[row_word[r] + q] |= 1u << (l % 32);
            }
            if (bad) break;
            next_row(&pdepth, &pstep, &cdepth, &cstep, &c1, &c2, c);
        }
    }
    free(buf);
    return bad;
}

/* an importable module, so that pip builds and installs it (its functions are called through ctypes) */
static struct PyModuleDef vc_module = {PyModuleDef_HEAD_INIT, "_voxcodec", "voxel array depth coding (ctypes)", -1, NULL};
PyMODINIT_FUNC PyInit__voxcodec(void) { return PyModule_Create(&vc_module); }
