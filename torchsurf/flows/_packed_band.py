"""The band Laplacian ``L = M W^-1 A E M`` and the heat flow's stencils on the band's nodes
alone, for a fixed surface.

:class:`~torchsurf.flows.exponential.BandLaplacian` and the flows apply their stencils to whole
volumes: they run over every node of the box, of which the band holds 4-12% at 64^3-128^3 (or
over every stored brick's, 2-5 times the band's). With ``phi`` fixed, the linear operators are
fixed sparse matrices, assembled here once per surface as
:class:`~torchsurf.flows._gather_matrix.GatherMatrix` es on the band and ring's nodes and applied
to packed values ``(nodes, C, K)``:

- :class:`PackedRegion`: the packing, and ``W^-1 A`` on the band's rows, formed at the band's
  nodes in closed form (:func:`torchsurf.operators.spectrum.laplace_beltrami_rows`; on bricks
  from each brick's haloed geometry), with its Gershgorin bound (the heat flow's rate,
  :meth:`torchsurf.flows.HeatFlow.packed_system`); tested entry by entry against the volume
  operator applied to colour indicators (tests/flows/_probed_reference.py);
- :class:`PackedStencil`: a limited closest-point stencil (the flows' re-extensions), from the
  stencil's own tap positions and weights;
- :class:`PackedBand`: adds ``E``, the ring's first pass (the tricubic closest-point weights of
  :class:`~torchsurf.flows.exponential.RingFill`, or a box mean for its orphans) and its sweeps
  over the chained ring nodes, and the transposes, exactly, for ``L^T`` (the heat semigroup).

Results equal the volume path's to rounding (tests/flows/test_packed_band.py,
tests/flows/test_packed_flow.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import torch
from torch import Tensor

from .._inference import outside_inference
from .._transforms import refuse_batched_backward
from ..bricks.layout import BRICK
from ..operators.spectrum import ROWS_AT_ONCE, gershgorin_sums, laplace_beltrami_rows
from ..stencils import NEIGHBOURHOOD, BoxNeighbours
from ..surface import ImplicitSurface
from . import _limiter, _native_gather
from ._gather_matrix import GatherMatrix
from .extension import (
    STENCIL_CHUNK,
    BrickCubicStencil,
    CubicStencil,
    _dense_tap_indices,
    tap_weights,
)

Stencil = CubicStencil | BrickCubicStencil

BRICK_NODES = BRICK**3
"""Nodes of a brick."""


class RingFill(Protocol):
    """What :class:`PackedBand` reads of the ring's re-extension
    (:class:`~torchsurf.flows.exponential.RingFill`)."""

    first: Stencil
    chained: Stencil | None
    sweeps: int
    orphans: Tensor | None
    neighbours: Tensor | None


GATHER_ROWS = 2**14
"""Rows whose 64 taps the limiter's fallback (no C kernel) gathers at once: 64 values a row and
column."""


class PackedRegion:
    """A surface's band and ring as packed node values, and ``W^-1 A`` on the band's rows.

    Packed values are ``(nodes, C, K)``: for a dense surface of batch 1, ``K`` is the data's
    batch and the nodes are one volume's; for a dense surface of batch ``B``, ``K = 1`` and the
    nodes are every entry's, entry after entry; for a brick surface, ``K = 1`` and the nodes
    are the stored bricks', in storage order. The band's nodes come first (``band_count`` of
    them), then the ring's.

    Args:
        surface: the surface (dense or bricks); its ``phi`` does not require grad.
        scheme: the divergence-form scheme of ``A``.
        band, region: the band and the band with its ring, bool masks of the surface's storage.
    """

    def __init__(self, surface: ImplicitSurface, scheme: str, band: Tensor,
                 region: Tensor) -> None:
        self.storage = _Storage(surface, band)
        self.volume_shape = self.storage.volume_shape
        self.entries = band.shape[0]
        band_nodes = band.reshape(-1).nonzero().squeeze(1)
        ring_nodes = (region & ~band).reshape(-1).nonzero().squeeze(1)
        self.nodes = torch.cat([band_nodes, ring_nodes])
        self.band_count = len(band_nodes)
        count = len(self.nodes)
        # node -> packed position, 4 bytes a stored node (the whole box on a dense surface)
        index = torch.int32 if count < 2**31 else torch.long
        self.lookup = torch.full((band.numel(),), -1, dtype=index, device=band.device)
        self.lookup[self.nodes] = torch.arange(count, dtype=index, device=band.device)
        self.weighted, self.band_bound = _formed_rows(surface, scheme, self.storage,
                                                      band_nodes, self.lookup, count,
                                                      self.band_count)
        self._band_mask: Tensor | None = None
        self._stencils: dict[int, tuple[Stencil, PackedStencil]] = {}
        self.shapes = self.entries if surface.layout is None else len(surface.layout.grids)
        self._entry_of_nodes = (self.storage.coordinates(self.nodes)[0].long()
                                if self.shapes > 1 else None)
        self._entry_firsts = self._firsts_of_entries(self.shapes) if self.shapes > 1 else None

    def _firsts_of_entries(self, shapes: int) -> Tensor:
        """For each region node, the packed position of the first band node of its surface's
        entry (of ``shapes``; 0 for an entry without band nodes, which has no ring nodes)."""
        entry = self._entry_of_nodes
        count = len(self.nodes)
        positions = torch.arange(count, device=entry.device)
        firsts = torch.full((shapes,), count, dtype=torch.long, device=entry.device)
        firsts = firsts.scatter_reduce(0, entry[:self.band_count], positions[:self.band_count],
                                       "amin")
        return torch.where(firsts < count, firsts, 0)[entry]

    def entry_offsets(self, values: Tensor, nodes: int | None = None) -> Tensor:
        """Each node's offset: the values ``(band nodes or more, ...)`` at its entry's first band
        node, for the first ``nodes`` region nodes (all of them by default). Shifting by it
        keeps each entry's rounding its own: one offset for a batch cost an entry of values
        in ``[0, 1]`` beside one near ``1e4`` 4e-3 in float32."""
        if self._entry_firsts is None:
            return values[:1]
        firsts = self._entry_firsts if nodes is None else self._entry_firsts[:nodes]
        return values.index_select(0, firsts)

    def ring_within_band_range(self, values: Tensor) -> Tensor:
        """``values`` ``(nodes, C, K)`` with each ring node's value clamped to the range of its
        entry's band values (per channel and column), so that an unlimited fill of the ring
        brings no new extremum into a limited re-extension that reads it."""
        band, ring = values[:self.band_count], values[self.band_count:]
        if self._entry_of_nodes is None:
            low, high = band.amin(0, keepdim=True), band.amax(0, keepdim=True)
        else:
            entry = self._entry_of_nodes.view(-1, 1, 1)
            extremes = []
            for reduce, start in (("amin", math.inf), ("amax", -math.inf)):
                table = band.new_full((self.shapes, *band.shape[1:]), start)
                table = table.scatter_reduce(0, entry[:self.band_count].expand_as(band), band,
                                             reduce)
                extremes.append(table.index_select(0, entry[self.band_count:, 0, 0]))
            low, high = extremes
        return torch.cat([band, torch.minimum(torch.maximum(ring, low), high)])

    # --- packing -------------------------------------------------------------------------

    def pack(self, u: Tensor) -> Tensor:
        """The band's values of ``u`` ``(B, C, D, H, W)`` (or packed bricks ``(N, C, 8, 8,
        8)``): ``(band nodes, C, K)`` (autograd reaches ``u``)."""
        return self._gathered(u, self.nodes[:self.band_count])

    def pack_region(self, u: Tensor) -> Tensor:
        """The band and ring's values of ``u``: ``(nodes, C, K)`` (autograd reaches ``u``)."""
        return self._gathered(u, self.nodes)

    def _gathered(self, u: Tensor, nodes: Tensor) -> Tensor:
        flat = u.reshape(u.shape[0], u.shape[1], -1)
        if self.entries == 1:
            # a copy with the standard strides: (nodes, 1, 1) permuted keeps strides (1, N, N),
            # "contiguous" to torch, whose copies of such tensors ran 15x slower
            return flat.index_select(2, nodes).permute(2, 1, 0).clone(
                memory_format=torch.contiguous_format)
        flat = flat.expand(self.entries, *flat.shape[1:])
        size = flat.shape[-1]
        return flat[nodes // size, :, nodes % size][..., None]

    def unpack(self, values: Tensor, like: Tensor) -> Tensor:
        """Region values ``(nodes, C, K)`` as a field shaped like ``like`` ``(B, C, D, H, W)``
        (batch ``entries`` if ``like``'s is 1) or ``(N, C, 8, 8, 8)``, zero off the band and
        ring."""
        batch = max(like.shape[0], self.entries)
        channels = values.shape[1]
        size = math.prod(self.volume_shape)
        if self.entries == 1:
            flat = values.new_zeros((batch, channels, size)).index_copy(
                2, self.nodes, values.permute(2, 1, 0))
            return flat.reshape(batch, channels, *self.volume_shape)
        flat = values.new_zeros((batch * size, channels)).index_copy(0, self.nodes, values[..., 0])
        return flat.reshape(batch, *self.volume_shape, channels).permute(0, 4, 1, 2, 3)

    def unpack_onto(self, values: Tensor, like: Tensor, region: Tensor) -> Tensor:
        """``like`` with the nodes of ``region`` (this packing's band and ring, a bool mask of
        the storage) replaced by the region values ``values`` ``(nodes, C, K)``: a new tensor
        shaped like :meth:`unpack`'s (autograd reaches both)."""
        if self.entries != 1:
            return torch.where(region, self.unpack(values, like), like)
        flat = like.reshape(like.shape[0], like.shape[1], -1).clone()
        return flat.index_copy_(2, self.nodes, values.permute(2, 1, 0)).reshape(like.shape)

    def band_mask(self) -> Tensor:
        """``(nodes, 1, 1)`` bool, true on the band's nodes (a packed flow's band)."""
        if self._band_mask is None:
            with outside_inference():
                mask = torch.zeros((len(self.nodes), 1, 1), dtype=torch.bool,
                                   device=self.nodes.device)
                mask[:self.band_count] = True
            self._band_mask = mask  # whole: another thread may read it at once
        return self._band_mask

    def weighted_apply(self, z: Tensor) -> Tensor:
        """``W^-1 A z`` on the band's rows for region values ``z`` ``(nodes, F)``.

        ``A`` annihilates constants, so it is applied to ``z`` minus each entry's first node's
        values (:meth:`entry_offsets`): the products then carry the rounding of the data's
        variation, not of its offset (the volume stencils difference neighbours first; without
        the shift, float32 noise on an offset of 1e3 kept errors of 1e-3 that the volume path
        smooths away). The offsets are detached: ``A`` annihilates them, so their gradient is
        zero, which backward summed over the band's rows into each first node, in an order
        that follows the threads (the gradient then differed between 1 and 2 threads: 4.1e-5
        of 5.3 in float32 at 64^3)."""
        return self.weighted.apply(z - self.entry_offsets(z).detach())

    def laplacian(self, z: Tensor) -> Tensor:
        """``W^-1 A z`` on the band's rows, zero on the ring's, for region values ``z``
        ``(nodes, C, K)`` (the ring's values read as they are): autograd reaches ``z``."""
        image = self.weighted_apply(z.reshape(z.shape[0], -1))
        ring = image.new_zeros((len(self.nodes) - self.band_count, image.shape[1]))
        return torch.cat([image, ring]).reshape(z.shape)

    def stencil(self, stencil: Stencil) -> PackedStencil:
        """A limited closest-point stencil of the surface's storage on packed region values
        (assembled once per stencil and kept)."""
        key = id(stencil)
        if key not in self._stencils:  # the stencil is kept too: its id is not reused
            with outside_inference():
                self._stencils[key] = (stencil, PackedStencil(stencil, self.storage,
                                                              self.lookup, len(self.nodes)))
        return self._stencils[key][1]


class FusedStage:
    """The RKC stages of the heat rate ``scale W^-1 A z`` on a packed region's values, each in
    one native pass (:func:`~._native_gather.rkc_stage`: the operator's rows and the stage's
    combination together, instead of a product and seven pointwise passes; the ring's values
    held, or re-extended before each stage by ``fill``), for up to
    :data:`~._native_gather.STAGE_COLUMNS` columns of values and no gradient (:meth:`applies`).
    A :class:`~._rkc.LinearStage`.

    Args:
        packing: the packed band and ring.
        scale: the rate's constant factor (the diffusivity).
        fill: the ring's re-extension from the band's values, applied to each stage's input
            (region values ``(nodes, C, K)`` -> new ones), or ``None`` where a step holds the
            ring.
    """

    def __init__(self, packing: PackedRegion, scale: float,
                 fill: Callable[[Tensor], Tensor] | None = None) -> None:
        self.packing, self.scale, self.fill = packing, float(scale), fill

    def filled(self, fill: Callable[[Tensor], Tensor]) -> FusedStage:
        """These stages with the ring re-extended by ``fill`` before each."""
        return FusedStage(self.packing, self.scale, fill)

    def applies(self, u: Tensor) -> bool:
        """Whether the stages run natively for region values ``u`` ``(nodes, C, K)``."""
        if u.shape[1:].numel() > _native_gather.STAGE_COLUMNS or torch.compiler.is_compiling():
            return False
        if torch.is_grad_enabled() and u.requires_grad:
            return False
        matrix = self.packing.weighted
        return matrix.nonzeros > 0 and _native_gather.applies(matrix.offsets,
                                                              u.reshape(len(u), -1))

    def step(self, u: Tensor, weights: list[tuple[float, float, float, float]]) -> Tensor | None:
        """The whole step in one native call (:func:`~._native_gather.rkc_step`), or ``None``
        where its rows are split between threads or the ring is re-extended at each stage."""
        if self.fill is not None or u.shape[1:].numel() != 1:
            return None
        scaled = torch.tensor(weights, dtype=torch.float64)
        scaled[:, 2:] *= self.scale
        whole = _native_gather.rkc_step(self.packing.weighted.blocks(),
                                        u.reshape(-1, 1).contiguous(), scaled)
        return None if whole is None else whole.reshape(u.shape)

    def __call__(self, current: Tensor, u: Tensor, previous: Tensor, rate0: Tensor | None,
                 weights: tuple[float, float, float, float], rate: Tensor | None = None
                 ) -> Tensor:
        mu, nu, a, b = weights
        if self.fill is not None:  # the band's rows and the combination are the same
            current = self.fill(current)
        rows = len(u)
        values = (t.reshape(rows, -1).contiguous() for t in (current, u, previous))
        following = _native_gather.rkc_stage(
            self.packing.weighted, *values,
            None if rate0 is None else rate0.reshape(len(rate0), -1),
            (mu, nu, a * self.scale, b * self.scale),
            None if rate is None else rate.reshape(len(rate), -1))
        return following.reshape(u.shape)


class PackedBand:
    """``L`` and ``L^T`` on packed band values, and the ring's re-extension ``E``, on a
    :class:`PackedRegion` (its packing, nodes and ``W^-1 A``, shared with the heat flow's).

    Args:
        packing: the band and ring packed (a
            :class:`~torchsurf.flows.exponential.BandLaplacian`'s).
        ring: its ring's re-extension (:class:`~torchsurf.flows.exponential.RingFill`).
    """

    def __init__(self, packing: PackedRegion, ring: RingFill) -> None:
        self.packing = packing
        self.nodes, self.band_count, self.weighted = (packing.nodes, packing.band_count,
                                                      packing.weighted)
        self.pack, self.unpack = packing.pack, packing.unpack
        storage, lookup, count = packing.storage, packing.lookup, len(self.nodes)
        self.weighted_transposed = self.weighted.transposed()
        self.first = _first_pass(ring, storage, lookup, self.band_count, count - self.band_count)
        self.first_transposed = self.first.transposed()
        self.sweeps = ring.sweeps if ring.chained is not None else 0
        if self.sweeps:
            self.chained_rows, self.chained = _stencil_rows(ring.chained, storage, lookup, count)
            self.chained_transposed = self.chained.transposed()

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
        image = self.packing.weighted_apply(self.fill(x).reshape(-1, x.shape[1] * x.shape[2]))
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
        refuse_batched_backward("the packed band's ring fill", grad_output)
        return None, ctx.packed.fill_transpose(grad_output)


class PackedStencil:
    """A limited closest-point stencil on packed region values ``(nodes, C, K)``: each target
    node takes the tricubic interpolant at its closest point, clamped to the limiter's bounds
    (:mod:`._limiter`); other nodes keep their values. The numbers of
    :class:`~torchsurf.flows.extension.CubicStencil` (``limited=True``) to rounding.

    Args:
        stencil: the stencil on the surface's storage, reading only the band and ring.
        storage, lookup, count: the packing's (:class:`PackedRegion`).
    """

    def __init__(self, stencil: Stencil, storage: _Storage, lookup: Tensor, count: int) -> None:
        target, tap, weight = _stencil_entries(stencil, storage, lookup)
        if bool((tap < 0).any()):
            raise RuntimeError("a closest-point stencil reads a node off the band and ring")
        nodes = len(target) // 64
        self.rows = target.view(nodes, 64)[:, 0].long()
        self.matrix = GatherMatrix.of_rows(tap.view(nodes, 64), weight.view(nodes, 64), count)
        self.taps = self.matrix.columns.view(nodes, 64)  # the same indices: one copy kept
        self.corners = _limiter.corner_weights_of_taps(weight.view(nodes, 64))
        self._separable = _native_gather.SeparableStencil(self.taps, _stencil_axes(stencil),
                                                          self.corners, self.rows)

    def separable(self) -> _native_gather.SeparableStencil:
        """The stencil laid out for the one-pass kernels (its layouts formed at their first
        use)."""
        return self._separable

    def apply(self, z: Tensor) -> Tensor:
        """``z`` ``(nodes, C, K)`` with the targets re-extended; a new tensor (autograd reaches
        ``z``)."""
        if len(self.rows) == 0:
            return z.clone()
        flat = z.reshape(z.shape[0], -1)
        corners = self.corners.to(z.dtype)
        # the kernel takes a few float32 columns at a time (MAX_COLUMNS): more columns (a
        # batch of 17 or more) go through it in groups; the gather below had held 64 values a
        # row and column at once, 30 times the field (0.2 s -> 2.2 s at 48^3 from 16 to 17)
        width = min(flat.shape[1], _native_gather.MAX_COLUMNS.get(flat.dtype, flat.shape[1]))
        groups = [_native_gather.limited(flat[:, start: start + width], self.matrix, self.taps,
                                         corners, self.rows, self.separable)
                  for start in range(0, flat.shape[1], max(width, 1))]
        if groups and all(group is not None for group in groups):
            return torch.cat(groups, dim=1).reshape(z.shape)
        value = self.matrix.apply(flat)  # (R, F)
        clamped = []
        for start in range(0, len(self.rows), GATHER_ROWS):  # the clamp's bounds, in chunks
            part = slice(start, start + GATHER_ROWS)
            taps = self.taps[part]
            gathered = flat.index_select(0, taps.reshape(-1).long()).view(len(taps), 64, -1)
            low, high = _limiter.corner_extremes(gathered.permute(2, 0, 1))  # (F, r, 8)
            clamped.append(_limiter.clamp(value[part].t(), low, high, corners[part]).t())
        return flat.index_copy(0, self.rows, torch.cat(clamped)).reshape(z.shape)


class _Storage:
    """Where a surface stores its nodes: flat positions in ``(entries, D, H, W)`` for a dense
    surface, in the packed ``(N, 8, 8, 8)`` for bricks; their grid coordinates and
    neighbours."""

    def __init__(self, surface: ImplicitSurface, band: Tensor) -> None:
        self.layout = surface.layout
        self.volume_shape = tuple(band.shape[-3:])
        if self.layout is not None:
            self.index = self.layout.node_index().transpose(0, 1).reshape(3, -1)
            device = band.device
            self.brick_neighbours = self.layout.neighbours.to(device)
            self.brick_present = self.layout.present.to(device)
            self.inside = self.layout.inside.reshape(-1).to(device)

    def coordinates(self, positions: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Entry and grid ``(z, y, x)`` of ``positions``."""
        if self.layout is None:
            depth, height, width = self.volume_shape
            x, y = positions % width, (positions // width) % height
            z = (positions // (width * height)) % depth
            return positions // (width * height * depth), z, y, x
        z, y, x = self.index[:, positions]
        return self.layout.batch[positions // BRICK_NODES], z, y, x

    def neighbourhood(self, positions: Tensor) -> Tensor:
        """``(R, 27)``: :meth:`neighbour` of ``positions`` ``(R,)`` at each offset of
        :data:`~torchsurf.stencils.NEIGHBOURHOOD`; on a dense surface whose nodes ``positions``
        are all off the box's faces, each a fixed flat offset away."""
        if self.layout is not None:
            return self._brick_neighbours(positions, NEIGHBOURHOOD)
        _, *at = self.coordinates(positions)
        box = BoxNeighbours(at, self.volume_shape)
        if not box.on_faces:
            deltas = torch.tensor([box.delta(offset) for offset in NEIGHBOURHOOD],
                                  dtype=positions.dtype, device=positions.device)
            return positions[:, None] + deltas
        return torch.stack([self.neighbour(positions, offset) for offset in NEIGHBOURHOOD], 1)

    def neighbour(self, positions: Tensor, offset: tuple[int, int, int]) -> Tensor:
        """The positions of the nodes ``offset`` ``(dz, dy, dx)`` away, -1 beyond an entry's
        box or in a brick that is not stored."""
        if self.layout is not None:
            return self._brick_neighbours(positions, [offset])[:, 0]
        entry, *at = self.coordinates(positions)
        moved = [a + o for a, o in zip(at, offset, strict=True)]
        shape = self.volume_shape
        inside = torch.ones_like(positions, dtype=torch.bool)
        for m, n in zip(moved, shape, strict=True):
            inside &= (m >= 0) & (m < n)
        z, y, x = (m.clamp(0, n - 1) for m, n in zip(moved, shape, strict=True))
        found = ((entry * shape[0] + z) * shape[1] + y) * shape[2] + x
        return torch.where(inside, found, -1)

    def _brick_neighbours(self, positions: Tensor, offsets: Sequence[tuple[int, int, int]]
                          ) -> Tensor:
        """``(R, K)`` packed positions ``offsets`` (each within one node along every axis) from
        ``positions`` ``(R,)``, -1 in a brick that is not stored or beyond the entry's box:
        the brick's neighbour in the layout's table and the local index there, both read from
        :func:`_local_moves` by the node's local index."""
        which, local = _local_moves(offsets, positions.device)  # (512, K) each
        brick, at = positions // BRICK_NODES, positions % BRICK_NODES
        towards = which[at]
        found = self.brick_neighbours[brick].gather(1, towards) * BRICK_NODES + local[at]
        readable = self.brick_present[brick].gather(1, towards) & self.inside[found]
        return torch.where(readable, found, -1)


def _local_moves(offsets: Sequence[tuple[int, int, int]], device: torch.device
                 ) -> tuple[Tensor, Tensor]:
    """For each local index of a brick's nodes and each of ``offsets`` ``(dz, dy, dx)`` (each
    within one node), the brick it moves into (the column of the layout's neighbour table,
    :data:`torchsurf.bricks.layout.OFFSETS`) and the local index there: ``(512, K)`` int64
    each."""
    if any(abs(step) > 1 for offset in offsets for step in offset):
        raise ValueError(f"offsets must each lie within one node along every axis, got "
                         f"{[tuple(o) for o in offsets]}")
    moves = torch.tensor(offsets, dtype=torch.long, device=device)  # (K, 3)
    local = torch.arange(BRICK_NODES, device=device)
    at = torch.stack([local // (BRICK * BRICK), (local // BRICK) % BRICK, local % BRICK], 1)
    moved = at[:, None, :] + moves  # (512, K, 3), each in [-1, BRICK]
    carry = torch.div(moved, BRICK, rounding_mode="floor") + 1  # 0, 1, 2 along each axis
    wrapped = moved % BRICK
    return ((carry[..., 0] * 3 + carry[..., 1]) * 3 + carry[..., 2],
            (wrapped[..., 0] * BRICK + wrapped[..., 1]) * BRICK + wrapped[..., 2])


def _formed_rows(surface: ImplicitSurface, scheme: str, storage: _Storage, rows: Tensor,
                 lookup: Tensor, count: int, band_count: int) -> tuple[GatherMatrix, float]:
    """``W^-1 A`` on the band's rows, formed at the rows in closed form
    (:func:`torchsurf.operators.spectrum.laplace_beltrami_rows`, dense or bricks) instead of
    probed over the volume (at 200^3, the octant scheme's 27 eager volume passes took 12 of a
    flow's first 24 s; on a 64^3 bunny's bricks the probes took 0.3 of 0.7 s of setup), and its
    Gershgorin bound on the band (its first ``band_count`` columns), the same float
    :func:`~torchsurf.operators.spectrum.laplace_beltrami_bound` gives. The entries come row
    after row, so the matrix takes them without sorting."""
    row_parts, column_parts, value_parts = [], [], []
    largest = 0.0
    with torch.no_grad():
        for start in range(0, max(len(rows), 1), ROWS_AT_ONCE):  # one (empty) part for none
            part = rows[start: start + ROWS_AT_ONCE]
            coefficients = laplace_beltrami_rows(surface, part, scheme)
            neighbours = storage.neighbourhood(part)
            columns = torch.where(neighbours >= 0, lookup[neighbours.clamp(min=0)], -1)
            evolving = (columns >= 0) & (columns < band_count)
            sums = gershgorin_sums(coefficients, evolving.unbind(1))
            largest = max(largest, float(sums.max()) if len(sums) else 0.0)
            kept = columns >= 0
            take = torch.arange(start, start + len(part), device=rows.device)
            row_parts.append(take[:, None].expand_as(kept)[kept])
            column_parts.append(columns[kept])
            value_parts.append(coefficients[kept])
    matrix = GatherMatrix(torch.cat(row_parts), torch.cat(column_parts), torch.cat(value_parts),
                          (len(rows), count))
    return matrix, largest


def _stencil_entries(stencil: Stencil, storage: _Storage, lookup: Tensor
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """A closest-point stencil's ``(target, tap, weight)`` as region positions ``(n * 64,)``
    each (taps off the region at -1)."""
    parts = []
    if isinstance(stencil, CubicStencil):
        size = math.prod(storage.volume_shape)
        for entry, (target, corners, weight) in enumerate(stencil.parts):
            sources = _dense_tap_indices(corners, *storage.volume_shape[1:])(slice(None))
            parts.append((target + entry * size, sources + entry * size, weight))
    else:
        for start in range(0, len(stencil.targets), STENCIL_CHUNK):
            part = slice(start, start + STENCIL_CHUNK)
            parts.append((stencil.targets[part], stencil._tap_indices(part),
                          stencil.weights[:, part]))
    empty = stencil.parts[0][2] if isinstance(stencil, CubicStencil) else stencil.weights
    targets, taps, weights = [lookup[:0]], [lookup[:0]], [empty.new_zeros(0)]
    for target, sources, weight in parts:
        targets.append(lookup[target][:, None].expand(-1, 64).reshape(-1))
        taps.append(torch.where(sources >= 0, lookup[sources.clamp(min=0)], -1).reshape(-1))
        weights.append(tap_weights(weight).reshape(-1))
    return torch.cat(targets), torch.cat(taps), torch.cat(weights)


def _stencil_axes(stencil: Stencil) -> Tensor:
    """A closest-point stencil's separable weights ``(3, n, 4)`` (x, y, z), its nodes in the
    order of :func:`_stencil_entries`."""
    if isinstance(stencil, CubicStencil):
        return torch.cat([weight for _, _, weight in stencil.parts], dim=1)
    return stencil.weights


def _first_pass(ring: RingFill, storage: _Storage, lookup: Tensor, band_count: int,
                ring_count: int) -> GatherMatrix:
    """The ring's first values from the band's: ``(ring nodes, band nodes)``. The closest-point
    taps on the band (those on the ring read zero in this pass); orphans take the mean of their
    3x3x3 band neighbours instead."""
    target, tap, weight = _stencil_entries(ring.first, storage, lookup)
    keep = (tap >= 0) & (tap < band_count)
    target, tap, weight = target[keep] - band_count, tap[keep], weight[keep]
    if ring.orphans is not None:
        orphans = ring.orphans.reshape(-1).nonzero().squeeze(1)
        rows = lookup[orphans] - band_count
        adopted = torch.zeros(ring_count, dtype=torch.bool, device=lookup.device)
        adopted[rows] = True
        keep = ~adopted[target]
        target, tap, weight = [target[keep]], [tap[keep]], [weight[keep]]
        share = 1.0 / ring.neighbours.reshape(-1)[orphans].to(weight[0].dtype)
        for dz in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    q = storage.neighbour(orphans, (dz, dy, dx))
                    column = torch.where(q >= 0, lookup[q.clamp(min=0)], -1)
                    take = (column >= 0) & (column < band_count)
                    target.append(rows[take])
                    tap.append(column[take])
                    weight.append(share[take])
        target, tap, weight = torch.cat(target), torch.cat(tap), torch.cat(weight)
    return GatherMatrix(target, tap, weight, (ring_count, band_count))


def _stencil_rows(stencil: Stencil, storage: _Storage, lookup: Tensor, count: int
                  ) -> tuple[Tensor, GatherMatrix]:
    """A stencil's target rows (region positions) and its weights ``(targets, region nodes)``."""
    target, tap, weight = _stencil_entries(stencil, storage, lookup)
    if bool((tap < 0).any()):
        raise RuntimeError("a ring sweep reads a node off the band and ring")
    rows, local = torch.unique(target.long(), return_inverse=True)
    return rows, GatherMatrix(local, tap, weight, (len(rows), count))
