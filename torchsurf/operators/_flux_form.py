"""The flux-form core shared by every divergence-form intrinsic operator.

``L u = (1/W) D- . (W f(P D+ u))`` (the paper's Appendix B, ``scheme="conservative"``) or the
mean of that and its mirror ``(1/W) D+ . (W f(P D- u))`` (``scheme="symmetric"``), for a flux
map ``f`` acting on the projected one-sided gradient ``v`` ``(B, C, 3, D, H, W)``: the identity
for Laplace–Beltrami, ``g(|v|) v`` for edge-stopping diffusion, ``(T . v) T`` for directional
diffusion. Pure functions of tensors, so that the whole composition can be compiled.

Two formulations give the same numbers. The modular one (:func:`projected_gradient`, then
:func:`weighted_divergence`) materialises the flux and is the faster one eagerly. The fused
one (:func:`fused_flux_form`) recomputes the flux through each face from the haloed inputs
where the divergence needs it: more arithmetic, but under ``torch.compile`` it becomes a single
pass that reads ``u``, the normals and ``W`` once and writes the result, so :func:`flux_form`
takes it whenever it is being compiled (docs/benchmarks.md).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import torch
from torch import Tensor

from .. import stencils
from ..stencils import Offset, shifted

FluxMap = Callable[[Tensor], Tensor]

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
    scheme: str,
    path: str,
) -> Tensor:
    """``(1/W) div(W f(P grad u))`` by the one-sided compositions of ``scheme``; ``(B, C, D, H, W)``.

    ``flux_map=None`` is the identity (Laplace–Beltrami).
    """
    if torch.compiler.is_compiling():
        haloed = (stencils.pad(t, "replicate") for t in (u, normal, grad_norm))
        return fused_flux_form(*haloed, grad_norm, spacing, flux_map, scheme)
    sides = SIDES[scheme]
    result = None
    for side in sides:
        v = projected_gradient(u, normal, spacing, side, path)
        flux = v if flux_map is None else flux_map(v)
        term = weighted_divergence(flux, grad_norm, spacing, side, path)
        result = term if result is None else result + term
    return result if len(sides) == 1 else result / len(sides)


def _combine(terms: list[tuple[float, Tensor]]) -> Tensor:
    """``sum(weight * term)``, adding or subtracting for weights of +1 and -1.

    Inductor does not fold a multiplication by ±1.0; in the fused kernel, which is bound by
    arithmetic, skipping those multiplications saves about a quarter of the time.
    """
    result = None
    for weight, term in terms:
        if result is None:
            result = term if weight == 1 else -term if weight == -1 else weight * term
        elif weight in (1, -1):
            result = result + term if weight == 1 else result - term
        else:
            result = result + weight * term
    return result


def _open_faces(like: Tensor, axis: int, side: int, at: Offset) -> Tensor:
    """1 where the face of each node shifted by ``at`` along ``axis`` lies inside the box, else 0.

    ``side`` is the sign of the one-sided differences along ``axis``.

    Broadcastable to ``like`` ``(..., D, H, W)``: varies along ``axis`` only, so that it costs
    no memory traffic. The face of node ``p`` for differences of ``side`` lies between ``p``
    and ``p + side``; it is outside for the last node (``side = +1``), the first node
    (``side = -1``) and every halo node.
    """
    dim = like.dim() - 1 - axis
    length = like.shape[dim]
    index = torch.arange(length, device=like.device) + at[2 - axis]
    closed = length - 1 if side == 1 else 0
    inside = (index >= 0) & (index < length) & (index != closed)
    shape = [1] * like.dim()
    shape[dim] = length
    return inside.to(like.dtype).view(shape)


def _face_flux(
    u: Tensor, normal: Tensor, weight: Tensor, spacing: float,
    flux_map: FluxMap | None, side: tuple[int, int, int], axis: int, at: Offset,
) -> Tensor:
    """Component ``axis`` of ``W f(P D_side u)`` at the nodes shifted by ``at``; ``(B, C, D, H, W)``.

    ``u``, ``normal`` and ``weight`` carry a halo of one node. Without a flux map the result
    is in index units (the caller divides by ``spacing``), which saves the divisions.
    """
    gradient = [
        _combine([(w, shifted(u, stencils.add(at, offset))) for offset, w in stencil.taps])
        for stencil in stencils.one_sided(side)
    ]
    if flux_map is not None:
        gradient = [g / spacing for g in gradient]
    n = [shifted(normal[:, c: c + 1], at) for c in range(3)]
    along = gradient[0] * n[0] + gradient[1] * n[1] + gradient[2] * n[2]
    scale = shifted(weight, at) * _open_faces(gradient[0], axis, side[axis], at)
    if flux_map is None:
        return scale * (gradient[axis] - along * n[axis])
    v = torch.stack([g - along * nc for g, nc in zip(gradient, n, strict=True)], dim=2)
    return scale * flux_map(v)[:, :, axis]


def fused_flux_form(
    padded_u: Tensor, padded_normal: Tensor, padded_weight: Tensor, grad_norm: Tensor,
    spacing: float, flux_map: FluxMap | None, scheme: str, adjoint: bool = False,
) -> Tensor:
    """``(1/W) div(W f(P grad u))`` as :func:`flux_form` computes it, as one pointwise expression.

    Every input carries a halo of one node: ``u`` replicated (as :func:`projected_gradient`
    pads it), the normals and ``W`` with any finite values (faces outside the box carry no
    flux). Passing them haloed keeps the padding out of the compiled kernel, whose loads then
    stay contiguous and vectorise (3-4x faster at 128^3, docs/benchmarks.md).

    Args:
        padded_u: ``(B, C, D + 2, H + 2, W + 2)``.
        padded_normal: ``(B or 1, 3, D + 2, H + 2, W + 2)``.
        padded_weight: ``W`` haloed, ``(B or 1, 1, D + 2, H + 2, W + 2)``.
        grad_norm: ``W``, ``(B or 1, 1, D, H, W)``.
        flux_map: ``None`` for the identity (no stacked flux is built).
        adjoint: compute the transpose ``L^T g = W L(g / W)`` of the linear operator instead;
            ``padded_u`` must then hold ``g / W``, haloed.

    Returns:
        ``(B, C, D, H, W)``.
    """
    sides = SIDES[scheme]
    terms = [
        (w, _face_flux(padded_u, padded_normal, padded_weight, spacing, flux_map, side, axis, offset))
        for side in sides
        for axis, stencil in enumerate(stencils.one_sided(stencils.opposite(side)))
        for offset, w in stencil.taps
    ]
    scale = spacing * len(sides) * (spacing if flux_map is None else 1.0)
    result = _combine(terms)
    return result / scale if adjoint else result / (scale * grad_norm)
