"""Closest points of S for the re-extension stencils: the first-order step, refined where it misses.

The first-order closest point of a node is ``x - d n``, ``d`` the surface's
:meth:`~torchsurf.ImplicitSurface.signed_distance`. It lies on S when ``phi`` is a
distance and ``n`` its gradient; near a medial axis, a thin feature or a sharp edge the central-
difference normal is not the distance's gradient, and the point lands off S: up to 3 cells on a
33^3 torus and 4-10 cells on the shared meshes at 64^3-128^3, so that its 4^3 interpolation taps
reach nodes outside the band and its ring, where nothing is evolved (0.05-0.6% of the region's
nodes). :func:`refine` repeats the step from such a point,
``y <- y - d(y) n(y) / max(|n(y)|, NORMAL_FLOOR)`` with ``d`` that distance and ``n`` read
trilinearly, while ``|d(y)|`` exceeds :data:`REFINE_TOLERANCE` cells (a growing fraction of
the step from half of it), at most :data:`REFINE_STEPS` times: on those meshes and tori every
point then reads the region only, except where ``phi`` is not a distance at all (an open
mesh's sign flips), which the stencils leave out (:func:`taps_inside`). Points within half the
tolerance are not touched, so a surface whose first-order points are good keeps its numbers
exactly.

Dense volumes and bricks read through the same arithmetic (:func:`trilinear` with a node
lookup), so that both give the same points to the last bit.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..bricks.layout import BRICK
from ..surface import ImplicitSurface

REFINE_TOLERANCE = 0.5
"""A closest point farther than this from S (cells, ``|d|`` read trilinearly) is refined by
full steps; between half of it and it, by a fraction of a step that grows from 0 to 1
(:func:`step_share`), so that the points are continuous in ``phi``: with all or nothing, a
point crossing the tolerance under a tiny change of ``phi`` moved by half a cell."""

REFINE_STEPS = 4
"""Most refinement steps (measured: 2-3 reach the tolerance on the shared meshes at 64^3-128^3)."""

NORMAL_FLOOR = 0.2
"""The interpolated normal is divided by ``max(|n|, NORMAL_FLOOR)``: across a medial axis the
normals of both sides average to a short vector, whose direction is then not trusted for a
full step."""

NodeLookup = Callable[[Tensor], tuple[Tensor, Tensor]]
"""``(M, 3)`` integer node indices ``(x, y, z)`` -> flat positions ``(M,)`` in the fields and
whether each node is stored ``(M,)`` bool."""

_CORNERS = [(corner & 1, (corner >> 1) & 1, corner >> 2) for corner in range(8)]


Reader = Callable[[Tensor, Tensor | None], tuple[Tensor, Tensor]]
"""``(at (m, 3), rows (m,) or None) -> (values (4, m), readable (m,))``: the signed distance in
cells (``d / h``) and the normal ``(x, y, z)`` at fractional node indices ``at`` of the
points ``rows`` (all when ``None``), and whether they could be read."""


def trilinear(fields: list[Tensor], at: Tensor, high: Tensor, lookup: NodeLookup
              ) -> tuple[Tensor, Tensor]:
    """Trilinear interpolation of flat ``fields`` at fractional node indices ``at``.

    Args:
        fields: tensors ``(C_k, K)`` of values at the flat node positions ``lookup`` gives.
        at: ``(M, 3)`` fractional ``(x, y, z)`` node indices.
        high: the last node index per axis, ``(3,)`` or ``(M, 3)``, in ``at``'s dtype.
        lookup: node indices to flat positions and whether they are stored.

    Returns:
        ``(sum C_k, M)`` interpolated values (zero where unreadable) and ``(M,)`` bool: the
        point's 8 cell nodes lie in the box and are stored.
    """
    low = torch.minimum(at.detach().floor(), high - 1)
    fraction = at - low
    low = low.long()
    values, readable = None, torch.ones(at.shape[0], dtype=torch.bool, device=at.device)
    for offset in _CORNERS:
        node = low + torch.tensor(offset, device=at.device)
        inside = ((node >= 0) & (node <= high)).all(dim=1)
        flat, stored = lookup(torch.minimum(node.clamp(min=0), high.long()).expand_as(node))
        readable &= inside & stored
        weight = torch.ones_like(fraction[:, 0])
        for axis, bit in enumerate(offset):
            weight = weight * (fraction[:, axis] if bit else 1 - fraction[:, axis])
        flat = torch.where(inside & stored, flat, 0)
        term = torch.cat([field[:, flat] for field in fields]) * weight
        values = term if values is None else values + term
    return torch.where(readable, values, 0.0), readable


DIRECTED = 0.25
"""A node's normal points to S where ``|n|^2`` reaches this (:func:`has_direction`)."""

FULLY_DIRECTED = 0.999
"""... and counts fully in :func:`refine`'s reads from this ``|n|^2`` on (:func:`faded_normal`);
a unit normal's rounding stays above it."""


def has_direction(surface: ImplicitSurface) -> Tensor:
    """Where the surface's normal points to S: bool, like ``surface.grad_norm`` (dense
    ``(B, 1, D, H, W)`` or packed ``(N, 1, 8, 8, 8)``). Elsewhere the normal is short
    (:data:`torchsurf.surface.DIRECTION_FLOOR`: the central differences of ``phi`` cancel) and
    every point of S as near: the node has no closest point (following the normal, :func:`refine`
    would pick one that jumps with any change of ``phi``), and stencils leave it out."""
    return (surface.normal.detach() ** 2).sum(dim=1, keepdim=True) >= DIRECTED


def faded_normal(normal: Tensor, dim: int) -> Tensor:
    """The normal as :func:`refine` reads it: 0 where the node has no direction
    (:func:`has_direction`), the normal itself where ``|n|^2 >= FULLY_DIRECTED`` (every node
    whose ``|grad phi|`` is above the direction floor, bit for bit), linear in ``|n|^2`` between.

    The short normal of a node without direction is ``grad phi / floor``: read into the
    interpolated normals of nearby points, its derivative in ``phi`` (``1 / floor``) moved
    their refined closest points by thousands of cells per unit of ``phi`` (a heat flow's
    largest derivative in ``phi`` was 2.6e5 on a torus whose centre is a node, 3.9e3 faded).

    Args:
        normal: normals with their 3 components along ``dim``.
    """
    squared = (normal ** 2).sum(dim=dim, keepdim=True)
    return normal * ((squared - DIRECTED) / (FULLY_DIRECTED - DIRECTED)).clamp(0, 1)


def step_share(distance: Tensor) -> Tensor:
    """The fraction of a refinement step taken at distance ``distance`` (cells): 0 within
    half of :data:`REFINE_TOLERANCE`, 1 beyond it, linear between."""
    start = REFINE_TOLERANCE / 2
    return ((distance.abs() - start) / (REFINE_TOLERANCE - start)).clamp(0, 1)


def refine(at: Tensor, read: Reader) -> Tensor:
    """First-order closest points ``at`` ``(M, 3)`` (fractional node indices), refined.

    Args:
        at: ``(M, 3)`` fractional ``(x, y, z)`` node indices of the first-order points.
        read: the fields at given points (:data:`Reader`).

    Returns:
        ``(M, 3)``: ``at`` where it was within half of :data:`REFINE_TOLERANCE` of S (or
        unreadable), the refined points elsewhere; in ``at``'s graph and ``read``'s.
    """
    values, readable = read(at, None)
    far = (readable & (step_share(values[0]) > 0)).nonzero().squeeze(1)
    if len(far) == 0:
        return at
    moving = at[far]
    for _ in range(REFINE_STEPS):
        values, readable = read(moving, far)
        distance, normal = values[0], values[1:].T
        length = normal.norm(dim=1, keepdim=True).clamp(min=NORMAL_FLOOR)
        share = torch.where(readable, step_share(distance), 0.0)[:, None]
        moving = moving - share * distance[:, None] * normal / length
    return at.index_copy(0, far, moving)


def dense_reader(distance: Tensor, normal: Tensor) -> Reader:
    """:func:`refine`'s ``read`` on one dense volume.

    Args:
        distance: ``(D, H, W)`` signed distance in cells, ``signed_distance() / h``.
        normal: ``(3, D, H, W)`` the surface's normals, channels ``x, y, z`` (read faded,
            :func:`faded_normal`).
    """
    depth, height, width = distance.shape
    high = torch.tensor([width - 1, height - 1, depth - 1], dtype=distance.dtype,
                        device=distance.device)
    fields = [distance.reshape(1, -1), faded_normal(normal, 0).reshape(3, -1)]

    def lookup(node: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = node.unbind(1)
        return (z * height + y) * width + x, torch.ones_like(x, dtype=torch.bool)

    return lambda at, rows: trilinear(fields, at, high, lookup)


def brick_fields(distance: Tensor, normal: Tensor) -> list[Tensor]:
    """What :func:`brick_reader` reads, formed once for every chunk of points: the packed
    distance ``(1, K)`` and faded normal ``(3, K)`` (at 512^3, forming them for each chunk of a
    stencil took 4 s of a flow's first call).

    Args:
        distance: ``(N, 1, 8, 8, 8)`` signed distance in cells, ``signed_distance() / h``.
        normal: ``(N, 3, 8, 8, 8)`` the surface's normals (read faded, :func:`faded_normal`).
    """
    return [distance.transpose(0, 1).reshape(1, -1),
            faded_normal(normal, 1).transpose(0, 1).reshape(3, -1)]


def brick_reader(fields: list[Tensor], lookup_table: Tensor, batch: Tensor,
                 shapes: Tensor) -> Reader:
    """:func:`refine`'s ``read`` on packed fields of a brick layout.

    Args:
        fields: :func:`brick_fields` of the surface.
        lookup_table: ``(B, Z, Y, X)`` the packed row of each brick, ``-1`` if not stored.
        batch: ``(M,)`` each point's batch entry.
        shapes: ``(M, 3)`` each point's entry's grid shape ``(W, H, D)``.
    """
    brick = BRICK
    last = (shapes - 1).to(fields[0].dtype)

    def read(at: Tensor, rows: Tensor | None) -> tuple[Tensor, Tensor]:
        entry = batch if rows is None else batch[rows]
        high = last if rows is None else last[rows]

        def lookup(node: Tensor) -> tuple[Tensor, Tensor]:
            x, y, z = node.unbind(1)
            row = lookup_table[entry, z // brick, y // brick, x // brick]
            local = ((z % brick) * brick + y % brick) * brick + x % brick
            return row.clamp(min=0) * brick**3 + local, row >= 0

        return trilinear(fields, at, high, lookup)

    return read


def taps_inside(readable: Tensor, tap_indices: Callable[[slice], Tensor], count: int,
                chunk: int = 2**16) -> Tensor:
    """Which of ``count`` nodes read only nodes of ``readable``.

    Args:
        readable: flat bool ``(K,)``, the nodes that may be read.
        tap_indices: a slice of the nodes -> their flat tap positions ``(n, T)``, negative for
            a tap that is not stored.
        count: the number of nodes.
        chunk: nodes checked at once.

    Returns:
        ``(count,)`` bool.
    """
    keep = torch.ones(count, dtype=torch.bool, device=readable.device)
    for start in range(0, count, chunk):
        part = slice(start, start + chunk)
        taps = tap_indices(part)
        keep[part] = ((taps >= 0) & readable[taps.clamp(min=0)]).all(dim=1)
    return keep
