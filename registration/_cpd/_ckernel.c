/* CPD's compiled passes (registration._cpd._ckernel): the truncated E-step's over its pair
 * list, the dense Gauss sums (the dense E-step, the final correspondences, a field's
 * kernel product, the low-rank kernel's pivoted Cholesky factor) and nearest neighbours
 * over every pair.
 *
 * Optional: `registration/_cpd/_estep.py` runs the same computation with numpy when this
 * module is not built (no C compiler at install time) or when REGTREE_NO_CKERNEL=1.  The
 * numpy version of the truncated E-step makes ten passes over the list (repeat, subtract,
 * square, ... and four sparse products), 5.5-6 ns a pair at 8000 points; `kernels` and
 * `sums` make three (bench/RESULTS.md 7.10, 7.18).
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
#include <stdlib.h>
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

/* A workspace of `items` elements of `size` bytes (at least one element), or NULL with
 * a MemoryError set. */
static void *workspace(Py_ssize_t items, size_t size) {
    void *p = malloc((size_t)(items > 0 ? items : 1) * size);
    if (p == NULL)
        PyErr_NoMemory();
    return p;
}

/* ---- the dense Gauss sums ----------------------------------------------------------------
 *
 * Every pair's kernel exp(-scale |a - b|^2), from the coordinate differences, through an
 * exp written for exponents <= 0 that the compiler vectorises (libm's exp is a call per
 * value; numpy's vector exp needs the exponents in an array of their own, which is what
 * made the numpy passes cost 1.4-2.8 ns a pair). Each function is built in several
 * clones and the loader picks the one the CPU runs (`target_clones`, GCC and clang on
 * glibc; elsewhere the baseline alone). GCC 12 and later build the x86-64 psABI levels v4
 * (AVX-512) and v3 (AVX2), both with FMA, and the baseline. Older GCC and clang build
 * "avx512f", "avx2,fma" and the baseline, which has no FMA: a clone list names one clone
 * per entry, so "avx2,fma" is an AVX2 clone without FMA (the one an AVX2 CPU takes) and an
 * FMA clone without AVX2, and "avx512f" does not imply FMA. With FMA the dense float64
 * pass takes 2.0 instead of 3.75 ns a pair on an AVX2 machine (float32 1.1 instead of 1.8;
 * bench/RESULTS.md 7.20); sums and kernels move by rounding. `simd()` names the clone.
 *
 * The kernels: exponents below -700 (float64) or -87 (float32) give 0, where libm's exp
 * gives a denormal or 0; every kernel within 2 ulp of libm's otherwise (a degree-13,
 * float32 degree-7, polynomial after the reduction by ln 2). */
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12 && defined(__x86_64__) \
    && defined(__GLIBC__)
#define CLONES_LEVELS 1 /* `simd()` reports the clone the same way */
#define CLONES \
    __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#elif defined(__GNUC__) && defined(__x86_64__) && defined(__GLIBC__) \
    && (!defined(__clang__) || __clang_major__ >= 14)
/* older GCC (no x86-64 levels in the dispatch) and clang: vectorised clones without FMA */
#define CLONES_FEATURES 1
#define CLONES __attribute__((target_clones("avx512f", "avx2,fma", "default")))
#else
#define CLONES
#endif

static inline double exp_nonpos(double v) {
    const double keep = v < -700.0 ? 0.0 : 1.0;
    v = v < -700.0 ? -700.0 : v;
    /* v = k ln2 + r, |r| <= ln2 / 2: k from the rounding of 1.5 * 2^52 + v log2(e) */
    union { double d; int64_t i; } sh, sc;
    sh.d = v * 1.4426950408889634 + 6755399441055744.0;
    const double k = sh.d - 6755399441055744.0;
    const double r = (v - k * 6.93147180369123816490e-01) - k * 1.90821492927058770002e-10;
    double p = 1.0 / 6227020800.0;
    p = p * r + 1.0 / 479001600.0;
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    /* 2^k: k is the difference of sh's bits from those of 1.5 * 2^52 */
    sc.i = (sh.i - 0x4338000000000000LL + 1023) << 52;
    return keep * (p * sc.d);
}

static inline float expf_nonpos(float v) {
    const float keep = v < -87.0f ? 0.0f : 1.0f;
    v = v < -87.0f ? -87.0f : v;
    union { float f; int32_t i; } sh, sc;
    sh.f = v * 1.44269504f + 12582912.0f;
    const float k = sh.f - 12582912.0f;
    const float r = (v - k * 0.693359375f) + k * 2.12194440e-4f;
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    sc.i = (sh.i - 0x4B400000 + 127) << 23; /* 2^k, as above (1.5 * 2^23) */
    return keep * (p * sc.f);
}

#define KERNELS(T, EXP, U)                                                                \
    for (Py_ssize_t i = 0; i < m; i++) {                                                  \
        const double tx = t[2 * i], ty = t[2 * i + 1];                                    \
        T *out = (T *)be.buf;                                                             \
        _Pragma("omp simd")                                                               \
        for (int64_t k = ip[i]; k < ip[i + 1]; k++) {                                     \
            const double dx = tx - x0[k], dy = ty - x1[k];                                \
            out[k] = EXP((U)(-scale * (dx * dx + dy * dy)));                              \
        }                                                                                 \
    }

CLONES static void kernels64(Py_ssize_t m, const double *t, const double *x0, const double *x1,
                             const int64_t *ip, double scale, Py_buffer be) {
    KERNELS(double, exp_nonpos, double)
}

CLONES static void kernels32(Py_ssize_t m, const double *t, const double *x0, const double *x1,
                             const int64_t *ip, double scale, Py_buffer be) {
    KERNELS(float, expf_nonpos, float)
}

/* kernels(t, xj, indptr, scale, out): out[k] = exp(-scale |t_m - xj_k|^2) for every pair k
 * of centroid m: t (M, 2), xj (2, P) float64; out (P,) float64 or float32 (the exponents
 * in float64, a float32 out takes the float32 exp). */
static PyObject *kernels(PyObject *self, PyObject *args) {
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
        if (f32)
            kernels32(m, t, x0, x1, ip, scale, be);
        else
            kernels64(m, t, x0, x1, ip, scale, be);
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

/* obj None: 0; else its buffer in b, checked to hold `items` of `size` bytes: 1; -1 on
 * error (an exception set). An output (`writable`) must be writable; an input need not
 * be, so a read-only array (a view of a frozen one) is taken as it is. */
static int optional_buffer(PyObject *obj, Py_buffer *b, Py_ssize_t items, Py_ssize_t size,
                           const char *name, int writable) {
    if (obj == Py_None)
        return 0;
    if (PyObject_GetBuffer(obj, b, (writable ? PyBUF_WRITABLE : 0) | PyBUF_C_CONTIGUOUS) < 0)
        return -1;
    if (check_len(b, items, size, name)) {
        PyBuffer_Release(b);
        return -1;
    }
    return 1;
}

/* One subject point's (xa, ya) kernels with the m centroids (t0, t1) into kb, float64;
 * returns their sum. lw (M,): each centroid's log mixture weight (<= 0), added to its
 * exponents; NULL: none. */
static inline double column64(Py_ssize_t m, const double *t0, const double *t1,
                              const double *lw, double xa, double ya, double scale,
                              double *kb) {
    double s = 0.0;
    if (lw) {
#pragma omp simd reduction(+ : s)
        for (Py_ssize_t i = 0; i < m; i++) {
            const double dx = t0[i] - xa, dy = t1[i] - ya;
            const double k = exp_nonpos(lw[i] - scale * (dx * dx + dy * dy));
            kb[i] = k;
            s += k;
        }
        return s;
    }
#pragma omp simd reduction(+ : s)
    for (Py_ssize_t i = 0; i < m; i++) {
        const double dx = t0[i] - xa, dy = t1[i] - ya;
        const double k = exp_nonpos(-scale * (dx * dx + dy * dy));
        kb[i] = k;
        s += k;
    }
    return s;
}

/* The dense E-step's sums, float64: column n's kernels into kb, their sum, then each
 * centroid's share. */
CLONES static double dense64(Py_ssize_t m, Py_ssize_t n, const double *t0, const double *t1,
                             const double *lw, const double *x, double scale, double c,
                             double floor_,
                             double *kb, double *p1, double *px0, double *px1, double *pt1) {
    double sumlog = 0.0;
    for (Py_ssize_t i = 0; i < m; i++)
        p1[i] = px0[i] = px1[i] = 0.0;
    for (Py_ssize_t a = 0; a < n; a++) {
        const double xa = x[2 * a], ya = x[2 * a + 1];
        const double s = column64(m, t0, t1, lw, xa, ya, scale, kb);
        double den = s + c;
        if (!(den >= floor_))
            den = floor_;
        const double inv = 1.0 / den, wx = xa * inv, wy = ya * inv;
        sumlog += log(den);
        pt1[a] = s * inv;
#pragma omp simd
        for (Py_ssize_t i = 0; i < m; i++) {
            const double k = kb[i];
            p1[i] += k * inv;
            px0[i] += k * wx;
            px1[i] += k * wy;
        }
    }
    return sumlog;
}

/* float32: the exponents in float64 (from float32 coordinates, a difference of 0.01 at a
 * sigma of 0.005 would be 1e-5 off), the kernels and the centroids' sums in float32
 * (those summed over at most F32_RUN subject points, then added up in float64); the
 * column sums' denominators and logs in float64. A subject point whose kernels are all
 * below float32's range (no outlier weight, far from every centroid: its posteriors are
 * still theirs over their sum) has its column taken in float64. */
#define F32_RUN 256
CLONES static double dense32(Py_ssize_t m, Py_ssize_t n, const double *t0, const double *t1,
                             const double *lw, const double *x, double scale, double c,
                             double floor_,
                             float *kb, float *acc, double *kb64, double *p1, double *px0,
                             double *px1, double *pt1) {
    double sumlog = 0.0;
    float *a1 = acc, *a2 = acc + m, *a3 = acc + 2 * m;
    for (Py_ssize_t i = 0; i < m; i++)
        p1[i] = px0[i] = px1[i] = 0.0;
    for (Py_ssize_t a0 = 0; a0 < n; a0 += F32_RUN) {
        const Py_ssize_t end = a0 + F32_RUN < n ? a0 + F32_RUN : n;
        for (Py_ssize_t i = 0; i < 3 * m; i++)
            acc[i] = 0.0f;
        for (Py_ssize_t a = a0; a < end; a++) {
            const double xa = x[2 * a], ya = x[2 * a + 1];
            float s = 0.0f;
            if (lw) {
#pragma omp simd reduction(+ : s)
                for (Py_ssize_t i = 0; i < m; i++) {
                    const double dx = t0[i] - xa, dy = t1[i] - ya;
                    const float k =
                        expf_nonpos((float)(lw[i] - scale * (dx * dx + dy * dy)));
                    kb[i] = k;
                    s += k;
                }
            } else {
#pragma omp simd reduction(+ : s)
                for (Py_ssize_t i = 0; i < m; i++) {
                    const double dx = t0[i] - xa, dy = t1[i] - ya;
                    const float k = expf_nonpos((float)(-scale * (dx * dx + dy * dy)));
                    kb[i] = k;
                    s += k;
                }
            }
            /* kernels below float32's range (w = 0, far from every centroid), or weights
               x / den beyond it: the column in float64 */
            if (s < 1e-30f || (fabs(xa) + fabs(ya)) / ((double)s + c) > 1e30) {
                const double s64 = column64(m, t0, t1, lw, xa, ya, scale, kb64);
                double den = s64 + c;
                if (!(den >= floor_))
                    den = floor_;
                const double inv = 1.0 / den;
                sumlog += log(den);
                pt1[a] = s64 * inv;
                for (Py_ssize_t i = 0; i < m; i++) {
                    const double k = kb64[i] * inv;
                    a1[i] += (float)k;
                    a2[i] += (float)(k * xa);
                    a3[i] += (float)(k * ya);
                }
                continue;
            }
            const double den = (double)s + c, inv = 1.0 / den;
            sumlog += log(den);
            pt1[a] = (double)s * inv;
            const float fi = (float)inv, wx = (float)(xa * inv), wy = (float)(ya * inv);
#pragma omp simd
            for (Py_ssize_t i = 0; i < m; i++) {
                const float k = kb[i];
                a1[i] += k * fi;
                a2[i] += k * wx;
                a3[i] += k * wy;
            }
        }
        for (Py_ssize_t i = 0; i < m; i++) {
            p1[i] += (double)a1[i];
            px0[i] += (double)a2[i];
            px1[i] += (double)a3[i];
        }
    }
    return sumlog;
}

/* dense(tt, x, scale, c, floor, f32, p1, px, pt1, lw=None) -> sum_n log den_n
 *
 * tt (2, M) float64 the centroids' coordinates; x (N, 2) float64 the subject; scale =
 * 1 / (2 sigma^2); c the outlier constant; f32 true: the kernels in float32; lw (M,)
 * float64 or None: each centroid's log mixture weight (<= 0), K_mn = exp(lw_m - scale
 * |t_m - x_n|^2).  den_n = max(sum_m K_mn + c, floor); p1 (M,) = K (1 / den), px (2, M) =
 * (K (x / den))^T, pt1 (N,) = colsum / den, all float64 and overwritten. */
static PyObject *dense(PyObject *self, PyObject *args) {
    Py_buffer bt, bx, bp1, bpx, bpt1, blw;
    double scale, c, floor_;
    int f32, have_lw = 0;
    PyObject *lw_obj = Py_None;
    if (!PyArg_ParseTuple(args, "y*y*dddpw*w*w*|O", &bt, &bx, &scale, &c, &floor_, &f32,
                          &bp1, &bpx, &bpt1, &lw_obj))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = bp1.len / 8, n = bx.len / 16;
    void *work = NULL;
    if (check_len(&bt, 2 * m, 8, "tt") || check_len(&bp1, m, 8, "p1")
        || check_len(&bx, 2 * n, 8, "x") || check_len(&bpx, 2 * m, 8, "px")
        || check_len(&bpt1, n, 8, "pt1"))
        goto done;
    if ((have_lw = optional_buffer(lw_obj, &blw, m, 8, "lw", 0)) < 0) {
        have_lw = 0;
        goto done;
    }
    /* float32: the kernels, three sums and a float64 column; float64: the kernels */
    if ((work = workspace(m, f32 ? 4 * sizeof(float) + sizeof(double) : sizeof(double)))
        == NULL)
        goto done;
    {
        double sumlog;
        double *p1 = bp1.buf, *px = bpx.buf;
        const double *lw = have_lw ? blw.buf : NULL;
        Py_BEGIN_ALLOW_THREADS
        const double *t = bt.buf;
        if (f32) {
            sumlog = dense32(m, n, t, t + m, lw, bx.buf, scale, c, floor_, work,
                             (float *)work + m, (double *)((float *)work + 4 * m), p1, px,
                             px + m, bpt1.buf);
        } else {
            sumlog = dense64(m, n, t, t + m, lw, bx.buf, scale, c, floor_, work, p1, px,
                             px + m, bpt1.buf);
        }
        Py_END_ALLOW_THREADS
        ret = PyFloat_FromDouble(sumlog);
    }
done:
    free(work);
    if (have_lw)
        PyBuffer_Release(&blw);
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&bp1);
    PyBuffer_Release(&bpx);
    PyBuffer_Release(&bpt1);
    return ret;
}

CLONES static void posterior64(Py_ssize_t m, Py_ssize_t n, const double *t0,
                               const double *t1, const double *lw, const double *x,
                               double scale, double c, double floor_, double *kb,
                               int64_t *arg, double *best) {
    for (Py_ssize_t i = 0; i < m; i++) {
        best[i] = -1.0;
        arg[i] = 0;
    }
    for (Py_ssize_t a = 0; a < n; a++) {
        const double xa = x[2 * a], ya = x[2 * a + 1];
        const double s = column64(m, t0, t1, lw, xa, ya, scale, kb);
        double den = s + c;
        if (!(den >= floor_))
            den = floor_;
        const double inv = 1.0 / den;
#pragma omp simd
        for (Py_ssize_t i = 0; i < m; i++) {
            const double v = kb[i] * inv;
            const int better = v > best[i];
            best[i] = better ? v : best[i];
            arg[i] = better ? (int64_t)a : arg[i];
        }
    }
}

/* posterior_max(tt, x, scale, c, floor, arg, best, lw=None): for each centroid m the
 * first n maximising P(m | x_n) = K_mn / den_n (K, den and lw as in `dense`) and that
 * maximum; tt (2, M) float64, arg (M,) int64, best (M,) float64, both overwritten. */
static PyObject *posterior_max(PyObject *self, PyObject *args) {
    Py_buffer bt, bx, barg, bbest, blw;
    double scale, c, floor_;
    int have_lw = 0;
    PyObject *lw_obj = Py_None;
    if (!PyArg_ParseTuple(args, "y*y*dddw*w*|O", &bt, &bx, &scale, &c, &floor_, &barg,
                          &bbest, &lw_obj))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = bbest.len / 8, n = bx.len / 16;
    double *work = NULL;
    if (check_len(&bt, 2 * m, 8, "tt") || check_len(&bx, 2 * n, 8, "x")
        || check_len(&barg, m, 8, "arg") || check_len(&bbest, m, 8, "best"))
        goto done;
    if ((have_lw = optional_buffer(lw_obj, &blw, m, 8, "lw", 0)) < 0) {
        have_lw = 0;
        goto done;
    }
    if ((work = workspace(m, sizeof(double))) == NULL)
        goto done;
    {
        const double *t = bt.buf;
        Py_BEGIN_ALLOW_THREADS
        posterior64(m, n, t, t + m, have_lw ? blw.buf : NULL, bx.buf, scale, c, floor_,
                    work, barg.buf, bbest.buf);
        Py_END_ALLOW_THREADS
        ret = Py_NewRef(Py_None);
    }
done:
    free(work);
    if (have_lw)
        PyBuffer_Release(&blw);
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&barg);
    PyBuffer_Release(&bbest);
    return ret;
}

CLONES static void product64(Py_ssize_t k, Py_ssize_t m, Py_ssize_t r, const double *z,
                             const double *c0, const double *c1, const double *q,
                             double scale, double *kb, double *out) {
    for (Py_ssize_t a = 0; a < k; a++) {
        const double za = z[2 * a], zb = z[2 * a + 1];
#pragma omp simd
        for (Py_ssize_t j = 0; j < m; j++) {
            const double dx = c0[j] - za, dy = c1[j] - zb;
            kb[j] = exp_nonpos(-scale * (dx * dx + dy * dy));
        }
        for (Py_ssize_t col = 0; col < r; col++) {
            const double *qc = q + col * m;
            double s = 0.0;
#pragma omp simd reduction(+ : s)
            for (Py_ssize_t j = 0; j < m; j++)
                s += kb[j] * qc[j];
            out[a * r + col] = s;
        }
    }
}

/* product(z, ct, qt, scale, out): out (K, R) = G(z, c) q, G[a, j] = exp(-scale |z_a -
 * c_j|^2); z (K, 2), ct (2, M) and qt (R, M) (q transposed) float64, out overwritten. */
static PyObject *product(PyObject *self, PyObject *args) {
    Py_buffer bz, bc, bq, bo;
    double scale;
    if (!PyArg_ParseTuple(args, "y*y*y*dw*", &bz, &bc, &bq, &scale, &bo))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t k = bz.len / 16, m = bc.len / 16, r = m > 0 ? bq.len / (8 * m) : 0;
    double *work = NULL;
    if (check_len(&bz, 2 * k, 8, "z") || check_len(&bc, 2 * m, 8, "ct")
        || check_len(&bq, r * m, 8, "qt") || check_len(&bo, k * r, 8, "out"))
        goto done;
    if ((work = workspace(m, sizeof(double))) == NULL)
        goto done;
    {
        const double *ct = bc.buf;
        Py_BEGIN_ALLOW_THREADS
        product64(k, m, r, bz.buf, ct, ct + m, bq.buf, scale, work, bo.buf);
        Py_END_ALLOW_THREADS
        ret = Py_NewRef(Py_None);
    }
done:
    free(work);
    PyBuffer_Release(&bz);
    PyBuffer_Release(&bc);
    PyBuffer_Release(&bq);
    PyBuffer_Release(&bo);
    return ret;
}

CLONES static Py_ssize_t cholesky64(Py_ssize_t m, Py_ssize_t cols, Py_ssize_t k,
                                     Py_ssize_t kmax, const double *y, double scale,
                                     double stop, double *l, double *d, double *col,
                                     int *done) {
    *done = 0;
    while (k < kmax) {
        Py_ssize_t i = 0;
        double total = 0.0;
        for (Py_ssize_t r = 0; r < m; r++) {
            total += d[r];
            if (d[r] > d[i])
                i = r;
        }
        const double piv = d[i];
        if (!(piv > 0) || (stop >= 0 && total <= stop)) {
            *done = 1;
            return k;
        }
        if (k == cols)
            return k; /* out of columns: the caller grows l and calls again */
        const double yi0 = y[2 * i], yi1 = y[2 * i + 1], inv = 1.0 / sqrt(piv);
        const double *li = l + i * cols;
#pragma omp simd
        for (Py_ssize_t r = 0; r < m; r++) {
            const double dx = y[2 * r] - yi0, dy = y[2 * r + 1] - yi1;
            col[r] = exp_nonpos(-scale * (dx * dx + dy * dy));
        }
        for (Py_ssize_t r = 0; r < m; r++) {
            double g = col[r];
            const double *lr = l + r * cols;
            double s = 0.0;
#pragma omp simd reduction(+ : s)
            for (Py_ssize_t c = 0; c < k; c++)
                s += lr[c] * li[c];
            g = (g - s) * inv;
            l[r * cols + k] = g;
            const double dr = d[r] - g * g;
            d[r] = dr > 0.0 ? dr : 0.0;
        }
        d[i] = 0.0;
        k++;
    }
    *done = 1;
    return k;
}

/* pivoted_cholesky(y, scale, kmax, stop, l, d, k0) -> (k, done)
 *
 * Greedy diagonal pivoting of the Gaussian kernel exp(-scale |y_i - y_j|^2) of y (M, 2)
 * float64 (see `_fgt.pivoted_cholesky`), resumed at column k0 of l (M, C) float64 with the
 * residual diagonal d (M,) float64, both updated in place.  Adds columns until k = kmax,
 * the largest residual is not positive or (stop >= 0) the residual's trace is <= stop
 * (done true), or l has no column left (done false: grow l and call again). */
static PyObject *pivoted_cholesky(PyObject *self, PyObject *args) {
    Py_buffer by, bl, bd;
    double scale, stop;
    Py_ssize_t kmax, k0;
    if (!PyArg_ParseTuple(args, "y*dndw*w*n", &by, &scale, &kmax, &stop, &bl, &bd, &k0))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = by.len / 16, cols = m > 0 ? bl.len / (8 * m) : 0;
    double *work = NULL;
    if (check_len(&by, 2 * m, 8, "y") || check_len(&bd, m, 8, "d")
        || check_len(&bl, m * cols, 8, "l"))
        goto done;
    if (k0 < 0 || k0 > cols || kmax > m) {
        PyErr_SetString(PyExc_ValueError, "_ckernel: k0 must lie in [0, columns], kmax <= M");
        goto done;
    }
    if ((work = workspace(m, sizeof(double))) == NULL)
        goto done;
    {
        Py_ssize_t k;
        int finished;
        Py_BEGIN_ALLOW_THREADS
        k = cholesky64(m, cols, k0, kmax, by.buf, scale, stop, bl.buf, bd.buf, work,
                       &finished);
        Py_END_ALLOW_THREADS
        ret = Py_BuildValue("(nO)", k, finished ? Py_True : Py_False);
    }
done:
    free(work);
    PyBuffer_Release(&by);
    PyBuffer_Release(&bl);
    PyBuffer_Release(&bd);
    return ret;
}

CLONES static void nearest64(Py_ssize_t nb, Py_ssize_t n, Py_ssize_t m, const double *a0,
                              const double *a1, const double *b0, const double *b1,
                              double *d, int64_t *row_arg, double *row_d2, int64_t *col_arg,
                              double *col_d2) {
    for (Py_ssize_t p = 0; p < nb; p++) {
        const double *pa0 = a0 + p * n, *pa1 = a1 + p * n, *pb0 = b0 + p * m, *pb1 = b1 + p * m;
        double *cd = col_d2 ? col_d2 + p * m : NULL;
        int64_t *ca = col_arg ? col_arg + p * m : NULL;
        if (cd || ca) {
            for (Py_ssize_t j = 0; j < m; j++) {
                if (cd)
                    cd[j] = INFINITY;
                if (ca)
                    ca[j] = 0;
            }
        }
        double *cmin = cd ? cd : d + m; /* the column minima, kept for col_arg */
        if (!cd)
            for (Py_ssize_t j = 0; j < m; j++)
                cmin[j] = INFINITY;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double x = pa0[i], y = pa1[i];
            double best = INFINITY;
#pragma omp simd reduction(min : best)
            for (Py_ssize_t j = 0; j < m; j++) {
                const double dx = pb0[j] - x, dy = pb1[j] - y, v = dx * dx + dy * dy;
                d[j] = v;
                best = v < best ? v : best;
            }
            if (row_arg) {
                Py_ssize_t j = 0;
                while (j < m - 1 && !(d[j] == best))
                    j++;
                row_arg[p * n + i] = j;
            }
            if (row_d2)
                row_d2[p * n + i] = best;
            if (ca) {
                for (Py_ssize_t j = 0; j < m; j++) {
                    if (d[j] < cmin[j]) { /* strict: the first i keeps a tie */
                        cmin[j] = d[j];
                        ca[j] = i;
                    }
                }
            } else if (cd) {
#pragma omp simd
                for (Py_ssize_t j = 0; j < m; j++)
                    cmin[j] = d[j] < cmin[j] ? d[j] : cmin[j];
            }
        }
    }
}

/* nearest(a0, a1, b0, b1, n, m, row_arg, row_d2, col_arg, col_d2)
 *
 * For B problems at once (a0, a1: (B, n) float64, the query points' coordinates; b0, b1:
 * (B, m) float64, the other set's): each query point's nearest point of the other set
 * (row_arg (B, n) int64, the first index at the least squared distance, and row_d2 (B, n)
 * float64 that distance) and each of the other set's points' nearest query point
 * (col_arg (B, m) int64, col_d2 (B, m) float64); each output None when not wanted. */
static PyObject *nearest(PyObject *self, PyObject *args) {
    Py_buffer ba0, ba1, bb0, bb1, bo[4];
    PyObject *obj[4];
    Py_ssize_t n, m;
    if (!PyArg_ParseTuple(args, "y*y*y*y*nnOOOO", &ba0, &ba1, &bb0, &bb1, &n, &m, &obj[0],
                          &obj[1], &obj[2], &obj[3]))
        return NULL;
    PyObject *ret = NULL;
    int have[4] = {0, 0, 0, 0};
    double *work = NULL;
    Py_ssize_t nb = n > 0 ? ba0.len / (8 * n) : 0;
    if (n < 1 || m < 1) {
        PyErr_SetString(PyExc_ValueError, "_ckernel: nearest needs n >= 1 and m >= 1");
        goto done;
    }
    if (check_len(&ba0, nb * n, 8, "a0") || check_len(&ba1, nb * n, 8, "a1")
        || check_len(&bb0, nb * m, 8, "b0") || check_len(&bb1, nb * m, 8, "b1"))
        goto done;
    {
        const char *names[4] = {"row_arg", "row_d2", "col_arg", "col_d2"};
        const Py_ssize_t items[4] = {nb * n, nb * n, nb * m, nb * m};
        for (int k = 0; k < 4; k++)
            if ((have[k] = optional_buffer(obj[k], &bo[k], items[k], 8, names[k], 1)) < 0) {
                have[k] = 0;
                goto done;
            }
    }
    if ((work = workspace(2 * m, sizeof(double))) == NULL)
        goto done;
    Py_BEGIN_ALLOW_THREADS
    nearest64(nb, n, m, ba0.buf, ba1.buf, bb0.buf, bb1.buf, work,
              have[0] ? bo[0].buf : NULL, have[1] ? bo[1].buf : NULL,
              have[2] ? bo[2].buf : NULL, have[3] ? bo[3].buf : NULL);
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    free(work);
    for (int k = 0; k < 4; k++)
        if (have[k])
            PyBuffer_Release(&bo[k]);
    PyBuffer_Release(&ba0);
    PyBuffer_Release(&ba1);
    PyBuffer_Release(&bb0);
    PyBuffer_Release(&bb1);
    return ret;
}

/* farthest(x, y, d2, chosen): the farthest-point subsample's remaining picks. x, y (m,)
 * float64 the points' coordinates; d2 (m,) float64 each point's squared distance to the
 * picks so far (overwritten); chosen (n,) int64 with chosen[0] the first pick, its rest
 * written: each time the first point at the largest d2, then d2 lowered to the squared
 * distances to it, dx^2 + dy^2, where smaller. Not among the clones: the baseline has no
 * FMA to contract those sums into, so they and the picks are numpy's
 * (`_points.farthest_point_indices`) bit for bit. Three vectorised passes a pick (lower,
 * the largest, its first index) instead of numpy's seven. */
static Py_ssize_t first_largest(Py_ssize_t m, const double *d2) {
    double best = d2[0];
#pragma omp simd reduction(max : best)
    for (Py_ssize_t i = 0; i < m; i++)
        best = d2[i] > best ? d2[i] : best;
    for (Py_ssize_t i = 0; i < m; i++)
        if (d2[i] == best)
            return i;
    return 0; /* NaN: numpy's argmax would name the first NaN; finite points have none */
}

static void farthest_picks(Py_ssize_t m, Py_ssize_t n, const double *x, const double *y,
                           double *d2, int64_t *chosen) {
    Py_ssize_t next = first_largest(m, d2);
    for (Py_ssize_t k = 1; k < n; k++) {
        chosen[k] = (int64_t)next;
        const double px = x[next], py = y[next];
#pragma omp simd
        for (Py_ssize_t i = 0; i < m; i++) {
            const double dx = x[i] - px, dy = y[i] - py;
            const double dx2 = dx * dx, dy2 = dy * dy;
            const double d = dx2 + dy2;
            d2[i] = d < d2[i] ? d : d2[i];
        }
        next = first_largest(m, d2);
    }
}

static PyObject *farthest(PyObject *self, PyObject *args) {
    Py_buffer bx, by, bd, bc;
    if (!PyArg_ParseTuple(args, "y*y*w*w*", &bx, &by, &bd, &bc))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t m = bd.len / 8, n = bc.len / 8;
    if (check_len(&bx, m, 8, "x") || check_len(&by, m, 8, "y") || check_len(&bd, m, 8, "d2")
        || check_len(&bc, n, 8, "chosen"))
        goto done;
    if (n > m || m < 1) {
        PyErr_SetString(PyExc_ValueError, "_ckernel: farthest needs 1 <= len(chosen) <= m");
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    farthest_picks(m, n, bx.buf, by.buf, bd.buf, bc.buf);
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&bx);
    PyBuffer_Release(&by);
    PyBuffer_Release(&bd);
    PyBuffer_Release(&bc);
    return ret;
}

/* interp(u, nodes, wb, out): the barycentric Lagrange weights of the r Chebyshev nodes
 * (weights wb) at each of the n points u, out (n, r): wb_k / (u - node_k) over their
 * sum (times its inverse: within an ulp of numpy's division); a point whose sum is not
 * finite (on a node, or within a denormal of one) gets the one-hot row of its nearest
 * node (the first of equals). numpy's version made four passes over (n, r) temporaries
 * (`_fgt._interp_matrix`). */
CLONES static void interp_rows(Py_ssize_t n, Py_ssize_t r, const double *u,
                               const double *nodes, const double *wb, double *out) {
    for (Py_ssize_t i = 0; i < n; i++) {
        const double ui = u[i];
        double *row = out + i * r, total = 0.0;
        for (Py_ssize_t k = 0; k < r; k++) {
            row[k] = wb[k] / (ui - nodes[k]);
            total += row[k];
        }
        if (isfinite(total)) {
            const double inv = 1.0 / total;
            for (Py_ssize_t k = 0; k < r; k++)
                row[k] *= inv;
            continue;
        }
        Py_ssize_t best = 0;
        for (Py_ssize_t k = 0; k < r; k++) {
            row[k] = 0.0;
            if (fabs(ui - nodes[k]) < fabs(ui - nodes[best]))
                best = k;
        }
        row[best] = 1.0;
    }
}

static PyObject *interp(PyObject *self, PyObject *args) {
    Py_buffer bu, bn, bw, bo;
    if (!PyArg_ParseTuple(args, "y*y*y*w*", &bu, &bn, &bw, &bo))
        return NULL;
    PyObject *ret = NULL;
    Py_ssize_t n = bu.len / 8, r = bn.len / 8;
    if (check_len(&bu, n, 8, "u") || r < 1 || check_len(&bn, r, 8, "nodes")
        || check_len(&bw, r, 8, "wb") || check_len(&bo, n * r, 8, "out"))
        goto done;
    {
        const double *u = bu.buf, *nodes = bn.buf, *wb = bw.buf;
        double *out = bo.buf;
        Py_BEGIN_ALLOW_THREADS
        interp_rows(n, r, u, nodes, wb, out);
        Py_END_ALLOW_THREADS
        ret = Py_NewRef(Py_None);
    }
done:
    PyBuffer_Release(&bu);
    PyBuffer_Release(&bn);
    PyBuffer_Release(&bw);
    PyBuffer_Release(&bo);
    return ret;
}

/* ---- the low-rank M-step ------------------------------------------------------------------
 *
 * CPD's M-step with the kernel G ~= Q diag(lam) Q^T (`_mstep.LowRankMStep`): the k x k
 * system (Q^T d(P1) Q + reg diag(1/lam)) v = Q^T F, F = P X - d(P1) Y, by Cholesky, then
 * W = Q (v / lam) and the displacement Q v. numpy took about 0.2-0.3 ms of it at 400
 * points and rank 62, most of it in calls on small arrays. Q comes row by row, each row
 * padded with zeros to a multiple of 8 columns (kp), so that the Gram matrix's upper
 * triangle is summed in tiles of 4 x 8 sums held in registers, over blocks of
 * GRAM_ROWS rows of Q that stay in the first-level cache. */

#define GRAM_ROWS 16

/* h[i kp + j] = sum_r s[r kp + i] q[r kp + j] for the tiles on or above the diagonal
 * (i < k rounded up to 4, j < kp; the rest of h is not written). */
CLONES static void gram_tiles(Py_ssize_t m, Py_ssize_t k, Py_ssize_t kp, const double *s,
                              const double *q, double *h) {
    for (Py_ssize_t r0 = 0; r0 < m; r0 += GRAM_ROWS) {
        const Py_ssize_t r1 = r0 + GRAM_ROWS < m ? r0 + GRAM_ROWS : m;
        for (Py_ssize_t i0 = 0; i0 < k; i0 += 4) {
            for (Py_ssize_t j0 = (i0 / 8) * 8; j0 < kp; j0 += 8) {
                double *h0 = h + i0 * kp + j0;
                double acc[4][8];
                for (int u = 0; u < 4; u++)
                    for (int v = 0; v < 8; v++)
                        acc[u][v] = r0 == 0 ? 0.0 : h0[u * kp + v];
                for (Py_ssize_t r = r0; r < r1; r++) {
                    const double *qr = q + r * kp + j0, *sr = s + r * kp + i0;
                    for (int u = 0; u < 4; u++)
                        for (int v = 0; v < 8; v++)
                            acc[u][v] += sr[u] * qr[v];
                }
                for (int u = 0; u < 4; u++)
                    for (int v = 0; v < 8; v++)
                        h0[u * kp + v] = acc[u][v];
            }
        }
    }
}

#if defined(CLONES_LEVELS) || defined(CLONES_FEATURES)
/* The same tiles in AVX2 with FMA, written with GCC's vector types: the compiler kept the
 * plain loop's 32 sums in registers only in part (about twice this one's time on an AVX2
 * machine), and the vector types cannot go in the baseline clone (without AVX they were
 * 30x slower there). */
typedef double v4d __attribute__((vector_size(32), aligned(8)));
#define V4D(p) (*(v4d *)(p))
__attribute__((target("avx2,fma"))) static void gram_tiles_avx2(Py_ssize_t m, Py_ssize_t k,
                                                                 Py_ssize_t kp, const double *s,
                                                                 const double *q, double *h) {
    for (Py_ssize_t r0 = 0; r0 < m; r0 += GRAM_ROWS) {
        const Py_ssize_t r1 = r0 + GRAM_ROWS < m ? r0 + GRAM_ROWS : m;
        for (Py_ssize_t i0 = 0; i0 < k; i0 += 4) {
            for (Py_ssize_t j0 = (i0 / 8) * 8; j0 < kp; j0 += 8) {
                double *h0 = h + i0 * kp + j0, *h1 = h0 + kp, *h2 = h1 + kp, *h3 = h2 + kp;
                v4d a00 = {0, 0, 0, 0}, a01 = a00, a10 = a00, a11 = a00, a20 = a00,
                    a21 = a00, a30 = a00, a31 = a00;
                if (r0 > 0) {
                    a00 = V4D(h0), a01 = V4D(h0 + 4), a10 = V4D(h1), a11 = V4D(h1 + 4);
                    a20 = V4D(h2), a21 = V4D(h2 + 4), a30 = V4D(h3), a31 = V4D(h3 + 4);
                }
                for (Py_ssize_t r = r0; r < r1; r++) {
                    const double *qr = q + r * kp + j0, *sr = s + r * kp + i0;
                    const v4d q0 = V4D(qr), q1 = V4D(qr + 4);
                    a00 += sr[0] * q0, a01 += sr[0] * q1, a10 += sr[1] * q0, a11 += sr[1] * q1;
                    a20 += sr[2] * q0, a21 += sr[2] * q1, a30 += sr[3] * q0, a31 += sr[3] * q1;
                }
                V4D(h0) = a00, V4D(h0 + 4) = a01, V4D(h1) = a10, V4D(h1 + 4) = a11;
                V4D(h2) = a20, V4D(h2 + 4) = a21, V4D(h3) = a30, V4D(h3 + 4) = a31;
            }
        }
    }
}

static int use_avx2_fma = 0; /* set at import: the CPU runs AVX2 and FMA */
#endif

/* The M-step (see above): qp (m, kp) = Q row by row, zero past column k; lam (k,), y and
 * px (m, 2), p1 (m,); w and disp (m, 2) written, and the sums of `lowrank_mstep` when
 * `sums` is not NULL. Work: s (m kp), h (kp kp), b and c (2 kp each).
 * Returns 0 when the system is not numerically positive definite (a pivot <= 0 or NaN, as
 * LAPACK's potrf reports it): nothing is written then. */
CLONES static int lowrank64(Py_ssize_t m, Py_ssize_t k, Py_ssize_t kp, const double *qp,
                            const double *lam, const double *y, const double *p1,
                            const double *px, double reg, int plain, double *s, double *h,
                            double *b, double *c, double *w, double *disp, double *sums) {
    double *b0 = b, *b1 = b + kp;
    memset(b, 0, (size_t)(2 * kp) * sizeof(double));
    for (Py_ssize_t r = 0; r < m; r++) {
        const double *qr = qp + r * kp;
        double *sr = s + r * kp;
        const double pr = p1[r], f0 = px[2 * r] - pr * y[2 * r],
                     f1 = px[2 * r + 1] - pr * y[2 * r + 1];
#pragma omp simd
        for (Py_ssize_t i = 0; i < kp; i++) {
            sr[i] = pr * qr[i];
            b0[i] += qr[i] * f0;
            b1[i] += qr[i] * f1;
        }
    }
#if defined(CLONES_LEVELS) || defined(CLONES_FEATURES)
    if (use_avx2_fma && !plain)
        gram_tiles_avx2(m, k, kp, s, qp, h);
    else
#else
    (void)plain; /* the plain tiles are the only ones here */
#endif
        gram_tiles(m, k, kp, s, qp, h);
    /* Cholesky h = U^T U in place in the upper triangle, by rows (each update runs along a
     * row), the ridge added on the diagonal as each row is reached */
    for (Py_ssize_t p = 0; p < k; p++) {
        double *up = h + p * kp;
        const double d = up[p] + reg / lam[p];
        if (!(d > 0.0))
            return 0;
        const double piv = sqrt(d), inv = 1.0 / piv;
        up[p] = piv;
        for (Py_ssize_t j = p + 1; j < k; j++)
            up[j] *= inv;
        for (Py_ssize_t i = p + 1; i < k; i++) {
            const double c = up[i];
            double *hi = h + i * kp;
#pragma omp simd
            for (Py_ssize_t j = i; j < k; j++)
                hi[j] -= c * up[j];
        }
    }
    /* U^T z = b, then U v = z (in b, both right-hand sides) */
    for (Py_ssize_t p = 0; p < k; p++) {
        const double *up = h + p * kp;
        const double z0 = b0[p] / up[p], z1 = b1[p] / up[p];
        b0[p] = z0;
        b1[p] = z1;
        for (Py_ssize_t i = p + 1; i < k; i++) {
            b0[i] -= up[i] * z0;
            b1[i] -= up[i] * z1;
        }
    }
    for (Py_ssize_t i = k - 1; i >= 0; i--) {
        const double *ui = h + i * kp;
        double d0 = 0.0, d1 = 0.0;
        for (Py_ssize_t j = i + 1; j < k; j++) {
            d0 += ui[j] * b0[j];
            d1 += ui[j] * b1[j];
        }
        b0[i] = (b0[i] - d0) / ui[i];
        b1[i] = (b1[i] - d1) / ui[i];
    }
    /* W = Q (v / lam) and the displacement Q v, row by row */
    double *c0 = c, *c1 = c + kp;
    for (Py_ssize_t i = 0; i < kp; i++) {
        c0[i] = i < k ? b0[i] / lam[i] : 0.0;
        c1[i] = i < k ? b1[i] / lam[i] : 0.0;
        if (i >= k)
            b0[i] = b1[i] = 0.0;
    }
    double s_p1 = 0.0, s_tt = 0.0, s_xt = 0.0, s_wd = 0.0, finite = 0.0;
    for (Py_ssize_t r = 0; r < m; r++) {
        const double *qr = qp + r * kp;
        double w0 = 0.0, w1 = 0.0, d0 = 0.0, d1 = 0.0;
#pragma omp simd reduction(+ : w0, w1, d0, d1)
        for (Py_ssize_t i = 0; i < kp; i++) {
            w0 += qr[i] * c0[i];
            w1 += qr[i] * c1[i];
            d0 += qr[i] * b0[i];
            d1 += qr[i] * b1[i];
        }
        w[2 * r] = w0;
        w[2 * r + 1] = w1;
        disp[2 * r] = d0;
        disp[2 * r + 1] = d1;
        if (sums != NULL) {
            const double t0 = y[2 * r] + d0, t1 = y[2 * r + 1] + d1;
            s_p1 += p1[r];
            s_tt += p1[r] * (t0 * t0 + t1 * t1);
            s_xt += px[2 * r] * t0 + px[2 * r + 1] * t1;
            s_wd += w0 * d0 + w1 * d1;
            finite += (w0 - w0) + (w1 - w1) + (t0 - t0) + (t1 - t1); /* NaN unless finite */
        }
    }
    if (sums != NULL) {
        sums[0] = s_p1;
        sums[1] = s_tt;
        sums[2] = s_xt;
        sums[3] = s_wd;
        sums[4] = finite == 0.0 ? 1.0 : 0.0;
    }
    return 1;
}

/* lowrank_mstep(qp, lam, y, p1, px, reg, w, disp[, plain[, sums]]) -> solved: CPD's
 * low-rank M-step (see above); qp (m, kp) float64 with kp a multiple of 8 and >= k (Q, zero
 * past column k), lam (k,), y and px (m, 2), p1 (m,) float64; w and disp (m, 2) float64
 * overwritten when solved. False (nothing written) when the k x k system is not
 * numerically positive definite: the caller solves it its own way. `plain` true takes the
 * plain tiles where the AVX2 ones would run (for the tests: a CPU without AVX2 runs them).
 * `sums` (5,) float64 (or None): when solved, the EM loop's next sums from the same pass
 * over the rows, with t = y + disp: sum p1, sum p1 |t|^2, sum px . t, sum w . disp, and
 * 1.0 when every w and t is finite (else 0.0). */
static PyObject *lowrank_mstep(PyObject *self, PyObject *args) {
    Py_buffer bq, bl, by, bp, bx, bw, bd, bs;
    double reg;
    int plain = 0, have_sums = 0;
    PyObject *sums_obj = Py_None;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*dw*w*|pO", &bq, &bl, &by, &bp, &bx, &reg, &bw, &bd,
                          &plain, &sums_obj))
        return NULL;
    PyObject *ret = NULL;
    double *work = NULL;
    Py_ssize_t m = bp.len / 8, k = bl.len / 8, kp = m > 0 ? bq.len / (8 * m) : 0;
    if ((have_sums = optional_buffer(sums_obj, &bs, 5, 8, "sums", 1)) < 0) {
        have_sums = 0;
        goto done;
    }
    if (m < 1 || k < 1 || kp < k || kp % 8 != 0) {
        PyErr_Format(PyExc_ValueError, "_ckernel: qp must be (m, kp) with kp a multiple of 8 "
                     "and >= k = %zd, m >= 1; got m = %zd, %zd bytes", k, m, bq.len);
        goto done;
    }
    if (check_len(&bq, m * kp, 8, "qp") || check_len(&by, 2 * m, 8, "y")
        || check_len(&bx, 2 * m, 8, "px") || check_len(&bw, 2 * m, 8, "w")
        || check_len(&bd, 2 * m, 8, "disp"))
        goto done;
    if ((work = workspace(m * kp + kp * kp + 4 * kp, sizeof(double))) == NULL)
        goto done;
    {
        double *s = work, *h = s + m * kp, *b = h + kp * kp, *c = b + 2 * kp;
        int solved;
        Py_BEGIN_ALLOW_THREADS
        solved = lowrank64(m, k, kp, bq.buf, bl.buf, by.buf, bp.buf, bx.buf, reg, plain, s,
                           h, b, c, bw.buf, bd.buf, have_sums ? (double *)bs.buf : NULL);
        Py_END_ALLOW_THREADS
        ret = PyBool_FromLong(solved);
    }
done:
    free(work);
    if (have_sums)
        PyBuffer_Release(&bs);
    PyBuffer_Release(&bq);
    PyBuffer_Release(&bl);
    PyBuffer_Release(&by);
    PyBuffer_Release(&bp);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&bw);
    PyBuffer_Release(&bd);
    return ret;
}

/* simd() -> the instruction set the CLONES functions run with on this CPU, as their
 * dispatch picks it: "x86-64-v4" (AVX-512 with FMA) or "x86-64-v3" (AVX2 with FMA) with GCC
 * 12 and later, "avx512f", "avx2" or "fma" with older GCC and clang, else "baseline". */
static PyObject *simd(PyObject *self, PyObject *args) {
    const char *isa = "baseline";
#if defined(CLONES_LEVELS)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("x86-64-v4"))
        isa = "x86-64-v4";
    else if (__builtin_cpu_supports("x86-64-v3"))
        isa = "x86-64-v3";
#elif defined(CLONES_FEATURES)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f"))
        isa = "avx512f";
    else if (__builtin_cpu_supports("avx2"))
        isa = "avx2";
    else if (__builtin_cpu_supports("fma"))
        isa = "fma";
#endif
    return PyUnicode_FromString(isa);
}

static PyMethodDef methods[] = {
    {"simd", simd, METH_NOARGS,
     "simd() -> the instruction set of the vectorised passes on this CPU"},
    {"kernels", kernels, METH_VARARGS,
     "kernels(t, xj, indptr, scale, out): out[k] = exp(-scale |t_m - xj_k|^2)"},
    {"sums", sums, METH_VARARGS,
     "sums(kern, indptr, j, x, c, floor, colsum, q, p1, px, pt1) -> sum log den"},
    {"dense", dense, METH_VARARGS,
     "dense(tt, x, scale, c, floor, f32, p1, px, pt1) -> sum log den"},
    {"posterior_max", posterior_max, METH_VARARGS,
     "posterior_max(tt, x, scale, c, floor, arg, best)"},
    {"product", product, METH_VARARGS, "product(z, ct, qt, scale, out): out = G(z, c) q"},
    {"pivoted_cholesky", pivoted_cholesky, METH_VARARGS,
     "pivoted_cholesky(y, scale, kmax, stop, l, d, k0) -> (k, done)"},
    {"nearest", nearest, METH_VARARGS,
     "nearest(a0, a1, b0, b1, n, m, row_arg, row_d2, col_arg, col_d2)"},
    {"pair_counts", pair_counts, METH_VARARGS,
     "pair_counts(t, xs0, xs1, starts, lens, r2, cap, counts) -> total, or -1 over cap"},
    {"interp", interp, METH_VARARGS,
     "interp(u, nodes, wb, out): barycentric weights of the nodes at u, out (n, r)"},
    {"lowrank_mstep", lowrank_mstep, METH_VARARGS,
     "lowrank_mstep(qp, lam, y, p1, px, reg, w, disp[, plain]) -> solved"},
    {"farthest", farthest, METH_VARARGS,
     "farthest(x, y, d2, chosen): the farthest-point picks after chosen[0]"},
    {"pair_fill", pair_fill, METH_VARARGS,
     "pair_fill(t, xs0, xs1, order, starts, lens, r2, j, xj, d2 or None)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_ckernel",
    "CPD's compiled passes: the truncated E-step's and the dense Gauss sums.", -1, methods,
};

PyMODINIT_FUNC PyInit__ckernel(void) {
#if defined(CLONES_LEVELS) || defined(CLONES_FEATURES)
    __builtin_cpu_init();
    use_avx2_fma = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#endif
    return PyModule_Create(&module);
}
