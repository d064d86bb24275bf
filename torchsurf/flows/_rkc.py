"""Second-order Runge–Kutta–Chebyshev (Sommeijer, Shampine & Verwer 1997) for ``u' = F(u)``.

An ``s``-stage step is stable for ``dt * rho <= beta(s)`` when the Jacobian's spectrum lies in
``[-rho, 0]`` (diffusion), so reaching time ``t`` costs about ``sqrt(t * rho)`` evaluations of
``F`` instead of the ``t * rho / 2`` of forward Euler.

The damping ``eps`` trades stages for smoothing. With the usual ``eps = 2 / 13``
(``beta ~ 0.65 s^2``) the stability polynomial stays near ``0.95`` in magnitude over the stiff
part of the interval: eight steps left 66% of the highest frequencies of noise that the exact
flow removes (heat flow of uniform noise on a sphere, ``t = 30 h^2``: mean ``|grad_S u|`` 0.60
against 0.010), so denoising flows kept their noise. ``eps = 3`` bounds it by 0.5 for
``dt lambda > 2`` (``beta ~ 0.49 s^2``, 15% more stages): the same run gives 0.011, and the
sphere's second-order accuracy is kept (docs/band.md). ``eps = 10`` (0.27, a third more
stages) smoothed no better and cost 20% more time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from .. import backend

DAMPING = 3.0
"""``eps``: the shift ``w0 = 1 + eps / s^2`` of the Chebyshev polynomial (see above)."""
MAX_STAGES = 256
"""Beyond this the recurrence loses digits in float32; more steps are taken instead."""


@dataclass(frozen=True)
class Coefficients:
    """The recurrence ``Y_j = (1 - mu_j - nu_j) Y0 + mu_j Y_{j-1} + nu_j Y_{j-2}
    + mu_tilde_j dt F(Y_{j-1}) + gamma_tilde_j dt F(Y0)`` (``j >= 2``), ``Y1 = Y0 + mu_tilde_1 dt F(Y0)``.
    """

    stages: int
    mu: tuple[float, ...]
    nu: tuple[float, ...]
    mu_tilde: tuple[float, ...]
    gamma_tilde: tuple[float, ...]
    stability: float
    """``beta(s)``: the step is stable while ``dt * rho <= stability``."""


def _chebyshev(stages: int, w0: float) -> tuple[list[float], list[float], list[float]]:
    """``T_j(w0)``, ``T_j'(w0)``, ``T_j''(w0)`` for ``j = 0 .. stages``."""
    t, d1, d2 = [1.0, w0], [0.0, 1.0], [0.0, 0.0]
    for j in range(2, stages + 1):
        t.append(2 * w0 * t[j - 1] - t[j - 2])
        d1.append(2 * t[j - 1] + 2 * w0 * d1[j - 1] - d1[j - 2])
        d2.append(4 * d1[j - 1] + 2 * w0 * d2[j - 1] - d2[j - 2])
    return t, d1, d2


_COEFFICIENTS: dict[int, Coefficients] = {}
"""Coefficients already computed, by stages: a plain dict, which ``torch.compile`` reads as
constants (it traces through ``functools.cache`` and would recompute them while tracing)."""


def coefficients(stages: int) -> Coefficients:
    """The RKC2 coefficients of ``stages >= 2`` stages (kept in :data:`_COEFFICIENTS`)."""
    if stages < 2:
        raise ValueError(f"RKC2 needs at least 2 stages, got {stages}")
    if stages not in _COEFFICIENTS:
        _COEFFICIENTS[stages] = _coefficients(stages)
    return _COEFFICIENTS[stages]


def _coefficients(stages: int) -> Coefficients:
    s = stages
    w0 = 1.0 + DAMPING / s**2
    t, d1, d2 = _chebyshev(s, w0)
    w1 = d1[s] / d2[s]
    b = [0.0] * (s + 1)
    for j in range(2, s + 1):
        b[j] = d2[j] / d1[j] ** 2
    b[0] = b[1] = b[2]
    a = [1.0 - b[j] * t[j] for j in range(s + 1)]
    mu, nu, mu_tilde, gamma_tilde = [0.0, 0.0], [0.0, 0.0], [0.0, b[1] * w1], [0.0, 0.0]
    for j in range(2, s + 1):
        mu.append(2 * b[j] * w0 / b[j - 1])
        nu.append(-b[j] / b[j - 2])
        mu_tilde.append(2 * b[j] * w1 / b[j - 1])
        gamma_tilde.append(-a[j - 1] * mu_tilde[j])
    stability = (w0 + 1) * d2[s] / d1[s]
    return Coefficients(s, tuple(mu), tuple(nu), tuple(mu_tilde), tuple(gamma_tilde), stability)


def stages_for(step_times_rho: float) -> int:
    """The fewest stages (at least 2) whose step is stable for ``dt * rho = step_times_rho``."""
    s = max(2, math.ceil(math.sqrt(max(step_times_rho, 0.0) / 0.7)))
    while coefficients(s).stability < step_times_rho and s < MAX_STAGES:
        s += 1
    while s > 2 and coefficients(s - 1).stability >= step_times_rho:
        s -= 1
    return s


def largest_step_times_rho() -> float:
    """``beta(MAX_STAGES)``: the largest ``dt * rho`` one step can carry."""
    return coefficients(MAX_STAGES).stability


def rkc_step(rate: Callable[[Tensor], Tensor], u: Tensor, dt: float | Tensor,
             stages: int, path: str = "auto") -> Tensor:
    """One RKC2 step of ``u' = rate(u)`` of size ``dt`` with ``stages`` evaluations of ``rate``.

    ``path``: how each stage's combination runs (:data:`torchsurf.backend.PATHS`): seven eager
    passes over memory, or one compiled pass.
    """
    c = coefficients(stages)
    rate0 = rate(u)
    previous, current = u, u + (c.mu_tilde[1] * dt) * rate0
    for j in range(2, stages + 1):
        following = _stage(c, j, dt, u, current, previous, rate(current), rate0, path)
        previous, current = current, following
    return current


class LinearStage(Protocol):
    """One RKC stage of a linear rate ``u' = A u`` in one pass (e.g.
    :class:`~torchsurf.flows._packed_band.FusedStage`): the new stage ``u + mu (current - u) +
    a A current + b rate0 + nu (previous - u)`` for ``weights = (mu, nu, a, b)``, ``A current``
    written into ``rate`` when given; ``rate0`` ``None`` reads zeros."""

    def applies(self, u: Tensor) -> bool: ...

    def filled(self, fill: Callable[[Tensor], Tensor]) -> LinearStage:
        """The same stages applying the rate to ``fill(current)``."""

    def step(self, u: Tensor, weights: list[tuple[float, float, float, float]]) -> Tensor | None:
        """The whole step in one call (stage ``j``'s weights ``weights[j]``), or ``None``."""

    def __call__(self, current: Tensor, u: Tensor, previous: Tensor, rate0: Tensor | None,
                 weights: tuple[float, float, float, float], rate: Tensor | None = None
                 ) -> Tensor: ...


def rkc_step_linear(stage: LinearStage, u: Tensor, dt: float, stages: int) -> Tensor:
    """:func:`rkc_step` for a linear rate, each stage one call of ``stage`` (its operator
    application and combination in one pass): the same step to rounding."""
    c = coefficients(stages)
    weights = [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, c.mu_tilde[1] * dt, 0.0)] + [
        (c.mu[j], c.nu[j], c.mu_tilde[j] * dt, c.gamma_tilde[j] * dt)
        for j in range(2, stages + 1)]
    whole = stage.step(u, weights)
    if whole is not None:
        return whole
    rate0 = torch.empty_like(u)
    current = stage(u, u, u, None, weights[1], rate0)
    previous = u
    for j in range(2, stages + 1):
        previous, current = current, stage(current, u, previous, rate0, weights[j])
    return current


def _stage(c: Coefficients, j: int, dt: float | Tensor, u: Tensor, current: Tensor,
           previous: Tensor, rate: Tensor, rate0: Tensor, path: str = "auto") -> Tensor:
    """Stage ``j``: ``u + mu (current - u) + nu (previous - u) + mu~ dt rate + gamma~ dt
    rate0``, the textbook ``(1 - mu - nu) u + mu current + nu previous + ...`` in increment
    form: the stages' rounding is that of the changes, not of ``u`` (the textbook form moved
    a float32 constant by a few units a stage, 15 in all on 1e4 over 1000 h^2). For a float
    ``dt``: eager passes on an eager path or a small volume, else :data:`_STAGE` (its weights
    as 0-d tensors, so that one compiled kernel serves every stage); as tensor arithmetic for a
    learned 0-d ``dt`` or under ``torch.compile``."""
    weights = (c.mu[j], c.nu[j], c.mu_tilde[j] * dt, c.gamma_tilde[j] * dt)
    if isinstance(dt, Tensor) or torch.compiler.is_compiling():
        return _stage_in_one_pass(u, current, previous, rate, rate0, weights)
    if path in backend.EAGER_PATHS or (path == "auto" and u.numel() < STAGE_COMPILE_MIN_VOXELS):
        return _stage_eagerly(u, current, previous, rate, rate0, weights)
    scalars = tuple(torch.tensor(w, dtype=u.dtype, device=u.device) for w in weights)
    return backend.run(_STAGE, path, u, u, current, previous, rate, rate0, scalars)


STAGE_COMPILE_MIN_VOXELS = 2**18
"""Below this many values (``64^3``) a stage's combination stays eager under ``"auto"``: its
passes cost less there than the compiled call's dispatch (37^3: no faster compiled)."""


def _stage_eagerly(u: Tensor, current: Tensor, previous: Tensor, rate: Tensor, rate0: Tensor,
                   weights: tuple[Tensor | float, ...], *, path: str = "slicing") -> Tensor:
    """The stage in one new tensor updated in place; ``previous - u`` is formed in
    ``previous`` itself when nothing else needs it (it is dropped after this stage), else in a
    temporary (autograd may have saved it)."""
    mu, nu, mu_rate, gamma_rate = (float(weight) for weight in weights)
    following = torch.sub(current, u).mul_(mu)
    following.add_(rate, alpha=mu_rate)
    following.add_(rate0, alpha=gamma_rate)
    if previous is not u:
        in_place = not (torch.is_grad_enabled() and previous.requires_grad)
        change = previous.sub_(u) if in_place else previous - u
        following.add_(change, alpha=nu)
    return following.add_(u)


def _stage_in_one_pass(u: Tensor, current: Tensor, previous: Tensor, rate: Tensor,
                       rate0: Tensor, weights: tuple[Tensor | float, ...]) -> Tensor:
    """The stage as one pointwise expression (one pass when compiled)."""
    return (u + weights[0] * (current - u) + weights[1] * (previous - u) + weights[2] * rate
            + weights[3] * rate0)


_STAGE = backend.Kernel("rkc_stage", _stage_eagerly, _stage_in_one_pass, lambda *args: args)
"""An RKC stage's combination: seven eager passes (64^3 x 4: 3.0 ms, 2.1 ms for the textbook
form's five), or one compiled (textbook form at 97^3: 2.2 ms against 1.0
ms; docs/benchmarks.md, heat flow)."""
