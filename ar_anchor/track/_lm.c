/* The pose polish of ar_anchor.track.marker_poses.refine_poses, compiled: Levenberg-Marquardt on every
 * pose of a frame, each on its own points, through OpenCV's distortion model (12 coefficients: k1 k2 p1 p2
 * k3 k4 k5 k6 s1 s2 s3 s4). The same steps, acceptance and stopping rules as the numpy version in
 * marker_poses.py (see there); results agree with it to rounding.
 *
 * refine(rotations, tvecs, obj, img, n, fx, fy, cx, cy, dist12, steps, step_done, cost_done, lambda0,
 *        after, before)
 *   rotations (P*9, row-major 3x3, updated in place), tvecs (P*3, in place), obj (P*n*3), img (P*n*2),
 *   dist12 (12), after / before (P, written: RMS pixel error after / before; NaN when a point of the start
 *   pose is not in front of the camera). All buffers C-contiguous float64. Runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

/* Pixels (n, 2) of obj (n, 3) under (rot, t), and their derivatives (n, 2, 6) by the rotation step (left:
 * exp([w]x) R) and the translation. 0 if a point is not in front of the camera. */
static int project(const double *rot, const double *t, const double *obj, Py_ssize_t n, double fx, double fy,
                   double cx, double cy, const double *d, double *pix, double *jac) {
    const double k1 = d[0], k2 = d[1], p1 = d[2], p2 = d[3], k3 = d[4], k4 = d[5], k5 = d[6], k6 = d[7];
    const double s1 = d[8], s2 = d[9], s3 = d[10], s4 = d[11];
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *o = obj + 3 * i;
        double ax = rot[0] * o[0] + rot[1] * o[1] + rot[2] * o[2];
        double ay = rot[3] * o[0] + rot[4] * o[1] + rot[5] * o[2];
        double az = rot[6] * o[0] + rot[7] * o[1] + rot[8] * o[2];
        double X = ax + t[0], Y = ay + t[1], Z = az + t[2];
        if (!(Z > 1e-9)) return 0;
        double iz = 1.0 / Z, x = X * iz, y = Y * iz;
        double r2 = x * x + y * y, r4 = r2 * r2, r6 = r4 * r2;
        double num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6;
        double den = 1.0 / (1.0 + k4 * r2 + k5 * r4 + k6 * r6);
        double radial = num * den;
        double xy2 = 2.0 * x * y;
        double xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4;
        double yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2 + s3 * r2 + s4 * r4;
        pix[2 * i] = fx * xd + cx;
        pix[2 * i + 1] = fy * yd + cy;
        double dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4;
        double dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4;
        double drad = (dnum - radial * dden) * den; /* d radial / d r2 */
        double px = s1 + 2.0 * s2 * r2, py = s3 + 2.0 * s4 * r2;
        double dxd_dx = radial + x * drad * 2.0 * x + 2.0 * p1 * y + 6.0 * p2 * x + px * 2.0 * x;
        double dxd_dy = x * drad * 2.0 * y + 2.0 * p1 * x + 2.0 * p2 * y + px * 2.0 * y;
        double dyd_dx = y * drad * 2.0 * x + 2.0 * p1 * x + 2.0 * p2 * y + py * 2.0 * x;
        double dyd_dy = radial + y * drad * 2.0 * y + 6.0 * p1 * y + 2.0 * p2 * x + py * 2.0 * y;
        double du0 = fx * dxd_dx * iz, du1 = fx * dxd_dy * iz, du2 = -fx * (dxd_dx * x + dxd_dy * y) * iz;
        double dv0 = fy * dyd_dx * iz, dv1 = fy * dyd_dy * iz, dv2 = -fy * (dyd_dx * x + dyd_dy * y) * iz;
        double *ju = jac + 12 * i, *jv = ju + 6;
        /* by the rotation step: (R X) x d, row by row; by the translation: d */
        ju[0] = ay * du2 - az * du1;
        ju[1] = az * du0 - ax * du2;
        ju[2] = ax * du1 - ay * du0;
        ju[3] = du0;
        ju[4] = du1;
        ju[5] = du2;
        jv[0] = ay * dv2 - az * dv1;
        jv[1] = az * dv0 - ax * dv2;
        jv[2] = ax * dv1 - ay * dv0;
        jv[3] = dv0;
        jv[4] = dv1;
        jv[5] = dv2;
    }
    return 1;
}

static void exp_so3(const double *w, double *out) {
    double theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2], theta = sqrt(theta2), a, b;
    if (theta < 1e-6) {
        a = 1.0 - theta2 / 6.0;
        b = 0.5 - theta2 / 24.0;
    } else {
        a = sin(theta) / theta;
        b = (1.0 - cos(theta)) / theta2;
    }
    double x = w[0], y = w[1], z = w[2];
    out[0] = 1.0 - b * (y * y + z * z);
    out[1] = -a * z + b * x * y;
    out[2] = a * y + b * x * z;
    out[3] = a * z + b * x * y;
    out[4] = 1.0 - b * (x * x + z * z);
    out[5] = -a * x + b * y * z;
    out[6] = -a * y + b * x * z;
    out[7] = a * x + b * y * z;
    out[8] = 1.0 - b * (x * x + y * y);
}

/* x = -a^-1 b for a symmetric positive definite 6x6 a (Cholesky). 0 if a is not positive definite. */
static int solve6(const double *a, const double *b, double *x) {
    double low[36] = {0}, y[6];
    for (int i = 0; i < 6; i++) {
        for (int j = 0; j <= i; j++) {
            double s = a[6 * i + j];
            for (int q = 0; q < j; q++) s -= low[6 * i + q] * low[6 * j + q];
            if (i == j) {
                if (!(s > 0.0)) return 0;
                low[6 * i + i] = sqrt(s);
            } else {
                low[6 * i + j] = s / low[6 * j + j];
            }
        }
    }
    for (int i = 0; i < 6; i++) {
        double s = b[i];
        for (int q = 0; q < i; q++) s -= low[6 * i + q] * y[q];
        y[i] = s / low[6 * i + i];
    }
    for (int i = 5; i >= 0; i--) {
        double s = y[i];
        for (int q = i + 1; q < 6; q++) s -= low[6 * q + i] * x[q];
        x[i] = s / low[6 * i + i];
    }
    for (int i = 0; i < 6; i++) x[i] = -x[i];
    return 1;
}

static double cost_of(const double *pix, const double *img, Py_ssize_t n) {
    double cost = 0.0;
    for (Py_ssize_t k = 0; k < 2 * n; k++) {
        double e = pix[k] - img[k];
        cost += e * e;
    }
    return cost;
}

static void refine_all(double *rotations, double *tvecs, const double *obj, const double *img, Py_ssize_t count,
                       Py_ssize_t n, double fx, double fy, double cx, double cy, const double *d, int steps,
                       double step_done, double cost_done, double lambda0, double *after, double *before,
                       double *work) {
    double *pix = work, *jac = pix + 2 * n, *tpix = jac + 12 * n, *tjac = tpix + 2 * n;
    double h[36], damped[36], g[6], step[6], ex[9], trial_r[9], trial_t[3];
    for (Py_ssize_t p = 0; p < count; p++) {
        double *rot = rotations + 9 * p, *t = tvecs + 3 * p;
        const double *o = obj + 3 * n * p, *im = img + 2 * n * p;
        if (!project(rot, t, o, n, fx, fy, cx, cy, d, pix, jac)) {
            before[p] = after[p] = NAN;
            continue;
        }
        double cost = cost_of(pix, im, n);
        before[p] = sqrt(cost / (double)n);
        double damping = lambda0;
        for (int it = 0; it < steps; it++) {
            memset(h, 0, sizeof h);
            memset(g, 0, sizeof g);
            for (Py_ssize_t k = 0; k < 2 * n; k++) {
                const double *jk = jac + 6 * k;
                double e = pix[k] - im[k];
                for (int a = 0; a < 6; a++) {
                    g[a] += jk[a] * e;
                    for (int b = a; b < 6; b++) h[6 * a + b] += jk[a] * jk[b];
                }
            }
            for (int a = 0; a < 6; a++)
                for (int b = 0; b < a; b++) h[6 * a + b] = h[6 * b + a];
            memcpy(damped, h, sizeof h);
            for (int a = 0; a < 6; a++) damped[7 * a] += damping * (h[7 * a] > 1e-12 ? h[7 * a] : 1e-12);
            if (!solve6(damped, g, step)) break;
            exp_so3(step, ex);
            for (int a = 0; a < 3; a++) {
                for (int b = 0; b < 3; b++)
                    trial_r[3 * a + b] = ex[3 * a] * rot[b] + ex[3 * a + 1] * rot[3 + b] + ex[3 * a + 2] * rot[6 + b];
                trial_t[a] = t[a] + step[3 + a];
            }
            int ok = project(trial_r, trial_t, o, n, fx, fy, cx, cy, d, tpix, tjac);
            double trial_cost = ok ? cost_of(tpix, im, n) : INFINITY;
            double norm = 0.0;
            for (int a = 0; a < 6; a++) norm += step[a] * step[a];
            norm = sqrt(norm);
            if (ok && isfinite(trial_cost) && trial_cost < cost) {
                double drop = cost - trial_cost;
                memcpy(rot, trial_r, sizeof trial_r);
                memcpy(t, trial_t, sizeof trial_t);
                memcpy(pix, tpix, sizeof(double) * 2 * n);
                memcpy(jac, tjac, sizeof(double) * 12 * n);
                cost = trial_cost;
                damping = damping * 0.1 > 1e-12 ? damping * 0.1 : 1e-12;
                if (norm < step_done || drop <= cost_done * (cost > 1e-30 ? cost : 1e-30)) break;
            } else {
                damping *= 10.0;
                if (norm < step_done || damping > 1e12) break;
            }
        }
        after[p] = sqrt(cost / (double)n);
    }
}

static int want(Py_buffer *view, Py_ssize_t doubles, const char *name) {
    if (view->len != doubles * (Py_ssize_t)sizeof(double) || !PyBuffer_IsContiguous(view, 'C')) {
        PyErr_Format(PyExc_ValueError, "refine: %s must be %zd contiguous float64 values", name, doubles);
        return 0;
    }
    return 1;
}

static PyObject *refine(PyObject *self, PyObject *args) {
    Py_buffer rot, tv, obj, img, dist, after, before;
    Py_ssize_t n;
    double fx, fy, cx, cy, step_done, cost_done, lambda0;
    int steps;
    (void)self;
    if (!PyArg_ParseTuple(args, "w*w*y*y*nddddy*idddw*w*", &rot, &tv, &obj, &img, &n, &fx, &fy, &cx, &cy, &dist,
                          &steps, &step_done, &cost_done, &lambda0, &after, &before))
        return NULL;
    PyObject *result = NULL;
    Py_ssize_t count = rot.len / (9 * (Py_ssize_t)sizeof(double));
    double *work = NULL;
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "refine: n must be >= 1");
        goto done;
    }
    if (!want(&rot, 9 * count, "rotations") || !want(&tv, 3 * count, "tvecs") || !want(&obj, 3 * n * count, "obj") ||
        !want(&img, 2 * n * count, "img") || !want(&dist, 12, "dist12") || !want(&after, count, "after") ||
        !want(&before, count, "before"))
        goto done;
    work = PyMem_RawMalloc(sizeof(double) * 28 * (size_t)n);
    if (work == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS refine_all((double *)rot.buf, (double *)tv.buf, (const double *)obj.buf,
                                      (const double *)img.buf, count, n, fx, fy, cx, cy, (const double *)dist.buf,
                                      steps, step_done, cost_done, lambda0, (double *)after.buf,
                                      (double *)before.buf, work);
    Py_END_ALLOW_THREADS result = Py_None;
    Py_INCREF(result);
done:
    PyMem_RawFree(work);
    PyBuffer_Release(&rot);
    PyBuffer_Release(&tv);
    PyBuffer_Release(&obj);
    PyBuffer_Release(&img);
    PyBuffer_Release(&dist);
    PyBuffer_Release(&after);
    PyBuffer_Release(&before);
    return result;
}

static PyMethodDef methods[] = {
    {"refine", refine, METH_VARARGS, "Levenberg-Marquardt polish of poses in place (see the module source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_lm", "Compiled pose polish.", -1, methods};

PyMODINIT_FUNC PyInit__lm(void) { return PyModule_Create(&module); }
