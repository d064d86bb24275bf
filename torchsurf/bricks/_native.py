"""The octant Laplace–Beltrami on bricks as a small C kernel that skips what is not in the band.

The compiled one-pass kernel (:func:`torchsurf.operators._octant.fused_octant`) evaluates every
node a brick stores, after its halo is gathered into a copy of the field: at 512^3 about a
quarter of the stored nodes are in a flow's band, and the gather costs as much as the stencil.
This kernel reads each brick's halo from its neighbours row by row into a small tile on the
stack, forms the coefficients ``w - w n_a^2`` and ``w n_a n_b`` once per brick for the tile rows
the band reads, and evaluates only the rows of 8 nodes (along x) that hold a band node, 8 nodes
at a time in the CPU's vector registers. Its numbers are the octant expression's with the
coefficients formed first, so they agree with the other paths to rounding.

On a band (a mask), the geometry rows those coefficients need are packed once into one stream
(:class:`_GeometryPlan`, kept while the band and the geometry stay the same) that the kernel
reads ahead of use: at 256^3 the haloed planes' scattered rows stalled it for a quarter of its
time (docs/bricks.md, "The C kernel").

It is compiled once per machine (:mod:`torchsurf._native`: ``$CC``, about half a second, into
``~/.cache/torchsurf`` or ``$TORCHSURF_CACHE_DIR``). Without a compiler, or with
``TORCHSURF_NATIVE=never``, :func:`octant` returns ``None`` and the operators take their other
paths; :func:`unavailable_reason` says why.
"""

from __future__ import annotations

import ctypes
import weakref

import torch
from torch import Tensor

from .._native import NativeLibrary, carries_tangents, in_threads

BRICK = 8
TILE = BRICK + 2

_SHARED = r"""
/* Of a brick whose rows (z, y) of 8 nodes along x hold band nodes as the bits of row_bits
   (B * B bytes), the rows of its haloed tile (T = B + 2 along each side) that the stencil reads:
   need[zz] bit yy, tile row (zz, yy) of u (3x3 rows around each band row); plus[zz], the rows
   whose coefficients it reads (the band rows and their four neighbours across y and z).
   Returns whether the brick holds a band node. */
static unsigned tile_rows(const uint8_t *row_bits, unsigned *need, unsigned *plus)
{
    unsigned ys[B + 4] = {0};
    unsigned any = 0;
    for (int z = 0; z < B; ++z) {
        unsigned m = 0;
        for (int y = 0; y < B; ++y) m |= (unsigned)(row_bits[z * B + y] != 0) << y;
        ys[z + 2] = m;
        any |= m;
    }
    for (int zz = 0; zz < T; ++zz) {
        unsigned near = ys[zz] | ys[zz + 1] | ys[zz + 2];
        need[zz] = near | near << 1 | near << 2;
        plus[zz] = ys[zz + 1] | ys[zz + 1] << 1 | ys[zz + 1] << 2 | (ys[zz] | ys[zz + 2]) << 1;
    }
    return any;
}

/* The end of the run of set bits of rows that starts at bit start (set), at most T. */
static inline int run_end(unsigned rows, int start)
{
    int end = start + 1;
    while (end < T && ((rows >> end) & 1)) ++end;
    return end;
}

/* offsets[n]: the plus rows of bricks [0, n), for n in [0, bricks]. */
void geometry_offsets(const uint8_t *rows, int64_t bricks, int64_t *offsets)
{
    int64_t total = 0;
    for (int64_t n = 0; n < bricks; ++n) {
        unsigned need[T], plus[T];
        offsets[n] = total;
        if (!tile_rows(rows + n * B * B, need, plus)) continue;
        for (int zz = 0; zz < T; ++zz) total += __builtin_popcount(plus[zz]);
    }
    offsets[bricks] = total;
}
"""

_BODY = r"""
static const REAL zero_brick_SUFFIX[B * B * B];

/* The coefficients of nodes [0, count) of nx, ny, nz, w into the planes of k (stride T^3),
   w itself in the last. */
static inline void coefficients_SUFFIX(const REAL *restrict nx, const REAL *restrict ny,
        const REAL *restrict nz, const REAL *restrict w, REAL *restrict k, int count)
{
    for (int i = 0; i < count; ++i) {
        REAL wx = w[i] * nx[i], wy = w[i] * ny[i], wz = w[i] * nz[i];
        k[0 * T * T * T + i] = w[i] - wx * nx[i];
        k[1 * T * T * T + i] = w[i] - wy * ny[i];
        k[2 * T * T * T + i] = w[i] - wz * nz[i];
        k[3 * T * T * T + i] = wx * ny[i];
        k[4 * T * T * T + i] = wx * nz[i];
        k[5 * T * T * T + i] = wy * nz[i];
        k[6 * T * T * T + i] = w[i];
    }
}

/* One row of 8 nodes: the tile row r = (z + 1) T + y + 1 of u and of the coefficients. */
static inline void row_SUFFIX(const REAL *restrict t, const REAL *restrict k, int r,
        const REAL *restrict divisor, REAL scale, unsigned bits,
        REAL *restrict target)
{
    const REAL *c0 = t + r * T + 1;
    const REAL *yp = c0 + T, *ym = c0 - T, *zp = c0 + T * T, *zm = c0 - T * T;
    const REAL *yp_zp = zp + T, *ym_zp = zp - T, *yp_zm = zm + T, *ym_zm = zm - T;
    const REAL *k0 = k + r * T + 1;
    const REAL *kyp = k0 + T, *kym = k0 - T;
    const REAL *kzp = k0 + T * T, *kzm = k0 - T * T;
    enum { AX = 0, AY = T * T * T, AZ = 2 * T * T * T, CXY = 3 * T * T * T, CXZ = 4 * T * T * T,
           CYZ = 5 * T * T * T };
    REAL value[B];
    for (int x = 0; x < B; ++x) {
        REAL u0 = c0[x];
        REAL ax = k0[AX + x], ay = k0[AY + x], az = k0[AZ + x];
        REAL dx = (ax + k0[AX + x + 1]) * (c0[x + 1] - u0) - (k0[AX + x - 1] + ax) * (u0 - c0[x - 1]);
        REAL dy = (ay + kyp[AY + x]) * (yp[x] - u0) - (kym[AY + x] + ay) * (u0 - ym[x]);
        REAL dz = (az + kzp[AZ + x]) * (zp[x] - u0) - (kzm[AZ + x] + az) * (u0 - zm[x]);
        REAL sx = (k0[CXY + x - 1] * (yp[x - 1] - ym[x - 1]) + k0[CXZ + x - 1] * (zp[x - 1] - zm[x - 1]))
                - (k0[CXY + x + 1] * (yp[x + 1] - ym[x + 1]) + k0[CXZ + x + 1] * (zp[x + 1] - zm[x + 1]));
        REAL sy = (kym[CXY + x] * (ym[x + 1] - ym[x - 1]) + kym[CYZ + x] * (ym_zp[x] - ym_zm[x]))
                - (kyp[CXY + x] * (yp[x + 1] - yp[x - 1]) + kyp[CYZ + x] * (yp_zp[x] - yp_zm[x]));
        REAL sz = (kzm[CXZ + x] * (zm[x + 1] - zm[x - 1]) + kzm[CYZ + x] * (yp_zm[x] - ym_zm[x]))
                - (kzp[CXZ + x] * (zp[x + 1] - zp[x - 1]) + kzp[CYZ + x] * (yp_zp[x] - ym_zp[x]));
        REAL diag = dx + dy + dz, cross = sx + sy + sz;
        REAL total = (REAL)2 * diag + cross;
        value[x] = total / (scale * divisor[x]);
    }
    for (int x = 0; x < B; ++x) {   /* zero off the band, without branches */
        UINT v, keep = (UINT)0 - (UINT)((bits >> x) & 1);
        memcpy(&v, value + x, sizeof v);
        v &= keep;
        memcpy(target + x, &v, sizeof v);
    }
}

/* Each brick's plus rows (tile_rows), from offsets[n] * 4 T on: per run of R consecutive rows,
   nx, ny, nz and w of its R T nodes one after the other. */
void geometry_pack_SUFFIX(
        const REAL *normal, int64_t normal_brick, int64_t normal_channel,
        const REAL *weight, int64_t weight_brick, const uint8_t *rows, const int64_t *offsets,
        REAL *packed, int64_t first, int64_t stop)
{
    for (int64_t n = first; n < stop; ++n) {
        unsigned need[T], plus[T];
        if (!tile_rows(rows + n * B * B, need, plus)) continue;
        const REAL *nx = normal + n * normal_brick, *ny = nx + normal_channel, *nz = ny + normal_channel;
        const REAL *w = weight + n * weight_brick;
        REAL *g = packed + offsets[n] * 4 * T;
        for (int zz = 0; zz < T; ++zz)
            for (int yy = 0; yy < T;) {
                if (!((plus[zz] >> yy) & 1)) { ++yy; continue; }
                int end = run_end(plus[zz], yy);
                int r = (zz * T + yy) * T, count = (end - yy) * T;
                memcpy(g, nx + r, sizeof(REAL) * count); g += count;
                memcpy(g, ny + r, sizeof(REAL) * count); g += count;
                memcpy(g, nz + r, sizeof(REAL) * count); g += count;
                memcpy(g, w + r, sizeof(REAL) * count); g += count;
                yy = end;
            }
    }
}

/* The coefficients come from packed + offsets[n] * 4 T (geometry_pack) where packed is not
   NULL, read ahead of use; else from the haloed normal and weight. */
void octant_bricks_SUFFIX(
        const REAL *u, int64_t u_brick, int64_t u_channel,
        const REAL *normal, int64_t normal_brick, int64_t normal_channel,
        const REAL *weight, int64_t weight_brick,
        const REAL *packed, const int64_t *offsets,
        const int64_t *neighbours, const uint8_t *present, const uint8_t *rows,
        REAL *out, int64_t first, int64_t stop, int64_t channels, double scale_in,
        int weighted)
{
    enum { AHEAD = 32768 / sizeof(REAL), LINE = 64 / sizeof(REAL) };
    const REAL scale = (REAL)scale_in;
    static const REAL ones[B] = {1, 1, 1, 1, 1, 1, 1, 1};
    REAL tile[T * T * T];
    REAL k[T * T * NK * T];
    for (int64_t n = first; n < stop; ++n) {
        const uint8_t *row_bits = rows + n * B * B;
        REAL *o = out + n * channels * B * B * B;
        unsigned need[T], plus[T];
        if (!tile_rows(row_bits, need, plus)) {
            memset(o, 0, sizeof(REAL) * B * B * B * channels);
            continue;
        }
        const int64_t *nb = neighbours + n * 27;
        const uint8_t *pr = present + n * 27;
        const REAL *nx = normal + n * normal_brick;
        const REAL *ny = nx + normal_channel, *nz = ny + normal_channel;
        const REAL *w = weight + n * weight_brick;
        const REAL *g = packed ? packed + offsets[n] * 4 * T : 0;
        for (int zz = 0; zz < T; ++zz)
            for (int yy = 0; yy < T;) {   /* runs of consecutive rows */
                if (!((plus[zz] >> yy) & 1)) { ++yy; continue; }
                int end = run_end(plus[zz], yy);
                int r = (zz * T + yy) * T, count = (end - yy) * T;
                if (g) {
                    for (int q = 0; q < 4 * count; q += LINE) __builtin_prefetch(g + AHEAD + q, 0, 2);
                    coefficients_SUFFIX(g, g + count, g + 2 * count, g + 3 * count, k + r, count);
                    g += 4 * count;
                } else {
                    coefficients_SUFFIX(nx + r, ny + r, nz + r, w + r, k + r, count);
                }
                yy = end;
            }
        for (int64_t c = 0; c < channels; ++c) {
            const REAL *base[27];
            for (int j = 0; j < 27; ++j)
                base[j] = pr[j] ? u + nb[j] * u_brick + c * u_channel : zero_brick_SUFFIX;
            for (int zz = 0; zz < T; ++zz) {
                int bz = zz == 0 ? 0 : zz == T - 1 ? 2 : 1, lz = (zz + B - 1) % B;
                unsigned m = need[zz];
                for (int yy = 0; yy < T; ++yy) {
                    if (!((m >> yy) & 1)) continue;
                    int by = yy == 0 ? 0 : yy == T - 1 ? 2 : 1, ly = (yy + B - 1) % B;
                    const REAL **b = base + bz * 9 + by * 3;
                    int row = (lz * B + ly) * B;
                    REAL *dst = tile + (zz * T + yy) * T;
                    dst[0] = b[0][row + B - 1];
                    memcpy(dst + 1, b[1] + row, sizeof(REAL) * B);
                    dst[T - 1] = b[2][row];
                }
            }
            REAL *oc = o + c * B * B * B;
            for (int z = 0; z < B; ++z)
                for (int y = 0; y < B; ++y) {
                    REAL *target = oc + (z * B + y) * B;
                    unsigned bits = row_bits[z * B + y];
                    if (!bits) { memset(target, 0, sizeof(REAL) * B); continue; }
                    int r = (z + 1) * T + y + 1;
                    row_SUFFIX(tile, k, r, weighted ? ones : k + 6 * T * T * T + r * T + 1, scale,
                               bits, target);
                }
        }
    }
}
"""


def _source() -> str:
    source = ("#include <stdint.h>\n#include <string.h>\n#define B 8\n#define T 10\n"
              "#define NK 7\n") + _SHARED
    for real, suffix, bits in (("float", "f32", "uint32_t"), ("double", "f64", "uint64_t")):
        source += _BODY.replace("REAL", real).replace("SUFFIX", suffix).replace("UINT", bits)
    return source


_ARGUMENTS = ([ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64] * 2
              + [ctypes.c_void_p, ctypes.c_int64]
              + [ctypes.c_void_p] * 6
              + [ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_double, ctypes.c_int])
_PACK_ARGUMENTS = ([ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p,
                    ctypes.c_int64] + [ctypes.c_void_p] * 3 + [ctypes.c_int64] * 2)

LIBRARY = NativeLibrary(
    "octant_bricks", _source,
    {"geometry_offsets": [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p],
     **{f"octant_bricks_{suffix}": _ARGUMENTS for suffix in ("f32", "f64")},
     **{f"geometry_pack_{suffix}": _PACK_ARGUMENTS for suffix in ("f32", "f64")}})
"""The kernel's shared library (:class:`torchsurf._native.NativeLibrary`)."""


def library() -> ctypes.CDLL | None:
    """The compiled kernel, compiled on first use; ``None`` where it cannot be."""
    return LIBRARY.load()


def unavailable_reason() -> str | None:
    """Why :func:`octant` falls back (no compiler, ``TORCHSURF_NATIVE=never``), or ``None``."""
    return LIBRARY.unavailable_reason()


class _RowBits:
    """Per brick and row ``(z, y)`` of a mask ``(N, 1, 8, 8, 8)``, its nodes along x as the
    bits of a byte ``(N, 8, 8)``; kept while the mask lives and is not written to. What is kept
    is one tuple, replaced whole: threads sharing a layout read a mask's bits with its own
    version, never one's reference with another's bits."""

    def __init__(self) -> None:
        self._kept: tuple[weakref.ref, int, Tensor] | None = None

    def __getstate__(self) -> dict:
        return {}   # a cache: pickled empty (a weak reference cannot be pickled)

    def __setstate__(self, state: dict) -> None:
        self.__init__()

    def __call__(self, mask: Tensor | None, bricks: int) -> Tensor:
        if mask is None:
            return torch.full((bricks, BRICK, BRICK), 255, dtype=torch.uint8)
        if mask.is_inference():  # no version counter: formed for this call only
            return _row_bits(mask, bricks)
        kept = self._kept
        if kept is not None and kept[0]() is mask and mask._version == kept[1]:
            return kept[2]
        version = mask._version
        bits = _row_bits(mask, bricks)
        self._kept = (weakref.ref(mask), version, bits)
        return bits


def _row_bits(mask: Tensor, bricks: int) -> Tensor:
    """:class:`_RowBits` of ``mask`` ``(N, 1, 8, 8, 8)`` bool: ``(N, 8, 8)`` uint8."""
    powers = 1 << torch.arange(BRICK, dtype=torch.int32)
    bits = (mask.reshape(bricks, BRICK, BRICK, BRICK).to(torch.int32) * powers).sum(-1)
    return bits.to(torch.uint8).contiguous()


class _GeometryPlan:
    """The haloed geometry's rows that a band's stencils read (the band rows and their
    neighbours across y and z, 10 nodes long), each brick's in the order the kernel reads them:
    one stream it reads ahead of use, against rows scattered over four ``10^3`` planes a brick.
    About 45% of the haloed geometry's bytes on a 3-cell band; kept while the geometry is
    not written to and the band's row bits stay equal (a new mask of the same band reuses it).
    Packed at the second application to the same geometry and band, not the first: a single
    application (or geometry made anew for each, as for a ``phi`` that requires grad under
    ``no_grad``) would pay the packing pass and its memory for nothing.
    """

    def __init__(self) -> None:
        self._kept: tuple[tuple, Tensor, tuple[Tensor, Tensor] | None] | None = None

    def __getstate__(self) -> dict:
        return {}   # a cache: pickled empty (a weak reference cannot be pickled)

    def __setstate__(self, state: dict) -> None:
        self.__init__()

    def __call__(self, compiled: ctypes.CDLL, normal: Tensor, normal_strides: tuple[int, int],
                 weight: Tensor, weight_strides: tuple[int, int], bits: Tensor
                 ) -> tuple[Tensor, Tensor] | None:
        """``(offsets (N + 1,) int64, packed)``: brick ``n``'s rows from ``packed`` element
        ``40 offsets[n]`` on; ``None`` the first time this geometry and band are seen, and
        for geometry made under ``torch.inference_mode`` (no version counter to keep it by).

        What is kept, ``(geometry's key, row bits, plan packed for them or None)``, is one
        tuple replaced whole: threads sharing a layout with other bands had read one band's
        plan with another's bits (garbage, NaN) when the three were kept apart."""
        if normal.is_inference() or weight.is_inference():
            return None
        kept = self._kept
        if kept is None or not _holds(kept, normal, weight, bits):
            # seen once: the former plan let go before a new one would be allocated
            self._kept = ((weakref.ref(normal), normal._version, weakref.ref(weight),
                           weight._version), bits, None)
            return None
        key, kept_bits, plan = kept
        if plan is not None:
            if kept_bits is not bits:  # equal bits: the next call compares by identity
                self._kept = (key, bits, plan)
            return plan
        bricks = bits.shape[0]
        offsets = torch.empty(bricks + 1, dtype=torch.int64)
        compiled.geometry_offsets(bits.data_ptr(), bricks, offsets.data_ptr())
        packed = torch.empty(int(offsets[-1]) * 4 * TILE, dtype=normal.dtype)
        pack = (compiled.geometry_pack_f32 if normal.dtype == torch.float32
                else compiled.geometry_pack_f64)

        def run(first: int, stop: int) -> None:
            pack(normal.data_ptr(), *normal_strides, weight.data_ptr(), weight_strides[0],
                 bits.data_ptr(), offsets.data_ptr(), packed.data_ptr(), first, stop)

        in_threads(run, bricks, THREAD_MIN_BRICKS)
        plan = (offsets, packed)
        self._kept = (key, bits, plan)
        return plan


def _holds(kept: tuple, normal: Tensor, weight: Tensor, bits: Tensor) -> bool:
    """The geometry and row bits of ``kept`` (:class:`_GeometryPlan`) are these, the geometry
    unchanged since."""
    (normal_ref, normal_version, weight_ref, weight_version), kept_bits, _ = kept
    return (normal_ref() is normal and normal._version == normal_version
            and weight_ref() is weight and weight._version == weight_version
            and (kept_bits is bits or torch.equal(kept_bits, bits)))


def _strides(tensor: Tensor, side: int) -> tuple[int, int] | None:
    """``(brick, channel)`` strides of a ``(N, C, side, side, side)`` tensor whose blocks of
    ``side^3`` nodes are each contiguous, else ``None``."""
    if tuple(tensor.stride()[2:]) != (side * side, side, 1):
        return None
    return tensor.stride(0), tensor.stride(1)


def octant(u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, neighbours: Tensor,
           present: Tensor, row_bits: _RowBits, spacing: float, weighted: bool,
           mask: Tensor | None, plan: _GeometryPlan | None = None) -> Tensor | None:
    """The octant scheme's ``L u`` (``W L u`` if ``weighted``) at the nodes of ``mask`` (every
    stored node if ``None``), zero elsewhere; ``None`` where this kernel does not apply (no
    compiler, not on the CPU, a dtype other than float32 and float64, an input that needs a
    gradient through it, a layout of bricks it does not take).

    Args:
        u: ``(N, C, 8, 8, 8)``.
        haloed_normal: ``(N, 3, 10, 10, 10)``, ``haloed_weight``: ``(N, 1, 10, 10, 10)``: the
            geometry with its halo (:meth:`torchsurf.ImplicitSurface.haloed`).
        neighbours, present: the layout's ``(N, 27)`` tables, contiguous, int64 and uint8.
        mask: ``(N, 1, 8, 8, 8)`` bool or ``None``.
        plan: where given and ``mask`` is, the band's geometry is read from the rows it keeps
            (:class:`_GeometryPlan`, packed at the second application to the same geometry
            and band), not from the haloed planes.
    """
    tensors = (u, haloed_normal, haloed_weight) + (() if mask is None else (mask,))
    if (torch.jit.is_tracing()  # a trace would replay the empty output, not the kernel
            or u.dtype not in (torch.float32, torch.float64) or any(t.device.type != "cpu"
                                                             for t in tensors)
            or haloed_normal.dtype != u.dtype or haloed_weight.dtype != u.dtype
            or (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))
            or carries_tangents(*tensors)
            or haloed_normal.shape[0] != u.shape[0] or haloed_weight.shape[0] != u.shape[0]
            or (mask is not None and mask.shape != (u.shape[0], 1, BRICK, BRICK, BRICK))):
        return None
    bricks, channels = u.shape[:2]
    u_strides = _strides(u, BRICK)
    normal_strides = _strides(haloed_normal, TILE)
    weight_strides = _strides(haloed_weight, TILE)
    if u_strides is None or normal_strides is None or weight_strides is None:
        return None
    compiled = library()
    if compiled is None:
        return None
    bits = row_bits(mask, bricks)
    offsets = packed = None
    planned = None if plan is None or mask is None else plan(
        compiled, haloed_normal, normal_strides, haloed_weight, weight_strides, bits)
    if planned is not None:
        offsets, packed = planned
    out = torch.empty((bricks, channels, BRICK, BRICK, BRICK), dtype=u.dtype)
    kernel = compiled.octant_bricks_f32 if u.dtype == torch.float32 else compiled.octant_bricks_f64

    def run(first: int, stop: int) -> None:
        kernel(u.data_ptr(), *u_strides, haloed_normal.data_ptr(), *normal_strides,
               haloed_weight.data_ptr(), weight_strides[0],
               None if packed is None else packed.data_ptr(),
               None if offsets is None else offsets.data_ptr(), neighbours.data_ptr(),
               present.data_ptr(), bits.data_ptr(), out.data_ptr(), first, stop, channels,
               4.0 * spacing * spacing, int(bool(weighted)))

    in_threads(run, bricks, THREAD_MIN_BRICKS)
    return out


THREAD_MIN_BRICKS = 256
"""Fewest bricks per thread: below, starting a thread costs more than it saves."""
