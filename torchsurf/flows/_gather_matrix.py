"""Sparse matrices applied as weighted row gathers: the band operators on packed node values.

A :class:`GatherMatrix` of ``R`` rows holds its entries row by row (compressed rows: each row's
columns and weights, and where each row starts). ``A x`` for ``x`` ``(N, F)`` is, for each row,
the weighted sum of the rows of ``x`` its columns name. On the CPU a small C kernel computes it
(:mod:`torchsurf.flows._native_gather`: 1.5-5x faster than ``embedding_bag`` for 1-8
columns, on a par at 16, its backward 10-30x faster); where that kernel does not run (no
compiler, ``torch.compile`` tracing, other devices, more than 16 float32 columns)
:func:`torch.nn.functional.embedding_bag` with ``mode="sum"`` and per-sample weights computes
the same sums in one call (FBGEMM's kernel in float32, a standard operator that
``torch.compile`` traces). Other dtypes take the padded form: each row's entries padded to the
longest row's count ``T``, applied as ``T`` row gathers (``index_select``) and fused
multiply-adds.

Measured (AMD EPYC, one thread, rows of 27 entries, 30k rows): float32, 0.7-1.7 ms for 4-16
columns of ``x`` by ``embedding_bag``, 4.3-4.5 ms by the gathers, 3.7 ms by a CSR product
(which ``torch.compile`` does not trace); float64, 3.9 / 5.4 / 11 ms for 1 / 4 / 16 columns by
``embedding_bag`` against 3.9 / 9.1 / 18 ms by the gathers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .._inference import outside_inference
from . import _native_gather

PADDING = 1.2
"""In the padded form, rows are reordered by their counts when padding every row to the longest
would gather this many times the entries or more."""

BAGGED = (torch.float32, torch.float64)
"""The dtypes applied by ``embedding_bag`` (as fast as the gathers or faster)."""


class GatherMatrix:
    """A sparse ``(rows, columns)`` matrix, applied to ``(columns, F)`` values.

    Args:
        rows, columns: ``(nnz,)`` integer positions of the entries.
        values: ``(nnz,)`` the entries (zeros dropped; repeated positions add up).
        shape: ``(rows, columns)`` of the matrix.
    """

    def __init__(self, rows: Tensor, columns: Tensor, values: Tensor,
                 shape: tuple[int, int]) -> None:
        self.shape = (int(shape[0]), int(shape[1]))
        rows, columns, values = _by_row(rows.long(), columns.long(), values)
        self.nonzeros = len(rows)
        counts = torch.bincount(rows, minlength=self.shape[0])
        self.taps = int(counts.max()) if len(rows) else 0
        index = torch.int32 if max(self.shape[1], len(rows)) < 2**31 else torch.long
        self.offsets = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)]).to(index)
        self.columns = columns.to(index)
        self._values = {values.dtype: values}
        self._padded: _Padded | None = None
        self._blocks: _native_gather.RowBlocks | None = None

    @classmethod
    def of_rows(cls, columns: Tensor, values: Tensor, count: int) -> GatherMatrix:
        """The matrix whose row ``r`` holds ``values[r]`` at columns ``columns[r]``, both
        ``(R, T)`` (every row ``T`` entries, zeros and repeats kept), of ``count`` columns:
        stored as given, without sorting."""
        matrix = cls.__new__(cls)
        rows, taps = columns.shape
        matrix.shape, matrix.taps, matrix.nonzeros = (rows, int(count)), taps, rows * taps
        index = torch.int32 if max(count, rows * taps) < 2**31 else torch.long
        matrix.offsets = torch.arange(0, rows * taps + 1, taps, dtype=index,
                                      device=columns.device)
        matrix.columns = columns.reshape(-1).to(index)
        matrix._values = {values.dtype: values.reshape(-1)}
        matrix._padded = None
        matrix._blocks = None
        return matrix

    def values(self, dtype: torch.dtype) -> Tensor:
        """The entries ``(nnz,)`` in row order, in ``dtype`` (converted once and kept)."""
        if dtype not in self._values:
            with outside_inference():
                self._values[dtype] = next(iter(self._values.values())).to(dtype)
        return self._values[dtype]

    def rows(self) -> Tensor:
        """The row of each entry ``(nnz,)``."""
        counts = (self.offsets[1:] - self.offsets[:-1]).long()
        return torch.repeat_interleave(torch.arange(self.shape[0], device=counts.device), counts)

    def apply(self, x: Tensor) -> Tensor:
        """``A x`` for ``x`` ``(columns, F)``: a new ``(rows, F)`` tensor."""
        if x.dim() != 2 or x.shape[0] != self.shape[1]:
            raise ValueError(f"x must be ({self.shape[1]}, F), got shape {tuple(x.shape)}")
        if self.nonzeros == 0:
            return x.new_zeros((self.shape[0], x.shape[1]))
        if _native_gather.applies(self.offsets, x):
            blocks = self.blocks() if x.shape[1] == 1 else None
            return _native_gather.product(self.offsets, self.columns, self.values(x.dtype), x,
                                          self.shape[0], blocks)
        if x.dtype in BAGGED:
            return F.embedding_bag(self.columns, x, self.offsets, mode="sum",
                                   per_sample_weights=self.values(x.dtype),
                                   include_last_offset=True)
        if self._padded is None:
            with outside_inference():
                self._padded = _Padded(self)
        return self._padded.apply(x)

    def blocks(self) -> _native_gather.RowBlocks:
        """The entries laid out for one column (:class:`~._native_gather.RowBlocks`), formed at
        the first call and kept; for the native kernels only (32-bit indices)."""
        if self._blocks is None:
            with outside_inference():
                self._blocks = _native_gather.RowBlocks(self.offsets, self.columns,
                                                        next(iter(self._values.values())))
        return self._blocks

    def transposed(self) -> GatherMatrix:
        """``A^T``, exactly (the same entries)."""
        values = next(iter(self._values.values()))
        return GatherMatrix(self.columns.long(), self.rows(), values,
                            (self.shape[1], self.shape[0]))

    def nbytes(self) -> int:
        """Bytes of the kept index and weight tensors."""
        tensors = [self.offsets, self.columns, *self._values.values()]
        if self._padded is not None:
            tensors += self._padded.tensors()
        if self._blocks is not None:
            tensors += self._blocks.tensors()
        return sum(t.numel() * t.element_size() for t in tensors)


class _Padded:
    """A :class:`GatherMatrix`'s entries padded to ``T`` per row, one gather a tap: ``columns``
    and ``weights`` per tap ``k`` for the first ``active[k]`` rows (in ``order`` when the
    rows are reordered by decreasing count, so that a few long rows do not pad every row)."""

    def __init__(self, matrix: GatherMatrix) -> None:
        rows, columns = matrix.rows(), matrix.columns.long()
        values = next(iter(matrix._values.values()))
        count = matrix.shape[0]
        counts = (matrix.offsets[1:] - matrix.offsets[:-1]).long()
        taps = matrix.taps
        self.order: Tensor | None = None
        if taps * count > PADDING * len(rows):
            counts, self.order = torch.sort(counts, descending=True, stable=True)
            position = torch.empty_like(self.order)
            position[self.order] = torch.arange(count, device=rows.device)
            rows, by_row = torch.sort(position[rows], stable=True)
            columns, values = columns[by_row], values[by_row]
            levels = torch.arange(taps, device=rows.device)[:, None]
            self.active = [int(n) for n in (counts[None, :] > levels).sum(1)]
        else:
            self.active = [count] * taps
        rank = torch.arange(len(rows), device=rows.device) - (torch.cumsum(counts, 0)
                                                              - counts)[rows]
        padded = torch.zeros((taps, count), dtype=matrix.columns.dtype, device=rows.device)
        padded[rank, rows] = columns.to(padded.dtype)
        weights = values.new_zeros((taps, count))
        weights[rank, rows] = values
        # one contiguous tensor a tap: the padded blocks are freed
        self.columns = [padded[k, :n].clone() for k, n in enumerate(self.active)]
        self._weights = {values.dtype: [weights[k, :n, None].clone()
                                        for k, n in enumerate(self.active)]}
        self.shape = matrix.shape

    def weights(self, dtype: torch.dtype) -> list[Tensor]:
        if dtype not in self._weights:
            with outside_inference():
                self._weights[dtype] = [w.to(dtype) for w in next(iter(self._weights.values()))]
        return self._weights[dtype]

    def apply(self, x: Tensor) -> Tensor:
        weights = self.weights(x.dtype)
        result = x.index_select(0, self.columns[0]) * weights[0]
        for k in range(1, len(self.columns)):
            result[:self.active[k]].addcmul_(x.index_select(0, self.columns[k]), weights[k])
        if self.order is None:
            return result
        return x.new_zeros((self.shape[0], x.shape[1])).index_copy_(
            0, self.order[:self.active[0]], result)

    def tensors(self) -> list[Tensor]:
        kept = [*self.columns, *(w for ws in self._weights.values() for w in ws)]
        return kept if self.order is None else [*kept, self.order]


def _by_row(rows: Tensor, columns: Tensor, values: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The entries without exact zeros, sorted by row (stably; repeated positions are kept:
    the products add them up)."""
    keep = values != 0
    rows, columns, values = rows[keep], columns[keep], values[keep]
    if len(rows) > 1 and not bool((rows[1:] >= rows[:-1]).all()):
        order = torch.argsort(rows, stable=True)
        rows, columns, values = rows[order], columns[order], values[order]
    return rows, columns, values
