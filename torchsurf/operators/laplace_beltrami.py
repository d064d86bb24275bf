"""The Laplace–Beltrami operator ``(1/W) div(W P grad u)`` on implicit surfaces (SPEC §2-3)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .. import stencils
from .._checks import check_choice
from ..surface import ImplicitSurface
from . import _paths
from ._flux_form import flux_form, fused_flux_form
from ._inputs import check_data
from ._octant import fused_octant, octant

SCHEMES = ("octant", "symmetric", "conservative", "central")


def _divergence_form(
    u: Tensor, normal: Tensor, grad_norm: Tensor, spacing: float, scheme: str, path: str
) -> Tensor:
    if scheme == "octant":
        return octant(u, normal, grad_norm, spacing, path)
    return flux_form(u, normal, grad_norm, spacing, None, scheme, path)


def _adjoint(
    g: Tensor, normal: Tensor, grad_norm: Tensor, spacing: float, scheme: str, path: str
) -> Tensor:
    """``L^T g = W L(g / W)``: the divergence-form schemes are ``W^-1 A`` with ``A`` symmetric."""
    return grad_norm * _divergence_form(g / grad_norm, normal, grad_norm, spacing, scheme, path)


def _one_pass(scheme: str, path: str) -> bool:
    """Whether ``scheme`` runs as one pointwise kernel over haloed inputs on ``path``: the
    octant scheme on every path but conv3d (its reference), the others when compiled."""
    return path == "compiled" or (scheme == "octant" and path != "conv3d")


def _run_one_pass(
    haloed_u: Tensor, haloed_normal: Tensor, haloed_grad_norm: Tensor, grad_norm: Tensor,
    spacing: float, scheme: str, path: str, weighted: bool,
) -> Tensor:
    """``L u``, or ``W L u`` when ``weighted`` (with ``haloed_u`` holding ``g / W``: ``L^T g``)."""
    inputs = (haloed_u, haloed_normal, haloed_grad_norm, grad_norm, spacing)
    if scheme == "octant":
        kernel = _paths.compiled(fused_octant) if path == "compiled" else fused_octant
        return kernel(*inputs, weighted)
    return _paths.compiled(fused_flux_form)(*inputs, None, scheme, weighted)


def _apply(
    u: Tensor, surface: ImplicitSurface, scheme: str, path: str, adjoint: bool
) -> Tensor:
    """``L u`` (or ``L^T u``) of a divergence-form scheme on the path chosen for ``u``."""
    path = _paths.resolve(path, u)
    if _one_pass(scheme, path):
        haloed_normal, haloed_grad_norm = surface.haloed()
        haloed_u = stencils.pad(u, "replicate")
        if adjoint:
            haloed_u = haloed_u / haloed_grad_norm
        return _run_one_pass(
            haloed_u, haloed_normal, haloed_grad_norm, surface.weight, surface.spacing,
            scheme, path, weighted=adjoint,
        )
    function = _adjoint if adjoint else _divergence_form
    return function(u, surface.normal, surface.weight, surface.spacing, scheme, path)


def weighted_operator(
    x: Tensor, normal: Tensor, grad_norm: Tensor, haloed_normal: Tensor, haloed_grad_norm: Tensor,
    spacing: float, scheme: str, path: str,
) -> Tensor:
    """``A x = W L x`` of a divergence-form scheme, symmetric negative semi-definite.

    The form the implicit flows hand to conjugate gradients. Every geometric tensor is an
    argument, so that autograd reaches all of them; the haloed ones are
    :meth:`ImplicitSurface.haloed`'s and spare the compiled kernel its padding.

    Args:
        x: ``(B, C, D, H, W)``.
        normal, grad_norm: ``(B or 1, 3 | 1, D, H, W)``.
        haloed_normal, haloed_grad_norm: the same with a halo of one node.

    Returns:
        ``(B, C, D, H, W)``, units of ``x`` per world length squared.
    """
    path = _paths.resolve(path, x)
    if _one_pass(scheme, path):
        return _run_one_pass(
            stencils.pad(x, "replicate"), haloed_normal, haloed_grad_norm, grad_norm, spacing,
            scheme, path, weighted=True,
        )
    return grad_norm * _divergence_form(x, normal, grad_norm, spacing, scheme, path)


class _WeightedSelfAdjoint(torch.autograd.Function):
    """Backward of a divergence-form scheme w.r.t. ``u`` by its adjoint, one forward-sized pass.

    Used when the surface is fixed (no gradient to ``phi``): backpropagating through the
    stencil composition instead costs about twice as much (docs/benchmarks.md).
    """

    @staticmethod
    def forward(ctx, u, surface, scheme, path):  # noqa: ANN001, ANN205
        ctx.surface, ctx.settings = surface, (scheme, path, u.shape[0])
        return _apply(u, surface, scheme, path, adjoint=False)

    @staticmethod
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        scheme, path, batch = ctx.settings
        grad_u = _apply(grad_output, ctx.surface, scheme, path, adjoint=True)
        if grad_u.shape[0] != batch:
            grad_u = grad_u.sum(dim=0, keepdim=True)
        return grad_u, None, None, None


def _central(
    padded: Tensor, normal: Tensor, mean_curvature: Tensor, spacing: float, path: str
) -> Tensor:
    """The central scheme on ``u`` haloed by replication (padding outside a compiled kernel
    keeps its loads contiguous)."""
    gradient = stencils.apply(padded, stencils.CENTRAL, path) / spacing
    xx, yy, zz, xy, xz, yz = stencils.apply(padded, stencils.HESSIAN, path).unbind(dim=2)
    nx, ny, nz = normal[:, None].unbind(dim=2)
    laplacian = xx + yy + zz
    normal_second = (
        nx * nx * xx + ny * ny * yy + nz * nz * zz
        + 2.0 * (nx * ny * xy + nx * nz * xz + ny * nz * yz)
    )
    normal_first = (gradient * normal[:, None]).sum(dim=2)
    return (laplacian - normal_second) / spacing**2 - mean_curvature * normal_first


def laplace_beltrami(
    u: Tensor, surface: ImplicitSurface, scheme: str = "octant", path: str = "auto"
) -> Tensor:
    """Intrinsic Laplacian ``Lap_S u = (1/W) div(W P grad u)`` of data on ``surface``.

    With ``u`` constant along the normals this is the Laplace–Beltrami operator of the level
    set through each node (sphere of radius R, spherical harmonic of degree l:
    ``-l(l+1) u / R^2``). Boundary condition at the faces of the grid's box: no flux.

    Schemes (orders measured on a torus, max norm over the nodes within one cell of S, and the
    stable explicit Euler step for ``u_t = L u`` with ``W = 1``). Relative errors are for a
    torus ``R = 1, r = 0.4`` at 129^3 (16 cells per tube radius), three functions of its angles:

    - ``"octant"`` (default): the mean of the eight compositions ``(1/W) D^-s . (W P D^s u)``
      that pick forward or backward differences per axis, which sums to the standard symmetric
      discretisation of ``div(W P grad u)``: diagonal terms on the faces between neighbours,
      cross terms by central differences. Symmetric negative semi-definite in the W-weighted
      inner product; second order (2.0); relative error 1.2e-3 to 4.0e-3;
      ``dt <= h^2 / 6``. Evaluated in one pass; as fast as ``"symmetric"`` when compiled.
    - ``"symmetric"``: ``(1/2W) [D- . (W P D+ u) + D+ . (W P D- u)]``, two of the eight;
      symmetric negative semi-definite; second order (2.0), but its biased cross terms leave an
      error 2.5-4x larger (3.8e-3 to 9.5e-3); ``dt <= h^2 / 6``.
    - ``"conservative"``: ``(1/W) D- . (W P D+ u)``, the paper's Appendix B exactly; symmetric
      negative semi-definite; first order (1.0) on curved surfaces; ``dt <= h^2 / 6``.
    - ``"central"``: ``Lap u - n^T (Hess u) n - H dn u`` with central differences; second order
      (2.0); not symmetric; explicit steps take ``dt <= h^2 / 6`` in practice.

    Args:
        u: data ``(B, C, D, H, W)``; ``surface`` has batch 1 or B.
        surface: the implicit surface.
        scheme: one of ``"octant"``, ``"symmetric"``, ``"conservative"``, ``"central"``.
        path: ``"auto"``, ``"slicing"``, ``"conv3d"`` or ``"compiled"``: how the stencils are
            applied; every path gives the same numbers. ``"auto"`` compiles volumes of at least
            64^3 voxels (double backward needs an eager path).

    Returns:
        ``(B, C, D, H, W)``, units of ``u`` per world length squared.

    Example:
        >>> import torchsurf as ts
        >>> grid = ts.Grid.cube(33, bound=1.5)
        >>> surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
        >>> z = grid.points()[..., 2][None, None]
        >>> ts.laplace_beltrami(z / (z**2 + 1e-9).sqrt(), surface).shape
        torch.Size([1, 1, 33, 33, 33])
    """
    check_choice(scheme, "scheme", SCHEMES)
    check_data(u, "u", surface)
    if scheme == "central":
        return _paths.run(
            _central, path, u, stencils.pad(u, "replicate"), surface.normal,
            surface.mean_curvature(), surface.spacing,
        )
    if surface.normal.requires_grad or surface.weight.requires_grad:
        return _apply(u, surface, scheme, path, adjoint=False)
    return _WeightedSelfAdjoint.apply(u, surface, scheme, path)


class LaplaceBeltrami(nn.Module):
    """Module form of :func:`laplace_beltrami`: ``(B, C, D, H, W) -> (B, C, D, H, W)``.

    Args:
        scheme: ``"octant"`` (default), ``"symmetric"``, ``"conservative"`` or ``"central"``.
        path: how stencils are applied (see :func:`laplace_beltrami`).
    """

    def __init__(self, scheme: str = "octant", path: str = "auto") -> None:
        super().__init__()
        self.scheme = check_choice(scheme, "scheme", SCHEMES)
        self.path = check_choice(path, "path", _paths.PATHS)

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        return laplace_beltrami(u, surface, scheme=self.scheme, path=self.path)

    def extra_repr(self) -> str:
        return f"scheme={self.scheme!r}, path={self.path!r}"
