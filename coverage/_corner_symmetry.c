/* Gauss-Newton on the point-symmetry cost of coverage/corner_symmetry.py, every corner of a frame in one call.
 *
 * For each corner: sum over its sample pairs of w (I(c + d) - I(c - d))^2, I the image
 * interpolated bilinearly, minimised over the corner c (2 unknowns) from `starts`. Each step
 * solves the 2 x 2 normal equations with the exact derivative of the interpolation, and stops once
 * a step is under `tol` px. In NumPy the same loop is ~40 whole-array passes an iteration over
 * ~25k pairs a 720p frame; here each pair is visited once an iteration.
 *
 * The offsets d and their weights are made here too, per corner, from its board-to-image map
 * (`_pairs` in NumPy: ~0.7 ms a 720p frame there for (M, P, 2) arrays that this makes in a
 * corner's own scratch row).
 *
 * The numbers are NumPy's (`_pairs` and `_fit_in_numpy`): the same float64 arithmetic in the same
 * order (the build turns off fused multiply-adds); only the order of the fit's sums differs (~1e-13
 * of a step).
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

/* One corner's sample offsets from its map, as `_offsets_under` and `_pairs` make them (same order of
 * operations): board offsets (u, v) = template * step, their image offsets through the homography
 * plus the corner's quadratic correction, and weight 1 where the sample lies within `half` and in a
 * marker-free square (`left` for u < 0, `right` otherwise) or within `border` of its square's edge.
 * Returns how many samples count. */
static Py_ssize_t offsets(const double *h, double gx, double gy, const double *corr, double step, double half,
                          double border, int left, int right, const double *tmpl, const double *radius, Py_ssize_t p,
                          double *d, double *w) {
    const double w0 = h[6] * gx + h[7] * gy + h[8];
    const double x0 = (h[0] * gx + h[1] * gy + h[2]) / w0, y0 = (h[3] * gx + h[4] * gy + h[5]) / w0;
    const double *cx = corr, *cy = corr + 5;
    Py_ssize_t counted = 0;
    for (Py_ssize_t k = 0; k < p; k++) {
        const double tu = tmpl[2 * k], tv = tmpl[2 * k + 1];
        const double u = tu * step, v = tv * step;
        const int free_square = tu < 0.0 ? left : right;
        const double au = fabs(u);
        const int in_border = (au < v ? au : v) <= border;
        const int within = radius[k] * step <= half;
        w[k] = (within && (free_square || in_border)) ? 1.0 : 0.0;
        counted += w[k] != 0.0;
        const double ax = gx + u, ay = gy + v;
        const double ww = h[6] * ax + h[7] * ay + h[8];
        double dx = (h[0] * ax + h[1] * ay + h[2]) / ww - x0;
        double dy = (h[3] * ax + h[4] * ay + h[5]) / ww - y0;
        dx = dx + ((((cx[0] * u + cx[1] * v) + (cx[2] * u) * u) + (cx[3] * u) * v) + (cx[4] * v) * v);
        dy = dy + ((((cy[0] * u + cy[1] * v) + (cy[2] * u) * u) + (cy[3] * u) * v) + (cy[4] * v) * v);
        d[2 * k] = dx;
        d[2 * k + 1] = dy;
    }
    return counted;
}

/* fit(image, height, width, n, p, starts, homography, board, correction, step, half, border, left, right,
 *     template, radius, min_pairs, max_iter, tol, out, iterations)
 *   image       C-contiguous (height, width) uint8
 *   starts      (n, 2) float64: each corner's start (x, y)
 *   homography  (3, 3) float64: the frame's board (squares) -> image map
 *   board       (n, 2) float64: each corner on the board, in squares
 *   correction  (n, 2, 5) float64: each corner's quadratic correction (x, y rows; u, v, u^2, uv, v^2)
 *   step, half, border  (n,) float64: sample step, window's half-width and marker-free border, in squares
 *   left, right (n,) float64: 1 where the square left / right of the corner (upper row) holds no marker
 *   template    (p, 2) float64: sample grid in steps (upper half-plane); radius (p,) its distances
 *   out         (n, 2) float64, written: the corners
 *   iterations  (n,) int32, written: steps taken until one was under `tol`; 0 where fewer than
 *               `min_pairs` samples count (not fitted); -1 where the normal equations were
 *               singular or no step got under `tol` in `max_iter`
 * The GIL is released. */
static PyObject *fit(PyObject *self, PyObject *args) {
    Py_buffer img, sta, hb, bb, cb, stb, hab, bob, lb, rb, tb, radb, out, itb;
    Py_ssize_t height, width, n, p, min_pairs, max_iter;
    double tol;
    if (!PyArg_ParseTuple(args, "y*nnnny*y*y*y*y*y*y*y*y*y*y*nndw*w*", &img, &height, &width, &n, &p, &sta, &hb, &bb,
                          &cb, &stb, &hab, &bob, &lb, &rb, &tb, &radb, &min_pairs, &max_iter, &tol, &out, &itb))
        return NULL;
    PyObject *result = NULL;
    double *scratch = NULL;
    const Py_ssize_t nd = n * (Py_ssize_t)sizeof(double);
    if (height < 2 || width < 2 || n < 0 || p < 0 || img.len < height * width || sta.len < 2 * nd ||
        hb.len < 9 * (Py_ssize_t)sizeof(double) || bb.len < 2 * nd || cb.len < 10 * nd || stb.len < nd ||
        hab.len < nd || bob.len < nd || lb.len < nd || rb.len < nd || tb.len < 2 * p * (Py_ssize_t)sizeof(double) ||
        radb.len < p * (Py_ssize_t)sizeof(double) || out.len < 2 * nd || itb.len < n * (Py_ssize_t)sizeof(int32_t)) {
        PyErr_SetString(PyExc_ValueError, "fit: buffer sizes do not match the corner and sample counts");
        goto done;
    }
    scratch = (double *)PyMem_RawMalloc((size_t)(3 * (p > 0 ? p : 1)) * sizeof(double));
    if (scratch == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    const uint8_t *pixels = (const uint8_t *)img.buf;
    const double *starts = (const double *)sta.buf, *h = (const double *)hb.buf, *board = (const double *)bb.buf;
    const double *corr = (const double *)cb.buf, *step = (const double *)stb.buf, *half = (const double *)hab.buf;
    const double *border = (const double *)bob.buf, *left = (const double *)lb.buf, *right = (const double *)rb.buf;
    const double *tmpl = (const double *)tb.buf, *radius = (const double *)radb.buf;
    double *corners = (double *)out.buf, *d = scratch, *weights = scratch + 2 * p;
    int32_t *iterations = (int32_t *)itb.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) {
        double cx = starts[2 * i], cy = starts[2 * i + 1];
        corners[2 * i] = cx;
        corners[2 * i + 1] = cy;
        iterations[i] = 0;
        if (offsets(h, board[2 * i], board[2 * i + 1], corr + 10 * i, step[i], half[i], border[i], left[i] != 0.0,
                    right[i] != 0.0, tmpl, radius, p, d, weights) < min_pairs)
            continue;
        int32_t done_after = -1;
        for (Py_ssize_t it = 1; it <= max_iter; it++) {
            double sxx = 0.0, sxy = 0.0, syy = 0.0, sxr = 0.0, syr = 0.0;
            for (Py_ssize_t k = 0; k < p; k++) {
                const double w = weights[k];
                if (w == 0.0) continue;
                const double *q = d + 2 * k;
                double vp, gxp, gyp, vm, gxm, gym;
                if (!sample(pixels, height, width, cx + q[0], cy + q[1], &vp, &gxp, &gyp)) continue;
                if (!sample(pixels, height, width, cx + -q[0], cy + -q[1], &vm, &gxm, &gym)) continue;
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
    PyMem_RawFree(scratch);
    PyBuffer_Release(&img);
    PyBuffer_Release(&sta);
    PyBuffer_Release(&hb);
    PyBuffer_Release(&bb);
    PyBuffer_Release(&cb);
    PyBuffer_Release(&stb);
    PyBuffer_Release(&hab);
    PyBuffer_Release(&bob);
    PyBuffer_Release(&lb);
    PyBuffer_Release(&rb);
    PyBuffer_Release(&tb);
    PyBuffer_Release(&radb);
    PyBuffer_Release(&out);
    PyBuffer_Release(&itb);
    return result;
}

static PyMethodDef methods[] = {
    {"fit", fit, METH_VARARGS,
     "fit(image, height, width, n, p, starts, homography, board, correction, step, half, border, left, right, "
     "template, radius, min_pairs, max_iter, tol, out, iterations): "
     "each corner fitted to its pattern's point symmetry (coverage/corner_symmetry.py)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_corner_symmetry", NULL, -1, methods};

PyMODINIT_FUNC PyInit__corner_symmetry(void) { return PyModule_Create(&module); }
