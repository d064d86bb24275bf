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
        rows, columns, values = _summed(rows.long(), columns.long(), values, self.shape)
        self.nonzeros = len(rows)
        counts = torch.bincount(rows, minlength=self.shape[0])
        self.taps = int(counts.max()) if len(rows) else 0
        self.order: Tensor | None = None
        """The rows by decreasing count, when they are reordered: tap ``k`` is then gathered
        for the first ``active[k]`` rows only, so that a few long rows (a transpose's) do not
        pad every row to their length."""
        if self.taps * self.shape[0] > PADDING * len(rows):
            counts, self.order = torch.sort(counts, descending=True, stable=True)
            position = torch.empty_like(self.order)
            position[self.order] = torch.arange(len(self.order), device=rows.device)
            rows, by_row = torch.sort(position[rows], stable=True)
            columns, values = columns[by_row], values[by_row]
            levels = torch.arange(self.taps, device=rows.device)[:, None]
            self.active = [int(n) for n in (counts[None, :] > levels).sum(1)]
        else:
            self.active = [self.shape[0]] * self.taps
        rank = torch.arange(len(rows), device=rows.device) - (torch.cumsum(counts, 0)
                                                              - counts)[rows]
        index = torch.int32 if self.shape[1] < 2**31 else torch.long
        padded = torch.zeros((self.taps, self.shape[0]), dtype=index, device=rows.device)
        padded[rank, rows] = columns.to(index)
        weights = values.new_zeros((self.taps, self.shape[0]))
        weights[rank, rows] = values
        # one contiguous tensor a tap: the padded blocks are freed
        self.columns = [padded[k, :n].clone() for k, n in enumerate(self.active)]
        self._weights = {values.dtype: [weights[k, :n, None].clone()
                                        for k, n in enumerate(self.active)]}

    def weights(self, dtype: torch.dtype) -> list[Tensor]:
        """Each tap's weights ``(active rows, 1)`` in ``dtype`` (converted once and kept)."""
        if dtype not in self._weights:
            self._weights[dtype] = [w.to(dtype) for w in next(iter(self._weights.values()))]
        return self._weights[dtype]

    def apply(self, x: Tensor) -> Tensor:
        """``A x`` for ``x`` ``(columns, F)``: a new ``(rows, F)`` tensor."""
        if x.dim() != 2 or x.shape[0] != self.shape[1]:
            raise ValueError(f"x must be ({self.shape[1]}, F), got shape {tuple(x.shape)}")
        if self.taps == 0:
            return x.new_zeros((self.shape[0], x.shape[1]))
        weights = self.weights(x.dtype)
        result = x.index_select(0, self.columns[0]) * weights[0]
        for k in range(1, self.taps):
            result[:self.active[k]].addcmul_(x.index_select(0, self.columns[k]), weights[k])
        if self.order is None:
            return result
        return x.new_zeros((self.shape[0], x.shape[1])).index_copy_(
            0, self.order[:self.active[0]], result)

    def transposed(self) -> GatherMatrix:
        """``A^T``, exactly (the same entries)."""
        weights = next(iter(self._weights.values()))
        rows = [torch.arange(n, device=weights[0].device) for n in self.active]
        if self.order is not None:
            rows = [self.order[row] for row in rows]
        return GatherMatrix(torch.cat([c.long() for c in self.columns]), torch.cat(rows),
                            torch.cat([w[:, 0] for w in weights]), (self.shape[1], self.shape[0]))

    def nbytes(self) -> int:
        """Bytes of the kept index and weight tensors."""
        tensors = [*self.columns, *(w for ws in self._weights.values() for w in ws)]
        if self.order is not None:
            tensors.append(self.order)
        return sum(t.numel() * t.element_size() for t in tensors)


def _summed(rows: Tensor, columns: Tensor, values: Tensor, shape: tuple[int, int]
            ) -> tuple[Tensor, Tensor, Tensor]:
    """The entries with repeated positions summed and zeros dropped, sorted by row."""
    key = rows * shape[1] + columns
    unique, inverse = torch.unique(key, return_inverse=True)
    summed = values.new_zeros(len(unique)).index_add_(0, inverse, values)
    keep = summed != 0
    unique, summed = unique[keep], summed[keep]
    return unique // shape[1], unique % shape[1], summed
