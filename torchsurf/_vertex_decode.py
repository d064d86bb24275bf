"""Decoding weights at mesh vertices (``MeshAdapter(order=2)``), for any storage of the band.

Around each vertex, the ``4^3`` nodes of the cells next to it carry the trilinear weights of the
vertex (on the inner ``2^3``, zero on the outer ring), corrected by least change so that the
weights sum to 1 and reproduce the vertex from the closest points the band nodes stand for
(:class:`torchsurf.mesh.MeshAdapter` says why). The dense adapter and the bricks' one
(:class:`torchsurf.bricks.BrickMeshAdapter`) differ only in where a node's value is stored.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .grid import Grid

REGULARISATION = 1e-3
"""Tikhonov term of the decoding solve, in units of cells^2: where the closest points around a
vertex are (nearly) coplanar, their normal constraint is dropped instead of amplified."""


@dataclass(frozen=True)
class Cells:
    """The ``4^3`` nodes around each of ``V`` vertices, taps in ``(z, y, x)`` order.

    Attributes:
        nodes: ``(x, y, z)``, each ``(V, 4)`` int64 node indices along that axis, clamped to
            the box.
        inside: ``(V, 64)`` bool, the tap's node lies in the box (before clamping).
        trilinear: ``(V, 64)`` float64 trilinear weights of the vertex (0 on the outer ring).
    """

    nodes: tuple[Tensor, Tensor, Tensor]
    inside: Tensor
    trilinear: Tensor


def _combine(x: Tensor, y: Tensor, z: Tensor, op) -> Tensor:  # noqa: ANN001
    return op(op(z[:, :, None, None], y[:, None, :, None]), x[:, None, None, :]).flatten(1)


def cells(grid: Grid, vertices: Tensor) -> Cells:
    """The :class:`Cells` of float64 world ``vertices`` ``(V, 3)`` on ``grid``."""
    depth, height, width = grid.shape
    offsets = torch.arange(-1, 3)
    position = grid.world_to_index(vertices)
    base = position.floor()
    fraction = position - base
    nodes, valid, linear = [], [], []
    for axis, size in enumerate((width, height, depth)):
        raw = base[:, axis:axis + 1].long() + offsets
        nodes.append(raw.clamp(0, size - 1))
        valid.append((raw >= 0) & (raw < size))
        t = fraction[:, axis:axis + 1]
        linear.append(torch.where(offsets == 0, 1 - t, torch.where(offsets == 1, t, 0.0)))
    return Cells(tuple(nodes), _combine(*valid, op=torch.logical_and),
                 _combine(*linear, op=torch.mul))


HAT_EMPHASIS = 30.0
"""Scale of the hat-function rows against the regularisation: they hold to about
``REGULARISATION / HAT_EMPHASIS^2`` of their residual (measured round trip 4e-6, against 1e-3
unscaled)."""

HAT_LIMIT = 16
"""Most hat functions a vertex's weights reproduce. A vertex whose taps read more reproduces
its reference points (affine functions) and, among the hats, only those of the vertices read
farther than :data:`FAR_CELLS` from it, at most ``HAT_LIMIT`` of them."""

FAR_CELLS = 4.5
"""Distance from a vertex, in cells, beyond which a vertex its taps read is reached only through
a long facet: the taps lie within ``2 sqrt 3`` cells of it, a facet's far corner a cell or more
beyond. Where its taps read many vertices, the near ones sit on small facets, where a
piecewise-linear function is its affine part to second order, but the data bends at a long
facet's far corner, which affine functions do not follow. Reproducing those far hats decodes
trimesh's capsule (its side one strip of triangles 22 cells long at 32^3) to 2.8e-2 / 9.8e-3 /
5.8e-3 of the range at 32^3 / 48^3 / 64^3, against 8.8e-2 / 4.7e-2 / 1.0e-2 with affine
reproduction alone; at 3 cells icosphere(5)'s small facets took them too, and its worst vertex
at 32^3 rose from 4.3e-3 to 5.8e-3."""


HAT_AMPLIFICATION = 4.0
"""Largest ``sum |w|`` of a vertex's hat-reproducing weights: above it the vertex takes the
weights that reproduce its reference points only. Where the closest points of its taps are
(nearly) coplanar and read many small facets (the fandisk's and the teapot's flat parts at
64^3), reproducing every hat function took ``sum |w|`` up to 47-59, and a volume of uniform
noise in [0, 1] decoded to [-0.53, 1.28]."""


@dataclass(frozen=True)
class Hats:
    """The mesh closest point of each tap's node, as a triangle: what the hat functions need.

    Attributes:
        corners: ``(V, 64, 3)`` int64 vertex indices of the triangle (anything where the tap is
            not usable), numbered as ``own``.
        barycentric: ``(V, 64, 3)`` float64 barycentric weights of the closest point.
        own: ``(V,)`` int64 index of each vertex, in the same numbering.
        positions: ``(M, 3)`` float64 world positions of the vertices, in the same numbering.
    """

    corners: Tensor
    barycentric: Tensor
    own: Tensor
    positions: Tensor


UNREAD_WEIGHT = 1e-12
"""Barycentric weights at or below this count as 0: the corner is not read."""


def _hat_constraints(usable: Tensor, hats: Hats, spacing: float
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """The hat functions read by each vertex's 64 taps, as constraint rows.

    Returns ``values`` ``(V, L, 64)``: ``hat_j(c_n)`` for the (at most ``L`` = :data:`HAT_LIMIT`)
    vertices ``j`` read, one slot each; ``target`` ``(V, L)``: 1 in the vertex's own slot; and
    ``covered`` ``(V,)`` bool: every vertex read has a slot, the vertex itself among them. A
    vertex not covered has the slots of the vertices read beyond :data:`FAR_CELLS` (target 0)
    and keeps its reference points; the rest of its slots hold 0.
    """
    count, taps = usable.shape
    own = hats.own[:, None, None]
    # a corner of weight 0 (the closest point on the triangle's far edge) is not read: which
    # of the two triangles at an edge libigl returns is a tie that rounding breaks, so that
    # counting it changed the vertices read, and the weights, with the mesh's scale
    read = usable[..., None] & (hats.barycentric > UNREAD_WEIGHT)
    ids = torch.where(read, hats.corners, own).flatten(1)  # (V, 64 * 3)
    weights = (hats.barycentric * usable[..., None]).flatten(1)
    ordered, order = ids.sort(dim=1)
    first = torch.ones_like(ordered, dtype=torch.bool)
    first[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
    slot = torch.empty_like(order).scatter_(1, order, first.cumsum(1) - 1)
    mine = torch.where(ids == own[:, :, 0], slot, -1).amax(1)
    covered = (first.sum(1) <= HAT_LIMIT) & (mine >= 0)
    distance = (hats.positions[ids] - hats.positions[hats.own][:, None]).norm(dim=2)
    far = distance > FAR_CELLS * spacing
    far_first = first & far.gather(1, order)
    far_slot = torch.empty_like(order).scatter_(1, order, far_first.cumsum(1) - 1)
    slot = torch.where(covered[:, None], slot, torch.where(far, far_slot, HAT_LIMIT))
    keep = slot < HAT_LIMIT
    tap = torch.arange(taps).repeat_interleave(3)[None].expand(count, -1)
    values = torch.zeros(count, HAT_LIMIT * taps, dtype=torch.float64)
    values.scatter_add_(1, torch.where(keep, slot * taps + tap, 0),
                        torch.where(keep, weights, 0.0).to(torch.float64))
    target = torch.zeros(count, HAT_LIMIT, dtype=torch.float64)
    target[covered, mine[covered]] = 1.0
    return values.reshape(count, HAT_LIMIT, taps), target, covered


DECODE_CHUNK = 2048
"""Vertices whose weights are solved at once: each holds ``(1 + 3 sets + HAT_LIMIT) x 64``
float64 constraints and their products (about 50 kB a vertex at a time; all of bunny_closed's
35k vertices at once peaked 1.8 GB above the adapter's other memory, whatever the grid)."""


def weights(found: Cells, usable: Tensor, vertices: Tensor, references: list[Tensor],
            spacing: float, hats: Hats | None = None) -> Tensor:
    """Decoding weights ``(V, 64)``, float64: the trilinear weights plus the least change
    (Tikhonov-regularised) that makes them sum to 1 and reproduce the vertex from each set of
    reference points; 0 on taps that are not ``usable``.

    Args:
        found: the vertices' :class:`Cells`.
        usable: ``(V, 64)`` bool, the tap's node is in the box and holds data.
        vertices: ``(V, 3)`` float64 world.
        references: per set, ``(V, 64, 3)`` float64 world points at the taps' nodes (anything
            where not ``usable``) that the weights must reproduce (``sum_n w_n p_n = v``).
        spacing: the grid's spacing, world units.
        hats: the taps' mesh closest points as triangles. At a vertex whose taps read at most
            :data:`HAT_LIMIT` vertices, the weights reproduce each of their hat functions
            (``sum_n w_n hat_j(c_n) = [j = i]``) in place of the first reference set (the mesh
            closest points, which the hats reproduce): the decode of every piecewise-linear
            function of the mesh, what the adapters' ``encode`` writes, is then exact there.
            Where those weights' ``sum |w|`` exceeds :data:`HAT_AMPLIFICATION`, the vertex
            keeps the weights of the reference sets alone.

    The weights sum to 1 to rounding at every vertex with a usable tap (constants decode
    exactly). Solved :data:`DECODE_CHUNK` vertices at a time.
    """
    if len(vertices) > DECODE_CHUNK:
        parts = []
        for start in range(0, len(vertices), DECODE_CHUNK):
            part = slice(start, start + DECODE_CHUNK)
            parts.append(weights(
                Cells(tuple(n[part] for n in found.nodes), found.inside[part],
                      found.trilinear[part]),
                usable[part], vertices[part], [points[part] for points in references], spacing,
                None if hats is None else Hats(hats.corners[part], hats.barycentric[part],
                                               hats.own[part], hats.positions)))
        return torch.cat(parts)
    offsets_world = [(points - vertices[:, None]).permute(0, 2, 1) / spacing
                     for points in references]
    target = torch.zeros(len(vertices), 1 + 3 * len(references), dtype=torch.float64)
    target[:, 0] = 1.0
    plain = _least_change(found.trilinear, usable, offsets_world, target)
    if hats is None:
        return _summing_to_one(plain, found.trilinear, usable)
    hat_values, hat_target, covered = _hat_constraints(usable, hats, spacing)
    offsets_world[0] = offsets_world[0] * ~covered[:, None, None]
    offsets_world.append(HAT_EMPHASIS * hat_values)
    target = torch.cat([target, HAT_EMPHASIS * hat_target], dim=1)
    exact = _least_change(found.trilinear, usable, offsets_world, target)
    size = exact.abs().sum(dim=1, keepdim=True)
    amplified = (size > HAT_AMPLIFICATION) & (plain.abs().sum(dim=1, keepdim=True) < size)
    return _summing_to_one(torch.where(amplified, plain, exact), found.trilinear, usable)


def _summing_to_one(weights: Tensor, trilinear: Tensor, usable: Tensor) -> Tensor:
    """``weights`` ``(V, 64)`` shifted to sum to 1 exactly, by their shortfall spread like the
    usable trilinear weights (the regularised solve leaves up to ~5e-4 where its constraints
    conflict, and a constant would not decode exactly); a vertex without usable inner taps
    spreads it over its usable taps, one without any keeps zeros."""
    spread = trilinear * usable
    plain = usable.to(weights.dtype)
    spread = torch.where(spread.sum(dim=1, keepdim=True) > 0, spread, plain)
    total = spread.sum(dim=1, keepdim=True)
    shortfall = 1.0 - weights.sum(dim=1, keepdim=True)
    return weights + torch.where(total > 0, shortfall / total.clamp_min(1e-300), 0.0) * spread


def _least_change(trilinear: Tensor, usable: Tensor, offsets_world: list[Tensor],
                  target: Tensor) -> Tensor:
    """``trilinear`` ``(V, 64)`` plus the least (regularised) change that meets
    ``[1, offsets...] w = target``; 0 on taps that are not ``usable``."""
    constraints = torch.cat([torch.ones_like(trilinear)[:, None], *offsets_world], dim=1)
    constraints = constraints * usable[:, None]
    start = trilinear * usable
    residual = target - (constraints @ start[..., None])[..., 0]
    normal = constraints @ constraints.transpose(1, 2)
    normal = normal + REGULARISATION * torch.eye(constraints.shape[1], dtype=torch.float64)
    correction = constraints.transpose(1, 2) @ torch.linalg.solve(normal, residual[..., None])
    return (start + correction[..., 0]) * usable


def onto_weighted_taps(index: Tensor, weights: Tensor) -> Tensor:
    """``index`` ``(V, 64)`` with every tap of weight 0 moved onto its vertex's heaviest tap.

    A tap of weight 0 (a node beyond the band, outside the box, or of a brick not stored) adds
    ``0 * value``, which is NaN where the value is NaN or infinite: a volume that marks the
    nodes beyond its band so would decode to NaN at vertices that never read them. Moved onto
    a node the vertex reads anyway, the tap adds an exact 0 at no cost per decode.
    """
    heaviest = index.gather(1, weights.abs().argmax(dim=1, keepdim=True))
    return torch.where(weights != 0, index, heaviest)

