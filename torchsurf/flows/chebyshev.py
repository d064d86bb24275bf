"""Functions of a self-adjoint diffusion operator by Chebyshev expansion: ``exp(t L) x`` and
``t phi1(t L) x`` in ``O(sqrt(t rho))`` operator applications, with a backward that stores nothing.

``L`` is any linear operator ``apply(x)`` on volumes ``(B, C, D, H, W)`` whose spectrum lies in
``[-rho, 0]`` and which is self-adjoint in the ``W``-weighted inner product, ``L^T = W L W^-1``
(the divergence-form Laplace–Beltrami restricted to a band: docs/learning.md).
With ``Y = I + (2 / rho) L`` (spectrum in ``[-1, 1]``) and ``T_k`` the Chebyshev polynomials,

    f(L) x ~= sum_{k < K} c_k T_k(Y) x,      T_{k+1}(Y) x = 2 Y T_k(Y) x - T_{k-1}(Y) x,

``c_k`` the Chebyshev coefficients of ``s -> f((rho / 2)(s - 1))`` on ``[-1, 1]``. For
``f(s) = exp(t s)`` they are ``(2 - [k = 0]) e^-a I_k(a)``, ``a = t rho / 2`` (modified Bessel
functions), which fall below a tolerance ``tol`` once ``k > sqrt(2 a log(1 / tol))``: the
number of applications grows as ``sqrt(t rho)``, not as the ``t rho / 2`` of explicit steps,
up to ``a =`` :data:`PIECE_HALF_WIDTH`; longer times of ``exp`` run as powers of the expansion
for a fraction of the time, for operators whose spectrum is only close to real.
The coefficients are computed here by a cosine sum over ``2K + 16`` nodes (exact to rounding,
and differentiable in ``t``), one set per channel; the expansion stops when every channel's
remaining coefficients sum below ``tol`` (``1e-7`` in float32, ``1e-13`` in float64).

Backward, with the operator fixed (nothing it reads requires grad): the map is
``p(Y) = sum c_k T_k(Y)``, whose transpose is ``W p(Y) (g / W)`` since ``Y`` is self-adjoint in
the ``W`` inner product. One recurrence on ``g / W`` gives the gradient of ``x`` and, with the
inner products ``s_k = <x, W T_k(Y)(g / W)>`` per channel, the gradient of the times through the
coefficients: ``dL/dt_c = sum_k (dc_k / dt_c) s_k``, the exact derivative of the expansion
computed (equal to ``<g, L exp(t L) x>`` for ``f = exp``, to the tolerance). Nothing but ``x``,
the times and ``W`` is kept for backward. When the operator's tensors require grad (a learned
``phi``), the recurrence runs in groups of ``sqrt(K)`` terms without a graph, each recomputed
under autograd in backward (:func:`~torchsurf.flows._recompute.recomputed`): ``O(sqrt(K))``
volumes kept, and no graph held between forward and backward.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from .. import backend
from ._recompute import declared, recomputed, refuse_second_derivatives

KINDS = ("exp", "phi1")
"""``"exp"``: ``exp(t L)``; ``"phi1"``: ``t phi1(t L) = (exp(t L) - 1) / L`` (which maps a
constant source ``f`` to the solution of ``u' = L u + f``, ``u(0) = 0``, at time ``t``)."""

MAX_TERMS = 100_000
"""More terms than this are refused before any work: ``t rho`` near ``10^9``, a unit error."""

MAX_APPLICATIONS = 10**6
"""More operator applications than this in one expansion (its pieces' terms added up) are
refused before any work: ``t rho`` near ``10^7``, hours of work and a likely unit error."""


class TooManyApplications(ValueError):
    """An expansion over ``time`` would take ``applications`` operator applications, more than
    :data:`MAX_APPLICATIONS` (``bound``: the operator's ``rho``); raised before any work. A
    caller whose times are in other units restates it in them."""

    def __init__(self, applications: int, time: float, bound: float) -> None:
        self.applications, self.time, self.bound = applications, time, bound
        super().__init__(
            f"a time of {time:g} (world units squared) needs {applications} applications of "
            f"the operator (more than {MAX_APPLICATIONS}): time * rho = {time * bound:.3g} "
            f"(rho = {bound:.3g}, the operator's bound), hours of work and a likely unit error"
        )


def check_applications(applications: int, time: float, bound: float) -> None:
    """Raise :class:`TooManyApplications` (a ``ValueError``) before any work when an expansion
    over ``time`` would take more than :data:`MAX_APPLICATIONS` operator ``applications``."""
    if applications > MAX_APPLICATIONS:
        raise TooManyApplications(applications, time, bound)

PIECE_HALF_WIDTH = 250.0
"""The largest ``a = t rho / 2`` one expansion of ``exp`` covers; longer times are applied as
the ``m``-th power of the expansion for ``t / m`` (:func:`pieces_for`). A band operator whose
ring is filled by closest-point interpolation is not exactly self-adjoint: some of its
eigenvalues lie off the real axis (``|Im lambda| h^2`` up to 0.23 against ``rho h^2`` near 11
on small spheres), where ``|T_k|`` grows with ``k``, and one expansion of many terms amplified
rounding and truncation without bound (13^3 sphere, float64, t = 1000 h^2, ``a`` near 5500: a
range of [-2.5, 3.3] for data in [0, 1]; the 32^3 bunny in float32 was off from ``a`` near
1600)."""


def tolerance(dtype: torch.dtype) -> float:
    """Truncation tolerance of the expansion for ``dtype``: ``1e-13`` in float64, else ``1e-7``."""
    return 1e-13 if dtype == torch.float64 else 1e-7


def _nodes(count: int, dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
    """``theta_j = pi (j + 1/2) / count``, the Chebyshev nodes' angles ``(count,)``."""
    return (torch.arange(count, dtype=dtype, device=device) + 0.5) * (math.pi / count)


def _values(kind: str, times: Tensor, bound: float, theta: Tensor, derivative: bool) -> Tensor:
    """``f_t((rho / 2)(cos theta - 1))`` for each time ``(C,)`` and angle ``(N,)``: ``(C, N)``;
    its derivative in ``t`` if ``derivative``."""
    s = (0.5 * bound) * (torch.cos(theta) - 1.0)  # eigenvalues of L, all < 0 at the nodes
    ts = times[:, None] * s[None, :]
    if kind == "exp":
        return s[None, :] * torch.exp(ts) if derivative else torch.exp(ts)
    return torch.exp(ts) if derivative else torch.expm1(ts) / s[None, :]


def coefficients(kind: str, times: Tensor, bound: float, terms: int,
                 derivative: bool = False) -> Tensor:
    """Chebyshev coefficients ``(C, terms)`` of ``f_t`` on ``[-bound, 0]``, in ``times``' graph.

    Args:
        kind: ``"exp"`` or ``"phi1"`` (:data:`KINDS`).
        times: ``(C,)``, in the units of ``1 / bound`` (world length squared for a diffusion).
        bound: ``rho``, an upper bound of ``-L``'s spectrum.
        terms: ``K``.
        derivative: return ``dc / dt`` instead (each channel's coefficients depend on its own
            time only).

    Returns:
        ``c`` with ``f_t(L) ~= sum_k c[:, k] T_k(I + 2 L / rho)``, in ``times``' dtype.
    """
    count = 2 * terms + 16
    theta = _nodes(count, torch.float64, times.device)
    values = _values(kind, times.to(torch.float64), bound, theta, derivative)
    k = torch.arange(terms, dtype=torch.float64, device=times.device)
    cosines = torch.cos(k[:, None] * theta[None, :])  # (K, N)
    result = (2.0 / count) * values @ cosines.T
    result = torch.cat([0.5 * result[:, :1], result[:, 1:]], dim=1)
    return result.to(times.dtype)


_COUNTS: dict[tuple[str, float, float, torch.dtype], int] = {}
"""Term counts already computed: a call that ``torch.compile`` traces finds the count of an
earlier (eager) call with the same floats as a constant, instead of breaking the graph to
compute it on the host."""

MAX_COUNTS = 1024
"""Entries of :data:`_COUNTS` kept at most (it is emptied beyond: learned times vary)."""


def count_terms(kind: str, time: float, bound: float, dtype: torch.dtype) -> int:
    """The fewest terms ``K`` whose omitted coefficients sum below :func:`tolerance` times
    their total, for the largest time ``time`` (a float: the host decides the loop).

    Kept per arguments (:data:`_COUNTS`). Raises ``ValueError`` beyond :data:`MAX_TERMS`.
    """
    key = (kind, time, bound, dtype)
    if key not in _COUNTS:
        if len(_COUNTS) >= MAX_COUNTS:
            _COUNTS.clear()
        _COUNTS[key] = _count_terms(kind, time, bound, dtype)
    return _COUNTS[key]


def _count_terms(kind: str, time: float, bound: float, dtype: torch.dtype) -> int:
    a = 0.5 * time * bound
    tol = tolerance(dtype)
    cap = math.ceil(1.3 * math.sqrt(2.0 * a * math.log(1.0 / tol)) + 2.0 * math.log(1.0 / tol) + 8)
    if cap > MAX_TERMS:
        raise ValueError(
            f"time * rho = {time * bound:.3g} needs about {cap} Chebyshev terms (more than "
            f"{MAX_TERMS}): is the time in the expected units?"
        )
    values = coefficients(kind, torch.tensor([time], dtype=torch.float64), bound, cap)[0]
    magnitude = np.abs(values.numpy())
    # the cosine sums leave ~1e-17 of rounding in coefficients that are really far smaller
    magnitude[magnitude < 1e-16 * magnitude.sum()] = 0.0
    tail = np.cumsum(magnitude[::-1])[::-1]  # tail[k] = sum_{j >= k} |c_j|
    small = np.nonzero(tail <= tol * tail[0])[0]
    return int(small[0]) if len(small) else cap


def pieces_for(time: float, bound: float) -> int:
    """How many equal pieces ``exp(t L)`` is applied in: ``ceil(t rho / 2 /``
    :data:`PIECE_HALF_WIDTH` ``)``, at least 1."""
    return max(1, math.ceil(0.5 * time * bound / PIECE_HALF_WIDTH))


@torch.compiler.disable
def _host_largest(times: Tensor) -> float:
    """The largest of ``times`` on the host, checked finite and positive: it sets the loop's
    length (under ``torch.compile``, the one graph break of an expansion)."""
    largest = float(times.detach().max())
    if not math.isfinite(largest) or not largest > 0:
        raise ValueError(
            f"times must be finite and positive, got {times.detach().tolist()!r} (a learned "
            "time that is not: an optimiser step diverged)"
        )
    return largest


def _step(operator: Callable[..., Tensor], scale: float, current: Tensor, previous: Tensor,
          params: tuple[Tensor, ...]) -> Tensor:
    """``T_{k+1} x = 2 Y T_k x - T_{k-1} x`` with ``Y = I + scale L`` (``scale = 2 / rho``)."""
    image = operator(current, *params)
    return torch.add(2.0 * current - previous, image, alpha=2.0 * scale)


def _channelwise(c: Tensor, like: Tensor) -> Tensor:
    """Coefficients ``(C,)`` shaped to broadcast over ``like``, channels in dimension 1
    (``(B, C, D, H, W)`` volumes or packed ``(nodes, C, K)`` values)."""
    return c.view(1, -1, *([1] * (like.dim() - 2)))


def _channel_sums(x: Tensor) -> Tensor:
    """``x`` summed over every dimension but the channels' (dimension 1): ``(C,)``."""
    return x.sum(dim=[d for d in range(x.dim()) if d != 1])


def _recurrence(operator: Callable[..., Tensor], x: Tensor, c: Tensor, bound: float,
                params: tuple[Tensor, ...],
                inner: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """``sum_k c[:, k] T_k(Y) x`` ``(B, C, D, H, W)`` and, if ``inner`` is given, the inner
    products ``<inner, T_k(Y) x>`` per channel ``(C, K)``; four volumes live at a time.
    Without autograd only (the Function's forward and backward)."""
    terms = c.shape[1]
    scale = 2.0 / bound
    # one buffer, not one small tensor a term: small long-lived allocations between the
    # volumes' fragment the heap (measured: resident memory grew with the number of terms)
    products = x.new_empty((x.shape[1], terms)) if inner is not None else None
    index = 0

    def record(term: Tensor) -> None:
        nonlocal index
        if products is not None:
            products[:, index] = _channel_sums(inner * term)
        index += 1

    previous = x
    total = _channelwise(c[:, 0], x) * x
    record(x)
    if terms > 1:
        current = torch.add(x, operator(x, *params), alpha=scale)
        total.addcmul_(_channelwise(c[:, 1], x), current)
        record(current)
        for k in range(2, terms):
            # in place on the operator's output (no grad here): fewer allocations, less
            # fragmentation of the heap over a long expansion
            following = operator(current, *params).mul_(2.0 * scale)
            following.add_(current, alpha=2.0).sub_(previous)
            previous, current = current, following
            total.addcmul_(_channelwise(c[:, k], x), current)
            record(current)
    return total, products


class _Expansion(torch.autograd.Function):
    """``p(Y)^m x``, ``p = sum_k c_k(t / m) T_k``, for an operator that reads no tensor
    requiring grad; backward by the transposed expansion ``W p(Y)(g / W)`` applied ``m`` times,
    nothing stored but ``x``, ``t`` and ``W``."""

    @staticmethod
    def forward(ctx, operator, adjoint, kind, bound, terms, pieces, x, weight, times):  # noqa: ANN001, ANN205
        c = coefficients(kind, times.detach() / pieces, bound, terms)
        with torch.no_grad():
            total = x
            for _ in range(pieces):
                total, _ = _recurrence(operator, total, c, bound, ())
        ctx.operator, ctx.adjoint = operator, adjoint
        ctx.kind, ctx.bound, ctx.terms, ctx.pieces = kind, bound, terms, pieces
        ctx.save_for_backward(x, weight, times)
        return total

    @staticmethod
    @backend.part_of_recorded
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        refuse_second_derivatives("the Chebyshev expansion (LearnedDiffusion, "
                                  "HeatFlow(method='chebyshev'))", grad_output)
        x, weight, times = ctx.saved_tensors
        want_x, want_times = ctx.needs_input_grad[6], ctx.needs_input_grad[8]
        grad_x = grad_times = None
        if want_x or want_times:
            c = coefficients(ctx.kind, times.detach() / ctx.pieces, ctx.bound, ctx.terms)
            # one piece: the times' gradient through the coefficients, <x, p'(Y)^T g>; several:
            # that of exp(t L) itself, <g, L exp(t L) x> = <L x, exp(t L)^T g> per channel
            inner = want_times and ctx.pieces == 1
            with torch.no_grad():
                transposed = grad_output
                for _ in range(ctx.pieces):
                    if ctx.adjoint is None:  # p(Y)^T g = W p(Y)(g / W)
                        transposed, products = _recurrence(
                            ctx.operator, transposed / weight, c, ctx.bound, (),
                            inner=x * weight if inner else None,
                        )
                        transposed = weight * transposed
                    else:
                        transposed, products = _recurrence(
                            ctx.adjoint, transposed, c, ctx.bound, (),
                            inner=x if inner else None,
                        )
            if want_x:
                grad_x = transposed.sum_to_size(x.shape) if transposed.shape != x.shape else transposed
            if want_times and inner:
                slopes = coefficients(ctx.kind, times.detach(), ctx.bound, ctx.terms, True)
                grad_times = (slopes * products.to(slopes.dtype)).sum(dim=1)
            elif want_times:
                with torch.no_grad():
                    rate = ctx.operator(x)
                grad_times = _channel_sums(rate * transposed).to(times.dtype)
        return None, None, None, None, None, None, grad_x, None, grad_times


def _group(operator: Callable[..., Tensor], scale: float, c: Tensor, first: int, previous: Tensor,
           current: Tensor, total: Tensor, *params: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Terms ``first .. first + c.shape[1] - 1`` of the recurrence (a checkpointed group)."""
    for j in range(c.shape[1]):
        previous, current = current, _step(operator, scale, current, previous, params)
        total = torch.addcmul(total, _channelwise(c[:, j], current), current)
    return previous, current, total


def _stacked_group(operator: Callable[..., Tensor], scale: float, c: Tensor, first: int,
                   params: tuple[Tensor, ...], state: Tensor) -> Tensor:
    """:func:`_group` on ``state`` = ``(previous, current, total)`` stacked along a new first
    dimension (one tensor, as :func:`recomputed` takes)."""
    return torch.stack(_group(operator, scale, c, first, *state.unbind(0), *params))


def _checkpointed(operator: Callable[..., Tensor], x: Tensor, c: Tensor, bound: float,
                  params: tuple[Tensor, ...], reads: Sequence[Tensor] = ()) -> Tensor:
    """The recurrence under autograd, in groups of ``sqrt(K)`` terms run without a graph and
    recomputed in backward; ``reads``: what ``operator`` reads that needs gradients."""
    terms, scale = c.shape[1], 2.0 / bound
    total = _channelwise(c[:, 0], x) * x
    if terms == 1:
        return total
    current = torch.add(x, operator(x, *params), alpha=scale)
    total = total + _channelwise(c[:, 1], x) * current
    state = torch.stack((x, current, total))
    inputs = declared((*reads, *params, c))
    group = max(1, math.isqrt(terms))
    for first in range(2, terms, group):
        chunk = c[:, first: min(first + group, terms)]
        state = recomputed(
            functools.partial(_stacked_group, operator, scale, chunk, first, params), state,
            inputs, what="the Chebyshev expansion (LearnedDiffusion, HeatFlow(method='chebyshev'))",
        )
    return state[2]


def expansion(
    operator: Callable[[Tensor], Tensor], x: Tensor, times: Tensor, bound: float,
    weight: Tensor | None = None, adjoint: Callable[[Tensor], Tensor] | None = None,
    kind: str = "exp", differentiable_operator: bool = False, terms: int | None = None,
    reads: Sequence[Tensor] = (), largest: float | None = None,
) -> Tensor:
    """``f_t(L) x`` by Chebyshev expansion, one time per channel (module docstring).

    Args:
        operator: ``x -> L x`` on ``(B, C, D, H, W)``, linear, its spectrum in ``[-bound, 0]``
            (real, or close to it).
        x: ``(B, C, D, H, W)``.
        times: ``(C,)`` or ``()`` positive times, units of ``1 / bound``.
        bound: ``rho > 0``, an upper bound of the spectral radius of ``L``.
        weight: ``W`` ``(B or 1, 1, D, H, W)``, positive, when ``L`` is self-adjoint in the
            ``W`` inner product (``L^T = W L W^-1``): backward then uses ``operator`` itself.
        adjoint: ``g -> L^T g`` otherwise (one of ``weight`` and ``adjoint`` is needed).
        kind: ``"exp"`` (``exp(t L) x``) or ``"phi1"`` (``(exp(t L) - 1) L^-1 x``).
        differentiable_operator: ``operator`` reads tensors that require grad (``phi``'s
            geometry): the recurrence then runs in groups of ``sqrt(K)`` terms recomputed
            under autograd in backward, instead of the transposed expansion.
        terms: number of terms ``K``, applied once (default: :func:`count_terms` of the
            largest time, or of its pieces').
        reads: with ``differentiable_operator``, the tensors ``operator`` reads that need
            gradients (``phi``): backward raises if it reads another.
        largest: a host float no smaller than any of ``times``, so that nothing is read from
            them (``torch.compile`` traces the call whole); ``None``: their largest, read.

    Returns:
        ``(B, C, D, H, W)``. Operator applications: ``m (K - 1)`` forward, as many in backward,
        where ``exp`` over ``a = t rho / 2`` above :data:`PIECE_HALF_WIDTH` runs as the ``m``-th
        power of the expansion for ``t / m`` (:func:`pieces_for`).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if weight is None and adjoint is None:
        raise ValueError("expansion needs weight (a W-self-adjoint operator) or adjoint")
    times = times.reshape(-1).expand(x.shape[1]) if times.numel() == 1 else times
    pieces = 1
    if terms is None:
        top = _host_largest(times) if largest is None else largest
        pieces = pieces_for(top, bound) if kind == "exp" else 1
        terms = count_terms(kind, top / pieces, bound, x.dtype)
        check_applications(pieces * (terms - 1), top, bound)
    if differentiable_operator and torch.is_grad_enabled():
        c = coefficients(kind, times / pieces, bound, terms)
        for _ in range(pieces):
            x = _checkpointed(operator, x, c, bound, (), reads)
        return x
    if weight is None:
        weight = x.new_ones(())
    return _Expansion.apply(operator, adjoint, kind, bound, terms, pieces, x, weight, times)
