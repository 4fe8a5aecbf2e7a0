/* The weighted gradient moments of coverage/corner_refine.py's windows, one pass over each window's pixels.
 *
 * `refine_on_checker_edges` solves cornerSubPix's equations on the gradients at the window's own
 * pixels, weighted by a gaussian in board units with the markers' span masked out. In NumPy that
 * is ~20 whole-array passes over every window's pixels (~50k at 720p: the board position of each
 * pixel through the corner's quadratic map, the mask, the weight, the gradient products), ~1 ms a
 * frame for every frame that becomes a view. Here each pixel is visited once, ~5x cheaper.
 *
 * The numbers are NumPy's: the same float32 arithmetic in the same order (the build turns off
 * fused multiply-adds), the Sobel (ksize 3, scale 1/8) of the uint8 pixels, which is exact in
 * float32, zero where the 3x3 neighbourhood leaves the image (NumPy zeroes the outermost rows and
 * columns and pads outside with zeros); only expf and the order of the float64 sums may differ,
 * by ~1e-7 of a moment. Optional: where it is not built, corner_refine.py runs the NumPy path.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

/* moments(image, height, width, half, centres, rel0, coef, inv_scale, edges, weight_scale, out)
 *   image       C-contiguous (height, width) uint8
 *   centres     (N, 2) int64: each window's centre pixel (x, y)
 *   rel0        (N, 2) float32: centre - corner estimate (the window pixel's offset is added to it)
 *   coef        (N, 2, 6) float32: u and v = c0 + c1 x + c2 y + c3 x^2 + c4 xy + c5 y^2 of (x, y) = rel * inv_scale
 *   inv_scale   (N,) float32
 *   edges       (N, 2) float64: |u| above edges[0] and |v| above edges[1] is inside a marker's span
 *   weight_scale float32: the gaussian's exponent factor, w = exp((u^2 + v^2) * weight_scale)
 *   out         (N, 5) float64, written: sum w gx^2, sum w gx gy, sum w gy^2, and the right-hand sides
 *               sum (w gx^2 rx + w gx gy ry), sum (w gx gy rx + w gy^2 ry)
 * The GIL is released. */
static PyObject *moments(PyObject *self, PyObject *args) {
    Py_buffer img, cen, rel, cof, inv, edg, out;
    Py_ssize_t height, width, half;
    float weight_scale;
    if (!PyArg_ParseTuple(args, "y*nnny*y*y*y*y*fw*", &img, &height, &width, &half, &cen, &rel, &cof, &inv, &edg,
                          &weight_scale, &out))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = cen.len / (Py_ssize_t)(2 * sizeof(int64_t));
    if (height < 3 || width < 3 || half < 0 || img.len < height * width || rel.len < n * 2 * (Py_ssize_t)sizeof(float) ||
        cof.len < n * 12 * (Py_ssize_t)sizeof(float) || inv.len < n * (Py_ssize_t)sizeof(float) ||
        edg.len < n * 2 * (Py_ssize_t)sizeof(double) || out.len < n * 5 * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "moments: buffer sizes do not match the corner count");
        goto done;
    }
    const uint8_t *pixels = (const uint8_t *)img.buf;
    const int64_t *centres = (const int64_t *)cen.buf;
    const float *rel0 = (const float *)rel.buf, *coef = (const float *)cof.buf, *inv_scale = (const float *)inv.buf;
    const double *edges = (const double *)edg.buf;
    double *sums = (double *)out.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) {
        const int64_t cx = centres[2 * i], cy = centres[2 * i + 1];
        const float *cu = coef + 12 * i, *cv = cu + 6;
        const float s = inv_scale[i];
        const double edge_u = edges[2 * i], edge_v = edges[2 * i + 1];
        double a = 0.0, b = 0.0, c = 0.0, r1 = 0.0, r2 = 0.0;
        for (Py_ssize_t dy = -half; dy <= half; dy++) {
            const int64_t y = cy + dy;
            if (y < 1 || y > height - 2) continue;  /* no gradient: it weighs nothing */
            const float ry = rel0[2 * i + 1] + (float)dy;
            const uint8_t *up = pixels + (y - 1) * width, *row = up + width, *down = row + width;
            for (Py_ssize_t dx = -half; dx <= half; dx++) {
                const int64_t x = cx + dx;
                if (x < 1 || x > width - 2) continue;
                const float rx = rel0[2 * i] + (float)dx;
                const float px = rx * s, py = ry * s;
                const float xx = px * px, xy = px * py, yy = py * py;
                /* NumPy's order: c0 + (((((0 + c1 x) + c2 y) + c3 x^2) + c4 xy) + c5 y^2) */
                const float u = cu[0] + (((((0.0f + cu[1] * px) + cu[2] * py) + cu[3] * xx) + cu[4] * xy) + cu[5] * yy);
                const float v = cv[0] + (((((0.0f + cv[1] * px) + cv[2] * py) + cv[3] * xx) + cv[4] * xy) + cv[5] * yy);
                const float au = fabsf(u), av = fabsf(v);
                if (au > 0.5f || av > 0.5f) continue;  /* beyond half a square */
                if ((double)au > edge_u && (double)av > edge_v) continue;  /* in a marker's span */
                const float w = expf((u * u + v * v) * weight_scale);
                const float gx = (float)(((int)up[x + 1] - up[x - 1]) + 2 * ((int)row[x + 1] - row[x - 1]) +
                                         ((int)down[x + 1] - down[x - 1])) * 0.125f;
                const float gy = (float)(((int)down[x - 1] - up[x - 1]) + 2 * ((int)down[x] - up[x]) +
                                         ((int)down[x + 1] - up[x + 1])) * 0.125f;
                const float wgx = w * gx, wgy = w * gy;
                const float gxx = wgx * gx, gxy = wgx * gy, gyy = wgy * gy;
                a += gxx;
                b += gxy;
                c += gyy;
                r1 += gxx * rx + gxy * ry;
                r2 += gxy * rx + gyy * ry;
            }
        }
        sums[5 * i] = a;
        sums[5 * i + 1] = b;
        sums[5 * i + 2] = c;
        sums[5 * i + 3] = r1;
        sums[5 * i + 4] = r2;
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&img);
    PyBuffer_Release(&cen);
    PyBuffer_Release(&rel);
    PyBuffer_Release(&cof);
    PyBuffer_Release(&inv);
    PyBuffer_Release(&edg);
    PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"moments", moments, METH_VARARGS,
     "moments(image, height, width, half, centres, rel0, coef, inv_scale, edges, weight_scale, out): "
     "each window's weighted gradient moments (coverage/corner_refine.py)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_checker_edges", NULL, -1, methods};

PyMODINIT_FUNC PyInit__checker_edges(void) { return PyModule_Create(&module); }
