"""``Flow``: the module every surface flow derives from (integration method, times, steps).

A flow is built with its physical end time and its parameters and called as
``flow(u0, surface)``; it returns ``u`` at the end time, or at each of ``times=`` stacked in
front. Subclasses only describe their equation (:meth:`Flow.system`); the integration method is
a constructor choice:

- ``"euler"`` (forward Euler) or ``"heun"`` (second order): the step is the flow's stated
  stable bound, or ``time / steps`` when ``steps`` is given;
- ``"implicit"`` (backward Euler) or ``"crank_nicolson"``: for the linear symmetric flows, each
  step a matrix-free conjugate-gradient solve, differentiated implicitly (a second solve);
- any torchdiffeq method (``"dopri5"``, ``"rk4"``, ...): torchdiffeq is optional
  (``pip install torchdiffeq``); ``adjoint=True`` uses ``odeint_adjoint``.

Only nodes in a band ``|phi| <= band_width`` evolve; the others keep ``u0`` (a Dirichlet
condition, which keeps the band-restricted linear operators symmetric). The stale values at the
band's edge leak inwards by the flow's own diffusion, so the default band is the surface's
band widened by twice the diffusion length, ``surface.band_width + 2 sqrt(D_max time)``:
measured on the sphere (l = 2, t = 0.05, sampled on S), the surface's 3-cell band alone gives
a relative error of 2.8e-2 at both 33^3 and 65^3 (no convergence), the widened band the same
error as evolving every node (6.7e-3 and 1.6e-3). Re-extension along normals is off by
default; when asked for, it reads the closest point by tricubic interpolation. Trilinear
interpolation after every step costs the heat flow its second-order accuracy (issue 3;
measured here at 65^3, octant scheme, l = 2, t = 0.05: 5.6e-2 against 1.40e-3 without
re-extension), tricubic keeps it (1.41e-3 re-extending every step, 1.18e-3 every 10 steps).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .._checks import check_positive
from ..operators._inputs import check_data, check_surface
from ..surface import ImplicitSurface
from ._integrators import IMPLICIT, INTEGRATORS, Schedule, System, integrate
from ._positive import Positive
from ._solve import SolverOptions
from .extension import Extension


def _check_times(times: Sequence[float], end: float) -> list[float]:
    times = [check_positive(t, "times") for t in times]
    if not times or any(b <= a for a, b in zip(times, times[1:], strict=False)):
        raise ValueError(f"times must be a non-empty increasing sequence, got {times!r}")
    if times[-1] > end * (1 + 1e-12):
        raise ValueError(f"times must not exceed the flow's time {end:g}, got {times[-1]:g}")
    return times


class Flow(nn.Module):
    """Base of the surface flows: integration settings and the call ``flow(u0, surface)``.

    Args:
        time: physical end time (world units squared for diffusion); a positive number.
        method: ``"euler"``, ``"heun"``, ``"implicit"``, ``"crank_nicolson"`` (linear flows
            only) or a torchdiffeq method name.
        steps: number of time steps (``None``: the flow's stable explicit step, rounded so
            that the steps end exactly at ``time``); for adaptive torchdiffeq methods, unused.
        learn_time: make ``time`` an ``nn.Parameter`` (kept positive by softplus).
        tolerance, max_iterations: conjugate-gradient stopping rule of the implicit methods.
        options: extra keyword options for torchdiffeq (``rtol``, ``atol``, ``step_size``...).
        adjoint: integrate with ``torchdiffeq.odeint_adjoint``.
        progress: show a tqdm progress bar over the steps (tqdm is optional).
        reextend_every: re-extend the data along normals (closest point, tricubic) every
            this many steps; ``None`` (default) never does (see the module docstring).
        band_width: half-width of the evolving band, world units (default: see the module
            docstring).
    """

    def __init__(
        self,
        time: float,
        method: str = "euler",
        steps: int | None = None,
        learn_time: bool = False,
        tolerance: float | None = None,
        max_iterations: int = 1000,
        options: dict | None = None,
        adjoint: bool = False,
        progress: bool = False,
        reextend_every: int | None = None,
        band_width: float | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(method, str):
            raise TypeError(f"method must be a string, got {type(method).__name__}")
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
            raise ValueError(f"steps must be a whole number >= 1 or None, got {steps!r}")
        if reextend_every is not None and (
            isinstance(reextend_every, bool) or not isinstance(reextend_every, int)
            or reextend_every < 1
        ):
            raise ValueError(
                f"reextend_every must be a whole number >= 1 or None, got {reextend_every!r}"
            )
        self.time_value = Positive(time, "time", learnable=learn_time)
        if self.time_value.channels is not None:
            raise ValueError(f"time must be a single number, got {time!r}")
        self.method = method
        self.steps = steps
        self.solver = SolverOptions(
            None if tolerance is None else check_positive(tolerance, "tolerance"),
            int(max_iterations),
        )
        self.options = dict(options or {})
        self.adjoint = bool(adjoint)
        self.progress = bool(progress)
        self.reextend_every = reextend_every
        self.extension = (
            Extension(interpolation="cubic") if reextend_every is not None else None
        )
        self.band_width = None if band_width is None else check_positive(band_width, "band_width")

    @property
    def time(self) -> float | Tensor:
        """The end time: a float, or a positive 0-d tensor when learnable."""
        return self.time_value.value()

    def diffusion_length(self) -> float:
        """``sqrt(D_max time)``, world units: how far the band's edge leaks in by the end."""
        return self.time_value.maximum() ** 0.5

    def band(self, surface: ImplicitSurface, like: Tensor) -> Tensor:
        """The evolving band as a float mask ``(B or 1, 1, D, H, W)`` in ``like``'s dtype."""
        width = self.band_width
        if width is None:
            width = surface.band_width + 2.0 * self.diffusion_length()
        return surface.band(width).to(like.dtype)

    def system(self, u0: Tensor, surface: ImplicitSurface, **inputs: Tensor) -> System:
        """The flow's equation for ``u0`` on ``surface``; subclasses implement it."""
        raise NotImplementedError

    def _schedule(self, times: Sequence[float] | None, surface: ImplicitSurface,
                  total: int | None, bar: object | None) -> Schedule:
        end = self.time
        if times is None:
            times = [end]
        else:
            times = _check_times(times, self.time_value.maximum())
            if isinstance(end, Tensor):
                times = [end * (t / self.time_value.maximum()) for t in times]
        return Schedule(
            times=times, steps=self.steps, solver=self.solver, options=self.options,
            adjoint=self.adjoint, after_step=self._after_step(surface, bar),
        )

    def _progress_bar(self, total: int | None):  # noqa: ANN202
        if not self.progress:
            return None
        try:
            from tqdm.auto import tqdm
        except ImportError as error:
            raise ImportError(
                "progress=True needs tqdm, an optional dependency: pip install tqdm"
            ) from error
        return tqdm(total=total, desc=type(self).__name__, unit="step", leave=False)

    def _after_step(self, surface: ImplicitSurface, bar: object | None):  # noqa: ANN202
        hooks = []
        if bar is not None:
            hooks.append(lambda u, k: (bar.update(1), u)[1])
        if self.extension is not None:
            every, extension = self.reextend_every, self.extension
            hooks.append(lambda u, k: extension(u, surface) if k % every == 0 else u)
        if not hooks:
            return None

        def after_step(u: Tensor, k: int) -> Tensor:
            for hook in hooks:
                u = hook(u, k)
            return u

        return after_step

    def forward(
        self, u0: Tensor, surface: ImplicitSurface, times: Sequence[float] | None = None,
        **inputs: Tensor,
    ) -> Tensor:
        """Integrate from ``u0`` to the end time.

        Args:
            u0: initial data ``(B, C, D, H, W)``; ``surface`` has batch 1 or B.
            surface: the implicit surface.
            times: optional increasing times in ``(0, time]`` to return ``u`` at.
            inputs: flow-specific inputs (e.g. ``direction`` for tangent-field flows).

        Returns:
            ``u(time)`` ``(B, C, D, H, W)``, or ``(T, B, C, D, H, W)`` for ``T`` ``times``.
        """
        check_surface(surface)
        check_data(u0, "u0", surface)
        system = self.system(u0, surface, **inputs)
        if self.method in IMPLICIT and system.linear is None:
            raise ValueError(
                f"method={self.method!r} needs a linear symmetric flow; {type(self).__name__} "
                "is not: use 'euler', 'heun' or a torchdiffeq method"
            )
        total = self.steps
        if total is None and self.method in INTEGRATORS:
            total = max(1, math.ceil(self.time_value.maximum() / system.stable_step))
        bar = self._progress_bar(total)
        try:
            result = integrate(self.method, system, u0, self._schedule(times, surface, total, bar))
        finally:
            if bar is not None:
                bar.close()
        return result[-1] if times is None else torch.stack(result)

    def extra_repr(self) -> str:
        return f"method={self.method!r}, steps={self.steps}"

