"""``Flow``: the module every surface flow derives from (integration method, times, steps).

A flow is built with its physical end time and its parameters and called as
``flow(u0, surface)``; it returns ``u`` at the end time, or at each of ``times=`` stacked in
front. Subclasses only describe their equation (:meth:`Flow.system`); the integration method is
a constructor choice:

- ``"rkc"`` (default): second-order Runge–Kutta–Chebyshev, its stages chosen from a bound of
  the assembled operator's spectrum; its steps are limited by the time the diffusion takes to
  cross the band, not by stability (about 4x fewer operator applications than Euler on a
  3-cell band);
- ``"euler"`` (forward Euler) or ``"heun"`` (second order): the step ``1.8 / rho`` from the same
  bound (0.9 of the stability limit ``2 / rho`` it guarantees, so that the fastest mode is
  damped; the true limit is wider where the bound is loose: about 2x on meshes' phi), or
  ``time / steps`` when ``steps`` is given;
- ``"implicit"`` (backward Euler) or ``"crank_nicolson"``: for the linear symmetric flows, each
  step a matrix-free conjugate-gradient solve, differentiated implicitly (a second solve);
- any torchdiffeq method (``"dopri5"``, ``"rk4"``, ...): torchdiffeq is optional
  (``pip install torchdiffeq``); ``adjoint=True`` uses ``odeint_adjoint``.

The computational domain is a band of fixed width around S (``surface.band_width``, 3 cells by
default, widened to 5 cells on a dense surface whose phi is a distance that far, or
``band_width=``), measured as ``|phi| / W`` so that it does not depend on the scale of ``phi``,
and independent of the time. The ring of nodes its stencils read around it is refreshed by
closest-point re-extension (tricubic, limited) at every evaluation of the rate of RKC,
Euler, Heun and the torchdiffeq methods (RKC, Euler and Heun: only between re-extensions of
the band where the band is wide enough to hold the ring that long and the rate has no
reaction term), and the whole band
with it after each step, or, where steps are shorter than the time the fastest diffusion takes
to cross a cell, after as many steps as that takes (RKC steps that hold the ring: as many as
one step could hold it for; torchdiffeq methods: after each piece of
:func:`torchdiffeq_segment`), and at each requested time
(``reextend_every``): every re-extension errs a little, so more steps must not mean more of
them. The implicit methods, whose operator
must stay symmetric, hold the ring fixed during a step (a Dirichlet condition) and, where
Euler's steps would not hold it, re-extend it before each step. The explicit
steps and RKC's stages come from a Gershgorin bound ``rho`` of the operator assembled on that
band (:mod:`torchsurf.operators.spectrum`), never from the nominal ``h^2 / 6`` alone.
docs/band.md has the measurements behind these choices.
"""

from __future__ import annotations

import functools
import math
import numbers
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextvars import ContextVar, Token

import numpy as np
import torch
from torch import Tensor, nn

from .. import _memory
from .._as_is import run_as_is_first
from .._checks import (
    check_count,
    check_finite,
    check_flag,
    check_has_data,
    check_nonnegative,
    check_positive,
)
from .._stack import caller_stacklevel
from .._transforms import refuse_transforms, saved_plainly_in_checkpoints
from ..bricks.layout import BRICK, BrickLayout
from ..operators.spectrum import laplace_beltrami_bound
from ..surface import (  # noqa: F401  (WIDE_BAND_CELLS, DISTANCE_TOLERANCE: documented here too)
    DISTANCE_TOLERANCE,
    WIDE_BAND_CELLS,
    ImplicitSurface,
    check_data,
    check_surface,
    warned_already,
)
from ._integrators import (
    IMPLICIT,
    INTEGRATORS,
    TIME_ROUNDING,
    Linear,
    Plan,
    Schedule,
    System,
    check_method,
    check_options,
    first_warning,
    held_ring_bound,
    integrate,
    plan_steps,
    ring_held,
    shortest_step,
    step_ends,
    steps_taken,
    whole_steps,
    with_ring,
)
from ._packed_band import PackedRegion
from ._positive import Positive, check_learned_values
from ._reextension import (
    MIN_BAND_CELLS,
    check_reextension_width,
    kept_stencil,
    reextend,
)
from ._solve import SolverOptions
from .extension import stencil_key

RANGE_SLACK = 0.25
"""How far, as a fraction of ``u0``'s range over the band and its ring, the result of a flow
that keeps ``u`` within that range (:attr:`Flow.keeps_range`) may leave it before the call
warns. The projected stencils are not monotone on curved surfaces, so a stable flow may
overshoot: a heat flow of 0/1 data by up to 17% on coarse ellipsoids
(``tests/test_properties.py``), flow visualisation of noise without re-extension by 10%; an
unstable one grows without bound (docs/band.md, section 5)."""


_GATHERED_EXCESSES: ContextVar[tuple[tuple[Flow, list[tuple[float, Plan | str]]], ...]] = (
    ContextVar("torchsurf_gathered_excesses", default=()))
"""The flows whose runs apart this thread's call gathers range excesses for, with their lists
(:meth:`Flow._gather_excesses`)."""


RANGE_ROUNDING = 1024
"""The range a check compares with is at least this many rounding units of ``u0``'s magnitude:
data that varies less than that (a constant, ``1e4 + 0.01 noise`` in float32) may leave its
range by rounding alone (the operators' and re-extension's sums round at the data's
magnitude)."""


def _masked_range(x: Tensor, mask: Tensor, dims: list[int]) -> tuple[Tensor, Tensor]:
    """The least and largest values of ``x`` where ``mask`` holds, reduced over ``dims``."""
    return (torch.where(mask, x, torch.inf).amin(dim=dims),
            torch.where(mask, x, -torch.inf).amax(dim=dims))


def _range_excess(u0: Tensor, results: list[Tensor], region: Tensor, band: Tensor,
                  packed: bool) -> float:
    """How far the worst of ``results`` leaves the range of ``u0`` (over ``region``) in the
    ``band``, as a fraction of that range, per batch entry and channel (a packed field is one
    entry: a batch of several surfaces is integrated one entry at a time)."""
    dims = [0, 2, 3, 4] if packed else [2, 3, 4]
    with torch.no_grad():
        return _excess(_masked_range(u0.detach(), region, dims),
                       (_masked_range(value.detach(), band, dims) for value in results))


def _packed_range_excess(start: Tensor, results: list[Tensor], band_count: int) -> float:
    """:func:`_range_excess` on one volume's packed region values ``(nodes, C, K)`` (the band's
    nodes first, ``band_count`` of them): per channel and batch entry ``K``."""
    with torch.no_grad():
        bands = (value.detach()[:band_count] for value in results)
        return _excess(torch.aminmax(start.detach(), dim=0),
                       (torch.aminmax(band, dim=0) for band in bands))


def _excess(start: tuple[Tensor, Tensor], results: Iterable[tuple[Tensor, Tensor]]) -> float:
    """The largest step of the ``(least, largest)`` ``results`` beyond the ``(low, high)`` of
    ``start``, as a fraction of ``high - low`` (at least the rounding of the values)."""
    low, high = start
    rounding = RANGE_ROUNDING * torch.finfo(low.dtype).eps * torch.maximum(low.abs(), high.abs())
    span = torch.maximum(high - low, rounding).clamp_min(torch.finfo(low.dtype).tiny)
    excess = 0.0
    for least, largest in results:
        excess = max(excess, float((torch.maximum(largest - high, low - least) / span).max()))
    return excess


def _fewest_steps(method: str, system: System, band_cells: float, length: float,
                  end: float) -> int:
    """The steps of an interval of ``length`` that ends at the requested time ``end``: none
    longer than those ``method`` plans for a flow to ``end`` alone (:func:`plan_steps`; its
    warnings are the whole run's, given once by the run's own plan)."""
    longest = end / plan_steps(method, system, end, None, band_cells=band_cells,
                               warn=False).count
    return whole_steps(length, longest, end)


def _marks_by_time(ends: list[float], period: float, longest_held: float) -> set[int]:
    """The steps (from 1) whose ends ``ends`` (physical time) first reach a new multiple of
    ``period``, and any step after which the next would end more than ``longest_held`` after
    the last mark."""
    marks, last, previous = set(), 0.0, 0.0
    slack = TIME_ROUNDING * ends[-1]  # float32 requested times: a crossing one step early
    for k, end in enumerate(ends, start=1):
        crossed = (math.floor((end + slack) / period) > math.floor((previous + slack) / period))
        overdue = k < len(ends) and ends[k] - last > longest_held + slack
        if crossed or overdue:
            marks.add(k)
            last = end
        previous = end
    return marks


def _most_steps_between(marks: set[int], count: int) -> int:
    """The most steps from one mark (or the start) to the next (or the end)."""
    edges = [0, *sorted(marks), count]
    return max(1, *(b - a for a, b in zip(edges, edges[1:], strict=False)))


def placed(result: Tensor | None, part: Tensor, index: Tensor, size: int, axis: int) -> Tensor:
    """``part`` written at ``index`` along ``axis`` (counted from the end) of ``result``, or of
    zeros of ``part``'s shape with ``size`` along ``axis`` when ``result`` is ``None``."""
    if result is None:
        shape = list(part.shape)
        shape[axis] = size
        result = part.new_zeros(shape)
    return result.index_copy(part.dim() + axis, index, part)


def _steps_taken(plan: Plan) -> str:
    """The steps of a run, for messages."""
    return ("torchdiffeq's own steps" if plan.count is None
            else f"{plan.count} steps of {plan.step:.3g}")


def _warn_range_left(flow: Flow, excess: float, plan: Plan | str) -> None:
    """The warning of a flow that keeps ``u`` within the range of ``u0`` and left it by
    ``excess`` of that range (more than :data:`RANGE_SLACK`); ``plan`` its steps, or what it
    did in words."""
    if not first_warning(flow._warned_kinds(), "range left"):
        return
    steps = plan if isinstance(plan, str) else _steps_taken(plan)
    remedy = ("a finer grid" if flow.method in ("rkc", "chebyshev")
              else "method='rkc' (stable there in every case measured) or a finer grid")
    warnings.warn(
        f"{type(flow).__name__} (method={flow.method!r}, {steps}) left the range of u0 "
        f"by {excess:.3g} of that range, far more than stable runs overshoot, though its "
        "equation keeps u within it: its steps and the band's re-extensions were unstable on "
        "this surface (parts of S closer together, or more curved, than the band and the "
        f"interpolation stencil resolve; docs/band.md, section 5). Use {remedy}",
        RuntimeWarning, stacklevel=caller_stacklevel(),
    )


def _check_times(times: object, end: float) -> list[float]:
    """``times`` as increasing floats in ``[0, end]``; raises naming ``times`` otherwise.

    ``times`` is a sequence of numbers (Python, numpy or 0-d tensors), a 1-D numpy array or a
    1-D real tensor that does not require grad. The last entry, within a relative ``1e-6`` of
    ``end`` (float32 rounding: ``float(torch.tensor(0.1)) > 0.1``), is taken as ``end``; the
    others stay as given (taken as ``end`` too, two times close to it were one).
    """
    slack = 1e-6
    if isinstance(times, np.ndarray):
        times = torch.from_numpy(times)
    if isinstance(times, Tensor):
        check_has_data(times, "times")
        if times.dim() != 1 or times.dtype == torch.bool or times.is_complex():
            raise TypeError(
                "times must be a sequence or a 1-D real tensor of times, got a tensor of shape "
                f"{tuple(times.shape)} and dtype {times.dtype}"
                + ("; for one time use times=[t]" if times.dim() == 0 else "")
                + ("; a field such as a direction is a keyword argument, "
                   "flow(u0, surface, direction=T)" if times.dim() >= 4 else "")
            )
        if times.requires_grad:
            raise ValueError(
                "times must not require grad: the output times are not differentiable "
                "(learn_time=True makes the flow's end time learnable)"
            )
        times = list(times.detach().cpu().unbind())
    elif isinstance(times, (str, bytes, set, frozenset, dict)) or not hasattr(times, "__iter__"):
        raise TypeError(
            "times must be a sequence or a 1-D real tensor of times, got "
            f"{times!r} ({type(times).__name__})"
            + ("; for one time use times=[t]" if isinstance(times, numbers.Real) else "")
        )
    times = list(times)  # a generator is read once (it had been used up by the check below)
    for i, t in enumerate(times):
        if isinstance(t, Tensor) and t.requires_grad:
            raise ValueError(
                f"times[{i}] requires grad: the output times are not differentiable "
                "(learn_time=True makes the flow's end time learnable)"
            )
    values = [check_nonnegative(t, f"times[{i}]") for i, t in enumerate(times)]
    if not values:
        raise ValueError("times must hold at least one time, got an empty sequence")
    for i, (a, b) in enumerate(zip(values, values[1:], strict=False)):
        if b <= a:
            raise ValueError(
                f"times must increase strictly, got times[{i}] = {a:g} then times[{i + 1}] = {b:g}"
            )
    if values[-1] > end * (1 + slack):
        raise ValueError(f"times must not exceed the flow's time {end:g}, got {values[-1]:g}")
    if len(values) > 1 and values[-2] >= end:
        raise ValueError(f"times must not exceed the flow's time {end:g} before their last, got "
                         f"times[{len(values) - 2}] = {values[-2]:g}")
    return values[:-1] + [end if values[-1] > end * (1 - slack) else values[-1]]


PACKED_METHODS = ("rkc", "euler", "heun")
"""The methods whose steps a flow may take on packed band and ring values
(:meth:`Flow.packed_system`)."""

REEXTEND_CHOICES = ("auto",)


def _entry_surface(surface: ImplicitSurface, entry: int) -> ImplicitSurface:
    """Entry ``entry`` of a dense batch as a surface of its own (its ``phi`` a slice, in
    ``phi``'s graph), kept on ``surface`` unless ``phi`` requires grad."""

    def build() -> ImplicitSurface:
        def entry_surface() -> ImplicitSurface:
            return ImplicitSurface(surface.phi[entry:entry + 1], surface.grid,
                                   band_width=surface.band_width, eps=surface.eps)

        if torch.compiler.is_compiling():  # traced: no checks that warn, no context to set
            return entry_surface()
        with warned_already():  # the batch's surface warned about this phi already
            return entry_surface()

    if surface.phi.requires_grad:
        return build()
    return surface.kept(("entry surface", entry), build)


def torchdiffeq_segment(band_cells: float, rho: float) -> float:
    """The longest piece a torchdiffeq method integrates between re-extensions of the band,
    physical time: as long as an RKC step may hold the ring (:func:`held_ring_bound` over
    ``rho``), and at least the ``12 / rho`` the fastest diffusion takes to cross a
    cell. Pieces of ``12 w^2 / rho`` (the diffusion across the whole band) let the band's level
    sets drift apart from S's: rk4 on the l = 2 sphere harmonic erred 1.3e-3, 7.7e-4, 6.0e-4,
    3.2e-4 at 33^3-81^3 against RKC's 1.2e-3, 5.1e-4, 2.7e-4, 1.6e-4."""
    return max(12.0, held_ring_bound(band_cells)) / rho


def data_shape(surface: ImplicitSurface, batch: int, channels: int) -> tuple[int, ...]:
    """Shape of ``channels`` of data on ``surface``: ``(batch, C, D, H, W)``, or on a
    :class:`~torchsurf.bricks.BrickSurface` the packed ``(N, C, 8, 8, 8)``, which holds every
    entry (``batch`` must then be 1 or the surface's batch size)."""
    batch = check_count(batch, "batch")
    if surface.layout is None:
        return (batch, channels, *surface.grid.shape)
    if batch not in (1, surface.batch_size):
        raise ValueError(
            f"batch={batch}: a packed field on this BrickSurface holds its {surface.batch_size} "
            "entries, one data entry each; use batch=1 (or the surface's batch size)"
        )
    return (len(surface.layout), channels, BRICK, BRICK, BRICK)


def check_band_holds_nodes(band: Tensor, width: float, spacing: float,
                           layout: BrickLayout | None = None) -> None:
    """Raise ``ValueError`` naming ``band_width`` when the flow's ``band`` (dense
    ``(B, 1, D, H, W)`` or packed on ``layout``) holds no node in some batch entry: that entry
    would come back unchanged."""
    if layout is None:
        held = band.flatten(1).any(dim=1)
    else:
        held = torch.zeros(layout.batch_size, dtype=torch.bool, device=band.device)
        held[layout.batch.to(band.device)[band.flatten(1).any(dim=1)]] = True
    if bool(held.all()):
        return
    where = ("" if len(held) == 1
             else f" in batch entr{'y' if int((~held).sum()) == 1 else 'ies'} "
                  f"{(~held).nonzero().flatten().tolist()}")
    raise ValueError(
        f"the flow's band holds no node{where}: band_width={width:g} is {width / spacing:.2f} "
        f"cells of this grid and no node lies that close to S; widen band_width (at "
        f"least {MIN_BAND_CELLS} cells with re-extension)"
    )


def check_times_of_learned_time(time_value: Positive, times: object) -> None:
    """Refuse ``times=`` for a learned time without ``max_time`` (see :class:`Flow`)."""
    if times is not None and time_value.learnable and time_value.bound is None:
        raise ValueError(
            "times= with learn_time=True needs max_time: the requested times are fractions of "
            "max_time applied to the learned time. Without it they would be fractions of the "
            "parameter's current value, read anew at each call, and the gradient of the result "
            "would not be its derivative"
        )


def _diagonal_cells(surface: ImplicitSurface) -> float:
    grids = surface.grids if surface.layout is not None else (surface.grid,)
    return max(math.dist(grid.shape, (1, 1, 1)) for grid in grids)


def _learned_time(system: System, time: float | Tensor, nominal: float) -> None:
    """Make ``system`` integrate a learned ``time`` over the float time ``nominal >= time``.

    With ``s = t nominal / time``, ``du/ds = (time / nominal) rate(u)``: the integrators see
    plain floats (steps planned on the host, no read of the parameter) and the gradient reaches
    ``time`` through the scale of the rate. Every explicit and implicit step multiplies the rate
    (or ``A``) by its step, so they compute what steps of ``time / count`` would.
    """
    if not isinstance(time, Tensor):
        return
    scale = time / nominal
    rate = system.rate
    system.rate = lambda u: scale * rate(u)
    system.linear_stage = None  # its stages would not scale
    if system.linear is not None:
        operator = system.linear.operator
        system.linear = Linear(lambda x, *params: params[-1] * operator(x, *params[:-1]),
                               (*system.linear.params, scale))
    system.params = (*system.params, scale)



def keep_geometry_before_steps(surface: ImplicitSurface) -> None:
    """Form the surface's haloed geometry before a flow's steps where ``phi`` requires grad:
    formed first inside a traced checkpoint segment, it was kept with that segment's graph, and
    phi's gradient through a compiled flow came out twice the eager one (Euler steps) or the
    recomputation saved other tensors than the forward (``chebyshev``'s pieces)."""
    if surface.phi.requires_grad and torch.is_grad_enabled():
        surface.haloed()


class Flow(nn.Module):
    """Base of the surface flows: integration settings and the call ``flow(u0, surface)``.

    ``state_dict`` holds what a flow learns and the settings given as tensors or sequences (a
    time, diffusivity or contrast per channel, kept as buffers); a setting given as a number is
    a constructor argument, like ``nn.Dropout``'s ``p``, and loading a state leaves it as built.

    Args:
        time: physical end time (world units squared for diffusion); a positive number.
        method: ``"rkc"`` (default), ``"euler"``, ``"heun"``, ``"implicit"``,
            ``"crank_nicolson"`` (linear flows only) or a torchdiffeq method name.
        steps: number of time steps (``None``: for ``"rkc"``, steps no longer than the time
            the fastest diffusion takes to cross the band (:func:`plan_steps`); for
            ``"euler"`` and ``"heun"``, ``1.8 / rho``, 0.9 of the stable step ``2 / rho``,
            rounded so that the steps end exactly at ``time``; for ``"implicit"`` and
            ``"crank_nicolson"``, Euler's stable step ``2 / rho``, 0.9 of explicit Euler's
            count, each a CG solve: give fewer for longer steps, which they take stably, at
            their time error (backward Euler's 2.4x the others' at its default steps on a
            sphere harmonic of degree 3, 33^3), and on a 3-cell band (``from_mesh``, phi
            not a distance) at the error of a ring held stale through each step, which grows
            with ``dt rho`` whatever the grid: steps above ``12 / rho`` there warn); for
            adaptive torchdiffeq
            methods, unused (their step control takes one error norm over the whole state:
            entries of data on one surface, and channels, choose each other's steps, so an
            entry is its run alone only to the solver's tolerance). With
            ``times``, each interval between requested times takes its share of ``steps``
            rounded up, so that no step is longer than ``time / steps``. A run of more
            than ``10**6`` steps or evaluations of the rate (RKC's stages counted) is refused
            before any work; more than ``10**5`` evaluations warn with the count.
        learn_time: make ``time`` an ``nn.Parameter`` (kept positive by softplus).
        max_time: with ``learn_time``, the largest time the flow takes: the learned time is
            clamped to it (no gradient beyond) and the steps are planned for it, so the forward
            reads nothing from the parameter and ``torch.compile`` traces it whole. The band
            is re-extended by the time the diffusion takes, read on the host (the fixed
            flow's schedule); while ``torch.compile`` traces, by ``max_time``'s, more often the
            farther the time lies below it (each re-extension errs a little on thin parts of
            a mesh: keep ``max_time`` within a few times the time there), so compiled and eager
            results differ (6.2e-3 / 9.0e-3 near S at half the bound on noise, unit sphere at
            16^3 / 32^3; 4e-7 at the bound or with ``reextend_every=1``). Eager, the result
            is then piecewise smooth in the time, as without ``max_time``: it jumps where a
            re-extension moves to another step (docs/learning.md). ``None``
            (default): the steps follow the current time, read on the host at each call (a
            graph break). ``times=`` needs ``max_time``: the requested times are fractions
            of ``max_time``, applied to the learned time.
        tolerance, max_iterations: conjugate-gradient stopping rule of the implicit methods.
        options: extra keyword options for torchdiffeq (``rtol``, ``atol``, ``step_size``...),
            their numbers checked by name (:func:`~torchsurf.flows._integrators.check_options`).
            A ``step_size`` (fixed-step methods only) is the longest step: the run takes equal
            steps that end at the last time; one past the method's stable step warns before
            the run. Without it a fixed-step method takes 0.9 of its stable step: of Euler's
            ``2 / rho``, or of its own where shorter (torchdiffeq's Adams methods: 0.003 / rho
            for ``"explicit_adams"``, 0.06 / rho for ``"fixed_adams"`` and ``"implicit_adams"``).
            Adaptive methods stop with an error after ``max_num_steps`` steps in one piece
            (default :data:`~torchsurf.flows._integrators.MAX_STEPS`), and measure their error
            by its root mean square over the band (``norm``, default
            :func:`~torchsurf.flows._integrators.band_norm`; torchdiffeq's own, over the whole
            box, counted the nodes that never change, so that the tolerance was missed more
            the more room the box had). ``steps=`` and a ``step_size`` together are refused.
            ``method="scipy_solver"`` takes scipy's explicit solvers only,
            ``{"solver": "RK45"}`` (or ``"RK23"``, ``"DOP853"``): the stiff ones, LSODA (its
            default) among them, form a dense Jacobian of the whole volume and are refused.
        adjoint: integrate with ``torchdiffeq.odeint_adjoint``.
        progress: show a tqdm progress bar over the steps (tqdm is optional).
        reextend_every: re-extend the band and its ring along normals (closest point,
            tricubic, limited to the range of the nodes around each closest point) every this
            many steps; ``"auto"`` (default) after each step that reaches a new multiple of
            ``12 / rho``, the time the fastest diffusion takes to cross one cell
            (``floor(t rho / 12)`` re-extensions whatever the steps and requested times), or
            after every step where steps are longer (RKC steps that hold the ring: as many
            as one step could hold it for,
            ``floor(6 (w - 2 sqrt(3))^2 / (rho dt))`` on a band of ``w`` cells), and into each
            result at the requested times (docs/band.md). Between
            re-extensions, the torchdiffeq methods re-extend the ring around the band at every
            evaluation of the rate, and RKC, Euler and Heun too unless the band can hold it
            and the rate has no reaction term (docs/band.md). ``None``:
            never (the ring keeps ``u0``: only right for a band as wide as the diffusion
            length).
        band_width: half-width of the evolving band, world units. Default: on a surface
            whose ``phi`` is a distance out to :data:`WIDE_BAND_CELLS` cells and its ring,
            that width; otherwise ``surface.band_width``
            (:meth:`~torchsurf.ImplicitSurface.evolving_widths`).
        checkpoint: keep only ``u`` every ``sqrt(steps)`` steps for backward and recompute
            the stages in between (explicit methods: RKC, Euler, Heun): memory
            ``O(sqrt(steps))`` volumes instead of every stage's, for about 1.3-2x the time.
            ``"auto"`` (default): when autograd records the call (a parameter, ``u0`` or
            ``phi`` requires grad); ``True`` or ``False`` to force.

    Attributes:
        last_plan: the :class:`~torchsurf.flows.Plan` of the last call, the number of steps
            it took (``None`` for adaptive torchdiffeq methods) and their size; ``None``
            before the first call and for methods that take no steps (``"chebyshev"``).
            Where a batch's entries (or a heat flow's channels of different fixed
            diffusivities) are integrated apart, the last one's.
    """

    supports_bricks = False
    """Whether the flow runs on a :class:`~torchsurf.bricks.BrickSurface` (packed fields)."""

    linear: bool | None = None
    """Whether the flow's rate is linear and symmetric in ``u``, as the implicit methods
    (:data:`~torchsurf.flows.IMPLICIT`) need: ``False`` refuses them at construction, ``True``
    takes them, ``None`` (a flow of one's own) leaves it to the system the flow builds (its
    ``linear`` operator), checked at the call."""

    keeps_range = False
    """Whether the flow's equation keeps ``u`` within the range of ``u0`` (a maximum
    principle: heat, flow visualisation, total variation and edge-stopping diffusion). Where it
    does, a call whose result leaves that range by more than :data:`RANGE_SLACK` of it warns
    (``RuntimeWarning``, once per call): the steps and re-extensions were unstable on that
    surface. The range is each batch entry's and channel's, and at least
    :data:`RANGE_ROUNDING` rounding units of its magnitude. Checked for every method,
    ``HeatFlow(method="chebyshev")``'s semigroup too."""

    extra_methods: tuple[str, ...] = ()
    """Methods the flow integrates itself, beyond the built-in integrators and torchdiffeq's."""

    path = "auto"
    """How the stencils run (:data:`torchsurf.backend.PATHS`); flows whose operators take a
    ``path`` set it, and the closest-point re-extension follows it."""

    def __init__(
        self,
        time: float,
        method: str = "rkc",
        steps: int | None = None,
        learn_time: bool = False,
        max_time: float | None = None,
        tolerance: float | None = None,
        max_iterations: int = 1000,
        options: dict | None = None,
        adjoint: bool = False,
        progress: bool = False,
        reextend_every: int | str | None = "auto",
        band_width: float | None = None,
        checkpoint: bool | str = "auto",
    ) -> None:
        super().__init__()
        method = check_method(method, self.extra_methods)
        if method in IMPLICIT and self.linear is False:
            raise ValueError(
                f"method={method!r} solves a linear symmetric system each step; "
                f"{type(self).__name__} is not linear: use 'rkc' (default), 'euler', 'heun' or "
                "a torchdiffeq method")
        self.time_value = Positive(time, "time", learnable=learn_time, bound=max_time,
                                   bound_name="max_time", vector=False)
        self.method = method
        self.steps = None if steps is None else check_count(steps, "steps")
        self.solver = SolverOptions(
            None if tolerance is None else check_positive(tolerance, "tolerance"),
            check_count(max_iterations, "max_iterations"),
        )
        self.adjoint = check_flag(adjoint, "adjoint")
        if method in INTEGRATORS and (options or self.adjoint):
            raise ValueError(
                f"options and adjoint are torchdiffeq settings; method={method!r} is built in "
                "and takes neither"
            )
        self.options = check_options(options, method)
        if self.steps is not None and "step_size" in self.options:
            raise ValueError(f"steps={self.steps} and options['step_size'] both set the steps "
                             "(steps= took precedence without a word); give one of them")
        self.progress = check_flag(progress, "progress")
        if reextend_every is not None and reextend_every not in REEXTEND_CHOICES:
            reextend_every = check_count(reextend_every, "reextend_every")
        self.reextend_every = reextend_every
        if checkpoint != "auto" and not isinstance(checkpoint, bool):
            raise TypeError(f"checkpoint must be True, False or 'auto', got {checkpoint!r}")
        self.checkpoint = checkpoint
        self.band_width = None if band_width is None else check_positive(band_width, "band_width")
        self.last_plan: Plan | None = None

    @property
    def time(self) -> float | Tensor:
        """The end time: a float, or a positive 0-d tensor when learnable."""
        return self.time_value.value()

    def evolving_width(self, surface: ImplicitSurface) -> float:
        """Half-width of the band this flow evolves on ``surface``, world units.

        ``band_width`` when given. Otherwise the surface's
        :meth:`~torchsurf.ImplicitSurface.evolving_widths`: on a dense surface whose ``phi``
        is a distance (``|grad phi|`` within :data:`DISTANCE_TOLERANCE` of its scale) at every
        node out to :data:`WIDE_BAND_CELLS` cells and the ring beyond, that width (an analytic
        distance, a ``redistance``d phi); elsewhere (``sdf.from_mesh``'s 5-cell distances, thin
        features) ``surface.band_width``; on bricks the width their builder stored
        (:func:`torchsurf.bricks.from_dense` stores the dense surface's). Decided for each
        entry of a batch, once per surface and kept (each call while ``phi`` requires grad);
        the entries of a batch of several surfaces are integrated one at a time, each on its
        own band, and this returns the narrowest.
        """
        return min(self._entry_widths(surface))

    def _entry_widths(self, surface: ImplicitSurface) -> tuple[float, ...]:
        """:meth:`evolving_width` of each entry (the entries of a batch of several surfaces
        are integrated one at a time, each on its own band)."""
        if self.band_width is not None:
            surface.check_band_held(self.band_width, "band_width")
            return (self.band_width,)
        return surface.evolving_widths()

    def band_mask(self, surface: ImplicitSurface) -> Tensor:
        """The evolving band, a bool mask ``(B or 1, 1, D, H, W)``: within
        :meth:`evolving_width` of S. Kept on the surface while ``phi`` needs no gradient (a
        learned ``phi`` may change in place between calls)."""
        width = self.evolving_width(surface)
        if surface.phi.requires_grad:
            return surface.band_mask(width)
        return surface.kept(("flow band", width), lambda: surface.band_mask(width))

    def region_mask(self, surface: ImplicitSurface) -> Tensor:
        """:meth:`band_mask` and the ring of nodes its 3x3x3 stencils read, bool like it; kept
        beside the band while ``phi`` needs no gradient (on bricks the dilation is a halo
        gather: 1.5 ms of a 13 ms flow at 35^3)."""
        if surface.phi.requires_grad:
            return with_ring(self.band_mask(surface), surface.layout)
        return surface.kept(("flow region", self.evolving_width(surface)),
                            lambda: with_ring(self.band_mask(surface), surface.layout))

    def operator_bound(self, surface: ImplicitSurface, scheme: str = "octant") -> float:
        """Gershgorin bound of ``Lap_S`` restricted to this flow's band, ``1 / world length^2``."""
        return laplace_beltrami_bound(surface, scheme, self.evolving_width(surface))

    def system(self, u0: Tensor, surface: ImplicitSurface, **inputs: Tensor) -> System:
        """The flow's equation for ``u0`` ``(B, C, D, H, W)`` on ``surface``: a
        :class:`~torchsurf.flows._integrators.System` whose ``rate`` maps volumes of ``u0``'s
        shape to ``du/dt`` (units of ``u`` per unit of time), zero off the band, with the band,
        its spectral bound and what the integrators read. ``inputs`` are the flow's extra inputs
        of ``forward`` (e.g. ``direction=``). Subclasses implement it; ``forward`` calls it."""
        raise NotImplementedError

    def packed_system(self, system: System, u0: Tensor, surface: ImplicitSurface
                      ) -> tuple[System, PackedRegion] | None:
        """The flow's system on packed band and ring values (:class:`PackedRegion`), or
        ``None`` to integrate volumes (the default; :class:`~torchsurf.flows.HeatFlow` packs
        its linear rate when ``phi`` is fixed)."""
        return None

    def _schedule(self, end: float, times: list[float] | None, after_step: object) -> Schedule:
        """``times`` checked by :func:`_check_times`, all ``> 0``, or ``None`` for ``end``:
        floats of the nominal time (:func:`_learned_time`)."""
        return Schedule(
            times=[end] if times is None else times, steps=self.steps,
            solver=self.solver, options=self.options, adjoint=self.adjoint,
            after_step=after_step,
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

    def _reextension_steps(self, schedule: Schedule, longest: float, band_cells: float,
                           rho: float, reaction: bool = False
                           ) -> tuple[Callable[[int], bool] | None, int]:
        """Which steps (from 1) end with a re-extension of the band (``None``: none), and
        the most steps between two: ``longest`` the planned step (the integrator's time;
        requested times split some), ``band_cells`` the band's width in cells, ``rho`` the
        spectral radius of the rate the steps integrate (:meth:`_share_of_planned_rate`),
        ``reaction`` :attr:`System.reaction`."""
        if self.reextend_every is None:
            return None, 1
        if self.reextend_every != "auto":
            every = self.reextend_every
            return (lambda k: k % every == 0), every
        if self.method not in ("euler", "heun", "rkc", *IMPLICIT):
            return (lambda k: True), 1
        shortest = shortest_step(schedule)
        crossing = 12.0 / rho  # the time the fastest diffusion takes to cross one cell
        if self.method == "rkc" and ring_held("rkc", longest * rho, band_cells,
                                               reaction=reaction):
            # the ring is held as long as one step could hold it (held_ring_bound): short
            # steps, taken for their time error, share one re-extension, once every
            # steps_held planned steps by the time reached, not by the steps counted (requested
            # times split the steps: counted, they added re-extensions, and moved a
            # Perona-Malik flow's u(T) by 0.05 near S), and before the ring would be held
            # longer than it can be
            held = held_ring_bound(band_cells) / rho
            steps_held = math.floor(held / longest * (1 + 1e-9))
            if steps_held * longest >= crossing:
                marks = _marks_by_time(step_ends(schedule), steps_held * longest, held)
                return marks.__contains__, _most_steps_between(marks, len(step_ends(schedule)))
        # once a crossing time, by the time reached, not a whole number of steps: a period of
        # floor(12 / (rho dt)) steps re-extended at every step where 12 / (rho dt) lay in
        # [1, 2) (a TV flow's result swung by 0.003-0.2 as RKC's steps went from 12 to 64 on a
        # torus), and steps split by requested times shortened it
        ends = step_ends(schedule)
        slack = TIME_ROUNDING * ends[-1]  # float32 requested times: a crossing one step early
        crossed = [math.floor((t + slack) / crossing) for t in [0.0, *ends]]
        marks = {k for k in range(1, len(ends) + 1) if crossed[k] > crossed[k - 1]}
        return marks.__contains__, max(1, math.ceil(crossing / shortest * (1 + 1e-9)))

    def _share_of_planned_rate(self) -> float:
        """The share, in ``(0, 1]``, of the rate the steps were planned for that the flow
        integrates: a learned time given ``max_time`` runs over ``[0, max_time]`` at
        ``time / max_time`` of the rate (:func:`_learned_time`). Read on the host, 1 while
        ``torch.compile`` traces (:meth:`Positive.share_of_bound`)."""
        return self.time_value.share_of_bound()

    def _warned_kinds(self) -> set[str] | None:
        """The kinds of warning this flow gave (:func:`~torchsurf.flows._integrators.first_warning`):
        each once a flow (a channel group's copy: the flow's own). ``None`` (every one given)
        while ``torch.compile`` traces."""
        if torch.compiler.is_compiling():
            return None
        owner = self.__dict__.get("_part_of", self)
        return owner.__dict__.setdefault("_warned", set())

    def _checkpointing(self, u0: Tensor, surface: ImplicitSurface, system: System) -> bool:
        if self.checkpoint != "auto":
            return self.checkpoint
        if not torch.is_grad_enabled():
            return False
        learned = any(p.requires_grad for p in self.parameters())
        return learned or u0.requires_grad or surface.phi.requires_grad or bool(system.params)

    def _after_step(self, surface: ImplicitSurface, region: Tensor, bar: object | None,
                    reextends: Callable[[int], bool] | None,
                    packing: PackedRegion | None = None):  # noqa: ANN202
        """The schedule's ``after_step`` and ``output`` hooks: the progress bar, and the band's
        re-extension after the steps ``reextends`` names and at each requested time (there into the result
        only, so that the results do not depend on which times were requested); on packed
        values with ``packing``."""
        hooks = []
        if bar is not None:
            hooks.append(lambda u, k: (bar.update(1), u)[1])
        output = None
        if reextends is not None:
            stencil = kept_stencil(surface, self.evolving_width(surface), "region",
                                   region, region, limited=True)
            path = self.path
            if packing is None:
                def extended(u: Tensor) -> Tensor:
                    return reextend(stencil, u, path)
            else:
                extended = packing.stencil(stencil).apply

            def periodic(u: Tensor, k: int) -> Tensor:
                return extended(u) if reextends(k) else u

            def output(u: Tensor, k: int | None) -> Tensor:
                return u if k is not None and reextends(k) else extended(u)

            hooks.append(periodic)
        if not hooks:
            return None, output

        def after_step(u: Tensor, k: int) -> Tensor:
            for hook in hooks:
                u = hook(u, k)
            return u

        return after_step, output

    def _check_memory(self, u0: Tensor, surface: ImplicitSurface, band: Tensor,
                      snapshots: int = 0) -> None:
        """Raise ``MemoryError`` before any work if the call cannot fit (:mod:`torchsurf._memory`;
        ``snapshots``: the requested times, whose results are all returned); not while
        ``torch.compile`` traces (the band's size and the memory are host reads)."""
        if torch.compiler.is_compiling():
            return
        cached = (not surface.phi.requires_grad
                  and surface.is_kept(stencil_key(self.evolving_width(surface), "region", True)))
        band_nodes = None if cached else int(band.sum())
        _memory.check_fits(
            _memory.flow_bytes(tuple(u0.shape), surface.batch_size, u0.dtype,
                               self.method in IMPLICIT, band_nodes, snapshots),
            f"{type(self).__name__} on u0 of shape {tuple(u0.shape)}", u0.device,
        )

    @saved_plainly_in_checkpoints
    def forward(
        self, u0: Tensor, surface: ImplicitSurface,
        times: Sequence[float] | Tensor | np.ndarray | None = None,
        **inputs: Tensor,
    ) -> Tensor:
        """Integrate from ``u0`` to the end time.

        Args:
            u0: initial data ``(B, C, D, H, W)``; ``surface`` has batch 1 or B. Values are read
                in the band and the ring of nodes around it; elsewhere they are returned as
                they are.
            surface: the implicit surface.
            times: optional increasing times in ``[0, time]`` to return ``u`` at: a sequence
                of numbers, a 1-D numpy array or a 1-D tensor (not requiring grad), e.g.
                ``torch.linspace(0, time, 5)``; ``u`` at time 0 is ``u0``. The steps are
                planned for ``time`` (requested times split them), and without ``steps=`` no
                step before a requested time is longer than a call to that time alone would
                take, so an early time is as accurate as such a call (it was reached in the
                few long steps planned for ``time``: 0/1 data at 2 h^2 of 10 h^2, 9.7e-2
                against 8.5e-3 alone; now 2.8e-3). Evenly spaced times add a few steps early
                on (20 times: at most 3 steps a time). torchdiffeq's methods integrate
                pieces between the band's re-extensions, and a requested time splits one: its
                result differs from a call to that time alone by the re-extensions' placement,
                which more steps hardly reduce, though it is small (``rk4``, 60 / 120 / 240
                steps, ``exact.sphere_harmonic(2, 33)``, ``T = 0.05``, ``u(0.37 T)`` of
                ``times=[0.37 T, T]`` against a call to ``0.37 T`` with 0.37 times the steps:
                3.3e-6 / 2.7e-6 / 2.4e-6 of the data's largest value near S, against 7.8e-4
                from the exact decay; ``times=[0.37 T]`` alone: 7.5e-10 to 7.3e-12). That is
                on a 5-cell band; on a 3-cell band one re-extension moves the data more: a
                sphere of radius 0.6 at 24^3, l = 3, ``rk4`` with 60 steps, ``u(0.3 T)`` 5.0e-4
                from the call to ``0.3 T`` alone, about 6% of the flow's own error there (an
                audit, 2026-12-07); times on a piece's boundary give the same result.
            inputs: flow-specific inputs (e.g. ``direction`` for tangent-field flows).

        Returns:
            ``u(time)`` ``(B, C, D, H, W)``, or ``(T, B, C, D, H, W)`` for ``T`` ``times``.

        Raises:
            FloatingPointError: the integration diverged (NaN or infinity in the band).
            MemoryError: before any work, when a lower bound of the memory the call needs
                exceeds the memory available (:mod:`torchsurf._memory`).

        Warns:
            RuntimeWarning: a flow that keeps ``u`` within the range of ``u0``
                (:attr:`keeps_range`) left it by more than :data:`RANGE_SLACK` of it: unstable
                steps on that surface (docs/band.md, section 5). This and the warnings of the
                steps' plan (an unstable or too long step, a long run) are each given once a
                flow: their numbers change with a learned time, and Python's filter, once per
                text, printed one a training iteration.
        """
        times = list(times) if isinstance(times, Iterator) else times  # read once
        run_as_is_first(self, u0, surface, times, **inputs)
        check_surface(surface)
        refuse_transforms(type(self).__name__, u0, *inputs.values(), phi=surface.phi,
                          forward_mode=self.method in PACKED_METHODS,
                          why=f"method={self.method!r}: the explicit methods 'euler', 'heun' and "
                              "'rkc' have one")
        if surface.layout is not None and not self.supports_bricks:
            raise NotImplementedError(
                f"{type(self).__name__} does not run on a BrickSurface (its supports_bricks "
                "is False; every flow of torchsurf.flows does): use the dense ImplicitSurface "
                "(docs/bricks.md)"
            )
        check_data(u0, "u0", surface)
        check_learned_values(self, u0, "u0", type(self).__name__)
        check_times_of_learned_time(self.time_value, times)
        keep_geometry_before_steps(surface)
        separately = self._entries_apart(u0, surface, times, inputs)
        if separately is not None:
            return separately
        end = self.time_value.maximum()  # a host read only for a learned time without max_time
        wanted = None if times is None else _check_times(times, end)
        width = self.evolving_width(surface)
        if self.reextend_every is not None:
            check_reextension_width(width, surface.spacing, " (or reextend_every=None with a "
                                    "band as wide as the diffusion length)")
        band = self.band_mask(surface)
        if not torch.compiler.is_compiling():
            check_band_holds_nodes(band, width, surface.spacing, surface.layout)
        self._check_memory(u0, surface, band, 0 if wanted is None else len(wanted))
        # before the flow's system, whose bounds read u0 (reaction-diffusion's)
        region = self.region_mask(surface)
        check_finite(torch.where(region, u0, 0.0), "u0 (in the band and its ring)")
        system = self.system(u0, surface, **inputs)
        if system.band is band:
            system.region = region
        system.layout = surface.layout
        system.path = getattr(self, "path", "auto")
        band, region = system.band, system.region
        packing = None
        if self.method in PACKED_METHODS and self.reextend_every is not None:
            packed = self.packed_system(system, u0, surface)
            if packed is not None:
                system, packing = packed
        _learned_time(system, self.time, end)
        # re-extension's stencils read phi itself, not only the geometry computed from it
        system.params = (*system.params, surface.phi)
        if self.method in IMPLICIT and system.linear is None:
            raise ValueError(
                f"method={self.method!r} needs a linear symmetric flow; {type(self).__name__} "
                "is not: use 'rkc', 'euler', 'heun' or a torchdiffeq method"
            )
        initial = [] if wanted is None else [u0 for t in wanted if t == 0]
        if wanted is not None and len(initial) == len(wanted):
            return torch.stack(initial)
        wanted = None if wanted is None else wanted[len(initial):]
        plan = plan_steps(self.method, system, end, self.steps,
                          band_cells=width / surface.spacing,
                          diagonal_cells=_diagonal_cells(surface),
                          step_size=self.options.get("step_size"), warned=self._warned_kinds())
        schedule = self._schedule(end, wanted, None)
        schedule.step = plan.step
        # torchdiffeq's equal steps do not stop at requested times: its count stands
        built_in = self.method in INTEGRATORS
        if built_in and len(schedule.times) > 1 and self.steps is None and plan.count is not None:
            # no step up to a requested time longer than a flow to that time alone would take:
            # RKC's fewest steps bound the time error of the modes not yet decayed
            schedule.fewest = functools.partial(_fewest_steps, self.method, system,
                                                width / surface.spacing)
            plan = Plan(steps_taken(schedule), plan.step)
        elif built_in and len(schedule.times) > 1 and plan.count is not None:
            plan = Plan(steps_taken(schedule), plan.step)
        self.last_plan = plan
        bar = self._progress_bar(plan.count if built_in else None)
        # the band is re-extended by the time the diffusion takes, not by the steps planned
        # for a bound: a learned time at a tenth of max_time re-extended ten times as often
        # (0.39 off the fixed flow on a 40^3 bunny)
        rho = system.spectral_radius * self._share_of_planned_rate()
        reextends, gap = self._reextension_steps(schedule, plan.step, width / surface.spacing,
                                                 rho, system.reaction)
        schedule.after_step, schedule.output = self._after_step(surface, region, bar, reextends,
                                                                packing)
        schedule.segment = torchdiffeq_segment(width / surface.spacing, rho)
        schedule.checkpoint = self._checkpointing(u0, surface, system)
        held = ring_held(self.method, plan.step * rho, width / surface.spacing, period=gap,
                         reaction=system.reaction)
        if self.reextend_every is not None and not held:
            ring = kept_stencil(surface, width, "ring", region & ~band, region, limited=True)
            path = self.path
            fill = ((lambda u: reextend(ring, u, path)) if packing is None
                    else packing.stencil(ring).apply)
            if self.method in IMPLICIT:
                system.refresh_ring = fill
            else:
                rate = system.rate
                system.rate = lambda u: rate(fill(u))
                if system.linear_stage is not None:
                    system.linear_stage = system.linear_stage.filled(fill)
        # nodes beyond the band and its ring are never read, but a rate computed on the whole
        # volume and masked after still takes their derivatives: 0 * NaN in a backward
        recorded = torch.is_grad_enabled()
        if packing is not None:
            start = packing.pack_region(u0)
        else:
            start = torch.where(region, u0, 0.0) if recorded else u0
        try:
            result = integrate(self.method, system, start, schedule)
        finally:
            if bar is not None:
                bar.close()
        # checked on the packed values where they are one volume's (the region's nodes alone)
        checked = (start, result) if packing is not None and packing.entries == 1 else None
        if packing is not None:
            result = [packing.unpack_onto(value, u0, region) for value in result]
        elif recorded:
            result = [torch.where(region, value, u0) for value in result]
        if not torch.compiler.is_compiling():  # a host read: it would break a traced graph
            for value in (result if checked is None else checked[1]):
                finite = (torch.isfinite(value.detach()) if checked is not None
                          else torch.isfinite(torch.where(region, value.detach(), 0.0)))
                if not bool(finite.all()):
                    other = "" if self.method == "rkc" else "method='rkc', "
                    raise FloatingPointError(
                        f"{type(self).__name__} (method={self.method!r}, {_steps_taken(plan)}) "
                        f"diverged: u holds NaN or infinity in the band though u0 did not; use "
                        f"{other}more steps, or smaller parameters"
                    )
            if self.keeps_range:
                excess = (_range_excess(u0, result, region, band, surface.layout is not None)
                          if checked is None
                          else _packed_range_excess(*checked, packing.band_count))
                gathered = self._gathered_excesses()
                if gathered is not None:  # one entry of a batch: its caller warns
                    gathered.append((excess, plan))
                elif excess > RANGE_SLACK:
                    _warn_range_left(self, excess, plan)
        return result[-1] if times is None else torch.stack(initial + result)

    def _entries_apart(self, u0: Tensor, surface: ImplicitSurface, times: object,
                       inputs: dict[str, Tensor]) -> Tensor | None:
        """The result of integrating each entry of a batch of several surfaces alone, else
        ``None``: each entry's band, bound, steps and re-extensions are then its own, and its
        result what it would be without the others (a shared plan, from the batch's largest
        bound, left an off-centre sphere 2.6e-4 off its run alone beside a box; alone, dense
        batches of four shapes at 48^3 took 0.96-1.08x the time of the shared plan)."""
        if surface.batch_size == 1:
            return None
        if surface.layout is not None:
            return self._each_entry(u0, surface.entries(), len(surface.layout), times, inputs)
        entries = ((torch.tensor([b], device=u0.device), _entry_surface(surface, b))
                   for b in range(surface.batch_size))
        return self._each_entry(u0, entries, surface.batch_size, times, inputs)

    def _each_data_entry(self, u0: Tensor, surface: ImplicitSurface, times: object,
                         inputs: dict[str, Tensor]) -> Tensor:
        """Data of several entries on one dense surface, each integrated alone: for flows whose
        plan reads the data (each entry's steps then follow its own data)."""
        count = u0.shape[0]
        entries = ((torch.tensor([b], device=u0.device), surface) for b in range(count))
        return self._each_entry(u0, entries, count, times, inputs)

    def _each_entry(self, u0: Tensor, entries: Iterator[tuple[Tensor, ImplicitSurface]],
                    count: int, times: object, inputs: dict[str, Tensor]) -> Tensor:
        """A batch's entries ``(rows of u0 along its first dimension of size count, surface)``
        (the bricks of an entry, or a dense entry's own surface), each integrated
        alone with its own band, steps and stages: each entry's result is what it would be
        without the others. A ``ValueError`` of an entry is raised naming the entry."""
        result = None
        excesses, gathering = self._gather_excesses()
        try:
            for index, (rows, entry) in enumerate(entries):
                own = {name: value[rows] if isinstance(value, Tensor)
                       and value.shape[:1] == (count,) else value
                       for name, value in inputs.items()}
                try:
                    part = self.forward(u0[rows.clamp(max=u0.shape[0] - 1)], entry, times, **own)
                except ValueError as error:
                    raise ValueError(f"batch entry {index}: {error}") from error
                result = placed(result, part, rows, count, -5)
        finally:
            self._stop_gathering(gathering)
        self._warn_gathered(excesses, gathering)
        return result

    def _gather_excesses(self) -> tuple[list[tuple[float, Plan | str]], Token | None]:
        """Start gathering the range excesses of the runs a call makes apart (batch entries,
        channels) for one warning: the list, and the token ending it where this call started
        it (``None`` where a caller running parts apart already gathers them, or while
        ``torch.compile`` traces: traced calls check no range). The lists live in a context
        variable of this thread's, not on the module, which other threads may be calling."""
        gathered = self._gathered_excesses()
        if gathered is not None or torch.compiler.is_compiling():
            return ([] if gathered is None else gathered), None  # gathered by an outer call
        excesses: list[tuple[float, Plan | str]] = []
        owner = self.__dict__.get("_part_of", self)
        return excesses, _GATHERED_EXCESSES.set((*_GATHERED_EXCESSES.get(), (owner, excesses)))

    def _gathered_excesses(self) -> list[tuple[float, Plan | str]] | None:
        """The list this flow's runs gather their excesses into, or ``None`` outside such a
        run (:meth:`_gather_excesses`), and while ``torch.compile`` traces (dynamo cannot trace
        a context variable's get; traced calls check no range)."""
        if torch.compiler.is_compiling():
            return None
        owner = self.__dict__.get("_part_of", self)  # a copy running part of a call
        return next((excesses for flow, excesses in _GATHERED_EXCESSES.get() if flow is owner),
                    None)

    def _stop_gathering(self, token: Token | None) -> None:
        """End what :meth:`_gather_excesses` started, where this call started it."""
        if token is not None:
            _GATHERED_EXCESSES.reset(token)

    def _warn_gathered(self, excesses: list[tuple[float, Plan | str]], token: Token | None
                       ) -> None:
        """Where this call gathered the excesses, warn once for the worst past
        :data:`RANGE_SLACK`."""
        worst = max(excesses, key=lambda pair: pair[0], default=None)
        if token is not None and worst is not None and worst[0] > RANGE_SLACK:
            _warn_range_left(self, *worst)

    def extra_repr(self) -> str:
        return f"method={self.method!r}, steps={self.steps}"
