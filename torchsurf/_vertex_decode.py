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


def weights(found: Cells, usable: Tensor, vertices: Tensor, references: list[Tensor],
            spacing: float) -> Tensor:
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
    """
    offsets_world = [(points - vertices[:, None]).permute(0, 2, 1) / spacing
                     for points in references]
    trilinear = found.trilinear
    constraints = torch.cat([torch.ones_like(trilinear)[:, None], *offsets_world], dim=1)
    constraints = constraints * usable[:, None]
    target = torch.zeros(constraints.shape[1], dtype=torch.float64)
    target[0] = 1.0
    start = trilinear * usable
    residual = target - (constraints @ start[..., None])[..., 0]
    normal = constraints @ constraints.transpose(1, 2)
    normal = normal + REGULARISATION * torch.eye(constraints.shape[1], dtype=torch.float64)
    correction = constraints.transpose(1, 2) @ torch.linalg.solve(normal, residual[..., None])
    return (start + correction[..., 0]) * usable
