"""Time integrators of the flows, chosen by name from :data:`INTEGRATORS` (or torchdiffeq).

A flow hands the integrator a :class:`System`: the right-hand side ``du/dt`` (zero outside the
band), a bound ``rho`` of the spectral radius of its Jacobian on the band, an optional
projection applied after every step (renormalisation of unit vectors) and, for linear flows
``W du/dt = A u`` with ``A`` symmetric negative semi-definite, the operator ``A`` so that
implicit steps can use conjugate gradients. Nodes outside the band keep their values during a
step (a Dirichlet condition on the band's edge), which keeps the band-restricted ``A``
symmetric; the flow refreshes them between steps (:class:`Schedule`'s ``after_step``).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from .. import backend, stencils
from .._checks import check_count, check_nonnegative, check_positive
from .._stack import caller_stacklevel
from ..bricks.layout import BrickLayout
from ..surface import power_of_two_below
from ._recompute import declared, independent, recomputed
from ._rkc import MAX_STAGES, LinearStage, largest_step_times_rho, rkc_step, rkc_step_linear, stages_for
from ._solve import SolverOptions, solve_symmetric

Rate = Callable[[Tensor], Tensor]


def tensors(*values: object) -> tuple[Tensor, ...]:
    """The tensors among ``values`` that require grad (what ``odeint_adjoint`` differentiates)."""
    return tuple(v for v in values if isinstance(v, Tensor) and v.requires_grad)


def with_ring(band: Tensor, layout: BrickLayout | None = None) -> Tensor:
    """``band`` ``(B, 1, D, H, W)`` bool and every node a 3x3x3 stencil on it reads.

    The 3x3x3 dilation as three 1-D ones (max_pool3d took 13 ms at 81^3 on one thread). With
    ``layout``, ``band`` is packed ``(N, 1, 8, 8, 8)`` on it (:meth:`BrickLayout.dilate`).
    """
    if layout is not None:
        return layout.dilate(band)
    if torch.compiler.is_compiling():
        return _with_ring_traced(band)
    grown = band
    for dim in (2, 3, 4):
        length = grown.shape[dim]
        if length < 2:
            continue
        result = grown.clone()
        result.narrow(dim, 1, length - 1).logical_or_(grown.narrow(dim, 0, length - 1))
        result.narrow(dim, 0, length - 1).logical_or_(grown.narrow(dim, 1, length - 1))
        grown = result
    return grown


def _with_ring_traced(band: Tensor) -> Tensor:
    """:func:`with_ring` for a traced graph: in uint8, whose masked loads inductor's CPU code
    generation vectorises (the in-place ORs of bool views did not compile in torch 2.13)."""
    grown = band.to(torch.uint8)
    for dim in (2, 3, 4):
        if grown.shape[dim] < 2:
            continue
        before, after = stencils.replicated_shifts(grown, dim)
        grown = torch.maximum(torch.maximum(before, after), grown)
    return grown > 0


def zero_outside(value: Tensor, outside: Tensor) -> Tensor:
    """``value`` with zeros where ``outside`` (bool, broadcastable), for a flow's rate.

    ``value`` must be a tensor the caller owns (an operator's fresh result): it is filled in
    place unless autograd records it (then a new tensor), which saves a full-volume
    allocation and pass an evaluation against ``torch.where``.
    """
    if torch.is_grad_enabled() and value.requires_grad:
        return value.masked_fill(outside, 0.0)
    return value.masked_fill_(outside, 0.0)


@dataclass
class Linear:
    """A linear symmetric flow ``W du/dt = A u`` (``L = W^-1 A``, docs/band.md).

    Attributes:
        operator: ``(x, *params) -> A x``, symmetric negative semi-definite on volumes
            ``(B, C, D, H, W)``, reading every tensor it depends on from ``params``.
        params: those tensors; ``params[0]`` is ``W = |grad phi|`` ``(B or 1, 1, D, H, W)``.
    """

    operator: Callable[..., Tensor]
    params: tuple[Tensor, ...]


@dataclass
class System:
    """What an integrator needs from a flow.

    Attributes:
        rate: ``u -> du/dt``, zero outside ``band``.
        band: ``(B or 1, 1, D, H, W)`` bool mask of the nodes that evolve.
        spectral_radius: ``rho``, an upper bound of the spectral radius of ``rate``'s Jacobian
            on the band, ``1 / time``.
        project: applied to the start and after every step (e.g. ``u / |u|``; by
            torchdiffeq's methods to the start, between their pieces and at the requested
            times), or ``None``.
        linear: the symmetric linear form, for the implicit integrators; ``None`` if nonlinear.
        params: tensors ``rate`` reads that may need gradients (for ``odeint_adjoint`` and
            the recomputed segments of a checkpointed run, which check that no other is read);
            those computed from others among them are dropped where they are differentiated
            (:func:`~torchsurf.flows._recompute.independent`).
        layout: the :class:`~torchsurf.bricks.BrickLayout` of packed fields, or ``None``.
        growth: a bound of the fastest growth the rate allows (a positive eigenvalue of its
            Jacobian, ``1 / time``; e.g. a reaction term), 0 for none: RKC steps keep
            ``step * growth`` at most :data:`RKC_GROWTH`.
        path: how the integrator's own kernels run (RKC's stage combinations;
            :data:`torchsurf.backend.PATHS`), the flow's ``path``.
        refresh_ring: applied by the implicit methods before each step (the ring re-extended
            from the band), or ``None`` where they hold the ring between re-extensions.
        linear_stage: for a linear rate, its RKC stages each in one pass
            (:class:`~torchsurf.flows._rkc.LinearStage`), used where it applies; or ``None``.
        isotropic: the rate diffuses along every tangent direction (the Laplace-Beltrami
            operator), so re-extending the band often stays stable on thin and folded surfaces
            (docs/band.md, section 5): RKC steps that refresh the ring are then no longer than
            :data:`RKC_REFRESHED_STEP`. Operators that leave a direction undamped (rank one
            along a field, edge stopping) grew with each re-extension there and keep longer steps.
        stiffness: what besides the surface's operator sets ``spectral_radius`` (a flow's
            parameter, such as total variation's ``eps``), named where a run is refused or
            warned about as long; ``None``: nothing.
        reaction: the rate moves values pointwise besides diffusing them (a reaction term):
            the ring, set from S's values, must follow at every evaluation and is never held
            between re-extensions (:func:`ring_held`). Held, it pulled a reaction-diffusion
            flow's band back: on constant data, whose exact flow is the reaction's ODE, Heun
            stayed 1.1e-4-1.4e-4 off at 287-800 steps (24^3; 2.4e-5 and 3.0e-6 now).
    """

    rate: Rate
    band: Tensor
    spectral_radius: float
    project: Callable[[Tensor], Tensor] | None = None
    linear: Linear | None = None
    params: tuple[Tensor, ...] = field(default_factory=tuple)
    layout: BrickLayout | None = None
    growth: float = 0.0
    path: str = "auto"
    refresh_ring: Callable[[Tensor], Tensor] | None = None
    isotropic: bool = False
    linear_stage: LinearStage | None = None
    stiffness: str | None = None
    reaction: bool = False
    _region: Tensor | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.spectral_radius > 0 or not math.isfinite(self.spectral_radius):
            raise ValueError(
                f"the flow's operator has no finite positive spectral bound "
                f"({self.spectral_radius!r}): is its band empty?"
            )

    @property
    def stable_step(self) -> float:
        """The largest stable forward-Euler (and Heun) step, ``2 / rho``, physical time."""
        return 2.0 / self.spectral_radius

    @property
    def explicit_step(self) -> float:
        """Euler's and Heun's default step, :data:`EXPLICIT_STEP_FRACTION` of
        :attr:`stable_step` (``1.8 / rho``), physical time."""
        return EXPLICIT_STEP_FRACTION * self.stable_step

    @property
    def region(self) -> Tensor:
        """The band and the ring of nodes its 3x3x3 stencils read, a bool mask like ``band``."""
        # kept by hand: functools.cached_property takes a lock, which torch.compile cannot trace
        if self._region is None:
            self._region = with_ring(self.band, self.layout)
        return self._region

    @region.setter
    def region(self, value: Tensor) -> None:
        """The ring computed and kept by the caller (:meth:`Flow.region_mask`): it must be
        :func:`with_ring` of :attr:`band`."""
        self._region = value


@dataclass
class Schedule:
    """How to walk from time 0 through ``times``: ``steps`` per interval, or automatic.

    Attributes:
        times: increasing end times (floats or 0-d tensors), physical time.
        steps: total number of steps over ``[0, times[-1]]``, or ``None`` for ``step``.
        step: the step size when ``steps`` is ``None`` (:func:`plan_steps`), physical time.
        solver: the conjugate-gradient stopping rule (implicit integrators).
        options: extra keyword options passed to torchdiffeq.
        adjoint: use ``torchdiffeq.odeint_adjoint``.
        after_step: ``(u, step_index) -> u`` hook (progress bar, re-extension), or ``None``.
        output: ``(u, step_index) -> u`` applied to ``u`` at each requested time before it is
            returned, not to the state integrated on (a final re-extension), or ``None``;
            ``step_index`` is ``None`` for a time inside a step.
        fewest: ``(length, end) -> steps``: the fewest steps the interval of ``length`` that
            ends at the requested time ``end`` (physical time) takes when ``steps`` is
            ``None``, or ``None``.
        segment: torchdiffeq methods integrate pieces no longer than this (physical time) and
            call ``after_step`` between them; ``None``: one piece.
        checkpoint: the explicit methods (RKC, Euler, Heun) keep for backward only ``u`` at
            the start of each group of about ``sqrt(steps)`` steps and recompute the group's
            stages in backward (:func:`~torchsurf.flows._recompute.recomputed`: the forward
            runs without a graph): memory ``O(sqrt(steps))`` volumes instead of every
            stage's, for about 1.3-2x the time.
    """

    times: Sequence[float | Tensor]
    steps: int | None = None
    step: float | None = None
    solver: SolverOptions = field(default_factory=SolverOptions)
    options: dict = field(default_factory=dict)
    adjoint: bool = False
    after_step: Callable[[Tensor, int], Tensor] | None = None
    output: Callable[[Tensor, int], Tensor] | None = None
    segment: float | None = None
    checkpoint: bool = False
    fewest: Callable[[float, float], int] | None = None


def _value(time: float | Tensor) -> float:
    return float(time.detach()) if isinstance(time, Tensor) else float(time)


def eps_stiffness(eps: float, largest: float, spacing: float) -> str:
    """:attr:`System.stiffness` of a flow whose diffusivity peaks at ``largest`` because of its
    regulariser ``eps`` (total variation: ``1 / eps``; a p-harmonic map: ``eps^(p-2)``)."""
    if torch.compiler.is_compiling():
        # a compiled flow whose eps was set anew traces it as a symbol, which the format
        # codes below do not take
        return ("eps: rho holds the flow's largest diffusivity, set by eps (units of u per "
                "world length); a larger eps takes fewer steps?")
    return (f"eps: rho holds the flow's largest diffusivity {largest:.3g}, set by eps={eps:g} "
            f"(units of u per world length, {eps * spacing:.3g} per cell of this grid); a "
            f"larger eps takes fewer steps?")


MAX_STEPS = 10**6
"""More steps, or more evaluations of the rate (RKC's stages and Heun's two per step
counted), than this are refused before any work: a sign of a wrong time or unit."""

LONG_RUN = 10**5
"""More evaluations of the rate than this warn before the run, with the count: at 17^3 that is
already half an hour."""

RKC_STEPS = 8
"""Fewest RKC steps to a flow's end time (unless forward Euler would need fewer): the time
error of RKC2 on a mode decaying by ``e^-1`` over the flow stays below the second-order space
error at 33^3-65^3 (docs/band.md)."""

EXPLICIT_STEP_FRACTION = 0.9
"""Default explicit steps (Euler, Heun and torchdiffeq's fixed-step methods) are this fraction
of their stability limit on the Gershgorin bound ``rho`` (Euler's ``1.8 / rho``). At the limit
itself the fastest mode is not damped where ``rho`` is the top eigenvalue (S flat and aligned
with the grid): a checkerboard on a plane kept 0.90 of its size after ``40 h^2`` at Euler's
``2 / rho`` (RKC and the implicit methods: 0.002). At 0.9 of the limit a step multiplies that
mode by -0.8 at most."""

RKC_REFRESHED_STEPS = 16
"""Fewest RKC steps whose stages re-extend the ring (steps too long for the band to hold it,
:func:`ring_held`; a 3-cell band always), unless forward Euler would need fewer. Their time
error, still second order, is several times that of steps holding the ring: sphere, l = 2 and
4, t = 0.05, 3-cell band at 65^3, float64: 8 steps 3.8e-4 and 3.7e-3, 16 steps 3.1e-4 and
3.1e-3, 32 steps 2.9e-4 and 2.9e-3 (rerun 2026-12-06; docs/band.md)."""

RKC_REFRESHED_STEP = 12.0
"""Longest ``dt * rho`` of an RKC step whose stages re-extend the ring: the time the fastest
diffusion takes to cross a cell, the period at which Euler and Heun re-extend such a band. The
band is re-extended only between steps, and between re-extensions its data drift off S's values
(each level set diffuses at its own rate) while the ring is set from S's: the step's error grows
with the period between re-extensions, whatever the integrator. Sphere R = 0.7, l = 1, decayed
by ``e^-0.6``, phi = ``r^2 - R^2`` (3-cell band), 16 cells per radius, float64: Heun
re-extending every 2 / 6 / 12 / 24 / 48 ``/ rho`` erred -7.4e-4, -4.9e-4, +5.5e-5, +1.2e-3,
+1.8e-3; RKC's 16 steps of 48 ``/ rho``, +2.5e-3 (2.9e-3 at most on S); 12 ``/ rho`` on bricks,
phi a distance, 24 cells: 3.2e-4 at most against 1.0e-3 at 108 (docs/band.md). Applied to
isotropic rates only (:attr:`System.isotropic`): the others grew with frequent re-extensions on
a thin knot, where RKC's long steps kept them in range (docs/band.md, section 5)."""

RKC_GROWTH = 2.0
"""Largest ``step * growth`` of an RKC step (:attr:`System.growth`). RKC's stages damp the
diffusion's decaying modes; a growing mode they amplify like ``cosh`` of the stage count
times ``sqrt(step * growth)``, and a nonlinear growth (harmonic maps' ``u |P grad u|^2``)
feeds on that before the step's renormalisation: 8 steps of a p = 2 harmonic map flow on the
bunny's raw principal direction at 256^3 (``step * growth`` about 20) overflowed float32, 64
steps (2.5) did not."""


HELD_RING_CELLS = 2.0 * math.sqrt(3.0)
"""The nodes within ``2 sqrt(3)`` cells of S are those the band's re-extension reads: a ring
held stale must not spread its error that far (:data:`HELD_RING_SPREAD`)."""

HELD_RING_SPREAD = 6.0
"""An RKC step of ``dt rho <= HELD_RING_SPREAD (w - HELD_RING_CELLS)^2`` on a band of ``w``
cells (14.2 for 5 cells) holds the ring during the step and re-extends it with the band after
the step (:func:`held_ring_bound`). The stale ring's error spreads inward over the heat
kernel's width ``sqrt(2 dt)`` (``sqrt(dt rho / 6)`` cells, ``rho`` about ``12 / h^2``), which
then stays within the margin ``w - 2 sqrt(3)``. The factor was 12 (28.3 at 5 cells), a width of
``sqrt(dt rho / 12)``: the stale error reached the nodes the re-extension reads, and the
sphere's heat flow kept an error that did not shrink with h (l = 1, R = 0.7, amplitude off by
-2.6e-4, -3.0e-4, -3.4e-4 at 32, 40, 56 cells per radius against Heun's +8.5e-5 at 32; with
many short steps between re-extensions held 28 / rho apart, +4.5e-4, against +1.0e-4 and
+9.2e-5 at 19 / rho and 11 / rho: docs/band.md). Before 2026-12-01 the margin was ``w - 3``."""

HELD_RING_STEPS = 3.0
"""A nonlinear flow's RKC takes up to this many times the steps it would otherwise when that
lets it hold the ring (:func:`ring_held`); a linear one (:attr:`System.linear`: heat, flow
visualisation) up to :data:`HELD_RING_LINEAR_STEPS` times.
The stages grow as the square root of the step count, and each
costs about half as much without the ring's re-extension; steps that re-extend the ring at
every stage lose the time order, which shows over long times: a sphere's l = 1 heat flow to
``t = R^2`` (``t / h^2`` 106-238) stayed 0.9-1.7 % off at 33^3-49^3 in 8 such steps, and is
2.7e-3, 1.3e-3, 5.4e-4 of the decayed amplitude holding the ring, for 1.5-2.4 times the time.
The nonlinear flows' bound grows as their regularisation shrinks (total variation: ``1 / eps``),
and holding the ring over their usual times would multiply their steps tenfold."""


HELD_RING_LINEAR_STEPS = 24.0
"""A linear flow's RKC takes up to this many times the steps it would otherwise to hold the
ring; beyond, its stages re-extend the ring as on a band too narrow to hold it. The bound a step
may hold it for, ``6 (w - 2 sqrt(3))^2 / rho`` on a band of ``w`` cells, vanishes as ``w``
nears ``2 sqrt(3)``: with no limit a heat flow on a band of 3.47 cells took 51,070 steps
(18 s, against 0.14 s at 3.6 and 0.23 s at 3.4 cells; an audit, 32^3), and at 3.465 cells it
refused the time. The default 5-cell band asks at most 21 times the steps, and keeps holding."""


def ring_held(method: str, step_times_rho: float, band_cells: float, period: int = 1,
              reaction: bool = False) -> bool:
    """Whether ``method``'s steps of ``dt * rho = step_times_rho`` on a band of ``band_cells``
    cells keep the ring fixed between re-extensions (:data:`RING_HELD`,
    :data:`HELD_RING_CELLS`): for RKC, if one step fits the bound; for Euler, Heun and the
    implicit methods, which re-extend the band every ``period`` steps, if those steps together
    do; never for a rate with a ``reaction`` (:attr:`System.reaction`). Otherwise the ring is
    re-extended at every evaluation of the rate, or, by the implicit methods (whose operator
    must stay symmetric during a step's solve), before every step."""
    held_steps = period if method in ("euler", "heun", *IMPLICIT) else 1
    return (not reaction and method in RING_HELD and band_cells > HELD_RING_CELLS
            and held_steps * step_times_rho <= held_ring_bound(band_cells) * (1 + 1e-9))


def held_ring_bound(band_cells: float) -> float:
    """The longest time, times ``rho``, a band of ``band_cells`` cells holds its ring:
    ``HELD_RING_SPREAD (w - HELD_RING_CELLS)^2`` (0 where ``w <= HELD_RING_CELLS``)."""
    margin = max(0.0, band_cells - HELD_RING_CELLS)
    return HELD_RING_SPREAD * margin**2


@dataclass(frozen=True)
class Plan:
    """How many steps of which size a method takes to ``end``.

    Attributes:
        count: number of steps (``None`` for adaptive torchdiffeq methods).
        step: step size, physical time.
    """

    count: int | None
    step: float


EQUILIBRIUM_CROSSINGS = 10
"""A linear flow's time may be at most this many times the time its diffusion takes to cross
the grid's diagonal, ``12 (diagonal / h)^2 / rho``: by then every mode but the constant has
decayed by more than ``e^-100`` on any surface the grid resolves, and a longer time is a unit
error that would run for hours."""


class BeyondEquilibrium(ValueError):
    """A linear flow's time of more than :data:`EQUILIBRIUM_CROSSINGS` grid crossings
    (:func:`check_before_equilibrium`); ``crossings`` is how many."""

    def __init__(self, message: str, crossings: float) -> None:
        super().__init__(message)
        self.crossings = crossings


def check_before_equilibrium(end: float, rho: float, diagonal_cells: float) -> None:
    """Refuse a linear flow's time ``end`` above :data:`EQUILIBRIUM_CROSSINGS` times the time
    its diffusion takes to cross ``diagonal_cells`` cells, ``12 diagonal_cells^2 / rho``
    (:class:`BeyondEquilibrium`, a ``ValueError``)."""
    crossing = 12.0 * diagonal_cells**2 / rho
    if end > EQUILIBRIUM_CROSSINGS * crossing:
        raise BeyondEquilibrium(
            f"time={end:g} is {end / crossing:.3g} times the time the diffusion takes to "
            f"cross the whole grid ({crossing:.3g}: its diagonal of {diagonal_cells:.0f} "
            f"cells, from the operator's bound rho = {rho:.3g}); the flow reaches its "
            f"equilibrium long before, and more than {EQUILIBRIUM_CROSSINGS} times is "
            f"refused as a likely unit error (forward Euler would take {end * rho / 2:.3g} "
            "steps): the time is in world units squared", end / crossing
        )


def first_warning(warned: set[str] | None, kind: str) -> bool:
    """Whether to give a warning of ``kind``: always without ``warned``; else once, the kinds
    given kept in ``warned`` (a flow's own: its messages hold the call's numbers, which a
    learned time changes at every call, so Python's filter, once per text and line, printed
    one a training iteration)."""
    if warned is None:
        return True
    if kind in warned:
        return False
    warned.add(kind)
    return True


def plan_steps(method: str, system: System, end: float, steps: int | None,
               band_cells: float = 3.0, diagonal_cells: float | None = None,
               step_size: float | None = None, warn: bool = True,
               warned: set[str] | None = None) -> Plan:
    """The steps of ``method`` over ``[0, end]``; raises before work when they are absurd.

    ``steps`` given: ``end / steps`` (explicit steps above the stable step warn; an adaptive
    torchdiffeq method ignores it: its count is ``None``). Otherwise: torchdiffeq's fixed-step
    methods take :func:`fixed_step_count` (``step_size`` the option, if given), adaptive ones
    ``None``; Euler and Heun take :attr:`System.explicit_step` (``1.8 / rho``), the implicit methods
    Euler's stable step ``2 / rho``; RKC takes
    :data:`RKC_STEPS` steps (or Euler's count, if smaller) or more, none longer than
    ``12 band_cells^2 / rho``: about the time the diffusion takes to cross a band
    ``band_cells`` cells wide, after which the data must be re-extended (docs/band.md), nor
    than ``RKC_GROWTH / growth`` (:data:`RKC_GROWTH`); and more where that lets each step hold
    the ring (:func:`ring_held`): up to :data:`HELD_RING_LINEAR_STEPS` times as many for a
    linear flow, :data:`HELD_RING_STEPS` times for a nonlinear one; where the steps cannot hold it,
    at least :data:`RKC_REFRESHED_STEPS` (or Euler's count), and for an isotropic rate
    (:attr:`System.isotropic`) none longer than ``RKC_REFRESHED_STEP / rho``
    (:data:`RKC_REFRESHED_STEP`).

    Refused (``ValueError``): more than :data:`MAX_STEPS` steps or evaluations of the rate; for
    a linear flow, a time above :data:`EQUILIBRIUM_CROSSINGS` times the time its diffusion
    takes to cross ``diagonal_cells`` cells. Warned (unless not ``warn``: a plan made only
    to bound another's steps): more than :data:`LONG_RUN` evaluations. ``warned``: the kinds of
    warning the caller's flow gave already, each given once (:func:`first_warning`).
    """
    rho = system.spectral_radius
    per_rho = 1.0 / rho if rho > 0 else math.inf  # a time per unit of dt rho
    if system.linear is not None and diagonal_cells is not None:
        check_before_equilibrium(end, rho, diagonal_cells)
    if steps is None:
        explicit = whole_steps(end, system.stable_step, end)
        if method == "rkc":
            longest = min(12.0 * band_cells**2, largest_step_times_rho())
            count = max(min(RKC_STEPS, explicit), whole_steps(end, longest * per_rho, end),
                        math.ceil(end * system.growth / RKC_GROWTH * (1 - 1e-9)))
            # with a reaction too, whose ring is refreshed instead: these steps bound its time
            # error (Turk's ODE from a = 6, b = 3 at 24^3, T = 200, the larger of a's and b's
            # on S: 1.2e-3 in these 37 steps, 5.8e-3 in 16)
            if band_cells > HELD_RING_CELLS:
                holding = whole_steps(end, held_ring_bound(band_cells) * per_rho, end)
                allowed = HELD_RING_LINEAR_STEPS if system.linear is not None else HELD_RING_STEPS
                if count < holding <= allowed * count:
                    count = holding
            if not ring_held("rkc", end / count * rho, band_cells, reaction=system.reaction):
                count = max(count, min(RKC_REFRESHED_STEPS, explicit))
                if system.isotropic:
                    count = max(count, whole_steps(end, RKC_REFRESHED_STEP * per_rho, end))
        elif method in ("euler", "heun"):
            count = whole_steps(end, system.explicit_step, end)
        elif method in INTEGRATORS:
            count = explicit
        elif method in FIXED_STEP:
            count = fixed_step_count(method, system, end, None, step_size)
        else:
            count = None
    elif method in INTEGRATORS or method in FIXED_STEP:
        count = steps
    else:  # an adaptive torchdiffeq method chooses its own steps
        count = None
    if steps is not None:
        if (method in ("euler", "heun") and end / steps > system.stable_step * (1 + 1e-6)
                and first_warning(warned, "unstable step")):
            warnings.warn(
                f"steps={steps}: a step of {end / steps:.3g} exceeds the stable explicit step "
                f"{system.stable_step:.3g} of this surface's operator (2 / rho); the flow may "
                f"blow up. Use steps >= {math.ceil(end / system.stable_step)} or method='rkc'",
                RuntimeWarning, stacklevel=caller_stacklevel(),
            )
    if steps is not None and method in IMPLICIT and end / steps * rho > 12.0 * band_cells**2:
        if first_warning(warned, "step outlasting the band"):
            warnings.warn(
                f"steps={steps}: each {method} step outlasts the time the diffusion takes to cross "
                f"the {band_cells:.1f}-cell band ({12.0 * band_cells**2 / rho:.3g}), whose ring is "
                f"re-extended only between steps; expect errors from the band's edge. Use steps >= "
                f"{math.ceil(end * rho / (12.0 * band_cells**2))} or a wider band_width",
                RuntimeWarning, stacklevel=caller_stacklevel(),
            )
    elif (steps is not None and method in IMPLICIT and end / steps * rho > RKC_REFRESHED_STEP
          and band_cells <= HELD_RING_CELLS  # a band that never holds its ring
          and first_warning(warned, "step holding the ring")):
        warnings.warn(
            f"steps={steps}: each {method} step holds the ring of this {band_cells:.1f}-cell "
            f"band, re-extended before it, for {end / steps * rho:.3g} / rho, longer than the "
            f"{RKC_REFRESHED_STEP:g} / rho the diffusion takes to cross a cell; its staleness "
            f"reaches S and the error grows with the step, whatever the grid (a sphere's l = 1 "
            f"flow: 1.1e-2 at 30 steps of 35 / rho, 9.5e-4 at 8.7 / rho). Use steps >= "
            f"{math.ceil(end * rho / RKC_REFRESHED_STEP)} (or the default) or a band of more "
            f"than {HELD_RING_CELLS:.2f} cells on an exact distance",
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )
    evaluations = None
    if count is not None:
        per_step = ({"rkc": stages_for(end / count * rho), "heun": 2}.get(method, 1)
                    if method in INTEGRATORS else _EVALUATIONS.get(method, 1))
        evaluations = count * per_step
    if evaluations is not None and max(count, evaluations) > MAX_STEPS:
        advice = (f"steps={steps} is too many: use fewer" if steps is not None else
                  "is the time in this flow's units of this surface "
                  "(world units squared for diffusion, world units for total variation and p = 1 flows)?"
                  + (f" Or {system.stiffness}" if system.stiffness else ""))
        raise ValueError(
            f"time={end:g} needs {count} steps of method={method!r}, {evaluations} evaluations "
            f"of the rate (more than {MAX_STEPS}): {advice}; time * rho = {end * rho:.3g} "
            f"(rho = {rho:.3g}, the operator's bound)"
        )
    if (warn and evaluations is not None and evaluations > LONG_RUN
            and first_warning(warned, "long run")):
        warnings.warn(
            f"time={end:g} needs {count} steps of method={method!r}, {evaluations} evaluations "
            f"of the rate (more than {LONG_RUN}; time * rho = {end * rho:.3g}); a diffusion "
            "reaches its equilibrium once its length sqrt(time * diffusivity) exceeds the "
            "surface's size: is the time in this flow's units "
            "(world units squared for diffusion, world units for total variation and p = 1 flows)?"
            + (f" Or {system.stiffness}" if system.stiffness else ""),
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )
    step = end / count if count else end
    if method == "rkc" and step * rho > largest_step_times_rho():
        needed = math.ceil(end * rho / largest_step_times_rho())
        raise ValueError(
            f"steps={steps} is too few for RKC: a step would need more than {MAX_STAGES} "
            f"stages; use steps >= {needed}"
        )
    return Plan(count, step)


TIME_ROUNDING = 1e-6
"""Requested times within this fraction of the end time of a whole number of steps count as
that number (float32 times: ``5.0000002`` steps had become 6, moving the result by 20% of
Euler's error); a step then lasts at most 1% longer than planned."""


def whole_steps(length: float, step: float, end: float) -> int:
    """Steps of at most ``step`` over ``length`` (at least one), of a flow to ``end``: a length
    within :data:`TIME_ROUNDING` ``* end`` of a whole number of steps takes that number."""
    return max(1, math.ceil(length / step - min(TIME_ROUNDING * end / step, 0.01)))


def _intervals(schedule: Schedule) -> Iterator[tuple[int, Tensor | float, int]]:
    """``(interval index, step size, number of steps)`` for each interval of ``schedule``."""
    step = schedule.step
    end = _value(schedule.times[-1])
    previous: float | Tensor = 0.0
    for index, time in enumerate(schedule.times):
        length = time - previous
        if schedule.steps is not None:  # rounded up: no step longer than end / steps
            count = whole_steps(_value(length), end / schedule.steps, end)
        else:
            count = whole_steps(_value(length), step, end)
            if schedule.fewest is not None:
                count = max(count, schedule.fewest(_value(length), _value(time)))
        yield index, length / count, count
        previous = time


def steps_taken(schedule: Schedule) -> int:
    """The number of steps ``schedule`` takes over all its intervals."""
    return sum(count for _, _, count in _intervals(schedule))


def step_ends(schedule: Schedule) -> list[float]:
    """The time at the end of each step ``schedule`` takes, in order, physical time."""
    ends, start = [], 0.0
    for index, dt, count in _intervals(schedule):
        stop = _value(schedule.times[index])
        ends.extend(start + _value(dt) * j for j in range(1, count))
        ends.append(stop)
        start = stop
    return ends


def shortest_step(schedule: Schedule) -> float:
    """The shortest step ``schedule`` takes (requested times split the steps), physical time."""
    return min(_value(dt) for _, dt, _ in _intervals(schedule))


def _finish(system: System, u: Tensor) -> Tensor:
    return u if system.project is None else system.project(u)


def _returned(system: System, schedule: Schedule, u: Tensor, done: int | None,
              reads: Sequence[Tensor] | None = None) -> Tensor:
    """``u`` after ``done`` steps as returned at a requested time: through ``schedule.output``
    if any, recomputed in backward like the steps when they are checkpointed (``reads``);
    ``done=None`` for a time inside a step (torchdiffeq's), where no step's re-extension ran."""
    if schedule.output is None:
        return u
    output = schedule.output

    def returned(v: Tensor) -> Tensor:
        value = output(v, done)
        return v if value is v else _finish(system, value)

    return returned(u) if reads is None else recomputed(returned, u, reads)


def _explicit(
    step_fn: Callable[[System, Tensor, Tensor | float], Tensor],
) -> Callable[[System, Tensor, Schedule], list[Tensor]]:
    def advance(u: Tensor, dt: Tensor | float, first: int, count: int,
                schedule: Schedule, system: System) -> Tensor:
        for done in range(first + 1, first + count + 1):
            u = step_fn(system, u, dt)
            if schedule.after_step is not None:
                u = schedule.after_step(u, done)
            u = _finish(system, u)
            backend.step_taken()
        return u

    def integrate(system: System, u0: Tensor, schedule: Schedule) -> list[Tensor]:
        # projected first, as torchdiffeq's pieces are: unit vectors of other lengths took
        # their first step as they were
        u, out, done = _finish(system, u0), [], 0
        if schedule.checkpoint:
            reads = declared((*_tensor_times(schedule), *system.params))
            system = replace(system, rate=_checkpointed_rate(system.rate, reads))
        # groups of sqrt(all the steps): each requested time's result is kept anyway, so a
        # group of sqrt(its own interval's steps) kept up to 114 volumes for 64 times where
        # sqrt(steps) is 15
        whole = max(1, math.isqrt(steps_taken(schedule)))
        for _, dt, count in _intervals(schedule):
            group = min(whole, count) if schedule.checkpoint else count
            for first in range(done, done + count, group):
                length = min(group, done + count - first)
                if schedule.checkpoint:
                    u = recomputed(
                        functools.partial(_advance_from, advance, dt, first, length, schedule,
                                          system),
                        u, reads,
                    )
                else:
                    u = advance(u, dt, first, length, schedule, system)
            done += count
            out.append(_returned(system, schedule, u, done,
                                 reads if schedule.checkpoint else None))
        return out

    return integrate


def _tensor_times(schedule: Schedule) -> tuple[Tensor, ...]:
    return tuple(t for t in schedule.times if isinstance(t, Tensor))


def _advance_from(advance: Callable[..., Tensor], dt: Tensor | float, first: int, count: int,
                  schedule: Schedule, system: System, u: Tensor) -> Tensor:
    return advance(u, dt, first, count, schedule, system)


def _checkpointed_rate(rate: Rate, reads: Sequence[Tensor]) -> Rate:
    """``rate`` keeping for backward only its input: a stage's operator (a nonlinear flux form
    keeps a dozen volumes under autograd) is recomputed when its gradient is needed, so that
    the recomputed group of steps holds about two volumes a stage. ``reads``: the tensors
    needing gradients that ``rate`` reads (:attr:`System.params`)."""

    def checkpointed(u: Tensor) -> Tensor:
        return recomputed(rate, u, reads)

    return checkpointed


def _axpy(u: Tensor, dt: Tensor | float, rate: Tensor) -> Tensor:
    """``u + dt * rate`` in one pass over memory (``dt`` a number or a 0-d tensor)."""
    if isinstance(dt, Tensor):
        return torch.addcmul(u, dt, rate)
    return torch.add(u, rate, alpha=dt)


def _euler_step(system: System, u: Tensor, dt: Tensor | float) -> Tensor:
    return _axpy(u, dt, system.rate(u))


def _rkc_step(system: System, u: Tensor, dt: Tensor | float) -> Tensor:
    stages = stages_for(_value(dt) * system.spectral_radius)
    if (system.linear_stage is not None and not isinstance(dt, Tensor)
            and system.linear_stage.applies(u)):
        return rkc_step_linear(system.linear_stage, u, dt, stages)
    # the stages' combinations of u are exact only up to rounding: keep u outside the band as is
    return torch.where(system.band, rkc_step(system.rate, u, dt, stages, system.path), u)


def _heun_step(system: System, u: Tensor, dt: Tensor | float) -> Tensor:
    first = system.rate(u)
    second = system.rate(_finish(system, _axpy(u, dt, first)))
    return _axpy(u, 0.5 * dt, first + second)


def _theta_method(theta: float) -> Callable[[System, Tensor, Schedule], list[Tensor]]:
    """``W u_new - theta dt A u_new = W u + (1 - theta) dt A u``: 1 backward Euler, 1/2 CN.

    Solved for the change ``d = u_new - u`` on the band, ``(W - theta dt A) d = dt A u`` (the
    ring's values enter through ``A u``): its right-hand side holds no offset of the data, so
    the solver's relative tolerance is one of the change (solved for ``u_new``, data on an
    offset of 1e4 in float32 or 1e7 in float64 stopped with the change 3-13% wrong).
    """

    def integrate(system: System, u0: Tensor, schedule: Schedule) -> list[Tensor]:
        linear = system.linear
        if linear is None:
            raise ValueError(
                "method: the implicit integrators need a linear symmetric flow (HeatFlow, "
                "FlowVisualization); use 'euler', 'heun' or a torchdiffeq method"
            )
        band = system.band
        groups = None if system.layout is None else system.layout.batch.to(u0.device)
        mask = band.to(u0.dtype)
        # the system in units of a power of two of W per entry (exact): the solver's inner
        # products of W u stay in range for phi scaled near the float's limits (c = 1e20 in
        # float32 overflowed them, 1e-30 underflowed)
        scaled = mask / _entry_power_of_two(linear.params[0].detach(), band, system.layout)
        zero = torch.zeros((), dtype=u0.dtype, device=u0.device)
        u, out, done = u0, [], 0
        for _, dt, count in _intervals(schedule):
            step = dt if isinstance(dt, Tensor) else torch.tensor(float(dt), dtype=u0.dtype, device=u0.device)

            def matrix(x: Tensor, step: Tensor, *params: Tensor) -> Tensor:
                return scaled * (params[0] * x - theta * step * linear.operator(mask * x, *params))

            params = (step, *linear.params)
            for _ in range(count):
                if system.refresh_ring is not None:
                    u = system.refresh_ring(u)
                rhs = torch.where(band, scaled * (dt * linear.operator(u, *linear.params)), zero)
                change = solve_symmetric(matrix, rhs, torch.zeros_like(rhs), params,
                                         schedule.solver, groups)
                u = torch.where(band, u + change, u)
                done += 1
                if schedule.after_step is not None:
                    u = schedule.after_step(u, done)
                u = _finish(system, u)
                backend.step_taken()
            out.append(_returned(system, schedule, u, done))
        return out

    return integrate


def _entry_power_of_two(weight: Tensor, band: Tensor, layout: BrickLayout | None) -> Tensor:
    """The power of two at or below the largest ``weight`` ``(B or 1, 1, D, H, W)`` on the
    ``band`` of each batch entry, shaped to broadcast (packed fields on ``layout``: each
    brick its entry's)."""
    on_band = torch.where(band, weight, 0.0)
    largest = (on_band.amax(dim=(1, 2, 3, 4), keepdim=True) if layout is None
               else layout.entry_max(on_band))
    return power_of_two_below(largest)


def band_norm(band: Tensor) -> Callable[[Tensor], Tensor]:
    """The root mean square over the nodes of ``band`` (``(B or 1, 1, ...)`` bool, broadcast
    over the data's batch and channels): the error norm of torchdiffeq's adaptive steps.

    Its default, over the whole state, counts the nodes beyond the band, whose error is 0, so
    that a box with more room around the surface took longer steps and missed the tolerance on
    the surface: Perona–Malik at ``rtol`` 1e-5 on one sphere and spacing was 2.2e-6 off in a
    24^3 box and 1.0e-4 in a 47^3 one.
    """
    mask = band.to(torch.float64)

    def norm(error: Tensor) -> Tensor:
        weights = mask.to(error.dtype).expand_as(error)
        return (error.square() * weights).sum().div(weights.sum().clamp_min(1)).sqrt()

    return norm


def _torchdiffeq(method: str) -> Callable[[System, Tensor, Schedule], list[Tensor]]:
    def integrate(system: System, u0: Tensor, schedule: Schedule) -> list[Tensor]:
        try:
            import torchdiffeq
        except ImportError as error:
            raise ImportError(
                f"method={method!r} needs torchdiffeq, an optional dependency: "
                "pip install torchdiffeq (or pip install 'torchsurf[ode]'); the built-in "
                f"methods are {sorted(INTEGRATORS)}"
            ) from error
        options = dict(schedule.options)
        if method in FIXED_STEP:
            # equal steps that end at the last time: a given step_size is the longest step
            # (torchdiffeq's own grid ends with a partial step, whose length depends on the
            # end time outside autograd's graph: a learned time's gradient came out 3% off)
            end = _value(schedule.times[-1])
            count = fixed_step_count(method, system, end, schedule.steps,
                                     options.get("step_size"))
            options["step_size"] = end / count
            _warn_unstable_step(method, options["step_size"], system.spectral_radius,
                                end if schedule.steps is not None else None)
        elif method in ADAPTIVE_STEPS:
            options.setdefault("max_num_steps", MAX_STEPS)
            options.setdefault("norm", band_norm(system.band))
        kwargs = {key: options.pop(key) for key in ("rtol", "atol") if key in options}

        def func(t: Tensor, u: Tensor) -> Tensor:
            return system.rate(u)

        if method == "scipy_solver":
            options["solver"] = _reading_no_min_step(options["solver"])

        def solve(u: Tensor, times: list[float | Tensor]) -> Tensor:
            try:
                return solve_piece(u, times)
            except AssertionError as error:  # torchdiffeq's way of stopping a run
                if "max_num_steps" not in str(error):
                    raise RuntimeError(
                        f"method={method!r} stopped ({error}): its steps shrank without end, "
                        "as on an unstable or very stiff flow; use method='rkc' (or 'euler' "
                        "for the flows it suits), or a smaller time") from None
                raise RuntimeError(
                    f"method={method!r} took more than {options['max_num_steps']} steps in one "
                    f"piece of the flow ({error}): the time is long for this surface's operator "
                    f"(rho = {system.spectral_radius:.3g}); use method='rkc', a shorter time, or "
                    "raise options['max_num_steps']") from None

        def solve_piece(u: Tensor, times: list[float | Tensor]) -> Tensor:
            times = torch.stack([torch.as_tensor(t, dtype=u0.dtype, device=u0.device)
                                 for t in times])
            if schedule.adjoint:
                return torchdiffeq.odeint_adjoint(
                    _RateModule(func), u, times, method=method, options=options or None,
                    adjoint_params=independent(system.params), **kwargs,
                )
            return torchdiffeq.odeint(func, u, times, method=method,
                                      options=options or None, **kwargs)

        # projected first: the pieces run many steps before the next projection (a raw noise
        # field made tangent only after the first piece grew to NaN under rk4 and midpoint)
        out, u, start, done = [], _finish(system, u0), 0.0, 0
        for stop, inner, at_stop in _segments(schedule):
            # requested times that round together (float32 data) are one time of the solve
            # (torchdiffeq refuses times that do not increase), each given its result
            points, which = _distinct_times(start, inner,
                                            TIME_ROUNDING * _value(schedule.times[-1]))
            solution = solve(u, [*points, stop])
            if len(solution) != len(points) + 1:  # scipy's solve_ivp stopped on the way
                raise RuntimeError(
                    f"method={method!r} stopped at {len(solution)} of the {len(points) + 1} "
                    f"times of its solve up to t = {stop:.4g}: scipy's solve_ivp gave up (its "
                    "step fell below the float spacing, most often from a rate that turned NaN "
                    "or infinite); a torchdiffeq method such as 'dopri5' names the step")
            out.extend(_returned(system, schedule, _finish(system, solution[k]), None)
                       for k in which)
            u, start, done = solution[-1], stop, done + 1
            if schedule.after_step is not None:
                u = schedule.after_step(u, done)
            u = _finish(system, u)
            out.extend(_returned(system, schedule, u, done) for _ in range(at_stop))
        return out

    return integrate


def _segments(schedule: Schedule) -> Iterator[tuple[float | Tensor, list[float | Tensor], int]]:
    """Equal pieces of ``[0, end]`` no longer than ``schedule.segment``, between which the flow
    re-extends: ``(end of the piece, requested times inside it, how many requested times are
    its end)``. A requested time within :data:`TIME_ROUNDING` ``* end`` of a piece's end is
    that end (a float32 time, ``end / 3`` rounded, had fallen a rounding short of it: a time
    of the solve equal to its end once in the data's dtype, which torchdiffeq refused)."""
    end = schedule.times[-1]
    end_value = _value(end)
    slack = TIME_ROUNDING * end_value
    pieces = 1
    if schedule.segment is not None and schedule.after_step is not None:
        pieces = max(1, math.ceil(end_value / schedule.segment * (1 - 1e-9)))
    wanted = list(schedule.times)
    for k in range(1, pieces + 1):
        stop_value = end_value * k / pieces
        stop = end if k == pieces else end * (k / pieces)
        inner = []
        while wanted and _value(wanted[0]) < stop_value - slack:
            inner.append(wanted.pop(0))
        at_stop = 0
        while wanted and (k == pieces or _value(wanted[0]) <= stop_value + slack):
            wanted.pop(0)
            at_stop += 1
        yield stop, inner, at_stop


def _distinct_times(start: float | Tensor, times: list[float | Tensor], slack: float
                    ) -> tuple[list[float | Tensor], list[int]]:
    """``start`` and the requested ``times`` after it (increasing) without those within
    ``slack`` of the one before (a time that rounds to the start, ``1e-46`` in float32, is the
    start), and the index into that list of each requested time's representative."""
    points: list[float | Tensor] = [start]
    which = []
    for time in times:
        if _value(time) > _value(points[-1]) + slack:
            points.append(time)
        which.append(len(points) - 1)
    return points, which


class _RateModule(torch.nn.Module):
    """``odeint_adjoint`` wants an ``nn.Module``; its parameters are passed explicitly."""

    def __init__(self, func: Callable[[Tensor, Tensor], Tensor]) -> None:
        super().__init__()
        self.func = func

    def forward(self, t: Tensor, u: Tensor) -> Tensor:
        return self.func(t, u)


FIXED_STEP = ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "fixed_adams",
              "implicit_adams")
"""torchdiffeq's methods on a fixed grid of steps (``step_size``); the others choose their
own steps (``rtol``, ``atol``)."""

_STABLE_INTERVAL = {"midpoint": 2.0, "heun2": 2.0, "heun3": 2.51, "rk4": 2.78,
                    "explicit_adams": 0.003, "fixed_adams": 0.06, "implicit_adams": 0.06}
"""Length of the stability interval on the negative real axis of torchdiffeq's fixed-step
methods (``"euler"`` is the built-in one, which warns in :func:`plan_steps`): a step longer
than this over ``rho`` lets the fastest mode of a diffusion grow. The Adams methods' (up to
order 12 in torchdiffeq 0.2) were measured on ``y' = -y`` over 20,000 steps (growth began at
``dt = 0.0034`` and ``0.068``) and rounded down."""

_EVALUATIONS = {"midpoint": 2, "heun2": 2, "heun3": 3, "rk4": 4, "fixed_adams": 2,
                "implicit_adams": 5}
"""Evaluations of the rate per step of torchdiffeq's fixed-step methods (1 if not listed;
``implicit_adams``: its corrector's most iterations)."""

CORRECTED = ("fixed_adams", "implicit_adams")
"""torchdiffeq's fixed-step methods whose Adams–Moulton corrector iterates to ``rtol`` and
``atol`` (the others ignore them)."""

ADAPTIVE_STEPS = ("adaptive_heun", "bosh3", "dopri5", "dopri8", "fehlberg2")
"""torchdiffeq's adaptive Runge–Kutta methods: given ``max_num_steps`` = :data:`MAX_STEPS`
unless the options say otherwise, so that a run that would take longer stops with an error."""


def fixed_step_count(method: str, system: System, end: float, steps: int | None,
                     step_size: float | None) -> int:
    """Steps of a fixed-step torchdiffeq ``method`` over ``[0, end]``: ``steps``, else equal
    steps no longer than ``step_size``, else than :data:`EXPLICIT_STEP_FRACTION` of the method's
    stable step on ``system`` (Euler's ``2 / rho`` or its own stability interval over ``rho``,
    the shorter)."""
    if steps is not None:
        return steps
    if step_size is None:
        interval = min(2.0, _STABLE_INTERVAL.get(method, 2.0))
        step_size = EXPLICIT_STEP_FRACTION * system.stable_step * interval / 2.0
    return whole_steps(end, step_size, end)


SCIPY_EXPLICIT = ("RK45", "RK23", "DOP853")
"""scipy's explicit solvers, the ones ``method="scipy_solver"`` takes (:func:`check_options`)."""


SCIPY_STIFF = ("LSODA", "BDF", "Radau")
"""scipy's stiff solvers, refused by ``method="scipy_solver"`` (:func:`check_options`)."""


@functools.cache
def _reading_no_min_step(solver: str | type) -> type:
    """scipy's explicit ``solver`` (a ``solve_ivp`` name or class) taking the ``min_step`` that
    torchdiffeq hands every scipy solver and the explicit ones do not read. scipy warned of it
    at every solve; the warnings filter that silenced it is global, and threads overlapping in
    it left it in place for good."""
    import scipy.integrate

    base = getattr(scipy.integrate, solver) if isinstance(solver, str) else solver

    class Solver(base):  # type: ignore[valid-type, misc]
        def __init__(self, *args: object, min_step: float = 0.0, **options: object) -> None:
            super().__init__(*args, **options)

    Solver.__name__ = Solver.__qualname__ = base.__name__
    return Solver


def _check_scipy_solver(solver: object, default: bool) -> None:
    """Refuse a ``scipy_solver`` solver that is not one of scipy's explicit Runge-Kutta
    methods: a stiff one (a dense Jacobian of the whole volume) or a name scipy lacks."""
    if isinstance(solver, type):  # a solve_ivp OdeSolver class
        try:
            from scipy.integrate._ivp.rk import RungeKutta
        except ImportError:  # a private module: judged by the class's name instead
            RungeKutta = None  # noqa: N806
        if RungeKutta is not None and issubclass(solver, RungeKutta):
            return
        name = solver.__name__
    else:
        name = solver
    if name in SCIPY_EXPLICIT:
        return
    given = f"method='scipy_solver' with options['solver']={solver!r}"
    advice = (f"give options={{'solver': 'RK45'}} (or one of {list(SCIPY_EXPLICIT)}), or a "
              "torchdiffeq method such as 'dopri5'")
    if name in SCIPY_STIFF:
        raise ValueError(
            f"{given}{' (the default)' if default else ''}: scipy's stiff solvers form a dense "
            "Jacobian of the whole volume, (D H W C)^2 numbers (91 GiB for one channel at "
            f"48^3; LSODA's work array overflows first); {advice}")
    raise ValueError(f"{given}: not one of scipy's explicit solve_ivp methods; {advice}")


def check_options(options: object, method: str) -> dict:
    """torchdiffeq's ``options`` of ``method`` as a new dict; raises naming the option whose
    value is not a number of its range (``step_size``, ``first_step``: positive; ``rtol``,
    ``atol``: at least 0; ``max_num_steps``: a whole number >= 1), and ``scipy_solver`` with a
    solver other than :data:`SCIPY_EXPLICIT`. Other keys go to torchdiffeq as given (it warns
    about the ones its method does not read)."""
    if options is None:
        options = {}
    if not isinstance(options, Mapping):
        raise TypeError(f"options must be a dict of torchdiffeq options, got "
                        f"{type(options).__name__}")
    checked = dict(options)
    for key in ("step_size", "first_step"):
        if key in checked:
            checked[key] = check_positive(checked[key], f"options[{key!r}]")
    for key in ("rtol", "atol"):
        if key in checked:
            checked[key] = check_nonnegative(checked[key], f"options[{key!r}]")
    if "max_num_steps" in checked:
        checked["max_num_steps"] = check_count(checked["max_num_steps"],
                                               "options['max_num_steps']")
    if "step_size" in checked and method not in FIXED_STEP:
        raise ValueError(f"options['step_size'] is for torchdiffeq's fixed-step methods "
                         f"{list(FIXED_STEP)}; method={method!r} chooses its own steps (rtol, "
                         "atol)")
    tolerances = [key for key in ("rtol", "atol") if key in checked]
    if tolerances and method in FIXED_STEP and method not in CORRECTED:
        raise ValueError(f"options[{tolerances[0]!r}] is for torchdiffeq's methods that choose "
                         f"their own steps; method={method!r} takes fixed steps, which it "
                         "ignores (give steps= or options['step_size'])")
    if len(tolerances) == 2 and checked["rtol"] == 0 and checked["atol"] == 0:
        raise ValueError("options['rtol'] and options['atol'] are both 0: no step can meet "
                         "them (the steps would shrink until refused)")
    if method == "scipy_solver":
        _check_scipy_solver(checked.get("solver", "LSODA"), "solver" not in checked)
    if "norm" in checked and not callable(checked["norm"]):
        raise TypeError(f"options['norm'] must be a function of a tensor (torchdiffeq's error "
                        f"norm), got {type(checked['norm']).__name__}")
    return checked


def _warn_unstable_step(method: str, step: float, rho: float, end: float | None = None
                        ) -> None:
    """Warn before the run when a fixed-step torchdiffeq method's step is past its stable step
    on this operator (``method="euler"`` with ``steps=`` warns the same way); ``end``: the
    time, when the steps were given by ``steps=`` (the remedy is then more steps: ``steps``
    and ``options['step_size']`` are refused together)."""
    interval = _STABLE_INTERVAL.get(method)
    if interval is None or step * rho <= interval * (1 + 1e-6):
        return
    remedy = (f"options={{'step_size': {interval / rho:.3g}}} or less" if end is None
              else f"steps >= {math.ceil(end * rho / interval * (1 - 1e-9))}")
    warnings.warn(
        f"a {method} step of {step:.3g} exceeds its stable step {interval / rho:.3g} on this "
        f"surface's operator ({interval:g} / rho, rho = {rho:.3g}); the flow may blow up. Use "
        f"{remedy}, or method='rkc'",
        RuntimeWarning, stacklevel=caller_stacklevel(),
    )

INTEGRATORS: dict[str, Callable[[System, Tensor, Schedule], list[Tensor]]] = {
    "rkc": _explicit(_rkc_step),
    "euler": _explicit(_euler_step),
    "heun": _explicit(_heun_step),
    "implicit": _theta_method(1.0),
    "crank_nicolson": _theta_method(0.5),
}
"""Built-in integrators by name; any other name is handed to torchdiffeq (``"dopri5"``, ``"rk4"``...)."""

TORCHDIFFEQ_METHODS = ("adaptive_heun", "bosh3", "dopri5", "dopri8", "euler", "explicit_adams",
                       "fehlberg2", "fixed_adams", "heun2", "heun3", "implicit_adams", "midpoint",
                       "rk4", "scipy_solver")
"""torchdiffeq's method names (0.2.x); the installed torchdiffeq's own list is used when it is
importable."""


def check_method(method: object, extra: Sequence[str] = ()) -> str:
    """``method`` if it names a built-in integrator, one of ``extra`` or a torchdiffeq method.

    Raises:
        TypeError: ``method`` is not a string.
        ValueError: an unknown name, listing the built-in and torchdiffeq methods.
    """
    if not isinstance(method, str):
        raise TypeError(f"method must be a string, got {type(method).__name__}")
    try:
        from torchdiffeq._impl.odeint import SOLVERS
        external = tuple(sorted(SOLVERS))
    except ImportError:
        external = TORCHDIFFEQ_METHODS
    if method in INTEGRATORS or method in extra or method in external:
        return method
    raise ValueError(
        f"method={method!r} is unknown: built in {[*INTEGRATORS, *extra]}, or a torchdiffeq "
        f"method {list(external)}"
    )


IMPLICIT = ("implicit", "crank_nicolson")
"""Methods that solve a linear system each step: only for linear symmetric flows (heat with a
symmetric scheme, flow visualisation)."""

RING_HELD = (*IMPLICIT, "euler", "heun", "rkc")
"""Methods that may hold the ring between re-extensions instead of re-extending it at every
evaluation of the rate (:func:`ring_held`), where the band is wide enough for the time it is
held (on the 5-cell band of a distance, the periodic re-extension of Euler, Heun and the
implicit methods; never on a 3-cell band, where the stale ring reaches the nodes the
re-extension reads: docs/band.md). The implicit methods hold it during each step's solve
(their operator must stay symmetric) and refresh it before each step where it is not held."""


def integrate(method: str, system: System, u0: Tensor, schedule: Schedule) -> list[Tensor]:
    """Run ``method`` on ``system`` from ``u0``; returns ``u`` at each of ``schedule.times``."""
    integrator = INTEGRATORS.get(method)
    if integrator is None:
        return _torchdiffeq(method)(system, u0, schedule)
    if torch.compiler.is_compiling() or (schedule.steps is None and schedule.step is None):
        return integrator(system, u0, schedule)
    # the backend weighs compiling a kernel against the eager time the remaining steps need
    with backend.planned(steps_taken(schedule)):
        return integrator(system, u0, schedule)
