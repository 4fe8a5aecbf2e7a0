/* PNG row unfiltering (None, Sub, Up, Average, Paeth) for drivers/png_fast.py.
 *
 * The reconstruction rules are those of the PNG specification (section 9): each byte adds a
 * predictor from the reconstructed byte one pixel to its left (a), the byte above (b) and the
 * byte above-left (c), mod 256. Every rule but Up depends on the byte just reconstructed, so it
 * cannot be done in whole-array NumPy steps; in C it is one pass over the rows (0.1 ms for a
 * 720p grey Sub frame, in SSE2 blocks, against ~1.2 ms for NumPy's doubling prefix sums and 0.3
 * byte by byte). libpng's adaptive rows (a 720p grey frame written by OpenCV at compression 6:
 * 525 Paeth, 189 Average) take 0.9 ms with the branch-free Paeth predictor and grey rows undone
 * two at a time, 2.7 ms before either.
 * Optional: where it is not built, png_fast falls back on NumPy and libpng.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

/* The predictor of the three neighbours closest to a + b - c, ties in the order a, b, c (PNG
 * specification 9.4), in stb_image's branch-free form: with lo, hi the smaller and larger of a and
 * b, and t = 3c - a - b, the nearest is lo when hi <= t, hi when t <= lo, else c. The predictor
 * is data-dependent, so branches on it were mispredicted about as often as taken; this form
 * compiles to compare-and-selects. */
static inline unsigned char paeth(int a, int b, int c) {
    int threshold = 3 * c - (a + b);
    int lo = a < b ? a : b, hi = a < b ? b : a;
    int nearest = hi <= threshold ? lo : c;
    return (unsigned char)(threshold <= lo ? hi : nearest);
}

/* A grey Sub row: each byte adds the one reconstructed to its left, a running sum mod 256. Byte by
 * byte the loop is bound by its one store a byte (0.29 ms a 720p frame, warm), and OpenCV's
 * imwrite filters every row Sub. With SSE2, 16 bytes at a time: their own running sum in four
 * shift-and-add steps, then the carry from the bytes before (the previous block's last byte,
 * broadcast) added; the carry's chain is one addition a block, the rest runs ahead of it.
 * Integer additions mod 256 in either order: the same bytes. */
static void unfilter_sub_row_grey(const unsigned char *restrict f, unsigned char *restrict cur, Py_ssize_t stride) {
    Py_ssize_t x = 0;
    unsigned char left = 0;
#if defined(__SSE2__)
    __m128i carry = _mm_setzero_si128();
    for (; x + 16 <= stride; x += 16) {
        __m128i v = _mm_loadu_si128((const __m128i *)(f + x));
        v = _mm_add_epi8(v, _mm_slli_si128(v, 1));
        v = _mm_add_epi8(v, _mm_slli_si128(v, 2));
        v = _mm_add_epi8(v, _mm_slli_si128(v, 4));
        v = _mm_add_epi8(v, _mm_slli_si128(v, 8));  /* byte i: the sum of bytes 0..i of the block */
        __m128i last = _mm_srli_si128(v, 15);        /* the block's total, broadcast to all 16 bytes: */
        last = _mm_unpacklo_epi8(last, last);
        last = _mm_unpacklo_epi16(last, last);
        last = _mm_shuffle_epi32(last, 0);
        _mm_storeu_si128((__m128i *)(cur + x), _mm_add_epi8(v, carry));
        carry = _mm_add_epi8(carry, last);
    }
    if (x > 0) left = cur[x - 1];
#endif
    for (; x < stride; x++) cur[x] = left = (unsigned char)(f[x] + left);
}

/* One row. Sub, Average and Paeth carry the byte just reconstructed, `bpp` bytes back: it is kept
 * in a register (`left`) rather than read back from `cur`, since a store-to-load round trip per
 * byte made the Sub loop no faster than NumPy. `BPP` is a constant at each call site, so the
 * compiler unrolls the channel loop. `AT(k)` is where channel k of a pixel is stored in `cur` (and
 * so read back from `up`, the row above as stored): k for grey, 2 - k to store RGB as OpenCV's
 * BGR in the same pass (a separate swap cost 0.2 ms a 720p frame). Returns 0, or -1 for an
 * unknown filter byte. */
#define AT_SAME(k) (k)
#define AT_REVERSED(k) (2 - (k))
#define ROW_FUNCTION(NAME, BPP, AT)                                                                \
static int NAME(unsigned char filter, const unsigned char *restrict f, const unsigned char *restrict up, \
                unsigned char *restrict cur, Py_ssize_t stride) {                                  \
    unsigned char left[BPP] = {0}, upleft[BPP] = {0};                                              \
    Py_ssize_t x;                                                                                  \
    int k;                                                                                         \
    if (up == NULL && (filter == 2 || filter == 4)) /* first row, b = c = 0: Up adds nothing, */   \
        filter = filter == 2 ? 0 : 1;                /* Paeth picks a, i.e. Sub */                 \
    switch (filter) {                                                                              \
    case 0:                                                                                        \
        for (x = 0; x < stride; x += BPP)                                                          \
            for (k = 0; k < BPP; k++) cur[x + AT(k)] = f[x + k];                                   \
        return 0;                                                                                  \
    case 1:                                                                                        \
        if (BPP == 1) { /* grey: 16 bytes at a time where SSE2 is there */                        \
            unfilter_sub_row_grey(f, cur, stride);                                                 \
            return 0;                                                                              \
        }                                                                                          \
        for (x = 0; x < stride; x += BPP)                                                          \
            for (k = 0; k < BPP; k++) cur[x + AT(k)] = left[k] = (unsigned char)(f[x + k] + left[k]); \
        return 0;                                                                                  \
    case 2:                                                                                        \
        for (x = 0; x < stride; x += BPP)                                                          \
            for (k = 0; k < BPP; k++) cur[x + AT(k)] = (unsigned char)(f[x + k] + up[x + AT(k)]);   \
        return 0;                                                                                  \
    case 3:                                                                                        \
        for (x = 0; x < stride; x += BPP)                                                          \
            for (k = 0; k < BPP; k++)                                                              \
                cur[x + AT(k)] = left[k] =                                                         \
                    (unsigned char)(f[x + k] + ((left[k] + (up ? up[x + AT(k)] : 0)) >> 1));       \
        return 0;                                                                                  \
    case 4:                                                                                        \
        for (x = 0; x < stride; x += BPP)                                                          \
            for (k = 0; k < BPP; k++) {                                                            \
                unsigned char b = up[x + AT(k)];                                                   \
                cur[x + AT(k)] = left[k] = (unsigned char)(f[x + k] + paeth(left[k], b, upleft[k])); \
                upleft[k] = b;                                                                     \
            }                                                                                      \
        return 0;                                                                                  \
    default:                                                                                       \
        return -1;                                                                                 \
    }                                                                                              \
}

ROW_FUNCTION(unfilter_row_grey, 1, AT_SAME)
ROW_FUNCTION(unfilter_row_rgb_to_bgr, 3, AT_REVERSED)

/* Two consecutive grey rows, each filtered Average (3) or Paeth (4), in one pass. A grey row's
 * bytes form one chain, each waiting for the byte just reconstructed to its left (a Paeth byte:
 * an add, two compares and three selects in a row), which leaves most of the CPU idle; the second
 * row needs only the first's bytes above and above-left of it, so the two chains run side by
 * side (1.5 -> 0.9 ms on an adaptively filtered 720p frame). libpng's adaptive filtering (PIL,
 * imageio, OpenCV given a compression level) makes most rows Paeth or Average. The filters are
 * loop-invariant, so -O3 unswitches the loop into one specialised loop per pair. RGB rows already
 * hold three chains (one a channel). */
static void unfilter_pair_grey(unsigned char filter0, unsigned char filter1, const unsigned char *restrict f0,
                               const unsigned char *restrict f1, const unsigned char *restrict up,
                               unsigned char *restrict cur0, unsigned char *restrict cur1, Py_ssize_t stride) {
    const int paeth0 = filter0 == 4, paeth1 = filter1 == 4;
    unsigned char left0 = 0, upleft0 = 0, left1 = 0, upleft1 = 0;  /* a and c of each row (0 left of the first byte) */
    for (Py_ssize_t x = 0; x < stride; x++) {
        unsigned char b0 = up[x];
        unsigned char v0 = (unsigned char)(f0[x] + (paeth0 ? paeth(left0, b0, upleft0) : (left0 + b0) >> 1));
        cur0[x] = v0;
        unsigned char v1 = (unsigned char)(f1[x] + (paeth1 ? paeth(left1, v0, upleft1) : (left1 + v0) >> 1));
        cur1[x] = v1;
        left0 = v0, upleft0 = b0, left1 = v1, upleft1 = v0;
    }
}

static int pairs_with_next(unsigned char filter) { return filter == 3 || filter == 4; }

/* unfilter(rows, height, stride, bpp, out): `rows` holds `height` rows of 1 + `stride` bytes (the
 * filter byte first); `out` (writable, height * stride bytes) receives the reconstructed pixels,
 * grey (bpp 1) as they are, RGB (bpp 3) in OpenCV's BGR order. Returns None, or raises
 * ValueError for an unknown filter byte or sizes that do not match. The GIL is released while it
 * runs. */
static PyObject *unfilter(PyObject *self, PyObject *args) {
    Py_buffer in, out;
    Py_ssize_t height, stride, bpp;
    if (!PyArg_ParseTuple(args, "y*nnnw*", &in, &height, &stride, &bpp, &out)) return NULL;
    PyObject *result = NULL;
    if (height < 0 || stride <= 0 || (bpp != 1 && bpp != 3) || stride % bpp != 0 ||
        in.len < height * (stride + 1) || out.len < height * stride) {
        PyErr_SetString(PyExc_ValueError, "unfilter: buffer sizes do not match height, stride and bpp (1 or 3)");
        goto done;
    }
    const unsigned char *src = (const unsigned char *)in.buf;
    unsigned char *dst = (unsigned char *)out.buf;
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t y = 0; y < height && !bad; y++) {
        const unsigned char *row = src + y * (stride + 1);
        const unsigned char *up = y > 0 ? dst + (y - 1) * stride : NULL;
        unsigned char *cur = dst + y * stride;
        if (bpp == 1 && up != NULL && y + 1 < height && pairs_with_next(row[0]) && pairs_with_next(row[stride + 1])) {
            unfilter_pair_grey(row[0], row[stride + 1], row + 1, row + stride + 2, up, cur, cur + stride, stride);
            y++;  /* the next row is done too */
            continue;
        }
        bad = bpp == 1 ? unfilter_row_grey(row[0], row + 1, up, cur, stride)
                       : unfilter_row_rgb_to_bgr(row[0], row + 1, up, cur, stride);
    }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "unfilter: a row has an unknown PNG filter type (damaged file)");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&in);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"unfilter", unfilter, METH_VARARGS, "Undo PNG row filters: unfilter(rows, height, stride, bpp, out); RGB comes out as BGR."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_png_unfilter", NULL, -1, methods};

PyMODINIT_FUNC PyInit__png_unfilter(void) { return PyModule_Create(&module); }
