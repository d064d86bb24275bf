"""Compressed-row sparse products ``A x`` and ``A^T g`` as a small C kernel.

:class:`~torchsurf.flows._gather_matrix.GatherMatrix` applies its rows by
``F.embedding_bag``, which pays a fixed cost per row and entry that dominates for the few
columns a flow carries (one channel of one surface: 2.5 ms for 1.07 M entries against 0.46 ms by
this kernel; four columns 2.4 against 0.7 ms; AMD EPYC, one thread). This kernel sums each
row's entries into vector registers, the columns of ``x`` in blocks of 32, 16, 8 and 4 and the
rest one by one; a single column in blocks of 8 rows (:class:`RowBlocks`), each tap one vector
multiply-add over the 8 rows. Rows are split between threads. Its transpose scatters each row's
entries, on one thread. An autograd function pairs the two, so gradients (of any order) reach
``x``. :func:`limited` applies a packed closest-point stencil and its limiter in one pass,
its weights formed from the separable ones (:class:`SeparableStencil`); :func:`rkc_stage` and
:func:`rkc_step` run Runge-Kutta-Chebyshev stages of a linear packed rate, each operator
application and stage combination in one pass. :func:`brick_tricubic` applies a brick
closest-point stencil from its compact form (no matrix assembled), for bands too large to pack.

It runs on the CPU in float32 and float64 with 32-bit indices: as ctypes calls, and inside a
graph ``torch.compile`` traces as custom operators (``torch.ops.torchsurf``, torch 2.4 and
later) that call the same kernels; elsewhere :func:`applies` is false and the caller gathers by
``embedding_bag``. Compiled once per machine (:mod:`torchsurf._native`; about 2.3 s).
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

from .._inference import outside_inference
from .._native import NativeLibrary, carries_tangents, in_parts, in_threads
from .._transforms import refuse_batched_backward
from . import _limiter
from ._recompute import refuse_second_derivatives


class RowMatrix(Protocol):
    """What :func:`limited` and :func:`rkc_stage` read of a compressed-row matrix
    (:class:`~torchsurf.flows._gather_matrix.GatherMatrix` is one)."""

    offsets: Tensor
    columns: Tensor
    shape: tuple[int, int]

    def values(self, dtype: torch.dtype) -> Tensor: ...

    def apply(self, x: Tensor) -> Tensor: ...

    def blocks(self) -> RowBlocks: ...


_BODY = r"""
typedef REAL v8_SUFFIX __attribute__((vector_size(8 * sizeof(REAL))));
typedef REAL v4_SUFFIX __attribute__((vector_size(4 * sizeof(REAL))));

/* Rows [first, stop) of W = 8 NV8 + 4 NV4 + NS columns (NS < 4) in one pass: the sums held in
   vector registers. */
#define PRODUCT_SUFFIX(W, NV8, NV4, NS)                                                       \
static void product##W##_SUFFIX(const int32_t *restrict offsets,                             \
        const int32_t *restrict columns, const REAL *restrict weights,                        \
        const REAL *restrict x, int64_t ldx, REAL *restrict out, int64_t ldo,                 \
        int64_t first, int64_t stop)                                                          \
{                                                                                              \
    for (int64_t r = first; r < stop; ++r) {                                                   \
        v8_SUFFIX wide[NV8 + 1];                                                               \
        v4_SUFFIX half[NV4 + 1];                                                               \
        REAL s0 = 0, s1 = 0, s2 = 0;                                                           \
        memset(wide, 0, sizeof wide); memset(half, 0, sizeof half);                            \
        for (int32_t e = offsets[r]; e < offsets[r + 1]; ++e) {                                \
            const REAL w = weights[e];                                                         \
            const REAL *row = x + (int64_t)columns[e] * ldx;                                   \
            for (int k = 0; k < NV8; ++k) {                                                    \
                v8_SUFFIX value; memcpy(&value, row + 8 * k, sizeof value);                    \
                wide[k] += w * value;                                                          \
            }                                                                                  \
            for (int k = 0; k < NV4; ++k) {                                                    \
                v4_SUFFIX value; memcpy(&value, row + 8 * NV8, sizeof value);                  \
                half[k] += w * value;                                                          \
            }                                                                                  \
            const REAL *rest = row + 8 * NV8 + 4 * NV4;                                        \
            if (NS > 0) s0 += w * rest[0];                                                     \
            if (NS > 1) s1 += w * rest[1];                                                     \
            if (NS > 2) s2 += w * rest[2];                                                     \
        }                                                                                      \
        REAL *target = out + r * ldo;                                                          \
        memcpy(target, wide, sizeof(REAL) * 8 * NV8);                                          \
        memcpy(target + 8 * NV8, half, sizeof(REAL) * 4 * NV4);                                \
        REAL *rest = target + 8 * NV8 + 4 * NV4;                                               \
        if (NS > 0) rest[0] = s0;                                                              \
        if (NS > 1) rest[1] = s1;                                                              \
        if (NS > 2) rest[2] = s2;                                                              \
    }                                                                                          \
}

/* One column: four sums over every fourth entry, so that the additions overlap. */
static void product1_SUFFIX(const int32_t *restrict offsets, const int32_t *restrict columns,
        const REAL *restrict weights, const REAL *restrict x, int64_t ldx, REAL *restrict out,
        int64_t ldo, int64_t first, int64_t stop)
{
    for (int64_t r = first; r < stop; ++r) {
        REAL a = 0, b = 0, c = 0, d = 0;
        int32_t e = offsets[r], end = offsets[r + 1];
        for (; e + 3 < end; e += 4) {
            a += weights[e] * x[(int64_t)columns[e] * ldx];
            b += weights[e + 1] * x[(int64_t)columns[e + 1] * ldx];
            c += weights[e + 2] * x[(int64_t)columns[e + 2] * ldx];
            d += weights[e + 3] * x[(int64_t)columns[e + 3] * ldx];
        }
        for (; e < end; ++e) a += weights[e] * x[(int64_t)columns[e] * ldx];
        out[r * ldo] = (a + b) + (c + d);
    }
}

#define WIDTHS_SUFFIX(NV8) PRODUCT_SUFFIX(NV8##0, NV8, 0, 0) PRODUCT_SUFFIX(NV8##1, NV8, 0, 1) \
    PRODUCT_SUFFIX(NV8##2, NV8, 0, 2) PRODUCT_SUFFIX(NV8##3, NV8, 0, 3)                        \
    PRODUCT_SUFFIX(NV8##4, NV8, 1, 0) PRODUCT_SUFFIX(NV8##5, NV8, 1, 1)                        \
    PRODUCT_SUFFIX(NV8##6, NV8, 1, 2) PRODUCT_SUFFIX(NV8##7, NV8, 1, 3)
WIDTHS_SUFFIX(0) WIDTHS_SUFFIX(1) WIDTHS_SUFFIX(2) WIDTHS_SUFFIX(3) WIDTHS_SUFFIX(4)

typedef void (*product_kernel_SUFFIX)(const int32_t *restrict, const int32_t *restrict,
        const REAL *restrict, const REAL *restrict, int64_t, REAL *restrict, int64_t, int64_t,
        int64_t);
/* Indexed by 8 NV8 + (4 NV4 + NS): the kernel of each width up to 32 (00: none). */
static const product_kernel_SUFFIX products_SUFFIX[33] = {
    0, product1_SUFFIX, product02_SUFFIX, product03_SUFFIX, product04_SUFFIX,
    product05_SUFFIX, product06_SUFFIX, product07_SUFFIX,
    product10_SUFFIX, product11_SUFFIX, product12_SUFFIX, product13_SUFFIX, product14_SUFFIX,
    product15_SUFFIX, product16_SUFFIX, product17_SUFFIX,
    product20_SUFFIX, product21_SUFFIX, product22_SUFFIX, product23_SUFFIX, product24_SUFFIX,
    product25_SUFFIX, product26_SUFFIX, product27_SUFFIX,
    product30_SUFFIX, product31_SUFFIX, product32_SUFFIX, product33_SUFFIX, product34_SUFFIX,
    product35_SUFFIX, product36_SUFFIX, product37_SUFFIX,
    product40_SUFFIX};

/* out[r, :] = sum over the entries e of row r of weights[e] x[columns[e], :], rows [first, stop);
   x (columns, F) and out (rows, F) contiguous; 32 columns a pass. */
void product_SUFFIX(const int32_t *offsets, const int32_t *columns, const REAL *weights,
        const REAL *x, REAL *out, int64_t first, int64_t stop, int64_t F)
{
    for (int64_t f = 0; f < F; f += 32) {
        int64_t width = F - f < 32 ? F - f : 32;
        products_SUFFIX[width](offsets, columns, weights, x + f, F, out + f, F, first, stop);
    }
}

/* One column, rows in blocks of 8: block b holds the taps of its 8 rows at
   [starts[b] + 8 k + lane] (tap k of the 8 rows side by side), so that the 8 rows' sums fill
   one vector register and each tap is one vector multiply-add. The first shared[b] taps (the
   block's shortest row's count) run so; the rest row by row up to each row's count[8 b + lane]
   (the padded slots are never read). sums[lane] = sum_k w_k (x[c_k] - shift) over block b's
   rows. */
static inline void block_sums_SUFFIX(const int64_t *starts, const int32_t *shared,
        const int32_t *count, const int32_t *columns, const REAL *weights, const REAL *x,
        REAL shift, int64_t b, REAL sums[8])
{
    const int32_t *c = columns + starts[b];
    const REAL *w = weights + starts[b];
    const v8_SUFFIX offset = {shift, shift, shift, shift, shift, shift, shift, shift};
    v8_SUFFIX even = {0}, odd = {0};
    int32_t k = 0, common = shared[b];
    for (; k + 1 < common; k += 2, c += 16, w += 16) {
        v8_SUFFIX a = {x[c[0]], x[c[1]], x[c[2]], x[c[3]], x[c[4]], x[c[5]], x[c[6]], x[c[7]]};
        v8_SUFFIX b8 = {x[c[8]], x[c[9]], x[c[10]], x[c[11]], x[c[12]], x[c[13]], x[c[14]],
                        x[c[15]]};
        v8_SUFFIX wa, wb;
        memcpy(&wa, w, sizeof wa);
        memcpy(&wb, w + 8, sizeof wb);
        even += wa * (a - offset);
        odd += wb * (b8 - offset);
    }
    if (k < common) {
        v8_SUFFIX a = {x[c[0]], x[c[1]], x[c[2]], x[c[3]], x[c[4]], x[c[5]], x[c[6]], x[c[7]]};
        v8_SUFFIX wa;
        memcpy(&wa, w, sizeof wa);
        even += wa * (a - offset);
        ++k; c += 8; w += 8;
    }
    even += odd;
    memcpy(sums, &even, 8 * sizeof(REAL));
    for (int lane = 0; lane < 8; ++lane)
        for (int32_t j = k; j < count[8 * b + lane]; ++j)
            sums[lane] += w[8 * (j - k) + lane] * (x[c[8 * (j - k) + lane]] - shift);
}

/* The product in blocks of 8 rows (block_sums, no shift): blocks [first, stop), out (8 blocks,). */
void product_blocks_SUFFIX(const int64_t *starts, const int32_t *shared, const int32_t *count,
        const int32_t *columns, const REAL *weights, const REAL *x, REAL *out, int64_t first,
        int64_t stop)
{
    for (int64_t b = first; b < stop; ++b)
        block_sums_SUFFIX(starts, shared, count, columns, weights, x, 0, b, out + 8 * b);
}

/* One Runge-Kutta-Chebyshev stage of u' = A u on packed values (A's rows in blocks of 8, as
   product_blocks), blocks [first, stop) of the rows r < rows: with s = sum_k w_k (current[c_k]
   - current[0]) (A's row; the shift leaves the sums the rounding of the data's variation),
   following[r] = (current[r] - u[r]) mu + a s + b rate0[r] + (previous[r] - u[r]) nu + u[r],
   added in that order (the eager stage's); rate0 NULL reads zeros; rate, if not NULL,
   receives s. */
void rkc_stage_SUFFIX(const int64_t *starts, const int32_t *shared, const int32_t *count,
        const int32_t *columns, const REAL *weights, const REAL *current, const REAL *u,
        const REAL *previous, const REAL *rate0, REAL *following, REAL *rate, REAL mu, REAL nu,
        REAL a, REAL b, int64_t rows, int64_t first, int64_t stop)
{
    const REAL shift = current[0];
    const v8_SUFFIX vmu = {mu, mu, mu, mu, mu, mu, mu, mu}, vnu = {nu, nu, nu, nu, nu, nu, nu, nu},
                    va = {a, a, a, a, a, a, a, a}, vb = {b, b, b, b, b, b, b, b};
    for (int64_t block = first; block < stop; ++block) {
        REAL sums[8];
        block_sums_SUFFIX(starts, shared, count, columns, weights, current, shift, block, sums);
        const int64_t r0 = 8 * block;
        if (r0 + 8 <= rows) {   /* the block's 8 rows as vectors */
            v8_SUFFIX s8, c8, u8, p8, v;
            memcpy(&s8, sums, sizeof s8);
            memcpy(&c8, current + r0, sizeof c8);
            memcpy(&u8, u + r0, sizeof u8);
            memcpy(&p8, previous + r0, sizeof p8);
            v = (c8 - u8) * vmu;
            v += va * s8;
            if (rate0) {
                v8_SUFFIX q8;
                memcpy(&q8, rate0 + r0, sizeof q8);
                v += vb * q8;
            }
            v += (p8 - u8) * vnu;
            v += u8;
            memcpy(following + r0, &v, sizeof v);
            if (rate) memcpy(rate + r0, &s8, sizeof s8);
            continue;
        }
        for (int64_t r = r0; r < rows; ++r) {
            const REAL s = sums[r - r0];
            REAL v = (current[r] - u[r]) * mu;
            v += a * s;
            if (rate0) v += b * rate0[r];
            v += (previous[r] - u[r]) * nu;
            following[r] = v + u[r];
            if (rate) rate[r] = s;
        }
    }
}

/* out[rows[r], :] = value[r, :] clamped to the limiter's bounds (torchsurf.flows._limiter):
   low = sum_c corners[r, c] min(x[taps[r, t], :] over the 27 taps t around corner c), high
   likewise, the taps taps[r, 0:64] in the order 16 z + 4 y + x. Where codes is not NULL it
   records per target and column 0 (not clamped: the gradient reaches the 64 taps), 1 (clamped
   below) or 2 (above), and for the clamped, in extremes[r, f, 0:8], the tap holding each
   corner's extreme (the first such, strict comparisons; a value equal to a bound is not
   clamped). */
static REAL min3_SUFFIX(REAL a, REAL b, REAL c) { REAL m = a < b ? a : b; return m < c ? m : c; }
static REAL max3_SUFFIX(REAL a, REAL b, REAL c) { REAL m = a > b ? a : b; return m > c ? m : c; }

/* The tap holding corner c's least (sign 1) or largest (sign -1) value among its 27: the first
   such in the order 16 z + 4 y + x, as torch's min and max over the block pick. */
static uint8_t extreme_tap_SUFFIX(const REAL *u, int c, int sign)
{
    const int cx = 1 + (c & 1), cy = 1 + ((c >> 1) & 1), cz = 1 + (c >> 2);
    int best = 16 * (cz - 1) + 4 * (cy - 1) + (cx - 1);
    for (int z = cz - 1; z <= cz + 1; ++z)
        for (int y = cy - 1; y <= cy + 1; ++y)
            for (int x = cx - 1; x <= cx + 1; ++x) {
                const int t = 16 * z + 4 * y + x;
                if (sign * u[t] < sign * u[best]) best = t;
            }
    return (uint8_t)best;
}

static const int CELL_TAPS_SUFFIX[8] = {21, 22, 25, 26, 37, 38, 41, 42};

static REAL within_SUFFIX(REAL value, const REAL *extremes)
{
    REAL least = extremes[0], most = extremes[0];
    for (int c = 1; c < 8; ++c) {
        least = extremes[c] < least ? extremes[c] : least;
        most = extremes[c] > most ? extremes[c] : most;
    }
    return value < least ? least : (value > most ? most : value);
}

/* The limiter's bounds of one value from its 64 taps u (16 z + 4 y + x): sliding extremes of 3
   along x, then y, then z give each corner's 27, weighted by the corners' weights. */
static void bounds_SUFFIX(const REAL *u, const REAL *weight, REAL *low, REAL *high)
{
    REAL lx[32], hx[32], ly[16], hy[16];
    for (int row = 0; row < 16; ++row)
        for (int c = 0; c < 2; ++c) {
            const REAL *v = u + 4 * row + c;
            lx[2 * row + c] = min3_SUFFIX(v[0], v[1], v[2]);
            hx[2 * row + c] = max3_SUFFIX(v[0], v[1], v[2]);
        }
    for (int z = 0; z < 4; ++z)
        for (int c = 0; c < 4; ++c) {   /* c = 2 cy + cx */
            const int base = 8 * z + (c & 1) + 2 * (c >> 1);
            ly[4 * z + c] = min3_SUFFIX(lx[base], lx[base + 2], lx[base + 4]);
            hy[4 * z + c] = max3_SUFFIX(hx[base], hx[base + 2], hx[base + 4]);
        }
    REAL lows = 0, highs = 0, l[8], h[8];
    for (int c = 0; c < 8; ++c) {   /* c = 4 cz + 2 cy + cx */
        const int z = c >> 2, plane = c & 3;
        l[c] = min3_SUFFIX(ly[4 * z + plane], ly[4 * (z + 1) + plane], ly[4 * (z + 2) + plane]);
        h[c] = max3_SUFFIX(hy[4 * z + plane], hy[4 * (z + 1) + plane], hy[4 * (z + 2) + plane]);
        lows += weight[c] * l[c];
        highs += weight[c] * h[c];
    }
    /* each within its corners' range, which the sums' rounding would leave by an ulp */
    *low = within_SUFFIX(lows, l);
    *high = within_SUFFIX(highs, h);
}

/* v clamped to the limiter's bounds from its 64 taps' values u and its corners' weights: the
   code 0 (kept), 1 (raised to the lower bound) or 2 (lowered to the upper); NaN among the taps
   makes v NaN, as torch's clamp keeps a NaN. */
static uint8_t clamp_to_bounds_SUFFIX(REAL *v, const REAL *u, const REAL *corners)
{
    REAL low, high, magnitude = 0;
    int nan = 0;
    for (int t = 0; t < 64; ++t) {
        nan |= u[t] != u[t];
        magnitude = fabs(u[t]) > magnitude ? fabs(u[t]) : magnitude;
    }
    bounds_SUFFIX(u, corners, &low, &high);
    if (nan) { *v = (REAL)NAN; return 0; }
    /* on bounds one to rounding (data constant there), a value within TIES units of roundoff
       of them is clamped with the code 0: its gradient is the stencil's
       (torchsurf.flows._limiter.TIES) */
    const REAL slack = magnitude * (REAL)TIES * (sizeof(REAL) == 4 ? (REAL)FLT_EPSILON
                                                                   : (REAL)DBL_EPSILON);
    const int tie = high - low <= slack && *v >= low - slack && *v <= high + slack;
    if (*v < low) { *v = low; return tie ? 0 : 1; }
    if (*v > high) { *v = high; return tie ? 0 : 2; }
    return 0;
}

void clamp_into_SUFFIX(const int32_t *taps, const REAL *corners, const int64_t *rows,
        const REAL *x, const REAL *value, REAL *out, uint8_t *codes, uint8_t *extremes,
        int64_t first, int64_t stop, int64_t F)
{
    for (int64_t r = first; r < stop; ++r) {
        const int32_t *tap = taps + r * 64;
        REAL *target = out + rows[r] * F;
        for (int64_t f = 0; f < F; ++f) {
            REAL v = value[r * F + f];
            uint8_t code = 0;
            /* the bounds hold the range of the cell's 8 nodes: a value inside it stays */
            REAL least = x[(int64_t)tap[CELL_TAPS_SUFFIX[0]] * F + f], most = least;
            for (int k = 1; k < 8; ++k) {
                const REAL w = x[(int64_t)tap[CELL_TAPS_SUFFIX[k]] * F + f];
                least = w < least ? w : least;
                most = w > most ? w : most;
            }
            if (!(v >= least && v <= most) && v == v) {
                REAL u[64];
                for (int t = 0; t < 64; ++t) u[t] = x[(int64_t)tap[t] * F + f];
                code = clamp_to_bounds_SUFFIX(&v, u, corners + r * 8);
                if (code && codes)
                    for (int c = 0; c < 8; ++c)
                        extremes[(r * F + f) * 8 + c] = extreme_tap_SUFFIX(u, c, code == 1 ? 1 : -1);
            }
            target[f] = v;
            if (codes) codes[r * F + f] = code;
        }
    }
}

/* rkc_stage for F columns (values row-major (nodes, F), F <= 32) and A's compressed rows
   (offsets, columns, weights), row by row: each column shifted by its first value. Rows
   [first, stop) of the rows < rows; F a constant where inlined with one. */
static inline void rkc_stage_rows_of_SUFFIX(const int32_t *restrict offsets,
        const int32_t *restrict columns, const REAL *restrict weights,
        const REAL *restrict current, const REAL *restrict u, const REAL *restrict previous,
        const REAL *restrict rate0, REAL *restrict following, REAL *restrict rate, REAL mu,
        REAL nu, REAL a, REAL b, int64_t F, int64_t first, int64_t stop)
{
    REAL shift[32];
    for (int64_t f = 0; f < F; ++f) shift[f] = current[f];
    for (int64_t r = first; r < stop; ++r) {
        REAL sums[32];
        for (int64_t f = 0; f < F; ++f) sums[f] = 0;
        for (int32_t e = offsets[r]; e < offsets[r + 1]; ++e) {
            const REAL w = weights[e], *x = current + (int64_t)columns[e] * F;
            for (int64_t f = 0; f < F; ++f) sums[f] += w * (x[f] - shift[f]);
        }
        for (int64_t f = 0; f < F; ++f) {
            const int64_t i = r * F + f;
            REAL v = (current[i] - u[i]) * mu;
            v += a * sums[f];
            if (rate0) v += b * rate0[i];
            v += (previous[i] - u[i]) * nu;
            following[i] = v + u[i];
            if (rate) rate[i] = sums[f];
        }
    }
}

void rkc_stage_rows_SUFFIX(const int32_t *offsets, const int32_t *columns, const REAL *weights,
        const REAL *current, const REAL *u, const REAL *previous, const REAL *rate0,
        REAL *following, REAL *rate, REAL mu, REAL nu, REAL a, REAL b, int64_t F,
        int64_t first, int64_t stop)
{
#define STAGE_ROWS_SUFFIX(W) rkc_stage_rows_of_SUFFIX(offsets, columns, weights, current, u, \
        previous, rate0, following, rate, mu, nu, a, b, W, first, stop)
    switch (F) {
    case 2: STAGE_ROWS_SUFFIX(2); break;
    case 3: STAGE_ROWS_SUFFIX(3); break;
    case 4: STAGE_ROWS_SUFFIX(4); break;
    default: STAGE_ROWS_SUFFIX(F);
    }
#undef STAGE_ROWS_SUFFIX
}

/* A whole Runge-Kutta-Chebyshev step of u' = A u (rows as rkc_stage's, all blocks on this
   thread): stage 1 into stage[1 % 3] with its rate into rate0 (rows,), then stages j = 2..s
   into the three buffers in turn (stage[j % 3]; stage j - 2 and j - 1 are read from the other
   two, u for stage 0), with weights[4 j .. 4 j + 3] = (mu, nu, a, b) of stage j (a and b the
   rate's factors times dt). Each buffer is (nodes,), its rows >= rows already holding u's
   values (the rate is zero there). The step ends in stage[s % 3]. */
void rkc_step_SUFFIX(const int64_t *starts, const int32_t *shared, const int32_t *count,
        const int32_t *columns, const REAL *laid, const REAL *u, REAL *stage0, REAL *stage1,
        REAL *stage2, REAL *rate0, const double *weights, int64_t stages, int64_t rows,
        int64_t blocks)
{
    REAL *stage[3] = {stage0, stage1, stage2};
    rkc_stage_SUFFIX(starts, shared, count, columns, laid, u, u, u, NULL, stage[1], rate0, 0, 0,
                     (REAL)weights[4 + 2], 0, rows, 0, blocks);
    for (int64_t j = 2; j <= stages; ++j) {
        const REAL *current = stage[(j - 1) % 3], *previous = j == 2 ? u : stage[(j - 2) % 3];
        const double *w = weights + 4 * j;
        rkc_stage_SUFFIX(starts, shared, count, columns, laid, current, u, previous, rate0,
                         stage[j % 3], NULL, (REAL)w[0], (REAL)w[1], (REAL)w[2], (REAL)w[3], rows,
                         0, blocks);
    }
}

/* A limited tricubic stencil in one pass (its product, then clamp_into's test and bounds) for
   R rows in blocks of 8: block b's tap t (16 z + 4 y + x) of a lane at columns[(64 b + t) 8 +
   lane], the row's separable weights at axes[((3 b + axis) 4 + k) 8 + lane] (axis 0 x, 1 y,
   2 z), the tap's weight wz wy wx formed as tap_weights does ((wz wy) wx). For the F columns
   of x (nodes, F): out[rows[r], f] = row r's sum, clamped to the limiter's bounds with
   corners[r, 0:8] where it lies outside its cell's range. Blocks [first, stop). */
static inline void limited_tricubic_block_SUFFIX(const int32_t *restrict c,
        const REAL *restrict axes, const REAL *corners, const int64_t *rows, const REAL *x,
        REAL *out, int64_t R, int64_t F, int64_t b)
{
    v8_SUFFIX w[3][4];
    memcpy(w, axes, sizeof w);
    const int lanes = R - 8 * b < 8 ? (int)(R - 8 * b) : 8;
    for (int64_t f = 0; f < F; ++f) {
        v8_SUFFIX even = {0}, odd = {0};
        for (int k = 0; k < 4; ++k)
            for (int j = 0; j < 4; ++j) {
                const v8_SUFFIX zy = w[2][k] * w[1][j];
                for (int i = 0; i < 4; ++i) {
                    const int32_t *t = c + 8 * (16 * k + 4 * j + i);
                    v8_SUFFIX a = {x[t[0] * F + f], x[t[1] * F + f], x[t[2] * F + f],
                                   x[t[3] * F + f], x[t[4] * F + f], x[t[5] * F + f],
                                   x[t[6] * F + f], x[t[7] * F + f]};
                    if (i & 1) odd += (zy * w[0][i]) * a;
                    else even += (zy * w[0][i]) * a;
                }
            }
        even += odd;
        REAL sums[8];
        memcpy(sums, &even, sizeof sums);
        for (int lane = 0; lane < lanes; ++lane) {
            const int64_t r = 8 * b + lane;
            REAL v = sums[lane];
            REAL least = x[c[8 * CELL_TAPS_SUFFIX[0] + lane] * F + f], most = least;
            for (int n = 1; n < 8; ++n) {
                const REAL node = x[c[8 * CELL_TAPS_SUFFIX[n] + lane] * F + f];
                least = node < least ? node : least;
                most = node > most ? node : most;
            }
            if (!(v >= least && v <= most) && v == v) {
                REAL u[64];
                for (int t = 0; t < 64; ++t) u[t] = x[c[8 * t + lane] * F + f];
                clamp_to_bounds_SUFFIX(&v, u, corners + r * 8);
            }
            out[rows[r] * F + f] = v;
        }
    }
}

void limited_tricubic_SUFFIX(const int32_t *columns, const REAL *axes, const REAL *corners,
        const int64_t *rows, const REAL *x, REAL *out, int64_t R, int64_t F, int64_t first,
        int64_t stop)
{
    if (F == 1)   /* a constant F: no index products */
        for (int64_t b = first; b < stop; ++b)
            limited_tricubic_block_SUFFIX(columns + 512 * b, axes + 96 * b, corners, rows, x,
                                          out, R, 1, b);
    else
        for (int64_t b = first; b < stop; ++b)
            limited_tricubic_block_SUFFIX(columns + 512 * b, axes + 96 * b, corners, rows, x,
                                          out, R, F, b);
}

/* limited_tricubic for rows whose taps lie 4 by 4 side by side along x: row r's run k j (16 of
   them, z then y) holds taps starts[16 r + 4 k + j] + 0..3, its separable weights
   axes[12 r + 4 axis + i] (axis 0 x, 1 y, 2 z); the F <= 8 columns of x (nodes, F) row-major,
   so that a run's 4 F values lie side by side, read as F vectors of 4. Rows [first, stop). */
static inline void limited_runs_of_SUFFIX(const int32_t *restrict starts,
        const REAL *restrict axes, const REAL *corners, const int64_t *rows, const REAL *x,
        REAL *out, int64_t F, int64_t first, int64_t stop)
{
    for (int64_t r = first; r < stop; ++r) {
        const int32_t *run = starts + 16 * r;
        const REAL *wx = axes + 12 * r, *wy = axes + 12 * r + 4, *wz = axes + 12 * r + 8;
        /* the run's 4 F values side by side, in F vectors of 4: value m (node m / F, column
           m % F) weighted by wx[m / F] */
        v4_SUFFIX pattern[8], acc[8];
        for (int64_t c = 0; c < F; ++c)
            for (int e = 0; e < 4; ++e) {
                pattern[c][e] = wx[(4 * c + e) / F];
                acc[c][e] = 0;
            }
        for (int k = 0; k < 4; ++k)
            for (int j = 0; j < 4; ++j) {
                const REAL zy = wz[k] * wy[j], *t = x + (int64_t)run[4 * k + j] * F;
                for (int64_t c = 0; c < F; ++c) {
                    v4_SUFFIX values;
                    memcpy(&values, t + 4 * c, sizeof values);
                    acc[c] += (zy * pattern[c]) * values;
                }
            }
        for (int64_t f = 0; f < F; ++f) {
            REAL v;
            if (F == 1) {
                v = (acc[0][0] + acc[0][1]) + (acc[0][2] + acc[0][3]);
            } else {
                v = 0;
                for (int64_t m = f; m < 4 * F; m += F) v += acc[m / 4][m % 4];
            }
#define NODE_SUFFIX(k, j, i) x[((int64_t)run[4 * (k) + (j)] + (i)) * F + f]
            REAL least = NODE_SUFFIX(1, 1, 1), most = least;
            for (int k = 1; k < 3; ++k)
                for (int j = 1; j < 3; ++j)
                    for (int i = 1; i < 3; ++i) {
                        const REAL node = NODE_SUFFIX(k, j, i);
                        least = node < least ? node : least;
                        most = node > most ? node : most;
                    }
            if (!(v >= least && v <= most) && v == v) {
                REAL u[64];
                for (int t = 0; t < 64; ++t) u[t] = NODE_SUFFIX(t >> 4, (t >> 2) & 3, t & 3);
                clamp_to_bounds_SUFFIX(&v, u, corners + r * 8);
            }
#undef NODE_SUFFIX
            out[rows[r] * F + f] = v;
        }
    }
}

void limited_runs_SUFFIX(const int32_t *starts, const REAL *axes, const REAL *corners,
        const int64_t *rows, const REAL *x, REAL *out, int64_t F, int64_t first, int64_t stop)
{
    switch (F) {   /* a constant F: no index products */
    case 1: limited_runs_of_SUFFIX(starts, axes, corners, rows, x, out, 1, first, stop); break;
    case 2: limited_runs_of_SUFFIX(starts, axes, corners, rows, x, out, 2, first, stop); break;
    case 3: limited_runs_of_SUFFIX(starts, axes, corners, rows, x, out, 3, first, stop); break;
    case 4: limited_runs_of_SUFFIX(starts, axes, corners, rows, x, out, 4, first, stop); break;
    default: limited_runs_of_SUFFIX(starts, axes, corners, rows, x, out, F, first, stop);
    }   /* F <= 8: SeparableStencil.parts */
}

/* The clamp's backward: for each target r and column, the gradient g[rows[r]] goes to the
   values' taps (into free[r], for the transposed product) if not clamped, else to the taps
   holding its corners' extremes, with the corners' weights (added into grad, whose target rows
   the caller zeroed); extremes holds only the clamped entries', in the order of (r, f); one
   thread. */
void clamp_back_SUFFIX(const int32_t *taps, const REAL *corners, const int64_t *rows,
        const uint8_t *codes, const uint8_t *extremes, const REAL *g, REAL *grad, REAL *free,
        int64_t count, int64_t F)
{
    const uint8_t *at = extremes;
    for (int64_t r = 0; r < count; ++r)
        for (int64_t f = 0; f < F; ++f) {
            REAL incoming = g[rows[r] * F + f];
            uint8_t code = codes[r * F + f];
            free[r * F + f] = code ? (REAL)0 : incoming;
            if (!code) continue;
            for (int c = 0; c < 8; ++c)
                grad[(int64_t)taps[r * 64 + at[c]] * F + f] += corners[r * 8 + c] * incoming;
            at += 8;
        }
}

/* A brick closest-point stencil's tricubic interpolation (BrickCubicStencil's compact form),
   nodes [first, stop) of N: tap (k, j, i) of node r (z, y, x; 16 k + 4 j + i) lies at the
   packed position bases[(4 sz[k] + 2 sy[j] + sx[i]) N + r] + lz[k] + ly[j] + lx[i], where
   s* = second[axis][r][0:4] (axis 0 z, 1 y, 2 x) says whether the tap lies in the block's second
   brick along that axis and l* = local[axis][r][0:4] is its in-brick offset; its weight is
   wz[k] wy[j] wx[i] with w* = weights[axis][r][0:4] (axis 0 x, 1 y, 2 z). Written to
   out[f ldo + r - first] for the F channels of flat (channel f at flat + f M). With limit,
   a value outside the range of its cell's 8 nodes is clamped to the limiter's bounds
   (clamp_into's test and bounds). */
void brick_tricubic_SUFFIX(const int32_t *bases, const uint8_t *second, const int16_t *local,
        const REAL *weights, const REAL *flat, int64_t M, REAL *restrict out, int64_t ldo,
        int64_t N, int64_t F, int64_t limit, int64_t first, int64_t stop)
{
    for (int64_t r = first; r < stop; ++r) {
        const uint8_t *sz = second + 4 * r, *sy = second + 4 * (N + r),
                      *sx = second + 4 * (2 * N + r);
        const int16_t *lz = local + 4 * r, *ly = local + 4 * (N + r), *lx = local + 4 * (2 * N + r);
        const REAL *wx = weights + 4 * r, *wy = weights + 4 * (N + r), *wz = weights + 4 * (2 * N + r);
        /* row[4 k + j][b]: the position of tap (k, j, 0) moved to the brick b along x, less
           that tap's x offset; tap (k, j, i) = row[4 k + j][sx[i]] + lx[i] */
        int64_t row[16][2], corner[8];
        for (int c = 0; c < 8; ++c) corner[c] = bases[c * N + r];
        for (int k = 0; k < 4; ++k)
            for (int j = 0; j < 4; ++j) {
                const int b = 4 * sz[k] + 2 * sy[j];
                const int64_t offset = (int64_t)lz[k] + ly[j];
                row[4 * k + j][0] = corner[b] + offset;
                row[4 * k + j][1] = corner[b + 1] + offset;
            }
        int64_t column[4][2];
        for (int i = 0; i < 4; ++i) { column[i][0] = sx[i]; column[i][1] = lx[i]; }
        /* all 4 taps along x in one brick, one after the other (not clamped at a face) */
        const int contiguous = sx[0] == sx[3] && lx[3] - lx[0] == 3;
        if (contiguous) for (int k = 0; k < 16; ++k) row[k][0] = row[k][sx[0]];
        const v4_SUFFIX along_x = {wx[0], wx[1], wx[2], wx[3]};
#define TAP_SUFFIX(k, j, i) (row[4 * (k) + (j)][column[i][0]] + column[i][1])
        REAL corners[8];
        if (limit) {
            REAL fx, fy, fz;
            fx = wx[2] + 2 * wx[3] - wx[0]; fx = fx < 0 ? 0 : (fx > 1 ? 1 : fx);
            fy = wy[2] + 2 * wy[3] - wy[0]; fy = fy < 0 ? 0 : (fy > 1 ? 1 : fy);
            fz = wz[2] + 2 * wz[3] - wz[0]; fz = fz < 0 ? 0 : (fz > 1 ? 1 : fz);
            for (int c = 0; c < 8; ++c)
                corners[c] = ((c >> 2) ? fz : 1 - fz) * (((c >> 1) & 1) ? fy : 1 - fy)
                             * ((c & 1) ? fx : 1 - fx);
        }
        for (int64_t f = 0; f < F; ++f) {
            const REAL *x = flat + f * M;
            v4_SUFFIX sum = {0, 0, 0, 0};
            if (contiguous) {   /* each row's 4 taps side by side: one vector load a row */
                for (int k = 0; k < 4; ++k)
                    for (int j = 0; j < 4; ++j) {
                        v4_SUFFIX taps;
                        memcpy(&taps, x + row[4 * k + j][0] + column[0][1], sizeof taps);
                        sum += (wz[k] * wy[j]) * (along_x * taps);
                    }
            } else {
                for (int k = 0; k < 4; ++k)
                    for (int j = 0; j < 4; ++j) {
                        v4_SUFFIX taps = {x[TAP_SUFFIX(k, j, 0)], x[TAP_SUFFIX(k, j, 1)],
                                          x[TAP_SUFFIX(k, j, 2)], x[TAP_SUFFIX(k, j, 3)]};
                        sum += (wz[k] * wy[j]) * (along_x * taps);
                    }
            }
            REAL v = (sum[0] + sum[1]) + (sum[2] + sum[3]);
            if (limit) {
                REAL least = x[TAP_SUFFIX(1, 1, 1)], most = least;
                for (int k = 1; k < 3; ++k)
                    for (int j = 1; j < 3; ++j)
                        for (int i = 1; i < 3; ++i) {
                            const REAL node = x[TAP_SUFFIX(k, j, i)];
                            least = node < least ? node : least;
                            most = node > most ? node : most;
                        }
                if (!(v >= least && v <= most) && v == v) {
                    REAL u[64];
                    for (int t = 0; t < 64; ++t) u[t] = x[TAP_SUFFIX(t >> 4, (t >> 2) & 3, t & 3)];
                    clamp_to_bounds_SUFFIX(&v, u, corners);
                }
            }
            out[f * ldo + r - first] = v;
        }
#undef TAP_SUFFIX
    }
}

/* out[columns[e], :] += weights[e] g[r, :] over every entry: the transposed product, into a
   zeroed out (columns, F); g (rows, F) contiguous. */
void scatter_SUFFIX(const int32_t *offsets, const int32_t *columns, const REAL *weights,
        const REAL *g, REAL *out, int64_t rows, int64_t F)
{
    for (int64_t r = 0; r < rows; ++r) {
        const REAL *source = g + r * F;
        for (int32_t e = offsets[r]; e < offsets[r + 1]; ++e) {
            const REAL w = weights[e];
            REAL *target = out + (int64_t)columns[e] * F;
            int64_t f = 0;
            for (; f + 8 <= F; f += 8) {
                v8_SUFFIX a, b;
                memcpy(&a, target + f, sizeof a);
                memcpy(&b, source + f, sizeof b);
                a += w * b;
                memcpy(target + f, &a, sizeof a);
            }
            for (; f < F; ++f) target[f] += w * source[f];
        }
    }
}
"""


_TAPS_READABLE = r"""
/* keep[r - first]: whether every tap of the brick stencil's node r (compact form, as in
   brick_tricubic) lies in a stored brick (its base not negative) on a node of readable. */
void brick_taps_readable(const int32_t *bases, const uint8_t *second, const int16_t *local,
        const uint8_t *readable, int64_t N, uint8_t *keep, int64_t first, int64_t stop)
{
    for (int64_t r = first; r < stop; ++r) {
        const uint8_t *sz = second + 4 * r, *sy = second + 4 * (N + r),
                      *sx = second + 4 * (2 * N + r);
        const int16_t *lz = local + 4 * r, *ly = local + 4 * (N + r), *lx = local + 4 * (2 * N + r);
        int ok = 1;
        for (int k = 0; k < 4 && ok; ++k)
            for (int j = 0; j < 4 && ok; ++j) {
                const int b = 4 * sz[k] + 2 * sy[j];
                const int64_t offset = (int64_t)lz[k] + ly[j];
                for (int i = 0; i < 4; ++i) {
                    const int64_t base = bases[(b + sx[i]) * N + r];
                    if (base < 0 || !readable[base + offset + lx[i]]) { ok = 0; break; }
                }
            }
        keep[r - first] = (uint8_t)ok;
    }
}
"""


def _source() -> str:
    source = ("#include <float.h>\n#include <math.h>\n#include <stdint.h>\n#include <string.h>\n"
              f"#define TIES {_limiter.TIES}\n")
    for real, suffix in (("float", "f32"), ("double", "f64")):
        source += _BODY.replace("REAL", real).replace("SUFFIX", suffix)
    return source + _TAPS_READABLE


_POINTERS = [ctypes.c_void_p] * 5
LIBRARY = NativeLibrary(
    "gather_rows", _source,
    {**{f"product_{s}": _POINTERS + [ctypes.c_int64] * 3 for s in ("f32", "f64")},
     **{f"scatter_{s}": _POINTERS + [ctypes.c_int64] * 2 for s in ("f32", "f64")},
     **{f"clamp_into_{s}": [ctypes.c_void_p] * 8 + [ctypes.c_int64] * 3
        for s in ("f32", "f64")},
     **{f"clamp_back_{s}": [ctypes.c_void_p] * 8 + [ctypes.c_int64] * 2
        for s in ("f32", "f64")},
     **{f"product_blocks_{s}": [ctypes.c_void_p] * 7 + [ctypes.c_int64] * 2
        for s in ("f32", "f64")},
     **{f"limited_tricubic_{s}": [ctypes.c_void_p] * 6 + [ctypes.c_int64] * 4
        for s in ("f32", "f64")},
     **{f"limited_runs_{s}": [ctypes.c_void_p] * 6 + [ctypes.c_int64] * 3
        for s in ("f32", "f64")},
     **{f"rkc_step_{s}": [ctypes.c_void_p] * 11 + [ctypes.c_int64] * 3
        for s in ("f32", "f64")},
     **{f"rkc_stage_rows_{s}": [ctypes.c_void_p] * 9 + [real] * 4 + [ctypes.c_int64] * 3
        for s, real in (("f32", ctypes.c_float), ("f64", ctypes.c_double))},
     **{f"rkc_stage_{s}": [ctypes.c_void_p] * 11 + [real] * 4 + [ctypes.c_int64] * 3
        for s, real in (("f32", ctypes.c_float), ("f64", ctypes.c_double))},
     **{f"brick_tricubic_{s}": [ctypes.c_void_p] * 5 + [ctypes.c_int64] + [ctypes.c_void_p]
        + [ctypes.c_int64] * 6 for s in ("f32", "f64")},
     "brick_taps_readable": [ctypes.c_void_p] * 4 + [ctypes.c_int64, ctypes.c_void_p]
     + [ctypes.c_int64] * 2},
    # the vectors are written out; loops vectorized by the compiler become gathers
    # (vgatherdps), twice as slow as scalar loads on an AMD EPYC
    flags=("-fno-tree-vectorize",))
"""The kernels' shared library (:class:`torchsurf._native.NativeLibrary`)."""

THREAD_MIN_ROWS = 16384
"""Fewest rows per thread: below, starting a thread costs more than it saves."""

_SUFFIX = {torch.float32: "f32", torch.float64: "f64"}

MAX_COLUMNS = {torch.float32: 16, torch.float64: 1 << 62}
"""Most columns of ``x`` the kernel takes, per dtype: ``embedding_bag`` is as fast for 32
float32 columns and twice as fast for 40 (AMD EPYC, one thread, 1.07 M entries); in float64
the kernel is 1.6-6x faster at every width measured (1-40)."""


def applies(offsets: Tensor, x: Tensor) -> bool:
    """Whether the kernel takes this product: CPU, float32 or float64 ``x`` ``(N, F)`` with at
    most :data:`MAX_COLUMNS` columns, 32-bit indices, and the library compiled; while
    ``torch.compile`` traces, if torch has custom operators (2.4 and later), through which the
    traced graph calls the kernels."""
    if not (x.device.type == "cpu" and x.dtype in _SUFFIX and offsets.dtype == torch.int32
            and x.shape[1] <= MAX_COLUMNS[x.dtype]):
        return False
    if torch.compiler.is_compiling():
        return TRACEABLE and _library_loaded()
    return not carries_tangents(x) and LIBRARY.load() is not None


LAYOUT_ROWS = 2**16
"""Rows laid out at once by :class:`RowBlocks`: its int64 positions of every entry at once took
about 2.4 GB beside the 61 M entries of the 256^3 bunny's band re-extension (the peak of its heat
flow's first call, 5.1 GB against 2.7 GB before the layout)."""


class RowBlocks:
    """A compressed-row matrix's entries laid out for one column of ``x``: rows in blocks of 8,
    each block's taps interleaved (tap ``k`` of its 8 rows side by side; a row shorter than the
    block's longest leaves its slots unread), so that the kernel sums 8 rows in one vector
    register (1.7-1.9x faster than row by row for one column: 0.17 against 0.29 ms for the 37^3
    sphere's ``W^-1 A``, 0.43 against 0.79 ms at 64^3). Kept beside the compressed rows: as many
    entries again, plus the padding.

    Args:
        offsets, columns, values: the compressed rows' ``(rows + 1,)``, ``(nnz,)`` and
            ``(nnz,)``.
    """

    def __init__(self, offsets: Tensor, columns: Tensor, values: Tensor) -> None:
        rows = len(offsets) - 1
        counts = (offsets[1:] - offsets[:-1]).long()
        blocks = (rows + 7) // 8
        padded = counts.new_zeros(blocks * 8)
        padded[:rows] = counts
        by_block = padded.view(blocks, 8)
        starts = torch.zeros(blocks + 1, dtype=torch.long)
        starts[1:] = torch.cumsum(by_block.amax(1) * 8, 0)
        self.columns = torch.zeros(int(starts[-1]), dtype=torch.int32)
        laid = values.new_zeros(len(self.columns))
        first = offsets.long()
        for low in range(0, rows, LAYOUT_ROWS):  # int64 temporaries of a chunk, not of nnz
            high = min(rows, low + LAYOUT_ROWS)
            row = torch.repeat_interleave(torch.arange(low, high), counts[low:high])
            entries = slice(int(first[low]), int(first[high]))
            rank = torch.arange(entries.start, entries.stop) - first[row]
            position = starts[row // 8] + rank * 8 + row % 8
            self.columns[position] = columns[entries].to(torch.int32)
            laid[position] = values[entries]
        self._weights = {values.dtype: laid}
        self.starts, self.blocks, self.rows = starts, blocks, rows
        self.shared = by_block.amin(1).to(torch.int32)
        self.counts = padded.to(torch.int32)

    def weights(self, dtype: torch.dtype) -> Tensor:
        """The entries in this layout, in ``dtype`` (converted once and kept)."""
        if dtype not in self._weights:
            with outside_inference():
                self._weights[dtype] = next(iter(self._weights.values())).to(dtype)
        return self._weights[dtype]

    def tensors(self) -> list[Tensor]:
        """What this layout keeps."""
        return [self.starts, self.shared, self.counts, self.columns, *self._weights.values()]

    def laid(self, dtype: torch.dtype) -> list[Tensor]:
        """``starts, shared, counts, columns, weights`` (in ``dtype``): what
        :func:`_block_product` reads."""
        return [self.starts, self.shared, self.counts, self.columns, self.weights(dtype)]

    def apply(self, x: Tensor) -> Tensor:
        """``A x`` for ``x`` ``(columns, 1)``, contiguous: ``(rows, 1)``."""
        return _block_product(self.laid(x.dtype), x, self.rows)


def _block_product(laid: list[Tensor], x: Tensor, rows: int) -> Tensor:
    """:meth:`RowBlocks.apply` from its :meth:`RowBlocks.laid` tensors."""
    starts, shared, counts, columns, weights = laid
    blocks = len(starts) - 1
    out = torch.empty((blocks * 8, 1), dtype=x.dtype)
    kernel = getattr(LIBRARY.load(), f"product_blocks_{_SUFFIX[x.dtype]}")

    def run(first: int, stop: int) -> None:
        kernel(starts.data_ptr(), shared.data_ptr(), counts.data_ptr(), columns.data_ptr(),
               weights.data_ptr(), x.data_ptr(), out.data_ptr(), first, stop)

    in_threads(run, blocks, THREAD_MIN_ROWS // 8)
    return out[:rows]


STAGE_COLUMNS = 8
"""Most columns :func:`rkc_stage` takes row by row (beyond, the stages keep the product's
vector kernels and the eager or compiled combination)."""


def rkc_stage(matrix: RowMatrix, current: Tensor, u: Tensor, previous: Tensor,
              rate0: Tensor | None, weights: tuple[float, float, float, float],
              rate: Tensor | None = None) -> Tensor:
    """One stage of a Runge-Kutta-Chebyshev step of ``u' = A u`` in one pass, for ``A``
    ``(rows, nodes)`` (rows the first of the nodes; its other nodes' rate zero) and values
    ``current``, ``u``, ``previous`` ``(nodes, F)``: the new stage ``u + mu (current - u) + a A
    current + b rate0 + nu (previous - u)`` for ``weights = (mu, nu, a, b)`` on the rows (``A
    current`` formed from ``current`` less its first row, as
    :meth:`~torchsurf.flows._packed_band.PackedRegion.weighted_apply`), ``u`` on the other
    nodes; a new ``(nodes, F)`` tensor. One column runs by ``matrix.blocks()``, up to
    :data:`STAGE_COLUMNS` row by row. ``rate0`` ``(rows, F)`` or ``None`` (zero); ``rate``
    ``(rows, F)``, if given, receives ``A current``. All contiguous, in one dtype the kernel
    takes (:func:`applies`); no autograd."""
    rows, features = matrix.shape[0], u.shape[1]
    following = torch.empty(u.shape, dtype=u.dtype)  # standard strides, whatever u's
    following[rows:] = u[rows:]
    mu, nu, a, b = (float(w) for w in weights)
    rate0_pointer = None if rate0 is None else rate0.data_ptr()
    rate_pointer = None if rate is None else rate.data_ptr()
    values = [current.data_ptr(), u.data_ptr(), previous.data_ptr(), rate0_pointer,
              following.data_ptr(), rate_pointer, mu, nu, a, b]
    if features == 1:
        blocks = matrix.blocks()
        laid = [t.data_ptr() for t in blocks.laid(u.dtype)]
        kernel = getattr(LIBRARY.load(), f"rkc_stage_{_SUFFIX[u.dtype]}")

        def run(first: int, stop: int) -> None:
            kernel(*laid, *values, rows, first, stop)

        in_threads(run, blocks.blocks, THREAD_MIN_ROWS // 8)
    else:
        laid = [matrix.offsets.data_ptr(), matrix.columns.data_ptr(),
                matrix.values(u.dtype).data_ptr()]
        kernel = getattr(LIBRARY.load(), f"rkc_stage_rows_{_SUFFIX[u.dtype]}")

        def run(first: int, stop: int) -> None:
            kernel(*laid, *values, features, first, stop)

        in_threads(run, rows, THREAD_MIN_ROWS)
    return following


def rkc_step(blocks: RowBlocks, u: Tensor, weights: Tensor) -> Tensor | None:
    """A whole RKC step of ``u' = A u`` in one call, its stages as :func:`rkc_stage`'s with
    ``weights`` ``(stages + 1, 4)`` float64 (row ``j``: stage ``j``'s ``(mu, nu, a, b)``; row
    1 ``(0, 0, a, 0)``): a new ``(nodes, 1)`` tensor; ``None`` where the rows would be split
    between threads (the stages are then called one by one, each split)."""
    if in_parts(blocks.blocks, THREAD_MIN_ROWS // 8) > 1:
        return None
    stage = [torch.empty(u.shape, dtype=u.dtype) for _ in range(3)]
    for buffer in stage:
        buffer[blocks.rows:] = u[blocks.rows:]
    rate0 = u.new_empty((blocks.rows, 1))
    starts, shared, counts, columns, laid = blocks.laid(u.dtype)
    weights = weights.to(torch.float64).contiguous()
    stages = len(weights) - 1
    getattr(LIBRARY.load(), f"rkc_step_{_SUFFIX[u.dtype]}")(
        starts.data_ptr(), shared.data_ptr(), counts.data_ptr(), columns.data_ptr(),
        laid.data_ptr(), u.data_ptr(), *(t.data_ptr() for t in stage), rate0.data_ptr(),
        weights.data_ptr(), stages, blocks.rows, blocks.blocks)
    return stage[stages % 3]


def _product(offsets: Tensor, columns: Tensor, weights: Tensor, x: Tensor,
             rows: int, blocks: RowBlocks | list[Tensor] | None = None) -> Tensor:
    x, offsets, columns, weights = (t.contiguous() for t in (x, offsets, columns, weights))
    if blocks and x.shape[1] == 1:
        laid = blocks.laid(x.dtype) if isinstance(blocks, RowBlocks) else blocks
        return _block_product(laid, x, rows)
    out = torch.empty((rows, x.shape[1]), dtype=x.dtype)
    kernel = getattr(LIBRARY.load(), f"product_{_SUFFIX[x.dtype]}")
    features = x.shape[1]

    def run(first: int, stop: int) -> None:
        kernel(offsets.data_ptr(), columns.data_ptr(), weights.data_ptr(), x.data_ptr(),
               out.data_ptr(), first, stop, features)

    in_threads(run, rows, THREAD_MIN_ROWS)
    return out


def _scatter(offsets: Tensor, columns: Tensor, weights: Tensor, g: Tensor,
             count: int) -> Tensor:
    g, offsets, columns, weights = (t.contiguous() for t in (g, offsets, columns, weights))
    out = torch.zeros((count, g.shape[1]), dtype=g.dtype)
    kernel = getattr(LIBRARY.load(), f"scatter_{_SUFFIX[g.dtype]}")
    kernel(offsets.data_ptr(), columns.data_ptr(), weights.data_ptr(), g.data_ptr(),
           out.data_ptr(), g.shape[0], g.shape[1])
    return out


class _Product(torch.autograd.Function):
    """``A x``; backward ``A^T g`` (:class:`_Scatter`)."""

    @staticmethod
    def forward(ctx, offsets, columns, weights, x, rows, blocks=None):  # noqa: ANN001, ANN205
        ctx.matrix = (offsets, columns, weights)
        ctx.count = x.shape[0]
        return _product(offsets, columns, weights, x, rows, blocks)

    @staticmethod
    def backward(ctx, g):  # noqa: ANN001, ANN205
        refuse_batched_backward("the packed band's gathers (C kernels)", g)
        return None, None, None, _Scatter.apply(*ctx.matrix, g, ctx.count), None, None


class _Scatter(torch.autograd.Function):
    """``A^T g``; backward ``A x`` (:class:`_Product`)."""

    @staticmethod
    def forward(ctx, offsets, columns, weights, g, count):  # noqa: ANN001, ANN205
        ctx.matrix = (offsets, columns, weights)
        ctx.rows = g.shape[0]
        return _scatter(offsets, columns, weights, g, count)

    @staticmethod
    def backward(ctx, x):  # noqa: ANN001, ANN205
        refuse_batched_backward("the packed band's gathers (C kernels)", x)
        return None, None, None, _Product.apply(*ctx.matrix, x, ctx.rows), None


def product(offsets: Tensor, columns: Tensor, weights: Tensor, x: Tensor,
            rows: int, blocks: RowBlocks | None = None) -> Tensor:
    """``A x`` for the compressed-row matrix ``(offsets (rows + 1,), columns (nnz,), weights
    (nnz,))`` (32-bit indices, weights in ``x``'s dtype) and ``x`` ``(columns, F)``: a new
    ``(rows, F)`` tensor, in autograd's graph when ``x`` is; for one column by ``blocks`` (the
    same matrix as :class:`RowBlocks`) when given. Check :func:`applies` first."""
    if torch.compiler.is_compiling():
        laid = blocks.laid(x.dtype) if blocks is not None and x.shape[1] == 1 else []
        return torch.ops.torchsurf.csr_product(offsets, columns, weights, x, rows, laid)
    if torch.is_grad_enabled() and x.requires_grad:
        return _Product.apply(offsets, columns, weights, x, rows, blocks)
    return _product(offsets, columns, weights, x, rows, blocks)


def _clamped_into(z: Tensor, value: Tensor, taps: Tensor, corners: Tensor, rows: Tensor,
                  codes: Tensor | None, extremes: Tensor | None) -> Tensor:
    out = z.clone()
    kernel = getattr(LIBRARY.load(), f"clamp_into_{_SUFFIX[z.dtype]}")
    features = z.shape[1]
    code_pointer = None if codes is None else codes.data_ptr()
    extreme_pointer = None if extremes is None else extremes.data_ptr()

    def run(first: int, stop: int) -> None:
        kernel(taps.data_ptr(), corners.data_ptr(), rows.data_ptr(), z.data_ptr(),
               value.data_ptr(), out.data_ptr(), code_pointer, extreme_pointer, first, stop,
               features)

    in_threads(run, len(rows), THREAD_MIN_ROWS)
    return out


class _Limited(torch.autograd.Function):
    """A limited stencil's ``z -> z`` with its targets' values replaced (:func:`limited`);
    backward by the recorded clamp codes and extremes and the transposed product."""

    @staticmethod
    def forward(ctx, z, matrix, taps, corners, rows):  # noqa: ANN001, ANN205
        with torch.no_grad():
            value = matrix.apply(z)
        codes = torch.empty((len(rows), z.shape[1]), dtype=torch.uint8)
        extremes = torch.empty((len(rows), z.shape[1], 8), dtype=torch.uint8)
        out = _clamped_into(z, value, taps, corners, rows, codes, extremes)
        # the stencil keeps its matrix, taps, corners and rows; the codes and the clamped
        # values' extremes are this call's (saved so that checkpointing frees and recomputes
        # them)
        ctx.matrix, ctx.taps, ctx.corners, ctx.rows = matrix, taps, corners, rows
        ctx.save_for_backward(codes, extremes[codes.bool()].contiguous())
        return out

    @staticmethod
    def backward(ctx, g):  # noqa: ANN001, ANN205
        # once_differentiable's refusal is not reached by autograd.grad(loss, parameters) after
        # create_graph=True (its node hangs off a detached copy): the penalty's part would be
        # left out silently
        refuse_second_derivatives("the packed band's limited re-extension (its C kernels)", g)
        codes, extremes = ctx.saved_tensors
        matrix = ctx.matrix
        grad = _clamped_back(g, ctx.taps, ctx.corners, ctx.rows, codes, extremes,
                             matrix.offsets, matrix.columns, matrix.values(g.dtype))
        return grad, None, None, None, None


def _clamped_back(g: Tensor, taps: Tensor, corners: Tensor, rows: Tensor, codes: Tensor,
                  extremes: Tensor, offsets: Tensor, columns: Tensor, values: Tensor) -> Tensor:
    """The gradient of :func:`limited` for ``g`` ``(nodes, F)``: ``extremes`` of the clamped
    values alone, in order (``extremes[codes.bool()]``)."""
    g = g.contiguous()
    grad = g.index_fill(0, rows, 0.0)
    free = torch.empty((len(rows), g.shape[1]), dtype=g.dtype)
    getattr(LIBRARY.load(), f"clamp_back_{_SUFFIX[g.dtype]}")(
        taps.data_ptr(), corners.to(g.dtype).contiguous().data_ptr(), rows.data_ptr(),
        codes.data_ptr(), extremes.data_ptr(), g.data_ptr(), grad.data_ptr(), free.data_ptr(),
        len(rows), g.shape[1])
    grad += _scatter(offsets, columns, values, free, g.shape[0])
    return grad


def limited(z: Tensor, matrix: RowMatrix, taps: Tensor, corners: Tensor, rows: Tensor,
            separable: Callable[[], SeparableStencil] | None = None) -> Tensor | None:
    """A copy of ``z`` ``(nodes, F)`` whose rows ``rows`` ``(R,)`` (int64, distinct) hold
    ``matrix @ z`` ``(R, F)`` clamped to the limiter's bounds (:mod:`._limiter`) over each
    row's 64 taps ``taps`` ``(R, 64)`` (int32 rows of ``z``, in the order ``16 z + 4 y + x``)
    with its corners' trilinear weights ``corners`` ``(R, 8)`` (``z``'s dtype); in autograd's
    graph when ``z`` is (the gradient of a clamped value reaches the taps holding its corners'
    extremes, with the corners' weights). ``separable``, if given, returns the same stencil
    as a :class:`SeparableStencil`, which computes it in one pass where no gradient is recorded
    (several columns only where most rows lie in runs: :data:`RUNS_SHARE`). ``None`` where the
    kernel does not run (:func:`applies`)."""
    if (not applies(matrix.offsets, z) or taps.dtype != torch.int32
            or rows.dtype != torch.int64 or corners.dtype != z.dtype):
        return None
    z, taps, corners, rows = (t.contiguous() for t in (z, taps, corners, rows))
    if torch.compiler.is_compiling():
        out, _, _ = torch.ops.torchsurf.limited(z, matrix.offsets, matrix.columns,
                                                matrix.values(z.dtype), taps, corners, rows)
        return out
    if torch.is_grad_enabled() and z.requires_grad:
        return _Limited.apply(z, matrix, taps, corners, rows)
    if separable is not None:
        out = _limited_separable(z, separable())
        if out is not None:
            return out
    return _clamped_into(z, matrix.apply(z), taps, corners, rows, None, None)


RUNS_SHARE = 0.5
"""Several columns take :class:`SeparableStencil` where at least this share of its rows lie in
runs: the blocks of 8 were slower than the product and the clamp for several columns (a batch
of 4 at 64^3: 1.25x the time)."""


RUNS_COLUMNS = 8
"""Most columns :class:`SeparableStencil` takes (its runs kernel holds 4 x 8 values a run)."""


class SeparableStencil:
    """A limited tricubic stencil laid out for one pass (:func:`limited`), its 64 tap weights
    formed in the kernel from the 12 separable ones:

    - the rows whose taps lie 4 by 4 side by side along x (every row of a sphere's band at
      35^3) by their 16 runs' first taps (112 bytes a row in float32), a run's values read
      side by side (one vector load for one column);
    - the other rows in blocks of 8, each block's 64 taps interleaved (tap ``t`` of its 8 rows
      side by side) and its separable weights likewise (304 bytes a row, against the 512 of
      the taps and their 64 weights), the limiter's test reading the taps the product has just
      read.

    The layout is formed at its first use in a dtype and kept.

    Args:
        taps: ``(R, 64)`` int32 taps (rows of the values), in the order ``16 z + 4 y + x``.
        axes: ``(3, R, 4)`` separable weights (x, y, z), as
            :func:`~torchsurf.flows.extension.tap_weights` takes them.
        corners: ``(R, 8)`` the corners' weights of the limiter's bounds.
        rows: ``(R,)`` int64, the distinct target rows of the values.
    """

    def __init__(self, taps: Tensor, axes: Tensor, corners: Tensor, rows: Tensor) -> None:
        self.taps, self.axes, self.corners, self.rows = taps, axes, corners, rows
        self._side_by_side: Tensor | None = None
        self._layouts: dict[torch.dtype, list] = {}

    @property
    def side_by_side(self) -> Tensor:
        """Whether each row's taps lie in 16 runs of 4 consecutive rows ``(R,)`` bool (found at
        the first use, :data:`LAYOUT_ROWS` rows at a time: no ``(R, 64)`` temporaries)."""
        if self._side_by_side is None:
            self._find_runs()
        return self._side_by_side

    @property
    def runs_share(self) -> float:
        """The share of the rows whose taps lie in runs (1 without rows)."""
        if self._side_by_side is None:
            self._find_runs()
        return self._runs_share

    def _find_runs(self) -> None:
        step = torch.arange(4, dtype=torch.int32, device=self.taps.device)
        runs = self.taps.view(-1, 16, 4)
        found = [(runs[low:low + LAYOUT_ROWS] - runs[low:low + LAYOUT_ROWS, :, :1] == step)
                 .flatten(1).all(1) for low in range(0, len(runs), LAYOUT_ROWS)]
        with outside_inference():
            side_by_side = (torch.cat(found) if found
                            else torch.zeros(0, dtype=torch.bool, device=self.taps.device))
        # the share first: readers test the rows (another thread's read had found no share)
        self._runs_share = float(side_by_side.float().mean()) if found else 1.0
        self._side_by_side = side_by_side

    def parts(self, columns: int, dtype: torch.dtype) -> list | None:
        """The kernels' arguments for ``columns`` columns of ``dtype`` values: for each part, its
        kernel's name, its tensors and its row count; ``None`` for more than
        :data:`RUNS_COLUMNS` columns, or several where fewer than :data:`RUNS_SHARE` of the rows
        lie in runs."""
        if columns > RUNS_COLUMNS or (columns > 1 and self.runs_share < RUNS_SHARE):
            return None
        if dtype not in self._layouts:
            with outside_inference():
                self._layouts[dtype] = self._laid(dtype)
        return self._layouts[dtype]

    def _laid(self, dtype: torch.dtype) -> list:
        parts = []
        chosen = self.side_by_side.nonzero().squeeze(1)
        if len(chosen):
            starts = self.taps.view(-1, 16, 4)[chosen, :, 0].to(torch.int32).contiguous()
            axes = self.axes[:, chosen].to(dtype).permute(1, 0, 2).reshape(-1, 12).contiguous()
            parts.append(("limited_runs", [starts, axes, *self._targets(chosen, dtype)],
                          len(chosen)))
        rest = (~self.side_by_side).nonzero().squeeze(1)
        if len(rest):
            count = len(rest)
            blocks = (count + 7) // 8
            pad = blocks * 8 - count
            taps = torch.cat([self.taps[rest].to(torch.int32),
                              self.taps.new_zeros((pad, 64), dtype=torch.int32)])
            columns = taps.view(blocks, 8, 64).transpose(1, 2).contiguous()
            axes = torch.cat([self.axes[:, rest].to(dtype),
                              self.axes.new_zeros((3, pad, 4), dtype=dtype)], dim=1)
            axes = axes.view(3, blocks, 8, 4).permute(1, 0, 3, 2).contiguous()
            parts.append(("limited_tricubic", [columns, axes, *self._targets(rest, dtype)], count))
        return parts

    def _targets(self, chosen: Tensor, dtype: torch.dtype) -> list[Tensor]:
        return [self.corners[chosen].to(dtype).contiguous(), self.rows[chosen].contiguous()]


def limited_rows(z: Tensor, stencil: SeparableStencil) -> Tensor | None:
    """The values ``(R, F)`` of a :class:`SeparableStencil` whose rows are ``0 .. R - 1`` (not
    rows of ``z`` ``(M, F)``, which its taps read): the limited tricubic values alone, with no
    copy of ``z``. ``None`` where the kernel does not run: not the CPU, float32 or float64, a
    gradient or a forward-mode tangent to carry, while ``torch.compile`` traces, columns it does not take
    (:meth:`SeparableStencil.parts`), or no compiler."""
    if (z.device.type != "cpu" or z.dtype not in _SUFFIX or torch.compiler.is_compiling()
            or (torch.is_grad_enabled() and z.requires_grad) or carries_tangents(z)
            or LIBRARY.load() is None):
        return None
    return _limited_separable(z.contiguous(), stencil, len(stencil.rows))


def _limited_separable(z: Tensor, stencil: SeparableStencil, out_rows: int | None = None
                       ) -> Tensor | None:
    """:func:`limited` by ``stencil``'s layout in one pass, or ``None`` where it does not take
    ``z``'s columns (:meth:`SeparableStencil.parts`); no autograd. With ``out_rows``, the
    stencil's rows index a new ``(out_rows, F)`` tensor that it fills (:func:`limited_rows`)."""
    features = z.shape[1]
    parts = stencil.parts(features, z.dtype)
    if parts is None:
        return None
    if out_rows is not None:
        out = torch.empty((out_rows, features), dtype=z.dtype)
    else:
        out = (torch.empty(z.shape, dtype=z.dtype) if len(stencil.rows) == len(z)  # distinct
               else z.clone(memory_format=torch.contiguous_format))
    library = LIBRARY.load()
    for name, tensors, count in parts:
        kernel = getattr(library, f"{name}_{_SUFFIX[z.dtype]}")
        pointers = [t.data_ptr() for t in tensors]
        if name == "limited_runs":
            def run(first: int, stop: int, kernel=kernel, pointers=pointers) -> None:  # noqa: ANN001
                kernel(*pointers, z.data_ptr(), out.data_ptr(), features, first, stop)

            in_threads(run, count, THREAD_MIN_ROWS)
        else:
            def run(first: int, stop: int, kernel=kernel, pointers=pointers,  # noqa: ANN001
                    count=count) -> None:
                kernel(*pointers, z.data_ptr(), out.data_ptr(), count, features, first, stop)

            in_threads(run, (count + 7) // 8, THREAD_MIN_ROWS // 8)
    return out


# The kernels as custom operators: a graph ``torch.compile`` traces calls them, opaque to
# inductor, instead of the gathers inductor would generate for the same products (a flow's
# clamped re-extension took 4-10x the eager time compiled that way: docs/learning.md).

TRACEABLE = hasattr(torch.library, "custom_op")
"""Whether the kernels run inside a traced graph (``torch.library.custom_op``: torch >= 2.4)."""


@torch.compiler.assume_constant_result
def _library_loaded() -> bool:
    return LIBRARY.load() is not None


if TRACEABLE:
    @torch.library.custom_op("torchsurf::csr_product", mutates_args=())
    def _csr_product_op(offsets: Tensor, columns: Tensor, weights: Tensor, x: Tensor,
                        rows: int, blocks: list[Tensor]) -> Tensor:
        return _product(offsets, columns, weights, x, rows, blocks)

    @_csr_product_op.register_fake
    def _(offsets, columns, weights, x, rows, blocks):  # noqa: ANN001, ANN202
        return x.new_empty((rows, x.shape[1]))

    @torch.library.custom_op("torchsurf::csr_scatter", mutates_args=())
    def _csr_scatter_op(offsets: Tensor, columns: Tensor, weights: Tensor, g: Tensor,
                        count: int) -> Tensor:
        return _scatter(offsets, columns, weights, g, count)

    @_csr_scatter_op.register_fake
    def _(offsets, columns, weights, g, count):  # noqa: ANN001, ANN202
        return g.new_empty((count, g.shape[1]))

    def _save_matrix(ctx, inputs, output) -> None:  # noqa: ANN001
        offsets, columns, weights, x = inputs[:4]
        ctx.save_for_backward(offsets, columns, weights)
        ctx.count = x.shape[0]
        ctx.blocks = len(inputs[5]) if len(inputs) > 5 else 0

    def _product_backward(ctx, g):  # noqa: ANN001, ANN202
        offsets, columns, weights = ctx.saved_tensors
        grad = torch.ops.torchsurf.csr_scatter(offsets, columns, weights, g, ctx.count)
        return None, None, None, grad, None, [None] * ctx.blocks

    def _scatter_backward(ctx, x):  # noqa: ANN001, ANN202
        offsets, columns, weights = ctx.saved_tensors
        grad = torch.ops.torchsurf.csr_product(offsets, columns, weights, x, ctx.count, [])
        return None, None, None, grad, None

    _csr_product_op.register_autograd(_product_backward, setup_context=_save_matrix)
    _csr_scatter_op.register_autograd(_scatter_backward, setup_context=_save_matrix)

    @torch.library.custom_op("torchsurf::limited", mutates_args=())
    def _limited_op(z: Tensor, offsets: Tensor, columns: Tensor, values: Tensor, taps: Tensor,
                    corners: Tensor, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        value = _product(offsets, columns, values, z, len(rows))
        codes = torch.empty((len(rows), z.shape[1]), dtype=torch.uint8)
        extremes = torch.zeros((len(rows), z.shape[1], 8), dtype=torch.uint8)  # written if clamped
        return _clamped_into(z, value, taps, corners, rows, codes, extremes), codes, extremes

    @_limited_op.register_fake
    def _(z, offsets, columns, values, taps, corners, rows):  # noqa: ANN001, ANN202
        return (z.new_empty(z.shape), z.new_empty((rows.shape[0], z.shape[1]), dtype=torch.uint8),
                z.new_empty((rows.shape[0], z.shape[1], 8), dtype=torch.uint8))

    @torch.library.custom_op("torchsurf::limited_backward", mutates_args=())
    def _limited_backward_op(g: Tensor, taps: Tensor, corners: Tensor, rows: Tensor,
                             codes: Tensor, extremes: Tensor, offsets: Tensor, columns: Tensor,
                             values: Tensor) -> Tensor:
        return _clamped_back(g, taps, corners, rows, codes,
                             extremes[codes.bool()].contiguous(), offsets, columns, values)

    @_limited_backward_op.register_fake
    def _(g, taps, corners, rows, codes, extremes, offsets, columns, values):  # noqa: ANN001, ANN202
        return g.new_empty(g.shape)  # contiguous, as the kernel writes it

    def _save_limited(ctx, inputs, output) -> None:  # noqa: ANN001
        _, offsets, columns, values, taps, corners, rows = inputs
        _, codes, extremes = output
        ctx.save_for_backward(taps, corners, rows, codes, extremes, offsets, columns, values)

    def _limited_backward(ctx, g, *_):  # noqa: ANN001, ANN202
        grad = torch.ops.torchsurf.limited_backward(g, *ctx.saved_tensors)
        return grad, None, None, None, None, None, None

    _limited_op.register_autograd(_limited_backward, setup_context=_save_limited)


def brick_tricubic(flat: Tensor, bases: Tensor, second: Tensor, local: Tensor, weights: Tensor,
                   limited: bool, nodes: slice) -> Tensor | None:
    """A :class:`~torchsurf.flows.extension.BrickCubicStencil`'s interpolation of ``flat``
    ``(C, M)`` (packed values, channels first) at its nodes ``nodes`` (a slice of its ``N``),
    ``(C, n)``, from its compact form: ``bases`` ``(8, N)`` int32, ``second`` ``(3, N, 4)``
    bool, ``local`` ``(3, N, 4)`` int16, ``weights`` ``(3, N, 4)`` of ``flat``'s dtype; limited
    (:mod:`._limiter`) if ``limited``. The ``(n, 64)`` tap positions are not formed (the
    compiled gather forms each tap's brick by selects at every application: 1.4x slower,
    limited). ``None`` where the kernel does not run: not the CPU, float32 or float64, or
    32-bit bases; a gradient to record (to ``flat``, or from ``phi`` to ``weights``); while
    ``torch.compile`` traces; or no compiler."""
    if (flat.device.type != "cpu" or flat.dtype not in _SUFFIX or bases.dtype != torch.int32
            or second.dtype != torch.bool or local.dtype != torch.int16
            or weights.dtype != flat.dtype or torch.compiler.is_compiling()
            or (torch.is_grad_enabled() and (flat.requires_grad or weights.requires_grad))
            or carries_tangents(flat, weights)):
        return None
    library = LIBRARY.load()
    if library is None:
        return None
    kernel = getattr(library, f"brick_tricubic_{_SUFFIX[flat.dtype]}")
    flat, bases, second, local, weights = (
        t.contiguous() for t in (flat, bases, second, local, weights))
    start, stop, _ = nodes.indices(bases.shape[1])
    channels = flat.shape[0]
    out = torch.empty(channels, stop - start, dtype=flat.dtype)

    def run(first: int, last: int) -> None:
        kernel(bases.data_ptr(), second.data_ptr(), local.data_ptr(), weights.data_ptr(),
               flat.data_ptr(), flat.shape[1], out.data_ptr() + first * out.element_size(),
               out.shape[1], bases.shape[1], channels, int(limited), start + first,
               start + last)

    in_threads(run, stop - start, THREAD_MIN_ROWS)
    return out


def brick_taps_readable(bases: Tensor, second: Tensor, local: Tensor, readable: Tensor
                        ) -> Tensor | None:
    """Which nodes of a :class:`~torchsurf.flows.extension.BrickCubicStencil` (its compact
    form, as in :func:`brick_tricubic`) read only stored nodes of ``readable`` (flat bool over
    the packed nodes): ``(N,)`` bool, without forming the ``(N, 64)`` tap positions (1.55 s
    for the 1.14 M nodes of a 256^3 bunny's band and ring). ``None`` where the kernel does
    not run (not the CPU, other index dtypes, no compiler)."""
    if (bases.device.type != "cpu" or bases.dtype != torch.int32
            or second.dtype != torch.bool or local.dtype != torch.int16
            or readable.dtype != torch.bool):
        return None
    library = LIBRARY.load()
    if library is None:
        return None
    bases, second, local, readable = (t.contiguous() for t in (bases, second, local, readable))
    count = bases.shape[1]
    keep = torch.empty(count, dtype=torch.bool)

    def run(first: int, last: int) -> None:
        library.brick_taps_readable(bases.data_ptr(), second.data_ptr(), local.data_ptr(),
                                    readable.data_ptr(), count,
                                    keep.data_ptr() + first, first, last)

    in_threads(run, count, THREAD_MIN_ROWS)
    return keep
