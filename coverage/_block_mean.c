/* Means of whole cells of a grey image, rounded exactly as OpenCV's INTER_AREA resize rounds them,
 * for app/scan.py's thumbnails.
 *
 * A replay thumbnails every decoded frame (80 x 45 cells, 16 x 16 px at 720p) to see where the
 * board held still. cv2.resize with INTER_AREA takes its generic path for an integer factor other
 * than 2: per output pixel, one sum over the cell's pixels read through an offset table, ~0.25 ms
 * a 720p frame. Here the rows of a band of cells are added into per-column sums (uint16, which
 * vectorises: 16 rows of 255 fit) and those then into the cells, ~0.05 ms. The rounding is
 * OpenCV's own (resizeAreaFast_Invoker): sum * (1.f / area) in single precision, rounded to the
 * nearest integer, ties to even (cvRound), so the thumbnails are the same numbers bit for bit.
 * Optional: where it is not built, scan.py calls cv2.resize.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* The column sums fit uint16 for cells up to this many rows (257 * 255 = 65535). */
#define MAX_CELL_ROWS 257

/* block_means(image, height, width, cell_h, cell_w, out): `image` a C-contiguous (height, width)
 * uint8 buffer whose sides are whole multiples of the cell's; `out` a writable float32 buffer of
 * (height / cell_h) * (width / cell_w) values, each cell's rounded mean. The GIL is released. */
static PyObject *block_means(PyObject *self, PyObject *args) {
    Py_buffer in, out;
    Py_ssize_t height, width, cell_h, cell_w;
    if (!PyArg_ParseTuple(args, "y*nnnnw*", &in, &height, &width, &cell_h, &cell_w, &out)) return NULL;
    PyObject *result = NULL;
    uint16_t *columns = NULL;
    if (height <= 0 || width <= 0 || cell_h <= 0 || cell_w <= 0 || cell_h > MAX_CELL_ROWS ||
        height % cell_h != 0 || width % cell_w != 0 || in.len < height * width ||
        out.len < (Py_ssize_t)sizeof(float) * (height / cell_h) * (width / cell_w)) {
        PyErr_SetString(PyExc_ValueError, "block_means: sizes do not match (the image's sides must be whole multiples "
                                          "of the cell's, at most 257 rows a cell)");
        goto done;
    }
    columns = malloc(sizeof(uint16_t) * (size_t)width);
    if (columns == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    const uint8_t *src = (const uint8_t *)in.buf;
    float *dst = (float *)out.buf;
    const Py_ssize_t cells_x = width / cell_w, cells_y = height / cell_h;
    const float scale = 1.f / (float)(cell_h * cell_w);  /* OpenCV's `float scale = 1.f/(area)` */
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t cy = 0; cy < cells_y; cy++) {
        const uint8_t *band = src + cy * cell_h * width;
        for (Py_ssize_t x = 0; x < width; x++) columns[x] = band[x];
        for (Py_ssize_t r = 1; r < cell_h; r++) {
            const uint8_t *restrict row = band + r * width;
            uint16_t *restrict sums = columns;
            for (Py_ssize_t x = 0; x < width; x++) sums[x] = (uint16_t)(sums[x] + row[x]);
        }
        for (Py_ssize_t cx = 0; cx < cells_x; cx++) {
            const uint16_t *cell = columns + cx * cell_w;
            int32_t sum = 0;
            for (Py_ssize_t k = 0; k < cell_w; k++) sum += cell[k];
            dst[cy * cells_x + cx] = nearbyintf((float)sum * scale);  /* ties to even, as cvRound */
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    free(columns);
    PyBuffer_Release(&in);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"block_means", block_means, METH_VARARGS,
     "block_means(image, height, width, cell_h, cell_w, out): each whole cell's mean, rounded as cv2.resize INTER_AREA."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_block_mean", NULL, -1, methods};

PyMODINIT_FUNC PyInit__block_mean(void) { return PyModule_Create(&module); }
