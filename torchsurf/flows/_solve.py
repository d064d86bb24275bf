"""Matrix-free conjugate gradients for symmetric positive definite systems, with implicit gradients.

The implicit flows solve ``K x = b`` per volume and channel, where ``K`` (a callable on
``(B, C, D, H, W)`` volumes) is symmetric positive definite on the nodes it acts on. The
gradient of ``x`` is not backpropagated through the iterations: since ``K`` is symmetric,
``dL/db = K^-1 dL/dx`` (a second solve) and ``dL/dtheta = -(dK/dtheta x)^T K^-1 dL/dx`` for the
tensors ``theta`` that ``K`` reads (diffusivities, step, the surface's normals and weights).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import backend
from .._stack import caller_stacklevel
from ._recompute import refuse_second_derivatives

Operator = Callable[..., Tensor]

_SPATIAL = (2, 3, 4)


@dataclass(frozen=True)
class SolverOptions:
    """Stopping rule of :func:`conjugate_gradient`.

    Args:
        tolerance: stop when ``|b - K x| <= tolerance * |b|`` for every volume and channel;
            ``None`` picks ``1e-6`` in float32 and ``1e-10`` in float64.
        max_iterations: give up after this many iterations (the result is then the last iterate,
            with a ``RuntimeWarning`` stating the residual reached).
    """

    tolerance: float | None = None
    max_iterations: int = 1000

    def resolved_tolerance(self, dtype: torch.dtype) -> float:
        if self.tolerance is not None:
            return self.tolerance
        return 1e-10 if dtype == torch.float64 else 1e-6


def _dot(a: Tensor, b: Tensor, groups: Tensor | None = None) -> Tensor:
    """``<a, b>`` per volume and channel ``(B, C, 1, 1, 1)``; with ``groups`` ``(N,)``, the
    rows are the bricks of packed fields and the sums run over each batch entry's bricks."""
    rows = (a * b).sum(dim=_SPATIAL, keepdim=True)
    if groups is None:
        return rows
    entries = rows.new_zeros((int(groups.max()) + 1, *rows.shape[1:]))
    return entries.index_add(0, groups, rows)[groups]


def _largest(a: Tensor, groups: Tensor | None = None) -> Tensor:
    """``max |a|`` per volume and channel ``(B, C, 1, 1, 1)`` (per batch entry with ``groups``,
    as :func:`_dot`)."""
    rows = a.abs().amax(dim=_SPATIAL, keepdim=True)
    if groups is None:
        return rows
    entries = rows.new_zeros((int(groups.max()) + 1, *rows.shape[1:]))
    index = groups.reshape(-1, *[1] * (rows.dim() - 1)).expand_as(rows)
    return entries.scatter_reduce(0, index, rows, "amax")[groups]


def _check_residual(energy: Tensor, iteration: int) -> None:
    """Raise ``FloatingPointError`` if a squared residual ``(B, C, 1, 1, 1)`` is NaN or infinite."""
    if not bool(torch.isfinite(energy).all()):
        raise FloatingPointError(
            f"conjugate gradients: the residual became NaN or infinite at iteration {iteration}; "
            "the right-hand side (the data, e.g. u0) or the operator's coefficients (diffusivity, "
            "time step, the surface's normals and weights) hold NaN or infinity"
        )


def _warn_unconverged(energy: Tensor, norm: Tensor, tolerance: float, iterations: int) -> None:
    """Warn that conjugate gradients stopped at ``iterations`` above the tolerance.

    ``energy`` and ``norm`` are the squared residuals and right-hand sides ``(B, C, 1, 1, 1)``.
    """
    reached = float(torch.sqrt(energy / norm).max())
    warnings.warn(
        f"conjugate gradients stopped at max_iterations = {iterations} without converging: "
        f"relative residual |b - K x| / |b| = {reached:.3g}, tolerance {tolerance:.3g}; raise "
        "max_iterations or the tolerance, or take shorter steps",
        RuntimeWarning,
        stacklevel=caller_stacklevel(),
    )


@torch.no_grad()
def conjugate_gradient(
    operator: Callable[[Tensor], Tensor], rhs: Tensor, initial: Tensor, options: SolverOptions,
    groups: Tensor | None = None,
) -> tuple[Tensor, int]:
    """Solve ``operator(x) = rhs`` for every volume and channel of ``rhs`` ``(B, C, D, H, W)``.

    With ``groups`` ``(N,)`` (the batch index of each brick), ``rhs`` is a packed band field
    ``(N, C, 8, 8, 8)`` and each batch entry is one system.

    Returns:
        The solution ``(B, C, D, H, W)`` and the number of iterations taken.

    Raises:
        FloatingPointError: a residual is NaN or infinite (non-finite data or coefficients).

    Warns:
        RuntimeWarning: ``options.max_iterations`` was reached before the tolerance.

    Each system is solved divided by its largest value (``operator`` is linear and acts on
    each volume and channel alone): squared norms of data near ``1e-20`` underflowed in float32
    (the solve stopped at once, 0.49 off) and near ``1e19`` overflowed (``FloatingPointError``).
    """
    scale = torch.maximum(_largest(rhs, groups), _largest(initial, groups))
    scale = torch.where((scale > 0) & torch.isfinite(scale), scale, 1.0)
    x, iterations = _unit_conjugate_gradient(operator, rhs / scale, initial / scale, options,
                                             groups)
    return x * scale, iterations


def _unit_conjugate_gradient(
    operator: Callable[[Tensor], Tensor], rhs: Tensor, initial: Tensor, options: SolverOptions,
    groups: Tensor | None,
) -> tuple[Tensor, int]:
    """:func:`conjugate_gradient` on a system whose data are of size about 1."""
    tolerance = options.resolved_tolerance(rhs.dtype)
    x = initial.clone()
    residual = rhs - operator(x)
    direction = residual.clone()
    energy = _dot(residual, residual, groups)
    tiny = torch.finfo(rhs.dtype).tiny  # not 1e-300, which is 0 in float32
    norm = _dot(rhs, rhs, groups).clamp(min=tiny)
    target = tolerance**2 * norm
    for iteration in range(options.max_iterations + 1):
        _check_residual(energy, iteration)
        # converged volumes stay put, so a volume's answer does not depend on its batch
        active = energy > target
        if not bool(active.any()):
            return x, iteration
        if iteration == options.max_iterations:
            break
        image = operator(direction)
        curvature = _dot(direction, image, groups)
        alpha = torch.where(active & (curvature > 0), energy / curvature.clamp(min=tiny), 0.0)
        x = x + alpha * direction
        residual = residual - alpha * image
        new_energy = _dot(residual, residual, groups)
        direction = residual + (new_energy / energy.clamp(min=tiny)) * direction
        energy = new_energy
    _warn_unconverged(energy, norm, tolerance, options.max_iterations)
    return x, options.max_iterations


class _SymmetricSolve(torch.autograd.Function):
    """``x = K^-1 b`` with ``K`` symmetric; backward by a second solve (implicit differentiation)."""

    @staticmethod
    def forward(ctx, operator, options, groups, initial, rhs, *params):  # noqa: ANN001, ANN205
        def apply(x: Tensor) -> Tensor:
            return operator(x, *params)

        solution, _ = conjugate_gradient(apply, rhs, initial, options, groups)
        ctx.operator, ctx.options, ctx.groups = operator, options, groups
        ctx.save_for_backward(solution, *params)
        return solution

    @staticmethod
    @backend.part_of_recorded
    def backward(ctx, grad_solution):  # noqa: ANN001, ANN205
        refuse_second_derivatives("the implicit steps' conjugate-gradient solve", grad_solution)
        solution, *params = ctx.saved_tensors

        def apply(x: Tensor) -> Tensor:
            return ctx.operator(x, *params)

        adjoint, _ = conjugate_gradient(
            apply, grad_solution, torch.zeros_like(grad_solution), ctx.options, ctx.groups
        )
        wanted = [i for i in range(len(params)) if ctx.needs_input_grad[5 + i]]
        grads: list[Tensor | None] = [None] * len(params)
        if wanted:
            # fresh leaves: the gradient must stop at the parameters, not run into their graphs
            leaves = [p.detach().requires_grad_(i in wanted) for i, p in enumerate(params)]
            with torch.enable_grad():
                image = ctx.operator(solution, *leaves)
                found = torch.autograd.grad(
                    image, [leaves[i] for i in wanted], -adjoint, allow_unused=True
                )
            for i, grad in zip(wanted, found, strict=True):
                grads[i] = grad
        grad_rhs = adjoint if ctx.needs_input_grad[4] else None
        return None, None, None, None, grad_rhs, *grads


def solve_symmetric(
    operator: Operator,
    rhs: Tensor,
    initial: Tensor,
    params: Sequence[Tensor],
    options: SolverOptions,
    groups: Tensor | None = None,
) -> Tensor:
    """``K^-1 rhs`` by conjugate gradients, differentiable by implicit differentiation.

    Args:
        operator: ``(x, *params) -> K x`` on volumes ``(B, C, D, H, W)``, symmetric positive
            definite; it must read the tensors it depends on from ``params`` only.
        rhs: ``(B, C, D, H, W)``.
        initial: starting guess, same shape (treated as a constant).
        params: the tensors ``operator`` reads (diffusivities, steps, the surface's geometry).
        options: the stopping rule.
        groups: for packed band fields, the batch index of each brick ``(N,)``.
    """
    return _SymmetricSolve.apply(operator, options, groups, initial.detach(), rhs, *params)
