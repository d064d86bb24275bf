"""The heat semigroup ``exp(t Lap_S)`` on a surface's band, by Chebyshev expansion.

``u(t) = exp(t L) u0`` for each channel's own time, with ``L`` the divergence-form
Laplace–Beltrami (:func:`torchsurf.operators.functional.divergence_form`) evaluated on the
band, and the ring of nodes its stencils read around the band **re-extended from the band at
every application** by the tricubic closest-point stencil (:class:`CubicStencil`, unlimited so
that it is linear):

    L u = M W^-1 A E (M u),      M: the band mask,  A = W Lap_S (symmetric),  E: the re-extension.

That is the operator the explicit flows integrate (their ring is re-extended at every
evaluation of the rate), so the result matches theirs; the symmetric alternatives were measured
and rejected (docs/learning.md): with the ring held fixed (a Dirichlet condition, the implicit
methods' choice within a step) the data at the band's edge drifts from the surface's values as
soon as the diffusion length exceeds a cell, and on the sphere the l = 1..4 harmonics at
``t = 10 h^2`` carry errors of 1-15% (against 0.2-0.5% re-extended).

``L`` is not self-adjoint; its transpose ``M E^T A W^-1 M`` is applied exactly (``E^T`` scatters
each ring node's value back to the nodes it was read from), so backward is the same Chebyshev
expansion run on the incoming gradient with ``L^T`` (:mod:`torchsurf.flows.chebyshev`). The
spectrum of ``L`` is real to rounding in every case measured and lies within the Gershgorin bound
``rho`` of the band operator (:func:`torchsurf.operators.laplace_beltrami_bound`) times
:data:`BOUND_MARGIN`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..operators import functional
from ..operators.spectrum import laplace_beltrami_bound
from ..surface import ImplicitSurface
from . import chebyshev
from ._integrators import with_ring
from .extension import BrickCubicStencil, CubicStencil, cubic_stencil

BOUND_MARGIN = 1.1
"""The expansion's interval is ``[-BOUND_MARGIN rho, 0]``: the re-extended ring makes ``L``
slightly non-normal, and the cost of the margin is ``sqrt(1.1)``, 5% more terms."""

Stencil = CubicStencil | BrickCubicStencil


def _linear_stencil(surface: ImplicitSurface, width: float, kind: str, mask: Tensor,
                    region: Tensor) -> Stencil:
    """The linear closest-point stencil of ``mask`` (``kind`` names it: ``"ring"`` or
    ``"region"``) reading only ``region``, for the surface's storage, kept on the surface
    unless ``phi`` requires grad."""
    if surface.phi.requires_grad:
        return cubic_stencil(surface, mask, limited=False, readable=region)
    return surface.kept(("linear stencil", width, kind),
                        lambda: cubic_stencil(surface, mask, limited=False, readable=region))


class BandLaplacian:
    """``L`` of the module docstring on one surface: ``apply``, ``transpose`` and its bound.

    On a :class:`~torchsurf.bricks.BrickSurface` every field is packed ``(N, C, 8, 8, 8)``:
    ``A`` reads the haloed bricks, ``E`` and ``E^T`` are the :class:`BrickCubicStencil`'s, and
    a batch of several entries shares one bound (the largest entry's: each entry's result is
    its own ``exp(t L)`` to the expansion's tolerance).

    Args:
        surface: the implicit surface (batch 1 or B), or a brick surface.
        scheme: ``"octant"`` (default), ``"symmetric"`` or ``"conservative"``.
        band_width: half-width of the band, world units (default ``surface.band_width``).
        path: how the stencils run (:mod:`torchsurf.backend`).

    Attributes:
        band: ``(B or 1, 1, D, H, W)`` (or packed ``(N, 1, 8, 8, 8)``) bool, the nodes that
            evolve.
        region: the band and its ring (the nodes the result is written to).
        ring, extension: the closest-point stencils of the ring and of the whole region.
        bound: ``BOUND_MARGIN`` times the Gershgorin bound of ``Lap_S`` on the band,
            ``1 / world length^2``.
    """

    def __init__(self, surface: ImplicitSurface, scheme: str = "octant",
                 band_width: float | None = None, path: str = "auto") -> None:
        if scheme not in functional.SCHEMES:
            raise ValueError(
                f"scheme must be one of {functional.SCHEMES} (the divergence forms), got {scheme!r}"
            )
        width = surface.band_width if band_width is None else float(band_width)
        self.surface, self.scheme, self.path = surface, scheme, path
        self.band = surface.band_mask(width)
        self.region = with_ring(self.band, surface.layout)
        self.ring = _linear_stencil(surface, width, "ring", self.region & ~self.band,
                                    self.region)
        self.extension = _linear_stencil(surface, width, "region", self.region, self.region)
        self.bound = BOUND_MARGIN * laplace_beltrami_bound(surface, scheme, width)

    @property
    def differentiable(self) -> bool:
        """The geometry is in ``phi``'s graph (``phi`` requires grad)."""
        return self.surface.phi.requires_grad

    def _weighted(self, x: Tensor) -> Tensor:
        """``A x = W Lap_S x`` (symmetric negative semi-definite)."""
        surface = self.surface
        return functional.divergence_form(
            x, surface.normal, surface.weight, surface.spacing, self.scheme, self.path,
            weighted=True, haloed=surface.haloed(),
            pad=None if surface.layout is None else surface.layout.halo,
        )

    def apply(self, x: Tensor) -> Tensor:
        """``L x = M W^-1 A E (M x)`` for ``x`` ``(B, C, D, H, W)``."""
        zero = x.new_zeros(())
        inside = torch.where(self.band, x, zero)
        image = self._weighted(self.ring.apply(inside, self.path)) / self.surface.weight
        return torch.where(self.band, image, zero)

    def transpose(self, g: Tensor) -> Tensor:
        """``L^T g = M E^T A W^-1 (M g)`` (``A`` symmetric)."""
        zero = g.new_zeros(())
        inside = torch.where(self.band, g / self.surface.weight, zero)
        return torch.where(self.band, self.ring.transpose(self._weighted(inside)), zero)


class _Extend(torch.autograd.Function):
    """``E x`` for a linear stencil ``E`` with fixed weights; backward ``E^T g``, nothing saved
    (autograd through the gather would keep 64 values per node)."""

    @staticmethod
    def forward(ctx, stencil, x, path="auto"):  # noqa: ANN001, ANN205
        ctx.stencil, ctx.batch = stencil, x.shape[0]
        return stencil.apply(x, path)

    @staticmethod
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        grad = ctx.stencil.transpose(grad_output)
        return None, grad if grad.shape[0] == ctx.batch else grad.sum(dim=0, keepdim=True), None


def heat_semigroup(u0: Tensor, operator: BandLaplacian, times: Tensor,
                   largest: float | None = None) -> Tensor:
    """``exp(t_c L) u0`` per channel on the band, then re-extended along normals.

    As the flows do after each step, the result is re-extended from its values near S to the
    whole band and its ring (the linear tricubic closest-point stencil), so that it is constant
    along the normals: every level set in the band carries the surface's solution.

    Args:
        u0: ``(B, C, D, H, W)``; only its band values are read.
        operator: the band's :class:`BandLaplacian`.
        times: ``(C,)`` or ``()``, positive, world units squared (may require grad).
        largest: a float no smaller than any of ``times``: the expansion's terms are counted
            for it on the host, and nothing is read from ``times`` (``torch.compile`` traces the
            call whole). ``None``: counted for the largest of ``times``, read on the host (a
            graph break).

    Returns:
        ``(B, C, D, H, W)``: the band and its ring hold ``u(t)`` (constant along normals),
        other nodes ``u0``'s values.
        Gradients reach ``u0``'s band values, ``times`` and (by recomputation) ``phi``.
    """
    zero = u0.new_zeros(())
    inside = torch.where(operator.band, u0, zero)
    terms = None if largest is None else chebyshev.count_terms(
        "exp", largest, operator.bound, u0.dtype
    )
    result = chebyshev.expansion(
        operator.apply, inside, times, operator.bound, adjoint=operator.transpose,
        differentiable_operator=operator.differentiable, terms=terms,
        reads=(operator.surface.phi,),
    )
    if operator.differentiable:
        extended = operator.extension.apply(result, operator.path)
    else:
        extended = _Extend.apply(operator.extension, result, operator.path)
    return torch.where(operator.region, extended, u0)
