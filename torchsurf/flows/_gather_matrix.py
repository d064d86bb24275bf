"""Sparse matrices applied as a few row gathers: the band operators on packed node values.

A :class:`GatherMatrix` of ``R`` rows stores, for each row, its nonzero columns and weights
padded to the longest row's count ``T``: ``columns (T, R)``, ``weights (T, R, 1)``. ``A x`` for
``x`` ``(N, F)`` is then ``sum_k weights[k] * x[columns[k]]``, ``T`` gathers of whole rows of
``x`` and fused multiply-adds, which are plain tensor operations (``torch.compile`` traces
them). At ``R = 30k``, ``T = 27``, ``F = 16`` one application took 4 ms on one thread (AMD
EPYC), as long as a CSR product (which ``torch.compile`` does not trace) and 14x less than
gathering every tap at once.
"""

from __future__ import annotations

import torch
from torch import Tensor

PADDING = 1.2
"""Rows are reordered by their counts when padding every row to the longest would gather this
many times the entries or more."""


class GatherMatrix:
    """A sparse ``(rows, columns)`` matrix, applied to ``(columns, F)`` values by gathers.

    Args:
        rows, columns: ``(nnz,)`` integer positions of the entries.
        values: ``(nnz,)`` the entries (zeros dropped; repeated positions are summed).
        shape: ``(rows, columns)`` of the matrix.
    """

    def __init__(self, rows: Tensor, columns: Tensor, values: Tensor,
                 shape: tuple[int, int]) -> None:
        self.shape = (int(shape[0]), int(shape[1]))
        self._entries = _summed(rows.long(), columns.long(), values, self.shape)
        rows, columns, values = self._entries
        counts = torch.bincount(rows, minlength=self.shape[0])
        self.taps = int(counts.max()) if len(rows) else 0
        # rows by decreasing count: tap k is gathered for the first active[k] rows only, so
        # that a few long rows (a transpose's) do not pad every row to their length
        self.order = None
        if self.taps * self.shape[0] > PADDING * len(rows):
            counts, self.order = torch.sort(counts, descending=True, stable=True)
            position = torch.empty_like(self.order)
            position[self.order] = torch.arange(len(self.order), device=rows.device)
            rows = position[rows]
            rows, by_row = torch.sort(rows, stable=True)
            columns, values = columns[by_row], values[by_row]
            self.active = [int(n) for n in
                           (counts[None, :] > torch.arange(self.taps, device=rows.device)[:, None]).sum(1)]
        else:
            self.active = [self.shape[0]] * self.taps
        rank = torch.arange(len(rows), device=rows.device) - (torch.cumsum(counts, 0)
                                                              - counts)[rows]
        small = self.shape[1] < 2**31
        self.columns = torch.zeros((self.taps, self.shape[0]),
                                   dtype=torch.int32 if small else torch.long, device=rows.device)
        self.columns[rank, rows] = columns.to(self.columns.dtype)
        weights = values.new_zeros((self.taps, self.shape[0]))
        weights[rank, rows] = values
        self._weights = {weights.dtype: weights[..., None]}
        self.columns = [self.columns[k, :n] for k, n in enumerate(self.active)]

    @property
    def nonzeros(self) -> int:
        """The number of stored entries."""
        return len(self._entries[0])

    def weights(self, dtype: torch.dtype) -> Tensor:
        """``(T, R, 1)`` in ``dtype`` (converted once and kept)."""
        if dtype not in self._weights:
            self._weights[dtype] = next(iter(self._weights.values())).to(dtype)
        return self._weights[dtype]

    def apply(self, x: Tensor) -> Tensor:
        """``A x`` for ``x`` ``(columns, F)``: a new ``(rows, F)`` tensor."""
        if x.shape[0] != self.shape[1]:
            raise ValueError(f"x must have {self.shape[1]} rows, got shape {tuple(x.shape)}")
        if self.taps == 0:
            return x.new_zeros((self.shape[0], *x.shape[1:]))
        weights = self.weights(x.dtype)
        rows = self.active[0]
        result = x.index_select(0, self.columns[0]) * weights[0, :rows]
        for k in range(1, self.taps):
            active = self.active[k]
            result[:active].addcmul_(x.index_select(0, self.columns[k]), weights[k, :active])
        if self.order is None:
            return result
        return x.new_zeros((self.shape[0], *x.shape[1:])).index_copy_(
            0, self.order[:rows], result)

    def transposed(self) -> GatherMatrix:
        """``A^T``, exactly (the same entries)."""
        rows, columns, values = self._entries
        return GatherMatrix(columns, rows, values, (self.shape[1], self.shape[0]))


def _summed(rows: Tensor, columns: Tensor, values: Tensor, shape: tuple[int, int]
            ) -> tuple[Tensor, Tensor, Tensor]:
    """The entries with repeated positions summed and zeros dropped, sorted by row."""
    key = rows * shape[1] + columns
    unique, inverse = torch.unique(key, return_inverse=True)
    summed = values.new_zeros(len(unique)).index_add_(0, inverse, values)
    keep = summed != 0
    unique, summed = unique[keep], summed[keep]
    return unique // shape[1], unique % shape[1], summed
