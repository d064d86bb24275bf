"""The limiter of the closest-point stencils: bounds on a tricubic value that are continuous in
its point.

A limited stencil clamps the tricubic interpolant of its 4^3 taps to ``[low, high]``, so that
re-extension never creates a new extremum (data with jumps, the maximum principle). Clamping to
the range of the 8 nodes of the cell that holds the point would make the result jump wherever
the point crosses a cell face (the two cells' ranges differ there): a closest point on a node
plane (every symmetric placement, e.g. a sphere centred on a node) would make the flows'
output jump under any change of ``phi``, and autograd's derivative in ``phi`` meaningless.

Here each corner ``c`` of the cell contributes the extremes of the 27 nodes around it (inside
the 4^3 taps, and the same whichever of its cells holds the point), weighted by the point's
trilinear weight ``lambda_c``: ``high = sum_c lambda_c max_{27 around c} u``, likewise ``low``.
On a face the corners off it weigh nothing, so both cells give the same bounds; at a node the
bounds enclose the node's value, which the interpolant takes (data are reproduced there); and
they lie within the range of the taps, so no new extremum appears. The bounds are at least as
wide as the cell's range (every corner's 27 nodes hold the whole cell).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .._precision import in_data_dtype


def _constant(values: list, dtype: torch.dtype | None = None) -> Tensor:
    """A module constant on the CPU (callers move it), outside ``torch.inference_mode`` should
    this module be first imported inside it (an inference tensor could not be saved for a later
    backward) or under ``with torch.device(...)`` (a meta constant holds no values)."""
    with torch.inference_mode(False):
        return torch.tensor(values, dtype=dtype, device="cpu")


BLOCKS = _constant([
    [16 * (cz + dz) + 4 * (cy + dy) + (cx + dx)
     for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    for cz in (1, 2) for cy in (1, 2) for cx in (1, 2)
])
"""``(8, 27)``: the positions among the 4^3 taps (``16 z + 4 y + x``) of the 27 nodes around
each corner of the cell (corners in ``(z, y, x)`` order, ``4 z + 2 y + x``)."""

_OFFSETS = _constant([[x - 1, y - 1, z - 1] for z in range(4) for y in range(4)
                      for x in range(4)], dtype=torch.float64)
"""``(64, 3)``: each tap's ``(x, y, z)`` offset from the cell's first node."""


def corner_weights(wx: Tensor, wy: Tensor, wz: Tensor) -> Tensor:
    """The trilinear weights ``(N, 8)`` of the cell's corners (``4 z + 2 y + x``) at the points
    whose per-axis tricubic weights are ``wx, wy, wz`` ``(N, 4)`` (nodes ``-1, 0, 1, 2``): the
    fractions are ``sum_k w_k (k - 1)``, as Lagrange weights reproduce linear functions, kept
    in ``[0, 1]`` (a point past the box's last node: the weights stay convex)."""
    x, y, z = (torch.stack([1 - s, s], dim=1) for s in
               ((w[:, 2] + 2 * w[:, 3] - w[:, 0]).clamp(0, 1) for w in (wx, wy, wz)))
    return (z[:, :, None, None] * y[:, None, :, None] * x[:, None, None, :]).flatten(1)


def corner_weights_of_taps(taps: Tensor) -> Tensor:
    """:func:`corner_weights` from the 64 tap weights ``(N, 64)`` (their products)."""
    with in_data_dtype(taps):
        fractions = (taps @ _OFFSETS.to(taps)).clamp(0, 1)
    x, y, z = (torch.stack([1 - s, s], dim=1) for s in fractions.unbind(1))
    return (z[:, :, None, None] * y[:, None, :, None] * x[:, None, None, :]).flatten(1)


def corner_extremes(gathered: Tensor) -> tuple[Tensor, Tensor]:
    """The least and largest of the 27 taps around each corner, ``(..., 8)`` each, from the
    64 tap values ``(..., 64)``: sliding minima and maxima of 3 along each axis."""
    low = high = gathered.unflatten(-1, (4, 4, 4))
    for dim in (-1, -2, -3):
        low = torch.minimum(torch.minimum(low.narrow(dim, 0, 2), low.narrow(dim, 1, 2)),
                            low.narrow(dim, 2, 2))
        high = torch.maximum(torch.maximum(high.narrow(dim, 0, 2), high.narrow(dim, 1, 2)),
                             high.narrow(dim, 2, 2))
    return low.flatten(-3), high.flatten(-3)


def corner_extremes_of_taps(taps: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """:func:`corner_extremes` from the 64 tap values as a list of tensors (``16 z + 4 y + x``):
    elementwise operations only, for a compiled loop over the nodes."""
    def extremes(pick) -> list[Tensor]:  # noqa: ANN001
        x = [pick(pick(taps[4 * row + c], taps[4 * row + c + 1]), taps[4 * row + c + 2])
             for row in range(16) for c in (0, 1)]  # (z, y, cx): 32
        y = [pick(pick(x[8 * z + 2 * cy + cx], x[8 * z + 2 * (cy + 1) + cx]),
                  x[8 * z + 2 * (cy + 2) + cx])
             for z in range(4) for cy in (0, 1) for cx in (0, 1)]  # (z, cy, cx): 16
        return [pick(pick(y[4 * cz + plane], y[4 * (cz + 1) + plane]), y[4 * (cz + 2) + plane])
                for cz in (0, 1) for plane in range(4)]  # (cz, cy, cx): 8
    return extremes(torch.minimum), extremes(torch.maximum)


def bounds(low: Tensor, high: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The bounds ``sum_c weights_c low_c`` and ``... high_c`` ``(C, N)`` each, from the
    corners' extremes ``low, high`` ``(C, N, 8)`` and their weights ``(N, 8)``; each kept
    within its corners' range (``min_c low_c <= low <= max_c low_c``), which rounding of the
    sums (weights summing to ``1 +- ulp``) would leave by an ulp: clamped to a ``low`` above
    all-ones data, a value exceeded the data's range."""
    return (_within((low * weights).sum(-1), low.amin(-1), low.amax(-1)),
            _within((high * weights).sum(-1), high.amin(-1), high.amax(-1)))


def _within(value: Tensor, least: Tensor, most: Tensor) -> Tensor:
    """``value`` kept in ``[least, most]`` by ``maximum`` and ``minimum``, not ``torch.clamp``:
    where the weighted sum equals its corners' extreme (all corners alike, common) these split
    the gradient between the two as the re-extension's backward does; ``torch.clamp``'s went
    to one side (gradients off by up to 0.3 in ``tests/flows/test_reextension.py``)."""
    return torch.minimum(torch.maximum(value, least), most)


def bounds_of_lists(low: list[Tensor], high: list[Tensor], weights: list[Tensor]
                    ) -> tuple[Tensor, Tensor]:
    """:func:`bounds` from the 8 corners' extremes and weights as lists of tensors:
    elementwise operations only, for a compiled loop over the nodes."""
    def weighted_within(extremes: list[Tensor]) -> Tensor:
        least = most = extremes[0]
        for extreme in extremes[1:]:
            least, most = torch.minimum(least, extreme), torch.maximum(most, extreme)
        return _within(sum(w * m for w, m in zip(weights, extremes, strict=True)), least, most)
    return weighted_within(low), weighted_within(high)


TIES = 8
"""Where the bounds lie within this many units of roundoff of the taps' largest magnitude of
each other (data constant there to rounding) and the value within as much of them, it is
clamped, but its derivative is the stencil's own (the 64 taps), not the bounds' (the taps
holding the corners' extremes). On constant data the interpolant misses the constant by up to
2.6 units of roundoff either way (a review, 2026-12-07), and which nodes counted as clamped,
hence where their gradient went, was decided by rounding: a heat flow's gradient at constant
data was 0.82 off a central difference at every step, though the flow is linear there. The
same rule in the C kernels (``TIES`` there) and in the re-extension's backward
(``_reextension._scatter_back``)."""


def slack(magnitude: Tensor) -> Tensor:
    """:data:`TIES` units of roundoff of ``magnitude`` (the taps' largest ``|u|``)."""
    return magnitude * (TIES * torch.finfo(magnitude.dtype).eps)


def ties(value: Tensor, lower: Tensor, upper: Tensor, magnitude: Tensor) -> Tensor:
    """Where ``value`` sits on bounds ``[lower, upper]`` that are one to rounding
    (:data:`TIES`): a clamp there takes the stencil's derivative."""
    margin = slack(magnitude)
    return ((upper - lower <= margin) & (value >= lower - margin) & (value <= upper + margin)
            & torch.isfinite(value))


def limit(value: Tensor, lower: Tensor, upper: Tensor, magnitude: Tensor) -> Tensor:
    """``value`` clamped to ``[lower, upper]`` (all broadcastable); at :func:`ties`, with
    ``value``'s derivative. The values are the clamp's, bit for bit."""
    clamped = torch.minimum(torch.maximum(value, lower), upper)
    tied = ties(value, lower, upper, magnitude)
    return torch.where(tied, clamped.detach() + (value - value.detach()), clamped)


def clamp(value: Tensor, low: Tensor, high: Tensor, weights: Tensor) -> Tensor:
    """``value`` ``(C, N)`` limited (:func:`limit`) to the :func:`bounds` of the corners'
    extremes ``low, high`` ``(C, N, 8)`` with the corners' ``weights`` ``(N, 8)``."""
    lower, upper = bounds(low, high, weights)
    magnitude = torch.maximum(low.abs().amax(-1), high.abs().amax(-1))
    return limit(value, lower, upper, magnitude)


CELL = [16 * z + 4 * y + x for z in (1, 2) for y in (1, 2) for x in (1, 2)]
"""Positions, among the 4^3 taps, of the 8 nodes of the cell that holds the point: the bounds
hold their range, so a value inside it is not clamped."""

_CELL_TAPS = _constant(CELL)


def cell_values(gathered: Tensor) -> Tensor:
    """The values ``(..., 8)`` of the cell's nodes among the 64 taps' ``gathered`` ``(..., 64)``
    (``index_select``: 1.7x faster than indexing by a list)."""
    return gathered.index_select(-1, _CELL_TAPS.to(gathered.device))


def clamp_gathered(value: Tensor, gathered: Tensor, weights: Tensor) -> Tensor:
    """``value`` ``(C, N)`` limited, from its 64 taps' values ``gathered`` ``(C, N, 64)`` and
    the per-axis tricubic ``weights`` ``(3, N, 4)``. Eagerly, the bounds are formed only for
    the nodes whose value leaves its cell's range (the others are not clamped); traced by
    ``torch.compile``, for every node (no data-dependent shapes)."""
    if torch.compiler.is_compiling():
        return clamp(value, *corner_extremes(gathered), corner_weights(*weights.unbind(0)))
    cell = cell_values(gathered)
    outside = ((value < cell.amin(-1)) | (value > cell.amax(-1))).any(dim=0)
    nodes = outside.nonzero().squeeze(1)
    if len(nodes) == 0:
        return value
    limited = clamp(value[:, nodes], *corner_extremes(gathered[:, nodes]),
                    corner_weights(*weights[:, nodes].unbind(0)))
    return value.index_copy(1, nodes, limited)


def clamp_outside_range(value: Tensor, least: Tensor, most: Tensor, flat: Tensor,
                        taps: Callable[[Tensor], Tensor], weights: Tensor) -> Tensor:
    """The interpolated ``value`` ``(C, N)`` limited, given each cell's range ``least, most``
    ``(C, N)`` (the compiled interpolations form it from the taps they hold): the 64 taps of a
    node (``taps(nodes)``: flat positions ``(n, 64)`` in ``flat`` ``(C, M)``) are read only
    where ``value`` leaves that range (the bounds hold it: the others are not clamped);
    ``weights`` ``(3, N, 4)`` the per-axis weights."""
    outside = ((value < least) | (value > most)).any(dim=0)
    nodes = outside.nonzero().squeeze(1)
    if len(nodes) == 0:
        return value
    positions = taps(nodes)
    gathered = flat.index_select(1, positions.flatten()).view(flat.shape[0], *positions.shape)
    limited = clamp(value[:, nodes], *corner_extremes(gathered),
                    corner_weights(*weights[:, nodes].unbind(0)))
    return value.index_copy(1, nodes, limited)


def bounds_and_sources(gathered: Tensor, weights: Tensor
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The bounds ``(C, N)`` each and, for each, the taps ``(C, N, 8)`` (positions among the
    64) holding each corner's extreme: where a value is clamped, its gradient reaches those
    taps with the corners' ``weights`` ``(N, 8)``. ``gathered`` ``(C, N, 64)``."""
    blocks = gathered[..., BLOCKS.to(gathered.device)]  # (C, N, 8, 27)
    low, lowest = blocks.min(dim=-1)
    high, highest = blocks.max(dim=-1)
    table = BLOCKS.to(gathered.device)
    corners = torch.arange(8, device=gathered.device)
    return (*bounds(low, high, weights), table[corners, lowest], table[corners, highest])
