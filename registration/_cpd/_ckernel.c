/* The truncated E-step's passes over its pair list, compiled (registration._cpd._ckernel).
 *
 * Optional: `registration/_cpd/_estep.py` runs the same computation with numpy when this
 * module is not built (no C compiler at install time) or when REGTREE_NO_CKERNEL=1.  The
 * numpy version makes ten passes over the list (repeat, subtract, square, ... and four
 * sparse products), 5.5-6 ns a pair at 8000 points; these two functions and numpy's exp
 * between them make four, 2.5-3 ns a pair (bench/RESULTS.md 7.10).
 *
 * The list: pairs (m, j) grouped by centroid m, `indptr` (M + 1, int64) the CSR row
 * pointers, `j` (P, int32) the subject point of each pair and `xj` (2, P, float64) its
 * coordinates (row 0 the x's, row 1 the y's).  Arrays are passed through the buffer
 * protocol (no numpy headers needed to build); the sizes are checked here, the dtypes
 * and C order by the caller (`_estep._EStep._truncated_compiled`).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

static int check_len(Py_buffer *b, Py_ssize_t items, Py_ssize_t itemsize, const char *name) {
    if (b->len != items * itemsize) {
        PyErr_Format(PyExc_ValueError, "_ckernel: %s holds %zd bytes, expected %zd",
                     name, b->len, items * itemsize);
        return -1;
    }
    return 0;
}

static int check_indptr(const int64_t *ip, Py_ssize_t m, int64_t nnz) {
    if (ip[0] != 0 || ip[m] != nnz) {
        PyErr_SetString(PyExc_ValueError, "_ckernel: indptr must run from 0 to the pair count");
        return -1;
    }
    for (Py_ssize_t i = 0; i < m; i++) {
        if (ip[i + 1] < ip[i]) {
            PyErr_SetString(PyExc_ValueError, "_ckernel: indptr must not decrease");
            return -1;
        }
    }
    return 0;
}

/* The pair count of a list from its row pointers (checked), or -1 with an exception. */
static Py_ssize_t list_pairs(Py_buffer *bp, Py_ssize_t *m) {
    *m = bp->len / 8 - 1;
    if (*m < 0 || check_len(bp, *m + 1, 8, "indptr"))
        return -1;
    const int64_t nnz = ((const int64_t *)bp->buf)[*m];
    if (nnz < 0 || check_indptr(bp->buf, *m, nnz))
        return -1;
    return (Py_ssize_t)nnz;
}

/* 1 when a buffer holds float32 per pair, 0 for float64, -1 (exception) otherwise. */
static int pair_dtype(Py_buffer *b, Py_ssize_t nnz, const char *name) {
    if (b->len == 8 * nnz)
        return 0;
    if (b->len == 4 * nnz)
        return 1;
    PyErr_Format(PyExc_ValueError, "_ckernel: %s holds %zd bytes, expected 8 or 4 a pair (%zd)",
                 name, b->len, nnz);
    return -1;
}

#define EXPONENTS(T)                                                                      \
    for (Py_ssize_t i = 0; i < m; i++) {                                                  \
        const double tx = t[2 * i], ty = t[2 * i + 1];                                    \
        for (int64_t k = ip[i]; k < ip[i + 1]; k++) {                                     \
            const double dx = tx - x0[k], dy = ty - x1[k];                                \
            ((T *)be.buf)[k] = (T)(-scale * (dx * dx + dy * dy));                         \
        }                                                                                 \
    }

/* exponents(t, xj, indptr, scale, out): out[k] = -scale * |t_m - xj_k|^2 for every pair
 * k of centroid m.  t (M, 2), xj (2, P) float64; out (P,) float64 or float32 (rounded
 * once, from the float64 value). */
static PyObject *exponents(PyObject *self, PyObject *args) {
    Py_buffer bt, bx, bp, be;
    double scale;
    if (!PyArg_ParseTuple(args, "y*y*y*dw*", &bt, &bx, &bp, &scale, &be))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m, nnz = list_pairs(&bp, &m);
    int f32 = -1;
    if (nnz < 0 || check_len(&bt, 2 * m, 8, "t") || check_len(&bx, 2 * nnz, 8, "xj")
        || (f32 = pair_dtype(&be, nnz, "out")) < 0)
        goto done;
    {
        const double *t = bt.buf, *x0 = bx.buf, *x1 = (const double *)bx.buf + nnz;
        const int64_t *ip = bp.buf;
        Py_BEGIN_ALLOW_THREADS
        if (f32) {
            EXPONENTS(float)
        } else {
            EXPONENTS(double)
        }
        Py_END_ALLOW_THREADS
    }
    ret = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&bp);
    PyBuffer_Release(&be);
    return ret;
}

#define SCATTER(T)                                                                        \
    for (Py_ssize_t k = 0; k < nnz; k++) {                                                \
        const uint32_t jk = (uint32_t)j[k];                                               \
        if (jk >= (uint32_t)n) {                                                          \
            bad = 1;                                                                      \
            break;                                                                        \
        }                                                                                 \
        cs[jk] += (double)((const T *)be.buf)[k];                                         \
    }

/* two partial sums each: the adds' latency, not the loads, bound one */
#define ROWS(T)                                                                           \
    for (Py_ssize_t i = 0; i < m; i++) {                                                  \
        const T *kern = be.buf;                                                           \
        double a0 = 0.0, a1 = 0.0, a2 = 0.0, b0 = 0.0, b1 = 0.0, b2 = 0.0;               \
        int64_t k = ip[i];                                                                \
        const int64_t end = ip[i + 1];                                                    \
        for (; k + 1 < end; k += 2) {                                                     \
            const double *qa = q + 3 * (int64_t)j[k], *qb = q + 3 * (int64_t)j[k + 1];    \
            const double va = (double)kern[k], vb = (double)kern[k + 1];                  \
            a0 += va * qa[0];                                                             \
            a1 += va * qa[1];                                                             \
            a2 += va * qa[2];                                                             \
            b0 += vb * qb[0];                                                             \
            b1 += vb * qb[1];                                                             \
            b2 += vb * qb[2];                                                             \
        }                                                                                 \
        if (k < end) {                                                                    \
            const double *qa = q + 3 * (int64_t)j[k];                                     \
            const double va = (double)kern[k];                                            \
            a0 += va * qa[0];                                                             \
            a1 += va * qa[1];                                                             \
            a2 += va * qa[2];                                                             \
        }                                                                                 \
        p1[i] = a0 + b0;                                                                  \
        px[2 * i] = a1 + b1;                                                              \
        px[2 * i + 1] = a2 + b2;                                                          \
    }

/* sums(kern, indptr, j, x, c, floor, colsum, q, p1, px, pt1) -> sum_n log den_n
 *
 * kern (P,) the kernel on the pairs, float64 or float32; x (N, 2) the subject; c the
 * outlier constant.  colsum (N,) = sum over each subject point's pairs, den =
 * max(colsum + c, floor), pt1 = colsum / den, p1 (M,) = K (1 / den), px (M, 2) =
 * K (x / den), all summed in float64; q (N, 3) is workspace.  Every output is
 * overwritten. */
static PyObject *sums(PyObject *self, PyObject *args) {
    Py_buffer be, bp, bj, bx, bcs, bq, bp1, bpx, bpt1;
    double c, floor_;
    if (!PyArg_ParseTuple(args, "y*y*y*y*ddw*w*w*w*w*", &be, &bp, &bj, &bx, &c, &floor_,
                          &bcs, &bq, &bp1, &bpx, &bpt1))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m, n = bx.len / 16, nnz = list_pairs(&bp, &m);
    int f32 = -1;
    if (nnz < 0 || (f32 = pair_dtype(&be, nnz, "kern")) < 0 || check_len(&bj, nnz, 4, "j")
        || check_len(&bx, 2 * n, 8, "x") || check_len(&bcs, n, 8, "colsum")
        || check_len(&bq, 3 * n, 8, "q") || check_len(&bp1, m, 8, "p1")
        || check_len(&bpx, 2 * m, 8, "px") || check_len(&bpt1, n, 8, "pt1"))
        goto done;
    {
        const double *x = bx.buf;
        const int64_t *ip = bp.buf;
        const int32_t *j = bj.buf;
        double *cs = bcs.buf, *q = bq.buf, *p1 = bp1.buf, *px = bpx.buf, *pt1 = bpt1.buf;
        double sumlog = 0.0;
        int bad = 0;
        Py_BEGIN_ALLOW_THREADS
        memset(cs, 0, (size_t)n * sizeof(double));
        if (f32) {
            SCATTER(float)
        } else {
            SCATTER(double)
        }
        if (!bad) {
            for (Py_ssize_t a = 0; a < n; a++) {
                double den = cs[a] + c;
                if (!(den >= floor_))
                    den = floor_;
                const double inv = 1.0 / den;
                sumlog += log(den);
                q[3 * a] = inv;
                q[3 * a + 1] = x[2 * a] * inv;
                q[3 * a + 2] = x[2 * a + 1] * inv;
                pt1[a] = cs[a] * inv;
            }
            if (f32) {
                ROWS(float)
            } else {
                ROWS(double)
            }
        }
        Py_END_ALLOW_THREADS
        if (bad) {
            PyErr_SetString(PyExc_ValueError, "_ckernel: a pair's subject index is out of range");
            goto done;
        }
        ret = PyFloat_FromDouble(sumlog);
    }
done:
    PyBuffer_Release(&be);
    PyBuffer_Release(&bp);
    PyBuffer_Release(&bj);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&bcs);
    PyBuffer_Release(&bq);
    PyBuffer_Release(&bp1);
    PyBuffer_Release(&bpx);
    PyBuffer_Release(&bpt1);
    return ret;
}

/* The cell list's scan (`_neighbours.near_pairs`): every centroid m reads the runs
 * [starts[m, r], starts[m, r] + lens[m, r]) of the subject points sorted by cell (xs0,
 * xs1, their original indices `order`), r = 0..R-1, and keeps the points within
 * sqrt(r2), in that order.
 *
 * pair_counts(t, xs0, xs1, starts, lens, r2, cap, counts) -> total, or -1 as soon as
 * the total exceeds cap (cap < 0: no cap).  counts (M,) int64.
 * pair_fill(t, xs0, xs1, order, starts, lens, r2, j, xj, d2): the kept pairs' subject
 * index j (P,) int64, coordinates xj (2, P) float64 and squared distance d2 (P,) float64
 * (None: not asked), P the total pair_counts gave. */
static int scan_args(Py_buffer *bt, Py_buffer *bx0, Py_buffer *bx1, Py_buffer *bs,
                     Py_buffer *bl, Py_ssize_t *m, Py_ssize_t *n, Py_ssize_t *rows) {
    *m = bt->len / 16;
    *n = bx0->len / 8;
    if (check_len(bt, 2 * *m, 8, "t") || check_len(bx1, *n, 8, "xs1"))
        return -1;
    if (*m == 0 || bs->len % (*m * 8) != 0) {
        if (*m == 0 && bs->len == 0 && bl->len == 0) {
            *rows = 0;
            return 0;
        }
        PyErr_SetString(PyExc_ValueError, "_ckernel: starts must hold whole rows of int64");
        return -1;
    }
    *rows = bs->len / (*m * 8);
    if (check_len(bl, *m * *rows, 8, "lens"))
        return -1;
    const int64_t *st = bs->buf, *ln = bl->buf;
    for (Py_ssize_t a = 0; a < *m * *rows; a++) {
        if (ln[a] < 0 || st[a] < 0 || st[a] + ln[a] > *n) {
            PyErr_SetString(PyExc_ValueError, "_ckernel: a run lies outside the points");
            return -1;
        }
    }
    return 0;
}

static PyObject *pair_counts(PyObject *self, PyObject *args) {
    Py_buffer bt, bx0, bx1, bs, bl, bc;
    double r2;
    long long cap;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*dLw*", &bt, &bx0, &bx1, &bs, &bl, &r2, &cap, &bc))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m, n, rows;
    if (scan_args(&bt, &bx0, &bx1, &bs, &bl, &m, &n, &rows) || check_len(&bc, m, 8, "counts"))
        goto done;
    {
        const double *t = bt.buf, *xs0 = bx0.buf, *xs1 = bx1.buf;
        const int64_t *st = bs.buf, *ln = bl.buf;
        int64_t *counts = bc.buf, total = 0;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t i = 0; i < m; i++) {
            const double tx = t[2 * i], ty = t[2 * i + 1];
            int64_t c = 0;
            for (Py_ssize_t r = 0; r < rows; r++) {
                const int64_t a = st[i * rows + r], e = a + ln[i * rows + r];
                for (int64_t k = a; k < e; k++) {
                    const double dx = xs0[k] - tx, dy = xs1[k] - ty;
                    c += (dx * dx + dy * dy <= r2);
                }
            }
            counts[i] = c;
            total += c;
            if (cap >= 0 && total > cap) {
                total = -1;
                break;
            }
        }
        Py_END_ALLOW_THREADS
        ret = PyLong_FromLongLong(total);
    }
done:
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bx0);
    PyBuffer_Release(&bx1);
    PyBuffer_Release(&bs);
    PyBuffer_Release(&bl);
    PyBuffer_Release(&bc);
    return ret;
}

static PyObject *pair_fill(PyObject *self, PyObject *args) {
    Py_buffer bt, bx0, bx1, bo, bs, bl, bj, bxj, bd = {0};
    double r2;
    PyObject *d2obj;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*dw*w*O", &bt, &bx0, &bx1, &bo, &bs, &bl, &r2,
                          &bj, &bxj, &d2obj))
        return NULL;
    PyObject *ret = NULL;
    int with_d = d2obj != Py_None;
    if (with_d && PyObject_GetBuffer(d2obj, &bd, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) {
        with_d = 0;
        goto done;
    }
    Py_ssize_t m, n, rows, p = bj.len / 8;
    if (scan_args(&bt, &bx0, &bx1, &bs, &bl, &m, &n, &rows) || check_len(&bo, n, 8, "order")
        || check_len(&bxj, 2 * p, 8, "xj") || (with_d && check_len(&bd, p, 8, "d2")))
        goto done;
    {
        const double *t = bt.buf, *xs0 = bx0.buf, *xs1 = bx1.buf;
        const int64_t *order = bo.buf, *st = bs.buf, *ln = bl.buf;
        int64_t *j = bj.buf;
        double *x0 = bxj.buf, *x1 = (double *)bxj.buf + p, *d2 = with_d ? bd.buf : NULL;
        int64_t w = 0;
        int overflow = 0;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t i = 0; i < m && !overflow; i++) {
            const double tx = t[2 * i], ty = t[2 * i + 1];
            for (Py_ssize_t r = 0; r < rows && !overflow; r++) {
                const int64_t a = st[i * rows + r], e = a + ln[i * rows + r];
                for (int64_t k = a; k < e; k++) {
                    const double dx = xs0[k] - tx, dy = xs1[k] - ty, dd = dx * dx + dy * dy;
                    if (dd <= r2) {
                        if (w >= p) {
                            overflow = 1;
                            break;
                        }
                        j[w] = order[k];
                        x0[w] = xs0[k];
                        x1[w] = xs1[k];
                        if (d2)
                            d2[w] = dd;
                        w++;
                    }
                }
            }
        }
        Py_END_ALLOW_THREADS
        if (overflow || w != p) {
            PyErr_SetString(PyExc_ValueError, "_ckernel: the output does not hold the pairs");
            goto done;
        }
        ret = Py_NewRef(Py_None);
    }
done:
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bx0);
    PyBuffer_Release(&bx1);
    PyBuffer_Release(&bo);
    PyBuffer_Release(&bs);
    PyBuffer_Release(&bl);
    PyBuffer_Release(&bj);
    PyBuffer_Release(&bxj);
    if (with_d)
        PyBuffer_Release(&bd);
    return ret;
}

static PyMethodDef methods[] = {
    {"exponents", exponents, METH_VARARGS,
     "exponents(t, xj, indptr, scale, out): out[k] = -scale |t_m - xj_k|^2"},
    {"sums", sums, METH_VARARGS,
     "sums(kern, indptr, j, x, c, floor, colsum, q, p1, px, pt1) -> sum log den"},
    {"pair_counts", pair_counts, METH_VARARGS,
     "pair_counts(t, xs0, xs1, starts, lens, r2, cap, counts) -> total, or -1 over cap"},
    {"pair_fill", pair_fill, METH_VARARGS,
     "pair_fill(t, xs0, xs1, order, starts, lens, r2, j, xj, d2 or None)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_ckernel",
    "The truncated E-step's passes over its pair list, compiled.", -1, methods,
};

PyMODINIT_FUNC PyInit__ckernel(void) { return PyModule_Create(&module); }
