"""The flux-form core shared by every divergence-form intrinsic operator.

``L u = (1/W) D- . (W f(P D+ u))`` (the paper's Appendix B, ``scheme="conservative"``), the
mean of that and its mirror ``(1/W) D+ . (W f(P D- u))`` (``scheme="symmetric"``), or the mean
of all eight compositions that pick the side per axis (``"octant"``), for a flux map ``f``
acting on the projected one-sided gradient: the identity for Laplace–Beltrami, ``g(|v|) v`` for
edge-stopping diffusion, ``(T . v) T`` for directional diffusion. Pure functions of tensors.

Two formulations give the same numbers:

- :func:`flux_form` (the reference, eager): per composition, :func:`projected_gradient`, the
  flux map, then :func:`weighted_divergence`, each a bank of stencils (slicing or conv3d).
- :func:`fused_flux_form` (what is compiled): every flux of every composition at every node of
  the grid plus one halo layer, from haloed inputs, then the divergence of those fluxes, as one
  expression. Compiled, each flux is evaluated once per node and composition and the inputs are
  read once: 1.2x the octant Laplace–Beltrami's time at 128^3 for total variation
  (docs/benchmarks.md), where recomputing the flux at each of a node's faces cost 12x.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .. import stencils
from ..stencils import Offset, shifted

Components = tuple[Tensor, Tensor, Tensor]

FluxMap = Callable[[Components, Sequence[Tensor], int], Components]
"""``f(v, fields, k) -> flux``: ``v`` the ``x, y, z`` components of ``P D u`` of the scheme's
``k``-th composition (:data:`SIDES`), each ``(B, C, D, H, W)``; ``fields`` the per-node tensors
the map needs (a tangent field), given at the same nodes as ``v``."""


SIDES: dict[str, tuple[tuple[int, int, int], ...]] = {
    "conservative": ((1, 1, 1),),
    "symmetric": ((1, 1, 1), (-1, -1, -1)),
    "octant": tuple(itertools.product((1, -1), repeat=3)),
}
"""Each scheme's one-sided compositions: per axis, +1 for forward differences in the gradient
(then backward in the divergence), -1 for the reverse."""


def projected_gradient(
    u: Tensor, normal: Tensor, spacing: float, side: stencils.Side, path: str
) -> Tensor:
    """``P D± u``: one-sided gradient projected on the tangent plane.

    Args:
        u: ``(B, C, D, H, W)``; padded by replication (no flux through the grid's faces).
        normal: ``(B or 1, 3, D, H, W)`` unit normals.
        side: ``+1`` forward differences, ``-1`` backward, or one of them per axis.

    Returns:
        ``(B, C, 3, D, H, W)``, units of ``u`` per world length.
    """
    padded = stencils.pad(u, "replicate")
    gradient = stencils.apply(padded, stencils.one_sided(side), path) / spacing
    n = normal[:, None]
    return gradient - (gradient * n).sum(dim=2, keepdim=True) * n


def weighted_divergence(
    flux: Tensor, grad_norm: Tensor, spacing: float, side: stencils.Side, path: str
) -> Tensor:
    """``(1/W) D∓ . (W flux)`` for a flux built from one-sided differences of ``side``.

    The divergence uses the opposite one-sided differences and no flux through the faces of
    the grid's box, so that it is the exact negative adjoint of the gradient of ``side``.

    Args:
        flux: ``(B, C, 3, D, H, W)``.
        grad_norm: ``W``, ``(B or 1, 1, D, H, W)``.

    Returns:
        ``(B, C, D, H, W)``.
    """
    padded = stencils.pad_flux(flux * grad_norm[:, None], side)
    opposite = stencils.one_sided(stencils.opposite(side))
    return stencils.contract(padded, opposite, path) / (spacing * grad_norm)


def flux_form(
    u: Tensor,
    normal: Tensor,
    grad_norm: Tensor,
    spacing: float,
    flux_map: FluxMap | None,
    fields: Sequence[Tensor],
    scheme: str,
    path: str,
) -> Tensor:
    """``(1/W) div(W f(P grad u))`` by the one-sided compositions of ``scheme``; ``(B, C, D, H, W)``.

    ``flux_map=None`` is the identity (Laplace–Beltrami); ``fields`` are its per-node inputs
    ``(B or 1, K, D, H, W)``.
    """
    sides = SIDES[scheme]
    result = None
    for k, side in enumerate(sides):
        v = projected_gradient(u, normal, spacing, side, path)
        flux = v if flux_map is None else torch.stack(flux_map(v.unbind(2), fields, k), dim=2)
        term = weighted_divergence(flux, grad_norm, spacing, side, path)
        result = term if result is None else result + term
    return result if len(sides) == 1 else result / len(sides)


def _open_faces(like: Tensor, axis: int, side: int) -> Tensor:
    """1 where the face that a node of the haloed grid shares with its neighbour ``side`` along
    ``axis`` lies inside the box, else 0; broadcastable to ``like`` ``(..., D + 2, H + 2, W + 2)``.

    Closed: every halo node, and the last node (``side = +1``) or the first (``side = -1``):
    no flux through the box's faces. Varies along ``axis`` only, so it costs no memory traffic.
    """
    dim = like.dim() - 1 - axis
    length = like.shape[dim]
    index = torch.arange(length, device=like.device, dtype=torch.int32) - 1
    closed = length - 3 if side == 1 else 0
    inside = (index >= 0) & (index < length - 2) & (index != closed)
    shape = [1] * like.dim()
    shape[dim] = length
    return inside.to(like.dtype).view(shape)


def _haloed_slice(padded: Tensor, offset: Offset) -> Tensor:
    """The haloed grid (interior plus one layer) of a volume padded by two, shifted by ``offset``."""
    dz, dy, dx = offset
    depth, height, width = (n - 2 for n in padded.shape[-3:])
    return padded[..., 1 + dz: 1 + dz + depth, 1 + dy: 1 + dy + height, 1 + dx: 1 + dx + width]


def haloed_projected_gradient(
    padded_u: Tensor, haloed_normal: Tensor, spacing: float, side: tuple[int, int, int]
) -> Components:
    """``P D_side u`` at every node of the haloed grid, by components ``(B, C, D + 2, H + 2, W + 2)``.

    ``padded_u`` carries a halo of two nodes, ``haloed_normal`` ``(B or 1, 3, ...)`` of one.
    """
    centre = _haloed_slice(padded_u, stencils.CENTRE)
    normal = tuple(n[:, None] for n in haloed_normal.unbind(1))
    gradient = [
        (_haloed_slice(padded_u, stencils.unit(axis, s)) - centre) * (s / spacing)
        for axis, s in enumerate(side)
    ]
    along = gradient[0] * normal[0] + gradient[1] * normal[1] + gradient[2] * normal[2]
    return tuple(g - along * n for g, n in zip(gradient, normal, strict=True))


def fused_flux_form(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, grad_norm: Tensor,
    spacing: float, flux_map: FluxMap | None, haloed_fields: Sequence[Tensor], scheme: str,
    weighted: bool = False, box_faces: bool = True,
) -> Tensor:
    """``(1/W) div(W f(P grad u))`` as :func:`flux_form` computes it, as one expression.

    The fluxes ``W f(P D_s u)`` of every composition ``s`` are formed at every node of the grid
    plus one halo layer (zero on faces outside the box), then differenced. Halo values of the
    geometry only need to be finite: every flux they touch lies on a closed face.

    Args:
        padded_u: ``u`` replicated over a halo of two nodes, ``(B, C, D + 4, H + 4, W + 4)``.
        haloed_normal: ``(B or 1, 3, D + 2, H + 2, W + 2)``, halo of one node.
        haloed_weight: ``W``, ``(B or 1, 1, D + 2, H + 2, W + 2)``, halo of one node.
        grad_norm: ``W``, ``(B or 1, 1, D, H, W)``.
        flux_map: ``None`` for the identity.
        haloed_fields: the flux map's per-node tensors, halo of one node.
        weighted: return ``W L u`` (symmetric for a linear flux map) instead of ``L u``.
        box_faces: the inputs' outer faces are the box's (no flux through them); ``False``
            for bricks, whose halos hold their neighbours' values.

    Returns:
        ``(B, C, D, H, W)``.
    """
    sides = SIDES[scheme]
    total = None
    for k, side in enumerate(sides):
        v = haloed_projected_gradient(padded_u, haloed_normal, spacing, side)
        flux = v if flux_map is None else flux_map(v, haloed_fields, k)
        for axis, s in enumerate(side):
            face = haloed_weight * flux[axis]
            if box_faces:
                face = face * _open_faces(flux[axis], axis, s)
            ahead, behind = (stencils.unit(axis, 1), stencils.CENTRE) if s == -1 else (
                stencils.CENTRE, stencils.unit(axis, -1))
            term = shifted(face, ahead) - shifted(face, behind)
            total = term if total is None else total + term
    scale = spacing * len(sides)
    return total / scale if weighted else total / (scale * grad_norm)


def flux_form_rows(normal: Tensor, weight: Tensor, spacing: float, scheme: str, entry: Tensor,
                   at: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """The rows of a flux scheme's Laplace–Beltrami matrix (:func:`flux_form` with the identity
    flux map; the volume operator's, faces included) at the nodes ``at``, formed from the
    compositions instead of by applying the operator.

    A composition of sides ``s`` (one per axis) is, at ``p``,
    ``(1 / (W(p) h^2)) sum_a s_a (F_a(p) - F_a(p - s_a e_a))`` with the flux through the face
    between ``x`` and ``x + s_a e_a``
    ``F_a(x) = W(x) sum_b (delta_ab - n_a n_b)(x) s_b (u(x + s_b e_b) - u(x))``, zero where that
    face lies outside the box; ``u`` is replicated beyond the faces, so an entry whose node
    lies beyond a face is added to the face node's. The scheme is the mean of its
    compositions (:data:`SIDES`).

    Args:
        normal: ``(B or 1, 3, D, H, W)``; weight: ``W``, ``(B or 1, 1, D, H, W)``.
        spacing: ``h``, world units.
        scheme: ``"conservative"``, ``"symmetric"`` or ``"octant"``.
        entry: ``(R,)`` the batch entry of each node (any, with geometry of batch 1).
        at: ``(z, y, x)``, ``(R,)`` each, the nodes' grid indices.

    Returns:
        ``(R, 27)``: the coefficient of each node's neighbour at offset
        :data:`torchsurf.stencils.NEIGHBOURHOOD` ``[k]``, zero beyond the box; units
        ``1 / world length^2``.
    """
    shape = normal.shape[-3:]
    if normal.shape[0] == 1:
        entry = torch.zeros_like(entry)
    normal = normal.reshape(normal.shape[0], 3, -1)
    weight = weight.reshape(weight.shape[0], -1)

    box = stencils.BoxNeighbours(at, shape)

    def clamped(offset: Offset) -> tuple[Tensor, Tensor | None]:
        """The flat in-box position of ``p + offset`` and whether it lies in the box (``None``:
        every node's does)."""
        flat, beyond = box.neighbour(offset)
        return flat, None if beyond is None else ~(beyond[0] | beyond[1] | beyond[2])

    def add(offset: Offset, value: Tensor) -> None:
        column = box.column(offset)
        if isinstance(column, int):
            rows[:, column] += value
        else:
            rows.scatter_add_(1, column[:, None], value[:, None])

    centre_flat, _ = clamped(stencils.CENTRE)
    rows = weight.new_zeros((len(entry), len(stencils.NEIGHBOURHOOD)))
    sides = SIDES[scheme]
    scale = 1.0 / (spacing * spacing * len(sides) * weight[entry, centre_flat])
    for side in sides:
        for a, s_a in enumerate(side):
            for sign, x_offset in ((1.0, stencils.CENTRE), (-1.0, stencils.unit(a, -s_a))):
                flat, inside = clamped(x_offset)
                _, ahead = clamped(stencils.add(x_offset, stencils.unit(a, s_a)))
                w, n = weight[entry, flat], normal[entry, :, flat]
                if inside is not None:  # a face of the box closes the faces beyond it
                    w = (inside & ahead).to(rows.dtype) * w
                for b, s_b in enumerate(side):
                    projector = (1.0 if a == b else 0.0) - n[:, a] * n[:, b]
                    value = (sign * s_a * s_b) * w * projector * scale
                    add(stencils.add(x_offset, stencils.unit(b, s_b)), value)
                    add(x_offset, -value)
    return rows
