"""The flux-form core shared by every divergence-form intrinsic operator.

``L u = (1/W) D- . (W f(P D+ u))`` (the paper's Appendix B, ``scheme="conservative"``) or the
mean of that and its mirror ``(1/W) D+ . (W f(P D- u))`` (``scheme="symmetric"``), for a flux
map ``f`` acting on the projected one-sided gradient ``v`` ``(B, C, 3, D, H, W)``: the identity
for Laplace–Beltrami, ``g(|v|) v`` for edge-stopping diffusion, ``(T . v) T`` for directional
diffusion. Pure functions of tensors, so that the whole composition can be compiled.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from .. import stencils

FluxMap = Callable[[Tensor], Tensor]

SIDES = {"conservative": (1,), "symmetric": (1, -1)}


def projected_gradient(
    u: Tensor, normal: Tensor, spacing: float, side: int, path: str
) -> Tensor:
    """``P D± u``: one-sided gradient projected on the tangent plane.

    Args:
        u: ``(B, C, D, H, W)``; padded by replication (no flux through the grid's faces).
        normal: ``(B or 1, 3, D, H, W)`` unit normals.
        side: ``+1`` forward differences, ``-1`` backward.

    Returns:
        ``(B, C, 3, D, H, W)``, units of ``u`` per world length.
    """
    padded = stencils.pad(u, "replicate")
    gradient = stencils.apply(padded, stencils.one_sided(side), path) / spacing
    n = normal[:, None]
    return gradient - (gradient * n).sum(dim=2, keepdim=True) * n


def weighted_divergence(
    flux: Tensor, grad_norm: Tensor, spacing: float, side: int, path: str
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
    return stencils.contract(padded, stencils.one_sided(-side), path) / (spacing * grad_norm)


def flux_form(
    u: Tensor,
    normal: Tensor,
    grad_norm: Tensor,
    spacing: float,
    flux_map: FluxMap,
    scheme: str,
    path: str,
) -> Tensor:
    """``(1/W) div(W f(P grad u))`` by the one-sided compositions of ``scheme``; ``(B, C, D, H, W)``."""
    sides = SIDES[scheme]
    result = None
    for side in sides:
        v = projected_gradient(u, normal, spacing, side, path)
        term = weighted_divergence(flux_map(v), grad_norm, spacing, side, path)
        result = term if result is None else result + term
    return result if len(sides) == 1 else result / len(sides)
