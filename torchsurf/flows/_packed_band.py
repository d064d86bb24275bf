"""The band Laplacian ``L = M W^-1 A E M`` on the band's nodes alone, for a fixed surface.

:class:`~torchsurf.flows.exponential.BandLaplacian` applies ``L`` to whole volumes: its stencils
run over every node of the box, of which the band holds 4-12% at 64^3-128^3. With ``phi``
fixed, ``L`` is a fixed sparse matrix, so :class:`PackedBand` assembles its parts once per
surface as :class:`~torchsurf.flows._gather_matrix.GatherMatrix` es on the band and ring's nodes
and applies them to packed values ``(nodes, C, K)``:

- ``A / W`` on the band's rows, read off the volume operator itself: the operator applied to
  indicator volumes of the region's nodes of each of ``(2 r + 1)^3`` colours (``r`` the
  scheme's reach), no two nodes of a colour within ``2 r`` of each other, gives each band
  node's coefficient for each of its neighbours;
- ``E``: the ring's first pass (the tricubic closest-point weights of
  :class:`~torchsurf.flows.exponential.RingFill`, or a box mean for its orphans) and its sweeps
  over the chained ring nodes, taken from the stencils' own tap positions and weights;
- their transposes, exactly, for ``L^T``.

The result equals the volume path's to rounding (tests/flows/test_packed_band.py).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..operators import functional
from ._gather_matrix import GatherMatrix
from .extension import CubicStencil

if TYPE_CHECKING:
    from .exponential import BandLaplacian, RingFill

REACH = {"octant": 1, "symmetric": 1, "conservative": 1}
"""How many nodes along each axis a scheme's weighted operator ``A`` couples on each side: 19
(octant) and 13 (flux forms) of the 27 nodes of a 3x3x3 block (the flux forms' kernels pad by
two nodes, but ``A``'s coefficients reach one; tests/flows/test_packed_band.py measures it)."""

PROBES_AT_ONCE = 27
"""Most colour indicators run through the volume operator in one call."""

PROBE_VALUES = 2**25
"""Most values of the indicators run at once (128 MB in float32; fewer colours per call on
large grids)."""


class PackedBand:
    """``L`` and ``L^T`` on packed band values, and the ring's re-extension ``E``.

    Packed values are ``(nodes, C, K)``: for a surface of batch 1, ``K`` is the data's batch
    and the nodes are one volume's; for a surface of batch ``B``, ``K = 1`` and the nodes are
    every entry's, entry after entry. The band's nodes come first (``band_count`` of them),
    then the ring's.

    Args:
        operator: a :class:`~torchsurf.flows.exponential.BandLaplacian` on a dense surface whose
            ``phi`` does not require grad.
    """

    def __init__(self, operator: BandLaplacian) -> None:
        band, region = operator.band, operator.region
        self.volume_shape = tuple(band.shape[-3:])
        self.entries = band.shape[0]
        band_nodes = band.reshape(-1).nonzero().squeeze(1)
        ring_nodes = (region & ~band).reshape(-1).nonzero().squeeze(1)
        self.nodes = torch.cat([band_nodes, ring_nodes])
        self.band_count = len(band_nodes)
        count = len(self.nodes)
        lookup = torch.full((band.numel(),), -1, dtype=torch.long, device=band.device)
        lookup[self.nodes] = torch.arange(count, device=band.device)
        self.weighted = _probed(operator, self.nodes[:self.band_count], lookup, count)
        self.weighted_transposed = self.weighted.transposed()
        ring = operator.ring
        self.first = _first_pass(ring, lookup, self.band_count, count - self.band_count,
                                 self.volume_shape)
        self.first_transposed = self.first.transposed()
        self.sweeps = ring.sweeps if ring.chained is not None else 0
        if self.sweeps:
            self.chained_rows, self.chained = _stencil_rows(ring.chained, lookup, count,
                                                            self.volume_shape)
            self.chained_transposed = self.chained.transposed()

    # --- packing -------------------------------------------------------------------------

    def pack(self, u: Tensor) -> Tensor:
        """The band's values of ``u`` ``(B, C, D, H, W)``: ``(band nodes, C, K)`` (autograd
        reaches ``u``)."""
        flat = u.reshape(u.shape[0], u.shape[1], -1)
        band = self.nodes[:self.band_count]
        if self.entries == 1:
            return flat.index_select(2, band).permute(2, 1, 0).contiguous()
        flat = flat.expand(self.entries, *flat.shape[1:])
        size = flat.shape[-1]
        return flat[band // size, :, band % size][..., None]

    def unpack(self, values: Tensor, like: Tensor) -> Tensor:
        """Region values ``(nodes, C, K)`` as a volume shaped like ``like`` ``(B, C, D, H,
        W)`` (batch ``entries`` if ``like``'s is 1), zero off the band and ring."""
        batch = max(like.shape[0], self.entries)
        channels = values.shape[1]
        size = math.prod(self.volume_shape)
        if self.entries == 1:
            flat = values.new_zeros((batch, channels, size)).index_copy(
                2, self.nodes, values.permute(2, 1, 0))
            return flat.reshape(batch, channels, *self.volume_shape)
        flat = values.new_zeros((batch * size, channels)).index_copy(0, self.nodes, values[..., 0])
        return flat.reshape(batch, *self.volume_shape, channels).permute(0, 4, 1, 2, 3)

    # --- the operators on packed values --------------------------------------------------

    def fill(self, x: Tensor) -> Tensor:
        """``E x``: band values ``(band nodes, C, K)`` -> region values ``(nodes, C, K)``."""
        values = x.reshape(x.shape[0], -1)
        region = torch.cat([values, self.first.apply(values)])
        for _ in range(self.sweeps):
            region = region.index_copy(0, self.chained_rows, self.chained.apply(region))
        return region.reshape(-1, *x.shape[1:])

    def fill_transpose(self, g: Tensor) -> Tensor:
        """``E^T g``: region values -> band values."""
        shape = g.shape[1:]
        g = g.reshape(g.shape[0], -1)
        for _ in range(self.sweeps):
            swept = g.index_select(0, self.chained_rows)
            g = g.index_fill(0, self.chained_rows, 0.0).add_(self.chained_transposed.apply(swept))
        band = g[:self.band_count] + self.first_transposed.apply(g[self.band_count:])
        return band.reshape(-1, *shape)

    def apply(self, x: Tensor) -> Tensor:
        """``L x`` for band values ``x`` ``(band nodes, C, K)``."""
        image = self.weighted.apply(self.fill(x).reshape(-1, x.shape[1] * x.shape[2]))
        return image.reshape(x.shape)

    def transpose(self, g: Tensor) -> Tensor:
        """``L^T g`` for band values ``g`` ``(band nodes, C, K)``."""
        spread = self.weighted_transposed.apply(g.reshape(g.shape[0], -1))
        return self.fill_transpose(spread.reshape(-1, *g.shape[1:]))


class Fill(torch.autograd.Function):
    """``E x`` on packed values; backward ``E^T g`` (nothing saved)."""

    @staticmethod
    def forward(ctx, packed, x):  # noqa: ANN001, ANN205
        ctx.packed = packed
        return packed.fill(x)

    @staticmethod
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        return None, ctx.packed.fill_transpose(grad_output)


def _coordinates(flat: Tensor, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Entry and ``(z, y, x)`` of flat positions in ``(entries, D, H, W)``."""
    depth, height, width = shape
    x = flat % width
    y = (flat // width) % height
    z = (flat // (width * height)) % depth
    return flat // (width * height * depth), z, y, x


def _probed(operator: BandLaplacian, band_nodes: Tensor, lookup: Tensor, count: int
            ) -> GatherMatrix:
    """``W^-1 A`` on the band's rows and the region's columns, read off the volume operator
    applied to colour indicators of the region's nodes (module docstring), on the box around
    the region (with a margin of more than the stencil's reach: the rows see the geometry and
    the box faces the whole volume does)."""
    surface = operator.surface
    reach = REACH[operator.scheme]
    side = 2 * reach + 1
    shape = tuple(operator.band.shape[-3:])
    entries = operator.band.shape[0]
    region = operator.region[:, 0]
    occupied = [region.any(dim=tuple(d for d in range(4) if d != axis)).nonzero().squeeze(1)
                for axis in (1, 2, 3)]
    crop = [slice(max(0, int(o[0]) - reach - 2), min(n, int(o[-1]) + reach + 3))
            for o, n in zip(occupied, shape, strict=True)]
    low = [c.start for c in crop]
    cropped = tuple(c.stop - c.start for c in crop)
    cells = cropped[0] * cropped[1] * cropped[2]
    normal, weight = (field[(..., *crop)] for field in (surface.normal, surface.weight))
    device = band_nodes.device
    grids = torch.meshgrid(*(torch.arange(c.start, c.stop, device=device) % side for c in crop),
                           indexing="ij")
    colour = (grids[0] * side + grids[1]) * side + grids[2]  # (d, h, w) of the crop
    region = region[(slice(None), *crop)]
    entry, z, y, x = _coordinates(band_nodes, shape)
    z, y, x = z - low[0], y - low[1], x - low[2]
    node = (z * cropped[1] + y) * cropped[2] + x
    flat_weight = weight.reshape(weight.shape[0], -1)
    inverse_weight = 1.0 / flat_weight[entry % flat_weight.shape[0], node]
    at_once = max(1, min(PROBES_AT_ONCE, PROBE_VALUES // (entries * cells)))
    offsets = [(dz, dy, dx) for dz in range(-reach, reach + 1) for dy in range(-reach, reach + 1)
               for dx in range(-reach, reach + 1)]
    rows, columns, values = [], [], []
    with torch.no_grad():
        for first in range(0, side**3, at_once):
            colours = torch.arange(first, min(first + at_once, side**3), device=device)
            probes = (region[:, None] & (colour == colours[:, None, None, None])).to(
                surface.phi.dtype)
            response = functional.divergence_form(
                probes, normal, weight, surface.spacing, operator.scheme, operator.path,
                weighted=True).reshape(entries, len(colours), -1)
            for dz, dy, dx in offsets:
                qz, qy, qx = z + dz, y + dy, x + dx
                inside = ((qz >= 0) & (qz < cropped[0]) & (qy >= 0) & (qy < cropped[1])
                          & (qx >= 0) & (qx < cropped[2]))
                qz, qy, qx = (qz.clamp(0, cropped[0] - 1), qy.clamp(0, cropped[1] - 1),
                              qx.clamp(0, cropped[2] - 1))
                column = lookup[((entry * shape[0] + qz + low[0]) * shape[1] + qy + low[1])
                                * shape[2] + qx + low[2]]
                which = colour[qz, qy, qx] - first
                take = inside & (column >= 0) & (which >= 0) & (which < len(colours))
                rows.append(take.nonzero().squeeze(1))
                columns.append(column[take])
                values.append(response[entry[take], which[take], node[take]]
                              * inverse_weight[take])
    return GatherMatrix(torch.cat(rows), torch.cat(columns), torch.cat(values),
                        (len(band_nodes), count))


def _stencil_entries(stencil: CubicStencil, lookup: Tensor, shape: tuple[int, int, int]
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """Every part's ``(target, tap, weight)`` as region positions ``(n * 64,)`` each (taps
    outside the region at -1)."""
    size = shape[0] * shape[1] * shape[2]
    targets, taps, weights = [], [], []
    for entry, (target, corners, weight) in enumerate(stencil.parts):
        x, y, z = corners.long().unbind(0)
        sources = ((z[:, :, None, None] * shape[1] + y[:, None, :, None]) * shape[2]
                   + x[:, None, None, :]).flatten(1)
        wx, wy, wz = weight.unbind(0)
        products = (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).flatten(1)
        offset = entry * size
        targets.append(lookup[target + offset][:, None].expand(-1, 64).reshape(-1))
        taps.append(lookup[sources + offset].reshape(-1))
        weights.append(products.reshape(-1))
    return torch.cat(targets), torch.cat(taps), torch.cat(weights)


def _first_pass(ring: RingFill, lookup: Tensor, band_count: int, ring_count: int,
                shape: tuple[int, int, int]) -> GatherMatrix:
    """The ring's first values from the band's: ``(ring nodes, band nodes)``. The closest-point
    taps on the band (those on the ring read zero in this pass); orphans take the mean of their
    3x3x3 band neighbours instead."""
    target, tap, weight = _stencil_entries(ring.first, lookup, shape)
    keep = (tap >= 0) & (tap < band_count)
    target, tap, weight = target[keep] - band_count, tap[keep], weight[keep]
    if ring.orphans is not None:
        orphans = ring.orphans.reshape(-1).nonzero().squeeze(1)
        rows = lookup[orphans] - band_count
        adopted = torch.zeros(ring_count, dtype=torch.bool, device=lookup.device)
        adopted[rows] = True
        keep = ~adopted[target]
        target, tap, weight = target[keep], tap[keep], weight[keep]
        neighbours = ring._neighbours.reshape(-1)[orphans]
        entry, z, y, x = _coordinates(orphans, shape)
        extra_rows, extra_taps, extra_weights = [], [], []
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    qz, qy, qx = z + dz, y + dy, x + dx
                    inside = ((qz >= 0) & (qz < shape[0]) & (qy >= 0) & (qy < shape[1])
                              & (qx >= 0) & (qx < shape[2]))
                    flat = ((entry * shape[0] + qz.clamp(0, shape[0] - 1)) * shape[1]
                            + qy.clamp(0, shape[1] - 1)) * shape[2] + qx.clamp(0, shape[2] - 1)
                    column = lookup[flat]
                    take = inside & (column >= 0) & (column < band_count)
                    extra_rows.append(rows[take])
                    extra_taps.append(column[take])
                    extra_weights.append(1.0 / neighbours[take])
        target = torch.cat([target, *extra_rows])
        tap = torch.cat([tap, *extra_taps])
        weight = torch.cat([weight, *(w.to(weight.dtype) for w in extra_weights)])
    return GatherMatrix(target, tap, weight, (ring_count, band_count))


def _stencil_rows(stencil: CubicStencil, lookup: Tensor, count: int,
                  shape: tuple[int, int, int]) -> tuple[Tensor, GatherMatrix]:
    """A stencil's target rows (region positions) and its weights ``(targets, region nodes)``."""
    target, tap, weight = _stencil_entries(stencil, lookup, shape)
    if bool((tap < 0).any()):
        raise RuntimeError("a ring sweep reads a node off the band and ring")
    rows, local = torch.unique(target, return_inverse=True)
    return rows, GatherMatrix(local, tap, weight, (len(rows), count))
