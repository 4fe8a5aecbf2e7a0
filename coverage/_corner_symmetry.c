/* Gauss-Newton on the point-symmetry cost of coverage/corner_symmetry.py, every corner of a frame in one call.
 *
 * For each corner: sum over its sample pairs of w (I(c + dp) - I(c + dm))^2, I the image
 * interpolated bilinearly, minimised over the corner c (2 unknowns) from `starts`. Each step
 * solves the 2 x 2 normal equations with the exact derivative of the interpolation, and stops once
 * a step is under `tol` px. In NumPy the same loop is ~40 whole-array passes an iteration over
 * ~25k pairs a 720p frame; here each pair is visited once an iteration.
 *
 * The numbers are NumPy's (`_fit_in_numpy`): the same float64 arithmetic in the same order (the
 * build turns off fused multiply-adds); only the order of the sums differs (~1e-13 of a step).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

/* One bilinear sample of `pixels` at (x, y) with its derivatives; 0 when the 2x2 cell leaves the image. */
static int sample(const uint8_t *pixels, Py_ssize_t height, Py_ssize_t width, double x, double y,
                  double *value, double *gx, double *gy) {
    const double fx0 = floor(x), fy0 = floor(y);
    if (!(fx0 >= 0.0 && fy0 >= 0.0 && fx0 < (double)(width - 1) && fy0 < (double)(height - 1))) return 0;
    const Py_ssize_t x0 = (Py_ssize_t)fx0, y0 = (Py_ssize_t)fy0;
    const double fx = x - fx0, fy = y - fy0;
    const uint8_t *row = pixels + y0 * width + x0;
    const double a = row[0], b = row[1], c = row[width], d = row[width + 1];
    /* NumPy's order (`_bilinear`) */
    *value = ((a * (1.0 - fx)) * (1.0 - fy) + (b * fx) * (1.0 - fy)) + ((c * (1.0 - fx)) * fy + (d * fx) * fy);
    *gx = (1.0 - fy) * (b - a) + fy * (d - c);
    *gy = (1.0 - fx) * (c - a) + fx * (d - b);
    return 1;
}

/* fit(image, height, width, n, m, starts, dp, dm, weights, max_iter, tol, out, iterations)
 *   image       C-contiguous (height, width) uint8
 *   starts      (n, 2) float64: each corner's start (x, y)
 *   dp, dm      (n, m, 2) float64: each pair's two offsets from the corner, px
 *   weights     (n, m) float64: 0 for padding
 *   out         (n, 2) float64, written: the corners
 *   iterations  (n,) int32, written: steps taken until one was under `tol`; -1 where the normal
 *               equations were singular or no step got under `tol` in `max_iter`
 * The GIL is released. */
static PyObject *fit(PyObject *self, PyObject *args) {
    Py_buffer img, sta, dpb, dmb, wb, out, itb;
    Py_ssize_t height, width, n, m, max_iter;
    double tol;
    if (!PyArg_ParseTuple(args, "y*nnnny*y*y*y*ndw*w*", &img, &height, &width, &n, &m, &sta, &dpb, &dmb, &wb,
                          &max_iter, &tol, &out, &itb))
        return NULL;
    PyObject *result = NULL;
    if (height < 2 || width < 2 || n < 0 || m < 0 || img.len < height * width ||
        sta.len < n * 2 * (Py_ssize_t)sizeof(double) || dpb.len < n * m * 2 * (Py_ssize_t)sizeof(double) ||
        dmb.len < n * m * 2 * (Py_ssize_t)sizeof(double) || wb.len < n * m * (Py_ssize_t)sizeof(double) ||
        out.len < n * 2 * (Py_ssize_t)sizeof(double) || itb.len < n * (Py_ssize_t)sizeof(int32_t)) {
        PyErr_SetString(PyExc_ValueError, "fit: buffer sizes do not match the corner and pair counts");
        goto done;
    }
    const uint8_t *pixels = (const uint8_t *)img.buf;
    const double *starts = (const double *)sta.buf, *dp = (const double *)dpb.buf, *dm = (const double *)dmb.buf;
    const double *weights = (const double *)wb.buf;
    double *corners = (double *)out.buf;
    int32_t *iterations = (int32_t *)itb.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) {
        double cx = starts[2 * i], cy = starts[2 * i + 1];
        int32_t done_after = -1;
        for (Py_ssize_t it = 1; it <= max_iter; it++) {
            double sxx = 0.0, sxy = 0.0, syy = 0.0, sxr = 0.0, syr = 0.0;
            for (Py_ssize_t k = 0; k < m; k++) {
                const double w = weights[i * m + k];
                if (w == 0.0) continue;
                const double *p = dp + 2 * (i * m + k), *q = dm + 2 * (i * m + k);
                double vp, gxp, gyp, vm, gxm, gym;
                if (!sample(pixels, height, width, cx + p[0], cy + p[1], &vp, &gxp, &gyp)) continue;
                if (!sample(pixels, height, width, cx + q[0], cy + q[1], &vm, &gxm, &gym)) continue;
                const double r = vp - vm, jx = gxp - gxm, jy = gyp - gym;
                const double wjx = w * jx, wjy = w * jy;
                sxx += wjx * jx;
                sxy += wjx * jy;
                syy += wjy * jy;
                sxr += wjx * r;
                syr += wjy * r;
            }
            const double det = sxx * syy - sxy * sxy;
            if (!(det > 1e-12 * (sxx + syy) * (sxx + syy))) break;
            const double stepx = -(syy * sxr - sxy * syr) / det, stepy = -(sxx * syr - sxy * sxr) / det;
            cx += stepx;
            cy += stepy;
            if (sqrt(stepx * stepx + stepy * stepy) < tol) {
                done_after = (int32_t)it;
                break;
            }
        }
        corners[2 * i] = cx;
        corners[2 * i + 1] = cy;
        iterations[i] = done_after;
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&img);
    PyBuffer_Release(&sta);
    PyBuffer_Release(&dpb);
    PyBuffer_Release(&dmb);
    PyBuffer_Release(&wb);
    PyBuffer_Release(&out);
    PyBuffer_Release(&itb);
    return result;
}

static PyMethodDef methods[] = {
    {"fit", fit, METH_VARARGS,
     "fit(image, height, width, n, m, starts, dp, dm, weights, max_iter, tol, out, iterations): "
     "each corner fitted to its pattern's point symmetry (coverage/corner_symmetry.py)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_corner_symmetry", NULL, -1, methods};

PyMODINIT_FUNC PyInit__corner_symmetry(void) { return PyModule_Create(&module); }
