/* PNG row unfiltering (None, Sub, Up, Average, Paeth) for drivers/png_fast.py.
 *
 * The reconstruction rules are those of the PNG specification (section 9): each byte adds a
 * predictor from the reconstructed byte one pixel to its left (a), the byte above (b) and the
 * byte above-left (c), mod 256. Every rule but Up depends on the byte just reconstructed, so it
 * cannot be done in whole-array NumPy steps; in C it is one pass over the rows (~0.3 ms for a
 * 720p grey Sub frame against ~1.2 ms for NumPy's doubling prefix sums; Paeth ~2 ms against
 * libpng's ~3.5). Optional: where it is not built, png_fast falls back on NumPy and libpng.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdlib.h>
#include <string.h>

/* The predictor of the three neighbours closest to a + b - c, ties in the order a, b, c (PNG
 * specification 9.4), in libpng's branch-light form: pa = |b - c|, pb = |a - c|, pc = |a + b - 2c|. */
static inline unsigned char paeth(int a, int b, int c) {
    int p = b - c, q = a - c;
    int pa = abs(p), pb = abs(q), pc = abs(p + q);
    if (pb < pa) { pa = pb; a = b; }
    if (pc < pa) a = c;
    return (unsigned char)a;
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
