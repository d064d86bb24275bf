"""The packed band's ``W^-1 A`` read off the volume operator by colour probes: the plain
reference that the rows formed in closed form (``_packed_band._formed_rows``) are tested
against.

The weighted operator applied to indicator volumes of the region's nodes of each of
``(2 r + 1)^3`` colours (``r`` the scheme's reach), no two nodes of a colour within ``2 r`` of
each other, gives each band node's coefficient for each of its neighbours.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchsurf.flows._gather_matrix import GatherMatrix
from torchsurf.flows._packed_band import BRICK_NODES, _Storage
from torchsurf.operators import functional
from torchsurf.surface import ImplicitSurface

PROBE_VALUES = 2**22
"""Most values of the indicators run at once (16 MB in float32, and as much for each of the
operator's temporaries: with glibc's default allocator, larger blocks are returned to the system
when freed and faulted in again, 4.2 against 3.1 s for four 64^3 entries)."""

PROBES_AT_ONCE = 27
"""Most colour indicators run through the volume operator in one call."""

REACH = {"octant": 1, "symmetric": 1, "conservative": 1}
"""How many nodes along each axis a scheme's weighted operator ``A`` couples on each side: 19
(octant) and 13 (flux forms) of the 27 nodes of a 3x3x3 block (the flux forms' kernels pad by
two nodes, but ``A``'s coefficients reach one; tests/flows/test_packed_band.py measures it)."""


def probe_reader(surface: ImplicitSurface, scheme: str, region: Tensor, storage: _Storage,
                  rows: Tensor):  # noqa: ANN202
    """``(colours) -> read``: the weighted operator applied to the indicators of the region's
    nodes of each of ``colours``, and ``read(take, which)`` its values at ``rows[take]`` for
    colour ``which``. A dense surface is probed on the box around its region, with a margin of
    more than the stencil's reach (its rows see the geometry and box faces the whole volume
    does); bricks are probed whole."""
    reach = REACH[scheme]
    side = 2 * reach + 1
    if storage.layout is not None:
        if side != 3:
            raise NotImplementedError(f"bricks are probed with 3 colours a axis, not {side}")
        colour = storage.layout.colours().long()
        brick, node = rows // BRICK_NODES, rows % BRICK_NODES
        haloed, pad = surface.haloed(), storage.layout.halo

        def bricks(colours: Tensor):  # noqa: ANN202
            probes = (region & (colour == colours.view(1, -1, 1, 1, 1))).to(surface.phi.dtype)
            # once per surface, never compiled: the octant's "auto" on bricks is the C kernel
            response = functional.divergence_form(
                probes, surface.normal, surface.weight, surface.spacing, scheme,
                "auto" if scheme == "octant" else "slicing", weighted=True, haloed=haloed,
                pad=pad)
            response = response.reshape(len(probes), len(colours), -1)
            return lambda take, which: response[brick[take], which, node[take]]

        return bricks, len(region) * BRICK_NODES
    shape = storage.volume_shape
    occupied = [region[:, 0].any(dim=tuple(d for d in range(4) if d != axis)).nonzero()
                .squeeze(1) for axis in (1, 2, 3)]
    crop = [slice(max(0, int(o[0]) - reach - 2), min(n, int(o[-1]) + reach + 3))
            for o, n in zip(occupied, shape, strict=True)]
    cropped = tuple(c.stop - c.start for c in crop)
    normal, weight = (field[(..., *crop)] for field in (surface.normal, surface.weight))
    grids = torch.meshgrid(*(torch.arange(c.start, c.stop, device=rows.device) % side
                             for c in crop), indexing="ij")
    colour = (grids[0] * side + grids[1]) * side + grids[2]
    inside = region[(slice(None), slice(None), *crop)]
    entry, z, y, x = storage.coordinates(rows)
    node = (((z - crop[0].start) * cropped[1] + y - crop[1].start) * cropped[2]
            + x - crop[2].start)

    def dense(colours: Tensor):  # noqa: ANN202
        probes = (inside & (colour == colours.view(1, -1, 1, 1, 1))).to(surface.phi.dtype)
        response = functional.divergence_form(
            probes, normal, weight, surface.spacing, scheme, "slicing", weighted=True,
        ).reshape(len(probes), len(colours), -1)
        return lambda take, which: response[entry[take], which, node[take]]

    return dense, len(region) * math.prod(cropped)




def probed_by_colours(surface: ImplicitSurface, scheme: str, region: Tensor,
                       storage: _Storage, rows: Tensor, lookup: Tensor, count: int
                       ) -> GatherMatrix:
    """``W^-1 A`` on the band's rows (positions ``rows``) and the region's columns, read
    off the volume operator applied to colour indicators."""
    reach = REACH[scheme]
    side = 2 * reach + 1
    probe, cells = probe_reader(surface, scheme, region, storage, rows)
    weight = surface.weight
    inverse_weight = 1.0 / weight.expand(len(region), *weight.shape[1:]).reshape(-1)[rows]
    _, z, y, x = storage.coordinates(rows)
    at_once = max(1, min(PROBES_AT_ONCE, PROBE_VALUES // cells))
    offsets = [(dz, dy, dx) for dz in range(-reach, reach + 1) for dy in range(-reach, reach + 1)
               for dx in range(-reach, reach + 1)]
    neighbours = [storage.neighbour(rows, offset) for offset in offsets]
    columns = [torch.where(q >= 0, lookup[q.clamp(min=0)], -1) for q in neighbours]
    colours = [(((z + dz) % side) * side + (y + dy) % side) * side + (x + dx) % side
               for dz, dy, dx in offsets]
    entries: list[tuple[Tensor, Tensor, Tensor]] = []
    with torch.no_grad():
        for first in range(0, side**3, at_once):
            chunk = torch.arange(first, min(first + at_once, side**3), device=rows.device)
            read = probe(chunk)
            for column, colour in zip(columns, colours, strict=True):
                which = colour - first
                take = ((column >= 0) & (which >= 0) & (which < len(chunk))).nonzero().squeeze(1)
                entries.append((take, column[take],
                                read(take, which[take]) * inverse_weight[take]))
    return GatherMatrix(*(torch.cat(part) for part in zip(*entries, strict=True)),
                        (len(rows), count))
